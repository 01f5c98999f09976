"""Benchmark: identification speed/memory and a side-by-side with sdypy-EMA on real data.

Run: ``.venv/bin/python benchmarks/bench_identification.py`` (from the repo root).
Prints tables and writes ``benchmarks/results/identification.json``.

1. Synthetic 20 outputs x 2 inputs, 2,000 lines, accelerance, orders 44 and 90:
   wall time (best of 3) and peak traced memory of :func:`identification.identify`.
2. Real data from ../shared/reference/measured (skipped if absent): our
   identification vs sdypy-EMA 0.31 LSCF (optional benchmark dependency,
   ``pip install sdypy-EMA``; its columns are left empty if it is absent).
"""

from __future__ import annotations

import json
import platform
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from identification import identify  # noqa: E402
from tests.identification.synthetic import ring  # noqa: E402

MEASURED = REPO.parent / "shared" / "reference" / "measured"


def _timed(fn, repeat=3):
    """Best-of-``repeat`` wall and CPU time [s] and peak traced (numpy) memory [MiB]."""
    best = cpu = np.inf
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        best = min(best, time.perf_counter() - t0)
        cpu = min(cpu, time.process_time() - c0)
    tracemalloc.start()
    fn()
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return out, best, cpu, peak / 2**20


def bench_speed():
    t = ring(n_mass=20, inputs=(0, 3), n_lines=2000)
    rows = []
    for order in (44, 90):
        r, dt, cpu, mem = _timed(lambda: identify(t.freq_hz, t.H, order, band_hz=(100, 550)))
        fm = r.modal.frequency_hz
        ok = fm.size == t.f_n.size
        rows.append(
            {
                "case": "ring 20x2, 2000 lines",
                "order": order,
                "time_s": dt,
                "cpu_s": cpu,
                "peak_mem_mib": mem,
                "physical": int(fm.size),
                "max_f_err_rel": float(np.max(np.abs(fm - t.f_n) / t.f_n)) if ok else None,
                "max_zeta_err_rel": float(np.max(np.abs(r.modal.damping - t.zeta) / t.zeta)) if ok else None,
            }
        )
    return rows


def _sdypy():
    try:
        import sdypy.EMA as EMA  # noqa: N812
    except ImportError:
        return None
    return EMA


def _ema_fit(EMA, H_out_by_f, f, lo, hi, order, form, guesses, window):
    import contextlib
    import io

    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        m = EMA.Model(frf=H_out_by_f, freq=f, lower=lo, upper=hi, pol_order_high=order, frf_form=form)
        m.get_poles("lscf", show_progress=False)
        m.select_closest_poles(guesses, f_window=window)
    return np.asarray(m.nat_freq, float), np.asarray(m.nat_xi, float)


def bench_beam(EMA):
    path = MEASURED / "modelab-beam-hammer" / "frf.npz"
    if not path.exists():
        return []
    d = np.load(path)
    f, H = d["freq_hz"], d["H"]
    guesses = [112.0, 307.0, 596.0, 975.0]
    t0 = time.perf_counter()
    r = identify(f, H.T[:, :, None], 20, band_hz=(65, 1000))
    t_ours = time.perf_counter() - t0
    ours_f, ours_z = r.modal.frequency_hz, r.modal.damping
    ema_f = ema_z = None
    t_ema = None
    if EMA is not None:
        t0 = time.perf_counter()
        ema_f, ema_z = _ema_fit(EMA, H, f, 65, 1000, 40, "accelerance", guesses, 20)
        t_ema = time.perf_counter() - t0
    rows = []
    for k, g in enumerate(guesses):
        i = int(np.argmin(np.abs(ours_f - g))) if ours_f.size else None
        rows.append(
            {
                "data": "free beam 9x1, 47,873 lines",
                "mode": k + 1,
                "ours_f_hz": float(ours_f[i]) if i is not None else None,
                "ours_zeta": float(ours_z[i]) if i is not None else None,
                "ema_f_hz": float(ema_f[k]) if ema_f is not None and k < ema_f.size else None,
                "ema_zeta": float(ema_z[k]) if ema_z is not None and k < ema_z.size else None,
                "ours_time_s": t_ours,
                "ema_time_s": t_ema,
                "ours_settings": "order 20, band 65-1000 Hz",
                "ema_settings": "LSCF pol_order_high=40, select_closest_poles",
            }
        )
    return rows


def bench_brb(EMA):
    path = MEASURED / "brb-stepped-sine" / "frf.npz"
    if not path.exists():
        return []
    d = np.load(path)
    rows = []
    for tag in [f"fc{i}" for i in range(4)] + [f"rc{i}" for i in range(8)]:
        f = d[f"{tag}_freq_hz"]
        H = d[f"{tag}_acc_ms2"] / d[f"{tag}_force_n"] * np.exp(1j * d[f"{tag}_phase_rad"])
        t0 = time.perf_counter()
        r = identify(f, H[:, None, None], 2, quantity="receptance")
        t_ours = time.perf_counter() - t0
        row = {
            "data": f"bolted beam {tag}",
            "mean_force_n": float(np.mean(d[f"{tag}_force_n"])),
            "ours_f_hz": float(r.modal.frequency_hz[0]) if r.modal.n_modes else None,
            "ours_zeta": float(r.modal.damping[0]) if r.modal.n_modes else None,
            "ours_time_s": t_ours,
            "ema_f_hz": None,
            "ema_zeta": None,
            "ema_time_s": None,
        }
        if EMA is not None:
            t0 = time.perf_counter()
            try:
                ef, ez = _ema_fit(EMA, H[None], f, f[0], f[-1], 6, "receptance", [80.3], 50)
                if ef.size and np.isfinite(ef[0]) and ef[0] > 0:  # 0 means select_closest_poles failed
                    row["ema_f_hz"], row["ema_zeta"] = float(ef[0]), float(ez[0])
            except Exception as exc:  # sdypy-EMA fails on some tests (see README): report, don't stop
                row["ema_error"] = f"{type(exc).__name__}: {exc}"
            row["ema_time_s"] = time.perf_counter() - t0
        rows.append(row)
    return rows


def _fmt(v, spec):
    width = int("".join(ch for ch in spec.split(".")[0] if ch.isdigit()) or 0)
    return format(v, spec) if isinstance(v, (int, float)) else "-".rjust(width)


def main() -> int:
    EMA = _sdypy()
    speed = bench_speed()
    print("identify(): synthetic 20 outputs x 2 inputs, 2000 lines, accelerance (best of 3)")
    print(f"{'order':>5} {'wall [s]':>9} {'cpu [s]':>8} {'peak MiB':>9} {'physical':>8} {'max df/f':>9} {'max dz/z':>9}")
    for r in speed:
        print(
            f"{r['order']:>5} {r['time_s']:9.3f} {r['cpu_s']:8.3f} {r['peak_mem_mib']:9.1f} {r['physical']:>8} "
            f"{_fmt(r['max_f_err_rel'], '9.1e')} {_fmt(r['max_zeta_err_rel'], '9.1e')}"
        )
    beam = bench_beam(EMA)
    brb = bench_brb(EMA)
    if EMA is None:
        print("\nsdypy-EMA not installed: its columns are empty (pip install sdypy-EMA)")
    if beam:
        print(f"\nfree beam (ModeLAB), ours {beam[0]['ours_time_s']:.2f} s, sdypy-EMA {_fmt(beam[0]['ema_time_s'], '.2f')} s")
        print(f"{'mode':>4} {'ours f [Hz]':>12} {'EMA f [Hz]':>12} {'ours zeta':>10} {'EMA zeta':>10}")
        for r in beam:
            print(
                f"{r['mode']:>4} {_fmt(r['ours_f_hz'], '12.4f')} {_fmt(r['ema_f_hz'], '12.4f')} "
                f"{_fmt(r['ours_zeta'], '10.3e')} {_fmt(r['ema_zeta'], '10.3e')}"
            )
    if brb:
        print("\nbolted beam (BRB) stepped sine, 41 lines, SISO")
        print(f"{'test':>5} {'force N':>8} {'ours f':>9} {'EMA f':>9} {'ours zeta':>10} {'EMA zeta':>10} {'ours ms':>8} {'EMA ms':>8}")
        for r in brb:
            print(
                f"{r['data'][-3:]:>5} {r['mean_force_n']:8.3f} {_fmt(r['ours_f_hz'], '9.3f')} {_fmt(r['ema_f_hz'], '9.3f')} "
                f"{_fmt(r['ours_zeta'], '10.3e')} {_fmt(r['ema_zeta'], '10.3e')} "
                f"{_fmt(1e3 * r['ours_time_s'], '8.1f')} {_fmt(None if r['ema_time_s'] is None else 1e3 * r['ema_time_s'], '8.1f')}"
            )
        failed = [r["data"][-3:] for r in brb if r.get("ema_error") or (EMA is not None and r["ema_f_hz"] is None)]
        if EMA is not None and failed:
            print(f"  sdypy-EMA LSCF gave no pole for {', '.join(failed)} (error text in the JSON)")
    out = {
        "machine": {"python": platform.python_version(), "platform": platform.platform(), "numpy": np.__version__},
        "sdypy_ema": getattr(EMA, "__version__", None) if EMA is not None else None,
        "speed": speed,
        "free_beam": beam,
        "bolted_beam": brb,
    }
    res = REPO / "benchmarks" / "results"
    res.mkdir(parents=True, exist_ok=True)
    (res / "identification.json").write_text(json.dumps(out, indent=2))
    print(f"\nwrote {res / 'identification.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
