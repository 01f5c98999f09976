"""``frfcal demo``: the whole chain on the bundled example structure, end to end.

Each stage runs the same command a user would type (printed with a ``$``),
so the demo doubles as a tour:

1. ``frfcal example subframe``: the subframe-like FE model and its 17 parameters;
2. ``frfcal modes`` and a figure of the first elastic mode shapes;
3. ``frfcal pretest``: 20 accelerometers and a shaker by Effective Independence;
4. a "true" test article (the model at the method paper's calibrated
   parameter changes, Table 2.1) becomes the plant of the simulated lab;
   ``frfcal acquire --driver sim`` sweeps it with the stepped-sine controller;
5. ``frfcal identify``: state-space identification of the run file;
6. ``frfcal calibrate``: calibration on 11 channels, hold-out validation on
   the other 9, cross-validation.

Everything lands in ``--out``. The demo closes with the true, nominal and
calibrated parameters side by side.
"""

from __future__ import annotations

import argparse

HELP = "run the whole chain (model, modes, pretest, simulated sweep, identification, calibration) on the example"

#: The method paper's Table 2.1: (nominal, calibrated) of each parameter. Their
#: ratio is the demo's "true" change of the test article against the model.
PAPER_TABLE_2_1 = {
    "E_main": (210.0, 217.0),
    "rho_main": (7850.0, 7750.0),
    "t_bracket_RHS": (2.5, 2.46),
    "t_bracket_LHS": (2.5, 2.52),
    "t_top_skin": (2.3, 2.21),
    "t_bottom_skin": (2.0, 1.96),
    "t_arm_base_RHS": (2.3, 2.33),
    "t_arm_base_LHS": (2.3, 2.22),
    "t_arm_RHS": (3.0, 3.02),
    "t_arm_LHS": (3.0, 3.04),
    "t_arm_ext_base_RHS": (2.3, 2.46),
    "t_arm_ext_base_LHS": (2.3, 2.35),
    "M1": (0.136, 0.135),
    "M2": (0.136, 0.138),
    "M3": (0.215, 0.211),
    "M4": (0.215, 0.227),
    "E_weld": (210.0, 207.0),
}


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="demo-output", help="output directory (default demo-output)")
    parser.add_argument("--dof", type=int, default=5000, help="approximate model size in DOF (default 5000)")
    parser.add_argument("--band", type=float, nargs=2, default=(100.0, 400.0), metavar=("LO_HZ", "HI_HZ"),
                        help="calibration band, Hz (default 100 400, as in the paper)")
    parser.add_argument("--zeta", type=float, default=0.002, help="damping ratio of the simulated test article (default 0.002)")
    parser.add_argument("--starts", type=int, default=6, help="Latin-hypercube starts besides the nominal one (default 6)")
    parser.add_argument("--realizations", type=int, default=6, help="cross-validation realizations (default 6)")


def _stage(number: int, title: str) -> None:
    print(f"\n=== [{number}/6] {title}", flush=True)


def _call(argv: list[str]) -> None:
    from frfcal.cli import main

    print("$ frfcal " + " ".join(argv), flush=True)
    status = main(argv)
    if status != 0:
        raise RuntimeError(f"demo: 'frfcal {' '.join(argv)}' failed with status {status}")


def true_offsets(names) -> "np.ndarray":
    """Normalized parameter changes p of the demo's test article (paper Table 2.1 ratios)."""
    import numpy as np

    return np.array([PAPER_TABLE_2_1[n][1] / PAPER_TABLE_2_1[n][0] - 1.0 if n in PAPER_TABLE_2_1 else 0.0
                     for n in names])


def write_plant(pm, p_true, layout_path, out_path, *, zeta: float, f_max_hz: float, suspension_hz: float = 2.0):
    """Modal plant of the model at ``p_true``, seen by the layout's sensors and drives.

    Rigid-body modes become a soft suspension at ``suspension_hz`` (as on
    bungee cords); elastic modes up to ``f_max_hz`` are kept.
    Shapes are mass-normalized (m/sqrt(kg)) along each sensor's direction.
    """
    import numpy as np

    from femodel import sensor_matrix
    from labdata import read_layout_file

    layout = read_layout_file(layout_path)
    c_out = sensor_matrix(pm.assembly, layout.grids("channels"), layout.directions("channels"))
    c_in = sensor_matrix(pm.assembly, layout.grids("drives"), layout.directions("drives"))
    n_modes = 6 + 60
    modes = pm.modes(p_true, n_modes)
    keep = modes.frequencies_hz <= f_max_hz
    keep[: modes.n_rigid] = True
    freq = np.where(np.arange(modes.n_modes) < modes.n_rigid, suspension_hz, modes.frequencies_hz)[keep]
    shapes = modes.shapes[:, keep]
    np.savez(out_path, frequencies_hz=freq, damping=np.full(freq.shape, zeta),
             shapes_out=np.asarray(c_out @ shapes), shapes_in=np.asarray(c_in @ shapes))
    return modes.frequencies_hz[modes.n_rigid:][modes.frequencies_hz[modes.n_rigid:] <= f_max_hz]


def run(args) -> int:
    import json
    import time
    from pathlib import Path

    import numpy as np

    import femodel
    from frfcal._modeplot import plot_mode_shapes
    from labdata import read_layout_file

    t_start = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    lo, hi = args.band
    model_dir = out / "model"
    bdf = model_dir / "subframe.bdf"
    params = model_dir / "subframe_params.toml"

    _stage(1, "FE model: a subframe-like welded steel structure with the paper's 17 parameters")
    _call(["example", "subframe", "--dof", str(args.dof), "--units", "mm-t-s", "--out", str(model_dir)])

    _stage(2, "normal modes")
    _call(["modes", str(bdf), "--units", "mm-t-s", "--n", "20"])
    model = femodel.read_bdf(bdf, units="mm-t-s")
    assembly = femodel.assemble(model)
    modes = femodel.solve_modes(assembly, 12)
    png = plot_mode_shapes(assembly, modes, out / "modes.png", title=f"{bdf.name}: first elastic modes")
    print(f"wrote {png}")

    _stage(3, "pretest: 20 accelerometers and a shaker for the first 20 elastic modes")
    layout = out / "layout.json"
    _call(["pretest", str(bdf), "--units", "mm-t-s", "--sensors", "20", "--modes", "20", "--out", str(layout)])

    _stage(4, "stepped-sine test of a simulated test article (simulated lab)")
    pm = femodel.parametric_model(params)
    p_true = true_offsets(pm.parameters.names)
    f_true = write_plant(pm, p_true, layout, out / "plant.npz", zeta=args.zeta, f_max_hz=3.0 * hi)
    in_band = f_true[(f_true > 0.8 * lo) & (f_true < 1.25 * hi)]
    print("true article: the model with the paper's calibrated changes (Table 2.1); "
          f"{len(in_band)} modes in {0.8 * lo:.0f}-{1.25 * hi:.0f} Hz: " + ", ".join(f"{f:.1f}" for f in in_band))
    plan = out / "plan.toml"
    # The plan knows the poles the *nominal* model predicts (from the pretest);
    # the true article's resonances differ by a few per cent, and the
    # controller's peak search finds and refines them during the sweep.
    f_nom = [f for f in femodel.solve_modes(assembly, 40).frequencies_hz
                                     if 0.8 * lo < f < 1.25 * hi]
    poles = ", ".join(f"{{ frequency_hz = {f:.3f}, damping = {args.zeta} }}" for f in f_nom)
    plan.write_text(
        f'name = "demo"\nlayout = "{layout.name}"\nsample_rate_hz = 12800.0\n\n'
        f'[lines]\nkind = "bandwidth"\nstart_hz = {0.8 * lo}\nstop_hz = {1.25 * hi}\n'
        f"background_step = 0.02\nlines_per_bandwidth = 3\nspan_bandwidths = 2\npoles = [{poles}]\n\n"
        "[force]\nlevels_n = [1.0]\n\n[settle]\ntolerance = 2e-3\n\n[measure]\nblocks = 3\n\n"
        "[refine]\nenabled = true\nlines_per_bandwidth = 3\nspan_bandwidths = 2\n\n"
        '[ensemble]\narticles = ["SF01"]\n\n'
        '[sim]\nmodel = "plant.npz"\nnoise_rms = 1e-4\nseed = 7\n'
    )
    _call(["acquire", str(plan), "--driver", "sim", "--out", str(out / "runs")])
    runs = sorted((out / "runs").glob("*.h5"))
    if not runs:
        raise RuntimeError(f"demo: no run file in {out / 'runs'}")

    _stage(5, "identification: frequency-domain subspace, damping-equalized")
    for run_file in runs:  # the order and the physical poles from the stabilization diagram
        _call(["identify", str(run_file), "--band", f"{0.8 * lo:g}", f"{1.25 * hi:g}",
               "--zeta0", "0.01", "--plot", str(out / "identification")])

    _stage(6, "calibration, hold-out validation and cross-validation")
    names = list(read_layout_file(layout).names("channels"))
    calibrate, holdout = names[::2] + names[1:2], [n for n in names[1::2] if n != names[1]]
    campaign = out / "campaign.toml"
    run_entries = "\n".join(f'[[run]]\npath = "{r.relative_to(out)}"\n' for r in runs)
    campaign.write_text(
        f'[model]\nparameters = "{params.relative_to(out)}"\n\n{run_entries}\n'
        f"[channels]\ncalibrate = {json.dumps(calibrate)}\nholdout = {json.dumps(holdout)}\n\n"
        f"[band]\nlow_hz = {lo}\nhigh_hz = {hi}\n\n"
        f"[calibration]\nstarts = {args.starts}\n\n"
        f"[crossvalidation]\nrealizations = {args.realizations}\n\n"
        '[output]\ndir = "calibration"\n'
    )
    _call(["calibrate", str(campaign)])

    result = json.loads((out / "calibration" / "calibration.json").read_text())
    member = result["members"][0]
    print(f"\n=== summary ({time.perf_counter() - t_start:.0f} s)")
    print(f"{'parameter':<22}{'true p %':>10}{'calibrated p %':>16}  identifiability")
    truth = dict(zip(pm.parameters.names, p_true))
    for row in member["parameters"]:
        verdict = "identifiable" if row.get("identifiable") else f"NOT identifiable: {row.get('identifiability')}"
        print(f"{row['name']:<22}{100 * truth[row['name']]:>+10.2f}{100 * row['p']:>+16.2f}  {verdict}")
    n_id = sum(bool(r.get("identifiable")) for r in member["parameters"])
    print(f"{n_id} of {len(member['parameters'])} parameters identifiable from these channels and band; the "
          "others are reported with the combination the data cannot tell apart, not as results.")
    v = member.get("validation") or {}
    if v:
        print(f"\nhold-out square deviation (Eq. 2.23, raw lines) {v['sd_nominal']:.4g} -> {v['sd_calibrated']:.4g} "
              f"({v.get('verdict', '')}); raw calibration-line SD {member.get('sd_raw_calibration') or float('nan'):.4g}.")
    print(f"\nfigures and files in {out}/: modes.png, layout*.png, identification/, calibration/")
    return 0
