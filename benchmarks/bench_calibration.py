"""Calibration benchmark on the example subframe through the whole chain (paper Sec. 2.3.4 side by side).

Truth data come from ``frfcal.synth`` (full-order modes of the deck at parameter offsets, damping
varying from mode to mode, the exact residual of the higher modes, 0.5-1 % noise plus a floor, an
uneven line grid dense at the resonances), independently of the calibration path. The campaign then
runs as a user's would: run files -> identification (automatic order) -> equalized multi-start ->
re-basis cycles -> raw-line refinement -> hold-out validation -> cross-validation
(``calibration.run_campaign``), in a fresh interpreter started as the ``frfcal`` command is (cold imports
and heap, a main process: this process's own parametric model of the deck would flatter the timings by
~1.5 s, and a multiprocessing child is taken for a pool's worker and given one data thread).
Accuracy is reported beside its floor: the SD of the truth itself against its own noisy lines.

    python benchmarks/bench_calibration.py [--dof 200000] [--starts 20] [--realizations 10] [--cache DIR]

``--cache DIR`` keeps the example deck and the truth data in DIR and reuses them on the next run with the
same ``--dof`` and ``--seed`` (the truth takes 25-50 s to generate; it is never part of the timings).
``--no-truth-damping`` skips the hold-out SD with the truth's damping (a full-order solve, ~30 s).
``--split-holdout`` adds that SD at two mixtures of calibrated and true p (identifiable parameters
calibrated and the others true, and the reverse; two more full-order solves): where the hold-out error sits.

Prints a table and writes benchmarks/results/calibration.json. The script imports the installed
(editable) packages: to measure a worktree's code run it as ``PYTHONPATH=. python benchmarks/...``
from the worktree.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

PAPER = {  # seconds, 8 cores (method paper Sec. 2.3.4)
    "model, basis, gradients": 8 * 60 + 2,
    "LM (multi-start)": 5 * 60 + 50,
    "calibration total": 14 * 60 + 50,
    "hold-out validation": 5 * 60 + 16,
    "cross-validation (10)": 17 * 60 + 8,
    "overall": 37 * 60 + 14,
}


def _campaign_child(camp_path: str, out_path: str) -> None:
    """The campaign in this (fresh) process, with its own CPU, system time and page faults, pickled to
    ``out_path``."""
    from frfcal._malloc import keep_large_allocations

    malloc_tuned = keep_large_allocations()  # as the frfcal command does
    from frfcal.campaign import load_campaign, run_campaign

    camp = load_campaign(camp_path)
    lines = []
    t = time.perf_counter()
    c0 = time.process_time()
    o0 = os.times()
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    res = run_campaign(camp, log=lambda m: (lines.append(m), print("  " + m, flush=True)))
    wall = time.perf_counter() - t
    cpu_main = time.process_time() - c0
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    o1 = os.times()  # the executor's workers have ended: their CPU time is in the children's
    Path(out_path).write_bytes(pickle.dumps({
        "res": res, "lines": lines, "wall_s": wall, "cpu_main_s": cpu_main, "malloc_tuned": malloc_tuned,
        # system time and first touches of fresh pages in this process: on a VM that hands freed memory back
        # to its host (free page reporting) a fresh GB costs 1-2 s to page in (docs/calibration.md, stop 39)
        "sys_main_s": r1.ru_stime - r0.ru_stime,
        "faults_gb": (r1.ru_minflt - r0.ru_minflt) * resource.getpagesize() / 1e9,
        "cpu_workers_s": o1.children_user + o1.children_system - o0.children_user - o0.children_system,
        "peak_memory_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6,  # KiB on Linux
    }))


def _campaign_in_fresh_process(camp_path) -> dict:
    """The campaign in a new interpreter started as the ``frfcal`` command is (a main process: not a
    multiprocessing child, which frfcal would take for a pool's worker and give one data thread)."""
    import subprocess

    with tempfile.TemporaryDirectory(prefix="bench_cal_res_") as d:
        out = Path(d) / "result.pkl"
        proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--campaign-child", str(camp_path),
                               str(out)])
        if proc.returncode != 0 or not out.exists():
            raise SystemExit(f"the campaign process ended without a result (exit code {proc.returncode})")
        return pickle.loads(out.read_bytes())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dof", type=int, default=200_000)
    ap.add_argument("--starts", type=int, default=20)
    ap.add_argument("--realizations", type=int, default=10)
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--max-cycles", type=int, default=None, help="re-basis cycles of the equalized stage")
    ap.add_argument("--refine-cycles", type=int, default=None, help="re-basis cycles of the raw-line stage")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a [calibration] setting of the campaign (TOML value), e.g. --set seed=3; repeatable")
    ap.add_argument("--cache", default=None, help="directory keeping the deck and truth data between runs")
    ap.add_argument("--no-truth-damping", action="store_true",
                    help="skip the hold-out SD of the calibrated p with the truth's damping (~30 s)")
    ap.add_argument("--split-holdout", action="store_true",
                    help="also the hold-out SD with the truth's damping at two mixtures of calibrated and true p "
                         "(identifiable parameters calibrated, the others true; and the reverse): two more "
                         "full-order solves")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "calibration.json"))
    ap.add_argument("--campaign-child", nargs=2, metavar=("CAMPAIGN", "RESULT"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.campaign_child:
        _campaign_child(*args.campaign_child)
        return 0
    import tomllib

    settings = {}
    for kv in args.set:
        key, sep, value = kv.partition("=")
        if not sep:
            ap.error(f"--set {kv!r}: expected KEY=VALUE")
        settings[key.strip()] = tomllib.loads(f"v = {value}")["v"]
    import femodel
    from frfcal.synth import SynthChannel, synthesize

    band = (100.0, 400.0)
    tmp = Path(tempfile.mkdtemp(prefix="bench_cal_"))
    cache = None
    if args.cache:
        cache = Path(args.cache) / f"dof{args.dof}_seed{args.seed}"
        cache.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    ex = femodel.example_subframe((cache or tmp) / "model", target_dof=args.dof)
    print(f"example: {ex.n_dof} DOF ({time.perf_counter() - t0:.1f} s)", flush=True)
    pm = femodel.parametric_model(ex.params)
    g = np.asarray(pm.assembly.model.grid_ids)
    grids = g[np.linspace(3, len(g) - 10, 20).astype(int)]
    dirs = np.tile([0.0, 0.0, 1.0], (20, 1))
    dirs[1::4] = [1.0, 0.0, 0.0]
    dirs[2::4] = [0.0, 1.0, 0.0]
    names = [f"acc{i + 1}" for i in range(20)]
    sensors = [SynthChannel(n, int(gid), tuple(d)) for n, gid, d in zip(names, grids, dirs)]
    drives = [SynthChannel("force17", int(grids[16]), tuple(dirs[16]))]  # collocated with acc17
    cal = [names[i] for i in (0, 4, 6, 9, 11, 12, 13, 14, 17, 18, 19)]  # the paper's 11
    hold = [n for n in names if n not in cal]  # 9

    t = time.perf_counter()
    kept = None if cache is None else cache / "synth.pkl"
    if kept is not None and kept.exists():
        sc = pickle.loads(kept.read_bytes())
        t_truth = 0.0
        print(f"truth data: reused from {cache}", flush=True)
    else:
        sc = synthesize(ex.bdf, ex.params, (cache or tmp) / "data", sensors=sensors, drives=drives, band_hz=band,
                        n_articles=1, seed=args.seed, parametric=pm, write_uff=False)
        t_truth = time.perf_counter() - t
        if kept is not None:
            sc._cache.clear()
            kept.write_bytes(pickle.dumps(sc))
        print(f"truth data: {t_truth:.1f} s (not timed below)", flush=True)
    del pm
    camp_path = sc.write_campaign(
        tmp / "campaign.toml", calibrate=cal, holdout=hold, band_hz=band,
        calibration={"starts": args.starts,
                     **({} if args.max_cycles is None else {"max_cycles": args.max_cycles}),
                     **({} if args.refine_cycles is None else {"refine_cycles": args.refine_cycles}),
                     **settings},
        crossvalidation={"realizations": args.realizations},
        execution={"workers": args.workers} if args.workers else {}, output={"dir": str(tmp / "out"),
                                                                          "figures": False})
    # the campaign runs in a fresh interpreter, as the frfcal command would: this process has built a
    # parametric model of the deck (sensor grids, truth data), and its warm heap and imports would flatter
    # the timings by about 1.5 s (docs/calibration.md, stop 40)
    load_start = os.getloadavg()[0]
    run = _campaign_in_fresh_process(camp_path)
    res, lines = run["res"], run["lines"]
    wall, cpu_main, sys_main, faults_gb = run["wall_s"], run["cpu_main_s"], run["sys_main_s"], run["faults_gb"]
    cpu_workers, malloc_tuned = run["cpu_workers_s"], run["malloc_tuned"]
    m = res["members"][0]
    tm, tg = m["timings"], res["timings"]
    cyc = m["calibration"]["cycles"]
    ms = m["calibration"]["multistart"]
    n_run = len(ms["starts"])
    ref = m["calibration"].get("refinement") or {}
    T = {
        "parametric model": tg["model_s"],
        "identification": tg["identification_s"],
        "basis + reduced terms": tg["basis_s"],
        "LM (multi-start)": cyc[0]["fit_s"],
        # builds and fits of the further equalized cycles, and the basis checks that decided them
        "re-basis cycles": sum(c["basis_s"] + c["fit_s"] for c in cyc[1:])
        + sum(c.get("basis_check", {}).get("time_s", 0.0) for c in cyc),
    }
    T["model, basis, gradients"] = T["parametric model"] + T["basis + reduced terms"]
    T["refinement (raw lines, incl. its re-basis)"] = tm["calibration_s"] - sum(
        c["fit_s"] + (c["basis_s"] if k else 0.0) + c.get("basis_check", {}).get("time_s", 0.0)
        for k, c in enumerate(cyc))
    T["refinement LM stages"] = sum(st["time_s"] for st in ref.get("stages", []))
    T["refinement re-basis builds"] = T["refinement (raw lines, incl. its re-basis)"] - T["refinement LM stages"]
    T["calibration total"] = T["model, basis, gradients"] + tm["calibration_s"]
    T["hold-out validation"] = tm["validation_s"]
    T["cross-validation (10)"] = tm["crossvalidation_s"]
    T["overall"] = T["calibration total"] + T["hold-out validation"] + T["cross-validation (10)"]

    p = np.array([row["p"] for row in m["parameters"]])
    p_true = sc.p_true[0]
    err = np.abs((1 + p) / (1 + p_true) - 1)
    ident = np.array([row["identifiable"] for row in m["parameters"]])
    floor_hold, floor_cal = sc.floor_sd(hold, band), sc.floor_sd(cal, band)
    sd_hold = m["validation"]["sd_calibrated"]
    t = time.perf_counter()
    sd_hold_truth_damping = float("nan") if args.no_truth_damping else sc.model_sd(p, 0, hold, band)
    t_model_sd = time.perf_counter() - t
    split = {}
    if args.split_holdout:  # where the hold-out error sits: in the identifiable parameters or in the others
        split = {"identifiable calibrated, others true": sc.model_sd(np.where(ident, p, p_true), 0, hold, band),
                 "identifiable true, others calibrated": sc.model_sd(np.where(ident, p_true, p), 0, hold, band)}
    mem = run["peak_memory_gb"]  # the campaign process (its workers are small)

    print()
    print(f"{'step':<44}{'paper (8 cores)':>16}{'here (2 cores)':>16}")
    for k in ["model, basis, gradients", "LM (multi-start)", "calibration total", "hold-out validation",
              "cross-validation (10)", "overall"]:
        print(f"{k:<44}{PAPER[k]:>15.0f}s{T[k]:>15.1f}s")
    print(f"multi-start: {n_run} of {args.starts + 1} starts ran (paper: 21), {ms.get('distinct_minima')} distinct "
          "minimum/minima" + (" (stopped by the Bayesian rule)" if n_run < args.starts + 1 else ""))
    for k in ["parametric model", "basis + reduced terms", "re-basis cycles",
              "refinement (raw lines, incl. its re-basis)", "refinement LM stages", "refinement re-basis builds",
              "identification"]:
        print(f"{k:<44}{'':>16}{T[k]:>15.1f}s")
    print("equalized re-basis builds: " + ", ".join(f"{c['basis_s']:.1f} s (r={c['basis_size']})" for c in cyc[1:]))
    checks = [c["basis_check"] for c in cyc if "basis_check" in c] + list(ref.get("basis_checks", []))
    print("basis checks (largest Ritz residual / tolerance, time): " + ", ".join(
        f"{b['eta_max']:.2e}/{b['tol']:.2e} "
        f"{'final point' if b.get('final') else 'kept' if b['adequate'] else 're-basis'} {b['time_s']:.1f} s"
        f" (CPU {b.get('cpu_s', float('nan')):.1f} s)"
        for b in checks))
    print(f"peak memory {mem:.2f} GB; campaign wall {wall:.1f} s, CPU main process {cpu_main:.1f} s (of it system "
          f"{sys_main:.1f} s; fresh pages touched {faults_gb:.2f} GB) + workers {cpu_workers:.1f} s; "
          f"load average at start {load_start:.1f}, at end {os.getloadavg()[0]:.1f}")
    print()
    print(f"{'accuracy':<60}{'value':>12}{'floor':>12}{'ratio':>8}")
    print(f"{'hold-out SD, campaign (damping estimated on cal. channels)':<60}{sd_hold:>12.3g}{floor_hold:>12.3g}"
          f"{sd_hold / floor_hold:>8.2f}")
    print(f"{'hold-out SD, calibrated p with the truth damping':<60}{sd_hold_truth_damping:>12.3g}"
          f"{floor_hold:>12.3g}{sd_hold_truth_damping / floor_hold:>8.2f}")
    for k, v in split.items():
        print(f"{'  truth damping, ' + k:<60}{v:>12.3g}{floor_hold:>12.3g}{v / floor_hold:>8.2f}")
    print(f"{'raw calibration-line SD':<60}{m['sd_raw_calibration']:>12.3g}{floor_cal:>12.3g}"
          f"{m['sd_raw_calibration'] / floor_cal:>8.2f}")
    print(f"{'equalized-stage SD (identified model, zeta0)':<60}{m['sd_calibration']:>12.3g}")
    print(f"identifiable {ident.sum()} of {ident.size}; largest error of those {100 * err[ident].max():.3f} %, "
          f"rms {100 * np.sqrt(np.mean(err[ident] ** 2)):.3f} %; of the others: "
          + ", ".join(f"{row['name']} {100 * e:.1f} %" for row, e, i in zip(m["parameters"], err, ident) if not i))
    # each error against the std the campaign reports for it (p-error over p-std; the larger of the formal std
    # and the cross-validation refits' spread): an honest std keeps these near 1-3
    std = np.array([r["std_p"] if r["std_p"] is not None else np.inf for r in m["identifiability"]["parameters"]])
    in_std = np.abs(p - p_true) / std
    if ident.any():
        print("identifiable errors in units of their reported std: "
              + ", ".join(f"{row['name']} {z:.1f}" for row, z, i in zip(m["parameters"], in_std, ident) if i))
    out = {
        "dof": int(ex.n_dof), "n_params": int(p.size), "starts": args.starts + 1, "starts_run": n_run,
        "distinct_minima": ms.get("distinct_minima"),
        "realizations": args.realizations, "cores": os.cpu_count(), "load_avg": os.getloadavg(),
        "malloc_kept_large_blocks": malloc_tuned, "timings_s": T, "paper_s": PAPER, "peak_memory_gb": mem,
        "truth_generation_s": t_truth, "campaign_wall_s": wall, "campaign_main_cpu_s": cpu_main,
        "campaign_workers_cpu_s": cpu_workers, "campaign_main_system_s": sys_main,
        "campaign_main_fresh_pages_gb": faults_gb,
        "surrogate": res["surrogate"], "cycles": [{k: v for k, v in c.items() if k != "p"} for c in cyc],
        "basis_checks": [{k: v for k, v in b.items() if k not in ("eta", "freqs_hz")} for b in
                         [c["basis_check"] for c in cyc if "basis_check" in c] + list(ref.get("basis_checks", []))],
        "refinement_stages": [{k: v for k, v in s.items() if k != "p"} for s in ref.get("stages", [])],
        "identification_log": [x for x in lines if "identified" in x],
        "accuracy": {
            "sd_holdout": sd_hold, "sd_holdout_truth_damping": sd_hold_truth_damping, "floor_holdout": floor_hold,
            "sd_holdout_truth_damping_split": split,
            "sd_raw_calibration": m["sd_raw_calibration"], "floor_calibration": floor_cal,
            "sd_equalized": m["sd_calibration"], "n_identifiable": int(ident.sum()),
            "max_error_identifiable": float(err[ident].max()) if ident.any() else None,
            "errors": {row["name"]: float(e) for row, e in zip(m["parameters"], err)},
            "p": {row["name"]: float(v) for row, v in zip(m["parameters"], p)},
            "p_true": {row["name"]: float(v) for row, v in zip(m["parameters"], p_true)},
            "identifiable": {row["name"]: bool(i) for row, i in zip(m["parameters"], ident)},
            "std_p": {row["name"]: float(v) for row, v in zip(m["parameters"], std)},
            "error_in_std": {row["name"]: float(v) for row, v in zip(m["parameters"], in_std)},
        },
        "model_sd_s": t_model_sd,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
