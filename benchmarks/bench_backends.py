"""Sparse backend benchmark: one factorization, 30 modes and (optionally) one calibration per backend.

Each backend runs in a fresh subprocess with ``FRFCAL_SPARSE_BACKEND`` set, so
its peak RSS (ru_maxrss) and CPU time are its own.  Only the backends importable
by this interpreter run; run the script once per environment to cover them all
(rows of other backends already in the results file are kept).

    python benchmarks/bench_backends.py [--dof 200000] [--modes 30] [--calibration] [--backends a,b]

K and M are the example subframe at --dof (mm-t-s), assembled once by the parent.
Factorization: K + (2 pi 1 Hz)^2 M, as ``normal_modes`` factorizes at its default
shift.  Calibration: ``benchmarks/bench_calibration.py --realizations 1`` in the
same environment, its "calibration total" (parametric model + basis + LM starts
+ re-basis cycles) and main-process CPU.
Prints a table and writes benchmarks/results/backends.json.
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
import numpy as np, scipy.sparse as sp
import femodel
folder, n_modes = sys.argv[1], int(sys.argv[2])
K = sp.load_npz(folder + "/K.npz").tocsc(); M = sp.load_npz(folder + "/M.npz").tocsc()
rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
A = (K + (2 * np.pi) ** 2 * M).tocsc()
t0 = time.perf_counter(); c0 = time.process_time()
fac = femodel.factorize(A)
t1 = time.perf_counter(); c1 = time.process_time()
b = np.random.default_rng(0).standard_normal(A.shape[0])
x = fac(b)
resid = float(np.linalg.norm(A @ x - b) / np.linalg.norm(b))
t2 = time.perf_counter(); c2 = time.process_time()
for _ in range(10):
    fac(b)
t3 = time.perf_counter(); c3 = time.process_time()
rss_fac = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
del fac, A
t4 = time.perf_counter(); c4 = time.process_time()
modes = femodel.normal_modes(K, M, n_modes, n_threads=2)
t5 = time.perf_counter(); c5 = time.process_time()
print(json.dumps({
    "backend": femodel.default_backend(), "n_dof": int(K.shape[0]), "nnz_K": int(K.nnz),
    "factor_s": t1 - t0, "factor_cpu_s": c1 - c0, "solve_s": (t3 - t2) / 10, "solve_cpu_s": (c3 - c2) / 10,
    "residual": resid, "modes_s": t5 - t4, "modes_cpu_s": c5 - c4, "modes_factor_s": modes.factor_time_s,
    "lanczos_s": modes.solve_time_s, "solver": modes.solver,
    "frequencies_hz": modes.frequencies_hz.tolist(),
    "rss_after_load_mb": rss0, "peak_rss_factor_mb": rss_fac,
    "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
}))
"""


def _env(backend: str) -> dict:
    return dict(os.environ, PYTHONPATH=str(REPO), FRFCAL_SPARSE_BACKEND=backend, OMP_NUM_THREADS="2",
                OPENBLAS_NUM_THREADS="2", MKL_NUM_THREADS="2")


def run_backend(backend: str, folder: str, n_modes: int) -> dict:
    proc = subprocess.run([sys.executable, "-c", _CHILD, folder, str(n_modes)], capture_output=True, text=True,
                          env=_env(backend), cwd=REPO)
    if proc.returncode != 0:
        lines = proc.stderr.strip().splitlines()
        return {"backend": backend, "error": lines[-1] if lines else "failed"}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def run_calibration(backend: str, dof: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "cal.json"
        proc = subprocess.run([sys.executable, str(HERE / "bench_calibration.py"), "--dof", str(dof),
                               "--realizations", "1", "--out", str(out)],
                              capture_output=True, text=True, env=_env(backend), cwd=REPO)
        if proc.returncode != 0 or not out.is_file():
            lines = proc.stderr.strip().splitlines()
            return {"calibration_error": lines[-1] if lines else "failed"}
        res = json.loads(out.read_text())
    return {"calibration_total_s": res["timings_s"]["calibration total"],
            "calibration_cpu_s": res["campaign_main_cpu_s"],
            "calibration_basis_s": res["timings_s"]["basis + reduced terms"],
            "calibration_rebasis_s": res["timings_s"]["re-basis cycles"],
            "calibration_max_param_error": res["accuracy"]["max_error_identifiable"],
            "calibration_peak_memory_gb": res["peak_memory_gb"]}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dof", type=int, default=200000, help="target DOF of the example subframe")
    ap.add_argument("--modes", type=int, default=30)
    ap.add_argument("--backends", default="", help="comma-separated subset (default: every available one)")
    ap.add_argument("--calibration", action="store_true", help="also time one calibration per backend")
    ap.add_argument("--out", default=str(HERE / "results" / "backends.json"))
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    import scipy.sparse as sp

    import femodel

    names = [b.name for b in femodel.available_backends() if b.available]
    if args.backends:
        names = [n for n in args.backends.split(",") if n in names]
    load = os.getloadavg()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        ex = femodel.example_subframe(tmp, target_dof=args.dof, units="mm-t-s")
        asm = femodel.assemble(femodel.read_bdf(ex.bdf, units="mm-t-s"))
        sp.save_npz(f"{tmp}/K.npz", sp.csc_matrix(asm.stiffness()))
        sp.save_npz(f"{tmp}/M.npz", sp.csc_matrix(asm.mass()))
        del asm
        for name in names:
            row = run_backend(name, tmp, args.modes)
            if args.calibration and "error" not in row:
                row.update(run_calibration(name, args.dof))
            row["python"] = sys.executable
            row["load_average_after"] = os.getloadavg()
            rows.append(row)
            print(f"{name}: done", flush=True)
    out = Path(args.out)
    old = json.loads(out.read_text()).get("rows", []) if out.is_file() else []
    ran = {r["backend"] for r in rows}
    rows = [r for r in old if r["backend"] not in ran] + rows
    ref = next((r for r in rows if r["backend"] == "superlu" and "frequencies_hz" in r), None)
    print(f"load average at start: {load[0]:.1f} {load[1]:.1f} {load[2]:.1f} on {os.cpu_count()} cores "
          "(wall times scale with it; CPU times less so)")
    hdr = (f"{'backend':9} {'factor s':>8} {'cpu':>6} {'solve ms':>8} {'30 modes s':>10} {'cpu':>6} "
           f"{'peak MB':>7} {'calib s':>7} {'cpu':>6} {'max df/f vs superlu':>19}")
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        if "error" in r:
            print(f"{r['backend']:9} error: {r['error']}")
            continue
        pairs = [] if ref is None else list(zip(r["frequencies_hz"][6:], ref["frequencies_hz"][6:]))
        df = f"{max(abs(a / b - 1) for a, b in pairs):.1e}" if pairs else ""
        cal = (f"{r['calibration_total_s']:7.1f} {r['calibration_cpu_s']:6.1f}" if "calibration_total_s" in r
               else f"{'-':>7} {'-':>6}")
        print(f"{r['backend']:9} {r['factor_s']:8.2f} {r['factor_cpu_s']:6.2f} {1e3 * r['solve_s']:8.1f} "
              f"{r['modes_s']:10.2f} {r['modes_cpu_s']:6.2f} {r['peak_rss_mb']:7.0f} {cal} {df:>19}")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"dof": args.dof, "modes": args.modes, "threads": 2, "load_average": load,
                               "rows": rows}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
