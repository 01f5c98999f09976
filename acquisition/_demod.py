"""Harmonic demodulation of sampled blocks (least squares at the known drive frequency)."""

from __future__ import annotations

import numpy as np


def fit_harmonics(samples: np.ndarray, rate_hz: float, frequency_hz: float, n_harmonics: int = 5) -> np.ndarray:
    """Complex amplitudes of the fundamental and harmonics of every channel.

    A least-squares fit of ``c0 + sum_k Re(X_k exp(i k w t))`` over the block,
    ``t = n / rate_hz``. Over whole cycles this equals the DFT bin of each
    harmonic; the fit stays unbiased when a block holds a fractional number of
    samples per cycle.

    Parameters
    ----------
    samples : (n_channels, n_samples) float
    rate_hz : float
        Sample rate, Hz.
    frequency_hz : float
        Drive (fundamental) frequency, Hz.
    n_harmonics : int
        Number of harmonics including the fundamental (harmonics above Nyquist are skipped and set to 0).

    Returns
    -------
    (n_channels, n_harmonics) complex
        Peak complex amplitudes, e^{+iwt} convention, phase referenced to the first sample.
    """
    x = np.atleast_2d(np.asarray(samples, dtype=float))
    n = x.shape[1]
    t = np.arange(n) / rate_hz
    ks = [k for k in range(1, n_harmonics + 1) if k * frequency_hz < 0.5 * rate_hz]
    cols = [np.ones(n)]
    for k in ks:
        th = 2 * np.pi * k * frequency_hz * t
        cols += [np.cos(th), np.sin(th)]
    M = np.stack(cols)  # (n_basis, n): nearly orthogonal over >= 1 cycle, so normal equations are safe
    G = M @ M.T
    rhs = M @ x.T
    try:
        coef = np.linalg.solve(G, rhs)
    except np.linalg.LinAlgError:  # fewer samples than basis functions
        coef, *_ = np.linalg.lstsq(M.T, x.T, rcond=None)
    out = np.zeros((x.shape[0], n_harmonics), dtype=complex)
    for j, k in enumerate(ks):
        out[:, k - 1] = coef[1 + 2 * j] - 1j * coef[2 + 2 * j]
    return out


def thd(harmonics: np.ndarray) -> np.ndarray:
    """Total harmonic distortion ``sqrt(sum_{k>=2} |X_k|^2) / |X_1|`` per channel (fraction)."""
    h = np.atleast_2d(harmonics)
    fund = np.abs(h[:, 0])
    rest = np.sqrt(np.sum(np.abs(h[:, 1:]) ** 2, axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(fund > 0, rest / fund, np.inf)


def phasors(block, frequency_hz: float, n_harmonics: int = 5) -> np.ndarray:
    """Complex amplitudes ``(n_channels, n_harmonics)`` of any driver block.

    A :class:`~acquisition.SampleBlock` is demodulated by :func:`fit_harmonics`;
    a :class:`~acquisition.PhasorBlock` already holds them (padded with zeros or
    truncated to ``n_harmonics``). This is the one place the controller looks at
    what kind of driver produced a block.
    """
    from acquisition._driver import PhasorBlock

    if isinstance(block, PhasorBlock):
        X = np.atleast_2d(np.asarray(block.harmonics, dtype=complex))
        if X.shape[1] < n_harmonics:
            X = np.pad(X, ((0, 0), (0, n_harmonics - X.shape[1])))
        return X[:, :n_harmonics]
    return fit_harmonics(block.samples, block.rate_hz, frequency_hz, n_harmonics)
