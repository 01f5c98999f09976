"""``frfcal identify RUN.h5 --band LO HI [--order N]``: subspace identification of a run file.

Without ``--order`` the order is chosen from the stabilization diagram
(``identification.select_order``). The work is ``frfcal.campaign.identify_run``,
the same function the campaign uses.
"""

from __future__ import annotations

import argparse

HELP = "identify a state-space model and modes from a run file (frequency-domain subspace, damping equalization)"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", help="HDF5 run file written by 'frfcal acquire' or 'frfcal import-uff'")
    parser.add_argument("--band", nargs=2, type=float, metavar=("LO_HZ", "HI_HZ"), help="analysed band in Hz (default: all lines)")
    parser.add_argument("--order", type=int, help="model order n = number of states (2 per mode); default: automatic, from the stabilization diagram")
    parser.add_argument("--zeta0", type=float, help="also store the damping-equalized model with this damping ratio (e.g. 0.01)")
    parser.add_argument("--plot", metavar="DIR", help="write stabilization.png and fit.png into DIR")
    parser.add_argument("--no-weights", action="store_true", help="ignore the run's per-line standard errors")
    parser.add_argument("--block-rows", type=int, help="block rows q of the subspace data matrices (default: automatic)")
    parser.add_argument("--no-store", action="store_true", help="do not write the result into the run file")
    parser.add_argument("--json", action="store_true", help="print one JSON object (physical poles in Hz and zeta)")
    from frfcal.commands.run import add_campaign_options

    add_campaign_options(parser)  # with a campaign TOML as the first argument


def _stabilization_orders(order: int) -> list[int]:
    lo = max(2, order // 2)
    hi = max(lo + 2, order + 8, (3 * order) // 2)
    step = max(2, 2 * round((hi - lo) / 24))
    return list(range(lo - lo % 2, hi + 1, step))


def run(args: argparse.Namespace) -> int:
    from frfcal.commands.run import campaign_command, is_campaign_file

    if is_campaign_file(args.run):  # the campaign form: run the campaign up to this stage
        args._campaign_path = args.run
        return campaign_command(args, "identify")
    import json
    from pathlib import Path

    import numpy as np

    import identification as idf
    from acquisition.runfile import read_run, write_analysis
    from frfcal.campaign import identify_run
    from frfcal.campaign._identify import identification_weights, refit_line, run_std_error, unexplained_line

    path = Path(args.run)
    run_ = read_run(path)
    band = tuple(args.band) if args.band else None
    mode = None if args.no_weights else "std_error"
    result = identify_run(run_, band, order=args.order, weights=mode, block_rows=args.block_rows)
    sel = result.order_selection
    arrays, attrs = result.to_arrays()
    attrs["run"] = str(path.name)
    attrs["weights"] = result.settings["weights"]
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
        orders = _stabilization_orders(result.order)
        # the stabilization diagram with the weights the identification used
        weights, _ = identification_weights(run_.frequency_hz, run_.frf, run_.valid, run_std_error(run_), mode)
        kw = dict(band_hz=result.band_hz, weights=weights, quantity=run_.quantity, valid=run_.valid,
                  block_rows=args.block_rows)
        stab = idf.stabilization(run_.frequency_hz, run_.frf, orders, **kw)
        plots.append(str(idf.plot_stabilization(stab, out / "stabilization.png", run_.frequency_hz, run_.frf, title=f"{path.name}: stabilization")))
        plots.append(str(idf.plot_fit(result, run_.frequency_hz, run_.frf, out / "fit.png", equalized_model=eq, title=f"{path.name}: order {result.order}")))
    labels = {k: result.poles.count(k) for k in idf.LABELS if result.poles.count(k)}
    m = result.modal
    if args.json:
        obj = {
            "run": str(path),
            "quantity": result.quantity,
            "band_hz": list(result.band_hz),
            "requested_band_hz": list(band) if band else None,
            "band_clipped": bool(result.settings["band_clipped"]),
            "order": result.order,
            "order_mode": "automatic" if sel is not None else "set",
            "order_reason": sel.reason if sel is not None else f"order {result.order} set with --order",
            "order_selection": sel.to_dict() if sel is not None else None,
            "weights": result.settings["weights"],
            "physical_poles": [
                {"frequency_hz": float(f), "damping": float(z)} for f, z in zip(m.frequency_hz, m.damping)
            ],
            "labels": labels,
            "fit_deviation": result.fit_deviation_total,
            "n_states": int(result.model.A.shape[0]),
            "modal_refit": result.settings.get("modal_refit"),
            # where the model leaves > 10 sigma away from its modes (null: the weights are not the noise)
            "unexplained_residual": result.settings.get("unexplained"),
            "zeta0": args.zeta0,
            "stored": stored,
            "plots": plots,
        }
        print(json.dumps(obj))
        return 0
    clipped = f" (requested {band[0]:g}-{band[1]:g} Hz, clipped to the data)" if result.settings["band_clipped"] else ""
    print(f"{path.name}: {result.quantity}, {result.settings['n_lines']} lines in {result.band_hz[0]:g}-{result.band_hz[1]:g} Hz{clipped}, order {result.order}")
    if sel is not None:
        print(f"order chosen automatically: {sel.reason}")
    print("poles: " + ", ".join(f"{v} {k}" for k, v in labels.items()))
    print(refit_line(result))
    unexplained = unexplained_line(result)
    if unexplained:
        print(unexplained)
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
