"""``frfcal import-uff FILE.uff --out RUN.h5``: UFF58 FRFs into a run file.

Responses and references are identified by each record's node and direction
(a MIMO file of n_out x n_in records becomes an n_out x n_in run); ambiguous
files are refused (see docs/runfile.md, "UFF58").
"""

from __future__ import annotations

from pathlib import Path

import argparse

HELP = "convert UFF58 frequency response functions into an HDF5 run file"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("uff", help="universal file with UFF58 FRF records")
    parser.add_argument("--out", required=True, help="run file to write (.h5)")
    parser.add_argument("--article", help="test article name (default: from the file)")
    parser.add_argument("--force", action="store_true", help="overwrite an existing run file")
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def uff_to_run(uff, out, *, article=None, overwrite=False) -> dict:
    """Import a UFF58 file into the run file ``out`` (parent created); what was written, as a dict.

    The code of ``frfcal import-uff`` and of the campaign's import stage.
    """
    from acquisition._uff import import_uff

    Path(out).parent.mkdir(parents=True, exist_ok=True)  # like every other --out of frfcal
    r = import_uff(uff, out, article=article, overwrite=overwrite)
    return {"path": str(out), "article": r.article, "quantity": r.quantity, "n_lines": r.n_lines,
            "sensors": [c.name for c in r.sensors], "drives": [c.name for c in r.drives],
            "sensor_grids": [c.grid for c in r.sensors], "drive_grids": [c.grid for c in r.drives],
            "band_hz": [float(r.frequency_hz.min()), float(r.frequency_hz.max())],
            "dropped_hz": list(r.plan.get("dropped_hz", [])),
            "abscissa_spread": r.plan.get("abscissa_spread"),
            "skipped_records": {k: list(v) for k, v in r.plan.get("skipped_records", {}).items()}}


def spread_note(spread: dict) -> str:
    """What the import did to lines an ASCII abscissa printed the same (``plan["abscissa_spread"]``)."""
    return (f"{spread['lines']} lines in {spread['groups']} group(s) printed at the same frequency (an ASCII UFF58 "
            f"keeps 6 significant digits): spread within their last digit in file order, shifts up to "
            f"{spread['max_shift_hz']:.2g} Hz")


def run(args) -> int:
    import json

    if Path(args.out).exists() and not args.force:
        raise FileExistsError(f"{args.out}: the run file exists; pass --force to overwrite it")
    full = uff_to_run(args.uff, args.out, article=args.article, overwrite=args.force)
    info = {k: v for k, v in full.items() if k != "band_hz"}
    info["path"] = args.out
    if args.json:
        print(json.dumps(info))
    else:
        lo, hi = full["band_hz"]
        print(f"{args.out}: {info['n_lines']} lines {lo:.3f}-{hi:.3f} Hz, "
              f"{len(info['sensors'])} x {len(info['drives'])} {info['quantity']}, article {info['article']!r}")
        for what, ns in info["skipped_records"].items():
            print(f"left out {len(ns)} record(s) of {what}: not FRFs (records {', '.join(map(str, ns[:6]))}"
                  f"{', ...' if len(ns) > 6 else ''})")
        if info["dropped_hz"]:
            print(f"left out {len(info['dropped_hz'])} line(s) at 0 Hz (the analyzer's DC line: no FRF line)")
        if info["abscissa_spread"]:
            print(spread_note(info["abscissa_spread"]))
        print("references: " + ", ".join(info["drives"]))
        # the names to put in a campaign's [channels] (they come from the records' node, direction and entity)
        print("responses: " + ", ".join(info["sensors"]))
    return 0
