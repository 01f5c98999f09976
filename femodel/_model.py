"""The FE model as plain arrays: what the reader produces and assembly consumes.

Everything here is already converted to SI and (for geometry) to the basic
coordinate system.  Displacement components of a grid are in its displacement
(CD) system, as in Nastran's g-set.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np


class ModelError(ValueError):
    """Bad or unsupported model input; the message names the file, card and id at fault."""


@dataclass(frozen=True)
class CoordSystem:
    """A resolved coordinate system.

    Parameters
    ----------
    cid : int
        Coordinate system id (0 is basic).
    kind : str
        "R" (rectangular), "C" (cylindrical) or "S" (spherical).
    origin : (3,) float
        Origin in basic coordinates, m.
    axes : (3, 3) float
        Rows are the unit vectors e1, e2, e3 of the system in basic.
    """

    cid: int
    kind: str
    origin: np.ndarray
    axes: np.ndarray

    def to_basic(self, xyz_local: np.ndarray) -> np.ndarray:
        """Positions given in this system (n, 3) (r/theta[deg]/z etc.) -> basic (n, 3), m."""
        x = np.atleast_2d(np.asarray(xyz_local, dtype=float))
        if self.kind == "C":
            r, th, z = x[:, 0], np.radians(x[:, 1]), x[:, 2]
            x = np.column_stack([r * np.cos(th), r * np.sin(th), z])
        elif self.kind == "S":
            r, th, ph = x[:, 0], np.radians(x[:, 1]), np.radians(x[:, 2])
            x = np.column_stack([r * np.sin(th) * np.cos(ph), r * np.sin(th) * np.sin(ph), r * np.cos(th)])
        return self.origin + x @ self.axes

    def local_axes(self, xyz_basic: np.ndarray) -> np.ndarray:
        """Unit vectors of the (possibly curvilinear) system at basic points.

        Returns
        -------
        (n, 3, 3) float
            ``R[i]`` has the local unit directions as columns in basic, so that
            ``v_basic = R[i] @ v_local``.
        """
        x = np.atleast_2d(np.asarray(xyz_basic, dtype=float))
        n = x.shape[0]
        a = self.axes.T  # columns e1 e2 e3
        if self.kind == "R":
            return np.broadcast_to(a, (n, 3, 3)).copy()
        loc = (x - self.origin) @ self.axes.T  # rectangular components in this system
        if self.kind == "C":
            th = np.arctan2(loc[:, 1], loc[:, 0])
            c, s = np.cos(th), np.sin(th)
            z0 = np.zeros(n)
            er = np.column_stack([c, s, z0])
            et = np.column_stack([-s, c, z0])
            ez = np.column_stack([z0, z0, z0 + 1.0])
            local = np.stack([er, et, ez], axis=2)
        else:
            r = np.linalg.norm(loc, axis=1)
            rho = np.hypot(loc[:, 0], loc[:, 1])
            th = np.arctan2(rho, loc[:, 2])
            ph = np.arctan2(loc[:, 1], loc[:, 0])
            st, ct, sp_, cp = np.sin(th), np.cos(th), np.sin(ph), np.cos(ph)
            er = np.column_stack([st * cp, st * sp_, ct])
            et = np.column_stack([ct * cp, ct * sp_, -st])
            ep = np.column_stack([-sp_, cp, np.zeros(n)])
            local = np.stack([er, et, ep], axis=2)
            del r
        return np.einsum("ij,njk->nik", a, local)


@dataclass(frozen=True)
class Table:
    """A card table: ids plus named field arrays of the same length.

    Parameters
    ----------
    card : str
        Card name ("CBAR", "PSHELL", "MAT1", ...).
    ids : (n,) int64
        Element, property or material ids.
    fields : mapping of str to (n, ...) arrays
        Converted values (SI, basic coordinates where geometric).
    """

    card: str
    ids: np.ndarray
    fields: Mapping[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def __getitem__(self, name: str) -> np.ndarray:
        try:
            return self.fields[name]
        except KeyError:
            raise ModelError(f"{self.card} table has no field {name!r}") from None

    def rows(self, ids, owners=None) -> np.ndarray:
        """Row indices of ``ids`` in this table; ModelError naming missing ids (and, given ``owners``, the ids
        of the cards aligned with ``ids`` that reference them, e.g. the elements of a property id)."""
        ids = np.asarray(ids, dtype=np.int64)
        order = np.argsort(self.ids, kind="stable")
        pos = np.searchsorted(self.ids, ids, sorter=order)
        pos = np.clip(pos, 0, max(len(self) - 1, 0))
        idx = order[pos] if len(self) else pos
        bad = (len(self) == 0) | (self.ids[idx] != ids) if len(self) else np.ones(ids.shape, bool)
        if np.any(bad):
            missing = sorted(set(ids[bad].tolist()))[:10]
            by = ""
            if owners is not None:
                who = np.asarray(owners)[bad]
                by = f" by element(s) {who[:5].tolist()}{f' and {who.size - 5} more' if who.size > 5 else ''}"
            raise ModelError(f"{self.card} id(s) {missing} referenced{by} but not defined")
        return idx


@dataclass(frozen=True)
class RBE2:
    """Rigid element: all ``components`` of grids ``gm`` follow grid ``gn`` rigidly."""

    eid: int
    gn: int
    components: str
    gm: tuple[int, ...]


@dataclass(frozen=True)
class RBE3:
    """Interpolation element: ``refc`` of ``refgrid`` = weighted average of the groups.

    ``groups`` holds (weight, components, grids) triples.
    """

    eid: int
    refgrid: int
    refc: str
    groups: tuple[tuple[float, str, tuple[int, ...]], ...]


@dataclass(frozen=True)
class FEModel:
    """A Nastran model converted to SI arrays.

    Attributes
    ----------
    path : str or None
        The deck it was read from.
    units : str
        Declared unit system of the deck ("si", "mm-t-s", ...); arrays are SI.
    grid_ids : (n_grid,) int64
    xyz : (n_grid, 3) float
        Grid positions in basic coordinates, m.
    cp, cd : (n_grid,) int64
        Position and displacement coordinate systems of each grid.
    ps : (n_grid, 6) bool
        Permanent single-point constraints from GRID/GRDSET PS.
    coords : mapping int -> CoordSystem
        Resolved coordinate systems (0 = basic always present).
    elements : mapping str -> Table
        Element tables by card name; fields "pid", "nodes" (n, nn) grid ids,
        plus card-specific ones (orientation "v" (n, 3) basic, offsets
        "wa"/"wb" (n, 3) basic m, CONM2 "mass" kg, "offset" m, "inertia"
        (n, 3, 3) kg m^2 in basic, CELAS "k", "c1", "c2", ...).
    properties : mapping str -> Table
        Property tables (PSHELL, PBAR (PBARL/PBEAML/PBEAM resolved to section
        values), PROD, PELAS, PBUSH, PSOLID), SI.
    materials : mapping str -> Table
        "MAT1" with fields E, G, NU, RHO (SI) and g_follows_e (bool).
    rbe2, rbe3 : tuple
        Rigid elements.
    mpc : tuple of (sid, ((grid, component, coefficient), ...))
        Multipoint constraints of the case-control MPC set; the first term's
        DOF is the dependent one (as Nastran's m-set).
    spc_grid, spc_component : (k,) int64 / int8
        Single-point constraints of the active set (components in CD).
    wtmass : float
        PARAM,WTMASS (applied to every mass term at assembly).
    coupmass : bool
        PARAM,COUPMASS > 0: consistent instead of lumped mass.
    k6rot : float
        PARAM,K6ROT (shell drilling stiffness factor).
    ignored_cards : mapping str -> int
        Unsupported cards skipped under ``allow_unsupported=True``.
    """

    path: str | None
    units: str
    grid_ids: np.ndarray
    xyz: np.ndarray
    cp: np.ndarray
    cd: np.ndarray
    ps: np.ndarray
    coords: Mapping[int, CoordSystem]
    elements: Mapping[str, Table]
    properties: Mapping[str, Table]
    materials: Mapping[str, Table]
    rbe2: tuple = ()
    rbe3: tuple = ()
    mpc: tuple = ()
    spc_grid: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    spc_component: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int8))
    wtmass: float = 1.0
    coupmass: bool = False
    k6rot: float = 100.0
    ignored_cards: Mapping[str, int] = field(default_factory=dict)

    @property
    def n_grids(self) -> int:
        return int(self.grid_ids.shape[0])

    def grid_index(self, grids, *, what: str = "grid") -> np.ndarray:
        """Row index of each grid id; ModelError naming the missing ids."""
        grids = np.atleast_1d(np.asarray(grids, dtype=np.int64))
        pos = np.searchsorted(self.grid_ids, grids)
        pos = np.clip(pos, 0, self.n_grids - 1)
        bad = self.grid_ids[pos] != grids
        if np.any(bad):
            missing = sorted(set(grids[bad].tolist()))[:10]
            src = f" in {self.path}" if self.path else ""
            raise ModelError(f"{what} {missing} not defined{src}")
        return pos

    def cd_axes(self) -> np.ndarray:
        """(n_grid, 3, 3): columns are each grid's CD unit vectors in basic."""
        out = np.broadcast_to(np.eye(3), (self.n_grids, 3, 3)).copy()
        for cid in np.unique(self.cd):
            if cid == 0:
                continue
            sel = self.cd == cid
            out[sel] = self.coords[int(cid)].local_axes(self.xyz[sel])
        return out
