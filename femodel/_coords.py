"""Coordinate systems: resolve CORD1x/CORD2x cards to origins and axes in basic."""

from __future__ import annotations

import numpy as np

from femodel._model import CoordSystem, ModelError


def axes_from_points(a: np.ndarray, b: np.ndarray, c: np.ndarray, what: str) -> np.ndarray:
    """Rows e1, e2, e3 from Nastran's three points (origin, +z point, xz-plane point), in basic.

    Raises
    ------
    ModelError
        When the points are coincident or collinear (``what`` names the card).
    """
    z = b - a
    nz = np.linalg.norm(z)
    if nz == 0.0:
        raise ModelError(f"{what}: points A and B coincide")
    e3 = z / nz
    y = np.cross(e3, c - a)
    ny = np.linalg.norm(y)
    if ny <= 1e-12 * max(nz, np.linalg.norm(c - a)):
        raise ModelError(f"{what}: point C lies on the z axis (A-B line)")
    e2 = y / ny
    e1 = np.cross(e2, e3)
    return np.vstack([e1, e2, e3])


def resolve_coords(defs: dict[int, dict], grid_xyz_basic) -> dict[int, CoordSystem]:
    """Resolve coordinate system definitions, in dependency order.

    Parameters
    ----------
    defs : dict cid -> definition
        ``{"kind": "R"|"C"|"S", "type": 2, "rid": int, "points": (3, 3) in RID's
        coordinates (already in SI length)}`` for CORD2x, or ``{"kind": ..,
        "type": 1, "grids": (g1, g2, g3)}`` for CORD1x.
    grid_xyz_basic : callable(grid_id, systems) -> (3,) basic position or None
        Looks up a grid's basic position given the systems resolved so far
        (``systems``: dict cid -> CoordSystem); None while the grid's own
        position system is not yet resolved.  A CORD1x may so use grids
        positioned in other CORD1x/CORD2x systems, as in Nastran.

    Returns
    -------
    dict cid -> CoordSystem, including 0 (basic).
    """
    out: dict[int, CoordSystem] = {0: CoordSystem(0, "R", np.zeros(3), np.eye(3))}
    pending = dict(defs)
    while pending:
        progress = False
        for cid, d in list(pending.items()):
            name = f"CORD{d['type']}{d['kind']} {cid}"
            if d["type"] == 2:
                rid = d["rid"]
                if rid not in out:
                    if rid not in pending:
                        raise ModelError(f"{name}: reference system RID {rid} is not defined")
                    continue
                pts = out[rid].to_basic(np.asarray(d["points"], dtype=float))
            else:
                pts = [grid_xyz_basic(g, out) for g in d["grids"]]
                if any(p is None for p in pts):
                    continue
                pts = np.asarray(pts)
            axes = axes_from_points(pts[0], pts[1], pts[2], name)
            out[cid] = CoordSystem(cid, d["kind"], pts[0].copy(), axes)
            del pending[cid]
            progress = True
        if not progress:
            raise ModelError(f"coordinate systems {sorted(pending)} cannot be resolved (circular or missing references)")
    return out
