"""Benchmark: the subframe example at ~200k DOF with the paper's 17 parameters.

Stages: generation of the deck, read + assembly (CORE), parametric model build
(grouping and reducing the terms), 30 modes (CORE's solver), reassembly of
K(p), M(p) at a new p, one exact derivative, write-back of the deck at p, and
the parametric model straight from the deck (read + assemble + build, as a
calibration calls it).
Peak memory is the process's peak resident set size.

    .venv/bin/python benchmarks/bench_parametric.py [--dof 200000] [--modes 30]

Prints a table and writes ``benchmarks/results/parametric.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

TARGETS = {"assembly_s": 5.0, "modes_s": 15.0, "peak_rss_gb": 3.0}


def peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2  # Linux: kB


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dof", type=int, default=200_000)
    ap.add_argument("--modes", type=int, default=30)
    ap.add_argument("--units", default="mm-t-s", choices=["mm-t-s", "si"])
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "parametric.json"))
    args = ap.parse_args(argv)

    import femodel

    rows = []

    cpu = {}

    def stage(name, fn):
        t = time.perf_counter()
        c = time.process_time()  # CPU time: less sensitive than wall time to other jobs on the machine
        out = fn()
        dt = time.perf_counter() - t
        cpu[name] = time.process_time() - c
        rows.append((name, dt, peak_rss_gb()))
        print(f"  {name:<34s} {dt:8.2f} s  cpu {cpu[name]:7.2f} s   peak RSS {rows[-1][2]:.2f} GB", flush=True)
        return out

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        ex = stage("generate deck", lambda: femodel.example_subframe(tmp, args.dof, units=args.units))
        fe = stage("read deck (read_bdf)", lambda: femodel.read_bdf(ex.bdf, units=args.units))
        asm = stage("assemble (K, M terms + T)", lambda: femodel.assemble(fe))
        _ = stage("reduce nominal K, M to a-set", lambda: (asm.stiffness(), asm.mass()))
        pm = stage("parametric model (group + reduce)", lambda: femodel.parametric_model(ex.params, assembly=asm))
        modes = stage(f"{args.modes} modes (solve_modes)", lambda: femodel.solve_modes(asm, args.modes))
        p = np.linspace(-0.1, 0.1, pm.n_params)
        K = stage("reassemble K(p), M(p)", lambda: (pm.stiffness(p), pm.mass(p)))[0]
        stage("dK/dp_j (one parameter)", lambda: pm.dK(p, 4))
        stage("write-back deck at p", lambda: pm.write_bdf(tmp / "at_p.bdf", p))
        # what a calibration calls: deck -> parametric model (read, assemble and build; two threads)
        stage("parametric model from the deck", lambda: femodel.parametric_model(ex.params))
        n_a = K.shape[0]
        f = modes.frequencies_hz
        f_el = f[modes.n_rigid:]
        n_below = int(np.sum(f_el < 800.0))

    t = {name: dt for name, dt, _ in rows}
    assembly_s = t["read deck (read_bdf)"] + t["assemble (K, M terms + T)"] + t["reduce nominal K, M to a-set"]
    modes_s = t[f"{args.modes} modes (solve_modes)"]
    reassembly_s = t["reassemble K(p), M(p)"]
    peak = max(r[2] for r in rows)
    summary = {
        "model": {"target_dof": args.dof, "grid_dof": ex.n_dof, "a_set_dof": int(n_a), "elements": ex.n_elements,
                  "mass_kg": ex.mass_kg, "units": args.units, "parameters": pm.n_params,
                  "K_terms": len(pm.K.matrices), "M_terms": len(pm.M.matrices), "nnz_K": int(K.nnz),
                  "series_terms": int(np.sum(getattr(pm.K, "series_ratio", np.zeros(1)) > 0)),
                  "series_error_bound": pm.series_error_bound},
        "stages_s": {name: dt for name, dt, _ in rows},
        "stages_cpu_s": cpu,
        "assembly_cpu_s": cpu["read deck (read_bdf)"] + cpu["assemble (K, M terms + T)"] + cpu["reduce nominal K, M to a-set"],
        "parametric_build_s": t["parametric model (group + reduce)"],
        "parametric_build_cpu_s": cpu["parametric model (group + reduce)"],
        "parametric_from_deck_s": t["parametric model from the deck"],
        "parametric_from_deck_cpu_s": cpu["parametric model from the deck"],
        "load_average": os.getloadavg()[0],
        "assembly_timings_s": {k: float(v) for k, v in asm.timings.items()},
        "assembly_s": assembly_s,
        "modes_s": modes_s,
        "modes_solver": modes.solver,
        "reassembly_s": reassembly_s,
        "reassembly_over_assembly": reassembly_s / assembly_s,
        "peak_rss_gb": peak,
        "n_rigid": int(modes.n_rigid),
        "elastic_modes_below_800_hz": n_below,
        "frequencies_hz": [float(x) for x in f],
        "targets": TARGETS,
        "meets": {"assembly_s": assembly_s <= TARGETS["assembly_s"], "modes_s": modes_s <= TARGETS["modes_s"],
                  "peak_rss_gb": peak <= TARGETS["peak_rss_gb"]},
        "machine": {"python": sys.version.split()[0], "platform": platform.platform()},
    }
    print()
    print(f"subframe: {ex.n_dof} grid DOF, {n_a} a-set DOF, {ex.n_elements} CQUAD4, {ex.mass_kg:.2f} kg, "
          f"{pm.n_params} parameters ({len(pm.K.matrices)} K terms, {len(pm.M.matrices)} M terms)")
    print(f"{'figure':<32s} {'measured':>10s} {'target':>10s}")
    print(f"{'assembly (read+assemble+T), s':<32s} {assembly_s:10.2f} {TARGETS['assembly_s']:10.1f}")
    print(f"{'  (CPU time), s':<32s} {summary['assembly_cpu_s']:10.2f}")
    print(f"{'parametric model build, s':<32s} {summary['parametric_build_s']:10.2f}  (cpu {summary['parametric_build_cpu_s']:.2f})")
    print(f"{'parametric model from the deck, s':<32s} {summary['parametric_from_deck_s']:10.2f}  "
          f"(cpu {summary['parametric_from_deck_cpu_s']:.2f})")
    print(f"{f'{args.modes} modes, s':<32s} {modes_s:10.2f} {TARGETS['modes_s']:10.1f}")
    print(f"{'reassembly at new p, s':<32s} {reassembly_s:10.3f} {'':>10s}")
    print(f"{'peak RSS, GB':<32s} {peak:10.2f} {TARGETS['peak_rss_gb']:10.1f}")
    print(f"elastic modes below 800 Hz: {n_below}; first elastic: {np.round(f_el[:5], 1).tolist()} Hz")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(summary, indent=2))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
