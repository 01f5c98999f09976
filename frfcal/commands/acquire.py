"""``frfcal acquire PLAN.toml --driver sim|visa|ni --out DIR``: run a stepped-sine plan."""

from __future__ import annotations

import argparse

HELP = "run a stepped-sine sweep plan (simulated lab, VISA or NI-DAQmx) into HDF5 run files"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("plan", help="sweep plan (TOML, see docs/acquisition.md)")
    parser.add_argument("--driver", choices=("sim", "visa", "ni"), default="sim", help="backend (default: sim)")
    parser.add_argument("--out", default="runs", help="output directory for run files (default: runs)")
    parser.add_argument("--hardware", help="hardware configuration TOML (needed for visa/ni)")
    parser.add_argument("--dry-run", action="store_true", help="print the plan and estimated duration, move nothing")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--plot", action="store_true", help="live plot of the FRF while measuring (matplotlib)")
    parser.add_argument("--json", action="store_true", help="print one JSON object with the results")
    from frfcal.commands.run import add_campaign_options

    add_campaign_options(parser)  # with a campaign TOML as the first argument


def _sim_factory(plan):
    import numpy as np

    from acquisition import ModalPlant, ShakerModel, SimulatedLab
    from acquisition._plan import sim_plant_arrays

    sim = plan.sim
    fr, zeta, po, pi = sim_plant_arrays(plan)
    articles = list(plan.ensemble.articles)

    def make(article: str, drive_index: int, drive):
        rng = np.random.default_rng([sim.seed, articles.index(article)])
        f_art = fr * (1 + sim.article_scatter * rng.standard_normal(fr.shape))
        plant = ModalPlant(f_art, zeta, po, pi)
        return SimulatedLab(plant, drive_index=drive_index,
                            shaker=ShakerModel() if sim.shaker == "electrodynamic" else None,
                            noise_rms=sim.noise_rms, adc_bits=sim.adc_bits,
                            seed=sim.seed + 1000 * articles.index(article) + drive_index)

    def channels(sensors, drive):
        from dataclasses import replace

        return tuple(replace(c, physical=f"sim/{k}") for k, c in enumerate(sensors)) + (replace(drive, physical="sim/force"),)

    return make, channels


def _hardware_factory(plan, kind: str, hardware_path: str | None):
    if hardware_path is None:
        raise ValueError(f"--driver {kind} needs --hardware HW.toml (physical channels and instrument set-up)")
    try:
        from acquisition._hardware_config import read_hardware_config
    except ImportError as exc:
        raise ValueError(f"--driver {kind}: the hardware driver modules are not available ({exc})") from None
    cfg = read_hardware_config(hardware_path)

    def make(article, drive_index, drive):
        try:
            return cfg.make_driver(kind)
        except ImportError as exc:
            extra = "visa" if kind == "visa" else "ni"
            raise ValueError(f"--driver {kind}: missing package ({exc}); install the extra: pip install 'frfcal[{extra}]'") from None

    def channels(sensors, drive):
        return cfg.mapped(tuple(sensors) + (drive,))

    return make, channels


def _live_plot():
    try:
        import matplotlib.pyplot as plt
    except ImportError:
        raise ValueError("--plot needs matplotlib (pip install matplotlib)") from None
    import numpy as np

    plt.ion()
    fig, ax = plt.subplots()
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel("|H| (SI)")
    ax.set_yscale("log")
    data: list = []

    def on_line(f, frf, quality):
        data.append((f, np.abs(frf[:, 0])))
        fs = np.array([d[0] for d in data])
        order = np.argsort(fs)
        mags = np.array([d[1] for d in data])[order]
        ax.cla()
        ax.set_yscale("log")
        ax.plot(fs[order], mags, ".-", lw=0.8)
        ax.set_xlabel("frequency (Hz)")
        ax.set_ylabel("|H| (SI)")
        fig.canvas.draw_idle()
        plt.pause(0.001)

    return on_line


def run(args) -> int:
    from frfcal.commands.run import campaign_command, is_campaign_file

    if is_campaign_file(args.plan):  # the campaign form: run the campaign up to this stage
        args._campaign_path = args.plan
        return campaign_command(args, "acquire")
    import json
    import signal
    import sys

    from acquisition import load_plan, plan_channels, plan_lines, run_plan, summarize_plan
    from acquisition._plan import estimate_duration_s

    plan = load_plan(args.plan)
    sensors, drives = plan_channels(plan)
    summary = summarize_plan(plan, n_drives=len(drives))
    if args.dry_run:
        lines = plan_lines(plan)
        if args.json:
            print(json.dumps({"plan": plan.name, "n_lines": int(lines.size), "start_hz": float(lines.min()),
                              "stop_hz": float(lines.max()), "n_sensors": len(sensors), "n_drives": len(drives),
                              "estimated_s_per_run": float(estimate_duration_s(plan, lines).sum() / len(plan.force.levels_n)),
                              "dry_run": True}))
        else:
            print(summary)
            print(f"  {len(sensors)} response channel(s), drives: {', '.join(d.name for d in drives)}")
        return 0
    if args.driver == "sim":
        make, channels = _sim_factory(plan)
    else:
        make, channels = _hardware_factory(plan, args.driver, args.hardware)
    if not args.json:
        print(summary)

    def _term(signum, frame):  # SIGTERM takes the same safe path as Ctrl-C
        raise KeyboardInterrupt

    from acquisition import AcquisitionAbort, DriverError

    old = signal.signal(signal.SIGTERM, _term)
    try:
        results = run_plan(plan, make, args.out, progress=not (args.no_progress or args.json),
                           on_line=_live_plot() if args.plot else None, driver_channels=channels)
    except (AcquisitionAbort, DriverError, KeyboardInterrupt) as exc:
        # The controller has already ramped the drive to zero and closed the run
        # file as "aborted"; say so in one line instead of a traceback.
        what = "interrupted" if isinstance(exc, KeyboardInterrupt) else f"{type(exc).__name__}: {exc}"
        print(f"frfcal acquire: aborted ({what}); drive ramped to zero, every completed line is kept in "
              f"{args.out}; run the same command again to resume", file=sys.stderr)
        return 3 if not isinstance(exc, KeyboardInterrupt) else 130
    finally:
        signal.signal(signal.SIGTERM, old)
    if args.json:
        print(json.dumps({"runs": [{"path": r.path, "status": r.status, "n_lines": r.n_lines,
                                    "new_lines": r.n_new_lines, "refined_lines": r.lines_added_by_refinement,
                                    "clock_s": r.clock_s, "found_poles": [list(p) for p in r.found_poles]}
                                   for r in results]}))
    else:
        for r in results:
            print(f"{r.path}: {r.status}, {r.n_lines} lines ({r.n_new_lines} new, "
                  f"{r.lines_added_by_refinement} by refinement), {r.clock_s:.1f} s of driver clock")
    return 0
