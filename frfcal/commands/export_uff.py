"""``frfcal export-uff RUN.h5 --out FILE.uff``: a run file's FRFs as UFF58."""

from __future__ import annotations

import argparse

HELP = "write the FRFs of an HDF5 run file as UFF58 (binary 58b by default, exact)"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", help="run file (.h5)")
    parser.add_argument("--out", required=True, help="universal file to write (.uff)")
    parser.add_argument("--ascii", action="store_true", help="ASCII UFF58 (frequencies to 6 digits) instead of 58b")
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def run(args) -> int:
    import json

    from acquisition._uff import export_uff

    n = export_uff(args.run, args.out, binary=not args.ascii)
    if args.json:
        print(json.dumps({"path": args.out, "records": n, "binary": not args.ascii}))
    else:
        print(f"{args.out}: {n} UFF58{'' if args.ascii else 'b'} records")
    return 0
