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


def run(args) -> int:
    import json

    from acquisition._uff import import_uff

    Path(args.out).parent.mkdir(parents=True, exist_ok=True)  # like every other --out of frfcal
    r = import_uff(args.uff, args.out, article=args.article, overwrite=args.force)
    info = {"path": args.out, "article": r.article, "quantity": r.quantity, "n_lines": r.n_lines,
            "sensors": [c.name for c in r.sensors], "drives": [c.name for c in r.drives],
            "sensor_grids": [c.grid for c in r.sensors], "drive_grids": [c.grid for c in r.drives]}
    if args.json:
        print(json.dumps(info))
    else:
        print(f"{args.out}: {r.n_lines} lines {r.frequency_hz.min():.3f}-{r.frequency_hz.max():.3f} Hz, "
              f"{len(r.sensors)} x {len(r.drives)} {r.quantity}, article {r.article!r}")
        print("references: " + ", ".join(c.name for c in r.drives))
    return 0
