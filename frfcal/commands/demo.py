"""``frfcal demo``: the whole job of the toolkit on the bundled example, as one campaign.

1. ``frfcal example subframe --gap-mm 2``: the subframe FE model with its 17
   parameters and a doubler sheet facing the rail web across a 2 mm air gap
   (nothing joins them in the model);
2. ``frfcal pretest``: 20 accelerometers and a shaker by Effective Independence;
3. the campaign file ``campaign.toml`` (written here, docs/campaign.md): five
   simulated articles (``[simulation]``: the deck at the paper's Table 2.1
   changes plus scatter, free-free, damping per mode); on SF1-SF3 the gap is
   closed (a contact spring across the gap pairs), on SF4-SF5 open; SF5 has a
   loose part that rattles at the higher force level; the simulated lab sweeps
   each at 0.25 N and 1 N (at 1 N the sharpest resonance reaches about 270 m/s^2 of the 500 m/s^2 accelerometer range); calibration of the 17 parameters on 11 channels,
   hold-out validation on 9, cross-validation, one calibration per article group;
4. ``frfcal run campaign.toml``: every stage that exists, stored under ``DIR/campaign``;
5. the level check of every article (the 1 N runs against the 0.25 N runs)
   and the headline numbers.
"""

from __future__ import annotations

import argparse

from frfcal.campaign._acquire import PAPER_TABLE_2_1, paper_offsets  # noqa: F401  (the demo's truth)

HELP = "run the example campaign: model with an air gap, pretest, 5 simulated articles at 2 levels, calibration"

ARTICLES = ("SF1", "SF2", "SF3", "SF4", "SF5")
GAP_CLOSED = ("SF1", "SF2", "SF3")
LOOSE = "SF5"
LEVELS_N = (0.25, 1.0)
#: relative FRF error the settle detector leaves per line (the level check allows it between runs)
SETTLE_TOLERANCE = 3e-3


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="demo-output", help="output directory (default demo-output)")
    parser.add_argument("--dof", type=int, default=5000, help="approximate model size in DOF (default 5000)")
    parser.add_argument("--band", type=float, nargs=2, default=(100.0, 400.0), metavar=("LO_HZ", "HI_HZ"),
                        help="calibration band, Hz (default 100 400, as in the paper)")
    parser.add_argument("--starts", type=int, default=3, help="Latin-hypercube starts besides the nominal one (default 3)")
    parser.add_argument("--realizations", type=int, default=4, help="cross-validation realizations (default 4)")
    parser.add_argument("--workers", type=int, default=None, help="local worker processes (default: all cores)")


def _step(title: str) -> None:
    print(f"\n=== {title}", flush=True)


def _call(argv: list[str]) -> None:
    """Run one frfcal command as a user would type it (printed with a ``$``)."""
    from frfcal.cli import main

    print("$ frfcal " + " ".join(argv), flush=True)
    status = main(argv)
    if status != 0:
        raise RuntimeError(f"demo: 'frfcal {' '.join(argv)}' failed with status {status}")


def contact_rate(pm, layout_path, gap_pairs, band_hz) -> tuple[float, int]:
    """Rate (N/m) and component of the demo's contact spring: ``frfcal.effects`` sizing of a closed gap."""
    from frfcal.effects import standard_effects
    from frfcal.synth import SynthChannel
    from labdata import read_layout_file

    lay = read_layout_file(layout_path)
    sens = [SynthChannel(n, g, d) for n, g, d in zip(lay.names("channels"), lay.grids("channels"),
                                                     lay.directions("channels"))]
    drv = [SynthChannel(n, g, d) for n, g, d in zip(lay.names("drives"), lay.grids("drives"), lay.directions("drives"))]
    (eff,) = standard_effects(pm, sens, drv, gap=gap_pairs, band_hz=band_hz)["contact_spring"]
    comp = eff.term.dofs[0][1]
    return float(eff.term.scale), int(comp)


def write_campaign(path, *, params, layout, channels, band, gap_pairs, rate, component, starts, realizations,
                   workers=None) -> None:
    """The demo's campaign file (docs/campaign.md): simulated acquisition, calibration per article group."""
    import json

    lo, hi = band
    calibrate, holdout = channels[::2] + channels[1:2], [n for n in channels[1::2] if n != channels[1]]
    pairs = ", ".join(f"[{a}, {b}]" for a, b in gap_pairs)
    execution = "" if workers is None else f"\n[execution]\nworkers = {workers}\n"
    text = f"""# The frfcal demo campaign (written by 'frfcal demo'; run it with 'frfcal run campaign.toml')
[model]
parameters = "{params}"

[layout]
file = "{layout}"

[acquisition]
driver = "sim"
dir = "runs"

[acquisition.plan]          # the stepped-sine plan (docs/acquisition.md); channels from the layout
name = "demo"
sample_rate_hz = 1280.0
[acquisition.plan.lines]    # no predicted poles: the controller finds the articles' peaks on a 1 % background
kind = "bandwidth"
start_hz = {0.8 * lo:g}
stop_hz = {1.1 * hi:g}
background_step = 0.01
[acquisition.plan.force]
levels_n = {json.dumps(list(LEVELS_N))}
[acquisition.plan.settle]
tolerance = {SETTLE_TOLERANCE:g}
assumed_damping = 0.002
[acquisition.plan.measure]
blocks = 3
n_harmonics = 1
[acquisition.plan.limits]   # a local doubler-sheet mode near the shaker peaks at thousands of m/s^2 per N:
acceleration_m_s2_max = 1e4 # its few lines clip the accelerometers (flagged, left out), the sweep goes on
on_overload = "flag"
drive_v_max = 20.0          # and the shaker's force drops there (back-EMF): more voltage for the force level
[acquisition.plan.refine]
enabled = true
lines_per_bandwidth = 3
span_bandwidths = 2
peak_ratio = 1.02           # the noise is low: any local maximum of three background lines is a peak to refine
[acquisition.plan.ensemble]
articles = {json.dumps(list(ARTICLES))}

[simulation]                # what the articles are (the model does not know the gap or the loose part)
offsets = "paper"
scatter = 0.003
seed = 7
zeta_range = [1e-3, 3e-3]
mode_factor = 1.5
noise_rms = 2e-5

[[simulation.effect]]       # the air gap is closed on SF1-SF3: contact springs across the facing grids
name = "gap_contact"
kind = "spring"
articles = {json.dumps(list(GAP_CLOSED))}
pairs = [{pairs}]
components = [{component}]
rate_n_per_m = {rate:.6g}

[simulation.loose_part]     # SF5 rattles at the high level
article = "{LOOSE}"
shift = 0.003
from_level_n = {LEVELS_N[-1]:g}

[channels]
calibrate = {json.dumps(calibrate)}
holdout = {json.dumps(holdout)}

[band]
low_hz = {lo:g}
high_hz = {hi:g}

[calibration]
starts = {starts}
max_cycles = 2
refine_cycles = 1
ensemble = "group"
n_groups = 2

[crossvalidation]
realizations = {realizations}
{execution}
[output]
dir = "campaign"
"""
    from pathlib import Path

    Path(path).write_text(text)


def run(args) -> int:
    import json
    import os
    import time
    from pathlib import Path

    import femodel
    from frfcal.campaign import load_campaign, run_campaign
    from frfcal.campaign._acquire import level_checks, runs_by_level
    from labdata import read_layout_file

    t_start = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    lo, hi = args.band
    model_dir = out / "model"

    _step("[1/4] FE model: the subframe with 17 parameters and a doubler sheet 2 mm off the rail web")
    print(f"$ frfcal example subframe --dof {args.dof} --units mm-t-s --gap-mm 2 --out {model_dir}", flush=True)
    ex = femodel.example_subframe(model_dir, target_dof=args.dof, units="mm-t-s", gap_mm=2.0)
    print(f"wrote {ex.bdf} ({ex.n_dof} DOF, {ex.mass_kg:.2f} kg) and {ex.params}; air gap 2 mm: "
          f"{len(ex.gap_pairs)} facing grid pairs that no element joins")

    _step("[2/4] pretest: 20 accelerometers and a shaker for the first 20 elastic modes")
    layout = out / "layout.json"
    _call(["pretest", str(ex.bdf), "--units", "mm-t-s", "--sensors", "20", "--modes", "20", "--out", str(layout)])

    _step("[3/4] the campaign file: 5 simulated articles, gap closed on SF1-SF3, SF5 loose at the high level")
    pm = femodel.parametric_model(ex.params)
    rate, comp = contact_rate(pm, layout, ex.gap_pairs, (lo, hi))
    print(f"closed gap: {len(ex.gap_pairs)} contact springs of {rate:.4g} N/m along component {comp} "
          "(frfcal.effects sizing of a closed gap)")
    names = list(read_layout_file(layout).names("channels"))
    campaign = out / "campaign.toml"
    write_campaign(campaign, params=Path(os.path.relpath(ex.params, out)).as_posix(), layout=layout.name, channels=names, band=(lo, hi),
                   gap_pairs=ex.gap_pairs, rate=rate, component=comp, starts=args.starts,
                   realizations=args.realizations, workers=args.workers)
    print(f"wrote {campaign}")

    _step("[4/4] $ frfcal run campaign.toml")
    camp = load_campaign(campaign)
    res = run_campaign(camp, log=lambda m: print(m, flush=True))
    runs = runs_by_level(res_paths(out / "campaign" / "runs"))
    checks = level_checks(runs, settle_tolerance=SETTLE_TOLERANCE)

    _step(f"summary ({time.perf_counter() - t_start:.0f} s)")
    print("stages: " + ", ".join(f"{k} {v['status']} ({v.get('time_s') or 0:.0f} s)" for k, v in res["stages"].items()))
    for m in res.get("members", []):
        v = m.get("validation") or {}
        print(f"member {m.get('member', '?')}: articles {', '.join(m.get('articles', []))}")
        print(f"  calibration (equalized identified model): SD {m['sd_calibration_nominal']:.3g} (nominal) -> "
              f"{m['sd_calibration']:.3g} (calibrated)")
        if m.get("sd_raw_calibration") is not None:
            print(f"  calibration lines (raw): SD {m['sd_raw_calibration_start']:.3g} -> {m['sd_raw_calibration']:.3g}")
        if v:
            print(f"  hold-out channels: SD {v['sd_nominal']:.3g} (nominal) -> {v['sd_calibrated']:.3g} (calibrated); "
                  f"noise floor {v.get('sd_floor', float('nan')):.3g}; {v.get('verdict', '')}")
    for article, ld in checks.items():
        verdict = ld if isinstance(ld, str) else \
            "NONLINEAR (the FRF changes with force level beyond noise)" if ld.flagged else "linear"
        print(f"level check {article} ({', '.join(f'{x:g} N' for x, _ in runs[article])}): {verdict}")
    nonlinear = [a for a, ld in checks.items() if not isinstance(ld, str) and ld.flagged]
    print(f"nonlinear article(s): {', '.join(nonlinear) or 'none'}")
    print("the effect the model lacks: the diagnose stage is not part of this build (its stage is not merged); "
          f"the truth: the gap is closed on {', '.join(GAP_CLOSED)}")
    print(f"\nresults: {out / 'campaign'}/calibration.json, figures and stages/; campaign file {campaign}")
    (out / "demo_summary.json").write_text(json.dumps({
        "members": [{k: m.get(k) for k in ("member", "articles", "sd_calibration_nominal", "sd_calibration",
                                           "sd_raw_calibration_start", "sd_raw_calibration", "validation")}
                    for m in res.get("members", [])],
        "level_checks": {a: ld if isinstance(ld, str) else ld.flagged for a, ld in checks.items()},
        "nonlinear": nonlinear,
        "time_s": time.perf_counter() - t_start}, indent=1, default=str))
    return 0


def res_paths(directory):
    """Run files of the acquire stage's directory."""
    from pathlib import Path

    return sorted(Path(directory).glob("*.h5"))
