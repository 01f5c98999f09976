"""GRID, GRDSET and CORD1x/CORD2x cards: grid positions in basic and resolved coordinate systems."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from femodel._coords import resolve_coords
from femodel._model import CoordSystem, ModelError
from femodel._reader_fields import component_mask, component_string


@dataclass(frozen=True)
class GridSet:
    """Grids of a deck converted to SI and basic, with the lookups the element converters need.

    Parameters
    ----------
    where : str
        The deck path, for error messages.
    ids : (n_grid,) int64
        Sorted grid ids.
    xyz : (n_grid, 3) float
        Positions in basic, m.
    cp, cd : (n_grid,) int64
        Position and displacement coordinate systems (GRDSET defaults applied).
    ps : (n_grid, 6) bool
        Permanent single-point constraints.
    coords : mapping int -> CoordSystem
        Resolved coordinate systems, 0 (basic) included.
    row_of : mapping int -> int
        Row of each grid id in the arrays above.
    cd_axes_cache : dict
        Cache of :meth:`cd_rotation` results keyed by (row, cd); not part of
        the value (excluded from comparison and repr).
    """

    where: str
    ids: np.ndarray
    xyz: np.ndarray
    cp: np.ndarray
    cd: np.ndarray
    ps: np.ndarray
    coords: Mapping[int, CoordSystem]
    row_of: Mapping[int, int] = field(repr=False)
    cd_axes_cache: dict = field(default_factory=dict, compare=False, repr=False)

    def require(self, card: str, eid, ids) -> None:
        """ModelError naming ``card eid`` if any of ``ids`` (None skipped) is not a GRID of the deck."""
        for g in ids:
            if g is not None and int(g) not in self.row_of:
                raise ModelError(f"{self.where}: {card} {eid} references undefined GRID {g}")

    def position(self, gid) -> np.ndarray:
        """(3,) basic position of a grid, m."""
        return self.xyz[self.row_of[int(gid)]]

    def cd_rotation(self, gid) -> np.ndarray:
        """(3, 3) columns = the grid's CD unit vectors in basic (identity for CD 0)."""
        i = self.row_of[int(gid)]
        c = int(self.cd[i])
        if c == 0:
            return np.eye(3)
        if (i, c) not in self.cd_axes_cache:
            self.cd_axes_cache[(i, c)] = self.coords[c].local_axes(self.xyz[i : i + 1])[0]
        return self.cd_axes_cache[(i, c)]


def read_grids(bdf, L: float, where: str) -> GridSet:
    """Convert GRID/GRDSET and the coordinate systems of a parsed deck.

    Parameters
    ----------
    bdf : pyNastran BDF
        The parsed deck (not cross-referenced).
    L : float
        Deck length unit in m.
    where : str
        Deck path for messages.

    Returns
    -------
    GridSet

    Raises
    ------
    ModelError
        No GRID cards, bad PS codes, undefined CP/CD systems, unsupported,
        circular or degenerate coordinate system definitions.
    """
    nids = np.array(sorted(bdf.nodes), dtype=np.int64)
    if nids.size == 0:
        raise ModelError(f"{where}: no GRID cards")
    grdset = getattr(bdf, "grdset", None)
    gs_cp = int(grdset.cp or 0) if grdset is not None else 0
    gs_cd = int(grdset.cd or 0) if grdset is not None else 0
    gs_ps = component_string(grdset.ps) if grdset is not None and grdset.ps else ""
    grids = [bdf.nodes[nid] for nid in nids.tolist()]
    raw = np.zeros((nids.size, 3))
    raw[:] = [g.xyz for g in grids]
    cp = np.array([gs_cp if g.cp in (None, 0) and gs_cp else int(g.cp or 0) for g in grids], np.int64)
    cd = np.array([int((g.cd if g.cd not in (None, 0) else (gs_cd if g.cd is None or g.cd == 0 else 0)) or 0)
                   for g in grids], np.int64)
    codes = [g.ps if g.ps not in (None, "", 0) else gs_ps for g in grids]
    masks = {}  # PS code -> mask (most grids share a code)
    for i, code in enumerate(codes):
        key = (type(code), code)
        if key not in masks:
            try:
                masks[key] = component_mask(code)
            except ValueError:
                raise ModelError(f"{where}: GRID {int(nids[i])}: bad PS component code {grids[i].ps!r}") from None
    ps = np.zeros((nids.size, 6), bool)
    ps[:] = [masks[(type(code), code)] for code in codes]
    raw *= L
    xyz = np.full_like(raw, np.nan)
    xyz[cp == 0] = raw[cp == 0]
    row_of = {int(n): i for i, n in enumerate(nids.tolist())}

    defs = _coord_definitions(bdf, L, where)
    missing = sorted(int(c) for c in np.unique(cp) if c != 0 and c not in defs)
    if missing:
        raise ModelError(f"{where}: GRID CP references undefined coordinate systems {missing}")

    def grid_basic(gid, systems):
        # a CORD1x may use grids given in another (already resolved) system
        i = row_of.get(int(gid))
        if i is None:
            raise ModelError(f"{where}: coordinate system references undefined GRID {gid}")
        c = int(cp[i])
        if c == 0:
            return xyz[i]
        if c not in systems:
            return None
        return _local_to_basic(systems[c], raw[i : i + 1], L)[0]

    try:
        coords = resolve_coords(defs, grid_basic)
    except ModelError as exc:
        msg = str(exc)
        raise ModelError(msg if msg.startswith(where) else f"{where}: {msg}") from None
    for c in np.unique(cp):
        if c == 0:
            continue
        sel = cp == c
        xyz[sel] = _local_to_basic(coords[int(c)], raw[sel], L)
    bad_cd = sorted(set(np.unique(cd).tolist()) - set(coords))
    if bad_cd:
        raise ModelError(f"{where}: GRID CD references undefined coordinate systems {bad_cd}")
    return GridSet(where, nids, xyz, cp, cd, ps, coords, row_of)


def _local_to_basic(system: CoordSystem, raw: np.ndarray, L: float) -> np.ndarray:
    """Basic positions (n, 3) of grids whose coordinates ``raw`` (lengths already in m) are in ``system``.

    Angles of cylindrical/spherical systems were scaled with the lengths and
    are unscaled here.
    """
    loc = raw.copy()
    if system.kind == "C":
        loc[:, 1] /= L
    elif system.kind == "S":
        loc[:, 1:] /= L
    return system.to_basic(loc)


def _coord_definitions(bdf, L: float, where: str) -> dict[int, dict]:
    """CORD1x/CORD2x cards as :func:`femodel._coords.resolve_coords` definitions, CORD2 points in m."""
    defs = {}
    for cid, c in bdf.coords.items():
        if cid == 0:
            continue
        kind = c.type[-1]
        if c.type.startswith("CORD2"):
            pts = np.array([c.e1, c.e2, c.e3], dtype=float)
            defs[int(cid)] = {"kind": kind, "type": 2, "rid": int(c.rid or 0), "points": pts}
        elif c.type.startswith("CORD1"):
            defs[int(cid)] = {"kind": kind, "type": 1, "grids": (int(c.g1), int(c.g2), int(c.g3))}
        else:
            raise ModelError(f"{where}: coordinate system {c.type} {cid} is not supported")
    # CORD2 points are given in the RID system: in a rectangular RID all three
    # are lengths; in a cylindrical RID (r, theta, z) and a spherical RID
    # (r, theta, phi) the angles must not be scaled.
    rid_kind = {cid: d["kind"] for cid, d in defs.items()}
    rid_kind[0] = "R"
    for d in defs.values():
        if d["type"] != 2:
            continue
        rk = rid_kind.get(d["rid"], "R")
        pts = d["points"]
        if rk == "R":
            pts *= L
        elif rk == "C":
            pts[:, [0, 2]] *= L
        else:
            pts[:, 0] *= L
    return defs
