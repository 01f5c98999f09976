"""``frfcal modes``: natural frequencies of a Nastran deck or of Nastran-written matrices."""

from __future__ import annotations

import argparse

HELP = "natural frequencies (Hz) of a Nastran deck, DMIG punch or OP4/OP2 matrices"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("model", nargs="?", help="Nastran bulk data deck (.bdf/.dat)")
    parser.add_argument("--n", type=int, default=10, help="number of modes (default 10)")
    parser.add_argument(
        "--units",
        choices=["si", "mm-t-s", "in-lbf-s", "consistent"],
        default="si",
        help="unit system the deck is written in (default si); results are SI/Hz",
    )
    parser.add_argument("--allow-unsupported", action="store_true", help="ignore unsupported cards (with a warning)")
    parser.add_argument(
        "--matrices",
        metavar="FILE",
        help="read K and M from a DMIG punch (.pch), OP4 (.op4) or OP2 (.op2) file instead of a deck",
    )
    parser.add_argument("--stiffness", help="matrix name of K in --matrices (default KAAX for DMIG/OP2, KAA for OP4)")
    parser.add_argument("--mass", help="matrix name of M in --matrices (default MAAX for DMIG/OP2, MAA for OP4)")
    parser.add_argument(
        "--clamp-grids",
        action="store_true",
        help="with --matrices: clamp every grid DOF and keep scalar points "
        "(the fixed-interface problem of Craig-Bampton matrices)",
    )
    parser.add_argument("--shift-hz", type=float, default=None, help="Lanczos shift in Hz (negative: below zero; default -1)")
    parser.add_argument("--solver", choices=["auto", "cholmod", "pardiso", "cholespy", "superlu", "dense"], default="auto", help="factorization")
    parser.add_argument("--threads", type=int, default=None, help="BLAS/OpenMP thread limit (default: cores, at most 4)")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of text")


def run(args) -> int:
    import json
    import time

    import femodel
    from femodel._modes import default_threads

    if args.clamp_grids and not args.matrices:
        raise ValueError("--clamp-grids applies to --matrices only")
    if (args.model is None) == (args.matrices is None):
        raise ValueError("give exactly one of MODEL.bdf or --matrices FILE")
    if args.n < 1:
        raise ValueError(f"--n must be >= 1, got {args.n}")
    threads = args.threads if args.threads is not None else default_threads()
    t0 = time.perf_counter()
    info: dict = {}
    if args.matrices:
        mats = femodel.read_matrices(args.matrices, stiffness=args.stiffness, mass=args.mass)
        if args.clamp_grids:
            import numpy as np

            grids = np.unique(mats.dofs.grid[mats.dofs.component > 0])
            if grids.size == 0:
                raise ValueError(f"{args.matrices}: --clamp-grids: the DOF map has no grid DOF (only scalar points)")
            mats = mats.without(grids)
        t1 = time.perf_counter()
        K, M, dofs = mats.K, mats.M, mats.dofs
        info.update(source=mats.source, units="as written by Nastran", n_massless=len(mats.massless))
        assembly_s = 0.0
    else:
        model = femodel.read_bdf(args.model, units=args.units, allow_unsupported=args.allow_unsupported)
        t1 = time.perf_counter()
        asm = femodel.assemble(model)
        assembly_s = asm.timings.get("total_s", 0.0)
        K, M, dofs = asm.stiffness(), asm.mass(), asm.aset
        info.update(
            source=str(args.model),
            units=model.units,
            n_grids=model.n_grids,
            n_gset=len(asm.gset),
            n_autospc=len(asm.autospc),
            ignored_cards=dict(model.ignored_cards),
        )
    t2 = time.perf_counter()
    modes = femodel.normal_modes(K, M, args.n, shift_hz=args.shift_hz, solver=args.solver, n_threads=threads, dofs=dofs)
    t3 = time.perf_counter()
    out = {
        **info,
        "n_dof": int(K.shape[0]),
        "n_modes": modes.n_modes,
        "frequencies_hz": [float(f) for f in modes.frequencies_hz],
        "n_rigid": modes.n_rigid,
        "rigid_tol_hz": modes.rigid_tol_hz,
        "solver": modes.solver,
        "shift_hz": modes.shift_hz,
        "threads": modes.n_threads,
        "timing_s": {
            "read": t1 - t0,
            "assemble": assembly_s,
            "reduce": (t2 - t1) - assembly_s,
            "factorize": modes.factor_time_s,
            "eigensolve": modes.solve_time_s,
            "modes_total": t3 - t2,
            "total": t3 - t0,
        },
    }
    if args.json:
        print(json.dumps(out))
        return 0
    print(f"{out['source']}: {out['n_dof']} independent DOF")
    if info.get("ignored_cards"):
        print("ignored cards: " + ", ".join(f"{k} x{v}" for k, v in info["ignored_cards"].items()))
    print(f"{'mode':>5} {'frequency [Hz]':>16}")
    for i, f in enumerate(modes.frequencies_hz, 1):
        tag = "  rigid" if abs(f) < modes.rigid_tol_hz else ""
        print(f"{i:5d} {f:16.6g}{tag}")
    print(f"rigid-body modes: {modes.n_rigid} (below {modes.rigid_tol_hz:g} Hz)")
    print(f"solver: {modes.solver}, threads: {modes.n_threads}")
    t = out["timing_s"]
    print(
        f"time: read {t['read']:.2f} s, assemble {t['assemble']:.2f} s, factorize {t['factorize']:.2f} s, "
        f"eigensolve {t['eigensolve']:.2f} s, total {t['total']:.2f} s"
    )
    return 0
