"""Small synthetic Nastran decks for femodel tests (free-field bulk data)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

# SI values of the test frame; `scale_units` rewrites them for mm-t-s
E, NU, RHO = 2.1e11, 0.3, 7850.0


def frame_deck(path: Path, *, units: str = "si", cd_cyl: bool = False, spc: bool = False) -> Path:
    """A free-free 3D frame using every line/point card we support.

    CBAR (PBAR with K1/K2 and without), CBEAM (PBEAML BOX), CROD (PROD),
    CONROD, CONM2 with offset and inertia, CELAS1/CELAS2 between coincident
    grids, CBUSH with CID, RBE2 and RBE3, a CORD2R used for grid positions and
    (optionally) a CORD2C used as the displacement system of some grids.
    """
    L = 1e3 if units == "mm-t-s" else 1.0  # length factor deck/SI
    Mf = 1e-3 if units == "mm-t-s" else 1.0  # mass factor deck/SI (tonne)
    S = Mf / L  # stress: N/m^2 -> N/mm^2 = 1e-6 ; (M/L/T^2): 1e-3/1e3 = 1e-6
    D = Mf / L**3
    lines = ["SOL 103", "CEND", "BEGIN BULK", "PARAM,K6ROT,100."]
    lines.append(f"MAT1,1,{E * S!r},,{NU},{RHO * D!r}")
    lines.append(f"MAT1,2,{7.0e10 * S!r},{2.6e10 * S!r},,{2700.0 * D!r}")
    a, i1, i2, j = 4e-4, 2e-8, 3e-8, 4e-8
    lines.append(f"PBAR,10,1,{a * L**2!r},{i1 * L**4!r},{i2 * L**4!r},{j * L**4!r},{0.5 * Mf / L!r}")
    lines.append(f"PBAR,11,2,{a * L**2!r},{i1 * L**4!r},{i2 * L**4!r},{j * L**4!r},,,+P11")
    lines.append("+P11,,,,,,,,,+Q11")
    lines.append("+Q11,0.85,0.85")
    lines.append(f"PBEAML,12,1,,BOX,,,,,,,+B12")
    lines.append(f"+B12,{0.04 * L!r},{0.03 * L!r},{0.003 * L!r},{0.002 * L!r}")
    lines.append(f"PROD,13,1,{2e-4 * L**2!r},{1e-8 * L**4!r}")
    lines.append(f"PELAS,14,{2.0e5 * Mf!r}")  # N/m -> N/mm: 1e-3
    lines.append(f"PBUSH,15,K,{1e6 * Mf!r},{2e6 * Mf!r},{3e6 * Mf!r},{1e3 * Mf * L**2!r},{2e3 * Mf * L**2!r},{3e3 * Mf * L**2!r}")
    lines.append(f"CORD2R,5,0,{0.1 * L!r},{0.2 * L!r},0.,{0.1 * L!r},{0.2 * L!r},{1.0 * L!r},+C5")
    lines.append(f"+C5,{1.1 * L!r},{0.7 * L!r},0.")
    if cd_cyl:
        lines.append(f"CORD2C,6,0,{0.3 * L!r},0.,0.,{0.3 * L!r},0.,{1.0 * L!r},+C6")
        lines.append(f"+C6,{1.3 * L!r},{0.4 * L!r},0.")
    xyz = {
        1: (0, 0, 0), 2: (1, 0, 0), 3: (1, 1, 0), 4: (0, 1, 0),
        5: (0, 0, 1), 6: (1, 0, 1), 7: (1, 1, 1), 8: (0, 1, 1),
        9: (0.5, 0.5, 1.3), 10: (0.5, 0.5, 1.3), 11: (0.5, 0.5, 0.0), 12: (0.5, 0.5, -0.4),
        13: (1.5, 0.5, 0.5),
    }
    for g, x in xyz.items():
        cd = 6 if cd_cyl and g in (9, 10, 13) else 0
        lines.append(f"GRID,{g},0,{x[0] * L!r},{x[1] * L!r},{x[2] * L!r},{cd}")
    # grid 14 given in CORD2R 5 (position check), attached by a rod
    lines.append(f"GRID,14,5,{0.3 * L!r},{0.1 * L!r},{0.4 * L!r}")
    for eid, (ga, gb) in enumerate([(1, 2), (2, 3), (3, 4), (4, 1)], start=1):
        lines.append(f"CBAR,{eid},10,{ga},{gb},0.,0.,1.")
    for eid, (ga, gb) in enumerate([(5, 6), (6, 7), (7, 8), (8, 5)], start=5):
        lines.append(f"CBAR,{eid},11,{ga},{gb},0.3,0.2,1.0,,+W{eid}")
        lines.append(f"+W{eid},,,{0.01 * L!r},0.,0.,0.,{-0.01 * L!r},0.")
    for eid, (ga, gb) in enumerate([(1, 5), (2, 6), (3, 7), (4, 8)], start=9):
        lines.append(f"CBEAM,{eid},12,{ga},{gb},1.,0.,0.")
    lines.append("CROD,20,13,1,7")
    lines.append(f"CONROD,21,2,8,2,{3e-4 * L**2!r},{2e-8 * L**4!r}")
    lines.append("CROD,22,13,6,14")
    lines.append("CROD,23,13,8,14")
    lines.append("CROD,24,13,7,14")
    lines.append("RBE2,30,9,123456,5,6,7,8")
    lines.append("CELAS1,31,14,9,3,10,3")
    lines.append(f"CELAS2,32,{3.0e5 * Mf!r},9,1,10,1")
    lines.append(f"CELAS2,33,{3.0e5 * Mf!r},9,2,10,2")
    lines.append("RBE3,34,,11,123456,1.0,123,1,2,+R34")
    lines.append("+R34,3,4")
    lines.append("CBUSH,35,15,11,12,,,,5")
    lines.append("CBUSH,36,15,3,13,,,,0")
    lines.append("RBE2,37,9,123,13")  # translations only: rotations of 13 stay independent
    lines.append(f"CONM2,40,12,0,{2.0 * Mf!r},{0.01 * L!r},{-0.02 * L!r},{0.03 * L!r},,+M40")
    lines.append(f"+M40,{0.1 * Mf * L**2!r},{0.01 * Mf * L**2!r},{0.2 * Mf * L**2!r},{0.02 * Mf * L**2!r},{0.03 * Mf * L**2!r},{0.3 * Mf * L**2!r}")
    lines.append(f"CONM2,41,13,5,{1.5 * Mf!r},{0.02 * L!r},0.,0.")
    if spc:
        lines.append("SPC1,1,123456,1,2")
    lines.append("ENDDATA")
    path.write_text("\n".join(lines) + "\n")
    return path


def cantilever_deck(path: Path, *, n_el: int = 8, direction=(1.0, 2.0, 2.0), k_shear=None, length=2.0) -> Path:
    """A straight CBAR cantilever along an oblique direction, clamped at grid 1."""
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    lines = ["BEGIN BULK", f"MAT1,1,{E!r},,{NU},{RHO!r}"]
    kk = "" if k_shear is None else f"+K\n+K,,,,,,,,,+L\n+L,{k_shear},{k_shear}"
    lines.append(f"PBAR,1,1,1.e-3,2.e-7,3.e-7,4.e-7,,{kk}")
    for i in range(n_el + 1):
        x = d * length * i / n_el
        lines.append(f"GRID,{i + 1},,{x[0]!r},{x[1]!r},{x[2]!r}")
    for i in range(n_el):
        lines.append(f"CBAR,{i + 1},1,{i + 1},{i + 2},0.,0.,1.")
    lines.append("SPC1,1,123456,1")
    lines.append("ENDDATA")
    path.write_text("\n".join(l for l in "\n".join(lines).splitlines()) + "\n")
    return path
