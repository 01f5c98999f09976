"""Candidate sensor and drive sets on an FE model: grids, directions, target modes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pretest._errors import PretestError

__all__ = [
    "CandidateSet",
    "candidate_grids",
    "surface_normals",
    "candidate_set",
    "parse_direction",
    "select_target_modes",
]

_SHELLS = ("CQUAD4", "CTRIA3", "CQUAD8", "CTRIA6", "CQUADR", "CTRIAR")
_EDGE_RATIO = 0.25  # second/first eigenvalue of sum(n n^T) above which a grid is on an edge
_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


@dataclass(frozen=True)
class CandidateSet:
    """Single-axis candidate channels on a model, possibly bundled.

    Attributes
    ----------
    grids : ndarray, shape (n_rows,)
        Grid id of each candidate channel.
    directions : ndarray, shape (n_rows, 3)
        Unit measuring direction of each channel, basic system.
    xyz_m : ndarray, shape (n_rows, 3)
        Channel position (its grid's), basic system, m.
    group : ndarray, shape (n_rows,)
        Bundle label: rows with the same label are one physical sensor
        (a triaxial accelerometer); for single-axis sets each row is its own.
    axis : ndarray, shape (n_rows,)
        Axis label within a bundle ("x", "y", "z", "n" for a normal, "v" for a
        given vector).
    """

    grids: np.ndarray
    directions: np.ndarray
    xyz_m: np.ndarray
    group: np.ndarray
    axis: np.ndarray

    @property
    def n_rows(self) -> int:
        return int(self.grids.size)

    def rows_of_grids(self, grids) -> np.ndarray:
        """Row indices of every channel on the given grids (PretestError if none)."""
        grids = np.atleast_1d(np.asarray(grids, dtype=np.int64))
        missing = np.setdiff1d(grids, self.grids)
        if missing.size:
            raise PretestError(f"grid(s) {missing.tolist()[:10]} are not in the candidate set")
        return np.flatnonzero(np.isin(self.grids, grids))

    def subset(self, rows) -> "CandidateSet":
        rows = np.asarray(rows, dtype=np.int64)
        return CandidateSet(self.grids[rows], self.directions[rows], self.xyz_m[rows], self.group[rows], self.axis[rows])


def _element_tables(model, cards=None):
    for card, table in model.elements.items():
        if cards is not None and card not in cards:
            continue
        if "nodes" in table.fields and len(table):
            yield card, table


def _check_grids(model, grids, what: str) -> np.ndarray:
    grids = np.unique(np.atleast_1d(np.asarray(grids, dtype=np.int64)))
    missing = np.setdiff1d(grids, model.grid_ids)
    if missing.size:
        src = f" in {model.path}" if getattr(model, "path", None) else ""
        raise PretestError(f"{what} grid(s) {missing.tolist()[:10]} not defined{src}")
    return grids


def candidate_grids(model, *, grids=None, pids=None, box_m=None) -> np.ndarray:
    """Grid ids eligible for sensors.

    Parameters
    ----------
    model : femodel.FEModel
    grids : array_like of int, optional
        Explicit grid ids (each must exist in the model).
    pids : array_like of int, optional
        Property ids: grids of every element (shell, solid, bar) with these PIDs.
    box_m : array_like, shape (2, 3) or (6,), optional
        ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]`` in basic coordinates, m.

    Returns
    -------
    ndarray of int64
        Sorted unique grid ids.  With no selector: every grid attached to a
        shell element, or to any element when the model has no shells.  The
        selectors intersect.
    """
    sel = None
    if grids is not None:
        sel = _check_grids(model, grids, "candidate")
    if pids is not None:
        pids = np.unique(np.atleast_1d(np.asarray(pids, dtype=np.int64)))
        found = []
        seen = set()
        for _, table in _element_tables(model):
            if "pid" not in table.fields:
                continue
            mask = np.isin(table["pid"], pids)
            seen.update(np.unique(table["pid"][mask]).tolist())
            nodes = np.asarray(table["nodes"])[mask]
            found.append(nodes[nodes > 0])
        missing = sorted(set(pids.tolist()) - seen)
        if missing:
            raise PretestError(f"property id(s) {missing[:10]} have no elements in {model.path or 'the model'}")
        g = np.unique(np.concatenate(found)) if found else np.zeros(0, np.int64)
        sel = g if sel is None else np.intersect1d(sel, g)
    if sel is None:
        shells = [np.asarray(t["nodes"]).ravel() for _, t in _element_tables(model, _SHELLS)]
        if not shells:
            shells = [np.asarray(t["nodes"]).ravel() for _, t in _element_tables(model)]
        allg = np.concatenate(shells) if shells else model.grid_ids
        sel = np.unique(allg[allg > 0])
    if box_m is not None:
        box = np.asarray(box_m, dtype=float).reshape(2, 3)
        if np.any(box[0] > box[1]):
            raise PretestError(f"candidate box min {box[0].tolist()} exceeds max {box[1].tolist()} (m)")
        xyz = model.xyz[model.grid_index(sel)]
        inside = np.all((xyz >= box[0]) & (xyz <= box[1]), axis=1)
        sel = sel[inside]
    if sel.size == 0:
        raise PretestError("the candidate selection (grids/PIDs/box) contains no grid")
    return sel


def surface_normals(model, grids) -> np.ndarray:
    """Local surface normal at grids: average of the attached shell elements' normals.

    Element normals are averaged as the sign-free tensor ``sum n n^T`` (its
    dominant eigenvector), so inconsistently oriented neighbours do not cancel;
    the sign is chosen so that the largest component is positive.

    Parameters
    ----------
    model : femodel.FEModel
    grids : array_like of int, shape (n,)

    Returns
    -------
    ndarray, shape (n, 3)
        Unit normals, basic system.

    Raises
    ------
    PretestError
        Naming grids that belong to no shell element.
    """
    grids = np.atleast_1d(np.asarray(grids, dtype=np.int64))
    gi = model.grid_index(grids)
    tensor = np.zeros((model.n_grids, 3, 3))
    count = np.zeros(model.n_grids)
    corner_grid, corner_normal = [], []
    for card, table in _element_tables(model, _SHELLS):
        nodes = np.asarray(table["nodes"])
        corner = 3 if card.startswith("CTRIA") else 4
        nodes = nodes[:, :corner]
        idx = model.grid_index(nodes.ravel()).reshape(nodes.shape)
        p = model.xyz[idx]
        if corner == 4:
            n = np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1])
        else:
            n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        norm = np.linalg.norm(n, axis=1)
        ok = norm > 0
        n = n[ok] / norm[ok, None]
        nn = np.einsum("ei,ej->eij", n, n)
        for c in range(corner):
            np.add.at(tensor, idx[ok, c], nn)
            np.add.at(count, idx[ok, c], 1.0)
            corner_grid.append(idx[ok, c])
            corner_normal.append(n)
    lonely = grids[count[gi] == 0]
    if lonely.size:
        raise PretestError(
            f"grid(s) {lonely.tolist()[:10]} belong to no shell element: no surface normal; "
            "choose a direction (x, y, z or a vector) or triaxial sensors there"
        )
    w, v = np.linalg.eigh(tensor[gi])
    normal = v[:, :, -1]
    # On an edge or corner where faces meet at an angle (second eigenvalue of
    # the tensor comparable to the first) the principal direction is a
    # non-physical mix; a sensor sits on one face, so take the attached
    # element normal best aligned with it.
    edge = w[:, -2] > _EDGE_RATIO * w[:, -1]
    if np.any(edge):
        cg = np.concatenate(corner_grid)
        cn = np.concatenate(corner_normal)
        slot = -np.ones(model.n_grids, dtype=np.int64)
        slot[gi[edge]] = np.arange(int(edge.sum()))
        keep = slot[cg] >= 0
        cg, cn = slot[cg[keep]], cn[keep]
        score = np.abs(np.einsum("ei,ei->e", cn, normal[edge][cg]))
        order = np.lexsort((score, cg))
        last = np.r_[cg[order][1:] != cg[order][:-1], True]
        best = np.empty((int(edge.sum()), 3))
        best[cg[order][last]] = cn[order][last]
        normal[edge] = best
    big = np.argmax(np.abs(normal), axis=1)
    sign = np.sign(normal[np.arange(normal.shape[0]), big])
    return normal * sign[:, None]


def parse_direction(text):
    """A direction option: ``"normal"``, ``"x"``/``"y"``/``"z"`` or ``"vx,vy,vz"`` (or a 3-vector).

    Returns the string ``"normal"`` or a unit ndarray of shape (3,).
    """
    if isinstance(text, str):
        t = text.strip().lower()
        if t == "normal":
            return "normal"
        if t in _AXES:
            return np.array(_AXES[t])
        try:
            vec = np.array([float(x) for x in t.split(",")])
        except ValueError:
            raise PretestError(f"direction {text!r}: use normal, x, y, z or three numbers vx,vy,vz") from None
    else:
        vec = np.asarray(text, dtype=float)
    if vec.shape != (3,) or not np.all(np.isfinite(vec)) or np.linalg.norm(vec) == 0:
        raise PretestError(f"direction {text!r} must be a non-zero 3-vector")
    return vec / np.linalg.norm(vec)


def candidate_set(model, grids, *, direction="normal", triax: bool = False) -> CandidateSet:
    """Candidate channels at ``grids``.

    Parameters
    ----------
    model : femodel.FEModel
    grids : array_like of int
    direction : "normal", "x", "y", "z", "vx,vy,vz" or a 3-vector
        Measuring direction of single-axis sensors (ignored with ``triax``).
    triax : bool
        Triaxial bundles: three rows (basic x, y, z) per grid, kept together.

    Returns
    -------
    CandidateSet
    """
    grids = _check_grids(model, grids, "candidate")
    xyz = model.xyz[model.grid_index(grids)]
    if triax:
        g = np.repeat(grids, 3)
        d = np.tile(np.eye(3), (grids.size, 1))
        return CandidateSet(g, d, np.repeat(xyz, 3, axis=0), g.copy(), np.tile(np.array(["x", "y", "z"]), grids.size))
    parsed = parse_direction(direction)
    if isinstance(parsed, str):
        d = surface_normals(model, grids)
        axis = "n"
    else:
        d = np.broadcast_to(parsed, (grids.size, 3)).copy()
        axis = {tuple(v): k for k, v in _AXES.items()}.get(tuple(np.round(parsed, 15)), "v")
    return CandidateSet(grids, d, xyz, grids.copy(), np.full(grids.size, axis))


def select_target_modes(frequencies_hz, n_rigid: int, *, n_modes=None, band_hz=None, mode_numbers=None) -> np.ndarray:
    """Indices of the target modes among computed modes.

    Parameters
    ----------
    frequencies_hz : array_like, shape (n_computed,)
        Ascending natural frequencies.
    n_rigid : int
        Leading rigid-body modes (never targets unless named in ``mode_numbers``).
    n_modes : int, optional
        The first ``n_modes`` elastic modes (default when nothing else is given: 20).
    band_hz : (float, float), optional
        Every elastic mode with ``lo <= f <= hi``.
    mode_numbers : array_like of int, optional
        1-based mode numbers (Nastran numbering, rigid modes included).

    Returns
    -------
    ndarray of int
        0-based indices.
    """
    f = np.asarray(frequencies_hz, dtype=float)
    given = sum(x is not None for x in (n_modes, band_hz, mode_numbers))
    if given > 1:
        raise PretestError("give only one of: number of modes, a frequency band, a list of mode numbers")
    elastic = np.arange(int(n_rigid), f.size)
    if mode_numbers is not None:
        nums = np.atleast_1d(np.asarray(mode_numbers, dtype=np.int64))
        bad = nums[(nums < 1) | (nums > f.size)]
        if bad.size:
            raise PretestError(f"mode number(s) {bad.tolist()} outside 1..{f.size} computed modes")
        return np.unique(nums - 1)
    if band_hz is not None:
        lo, hi = (float(x) for x in band_hz)
        if not lo <= hi:
            raise PretestError(f"frequency band [{lo}, {hi}] Hz is empty")
        idx = elastic[(f[elastic] >= lo) & (f[elastic] <= hi)]
        if idx.size == 0:
            raise PretestError(f"no elastic mode in the band {lo:g}-{hi:g} Hz")
        return idx
    n = 20 if n_modes is None else int(n_modes)
    if n < 1:
        raise PretestError(f"number of target modes must be >= 1, got {n}")
    if elastic.size < n:
        raise PretestError(f"asked for {n} elastic modes but only {elastic.size} were computed")
    return elastic[:n]
