"""The log-ratio deviation metric of the method paper (Eq. 2.5-2.6, 2.22-2.23).

``eps = log10(H^A ./ H^X)`` is complex. We take the principal branch of the
complex logarithm of the *ratio*::

    eps = log10|H^A/H^X| + i * angle(H^A/H^X) / ln(10),  angle in (-pi, pi]

so the imaginary part is the phase error in "decades" (ln 10 rad per unit).
The ratio is formed before the logarithm, so the absolute phase of either FRF
never wraps; only a phase *error* crossing +-180 deg jumps (by 2*pi/ln 10).
That happens only when a model resonance sits on the wrong side of a test
resonance, is rare near the optimum and is the documented price of a metric
that is smooth everywhere else. The square deviation is ``delta = eps^H eps / N``.
"""

from __future__ import annotations

import numpy as np

from calibration._errors import CalibrationError

LN10 = np.log(10.0)


def log_deviation(h_model: np.ndarray, h_test: np.ndarray) -> np.ndarray:
    """eps = log10(h_model / h_test) elementwise, principal branch (complex).

    Parameters
    ----------
    h_model, h_test : complex array, same shape (e.g. ``(n_freq, n_out, n_in)``)

    Returns
    -------
    complex ndarray of the same shape.
    """
    h_model = np.asarray(h_model)
    h_test = np.asarray(h_test)
    if h_model.shape != h_test.shape:
        raise CalibrationError(f"model FRF shape {h_model.shape} != test FRF shape {h_test.shape}")
    if not np.all(np.isfinite(h_test)):
        raise CalibrationError("test FRF contains NaN/inf lines: flag or drop them before calibration")
    if np.any(h_test == 0):
        raise CalibrationError("test FRF contains exact zeros: log deviation undefined")
    return np.log(h_model / h_test) / LN10


def square_deviation(eps: np.ndarray) -> float:
    """delta = eps^H eps / N (paper Eq. 2.5 and 2.23); dimensionless."""
    eps = np.asarray(eps).ravel()
    if eps.size == 0:
        raise CalibrationError("square deviation of an empty data set")
    return float(np.real(np.vdot(eps, eps)) / eps.size)


def stacked(eps: np.ndarray) -> np.ndarray:
    """Real residual ``[Re eps; Im eps] / sqrt(N)`` so that ``sum(r**2) == delta``."""
    e = np.asarray(eps).ravel()
    return np.concatenate([e.real, e.imag]) / np.sqrt(e.size)
