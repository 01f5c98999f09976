"""Pretest benchmark: greedy EfI vs brute force, EfI speed vs candidate count, layouts on real models.

Run: ``.venv/bin/python benchmarks/bench_pretest.py [--quick]``.  Prints tables and
writes ``benchmarks/results/pretest.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from math import comb
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import pretest  # noqa: E402
from tests.pretest._problems import plate_modes  # noqa: E402


def brute_force_table(seeds: int) -> list[dict]:
    """Greedy EfI against the det(FIM) optimum over every subset."""
    cases = [
        ("plate 4x3, 3 modes", dict(nx=4, ny=3, n_modes=3), 4, None),
        ("plate 5x4, 4 modes", dict(nx=5, ny=4, n_modes=4), 6, None),
        ("plate 6x4, 6 modes", dict(nx=6, ny=4, n_modes=6), 8, None),
        ("plate 6x4, 5 modes", dict(nx=6, ny=4, n_modes=5), 10, None),
        ("random 20x6", None, 8, None),
        ("triax plate 4x4, 8 modes", dict(nx=4, ny=4, n_modes=8), 4, "triax"),
    ]
    rows = []
    for name, kw, n_keep, kind in cases:
        ratios, ranks, hits = [], [], 0
        n_sub = 0
        for seed in range(seeds):
            rng = np.random.default_rng(seed)
            if kw is None:
                phi = rng.standard_normal((20, 6))
                groups = None
            elif kind == "triax":
                base, _, _ = plate_modes(noise=0.05, seed=seed, **kw)
                phi = np.vstack([base, 0.5 * rng.standard_normal(base.shape), 0.3 * rng.standard_normal(base.shape)])
                groups = np.tile(np.arange(base.shape[0]), 3)
            else:
                phi, _, _ = plate_modes(noise=0.05, seed=seed, **kw)
                groups = None
            res = pretest.effective_independence(phi, n_keep, group_labels=groups)
            best, best_ld, all_ld = pretest.exhaustive_best_subset(phi, n_keep, group_labels=groups)
            n_sub = all_ld.size
            ratios.append(float(np.exp(res.logdet_fim - best_ld)))
            ranks.append(float(np.mean(all_ld > res.logdet_fim + 1e-12)))
            hits += int(res.logdet_fim >= best_ld - 1e-9)
        n_cand = phi.shape[0] if groups is None else np.unique(groups).size
        rows.append(
            dict(
                case=name, n_candidates=int(n_cand), n_sensors=n_keep, n_modes=int(phi.shape[1]), subsets=int(n_sub),
                trials=seeds, optimum_found=hits, det_ratio_min=min(ratios), det_ratio_median=float(np.median(ratios)),
                better_subsets_fraction_max=max(ranks),
            )
        )
    return rows


def speed_table(sizes) -> list[dict]:
    out = []
    for nx, ny, triax in sizes:
        phi, _, _ = plate_modes(nx=nx, ny=ny, n_modes=20, noise=1e-3)
        groups = None
        if triax:
            rng = np.random.default_rng(0)
            phi = np.vstack([phi, 0.3 * rng.standard_normal(phi.shape) * 1e-2 + 0.2 * phi, 0.1 * np.roll(phi, 3, 0)])
            groups = np.tile(np.arange(nx * ny), 3)
        t = time.perf_counter()
        res = pretest.effective_independence(phi, 20, group_labels=groups)
        dt = time.perf_counter() - t
        out.append(dict(candidates=int(nx * ny), rows=int(phi.shape[0]), triax=bool(triax), n_modes=20, n_sensors=20,
                        seconds=dt, log10_det=res.logdet_fim / np.log(10)))
    return out


def model_layouts(quick: bool) -> list[dict]:
    import femodel

    out = []
    tmp = Path(tempfile.mkdtemp(prefix="bench_pretest_"))
    models = []
    ex = femodel.example_subframe(tmp, target_dof=5000, units="mm-t-s")
    models.append(("subframe 5k DOF (example)", ex.bdf, "mm-t-s"))
    exhaust = ROOT.parent / "shared" / "reference" / "nastran" / "femap_exhaust" / "modal_example_from_op2.bdf"
    if exhaust.exists() and not quick:
        models.append(("femap_exhaust (NX shell deck)", exhaust, "in-lbf-s"))
    for name, path, units in models:
        t0 = time.perf_counter()
        model = femodel.read_bdf(path, units=units)
        asm = femodel.assemble(model)
        target = pretest.compute_target_modes(asm, n_modes=20)
        t1 = time.perf_counter()
        for triax in (False, True):
            cfg = pretest.PretestConfig(n_sensors=20 if not triax else 10, n_modes=20, triax=triax)
            t = time.perf_counter()
            res = pretest.plan_pretest(model, cfg, assembly=asm, target=target)
            dt = time.perf_counter() - t
            cands = res.candidates
            phi = np.asarray(femodel.sensor_matrix(asm, cands.grids, cands.directions) @ target.shapes)
            rng = np.random.default_rng(0)
            n_rows = res.sensors.n_rows
            rand = []
            labels = np.unique(cands.group)
            for _ in range(200):
                pick = rng.choice(labels, n_rows // (3 if triax else 1), replace=False)
                rand.append(pretest.layout_metrics(phi[np.isin(cands.group, pick)]))
            m = res.metrics
            out.append(dict(
                model=name, units=units, grids=int(model.n_grids), candidates=int(labels.size),
                sensors=("%d triax" % cfg.n_sensors) if triax else "%d normal" % cfg.n_sensors, channels=n_rows,
                target_hz=[float(target.frequencies_hz[0]), float(target.frequencies_hz[-1])],
                modes_seconds=t1 - t0, plan_seconds=dt,
                log10_det=m.fim_log10_det, condition=m.fim_condition, automac_max_offdiag=m.automac_max_offdiag,
                automac_worst_modes=[int(target.indices[i] + 1) for i in m.automac_worst_pair],
                min_independence=float(m.mode_independence.min()),
                random_median_condition=float(np.median([r.fim_condition for r in rand])),
                random_median_automac=float(np.median([r.automac_max_offdiag for r in rand])),
                random_best_log10_det=float(np.max([r.fim_log10_det for r in rand])),
                drive_grid=int(res.drives.grids[0]), drive_weakest=float(res.drive_ranking.weakest[res.drive_ranking.order[0]]),
                max_mass_shift_percent=float(-100 * res.mass_loading.relative_shift.min()),
            ))
    return out


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="fewer seeds and sizes")
    args = ap.parse_args()
    results = {"machine": {"cpus": os.cpu_count(), "load_avg": os.getloadavg()}}
    seeds = 3 if args.quick else 10
    print("Greedy EfI vs brute force (det of the Fisher information), %d trials per case" % seeds)
    bf = brute_force_table(seeds)
    print(f"{'case':<26s} {'cand':>4s} {'keep':>4s} {'modes':>5s} {'subsets':>8s} {'optimum':>8s} {'det/opt min':>11s} "
          f"{'median':>7s} {'worse-than frac':>15s}")
    for r in bf:
        print(f"{r['case']:<26s} {r['n_candidates']:4d} {r['n_sensors']:4d} {r['n_modes']:5d} {r['subsets']:8d} "
              f"{r['optimum_found']:3d}/{r['trials']:<4d} {r['det_ratio_min']:11.3f} {r['det_ratio_median']:7.3f} "
              f"{r['better_subsets_fraction_max']:15.2e}")
    results["brute_force"] = bf
    sizes = [(40, 25, False), (100, 50, False)] if args.quick else [(40, 25, False), (100, 50, False), (160, 100, False), (40, 25, True), (100, 50, True)]
    print("\nEfI speed (20 modes, keep 20 groups; load average %.1f on %d cores)" % (os.getloadavg()[0], os.cpu_count()))
    sp = speed_table(sizes)
    print(f"{'candidates':>10s} {'rows':>7s} {'triax':>6s} {'seconds':>8s}")
    for r in sp:
        print(f"{r['candidates']:10d} {r['rows']:7d} {str(r['triax']):>6s} {r['seconds']:8.2f}")
    results["speed"] = sp
    print("\nLayouts for the first 20 elastic modes on FE models (EfI vs 200 random layouts of the same size)")
    ml = model_layouts(args.quick)
    for r in ml:
        print(f"{r['model']}: {r['grids']} grids, {r['candidates']} candidates, {r['sensors']} ({r['channels']} ch), "
              f"targets {r['target_hz'][0]:.1f}-{r['target_hz'][1]:.1f} Hz")
        print(f"   EfI:    cond(FIM) {r['condition']:.4g}, max off-diag autoMAC {r['automac_max_offdiag']:.3f} "
              f"(modes {r['automac_worst_modes']}), log10 det {r['log10_det']:.2f}, min independence {r['min_independence']:.3f}")
        print(f"   random: median cond {r['random_median_condition']:.4g}, median max autoMAC {r['random_median_automac']:.3f}, "
              f"best log10 det {r['random_best_log10_det']:.2f}")
        print(f"   drive grid {r['drive_grid']} (weakest-mode participation {r['drive_weakest']:.3f}); "
              f"largest mass-loading shift {r['max_mass_shift_percent']:.3f} %; modes {r['modes_seconds']:.1f} s, "
              f"plan {r['plan_seconds']:.2f} s")
    results["models"] = ml
    out = ROOT / "benchmarks" / "results" / "pretest.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=1) + "\n")
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
