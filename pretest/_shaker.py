"""Shaker (drive point) ranking by driving-point residues and weakest-mode participation."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pretest._errors import PretestError

__all__ = ["DriveRanking", "rank_drive_points"]


@dataclass(frozen=True)
class DriveRanking:
    """Drive-point candidates ranked best first.

    Attributes
    ----------
    order : ndarray, shape (n_candidates,)
        Candidate indices, best first.
    adpr : ndarray, shape (n_candidates,)
        Average driving-point residue ``sum_r phi_r(d)^2 / omega_r`` (s/kg for
        mass-normalized modes in 1/sqrt(kg) and omega in rad/s), in candidate order.
    adpr_normalized : ndarray, shape (n_candidates,)
        ``adpr / adpr.max()``.
    participation : ndarray, shape (n_candidates, n_modes)
        ``|phi_r(d)| / max_d |phi_r(d)|``: how well candidate d drives mode r
        compared with the best candidate for that mode.
    weakest : ndarray, shape (n_candidates,)
        ``min_r participation[d, r]``: the weakest-excited mode's share.
    weakest_mode : ndarray, shape (n_candidates,)
        Index (within the target set) of that weakest mode.
    score : ndarray, shape (n_candidates,)
        The ranking score (see :func:`rank_drive_points`).
    """

    order: np.ndarray
    adpr: np.ndarray
    adpr_normalized: np.ndarray
    participation: np.ndarray
    weakest: np.ndarray
    weakest_mode: np.ndarray
    score: np.ndarray


def rank_drive_points(phi_drive: np.ndarray, frequencies_hz: np.ndarray, *, criterion: str = "weakest") -> DriveRanking:
    """Rank candidate drive points (with direction) for exciting every target mode.

    Parameters
    ----------
    phi_drive : array_like, shape (n_candidates, n_modes)
        Mass-normalized target mode shapes projected on each candidate's drive
        direction (1/sqrt(kg) in SI).
    frequencies_hz : array_like, shape (n_modes,)
        Natural frequencies of the target modes (Hz, all > 0: elastic modes).
    criterion : {"weakest", "adpr", "product"}
        ``"weakest"`` ranks by the weakest-mode participation (a drive near
        any mode's nodal line ranks low), ties by ADPR; ``"adpr"`` by the
        average driving-point residue; ``"product"`` by their product.

    Returns
    -------
    DriveRanking
    """
    p = np.asarray(phi_drive, dtype=float)
    f = np.asarray(frequencies_hz, dtype=float).ravel()
    if p.ndim != 2 or p.shape[0] == 0:
        raise PretestError(f"drive mode shapes must be (n_candidates, n_modes), got shape {p.shape}")
    if f.size != p.shape[1]:
        raise PretestError(f"{f.size} frequencies for {p.shape[1]} modes")
    if np.any(~np.isfinite(f)) or np.any(f <= 0):
        raise PretestError("drive-point ranking needs elastic target modes (all frequencies > 0 Hz)")
    omega = 2 * np.pi * f
    adpr = (p**2 / omega).sum(axis=1)
    amax = np.abs(p).max(axis=0)
    if np.any(amax == 0):
        raise PretestError(
            f"target mode(s) {np.flatnonzero(amax == 0).tolist()} cannot be driven from any drive candidate"
        )
    part = np.abs(p) / amax
    weakest = part.min(axis=1)
    weakest_mode = part.argmin(axis=1)
    adpr_n = adpr / adpr.max() if adpr.max() > 0 else adpr
    if criterion == "weakest":
        score = weakest
        order = np.lexsort((np.arange(p.shape[0]), -adpr_n, -weakest))
    elif criterion == "adpr":
        score = adpr_n
        order = np.lexsort((np.arange(p.shape[0]), -weakest, -adpr_n))
    elif criterion == "product":
        score = weakest * adpr_n
        order = np.lexsort((np.arange(p.shape[0]), -score))
    else:
        raise PretestError(f"unknown drive ranking criterion {criterion!r}; use 'weakest', 'adpr' or 'product'")
    return DriveRanking(
        order=order,
        adpr=adpr,
        adpr_normalized=adpr_n,
        participation=part,
        weakest=weakest,
        weakest_mode=weakest_mode,
        score=score,
    )
