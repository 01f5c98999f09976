"""``frfcal identify RUN.h5 --band LO HI --order N``: subspace identification of a run file."""

from __future__ import annotations

import argparse

HELP = "identify a state-space model and modes from a run file (frequency-domain subspace, damping equalization)"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", help="HDF5 run file written by 'frfcal acquire' or 'frfcal import-uff'")
    parser.add_argument("--band", nargs=2, type=float, metavar=("LO_HZ", "HI_HZ"), help="analysed band in Hz (default: all lines)")
    parser.add_argument("--order", type=int, required=True, help="model order n = number of states (2 per mode)")
    parser.add_argument("--zeta0", type=float, help="also store the damping-equalized model with this damping ratio (e.g. 0.01)")
    parser.add_argument("--plot", metavar="DIR", help="write stabilization.png and fit.png into DIR")
    parser.add_argument("--no-weights", action="store_true", help="ignore the run's per-line standard errors")
    parser.add_argument("--block-rows", type=int, help="block rows q of the subspace data matrices (default: automatic)")
    parser.add_argument("--no-store", action="store_true", help="do not write the result into the run file")
    parser.add_argument("--json", action="store_true", help="print one JSON object (physical poles in Hz and zeta)")


def _weights(run):
    import numpy as np

    se = np.asarray(run.std_error, dtype=float)
    v = run.valid
    if se.shape != run.frf.shape or not v.any():
        return None
    sev = se[v]
    if np.all(np.isfinite(sev)) and np.all(sev > 0):
        return np.where(np.isfinite(se) & (se > 0), se, 1.0)
    return None


def _stabilization_orders(order: int) -> list[int]:
    lo = max(2, order // 2)
    hi = max(lo + 2, order + 8, (3 * order) // 2)
    step = max(2, 2 * round((hi - lo) / 24))
    return list(range(lo - lo % 2, hi + 1, step))


def run(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    import numpy as np

    import identification as idf
    from acquisition.runfile import read_run, write_analysis

    path = Path(args.run)
    run_ = read_run(path)
    weights = None if args.no_weights else _weights(run_)
    kw = dict(
        band_hz=tuple(args.band) if args.band else None,
        weights=weights,
        quantity=run_.quantity,
        valid=run_.valid,
        block_rows=args.block_rows,
    )
    result = idf.identify(run_.frequency_hz, run_.frf, args.order, **kw)
    arrays, attrs = result.to_arrays()
    attrs["run"] = str(path.name)
    attrs["weights"] = "std_error" if weights is not None else "output_rms"
    eq = None
    if args.zeta0 is not None:
        eq = idf.equalized(result, args.zeta0)
        arrays.update({f"equalized_{k}": getattr(eq, k) for k in "ABCD"})
        attrs["equalized_zeta0"] = float(args.zeta0)
    stored = None
    if not args.no_store:
        write_analysis(path, "identification", arrays, attrs)
        stored = "analysis/identification"
    plots = []
    if args.plot:
        out = Path(args.plot)
        out.mkdir(parents=True, exist_ok=True)
        orders = _stabilization_orders(args.order)
        stab = idf.stabilization(run_.frequency_hz, run_.frf, orders, **kw)
        plots.append(str(idf.plot_stabilization(stab, out / "stabilization.png", run_.frequency_hz, run_.frf, title=f"{path.name}: stabilization")))
        plots.append(str(idf.plot_fit(result, run_.frequency_hz, run_.frf, out / "fit.png", equalized_model=eq, title=f"{path.name}: order {args.order}")))
    labels = {k: result.poles.count(k) for k in idf.LABELS if result.poles.count(k)}
    m = result.modal
    if args.json:
        obj = {
            "run": str(path),
            "quantity": result.quantity,
            "band_hz": list(result.band_hz),
            "order": result.order,
            "physical_poles": [
                {"frequency_hz": float(f), "damping": float(z)} for f, z in zip(m.frequency_hz, m.damping)
            ],
            "labels": labels,
            "fit_deviation": result.fit_deviation_total,
            "zeta0": args.zeta0,
            "stored": stored,
            "plots": plots,
        }
        print(json.dumps(obj))
        return 0
    print(f"{path.name}: {result.quantity}, {result.settings['n_lines']} lines in {result.band_hz[0]:g}-{result.band_hz[1]:g} Hz, order {result.order}")
    print("poles: " + ", ".join(f"{v} {k}" for k, v in labels.items()))
    print(f"{'mode':>4} {'f_n [Hz]':>11} {'zeta [%]':>9} {'importance':>11}")
    phys = np.flatnonzero(result.poles.physical)
    for i, (f, z, k) in enumerate(zip(m.frequency_hz, m.damping, phys), start=1):
        print(f"{i:>4} {f:11.4f} {100 * z:9.4f} {result.poles.importance[k]:11.3g}")
    print(f"fit: square deviation of log10 ratio {result.fit_deviation_total:.3g}")
    if eq is not None:
        print(f"equalized model: every physical pole at zeta0 = {args.zeta0:g}")
    if stored:
        print(f"stored in {path}:/{stored}")
    for p in plots:
        print(f"wrote {p}")
    return 0
