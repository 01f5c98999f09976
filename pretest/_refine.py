"""AutoMAC refinement of a sensor layout by single exchanges.

Effective Independence maximizes det(FIM); it does not look at the autoMAC,
and with as many sensors as target modes some pairs of modes often stay
correlated at the sensors.  This local search swaps one sensor group at a time
for the outside candidate that lowers the largest off-diagonal autoMAC most,
while keeping ``det(FIM)`` within a stated factor of the starting layout's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pretest._efi import as_group_indices, group_structure
from pretest._errors import PretestError

__all__ = ["RefineResult", "refine_automac"]


@dataclass(frozen=True)
class RefineResult:
    """Outcome of :func:`refine_automac`.

    Attributes
    ----------
    groups : ndarray, shape (n_sensors,)
        Selected groups after refinement (``np.unique(group_labels)`` order), sorted.
    rows : ndarray
        Their candidate rows, sorted.
    n_swaps : int
    automac_before, automac_after : float
        Largest off-diagonal autoMAC of the starting and the refined layout.
    log10_det_before, log10_det_after : float
        ``log10 det(Phi_s^T Phi_s)`` of both.
    """

    groups: np.ndarray
    rows: np.ndarray
    n_swaps: int
    automac_before: float
    automac_after: float
    log10_det_before: float
    log10_det_after: float


def _max_offdiag_mac(g: np.ndarray) -> np.ndarray:
    """Largest off-diagonal autoMAC from Gram matrices (..., m, m)."""
    d = np.einsum("...ii->...i", g)
    mac = g**2 / (d[..., :, None] * d[..., None, :])
    m = g.shape[-1]
    mac[..., np.arange(m), np.arange(m)] = 0.0
    return mac.reshape(mac.shape[:-2] + (m * m,)).max(axis=-1)


def refine_automac(
    phi: np.ndarray,
    groups,
    *,
    group_labels=None,
    include=None,
    exclude=None,
    positions=None,
    min_distance: float = 0.0,
    max_det_loss_decades: float = 1.0,
    max_swaps: int = 100,
    chunk: int = 2048,
) -> RefineResult:
    """Lower the largest off-diagonal autoMAC of a layout by one-for-one exchanges.

    Parameters
    ----------
    phi : array_like, shape (n_rows, n_modes)
        Target modes at every candidate row (as for :func:`effective_independence`).
    groups : array_like of int
        Starting selection, group indices in ``np.unique(group_labels)`` order
        (``EfIResult.groups``).
    group_labels, include, exclude, positions, min_distance
        As for :func:`effective_independence`; the same constraints hold for
        every exchange.
    max_det_loss_decades : float
        Accept layouts with ``log10 det(FIM)`` at most this much below the start.
    max_swaps : int
        Upper bound on exchanges.
    chunk : int
        Candidates evaluated per vectorized batch.

    Returns
    -------
    RefineResult
    """
    phi = np.asarray(phi, dtype=float)
    n_rows, m = phi.shape
    labels, table, _ = group_structure(n_rows, group_labels)
    n_groups = labels.size
    sel = np.zeros(n_groups, dtype=bool)
    groups = np.asarray(groups, dtype=np.int64)
    if groups.size == 0 or groups.min() < 0 or groups.max() >= n_groups:
        raise PretestError("starting selection must name candidate groups 0..n_groups-1")
    sel[groups] = True
    protected = np.zeros(n_groups, dtype=bool)
    protected[as_group_indices(include, labels, "include")] = True
    available = np.ones(n_groups, dtype=bool)
    available[as_group_indices(exclude, labels, "exclude")] = False
    col = np.linalg.norm(phi, axis=0)
    col[col == 0] = 1.0
    pad = np.where((table >= 0)[:, :, None], phi[np.maximum(table, 0)], 0.0) / col
    contrib = np.einsum("gkm,gkn->gmn", pad, pad)  # each group's FIM share, (n_groups, m, m)
    gpos = None
    if min_distance > 0:
        if positions is None:
            raise PretestError("min_distance needs candidate positions")
        positions = np.asarray(positions, dtype=float)
        cnt = (table >= 0).sum(axis=1)
        gpos = np.where((table >= 0)[:, :, None], positions[np.maximum(table, 0)], 0.0).sum(1) / cnt[:, None]
    scale = 2 * np.log10(col).sum()  # log10 det of the unscaled FIM = scaled + this

    def state(mask):
        q = contrib[mask].sum(axis=0)
        sign, ld = np.linalg.slogdet(q)
        return q, (ld / np.log(10) if sign > 0 else -np.inf), float(_max_offdiag_mac(q))

    q, ld0, mac0 = state(sel)
    floor = ld0 - max_det_loss_decades
    cur_ld, cur_mac = ld0, mac0
    n_swaps = 0
    while n_swaps < max_swaps:
        best = (cur_mac - 1e-6, None, None, None)
        outside = np.flatnonzero(available & ~sel)
        for r in np.flatnonzero(sel & ~protected):
            q_r = q - contrib[r]
            cand = outside
            if gpos is not None:
                others = np.flatnonzero(sel)
                others = others[others != r]
                if others.size:
                    d = np.linalg.norm(gpos[cand, None] - gpos[None, others], axis=-1).min(axis=1)
                    cand = cand[d >= min_distance]
            for s in range(0, cand.size, chunk):
                a = cand[s : s + chunk]
                qa = q_r[None] + contrib[a]
                macs = _max_offdiag_mac(qa)
                sign, ld = np.linalg.slogdet(qa)
                ld = np.where(sign > 0, ld / np.log(10), -np.inf)
                ok = ld >= floor
                if not ok.any():
                    continue
                macs = np.where(ok, macs, np.inf)
                i = int(np.argmin(macs))
                if macs[i] < best[0]:
                    best = (float(macs[i]), int(r), int(a[i]), float(ld[i]))
        if best[1] is None:
            break
        cur_mac, r, a, cur_ld = best
        sel[r], sel[a] = False, True
        q = q - contrib[r] + contrib[a]
        n_swaps += 1
    groups = np.flatnonzero(sel)
    rows = np.sort(table[groups][table[groups] >= 0])
    return RefineResult(
        groups=groups,
        rows=rows,
        n_swaps=n_swaps,
        automac_before=mac0,
        automac_after=float(_max_offdiag_mac(contrib[sel].sum(axis=0))),
        log10_det_before=ld0 + scale,
        log10_det_after=state(sel)[1] + scale,
    )
