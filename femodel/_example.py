"""Example structure: a free-free welded steel subframe-like shell model.

The generator writes a Nastran deck and its parameter file whose 17
parameters mirror Table 2.1 of the method paper (E and rho of the main steel,
ten sheet thicknesses, four bushing masses, weld E).

Geometry (millimetres; x rearward, y to the right, z up; LHS is y < 0)
---------------------------------------------------------------------
* two longitudinal box rails, 1000 long, 80 wide, 60 high, at
  y in [0, 80] (LHS) and [520, 600] (RHS), closed by end caps;
* two box cross members between the rails at x in [100, 180] (front) and
  [820, 900] (rear), sharing the rails' top and bottom planes;
* top skin (z = 60) and bottom skin (z = 0) of rails and cross members;
  the vertical webs are the main (unparameterized) sheet, t = 2.5;
* two lateral box arms at x in [420, 520], 60 high, protruding 120 from the
  outer webs: arm base (first 40 mm after a 15 mm weld seam), arm extended
  base (next 40 mm), arm (last 40 mm and the end cap);
* two U-channel brackets on the rails at x in [640, 740], 80 high;
* weld seams as 12-15 mm shell strips with their own MAT1 where the cross
  members, arms and brackets are joined to the rails;
* four bushing masses (CONM2) 40 mm above the rail ends, each attached by an
  RBE3 to the top-skin nodes of an 80 x 80 mm corner patch;
* optionally (``gap_mm``) an air gap: a doubler sheet (PSHELL 21, t = 2.0,
  steel) outside the LHS rail's outer web, x in [180, 380], z in [0, 50],
  ``gap_mm`` from the web (y = -gap_mm), welded along its top edge only
  through a flange of its own property in the top-skin plane (z = 50,
  y in [-gap_mm, 0]); its other grids face web grids (same x, z) at exactly
  ``gap_mm`` with no element between them.

Every panel is a flat axis-aligned rectangle meshed on one global tensor
grid, so meshes are conforming, quads are perfect rectangles (no warp, no
skew) and the same geometry is meshed at any density: only the element size
changes with ``target_dof``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

# ----------------------------------------------------------------------------
# Nominal data (Table 2.1 of the method paper), SI.
# ----------------------------------------------------------------------------
E_STEEL_PA = 210.0e9
NU_STEEL = 0.3
RHO_STEEL_KG_M3 = 7850.0
E_WELD_PA = 210.0e9
RHO_WELD_KG_M3 = 7850.0
T_WELD_MM = 3.0
BUSHING_MASS_KG = (0.136, 0.136, 0.215, 0.215)

#: PSHELL id -> (name, thickness in mm, MAT1 id).
PROPERTIES: dict[int, tuple[str, float, int]] = {
    1: ("top skin", 2.3, 1),
    2: ("bottom skin", 2.0, 1),
    3: ("webs and end caps", 2.0, 1),
    4: ("bracket RHS", 2.5, 1),
    5: ("bracket LHS", 2.5, 1),
    6: ("arm base RHS", 2.3, 1),
    7: ("arm base LHS", 2.3, 1),
    8: ("arm RHS", 3.0, 1),
    9: ("arm LHS", 3.0, 1),
    10: ("arm extended base RHS", 2.3, 1),
    11: ("arm extended base LHS", 2.3, 1),
    20: ("weld seams", T_WELD_MM, 2),
}

#: the paper's 17 parameters: (name, card, id, field, lower, upper, description)
PAPER_PARAMETERS: tuple[tuple[str, str, int, str, float, float, str], ...] = (
    ("E_main", "MAT1", 1, "E", -0.2, 0.2, "Young's modulus of the main steel"),
    ("rho_main", "MAT1", 1, "RHO", -0.2, 0.2, "density of the main steel"),
    ("t_bracket_RHS", "PSHELL", 4, "T", -0.3, 0.3, "thickness of the RHS bracket"),
    ("t_bracket_LHS", "PSHELL", 5, "T", -0.3, 0.3, "thickness of the LHS bracket"),
    ("t_top_skin", "PSHELL", 1, "T", -0.3, 0.3, "thickness of the top skin"),
    ("t_bottom_skin", "PSHELL", 2, "T", -0.3, 0.3, "thickness of the bottom skin"),
    ("t_arm_base_RHS", "PSHELL", 6, "T", -0.3, 0.3, "thickness of the RHS arm base"),
    ("t_arm_base_LHS", "PSHELL", 7, "T", -0.3, 0.3, "thickness of the LHS arm base"),
    ("t_arm_RHS", "PSHELL", 8, "T", -0.3, 0.3, "thickness of the RHS arm"),
    ("t_arm_LHS", "PSHELL", 9, "T", -0.3, 0.3, "thickness of the LHS arm"),
    ("t_arm_ext_base_RHS", "PSHELL", 10, "T", -0.3, 0.3, "thickness of the RHS arm extended base"),
    ("t_arm_ext_base_LHS", "PSHELL", 11, "T", -0.3, 0.3, "thickness of the LHS arm extended base"),
    ("M1", "CONM2", 1000001, "M", -0.5, 0.5, "bushing mass 1 (front LHS)"),
    ("M2", "CONM2", 1000002, "M", -0.5, 0.5, "bushing mass 2 (front RHS)"),
    ("M3", "CONM2", 1000003, "M", -0.5, 0.5, "bushing mass 3 (rear LHS)"),
    ("M4", "CONM2", 1000004, "M", -0.5, 0.5, "bushing mass 4 (rear RHS)"),
    ("E_weld", "MAT1", 2, "E", -0.5, 0.5, "Young's modulus of the weld seams"),
)

# Panels: (normal axis 0/1/2, plane coordinate, (lo, hi) along the first
# in-plane axis, (lo, hi) along the second, PSHELL id). In-plane axes are the
# cyclic successors of the normal: normal x -> (y, z), y -> (z, x), z -> (x, y).
_X_CROSS = ((100.0, 180.0), (820.0, 900.0))
_X_ARM = (420.0, 520.0)
_X_BRACKET = (640.0, 740.0)
_H = 50.0
_Z_BRACKET_WELD = _H + 12.0
_Z_BRACKET_TOP = _H + 80.0
_BUSHINGS = (  # (x, y) of the patch centre, patch is +-40 mm in x and y
    (40.0, 40.0), (40.0, 560.0), (960.0, 40.0), (960.0, 560.0),
)
_BUSHING_HEIGHT = 40.0
#: the optional doubler (air-gap variant): PSHELL id, thickness (mm), x range (mm)
DOUBLER_PID = 21
DOUBLER_T_MM = 2.0
_X_DOUBLER = (180.0, 380.0)
#: largest allowed gap (mm): the doubler stays inside the arm's 15 mm weld strip in y
_GAP_MAX_MM = 10.0


def _panels(gap_mm: float | None = None) -> list[tuple[int, float, tuple[float, float], tuple[float, float], int]]:
    P = []
    if gap_mm is not None:
        # doubler sheet parallel to the LHS outer web (y = 0) at y = -gap, and its flange welded to the
        # web/top-skin corner line (z = _H, y = 0): the flange is the only connection
        P.append((1, -gap_mm, (0.0, _H), _X_DOUBLER, DOUBLER_PID))
        P.append((2, _H, _X_DOUBLER, (-gap_mm, 0.0), DOUBLER_PID))
    for y0, y1 in ((0.0, 80.0), (520.0, 600.0)):
        # rail skins (z-normal: axes x, y)
        P.append((2, _H, (0.0, 1000.0), (y0, y1), 1))
        P.append((2, 0.0, (0.0, 1000.0), (y0, y1), 2))
        # rail webs (y-normal: axes z, x)
        P.append((1, y0, (0.0, _H), (0.0, 1000.0), 3))
        P.append((1, y1, (0.0, _H), (0.0, 1000.0), 3))
        # end caps (x-normal: axes y, z)
        P.append((0, 0.0, (y0, y1), (0.0, _H), 3))
        P.append((0, 1000.0, (y0, y1), (0.0, _H), 3))
    for x0, x1 in _X_CROSS:
        P.append((2, _H, (x0, x1), (80.0, 520.0), 1))
        P.append((2, 0.0, (x0, x1), (80.0, 520.0), 2))
        for xw in (x0, x1):
            P.append((0, xw, (80.0, 95.0), (0.0, _H), 20))
            P.append((0, xw, (95.0, 505.0), (0.0, _H), 3))
            P.append((0, xw, (505.0, 520.0), (0.0, _H), 20))
    xa0, xa1 = _X_ARM
    # arms: segments (y range, pid) for LHS and RHS, outward from the outer web
    arms = (
        ((-15.0, 0.0), 20), ((-55.0, -15.0), 7), ((-95.0, -55.0), 11), ((-120.0, -95.0), 9),
        ((600.0, 615.0), 20), ((615.0, 655.0), 6), ((655.0, 695.0), 10), ((695.0, 720.0), 8),
    )
    for (ya, yb), pid in arms:
        P.append((2, _H, (xa0, xa1), (ya, yb), pid))
        P.append((2, 0.0, (xa0, xa1), (ya, yb), pid))
        P.append((0, xa0, (ya, yb), (0.0, _H), pid))
        P.append((0, xa1, (ya, yb), (0.0, _H), pid))
    P.append((1, -120.0, (0.0, _H), (xa0, xa1), 9))
    P.append((1, 720.0, (0.0, _H), (xa0, xa1), 8))
    xb0, xb1 = _X_BRACKET
    for (yp0, yp1), pid in (((20.0, 60.0), 5), ((540.0, 580.0), 4)):
        for yp in (yp0, yp1):
            P.append((1, yp, (_H, _Z_BRACKET_WELD), (xb0, xb1), 20))
            P.append((1, yp, (_Z_BRACKET_WELD, _Z_BRACKET_TOP), (xb0, xb1), pid))
        P.append((2, _Z_BRACKET_TOP, (xb0, xb1), (yp0, yp1), pid))
    return P


def _key_lines(panels):
    keys = [set(), set(), set()]
    for normal, c, r1, r2, _ in panels:
        a1, a2 = (normal + 1) % 3, (normal + 2) % 3
        keys[normal].add(c)
        keys[a1].update(r1)
        keys[a2].update(r2)
    for bx, by in _BUSHINGS:  # corner patches are bounded by existing lines
        keys[0].update((bx - 40.0, bx + 40.0))
        keys[1].update((by - 40.0, by + 40.0))
    return [np.array(sorted(k)) for k in keys]


def _lines(keys: np.ndarray, h: float) -> np.ndarray:
    """Subdivide every interval between key coordinates into equal parts of about h."""
    out = [keys[:1]]
    for a, b in zip(keys[:-1], keys[1:]):
        n = max(1, int(round((b - a) / h)))
        out.append(a + (b - a) * np.arange(1, n + 1) / n)
    lines = np.concatenate(out)
    lines[np.searchsorted(lines, keys)] = keys  # exact key values
    return lines


@dataclass(frozen=True)
class _Mesh:
    xyz_mm: np.ndarray  # (n_nodes, 3)
    quads: np.ndarray  # (n_elem, 4) node index (0-based)
    pids: np.ndarray  # (n_elem,)
    areas_mm2: np.ndarray  # (n_elem,)
    bushing_nodes: tuple  # 4 arrays of node indices (0-based)
    gap_pairs: tuple = ()  # (doubler node, web node) index pairs (0-based) facing across the gap


def _mesh(h: float, count_only: bool = False, gap_mm: float | None = None):
    panels = _panels(gap_mm)
    keys = _key_lines(panels)
    lines = [_lines(k, h) for k in keys]
    shape = tuple(len(g) for g in lines)
    occupied = np.zeros(shape, dtype=bool)
    cells = []
    for normal, c, r1, r2, pid in panels:
        a1, a2 = (normal + 1) % 3, (normal + 2) % 3
        ic = int(np.searchsorted(lines[normal], c))
        i0, i1 = np.searchsorted(lines[a1], r1)
        j0, j1 = np.searchsorted(lines[a2], r2)
        idx = [None, None, None]
        idx[normal] = ic
        idx[a1] = slice(i0, i1 + 1)
        idx[a2] = slice(j0, j1 + 1)
        occupied[tuple(idx)] = True
        cells.append((normal, ic, a1, i0, i1, a2, j0, j1, pid))
    n_nodes = int(occupied.sum())
    n_elem = sum((c[4] - c[3]) * (c[7] - c[6]) for c in cells)
    if count_only:
        return n_nodes, n_elem
    node_id = np.full(shape, -1, dtype=np.int64)
    node_id[occupied] = np.arange(n_nodes)
    ii, jj, kk = np.nonzero(occupied)
    xyz = np.column_stack([lines[0][ii], lines[1][jj], lines[2][kk]])
    quads, pids, areas = [], [], []
    for normal, ic, a1, i0, i1, a2, j0, j1, pid in cells:
        I, J = np.meshgrid(np.arange(i0, i1), np.arange(j0, j1), indexing="ij")
        I, J = I.ravel(), J.ravel()
        corners = []
        for di, dj in ((0, 0), (1, 0), (1, 1), (0, 1)):
            idx = [None, None, None]
            idx[normal] = np.full(I.shape, ic)
            idx[a1] = I + di
            idx[a2] = J + dj
            corners.append(node_id[idx[0], idx[1], idx[2]])
        quads.append(np.column_stack(corners))
        pids.append(np.full(I.shape, pid))
        areas.append(np.diff(lines[a1])[I] * np.diff(lines[a2])[J])
    quads = np.concatenate(quads)
    if np.any(quads < 0):  # pragma: no cover - guards the panel table
        raise RuntimeError("subframe mesh: element refers to an unoccupied grid point")
    bushing_nodes = []
    top = np.isclose(xyz[:, 2], _H)
    for bx, by in _BUSHINGS:
        sel = top & (np.abs(xyz[:, 0] - bx) <= 40.0 + 1e-9) & (np.abs(xyz[:, 1] - by) <= 40.0 + 1e-9)
        bushing_nodes.append(np.flatnonzero(sel))
    pairs = ()
    if gap_mm is not None:
        on_doubler = np.isclose(xyz[:, 1], -gap_mm) & (xyz[:, 2] < _H - 1e-9) & \
            (xyz[:, 0] >= _X_DOUBLER[0] - 1e-9) & (xyz[:, 0] <= _X_DOUBLER[1] + 1e-9)
        where = {(x, z): i for i, (x, y, z) in enumerate(xyz.tolist()) if y == 0.0}
        pairs = tuple((int(i), int(where[(xyz[i, 0], xyz[i, 2])])) for i in np.flatnonzero(on_doubler))
    return _Mesh(xyz, quads, np.concatenate(pids), np.concatenate(areas), tuple(bushing_nodes), pairs)


def _element_size_for(target_dof: int) -> float:
    """Element size (mm) whose mesh has the grid-DOF count closest to ``target_dof``.

    The count is a step function of the size (intervals are split into whole
    numbers of elements), so bisect on log(h) and keep the closest size seen.
    """
    lo, hi = math.log(0.5), math.log(200.0)
    best = (float("inf"), 1.0)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        n_nodes, _ = _mesh(math.exp(mid), count_only=True)
        dof = 6 * (n_nodes + len(_BUSHINGS))
        best = min(best, (abs(dof - target_dof), math.exp(mid)))
        if dof > target_dof:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-6:
            break
    return best[1]


# ----------------------------------------------------------------------------
# Writing
# ----------------------------------------------------------------------------
_UNITS = {
    # length, mass, stress, density scale from the mm-t-s numbers; exponent
    # shift applied to the decimal exponent so both decks hold the same digits.
    "mm-t-s": {"length": 0, "mass_t": 0, "stress_mpa": 0, "rho_t_mm3": 0},
    "si": {"length": -3, "mass_t": 3, "stress_mpa": 6, "rho_t_mm3": 12},
}


def _f16(values, shift: int = 0) -> list[str]:
    """Right-justified 16-character large-field reals, exponent shifted by ``shift``.

    Shifting the printed decimal exponent (instead of multiplying in binary)
    keeps the mm-t-s and SI decks digit-for-digit identical.
    """
    out = []
    for s in np.char.mod("%.9E", np.asarray(values, dtype=float)):
        mant, exp = s.split("E")
        e = int(exp) + shift if float(mant) != 0.0 else 0
        out.append(f"{mant}E{e:+03d}".rjust(16))
    return out


def _f8(value: float, shift: int = 0) -> str:
    """An 8-character small-field real with the exponent shifted by ``shift``."""
    mant, exp = f"{value:.2E}".split("E")
    e = int(exp) + shift if float(mant) != 0.0 else 0
    s = f"{mant}E{e:+d}"
    if len(s) > 8:
        raise ValueError(f"value {value} does not fit an 8-character field")
    return s.rjust(8)


def _large_card(name: str, fields: list[str]) -> str:
    """A large-field card; ``fields`` are already 16-character strings."""
    lines = []
    head = f"{name + '*':<8s}"
    for i in range(0, max(len(fields), 1), 4):
        chunk = "".join(f.rjust(16) for f in fields[i:i + 4])
        lines.append((head if i == 0 else "*       ") + chunk)
    return "\n".join(lines) + "\n"


@dataclass(frozen=True)
class SubframeExample:
    """What :func:`example_subframe` wrote.

    Attributes
    ----------
    bdf, params : Path
        The Nastran deck and its parameter file (TOML).
    units : str
        Unit system of the deck, ``"mm-t-s"`` or ``"si"``.
    element_size_mm : float
        Target element edge length used for the mesh.
    n_grids, n_dof, n_elements : int
        Grid points (incl. the four bushing grids), grid DOF (6 per grid) and
        CQUAD4 elements.
    mass_kg : float
        Total mass (shells plus bushing masses).
    gap_mm : float or None
        The air gap of the doubler variant (None: no doubler).
    gap_pairs : tuple of (int, int)
        (doubler grid, web grid) id pairs facing each other across the gap,
        exactly ``gap_mm`` apart along y; no element joins them. Empty without a gap.
    """

    bdf: Path
    params: Path
    units: str
    element_size_mm: float
    n_grids: int
    n_dof: int
    n_elements: int
    mass_kg: float
    gap_mm: float | None = None
    gap_pairs: tuple = ()


def example_subframe(out_dir, target_dof: int = 5000, units: str = "mm-t-s", *,
                     gap_mm: float | None = None) -> SubframeExample:
    """Write the subframe example deck ``subframe.bdf`` and ``subframe_params.toml``.

    Parameters
    ----------
    out_dir : path-like
        Directory to write into (created if missing).
    target_dof : int
        Approximate number of grid DOF (6 per grid); about 5,000 for tests and
        200,000 and more for benchmarks. The geometry is the same at every
        density.
    units : {"mm-t-s", "si"}
        Unit system of the written deck (mm, tonne, s, N, MPa; or m, kg, s,
        N, Pa). Both decks describe the same physics digit for digit.
    gap_mm : float, optional
        Add the doubler sheet (PSHELL 21) outside the LHS rail web with this
        air gap, mm (0 < gap_mm < 10). The element size is the one of the deck
        without it; a few mm-wide strips appear where the line y = -gap_mm
        crosses the flange and the LHS arm's weld seam. None (default): the
        deck is byte-identical to the one without the option.

    Returns
    -------
    SubframeExample
        Paths and a summary (grid DOF, elements, total mass in kg).
    """
    if units not in _UNITS:
        raise ValueError(f"example_subframe: units must be one of {sorted(_UNITS)}, got {units!r}")
    if not isinstance(target_dof, (int, np.integer)) or target_dof < 1000:
        raise ValueError(f"example_subframe: target_dof must be an integer >= 1000, got {target_dof!r}")
    if gap_mm is not None:
        gap_mm = float(gap_mm)
        if not 0.0 < gap_mm < _GAP_MAX_MM:
            raise ValueError(f"example_subframe: gap_mm must be in (0, {_GAP_MAX_MM}) mm, got {gap_mm!r}")
    sh = _UNITS[units]
    h = _element_size_for(int(target_dof))
    mesh = _mesh(h, gap_mm=gap_mm)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    n_nodes = len(mesh.xyz_mm)

    parts: list[str] = []
    parts.append(
        "$ frfcal example subframe: free-free welded steel subframe-like shell model\n"
        f"$ units: {units}; target DOF {int(target_dof)}; element size {h:.4g} mm\n"
        "$ 17 calibration parameters in subframe_params.toml (method paper, Table 2.1)\n"
        + (f"$ air gap: doubler PSHELL {DOUBLER_PID} {gap_mm:g} mm outside the LHS rail web, welded along its "
           "top edge only\n" if gap_mm is not None else "")
        + "SOL 103\nCEND\nTITLE = FRFCAL EXAMPLE SUBFRAME\nMETHOD = 1\nBEGIN BULK\n"
        "EIGRL          1                      30\n"
    )
    # materials (small field is enough for these round numbers)
    for mid, e, rho in ((1, E_STEEL_PA, RHO_STEEL_KG_M3), (2, E_WELD_PA, RHO_WELD_KG_M3)):
        parts.append(
            f"MAT1    {mid:8d}{_f8(e / 1e6, sh['stress_mpa'])}        {NU_STEEL:8.2f}"
            f"{_f8(rho * 1e-12, sh['rho_t_mm3'])}\n"
        )
    for pid, (name, t_mm, mid) in PROPERTIES.items():
        parts.append(f"$ PSHELL {pid}: {name}\n")
        parts.append(f"PSHELL  {pid:8d}{mid:8d}{_f8(t_mm, sh['length'])}{mid:8d}        {mid:8d}\n")
    if gap_mm is not None:
        parts.append(f"$ PSHELL {DOUBLER_PID}: doubler sheet and its flange (air-gap variant)\n")
        parts.append(f"PSHELL  {DOUBLER_PID:8d}{1:8d}{_f8(DOUBLER_T_MM, sh['length'])}{1:8d}        {1:8d}\n")
    # grids: large field, digit-identical across unit systems
    xs = _f16(mesh.xyz_mm.ravel(), sh["length"])
    grid_lines = []
    for i in range(n_nodes):
        grid_lines.append(
            f"GRID*   {i + 1:16d}{'':16s}{xs[3 * i]}{xs[3 * i + 1]}\n*       {xs[3 * i + 2]}\n"
        )
    parts.append("".join(grid_lines))
    q = mesh.quads + 1
    parts.append(
        "".join(
            f"CQUAD4  {e + 1:8d}{p:8d}{a:8d}{b:8d}{c:8d}{d:8d}\n"
            for e, (p, (a, b, c, d)) in enumerate(zip(mesh.pids.tolist(), q.tolist()))
        )
    )
    # bushing masses on RBE3s
    for k, (mass, (bx, by), nodes) in enumerate(zip(BUSHING_MASS_KG, _BUSHINGS, mesh.bushing_nodes)):
        gid = n_nodes + k + 1
        c = _f16([bx, by, _H + _BUSHING_HEIGHT], sh["length"])
        parts.append(f"$ bushing mass M{k + 1}\n")
        parts.append(f"GRID*   {gid:16d}{'':16s}{c[0]}{c[1]}\n*       {c[2]}\n")
        m = _f16([mass * 1e-3], sh["mass_t"])[0]
        parts.append(_large_card("CONM2", [f"{1000001 + k:16d}", f"{gid:16d}", f"{0:16d}", m]))
        fields = [f"{2000001 + k:8d}", "", f"{gid:8d}", "  123456", "     1.0", "     123"]
        fields += [f"{n + 1:8d}" for n in nodes]
        lines = []
        body = fields
        first, rest = body[:8], body[8:]
        lines.append("RBE3    " + "".join(f.rjust(8) for f in first))
        for i in range(0, len(rest), 8):
            lines.append("        " + "".join(f.rjust(8) for f in rest[i:i + 8]))
        parts.append("\n".join(lines) + "\n")
    parts.append("ENDDATA\n")
    bdf = out / "subframe.bdf"
    bdf.write_text("".join(parts))

    params = out / "subframe_params.toml"
    params.write_text(_params_toml(bdf.name, units))

    t_mm = np.array([DOUBLER_T_MM if int(p) == DOUBLER_PID else PROPERTIES[int(p)][1] for p in mesh.pids])
    rho = np.where(mesh.pids == 20, RHO_WELD_KG_M3, RHO_STEEL_KG_M3)
    mass = float(np.sum(mesh.areas_mm2 * t_mm * rho) * 1e-9) + float(sum(BUSHING_MASS_KG))
    return SubframeExample(
        bdf=bdf,
        params=params,
        units=units,
        element_size_mm=float(h),
        n_grids=n_nodes + len(_BUSHINGS),
        n_dof=6 * (n_nodes + len(_BUSHINGS)),
        n_elements=len(mesh.quads),
        mass_kg=mass,
        gap_mm=gap_mm,
        gap_pairs=tuple((a + 1, b + 1) for a, b in mesh.gap_pairs),
    )


def _params_toml(bdf_name: str, units: str) -> str:
    unit_of = {
        ("MAT1", "E"): "Pa", ("MAT1", "RHO"): "kg/m^3", ("PSHELL", "T"): "m", ("CONM2", "M"): "kg",
    }
    lines = [
        "# Calibration parameters of the frfcal example subframe (method paper, Table 2.1).",
        "# Physical value P = P0 * (1 + p); lower/upper bound the normalized p.",
        "# Nominal values P0 are read from the deck; see docs/parameters.md.",
        "",
        "[model]",
        f'bdf = "{bdf_name}"',
        f'units = "{units}"',
        "",
    ]
    for name, card, pid, field, lo, hi, desc in PAPER_PARAMETERS:
        lines += [
            "[[parameter]]",
            f'name = "{name}"',
            f'card = "{card}"',
            f"id = {pid}",
            f'field = "{field}"',
            f"lower = {lo}",
            f"upper = {hi}",
            f'unit = "{unit_of[(card, field)]}"',
            f'description = "{desc}"',
            "",
        ]
    return "\n".join(lines)
