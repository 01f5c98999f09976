"""Effective Independence sensor placement (Kammer 1991), with grouped candidates.

Kammer's method deletes, one at a time, the candidate sensor that contributes
least to the determinant of the Fisher information matrix ``Q = Phi^T Phi`` of
the target modes.  For a single-axis candidate ``i`` the fractional
contribution is the effective-independence value
``E_D[i] = phi_i Q^-1 phi_i^T`` (the diagonal of the projector
``Phi Q^-1 Phi^T``), and deleting it scales ``det Q`` by ``1 - E_D[i]``.
For a group of rows ``B`` deleted together (a triaxial bundle) the block
determinant lemma gives ``det(Q - B^T B) = det(Q) det(I - B Q^-1 B^T)``, so
the group whose ``det(I - E_g)`` is largest is the cheapest to lose.

The inverse ``Q^-1`` and every group's ``E_g`` block are updated after each
deletion with the Woodbury identity (``O(n m k)`` per step for ``n``
candidate rows, ``m`` modes and groups of ``k`` rows) and recomputed exactly
every ``refresh_every`` steps and at every step once fewer than ``4 m`` rows
remain, so thousands of candidates take seconds.

References
----------
D. C. Kammer, "Sensor placement for on-orbit modal identification and
correlation of large space structures", J. Guidance, Control, and Dynamics
14(2), 251-259, 1991.
"""

from __future__ import annotations

import itertools
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
from scipy.linalg import solve_triangular

from pretest._errors import PretestError

__all__ = ["EfIResult", "effective_independence", "exhaustive_best_subset", "fim_logdet"]

#: Relative tolerance under which two deletion scores count as tied; ties are
#: broken by the candidate key so the selection does not depend on the order
#: in which candidates are listed.
_TIE_RTOL = 1e-9


@dataclass(frozen=True)
class EfIResult:
    """Outcome of an Effective Independence selection.

    Attributes
    ----------
    groups : ndarray, shape (n_sensors,)
        Selected candidate groups (indices ``0..n_groups-1`` in the order of
        ``np.unique(group_labels)``), sorted ascending.
    rows : ndarray, shape (n_rows_selected,)
        Rows of the candidate matrix that belong to the selected groups, sorted.
    deletion_order : ndarray, shape (n_deleted,)
        Groups in the order they were deleted (first = least informative).
    group_retention : ndarray, shape (n_sensors,)
        ``det(I - E_g)`` of each selected group in the final set: the factor by
        which ``det Q`` would shrink if that group were removed (0 = essential).
    effective_independence : ndarray, shape (n_rows_selected,)
        ``E_D`` of each selected row in the final set (sums to the rank, n_modes).
    logdet_fim : float
        ``log det(Phi_s^T Phi_s)`` of the selection (natural log).
    n_swaps : int
        Exchanges made to satisfy the minimum-distance constraint.
    """

    groups: np.ndarray
    rows: np.ndarray
    deletion_order: np.ndarray
    group_retention: np.ndarray
    effective_independence: np.ndarray
    logdet_fim: float
    n_swaps: int


def fim_logdet(phi_rows: np.ndarray) -> float:
    """Natural log of ``det(Phi^T Phi)``; ``-inf`` when the rows do not span the modes.

    Parameters
    ----------
    phi_rows : array_like, shape (n_rows, n_modes)
        Mode shapes at the sensor rows.
    """
    phi_rows = np.asarray(phi_rows, dtype=float)
    sign, logdet = np.linalg.slogdet(phi_rows.T @ phi_rows)
    return float(logdet) if sign > 0 else -np.inf


def group_structure(n_rows: int, group_labels) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (unique labels, padded row index table (n_groups, kmax) with -1, row -> group)."""
    if group_labels is None:
        labels = np.arange(n_rows)
        inverse = labels.copy()
    else:
        group_labels = np.asarray(group_labels)
        if group_labels.shape != (n_rows,):
            raise PretestError(
                f"group labels have shape {group_labels.shape}; expected ({n_rows},), one per candidate row"
            )
        labels, inverse = np.unique(group_labels, return_inverse=True)
    n_groups = labels.size
    sizes = np.bincount(inverse, minlength=n_groups)
    kmax = int(sizes.max()) if n_groups else 1
    table = -np.ones((n_groups, kmax), dtype=np.int64)
    order = np.argsort(inverse, kind="stable")
    starts = np.concatenate(([0], np.cumsum(sizes)[:-1]))
    slot = np.arange(n_rows) - np.repeat(starts, sizes)
    table[inverse[order], slot] = order
    return labels, table, inverse


def as_group_indices(values, labels: np.ndarray, what: str) -> np.ndarray:
    if values is None:
        return np.zeros(0, dtype=np.int64)
    values = np.atleast_1d(np.asarray(values))
    idx = np.searchsorted(labels, values)
    idx = np.clip(idx, 0, max(labels.size - 1, 0))
    bad = values[(labels.size == 0) | (labels[idx] != values)] if values.size else values
    if bad.size:
        raise PretestError(f"{what} names candidate group(s) not in the candidate set: {bad.tolist()[:10]}")
    return np.unique(idx)


def _det_i_minus(e: np.ndarray) -> np.ndarray:
    """det(I - E) for a stack of small square blocks, shape (n, k, k) -> (n,)."""
    k = e.shape[1]
    if k == 1:
        return 1.0 - e[:, 0, 0]
    return np.linalg.det(np.eye(k)[None] - e)


def _retentions(blocks: np.ndarray, chol: np.ndarray) -> np.ndarray:
    """det(I - B_g Q^-1 B_g^T) for blocks (n, k, m), Q = chol chol^T."""
    n, k, m = blocks.shape
    x = solve_triangular(chol, blocks.reshape(n * k, m).T, lower=True, check_finite=False)  # (m, n k)
    x = x.T.reshape(n, k, m)
    return _det_i_minus(np.einsum("gkm,glm->gkl", x, x))


def _cholesky(q: np.ndarray) -> np.ndarray | None:
    try:
        return np.linalg.cholesky(q)
    except np.linalg.LinAlgError:
        return None


def effective_independence(
    phi: np.ndarray,
    n_sensors: int,
    *,
    group_labels=None,
    include=None,
    exclude=None,
    positions: np.ndarray | None = None,
    min_distance: float = 0.0,
    keys=None,
    refresh_every: int = 256,
) -> EfIResult:
    """Select sensors by iterative Effective Independence deletion.

    Parameters
    ----------
    phi : array_like, shape (n_rows, n_modes)
        Target mode shapes at the candidate sensor rows (one row per
        single-axis channel: the mode shapes projected on that channel's
        direction).  Any column scaling is allowed: EfI depends only on the
        column space.
    n_sensors : int
        Number of candidate *groups* to keep (a triaxial bundle counts once).
    group_labels : array_like, shape (n_rows,), optional
        Rows with the same label are kept or deleted together (e.g. the three
        rows of a triaxial accelerometer).  Default: every row is its own group.
    include : array_like, optional
        Group labels that must be kept (never deleted).
    exclude : array_like, optional
        Group labels removed before selection.
    positions : array_like, shape (n_rows, 3), optional
        Row coordinates (m); a group's position is the mean of its rows.
        Required when ``min_distance > 0``.
    min_distance : float
        Minimum distance (m) between any two selected groups.  Enforced after
        the backward deletion by exchanges: of a too-close pair the group whose
        removal costs least det(FIM) goes, and the outside group that raises
        det(FIM) most while keeping the distance comes in.
    keys : array_like, shape (n_groups,), optional
        Tie-break keys per group (in ``np.unique(group_labels)`` order); among
        deletion scores equal within 1e-9 relative the smallest key is
        deleted first.  Default: the group labels themselves, which makes the
        result independent of the order the candidates are listed in.
    refresh_every : int
        Recompute ``Q^-1`` and every E block exactly from the remaining rows
        every this many deletions (between, they are updated by Woodbury).

    Returns
    -------
    EfIResult

    Raises
    ------
    PretestError
        When the candidates cannot span the target modes, more sensors are
        asked for than candidates remain, or the constraints cannot be met.
    """
    phi = np.asarray(phi, dtype=float)
    if phi.ndim != 2 or phi.shape[1] == 0:
        raise PretestError(f"mode-shape matrix must be (n_rows, n_modes) with n_modes >= 1, got shape {phi.shape}")
    if not np.all(np.isfinite(phi)):
        raise PretestError("mode-shape matrix contains NaN or infinite values")
    n_rows, n_modes = phi.shape
    labels, table, _ = group_structure(n_rows, group_labels)
    n_groups = labels.size
    n_sensors = int(n_sensors)
    if n_sensors < 1:
        raise PretestError(f"number of sensors must be >= 1, got {n_sensors}")
    inc = as_group_indices(include, labels, "include")
    exc = as_group_indices(exclude, labels, "exclude")
    both = np.intersect1d(inc, exc)
    if both.size:
        raise PretestError(f"candidate(s) both included and excluded: {labels[both].tolist()[:10]}")
    active = np.ones(n_groups, dtype=bool)
    active[exc] = False
    n_avail = int(active.sum())
    if n_sensors > n_avail:
        raise PretestError(
            f"asked for {n_sensors} sensors but only {n_avail} candidate(s) remain"
            + (f" after excluding {exc.size}" if exc.size else "")
        )
    if inc.size > n_sensors:
        raise PretestError(f"{inc.size} must-include candidates exceed the {n_sensors} sensors asked for")
    kmax = table.shape[1]
    if n_sensors * kmax < n_modes:
        raise PretestError(
            f"{n_sensors} sensor(s) of at most {kmax} channel(s) give fewer rows than the "
            f"{n_modes} target modes: Effective Independence needs at least one channel per mode"
        )
    phi_pad = np.where((table >= 0)[:, :, None], phi[np.maximum(table, 0)], 0.0)
    rows_per_group = (table >= 0).sum(axis=1)
    if rows_per_group[active].sum() < n_modes:
        raise PretestError(
            f"{rows_per_group[active].sum()} candidate rows cannot resolve {n_modes} target modes"
        )
    keys = labels if keys is None else np.asarray(keys)
    if keys.shape != (n_groups,):
        raise PretestError(f"keys have shape {keys.shape}; expected ({n_groups},)")
    key_rank = np.empty(n_groups, dtype=np.int64)
    key_rank[np.lexsort((np.arange(n_groups), keys))] = np.arange(n_groups)

    if min_distance and min_distance > 0:
        if positions is None:
            raise PretestError("min_distance needs candidate positions")
        positions = np.asarray(positions, dtype=float)
        if positions.shape != (n_rows, 3):
            raise PretestError(f"positions have shape {positions.shape}; expected ({n_rows}, 3)")

    # Scale the columns: EfI is invariant to it, and it keeps Q well conditioned.
    col = np.linalg.norm(phi[table[active][table[active] >= 0]], axis=0)
    if np.any(col == 0):
        raise PretestError(
            f"target mode(s) {np.flatnonzero(col == 0).tolist()} have zero amplitude at every candidate"
        )
    phi_pad = phi_pad / col
    protected = np.zeros(n_groups, dtype=bool)
    protected[inc] = True
    deletion_order = _backward_deletion(phi_pad, active, protected, n_sensors, key_rank, refresh_every)
    for g in deletion_order:
        active[g] = False

    selected = active.copy()
    n_swaps = 0
    if min_distance and min_distance > 0:
        gpos = np.where((table >= 0)[:, :, None], positions[np.maximum(table, 0)], 0.0).sum(1)
        gpos /= rows_per_group[:, None]
        available = np.ones(n_groups, dtype=bool)
        available[exc] = False
        selected, n_swaps = _enforce_distance(
            phi_pad, selected, available, protected, gpos, float(min_distance), key_rank, labels
        )

    groups = np.flatnonzero(selected)
    blocks = phi_pad[groups]
    chol = _cholesky(np.einsum("gkm,gkn->mn", blocks, blocks))
    retention = _retentions(blocks, chol) if chol is not None else np.zeros(groups.size)
    rows = np.sort(table[groups][table[groups] >= 0])
    sel_phi = phi[rows] / col
    q = sel_phi.T @ sel_phi
    sign, logdet = np.linalg.slogdet(q)
    if sign > 0:
        ed = np.einsum("im,mn,in->i", sel_phi, np.linalg.inv(q), sel_phi)
    else:
        ed = np.full(rows.size, np.nan)
    return EfIResult(
        groups=groups,
        rows=rows,
        deletion_order=np.asarray(deletion_order, dtype=np.int64),
        group_retention=retention,
        effective_independence=ed,
        logdet_fim=fim_logdet(phi[rows]),
        n_swaps=n_swaps,
    )


class _BlockState:
    """Q^-1 and the E blocks of the active candidate groups, updated by Woodbury.

    Works on a compacted copy of the active groups (``ids`` maps back to group
    indices) so each deletion costs O(n_active k m).  E blocks are stored as
    (k, k, n_active) so every update is a handful of contiguous vector ops.
    """

    def __init__(self, phi_pad: np.ndarray, active: np.ndarray, protected: np.ndarray):
        self.phi_pad = phi_pad  # (n_groups, kmax, m), zero rows for padding
        self.active = active
        self.protected = protected
        self.refresh()

    def _compact(self, ids: np.ndarray) -> None:
        self.ids = ids
        self.p = np.ascontiguousarray(self.phi_pad[ids])  # (n_w, k, m)
        # 0 for deletable groups, -inf for protected (must-include) and deleted ones
        self.penalty = np.where(self.protected[ids], -np.inf, 0.0)
        self.n_alive = ids.size

    def refresh(self) -> None:
        """Recompute Q^-1 and every E block exactly from the active rows."""
        self._compact(np.flatnonzero(self.active))
        n_w, k, m = self.p.shape
        self.alive = np.ones(n_w, dtype=bool)
        flat = self.p.reshape(n_w * k, m)
        chol = _cholesky(flat.T @ flat)
        if chol is None:
            self.qinv = None
            return
        linv = solve_triangular(chol, np.eye(m), lower=True, check_finite=False)
        self.qinv = linv.T @ linv
        x = (flat @ linv.T).reshape(n_w, k, m)
        self.e = np.ascontiguousarray(np.einsum("gkm,glm->klg", x, x))

    def pick(self, key_rank: np.ndarray) -> int:
        """The live, unprotected group whose deletion costs least det(Q)."""
        k = self.e.shape[0]
        e = self.e
        if k == 1:
            score = self.penalty - e[0, 0]  # retention 1 - E_D, shifted by -1
            best = score.max()
            cand = np.flatnonzero(score >= best - _TIE_RTOL * max(abs(1.0 + best), 1.0))
            if cand.size == 1:
                return int(self.ids[cand[0]])
            ids = self.ids[cand]
            return int(ids[np.argmin(key_rank[ids])])
        if k == 3:
            a00, a11, a22 = 1.0 - e[0, 0], 1.0 - e[1, 1], 1.0 - e[2, 2]
            score = (
                a00 * (a11 * a22 - e[1, 2] * e[2, 1])
                + e[0, 1] * (-e[1, 0] * a22 - e[1, 2] * e[2, 0])
                - e[0, 2] * (e[1, 0] * e[2, 1] + a11 * e[2, 0])
            )
        else:
            score = _det_i_minus(np.moveaxis(e, -1, 0))
        score += self.penalty
        best = score.max()
        cand = np.flatnonzero(score >= best - _TIE_RTOL * max(abs(best), 1.0))
        if cand.size == 1:
            return int(self.ids[cand[0]])
        ids = self.ids[cand]
        return int(ids[np.argmin(key_rank[ids])])

    def delete(self, g: int) -> None:
        self.active[g] = False
        w_idx = int(np.searchsorted(self.ids, g))
        self.alive[w_idx] = False
        self.penalty[w_idx] = -np.inf
        self.n_alive -= 1
        b = self.p[w_idx]  # (k, m)
        n_w, k, m = self.p.shape
        if k == 1:
            s = 1.0 - self.e[0, 0, w_idx]
            if not s > 0:
                self.qinv = None
                return
            w = self.qinv @ b[0]
            self.qinv += np.outer(w, w) / s
            v = self.p[:, 0, :] @ w
            self.e[0, 0] += v * v / s
        else:
            s = np.eye(k) - self.e[:, :, w_idx]
            w = self.qinv @ b.T  # (m, k)
            try:
                s_inv = np.linalg.inv(s)
            except np.linalg.LinAlgError:
                self.qinv = None
                return
            self.qinv = self.qinv + w @ s_inv @ w.T
            v = self.p.reshape(n_w * k, m) @ w  # rows (g, a), columns j
            vs = v @ s_inv
            vt = np.ascontiguousarray(v.reshape(n_w, k, k).transpose(1, 2, 0))  # (a, j, g)
            vst = np.ascontiguousarray(vs.reshape(n_w, k, k).transpose(1, 2, 0))
            for a in range(k):
                for c in range(a, k):
                    upd = (vst[a] * vt[c]).sum(axis=0)
                    self.e[a, c] += upd
                    if c != a:
                        self.e[c, a] += upd
        if self.n_alive < 0.6 * self.alive.size:
            keep = self.alive
            self._compact(self.ids[keep])
            self.e = np.ascontiguousarray(self.e[:, :, keep])
            self.alive = np.ones(self.ids.size, dtype=bool)


@contextmanager
def _one_blas_thread():
    """The deletion loop is thousands of tiny BLAS calls: threads only add sync cost."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        yield
        return
    with threadpool_limits(limits=1, user_api="blas"):
        yield


def _backward_deletion(phi_pad, active, protected, n_keep, key_rank, refresh_every) -> list[int]:
    """Greedy backward EfI deletion; returns the deleted groups in order."""
    with _one_blas_thread():
        return _backward_deletion_loop(phi_pad, active, protected, n_keep, key_rank, refresh_every)


def _backward_deletion_loop(phi_pad, active, protected, n_keep, key_rank, refresh_every) -> list[int]:
    state = _BlockState(phi_pad, active.copy(), protected)
    n_modes = phi_pad.shape[2]
    if state.qinv is None:
        rank = np.linalg.matrix_rank(phi_pad[active].reshape(-1, n_modes))
        raise PretestError(
            f"the candidate set cannot distinguish the target modes: Fisher information rank {rank} < {n_modes} modes"
        )
    rows_per_group = np.count_nonzero(np.any(phi_pad != 0, axis=2), axis=1)
    small = 4 * n_modes
    n_active = int(active.sum())
    rows_active = int(rows_per_group[active].sum())
    order: list[int] = []
    step = 0
    while n_active > n_keep:
        if state.qinv is None or step % max(refresh_every, 1) == 0 or rows_active <= small:
            state.refresh()
            if state.qinv is None:
                raise PretestError(
                    "Fisher information became singular during deletion: the remaining candidates "
                    "cannot distinguish the target modes"
                )
        g = state.pick(key_rank)
        order.append(g)
        state.delete(g)
        step += 1
        n_active -= 1
        rows_active -= int(rows_per_group[g])
    return order


def _group_logdets(phi_pad: np.ndarray, base_q: np.ndarray, candidates: np.ndarray, chunk: int = 4096) -> np.ndarray:
    """log det(base_q + B_c^T B_c) for each candidate group c (-inf if singular)."""
    out = np.empty(candidates.size)
    for start in range(0, candidates.size, chunk):
        idx = candidates[start : start + chunk]
        b = phi_pad[idx]
        mats = base_q[None] + np.einsum("gkm,gkn->gmn", b, b)
        sign, ld = np.linalg.slogdet(mats)
        out[start : start + chunk] = np.where(sign > 0, ld, -np.inf)
    return out


def _enforce_distance(phi_pad, selected, active, protected, gpos, dmin, key_rank, labels):
    """Exchange groups until every selected pair is at least dmin apart."""
    selected = selected.copy()
    prot_idx = np.flatnonzero(protected)
    if prot_idx.size > 1:
        d = np.linalg.norm(gpos[prot_idx, None] - gpos[None, prot_idx], axis=-1)
        np.fill_diagonal(d, np.inf)
        i, j = np.unravel_index(np.argmin(d), d.shape)
        if d[i, j] < dmin:
            raise PretestError(
                f"must-include candidates {labels[prot_idx[i]]} and {labels[prot_idx[j]]} are "
                f"{d[i, j]:.4g} m apart, closer than the minimum distance {dmin:.4g} m"
            )
    n_swaps = 0
    max_swaps = 10 * max(int(selected.sum()), 1)
    while True:
        sel = np.flatnonzero(selected)
        d = np.linalg.norm(gpos[sel, None] - gpos[None, sel], axis=-1)
        np.fill_diagonal(d, np.inf)
        conflicts = (d < dmin).sum(axis=1)
        if not conflicts.any():
            return selected, n_swaps
        if n_swaps >= max_swaps:
            raise PretestError(f"could not satisfy the minimum distance {dmin:.4g} m after {n_swaps} exchanges")
        blocks = phi_pad[sel]
        q = np.einsum("gkm,gkn->mn", blocks, blocks)
        # Remove the conflicting, non-protected group whose loss costs least.
        removable = sel[(conflicts > 0) & ~protected[sel]]
        if removable.size == 0:
            raise PretestError(f"must-include candidates violate the minimum distance {dmin:.4g} m")
        without = np.array([_slogdet_or_inf(q - phi_pad[r].T @ phi_pad[r]) for r in removable])
        best = without.max()
        tied = removable[without >= best - _TIE_RTOL * max(abs(best), 1.0)] if np.isfinite(best) else removable
        r = int(tied[np.argmin(key_rank[tied])])
        selected[r] = False
        q_r = q - phi_pad[r].T @ phi_pad[r]
        sel = np.flatnonzero(selected)
        outside = np.flatnonzero(active & ~selected)
        outside = outside[outside != r]
        if sel.size:
            dist = np.linalg.norm(gpos[outside, None] - gpos[None, sel], axis=-1).min(axis=1)
            outside = outside[dist >= dmin]
        if outside.size == 0:
            raise PretestError(
                f"no candidate left at least {dmin:.4g} m from the chosen sensors; "
                "lower --min-distance or ask for fewer sensors"
            )
        gain = _group_logdets(phi_pad, q_r, outside)
        if not np.isfinite(gain.max()):
            # The reduced set is rank deficient for every addition; rank by the
            # regularized determinant so the choice is still informative.
            eps = 1e-12 * np.trace(q)
            gain = _group_logdets(phi_pad, q_r + eps * np.eye(q.shape[0]), outside)
        best = gain.max()
        tied = outside[gain >= best - _TIE_RTOL * max(abs(best), 1.0)]
        a = int(tied[np.argmin(key_rank[tied])])
        selected[a] = True
        n_swaps += 1


def _slogdet_or_inf(q: np.ndarray) -> float:
    sign, ld = np.linalg.slogdet(q)
    return float(ld) if sign > 0 else -np.inf


def exhaustive_best_subset(phi: np.ndarray, n_sensors: int, *, group_labels=None, max_subsets: int = 2_000_000):
    """Best subset by det(FIM) over every choice of ``n_sensors`` groups (brute force).

    Parameters
    ----------
    phi : array_like, shape (n_rows, n_modes)
    n_sensors : int
    group_labels : array_like, shape (n_rows,), optional
    max_subsets : int
        Refuse problems with more subsets than this.

    Returns
    -------
    groups : ndarray, shape (n_sensors,)
        Best groups (indices in ``np.unique(group_labels)`` order).
    logdet : float
        Its ``log det(Phi_s^T Phi_s)``.
    all_logdets : ndarray, shape (n_subsets,)
        Log-determinant of every subset (for ranking the greedy choice).
    """
    phi = np.asarray(phi, dtype=float)
    labels, table, _ = group_structure(phi.shape[0], group_labels)
    from math import comb

    n_sub = comb(labels.size, n_sensors)
    if n_sub > max_subsets:
        raise PretestError(f"{n_sub} subsets exceed the brute-force limit {max_subsets}")
    phi_pad = np.where((table >= 0)[:, :, None], phi[np.maximum(table, 0)], 0.0)
    contrib = np.einsum("gkm,gkn->gmn", phi_pad, phi_pad)  # per-group FIM
    combos = np.array(list(itertools.combinations(range(labels.size), n_sensors)), dtype=np.int64)
    logdets = np.empty(len(combos))
    chunk = 20000
    for s in range(0, len(combos), chunk):
        c = combos[s : s + chunk]
        q = contrib[c].sum(axis=1)
        sign, ld = np.linalg.slogdet(q)
        logdets[s : s + chunk] = np.where(sign > 0, ld, -np.inf)
    best = int(np.argmax(logdets))
    return combos[best], float(logdets[best]), logdets
