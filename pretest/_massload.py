"""Mass loading: first-order frequency shifts from sensor and drive hardware masses."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pretest._errors import PretestError

__all__ = ["MassLoading", "mass_loading_shifts"]

#: Default accelerometer mass (kg): 0.5 g, e.g. PCB 352C22 as in the method paper.
DEFAULT_SENSOR_MASS_KG = 0.5e-3


@dataclass(frozen=True)
class MassLoading:
    """Predicted effect of attached point masses on the target modes.

    Attributes
    ----------
    frequencies_hz : ndarray, shape (n_modes,)
        Unloaded natural frequencies.
    loaded_frequencies_hz : ndarray, shape (n_modes,)
        ``f sqrt(1 - mu_r)`` with ``mu_r = sum_p m_p |u_r(p)|^2``.
    shift_hz : ndarray, shape (n_modes,)
        ``loaded - unloaded`` (negative: added mass lowers frequencies).
    relative_shift : ndarray, shape (n_modes,)
        ``shift_hz / frequencies_hz``.
    mu : ndarray, shape (n_points, n_modes)
        Per-point modal mass fraction ``m_p |u_r(p)|^2``: which attachment
        loads which mode.
    """

    frequencies_hz: np.ndarray
    loaded_frequencies_hz: np.ndarray
    shift_hz: np.ndarray
    relative_shift: np.ndarray
    mu: np.ndarray


def mass_loading_shifts(frequencies_hz, translations, masses_kg) -> MassLoading:
    """First-order frequency shifts from point masses at grid points.

    With mass-normalized modes, a mass change ``dM`` moves the eigenvalues by
    ``d(omega_r^2) = -omega_r^2 phi_r^T dM phi_r`` to first order.  A point
    mass ``m`` at a grid adds ``m I_3`` to its three translations, so
    ``phi_r^T dM phi_r = m |u_r|^2`` with ``u_r`` the grid's translation
    vector in mode r (a single-axis accelerometer loads all three directions).

    Parameters
    ----------
    frequencies_hz : array_like, shape (n_modes,)
    translations : array_like, shape (n_points, 3, n_modes)
        Mass-normalized translations of each loaded grid (m/sqrt(kg) in SI:
        1/sqrt(kg) per unit modal coordinate).
    masses_kg : array_like, shape (n_points,) or scalar
        Attached mass at each point (kg).

    Returns
    -------
    MassLoading
    """
    f = np.asarray(frequencies_hz, dtype=float).ravel()
    u = np.asarray(translations, dtype=float)
    if u.ndim != 3 or u.shape[1] != 3 or u.shape[2] != f.size:
        raise PretestError(f"translations must be (n_points, 3, {f.size}), got shape {u.shape}")
    m = np.broadcast_to(np.asarray(masses_kg, dtype=float), (u.shape[0],))
    if np.any(m < 0) or not np.all(np.isfinite(m)):
        raise PretestError("attached masses must be finite and >= 0 kg")
    mu = m[:, None] * np.einsum("pcr,pcr->pr", u, u)
    total = mu.sum(axis=0)
    loaded = f * np.sqrt(np.clip(1.0 - total, 0.0, None))
    shift = loaded - f
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = np.where(f > 0, shift / np.where(f > 0, f, 1.0), 0.0)
    return MassLoading(
        frequencies_hz=f,
        loaded_frequencies_hz=loaded,
        shift_hz=shift,
        relative_shift=rel,
        mu=mu,
    )
