"""femodel benchmark: read, assembly, 30 modes and peak memory on the largest model at hand.

Each case runs in a fresh subprocess so that its peak RSS (ru_maxrss) is its own.

    .venv/bin/python benchmarks/bench_femodel.py [--dof 200000] [--modes 30] [--deck PATH --units U]

Default cases: the example subframe at --dof (generated into a temp dir) and,
when ../shared is present, the bwb (51k independent DOF) and femap_exhaust
(27k DOF) reference decks.
Prints a table and writes benchmarks/results/femodel.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent

_CHILD = r"""
import json, resource, sys, time
t0 = time.perf_counter()
import femodel
path, units, n_modes, solver, allow = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4], sys.argv[5] == "1"
t1 = time.perf_counter()
c1 = time.process_time()
model = femodel.read_bdf(path, units=units, allow_unsupported=allow)
t2 = time.perf_counter(); c2 = time.process_time()
asm = femodel.assemble(model)
K = asm.stiffness(); M = asm.mass()
t3 = time.perf_counter(); c3 = time.process_time()
rss_asm = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
modes = femodel.normal_modes(K, M, n_modes, solver=solver, n_threads=2)
t4 = time.perf_counter(); c4 = time.process_time()
print(json.dumps({
    "read_cpu_s": c2 - c1, "assembly_cpu_s": c3 - c2, "modes_cpu_s": c4 - c3,
    "n_grids": model.n_grids, "n_gset": len(asm.gset), "n_dof": int(K.shape[0]),
    "nnz_K": int(K.nnz), "n_terms": len(asm.terms),
    "read_s": t2 - t1, "assembly_s": t3 - t2, "assembly_detail_s": asm.timings,
    "modes_s": t4 - t3, "factor_s": modes.factor_time_s, "lanczos_s": modes.solve_time_s,
    "solver": modes.solver, "n_modes": modes.n_modes, "n_rigid": modes.n_rigid,
    "f_first_elastic_hz": float(modes.frequencies_hz[modes.n_rigid]) if modes.n_rigid < modes.n_modes else None,
    "f_last_hz": float(modes.frequencies_hz[-1]),
    "peak_rss_after_assembly_mb": rss_asm,
    "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
}))
"""


def run_case(name, path, units, n_modes, solver, allow=False):
    env = dict(os.environ, OMP_NUM_THREADS="2", OPENBLAS_NUM_THREADS="2", MKL_NUM_THREADS="2")
    proc = subprocess.run(
        [sys.executable, "-c", _CHILD, str(path), units, str(n_modes), solver, "1" if allow else "0"],
        capture_output=True, text=True, env=env, cwd=REPO,
    )
    if proc.returncode != 0:
        return {"case": name, "error": proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else "failed"}
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    out.update(case=name, path=str(path), units=units)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dof", type=int, default=200000, help="target DOF of the example subframe (0: skip)")
    ap.add_argument("--modes", type=int, default=30)
    ap.add_argument("--solver", default="auto", choices=["auto", "cholmod", "cholespy", "pardiso", "superlu"])
    ap.add_argument("--deck", help="an extra deck to benchmark")
    ap.add_argument("--units", default="si")
    ap.add_argument("--out", default=str(HERE / "results" / "femodel.json"))
    args = ap.parse_args(argv)

    cases = []
    with tempfile.TemporaryDirectory() as tmp:
        if args.dof:
            sys.path.insert(0, str(REPO))
            from femodel._example import example_subframe

            ex = example_subframe(tmp, target_dof=args.dof, units="mm-t-s")
            cases.append(run_case(f"example subframe {ex.n_dof} DOF", ex.bdf, "mm-t-s", args.modes, args.solver))
        nas = REPO.parent / "shared" / "reference" / "nastran"
        for name, rel in (("bwb (reference)", "bwb/bwb_freq.bdf"), ("femap_exhaust (reference)", "femap_exhaust/modal_example_from_op2.bdf")):
            if (nas / rel).is_file():
                cases.append(run_case(name, nas / rel, "in-lbf-s", args.modes, args.solver))
        if args.deck:
            cases.append(run_case(Path(args.deck).name, args.deck, args.units, args.modes, args.solver))

    load = os.getloadavg()[0]
    print(f"load average at start: {load:.1f} on {os.cpu_count()} cores (wall times scale with it; CPU times less so)")
    hdr = (f"{'case':34} {'DOF':>7} {'read s':>7} {'asm s':>6} {'asm cpu':>7} {'modes s':>7} "
           f"{'mod cpu':>7} {'factor':>6} {'peakMB':>6}  solver")
    print(hdr)
    print("-" * len(hdr))
    for c in cases:
        if "error" in c:
            print(f"{c['case']:34} error: {c['error']}")
            continue
        print(
            f"{c['case']:34} {c['n_dof']:7d} {c['read_s']:7.2f} {c['assembly_s']:6.2f} {c['assembly_cpu_s']:7.2f} "
            f"{c['modes_s']:7.2f} {c['modes_cpu_s']:7.2f} {c['factor_s']:6.2f} {c['peak_rss_mb']:6.0f}  {c['solver']}"
        )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"modes": args.modes, "threads": 2, "load_average": load, "cases": cases}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
