"""``frfcal example subframe``: write the example structure and its parameter file."""

from __future__ import annotations

import argparse

HELP = "write an example model (the welded steel subframe) and its parameter file"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("structure", choices=["subframe"], help="which example structure to write")
    parser.add_argument("--dof", type=int, default=5000, help="approximate number of grid DOF (default 5000)")
    parser.add_argument(
        "--units", choices=["mm-t-s", "si"], default="mm-t-s", help="unit system of the written deck (default mm-t-s)"
    )
    parser.add_argument("--out", default=".", help="output directory (default: current directory)")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of text")


def run(args) -> int:
    import json

    from femodel._example import PAPER_PARAMETERS, example_subframe

    if args.dof < 1000:
        raise ValueError(f"--dof must be at least 1000, got {args.dof}")
    ex = example_subframe(args.out, target_dof=args.dof, units=args.units)
    params = [
        {"name": n, "card": c, "id": i, "field": f, "lower": lo, "upper": hi, "description": d}
        for n, c, i, f, lo, hi, d in PAPER_PARAMETERS
    ]
    if args.json:
        print(
            json.dumps(
                {
                    "bdf": str(ex.bdf),
                    "params": str(ex.params),
                    "units": ex.units,
                    "n_dof": ex.n_dof,
                    "n_grids": ex.n_grids,
                    "n_elements": ex.n_elements,
                    "element_size_mm": ex.element_size_mm,
                    "mass_kg": ex.mass_kg,
                    "parameters": params,
                }
            )
        )
        return 0
    print(f"wrote {ex.bdf}")
    print(f"wrote {ex.params}")
    print(
        f"subframe ({ex.units}): {ex.n_dof} grid DOF, {ex.n_grids} grids, {ex.n_elements} CQUAD4, "
        f"element size {ex.element_size_mm:.3g} mm, mass {ex.mass_kg:.3f} kg"
    )
    print(f"modes: frfcal modes {ex.bdf} --units {ex.units} --n 30")
    print(f"{len(params)} parameters (P = P0 (1 + p)):")
    for k, p in enumerate(params, 1):
        print(f"  {k:2d} {p['name']:<20s} {p['card']:>6s} {p['id']:>8d} {p['field']:<4s} "
              f"p in [{p['lower']:+.2f}, {p['upper']:+.2f}]  {p['description']}")
    return 0
