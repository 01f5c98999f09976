"""Per-line noise of FRFs that carry no standard errors, estimated from the lines themselves.

Run files from the acquisition carry per-line standard errors; UFF58 imports
carry none. The floor that every SD is compared with (``E|eps|^2`` per value,
:func:`calibration.noise_floor_sd`) then has to come from the data. The
identification's fit residual is not a floor (it holds the identification's
own misfit: 0.026 where the truth's floor is 6e-5 on outside data).

Estimate (per response/drive pair):

1. **Local differences of log H.** ``y = ln H`` (continuous complex log, built
   from adjacent-line ratios so the phase does not wrap). On every stencil of
   ``n_stencil`` consecutive lines (default 7) the combination ``d = sum c_j y_j``
   that annihilates every polynomial in f of degree ``n_stencil - 2`` on the
   stencil's own (uneven) frequencies, with ``sum |c_j|^2 = 1``. A smooth FRF
   (several lines per half-power bandwidth: a stepped sine or a grid dense at
   resonances) leaves ``d ~ 0``; independent noise ``delta y_j = n_j / H_j``
   leaves ``E|d|^2 = sum c_j^2 r_j^2`` with ``r_j = sigma_j / |H_j|``.
2. **Noise model** ``sigma^2 = a^2 |H|^2 + b^2`` (a relative part, sensor and
   drive noise proportional to the response, and an absolute floor), so
   ``E|d_k|^2 = a^2 u_k + b^2 v_k``, ``u_k = sum c_j^2``, ``v_k = sum c_j^2 / |H_j|^2``.
   ``|d_k|^2`` is exponential about its mean; ``(a^2, b^2) >= 0`` are fitted
   by iteratively reweighted non-negative least squares (weights ``1/m_k^2``,
   started from each part's own stencils: see :func:`_fit_pair`),
   leaving out the stencils with ``|d_k|^2 > trim x`` their fitted mean
   (resonances sharper than the line spacing, steps), whose curvature is not
   noise. With ``trim = 3`` a pure-noise stencil is left out with probability
   ``e^-3`` and the kept ones' mean is ``kappa = 0.843`` of the whole: the fit
   is divided by ``kappa`` (truncated exponential). A hard trim and a high
   stencil order matter on sparse grids near sharp modes (a base grid 7
   half-power bandwidths apart beside a 0.05 % mode curves log H over dozens
   of stencils by a few times the noise): 5 lines / trim 8 gave up to 1.9 x the
   truth there, 7 lines / trim 3 1.34 x.
3. ``sigma_k = sqrt(a^2 |H_k|^2 + b^2)`` on every line.

Validated (``tests/calibration/test_noise.py``) on synthetic FRFs with noise
0.5-1 % of |H| plus an absolute floor, uneven grids dense at resonances,
modal damping 0.05-0.3 %: the estimated floor ``mean (sigma/|H|)^2 / ln10^2``
is within 30 % of the truth's ``mean |log10(H_noisy / H_true)|^2`` and does
not grow with the resonances' sharpness.

Limits: the lines' noise must be independent from line to line (an FFT
analyzer's Hann window correlates adjacent bins: the estimate is then
biased, by up to 1 + 2/3 for adjacent-bin correlation -2/3 on a uniform grid);
a grid with fewer than ~2 lines per half-power bandwidth everywhere leaves
curvature in ``d`` that the trimming cannot tell from noise (the estimate is
then high: a conservative floor).

Conventions: frequencies Hz ascending; FRFs ``(n_f, n_out, n_in)`` complex.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import nnls

from calibration._errors import CalibrationError

#: source label of a floor estimated by :func:`estimate_std_error` (printed beside the floor)
ESTIMATED = "estimated from adjacent lines"


@dataclass(frozen=True)
class NoiseEstimate:
    """Outcome of :func:`estimate_std_error`.

    Attributes
    ----------
    std_error : (n_f, n_out, n_in) float, estimated standard error of each value (unit of the FRF)
    relative : (n_out, n_in) float, ``a``: noise rms relative to |H|
    absolute : (n_out, n_in) float, ``b``: absolute noise rms (unit of the FRF)
    n_used : (n_out, n_in) int, stencils kept in the fit (the others: curvature, not noise)
    source : str, :data:`ESTIMATED`
    """

    std_error: np.ndarray
    relative: np.ndarray
    absolute: np.ndarray
    n_used: np.ndarray
    source: str = ESTIMATED


def _stencil_weights(f: np.ndarray, n_stencil: int) -> np.ndarray:
    """(n_f - n_stencil + 1, n_stencil) unit-norm combinations annihilating degree n_stencil - 2 on each stencil."""
    m = f.size - n_stencil + 1
    idx = np.arange(m)[:, None] + np.arange(n_stencil)[None, :]
    x = f[idx]
    x = (x - x.mean(axis=1, keepdims=True)) / np.maximum(np.ptp(x, axis=1, keepdims=True), 1e-300)
    V = x[:, :, None] ** np.arange(n_stencil - 1)[None, None, :]  # (m, s, s-1)
    # the null space of V^T (one vector): the last left-singular vector of V
    U = np.linalg.svd(V, full_matrices=True)[0]
    return U[:, :, -1]


def _fit_pair(q, u, v, trim: float, n_iter: int = 12):
    """Non-negative (a2, b2) of E q = a2 u + b2 v, exponential q, trimmed; returns (a2, b2, n_kept).

    The reweighting starts from each part's own stencils: a2 from the quarter
    with the smallest v (largest |H|: the relative noise dominates there), b2
    from the quarter with the largest v (an anti-resonance, a channel near
    its floor), each a median of q / u or q / v over ln 2 (an exponential's
    mean). A start with equal weights (one median for every stencil) let the
    few anti-resonance stencils, whose q is up to 1e10 times the others',
    decide the first fit; where that fit came out with a2 ~ 0 the trimming
    then dropped the stencils that carry the relative noise and the
    iteration stayed there (an outside file: relative noise 0.0002 for
    0.0077, so that pair's floor 36 x too low).
    """
    keep = np.isfinite(q) & np.isfinite(v)
    if keep.sum() < 3:
        return np.nan, np.nan, 0
    qk, uk, vk = q[keep], u[keep], v[keep]
    v_lo, v_hi = np.quantile(vk, [0.25, 0.75])
    a2 = np.median((qk / uk)[vk <= v_lo]) / np.log(2)
    b2 = np.median((qk / vk)[vk >= v_hi]) / np.log(2)
    m = np.maximum(a2 * u, b2 * v) + 1e-300  # the larger part where each dominates
    keep = keep & (q <= trim * m)
    if keep.sum() < 3:
        keep = np.isfinite(q) & np.isfinite(v)
    A = np.stack([u, v], axis=1)
    kappa = (1 - (1 + trim) * np.exp(-trim)) / (1 - np.exp(-trim))  # mean of an exponential truncated at trim x mean
    for _ in range(n_iter):
        w = 1.0 / m[keep]
        (a2, b2), _ = nnls(A[keep] * w[:, None], q[keep] * w)
        a2, b2 = a2 / kappa, b2 / kappa
        m_new = a2 * u + b2 * v + 1e-300
        keep_new = np.isfinite(q) & np.isfinite(v) & (q <= trim * m_new)
        if keep_new.sum() < 3:
            break
        done = np.array_equal(keep_new, keep) and np.allclose(m_new, m, rtol=1e-6)
        m, keep = m_new, keep_new
        if done:
            break
    return a2, b2, int(keep.sum())


def estimate_std_error(freq_hz, frf, *, n_stencil: int = 7, trim: float = 3.0, what: str = "FRF") -> NoiseEstimate:
    """Per-line standard errors of an FRF without them, from its own lines (see the module docstring).

    Parameters
    ----------
    freq_hz : (n_f,) Hz, ascending (uneven grids welcome)
    frf : (n_f, n_out, n_in) complex (or (n_f,), (n_f, n_out))
    n_stencil : int, lines per stencil (>= 3; annihilates degree n_stencil - 2)
    trim : float, stencils beyond ``trim`` x their fitted mean are curvature, not noise
    what : str, named in errors (e.g. the run file)

    Returns
    -------
    NoiseEstimate (``std_error`` shaped as ``frf``)
    """
    f = np.asarray(freq_hz, float)
    H = np.asarray(frf, complex)
    shape = H.shape
    if H.ndim == 1:
        H = H[:, None, None]
    elif H.ndim == 2:
        H = H[:, :, None]
    if H.ndim != 3 or H.shape[0] != f.size:
        raise CalibrationError(f"{what}: noise estimate needs (n_f={f.size}, n_out, n_in) FRFs, got {shape}")
    if n_stencil < 3:
        raise CalibrationError(f"{what}: noise estimate stencil must hold >= 3 lines, got {n_stencil}")
    if f.size < n_stencil + 3:
        raise CalibrationError(f"{what}: {f.size} lines are too few to estimate the noise from adjacent lines")
    if np.any(np.diff(f) <= 0):
        raise CalibrationError(f"{what}: line frequencies must be strictly ascending to estimate the noise")
    n_f, n_out, n_in = H.shape
    c = _stencil_weights(f, n_stencil)  # (m, s)
    m = c.shape[0]
    idx = np.arange(m)[:, None] + np.arange(n_stencil)[None, :]
    c2 = c**2
    a = np.full((n_out, n_in), np.nan)
    b = np.full((n_out, n_in), np.nan)
    used = np.zeros((n_out, n_in), int)
    absH = np.abs(H)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.log(H[1:] / H[:-1])
        y = np.concatenate([np.zeros((1, n_out, n_in), complex), np.cumsum(ratio, axis=0)], axis=0)
        for o in range(n_out):
            for i in range(n_in):
                yy = y[:, o, i]
                if not np.all(np.isfinite(yy)):
                    continue
                d = np.einsum("ks,ks->k", c, yy[idx])
                q = np.abs(d) ** 2
                u = c2.sum(axis=1)
                v = (c2 / absH[idx, o, i] ** 2).sum(axis=1)
                a2, b2, n = _fit_pair(q, u, v, trim)
                a[o, i], b[o, i], used[o, i] = np.sqrt(a2), np.sqrt(b2), n
    sig = np.sqrt((a[None] * absH) ** 2 + b[None] ** 2)
    return NoiseEstimate(sig.reshape(shape), a, b, used)
