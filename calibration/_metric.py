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


def true_runs(mask) -> list[tuple[int, int]]:
    """``(first, last)`` index of every run of consecutive True values of a 1-D mask (``last`` inclusive), in order:
    the bands of adjacent lines that a per-line test flags."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    edges = np.flatnonzero(m[1:] != m[:-1])
    return [(int(a), int(b) - 1) for a, b in zip(edges[0::2], edges[1::2])]


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


def _log_noise_table():
    """Cubic spline of ln E|ln(1 + z)|^2 in ln q, for q = E|z|^2 in 1e-3..1e6 and z circular complex
    Gaussian, by quadrature.

    With z = r e^{i theta} the mean over theta is Li2(r^2) for r <= 1 and
    (ln r)^2 + pi^2/3 + Li2(1/r^2) - 2 Li2(1/r) for r > 1 (the Fourier series of
    ln(1 + z) inside and outside the unit circle), and s = r^2 has density
    e^{-s/q}/q: one vector quadrature in s for every node, split at the kink s = 1.
    """
    from scipy.integrate import quad_vec
    from scipy.interpolate import CubicSpline
    from scipy.special import spence

    def mean_over_phase(s):  # s = r^2
        if s <= 1.0:
            return spence(1.0 - s)
        r = np.sqrt(s)
        return np.log(r) ** 2 + np.pi**2 / 3 + spence(1.0 - 1.0 / s) - 2.0 * spence(1.0 - 1.0 / r)

    x = np.linspace(np.log(1e-3), np.log(1e6), 121)
    q = np.exp(x)

    def f(s):
        return np.exp(-s / q) / q * mean_over_phase(s)

    g = quad_vec(f, 0.0, 1.0, epsrel=1e-10, norm="max")[0] + quad_vec(f, 1.0, np.inf, epsrel=1e-10, norm="max")[0]
    return CubicSpline(x, np.log(g))


_LOG_NOISE_TABLE = None  # the spline of _log_noise_table, made on first use (0.05 s)


def _log_noise_large(q: np.ndarray) -> np.ndarray:
    """:func:`log_noise_variance` for rel2 >= 1e6: E[(ln r)^2] + pi^2/3 - 2 E[1/r] with r^2 = q t, t ~ Exp(1)
    (the mean over the phase beyond the unit circle, to O(1/r^2); the mass inside it is 1/q)."""
    lq = np.log(q)
    return 0.25 * (lq**2 - 2 * np.euler_gamma * lq + np.euler_gamma**2 + np.pi**2 / 6) + np.pi**2 / 3 \
        - 2.0 * np.sqrt(np.pi / q)


def log_noise_variance(rel2) -> np.ndarray:
    """``E|ln(1 + n/H)|^2`` of a value whose complex Gaussian noise n has ``E|n|^2 = rel2 |H|^2``.

    The noise floor of the log metric is this over (ln 10)^2, per value. It is
    ``rel2`` for small noise (the first-order ``(sigma / |H|)^2``), but grows only as
    ``(ln rel2)^2 / 4`` where the noise reaches |H| (an anti-resonance, a channel
    below its noise): the log of a noise-dominated value is bounded by the
    noise, not by the value. The first-order form there counted a single line
    with |H| at a tenth of sigma as 100 lines of full noise (outside trial, stop 33:
    one line held 99.5 % of a pair's floor, which came out 2.6-5x the truth's).

    Parameters
    ----------
    rel2 : array_like, (sigma / |H|)^2 >= 0 (inf where H = 0: returned as inf)

    Returns
    -------
    ndarray of the same shape (within 1e-5 relative: the series below 1e-3, a
    log-log spline of quadrature values up to 1e6, the asymptote beyond).
    """
    global _LOG_NOISE_TABLE
    q = np.array(rel2, dtype=float, ndmin=1)
    out = q * (1.0 + q / 2.0 + 2.0 * q**2 / 3.0)  # sum_k k! q^k / k^2, to q^3
    mid = (q > 1e-3) & (q <= 1e6)
    if np.any(mid):
        if _LOG_NOISE_TABLE is None:
            _LOG_NOISE_TABLE = _log_noise_table()
        out[mid] = np.exp(_LOG_NOISE_TABLE(np.log(q[mid])))
    big = (q > 1e6) & np.isfinite(q)
    out[big] = _log_noise_large(q[big])
    out[np.isinf(q)] = np.inf
    return out.reshape(np.shape(rel2))


def log_noise_floor(frf, std_error) -> np.ndarray:
    """Per value ``E|log10(1 + n/H)|^2`` (decades^2) of FRF values ``frf`` with standard errors ``std_error``
    (same shape): :func:`log_noise_variance` of ``(sigma / |H|)^2`` over (ln 10)^2; inf where H = 0 (callers
    decide: the hold-out floor refuses it, the residual check counts it as no expectation)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return log_noise_variance((np.asarray(std_error, float) / np.abs(np.asarray(frf))) ** 2) / LN10**2
