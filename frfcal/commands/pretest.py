"""``frfcal pretest``: sensor layout by Effective Independence, drive point, mass loading, layout file."""

from __future__ import annotations

import argparse

HELP = "plan sensors (Effective Independence) and the shaker position for a model; write the layout file"


def _ints(text: str) -> list[int]:
    out = []
    for part in text.replace(",", " ").split():
        if "-" in part.strip("-") and not part.startswith("-"):
            lo, hi = part.split("-", 1)
            out.extend(range(int(lo), int(hi) + 1))
        else:
            out.append(int(part))
    return out


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", metavar="MODEL.bdf", help="Nastran bulk data deck")
    parser.add_argument("--units", default="si", help="unit system of the deck: si, mm-t-s, in-lbf-s (default si)")
    parser.add_argument("--sensors", type=int, default=20, help="number of sensors (a triax counts once; default 20)")
    modes = parser.add_mutually_exclusive_group()
    modes.add_argument("--modes", type=int, default=None, help="target: the first N elastic modes (default 20)")
    modes.add_argument("--band", type=float, nargs=2, metavar=("LO_HZ", "HI_HZ"), help="target: elastic modes in a band")
    modes.add_argument("--mode-numbers", type=_ints, metavar="N,..", help="target: 1-based mode numbers, e.g. 7-26")
    parser.add_argument("--out", default="layout.json", help="layout file to write (figures go beside it)")
    parser.add_argument("--json", action="store_true", help="print one JSON object (the layout file content)")
    parser.add_argument("--triax", action="store_true", help="triaxial sensors (kept whole)")
    parser.add_argument("--direction", default="normal", metavar="normal|x|y|z|vx,vy,vz",
                        help="single-axis direction (default: local surface normal); write --direction=-1,0,0 for a leading minus")
    parser.add_argument("--include", type=_ints, default=[], metavar="G,..", help="grids that must carry a sensor")
    parser.add_argument("--exclude", type=_ints, default=[], metavar="G,..", help="grids that must not carry a sensor")
    parser.add_argument("--candidates", type=_ints, default=None, metavar="G,..", help="candidate grids (default: all shell grids)")
    parser.add_argument("--pids", type=_ints, default=None, metavar="PID,..", help="candidate grids of these property ids")
    parser.add_argument("--box", type=float, nargs=6, default=None,
                        metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"), help="candidate box, m (basic)")
    parser.add_argument("--min-distance", type=float, default=0.0, metavar="M", help="minimum sensor spacing, m")
    parser.add_argument("--shaker-candidates", type=int, default=5, metavar="N", help="ranked drive points to report")
    parser.add_argument("--drives", type=int, default=1, metavar="K", help="drive points to put in the layout (default 1)")
    parser.add_argument("--free-drive", action="store_true",
                        help="rank drive points over all candidates (default: collocated with the sensors)")
    parser.add_argument("--drive-criterion", choices=["weakest", "adpr", "product"], default="weakest",
                        help="drive ranking: weakest-mode participation (default), ADPR, or their product")
    parser.add_argument("--sensor-mass-g", type=float, default=0.5, help="mass of one sensor, g (default 0.5)")
    parser.add_argument("--drive-mass-g", type=float, default=5.0, help="force sensor + stinger mass, g (default 5)")
    parser.add_argument("--refine-automac", type=float, default=None, metavar="DECADES",
                        help="after EfI, swap sensors to lower the largest off-diagonal autoMAC, giving up at most "
                        "DECADES of det(FIM) (e.g. 1)")
    parser.add_argument("--no-figures", action="store_true", help="do not write the PNG figures")
    parser.add_argument("--evaluate", metavar="LAYOUT.json",
                        help="do not plan: print the metrics of this existing layout for the target modes")
    from frfcal.commands.run import add_campaign_options

    add_campaign_options(parser)  # with a campaign TOML as the first argument


def run(args) -> int:
    from frfcal.commands.run import campaign_command, is_campaign_file

    if is_campaign_file(args.model):  # the campaign form: run the campaign up to this stage
        args._campaign_path = args.model
        return campaign_command(args, "pretest")
    import json
    from pathlib import Path

    import numpy as np

    import femodel
    import pretest

    direction = args.direction
    if not args.triax:
        pretest.parse_direction(direction)
    from frfcal.campaign._schema import PretestSection

    # the campaign's [pretest] settings from the options, unvalidated here: PretestConfig checks them as before
    cfg = PretestSection.model_construct(
        sensors=args.sensors, modes=args.modes, band_hz=args.band, mode_numbers=args.mode_numbers,
        direction=direction, triax=args.triax, candidates=args.candidates, pids=args.pids, include=args.include,
        exclude=args.exclude, min_distance_m=args.min_distance, drives=args.drives,
        shaker_candidates=args.shaker_candidates, free_drive=args.free_drive, drive_criterion=args.drive_criterion,
        sensor_mass_g=args.sensor_mass_g, drive_mass_g=args.drive_mass_g, refine_automac=args.refine_automac,
        box_m=args.box,
    ).config()
    model = femodel.read_bdf(args.model, units=args.units)
    if args.evaluate:
        return _evaluate(args, cfg, model)
    res = pretest.plan_pretest(model, cfg)
    out = Path(args.out)
    pretest.write_layout(out, res, model_path=args.model, units=args.units)
    figures = []
    if not args.no_figures:
        stem = out.with_suffix("")
        figures.append(str(pretest.plot_layout(model, res, f"{stem}_layout.png")))
        figures.append(str(pretest.plot_automac(res, f"{stem}_automac.png")))
    data = pretest.layout_dict(res, model_path=args.model, units=args.units, relative_to=out.parent)
    if args.json:
        data["layout_file"] = str(out)
        data["figures"] = figures
        print(json.dumps(data))
        return 0
    m = res.metrics
    t = res.target
    n_sens = len(set(res.sensors.group.tolist()))
    print(f"model {args.model} ({args.units}): {model.n_grids} grids, {t.n_rigid} rigid-body mode(s)")
    print(f"target: {t.indices.size} modes, {t.frequencies_hz[0]:.2f}-{t.frequencies_hz[-1]:.2f} Hz "
          f"(mode numbers {t.indices[0] + 1}-{t.indices[-1] + 1})")
    print(f"candidates: {np.unique(res.candidates.group).size} "
          f"({'triaxial' if cfg.triax else 'single-axis, ' + str(cfg.direction)}); chosen {n_sens} sensors, "
          f"{res.sensors.n_rows} channels" + (f", {res.efi.n_swaps} distance swaps" if res.efi.n_swaps else ""))
    i, j = m.automac_worst_pair
    ref = res.extra.get("automac_refinement")
    if ref:
        print(f"autoMAC refinement: {ref['swaps']} swap(s), largest off-diagonal {ref['automac_before']:.4f} -> "
              f"{ref['automac_after']:.4f}, log10 det {ref['log10_det_before']:.3f} -> {ref['log10_det_after']:.3f}")
    print(f"Fisher information: log10 det {m.fim_log10_det:.3f}, condition number {m.fim_condition:.4g}")
    print(f"autoMAC: largest off-diagonal {m.automac_max_offdiag:.4f} (modes {t.indices[i] + 1} and {t.indices[j] + 1})")
    print(" mode   f (Hz)  independence  peak frac  mass-load shift (Hz)")
    for k in range(t.indices.size):
        print(f" {t.indices[k] + 1:4d} {t.frequencies_hz[k]:9.2f} {m.mode_independence[k]:12.3f} "
              f"{m.mode_peak_fraction[k]:10.3f} {res.mass_loading.shift_hz[k]:12.4f}")
    print("channels:")
    for name, g, d, x in zip(res.channel_names, res.sensors.grids, res.sensors.directions, res.sensors.xyz_m):
        print(f"  {name:<8s} grid {g:>8d}  dir [{d[0]:+.3f} {d[1]:+.3f} {d[2]:+.3f}]  "
              f"xyz_m [{x[0]:.4f} {x[1]:.4f} {x[2]:.4f}]")
    rk, dc = res.drive_ranking, res.drive_candidates
    print(f"drive candidates ({cfg.drive_criterion}; {'collocated' if cfg.collocated_drive else 'free'}):")
    for r, i in enumerate(rk.order[: cfg.n_shaker_candidates].tolist(), 1):
        d = dc.directions[i]
        print(f"  {r}. grid {dc.grids[i]:>8d} dir [{d[0]:+.3f} {d[1]:+.3f} {d[2]:+.3f}]  weakest "
              f"{rk.weakest[i]:.3f} (mode {t.indices[rk.weakest_mode[i]] + 1})  ADPR {rk.adpr_normalized[i]:.3f}")
    for n, g in zip(res.drive_names, res.drives.grids):
        print(f"{n}: grid {g}")
    print(f"wrote {out}" + "".join(f"\nwrote {f}" for f in figures))
    return 0


def _evaluate(args, cfg, model) -> int:
    """Metrics, drive ranking and mass loading of an existing layout file."""
    import json

    import numpy as np

    import femodel
    import pretest

    lay = pretest.read_layout(args.evaluate)
    asm = femodel.assemble(model)
    for which in ("channels", "drives"):
        grids = lay.grids(which)
        missing = np.setdiff1d(grids, model.grid_ids)
        if missing.size:
            raise pretest.PretestError(f"{args.evaluate}: {which} grid(s) {missing.tolist()[:10]} not in {args.model}")
    target = pretest.compute_target_modes(asm, n_modes=cfg.n_modes, band_hz=cfg.band_hz, mode_numbers=cfg.mode_numbers)
    m = pretest.evaluate_channels(asm, lay.grids(), lay.directions(), target)
    c = femodel.sensor_matrix(asm, lay.grids(), lay.directions())
    rk = pretest.rank_drive_points(np.asarray(c @ target.shapes), target.frequencies_hz, criterion=cfg.drive_criterion)
    sensor_grids = np.unique(lay.grids())
    load_grids = np.concatenate([sensor_grids, lay.grids("drives")])
    masses = np.concatenate([np.full(sensor_grids.size, cfg.sensor_mass_kg), np.full(len(lay.drives), cfg.drive_mass_kg)])
    g3 = np.repeat(load_grids, 3)
    u = np.asarray(femodel.sensor_matrix(asm, g3, np.tile(np.eye(3), (load_grids.size, 1))) @ target.shapes)
    ml = pretest.mass_loading_shifts(target.frequencies_hz, u.reshape(load_grids.size, 3, -1), masses)
    out = {
        "layout": str(args.evaluate),
        "target_modes_hz": [float(f) for f in target.frequencies_hz],
        "target_mode_numbers": [int(i) + 1 for i in target.indices],
        "metrics": m.as_dict(),
        "channel_drive_ranking": [
            {"name": lay.channels[i].name, "weakest_participation": float(rk.weakest[i]),
             "adpr_normalized": float(rk.adpr_normalized[i])} for i in rk.order.tolist()
        ],
        "mass_loading_shift_hz": [float(v) for v in ml.shift_hz],
    }
    if args.json:
        print(json.dumps(out))
        return 0
    i, j = m.automac_worst_pair
    print(f"layout {args.evaluate}: {len(lay.channels)} channels, {len(lay.drives)} drive(s) on {args.model}")
    print(f"target: {target.indices.size} modes, {target.frequencies_hz[0]:.2f}-{target.frequencies_hz[-1]:.2f} Hz")
    print(f"Fisher information: log10 det {m.fim_log10_det:.3f}, condition number {m.fim_condition:.4g}")
    print(f"autoMAC: largest off-diagonal {m.automac_max_offdiag:.4f} "
          f"(modes {target.indices[i] + 1} and {target.indices[j] + 1})")
    print(" mode   f (Hz)  independence  mass-load shift (Hz)")
    for k in range(target.indices.size):
        print(f" {target.indices[k] + 1:4d} {target.frequencies_hz[k]:9.2f} {m.mode_independence[k]:12.3f} "
              f"{ml.shift_hz[k]:12.4f}")
    return 0
