"""Fit quality: the paper's square deviation of log10 ratios (Eq. 2.5-2.6)."""

from __future__ import annotations

import numpy as np

from ._errors import IdentificationError


def log_ratio(H_model, H_data) -> np.ndarray:
    """``eps = log10(H_model ./ H_data)`` (complex, principal branch), paper Eq. 2.6."""
    Hm = np.asarray(H_model, dtype=complex)
    Hd = np.asarray(H_data, dtype=complex)
    if Hm.shape != Hd.shape:
        raise IdentificationError(f"square_deviation: model shape {Hm.shape} != data shape {Hd.shape}")
    if np.any(Hd == 0) or np.any(Hm == 0):
        raise IdentificationError("square_deviation: an FRF value is exactly zero (log ratio undefined)")
    return np.log(Hm / Hd) / np.log(10.0)


def square_deviation(H_model, H_data) -> float:
    """Square deviation ``delta = eps^H eps / N`` (paper Eq. 2.5-2.6).

    Parameters
    ----------
    H_model, H_data : array_like, complex, same shape (e.g. (n_f, n_out, n_in))

    Returns
    -------
    float
        Mean of ``|log10(H_model/H_data)|^2`` over all N elements [-].
        0 for a perfect fit; 0.01 corresponds to an RMS error of about 26 %
        in magnitude or 13 degrees in phase.
    """
    eps = log_ratio(H_model, H_data)
    if eps.size == 0:
        raise IdentificationError("square_deviation: no FRF values")
    return float(np.vdot(eps, eps).real / eps.size)


def channel_deviation(H_model, H_data) -> np.ndarray:
    """Square deviation per channel: ``(n_out, n_in)`` from ``(n_f, n_out, n_in)`` inputs."""
    eps = log_ratio(H_model, H_data)
    if eps.ndim != 3:
        raise IdentificationError(f"channel_deviation needs (n_f, n_out, n_in) arrays, got {eps.shape}")
    return np.mean(np.abs(eps) ** 2, axis=0)
