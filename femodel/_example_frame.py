"""Example structure: a free-free steel ladder frame with a spring-mounted cradle (CBAR, lumped mass).

A second example model, structurally unlike the shell subframe: beams only,
Nastran's default lumped mass (no ``PARAM,COUPMASS``: rotational DOF carry
no mass, so M is singular), and two parts joined by scalar springs.

Geometry (millimetres; x forward, y to the left, z up)
------------------------------------------------------
* **ladder** (MAT1 1, steel): two longitudinal rails (box 150 x 60 x 4,
  PBAR 1) at y = +-400, x in [0, 1800], welded (shared grids) to four cross
  members (box 80 x 80 x 4, PBAR 2) at x = 0, 600, 1200, 1800;
* **cradle** (MAT1 2, aluminium): a closed rectangular ring 100 mm below the
  rails, two side members (box 80 x 50 x 5, PBAR 3) under the rails at
  x in [600, 1200] and two cross members (same section) at x = 600 and
  1200; its four corner grids lie 100 mm below the rail grids at the middle
  cross members;
* **mounts**: each cradle corner is joined to the rail grid above it by three
  translational CELAS2 springs (x, y along the ladder plane; z vertical), so
  the mounts carry every load between the parts;
* **lumped masses** (CONM2): an engine (two 20 kg masses on the cradle
  cross-member midpoints, centre of gravity 200 mm above the cradle, 0.3 kg m^2
  about each axis) and a fuel tank (6 kg on the midpoint of the rear ladder
  cross member, x = 1800, hanging 150 mm below it, 0.05 kg m^2). The offsets
  couple the in-plane and out-of-plane motions of the two flat parts (without
  them the scalar mounts and the planar beams would decouple them exactly).

* optionally (``gap_mm``) an air gap: two bump-stop brackets (PBAR 4, steel
  box 40 x 40 x 3) standing vertically on the cradle side members at the
  grid nearest x = 900, each ending ``gap_mm`` below the ladder rail grid
  above it, no element between tip and rail (a closed gap would carry load
  along z as the mounts do).

Every member is split into ``elements_per_member`` CBARs of equal length
(the rails into that many per bay between cross members), so the geometry
is the same at every density. Bar mass is lumped (half of rho A L per end,
translations only), as Nastran does without ``PARAM,COUPMASS``: only the
three CONM2 grids carry rotary inertia, every other rotation is massless.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from femodel._example import _f16, _large_card

# ----------------------------------------------------------------------------
# Nominal data, SI (the deck is written in mm-t-s or SI from these).
# ----------------------------------------------------------------------------
E_STEEL_PA = 210.0e9
RHO_STEEL_KG_M3 = 7850.0
E_ALU_PA = 70.0e9
RHO_ALU_KG_M3 = 2700.0
NU_STEEL = 0.3
NU_ALU = 0.33
ENGINE_MASS_KG = 20.0
TANK_MASS_KG = 6.0
#: centre-of-gravity offsets of the CONM2s along z (mm) and their rotary inertia (kg m^2, each axis)
ENGINE_OFFSET_MM = 200.0
TANK_OFFSET_MM = -150.0
ENGINE_INERTIA_KG_M2 = 0.3
TANK_INERTIA_KG_M2 = 0.05
#: mount spring rates, N/m: along the ladder plane (x, y) and vertical (z)
K_MOUNT_XY_N_M = 5.0e6
K_MOUNT_Z_N_M = 3.0e6

_X_CROSS_MM = (0.0, 600.0, 1200.0, 1800.0)
_Y_RAIL_MM = 400.0
_Z_CRADLE_MM = -100.0
_X_CRADLE_MM = (600.0, 1200.0)


def _box(h_mm: float, b_mm: float, t_mm: float) -> tuple[float, float, float, float]:
    """A, I1 (about the width axis: bending in the height plane), I2, J of a thin box (mm units).

    J from Bredt's formula on the wall centre line, 4 A_m^2 t / perimeter.
    """
    hi, bi = h_mm - 2 * t_mm, b_mm - 2 * t_mm
    A = h_mm * b_mm - hi * bi
    I1 = (b_mm * h_mm**3 - bi * hi**3) / 12.0
    I2 = (h_mm * b_mm**3 - hi * bi**3) / 12.0
    hm, bm = h_mm - t_mm, b_mm - t_mm
    J = 4.0 * (hm * bm) ** 2 * t_mm / (2.0 * (hm + bm))
    return A, I1, I2, J


#: PBAR id -> (name, MAT1 id, (height, width, wall) in mm)
SECTIONS: dict[int, tuple[str, int, tuple[float, float, float]]] = {
    1: ("ladder rails, box 150 x 60 x 4", 1, (150.0, 60.0, 4.0)),
    2: ("ladder cross members, box 80 x 80 x 4", 1, (80.0, 80.0, 4.0)),
    3: ("cradle members, box 80 x 50 x 5", 2, (80.0, 50.0, 5.0)),
}
#: the bump-stop brackets of the air-gap variant (own PBAR, written only with ``gap_mm``)
BUMP_STOP_PID = 4
BUMP_STOP_SECTION = ("bump-stop brackets, box 40 x 40 x 3", 1, (40.0, 40.0, 3.0))
_X_BUMP_STOP_MM = 900.0

#: CONM2 ids
ENGINE_CONM2 = (9001, 9002)
TANK_CONM2 = 9003
#: CELAS2 ids: 8000 + 10 * corner + component (1 x, 2 y, 3 z)
_CORNERS = ((600.0, -_Y_RAIL_MM), (600.0, _Y_RAIL_MM), (1200.0, -_Y_RAIL_MM), (1200.0, _Y_RAIL_MM))
MOUNT_XY_CELAS2 = tuple(8000 + 10 * (k + 1) + c for k in range(4) for c in (1, 2))
MOUNT_Z_CELAS2 = tuple(8000 + 10 * (k + 1) + 3 for k in range(4))

#: (name, card, ids, field, lower, upper, unit, description)
FRAME_PARAMETERS: tuple[tuple[str, str, tuple[int, ...], str, float, float, str, str], ...] = (
    ("E_ladder", "MAT1", (1,), "E", -0.2, 0.2, "Pa", "Young's modulus of the ladder steel"),
    ("rho_ladder", "MAT1", (1,), "RHO", -0.2, 0.2, "kg/m^3", "density of the ladder steel"),
    ("E_cradle", "MAT1", (2,), "E", -0.3, 0.3, "Pa", "Young's modulus of the cradle aluminium"),
    ("M_engine", "CONM2", ENGINE_CONM2, "M", -0.5, 0.5, "kg", "engine masses on the cradle"),
    ("M_tank", "CONM2", (TANK_CONM2,), "M", -0.5, 0.5, "kg", "fuel tank mass on the rear cross member"),
    ("k_mount_xy", "CELAS2", MOUNT_XY_CELAS2, "K", -0.5, 0.5, "N/m", "in-plane (x, y) rate of the cradle mounts"),
    ("k_mount_z", "CELAS2", MOUNT_Z_CELAS2, "K", -0.5, 0.5, "N/m", "vertical rate of the cradle mounts"),
)

_SHIFT = {  # decimal-exponent shift from the mm-t-s numbers to the deck's units
    "mm-t-s": {"length": 0, "area": 0, "inertia": 0, "stress": 0, "density": 0, "mass": 0, "spring": 0, "rotary": 0},
    "si": {"length": -3, "area": -6, "inertia": -12, "stress": 6, "density": 12, "mass": 3, "spring": 3, "rotary": -3},
}


@dataclass(frozen=True)
class FrameExample:
    """What :func:`example_frame` wrote.

    Iterating gives ``(bdf, params)``, so ``bdf, params = example_frame(d)`` works.

    Attributes
    ----------
    bdf, params : Path
        The Nastran deck ``frame.bdf`` and its parameter file ``frame_params.toml``.
    units : str
        ``"mm-t-s"`` or ``"si"``.
    elements_per_member : int
        CBARs per member (per bay of the rails).
    n_grids, n_dof, n_elements, n_springs : int
        Grids, grid DOF (6 per grid), CBARs and CELAS2 springs.
    mass_kg : float
        Total mass (bars plus CONM2), kg.
    gap_mm : float or None
        The air gap of the bump-stop variant (None: no bump stops).
    gap_pairs : tuple of (int, int)
        (bump-stop tip grid, rail grid) id pairs, exactly ``gap_mm`` apart
        along z with no element between them. Empty without a gap.
    """

    bdf: Path
    params: Path
    units: str
    elements_per_member: int
    n_grids: int
    n_dof: int
    n_elements: int
    n_springs: int
    mass_kg: float
    gap_mm: float | None = None
    gap_pairs: tuple = ()

    def __iter__(self):
        return iter((self.bdf, self.params))


def _frame_mesh(n: int, gap_mm: float | None = None):
    """Grid coordinates (mm), bars (grid index pairs, PBAR id) and named grid indices."""
    xyz: list[tuple[float, float, float]] = []
    index: dict[tuple[float, float, float], int] = {}

    def grid(x, y, z):
        key = (round(x, 9), round(y, 9), round(z, 9))
        if key not in index:
            index[key] = len(xyz)
            xyz.append(key)
        return index[key]

    bars: list[tuple[int, int, int]] = []

    def member(a, b, pid):
        a, b = np.asarray(a, float), np.asarray(b, float)
        ids = [grid(*(a + (b - a) * k / n)) for k in range(n + 1)]
        bars.extend((i, j, pid) for i, j in zip(ids[:-1], ids[1:]))

    for y in (-_Y_RAIL_MM, _Y_RAIL_MM):
        for x0, x1 in zip(_X_CROSS_MM[:-1], _X_CROSS_MM[1:]):
            member((x0, y, 0.0), (x1, y, 0.0), 1)
    for x in _X_CROSS_MM:
        member((x, -_Y_RAIL_MM, 0.0), (x, _Y_RAIL_MM, 0.0), 2)
    z = _Z_CRADLE_MM
    xa, xb = _X_CRADLE_MM
    for y in (-_Y_RAIL_MM, _Y_RAIL_MM):
        member((xa, y, z), (xb, y, z), 3)
    for x in (xa, xb):
        member((x, -_Y_RAIL_MM, z), (x, _Y_RAIL_MM, z), 3)
    # the middle of a cross member is a grid only for even n: put the masses on the grid nearest it
    xyz_a = np.array(xyz)

    def nearest(p):
        return int(np.argmin(np.linalg.norm(xyz_a - np.asarray(p), axis=1)))

    named = {
        "engine": [nearest((x, 0.0, z)) for x in (xa, xb)],
        "tank": nearest((_X_CROSS_MM[-1], 0.0, 0.0)),
        "mounts": [(index[(x, y, 0.0)], index[(x, y, z)]) for x, y in _CORNERS],
    }
    if gap_mm is not None:
        # a stub at the same element size as the members (the rails' bay length / n), ending gap_mm below the rail
        h = (_X_CRADLE_MM[1] - _X_CRADLE_MM[0]) / n
        n_stub = max(1, int(round((-z - gap_mm) / h)))
        named["gap"] = []
        for y in (-_Y_RAIL_MM, _Y_RAIL_MM):
            base = nearest((_X_BUMP_STOP_MM, y, z))
            x = xyz_a[base, 0]
            rail = index[(x, y, 0.0)]  # the side member and the rail bay share their x grid
            ids = [grid(x, y, -gap_mm if k == n_stub else z + (-gap_mm - z) * k / n_stub) for k in range(n_stub + 1)]
            bars.extend((i, j, BUMP_STOP_PID) for i, j in zip(ids[:-1], ids[1:]))
            named["gap"].append((ids[-1], rail))
        xyz_a = np.array(xyz)
    return xyz_a, np.array(bars, dtype=np.int64), named


def example_frame(out_dir, *, units: str = "si", elements_per_member: int = 6,
                  gap_mm: float | None = None) -> FrameExample:
    """Write the frame example deck ``frame.bdf`` and ``frame_params.toml``.

    Parameters
    ----------
    out_dir : path-like
        Directory to write into (created if missing).
    units : {"si", "mm-t-s"}
        Unit system of the deck (m, kg, s, N, Pa; or mm, tonne, s, N, MPa).
        Both decks hold the same decimal mantissas, so they describe the same
        physics to round-off.
    elements_per_member : int
        CBARs per member (>= 2). Grid DOF = 84 n - 12: 492 at the default
        6, 996 at 12, 1,416 at 17; 120 gives about 10,000.
    gap_mm : float, optional
        Add two bump-stop brackets (PBAR 4) on the cradle ending this far
        below the rails, mm (0 < gap_mm < 50); their CBARs have about the
        members' element length. None (default): the deck is byte-identical
        to the one without the option.

    Returns
    -------
    FrameExample
        Paths (unpacks as ``bdf, params``) and a summary.
    """
    if units not in _SHIFT:
        raise ValueError(f"example_frame: units must be one of {sorted(_SHIFT)}, got {units!r}")
    if not isinstance(elements_per_member, (int, np.integer)) or elements_per_member < 2:
        raise ValueError(f"example_frame: elements_per_member must be an integer >= 2, got {elements_per_member!r}")
    if gap_mm is not None:
        gap_mm = float(gap_mm)
        if not 0.0 < gap_mm < 50.0:
            raise ValueError(f"example_frame: gap_mm must be in (0, 50) mm, got {gap_mm!r}")
    n = int(elements_per_member)
    sh = _SHIFT[units]
    xyz, bars, named = _frame_mesh(n, gap_mm)
    sections = dict(SECTIONS)
    if gap_mm is not None:
        sections[BUMP_STOP_PID] = BUMP_STOP_SECTION
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)

    parts = [
        "$ frfcal example frame: free-free steel ladder frame with a spring-mounted aluminium cradle\n"
        f"$ units: {units}; {n} CBAR per member; default lumped mass (no PARAM,COUPMASS)\n"
        "$ 7 calibration parameters in frame_params.toml\n"
        + (f"$ air gap: bump-stop brackets PBAR {BUMP_STOP_PID} end {gap_mm:g} mm below the rails\n"
           if gap_mm is not None else "")
        + "SOL 103\nCEND\nTITLE = FRFCAL EXAMPLE FRAME\nMETHOD = 1\nBEGIN BULK\n"
        "EIGRL          1                      30\n"
    ]
    for mid, e, nu, rho in ((1, E_STEEL_PA, NU_STEEL, RHO_STEEL_KG_M3), (2, E_ALU_PA, NU_ALU, RHO_ALU_KG_M3)):
        e_s = _f16([e / 1e6], sh["stress"])[0]
        rho_s = _f16([rho * 1e-12], sh["density"])[0]
        parts.append(_large_card("MAT1", [f"{mid:16d}", e_s, "", f"{nu:16.4f}", rho_s]))
    for pid, (name, mid, dims) in sections.items():
        A, I1, I2, J = _box(*dims)
        parts.append(f"$ PBAR {pid}: {name}\n")
        parts.append(_large_card("PBAR", [
            f"{pid:16d}", f"{mid:16d}", _f16([A], sh["area"])[0], _f16([I1], sh["inertia"])[0],
            _f16([I2], sh["inertia"])[0], _f16([J], sh["inertia"])[0],
        ]))
    xs = _f16(xyz.ravel(), sh["length"])
    parts.append("".join(
        f"GRID*   {i + 1:16d}{'':16s}{xs[3 * i]}{xs[3 * i + 1]}\n*       {xs[3 * i + 2]}\n" for i in range(len(xyz))
    ))
    # orientation vector +z for every bar: element y = basic z, so I1 is vertical bending; the vertical
    # bump stops (square section) take +x
    parts.append("".join(
        f"CBAR    {e + 1:8d}{pid:8d}{a + 1:8d}{b + 1:8d}"
        + ("     1.0     0.0     0.0\n" if pid == BUMP_STOP_PID else "     0.0     0.0     1.0\n")
        for e, (a, b, pid) in enumerate(bars.tolist())
    ))
    parts.append("$ cradle mounts: three translational springs per corner, rail grid to cradle grid\n")
    k_unit = {1: K_MOUNT_XY_N_M, 2: K_MOUNT_XY_N_M, 3: K_MOUNT_Z_N_M}
    for k, (g_rail, g_cradle) in enumerate(named["mounts"]):
        for c in (1, 2, 3):
            eid = 8000 + 10 * (k + 1) + c
            ks = _f16([k_unit[c] * 1e-3], sh["spring"])[0]
            parts.append(_large_card("CELAS2", [f"{eid:16d}", ks, f"{g_rail + 1:16d}", f"{c:16d}",
                                                f"{g_cradle + 1:16d}", f"{c:16d}"]))
    parts.append("$ lumped masses: engine (two) on the cradle, fuel tank on the rear cross member\n")
    for eid, g, m, dz, inertia in (
        (ENGINE_CONM2[0], named["engine"][0], ENGINE_MASS_KG, ENGINE_OFFSET_MM, ENGINE_INERTIA_KG_M2),
        (ENGINE_CONM2[1], named["engine"][1], ENGINE_MASS_KG, ENGINE_OFFSET_MM, ENGINE_INERTIA_KG_M2),
        (TANK_CONM2, named["tank"], TANK_MASS_KG, TANK_OFFSET_MM, TANK_INERTIA_KG_M2),
    ):
        # offset centre of gravity (X3) and rotary inertia I11, I22, I33 (kg m^2 = 1e3 t mm^2)
        i_s = _f16([inertia * 1e3], sh["rotary"])[0]
        zero = f"{0.0:16.1f}"
        parts.append(_large_card("CONM2", [
            f"{eid:16d}", f"{g + 1:16d}", f"{0:16d}", _f16([m * 1e-3], sh["mass"])[0],
            zero, zero, _f16([dz], sh["length"])[0], "",
            i_s, zero, i_s, zero,
            zero, i_s,
        ]))
    parts.append("ENDDATA\n")
    bdf = out / "frame.bdf"
    bdf.write_text("".join(parts))
    params = out / "frame_params.toml"
    params.write_text(_params_toml(bdf.name, units))

    length_mm = np.linalg.norm(xyz[bars[:, 1]] - xyz[bars[:, 0]], axis=1)
    mass = TANK_MASS_KG + 2 * ENGINE_MASS_KG
    for pid, (_, mid, dims) in sections.items():
        rho = RHO_STEEL_KG_M3 if mid == 1 else RHO_ALU_KG_M3
        mass += float(np.sum(length_mm[bars[:, 2] == pid]) * _box(*dims)[0] * 1e-9 * rho)
    return FrameExample(
        bdf=bdf, params=params, units=units, elements_per_member=n, n_grids=len(xyz), n_dof=6 * len(xyz),
        n_elements=len(bars), n_springs=12, mass_kg=mass, gap_mm=gap_mm,
        gap_pairs=tuple((a + 1, b + 1) for a, b in named.get("gap", ())),
    )


def _params_toml(bdf_name: str, units: str) -> str:
    lines = [
        "# Calibration parameters of the frfcal example frame (docs/example-frame.md).",
        "# Physical value P = P0 * (1 + p); lower/upper bound the normalized p.",
        "# Nominal values P0 are read from the deck; see docs/parameters.md.",
        "",
        "[model]",
        f'bdf = "{bdf_name}"',
        f'units = "{units}"',
        "",
    ]
    for name, card, ids, fld, lo, hi, unit, desc in FRAME_PARAMETERS:
        lines.append("[[parameter]]")
        lines.append(f'name = "{name}"')
        lines.append(f'card = "{card}"')
        lines.append(f"id = {ids[0]}" if len(ids) == 1 else f"ids = [{', '.join(str(i) for i in ids)}]")
        lines += [f'field = "{fld}"', f"lower = {lo}", f"upper = {hi}", f'unit = "{unit}"',
                  f'description = "{desc}"', ""]
    return "\n".join(lines)
