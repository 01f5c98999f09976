"""``frfcal example subframe|frame``: write an example structure and its parameter file."""

from __future__ import annotations

import argparse

HELP = "write an example model (welded steel subframe, or beam ladder frame) and its parameter file"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "structure", choices=["subframe", "frame"],
        help="which example structure to write: subframe (CQUAD4 shells) or frame (CBAR ladder frame, "
        "lumped mass, spring-mounted cradle)",
    )
    parser.add_argument("--dof", type=int, default=5000,
                        help="subframe: approximate number of grid DOF (default 5000)")
    parser.add_argument("--elements-per-member", type=int, default=6,
                        help="frame: CBARs per member (default 6: 492 grid DOF; DOF = 84 n - 12)")
    parser.add_argument(
        "--units", choices=["mm-t-s", "si"], default=None,
        help="unit system of the written deck (default: mm-t-s for the subframe, si for the frame)",
    )
    parser.add_argument(
        "--gap-mm", type=float, default=None,
        help="add a part with an air gap of this many mm (subframe: a doubler sheet outside the LHS rail web, "
        "welded along its top edge only; frame: two bump-stop brackets on the cradle ending below the rails); "
        "the facing grid pairs are printed",
    )
    parser.add_argument("--out", default=".", help="output directory (default: current directory)")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of text")


def _subframe(args):
    from femodel._example import PAPER_PARAMETERS, example_subframe

    if args.dof < 1000:
        raise ValueError(f"--dof must be at least 1000, got {args.dof}")
    ex = example_subframe(args.out, target_dof=args.dof, units=args.units or "mm-t-s", gap_mm=args.gap_mm)
    params = [
        {"name": n, "card": c, "id": i, "ids": [i], "field": f, "lower": lo, "upper": hi, "description": d}
        for n, c, i, f, lo, hi, d in PAPER_PARAMETERS
    ]
    summary = {"n_dof": ex.n_dof, "n_grids": ex.n_grids, "n_elements": ex.n_elements,
               "element_size_mm": ex.element_size_mm, "mass_kg": ex.mass_kg}
    text = (f"subframe ({ex.units}): {ex.n_dof} grid DOF, {ex.n_grids} grids, {ex.n_elements} CQUAD4, "
            f"element size {ex.element_size_mm:.3g} mm, mass {ex.mass_kg:.3f} kg")
    return ex, params, summary, text


def _frame(args):
    from femodel._example_frame import FRAME_PARAMETERS, example_frame

    if args.elements_per_member < 2:
        raise ValueError(f"--elements-per-member must be at least 2, got {args.elements_per_member}")
    ex = example_frame(args.out, units=args.units or "si", elements_per_member=args.elements_per_member,
                       gap_mm=args.gap_mm)
    params = [
        {"name": n, "card": c, "id": ids[0], "ids": list(ids), "field": f, "lower": lo, "upper": hi, "description": d}
        for n, c, ids, f, lo, hi, _unit, d in FRAME_PARAMETERS
    ]
    summary = {"n_dof": ex.n_dof, "n_grids": ex.n_grids, "n_elements": ex.n_elements, "n_springs": ex.n_springs,
               "elements_per_member": ex.elements_per_member, "mass_kg": ex.mass_kg}
    text = (f"frame ({ex.units}): {ex.n_dof} grid DOF, {ex.n_grids} grids, {ex.n_elements} CBAR, "
            f"{ex.n_springs} CELAS2, {ex.elements_per_member} CBAR per member, mass {ex.mass_kg:.3f} kg")
    return ex, params, summary, text


def run(args) -> int:
    import json

    ex, params, summary, text = (_subframe if args.structure == "subframe" else _frame)(args)
    if ex.gap_mm is not None:
        summary.update(gap_mm=ex.gap_mm, gap_pairs=[list(p) for p in ex.gap_pairs])
        text += (f"\nair gap {ex.gap_mm:g} mm: {len(ex.gap_pairs)} facing grid pairs (no element joins them): "
                 + " ".join(f"{a}-{b}" for a, b in ex.gap_pairs))
    if args.json:
        print(json.dumps({"structure": args.structure, "bdf": str(ex.bdf), "params": str(ex.params),
                          "units": ex.units, **summary, "parameters": params}))
        return 0
    print(f"wrote {ex.bdf}")
    print(f"wrote {ex.params}")
    print(text)
    print(f"modes: frfcal modes {ex.bdf} --units {ex.units} --n 30")
    print(f"{len(params)} parameters (P = P0 (1 + p)):")
    for k, p in enumerate(params, 1):
        ids = ",".join(str(i) for i in p["ids"])
        print(f"  {k:2d} {p['name']:<20s} {p['card']:>6s} {ids:>8s} {p['field']:<4s} "
              f"p in [{p['lower']:+.2f}, {p['upper']:+.2f}]  {p['description']}")
    return 0
