"""Is the residual nonlinear? Level dependence, harmonic distortion, sweep direction.

Closing the loop (issue 14) explains a calibration residual by *linear* candidate
effects (springs, masses). That is only admissible when the test article behaved
linearly. Three checks look at the acquisition data for evidence that it did not,
each judged against what noise and test-to-test repeatability explain:

* :func:`level_dependence` -- FRFs of the same article at two or more excitation
  levels. Every resonance is fitted locally at every level (one mode with complex
  residue plus a complex constant and slope for the out-of-band modes, weighted
  by the per-line standard errors); the natural frequency and damping ratio of
  each mode come with their Gauss-Newton standard deviations. A weighted straight
  line of the parameter against ``log10(level)`` gives a trend and its z-score;
  a mode whose |z| exceeds ``z_threshold`` changes with level. A model-free check
  compares every level with the lowest one by the log-ratio metric of
  :mod:`calibration._metric`: ``sum 2|eps|^2 / var(eps)`` is chi-square with 2N
  degrees of freedom under noise alone.
* :func:`distortion` -- per-line THD (run file) against a threshold and against
  the channel's own THD floor; flagged lines are attributed to a mode (at the
  resonance, or at 1/2, 1/3 of it: superharmonic resonance).
* :func:`sweep_direction` -- an up and a down sweep over the same lines; lines
  whose difference exceeds the noise (jump phenomenon, hysteresis of a
  hardening or softening mode) are flagged in contiguous bands.

:func:`nonlinearity` combines them into a :class:`Nonlinearity` verdict:
``"nonlinear"`` (and then no linear effect may be put in its place) or ``"linear"``.

Conventions: frequencies in Hz; FRFs ``(n_f, n_out, n_in)`` complex; standard
errors ``(n_f, n_out, n_in)`` in FRF units with ``E|e|^2 = std_error^2`` (the
acquisition controller's definition, block scatter of the complex mean);
significance is stated in sigma (the standard-normal z of the test's p-value).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from calibration._errors import CalibrationError
from calibration._metric import LN10, log_deviation, square_deviation, true_runs
from labdata import FRF_QUANTITIES, quantity_factor, quantity_power



def _z_of_p(p: float) -> float:
    """One-sided standard-normal z of a p-value."""
    from scipy.stats import norm

    # p = 1 (a statistic far below its expectation: a conservative floor) is held at z ~ -8, not -inf
    return float(norm.isf(min(p, 1.0 - 1e-16))) if np.isfinite(p) else float("nan")


def _chi2_z(t: float, dof: int) -> float:
    """z of a chi-square statistic ``t`` with ``dof`` degrees of freedom (upper tail).

    Exact while the tail probability is representable: the upper tail for a
    statistic above its median, the lower tail (z = -isf(cdf)) below it, so
    that a statistic far below its expectation gets its own size instead of
    the -8.2 at which ``isf(1 - 1e-16)`` saturates. Beyond, the Wilson-Hilferty
    cube-root normal approximation, so that a huge (or tiny) statistic keeps a
    finite, ordered size.
    """
    from scipy.stats import chi2, norm

    if dof <= 0 or not np.isfinite(t):
        return float("nan")
    p = float(chi2.sf(t, dof))
    if 1e-300 < p <= 0.5:
        return _z_of_p(p)
    if p > 0.5:
        c = float(chi2.cdf(t, dof))
        if c > 1e-300:
            return -float(norm.isf(c))
    v = 2.0 / (9.0 * dof)
    return float(((t / dof) ** (1.0 / 3.0) - (1.0 - v)) / np.sqrt(v))


# ------------------------------------------------------------------ input data
@dataclass(frozen=True)
class FRFLevel:
    """FRFs of one test at one excitation level.

    Parameters
    ----------
    frequency_hz : (n_f,) float
        Frequency lines, Hz (any order; they are sorted on construction).
    frf : (n_f, n_out, n_in) complex
        FRF of ``quantity`` (SI).
    level : float
        Excitation level: force amplitude (N, force control) or response amplitude
        (e.g. m/s^2, response control); only its ordering and ratios are used.
    std_error : (n_f, n_out, n_in) float or None
        Per-line standard error of the FRF (same unit), ``E|e|^2 = std_error^2``.
        ``None``: the noise is estimated from the local fit residual.
    unit : str
        Unit of ``level`` (for the words only).
    quantity : {"receptance", "mobility", "accelerance"}
    label : str
        Name of the test (file name, tag) used in messages.
    sweep : {"up", "down", "unknown"}
        Order in which the lines were measured.
    """

    frequency_hz: np.ndarray
    frf: np.ndarray
    level: float
    std_error: np.ndarray | None = None
    unit: str = "N"
    quantity: str = "accelerance"
    label: str = ""
    sweep: str = "unknown"

    def __post_init__(self) -> None:
        name = self.label or "FRF level"
        f = np.asarray(self.frequency_hz, float).ravel()
        H = np.asarray(self.frf)
        if H.ndim == 1:
            H = H[:, None, None]
        if H.ndim != 3 or H.shape[0] != f.size:
            raise CalibrationError(f"{name}: frf must be (n_f={f.size}, n_out, n_in), got {np.shape(self.frf)}")
        if f.size < 3 or not np.all(np.isfinite(f)) or np.any(f <= 0):
            raise CalibrationError(f"{name}: frequency_hz needs >= 3 finite positive lines")
        if not np.all(np.isfinite(H)):
            raise CalibrationError(f"{name}: frf has NaN/inf lines: drop invalid lines first")
        if not (np.isfinite(self.level) and self.level > 0):
            raise CalibrationError(f"{name}: level must be finite and > 0, got {self.level}")
        if self.quantity not in FRF_QUANTITIES:
            raise CalibrationError(f"{name}: quantity {self.quantity!r} not in {sorted(FRF_QUANTITIES)}")
        if self.sweep not in ("up", "down", "unknown"):
            raise CalibrationError(f"{name}: sweep {self.sweep!r} not in ('up', 'down', 'unknown')")
        order = np.argsort(f, kind="stable")
        if np.any(np.diff(f[order]) <= 0):
            raise CalibrationError(f"{name}: duplicate frequency lines")
        se = None
        if self.std_error is not None:
            se = np.asarray(self.std_error, float)
            if se.ndim == 1:
                se = se[:, None, None]
            if se.shape != H.shape:
                raise CalibrationError(f"{name}: std_error shape {se.shape} != frf shape {H.shape}")
            if not np.all(np.isfinite(se)) or np.any(se <= 0):
                raise CalibrationError(f"{name}: std_error must be finite and > 0 on every line")
            se = se[order]
        object.__setattr__(self, "frequency_hz", f[order])
        object.__setattr__(self, "frf", H[order])
        object.__setattr__(self, "std_error", se)
        object.__setattr__(self, "level", float(self.level))

    @property
    def name(self) -> str:
        return self.label or f"level {self.level:.4g} {self.unit}"


def frf_level_from_run(run, level: float | None = None, unit: str = "N", valid_only: bool = True) -> FRFLevel:
    """An :class:`FRFLevel` from a run file read by :func:`acquisition.runfile.read_run`.

    ``level`` defaults to the median achieved force over the used lines (mean over
    drives), N. The sweep order comes from ``time_s`` (measurement order).
    """
    m = np.asarray(run.valid, bool) if valid_only else np.ones(run.n_lines, bool)
    if m.sum() < 3:
        raise CalibrationError(f"{run.path}: only {int(m.sum())} valid lines")
    if level is None:
        level = float(np.median(np.mean(np.asarray(run.force_n)[m], axis=1)))
    t = np.asarray(run.time_s, float)[m]
    sweep = "unknown"
    if np.all(np.isfinite(t)) and t.size > 1:
        dt = np.diff(t)  # lines are stored by ascending frequency
        sweep = "up" if np.all(dt > 0) else "down" if np.all(dt < 0) else "unknown"
    return FRFLevel(
        frequency_hz=np.asarray(run.frequency_hz)[m],
        frf=np.asarray(run.frf)[m],
        level=level,
        std_error=np.asarray(run.std_error)[m],
        unit=unit,
        quantity=run.quantity,
        label=str(run.path),
        sweep=sweep,
    )


# -------------------------------------------------------------- local mode fit
@dataclass(frozen=True)
class ModeFit:
    """One resonance fitted at one level (one complex mode + constant + slope per channel).

    ``frequency_hz``/``damping`` with their standard deviations: Gauss-Newton,
    scaled by ``max(1, chi2/dof)`` when standard errors are given (model misfit
    inflates them); without standard errors the heteroscedasticity-consistent
    sandwich estimate from the fit residual (HC1). ``chi2_per_dof`` is NaN
    without standard errors.
    """

    frequency_hz: float
    damping: float
    frequency_sd_hz: float
    damping_sd: float
    chi2_per_dof: float
    n_lines: int
    residual_rms: np.ndarray  # (n_ch,) RMS fit residual, receptance units
    residual_rel_rms: np.ndarray  # (n_ch,) RMS of the fit residual relative to the FRF
    peak_snr: float  # modal peak / noise at the peak, best channel
    band_hz: tuple[float, float]


def _receptance(level: FRFLevel) -> tuple[np.ndarray, np.ndarray | None]:
    w = 2 * np.pi * level.frequency_hz
    fac = quantity_factor(level.quantity, w)
    H = level.frf / fac[:, None, None]
    se = None if level.std_error is None else level.std_error / np.abs(fac)[:, None, None]
    return H, se


def _basis(w: np.ndarray, wr: float, zeta: float, wc: float, with_slope: bool) -> np.ndarray:
    D = wr**2 - w**2 + 2j * zeta * wr * w
    cols = [1.0 / D, np.ones_like(w, dtype=complex)]
    if with_slope:
        cols.append((w - wc) / wc + 0j)
    return np.stack(cols, axis=1)


def _linear_solve(Phi: np.ndarray, Y: np.ndarray, W: np.ndarray) -> np.ndarray:
    """Complex weighted LS per channel: Y[:, c] ~ Phi @ coef[:, c], weights W[:, c]."""
    coef = np.empty((Phi.shape[1], Y.shape[1]), complex)
    for c in range(Y.shape[1]):
        A = Phi * W[:, c, None]
        coef[:, c] = np.linalg.lstsq(A, Y[:, c] * W[:, c], rcond=None)[0]
    return coef


def _fit_mode(
    f: np.ndarray,
    Y: np.ndarray,
    S: np.ndarray | None,
    f0: float,
    zeta0: float,
    band: tuple[float, float],
    name: str,
) -> ModeFit:
    """Fit one resonance on the lines inside ``band``; Y (n, n_ch) receptance, S its std errors."""
    from scipy.optimize import least_squares

    m = (f >= band[0]) & (f <= band[1])
    n = int(m.sum())
    if n < 6:
        raise CalibrationError(
            f"{name}: only {n} lines in {band[0]:.4g}-{band[1]:.4g} Hz around the mode at {f0:.4g} Hz (need >= 6)"
        )
    w = 2 * np.pi * f[m]
    Y = Y[m]
    n_ch = Y.shape[1]
    W = np.ones(Y.shape) if S is None else 1.0 / S[m]
    wc = 2 * np.pi * f0
    with_slope = n >= 10
    # scale the weights so that the unknowns are O(1) for the optimizer
    scale = np.sqrt(np.mean(np.abs(Y * W) ** 2))

    def resid(x):
        wr, zeta = wc * (1 + x[0]), np.exp(x[1])
        Phi = _basis(w, wr, zeta, wc, with_slope)
        coef = _linear_solve(Phi, Y, W)
        r = (Phi @ coef - Y) * W / scale
        return np.concatenate([r.real.ravel(), r.imag.ravel()])

    best = None
    for dz in (0.0, np.log(0.5), np.log(2.0)):  # a few damping starts: cheap insurance against a local minimum
        sol = least_squares(resid, [0.0, np.log(zeta0) + dz], x_scale=[zeta0, 1.0], method="lm")
        if best is None or sol.cost < best.cost:
            best = sol
    wr, zeta = wc * (1 + best.x[0]), float(np.exp(best.x[1]))
    if not (0 < zeta < 0.5) or not (band[0] <= wr / (2 * np.pi) <= band[1]):
        raise CalibrationError(
            f"{name}: the local fit near {f0:.4g} Hz did not converge to a resonance"
            f" inside {band[0]:.4g}-{band[1]:.4g} Hz"
        )
    Phi = _basis(w, wr, zeta, wc, with_slope)
    coef = _linear_solve(Phi, Y, W)
    R = Phi @ coef - Y
    # full Jacobian (wr, zeta, Re/Im of every linear coefficient) of the weighted complex residual
    D = wr**2 - w**2 + 2j * zeta * wr * w
    A = coef[0]  # (n_ch,)
    dwr = -(A[None, :] * ((2 * wr + 2j * zeta * w) / D**2)[:, None])
    dz = -(A[None, :] * ((2j * wr * w) / D**2)[:, None])
    n_lin = Phi.shape[1]
    cols = [dwr * W, dz * W]
    for c in range(n_ch):
        for k in range(n_lin):
            for unit in (1.0, 1j):
                col = np.zeros(Y.shape, complex)
                col[:, c] = unit * Phi[:, k] * W[:, c]
                cols.append(col)
    # E|e|^2 = s^2 gives Re and Im variance s^2 / 2 each: sqrt(2) makes every real residual unit-variance
    J = np.sqrt(2) * np.stack([np.concatenate([c.real.ravel(), c.imag.ravel()]) for c in cols], axis=1)
    r = np.sqrt(2) * np.concatenate([(R * W).real.ravel(), (R * W).imag.ravel()])
    dof = r.size - J.shape[1]
    if dof < 1:
        raise CalibrationError(f"{name}: too few lines for the local fit near {f0:.4g} Hz")
    chi2 = float(r @ r) / dof
    # column scaling keeps J^T J well conditioned (coefficients span many decades)
    cn = np.linalg.norm(J, axis=0)
    cn[cn == 0] = 1.0
    Js = J / cn
    Ainv = np.linalg.pinv(Js.T @ Js)
    if S is not None:
        # with standard errors, misfit beyond noise inflates the covariance
        cov_s = Ainv * max(1.0, chi2)
    else:
        # without, the residual is the noise, of unknown shape over the lines (absolute, relative or
        # between): the heteroscedasticity-consistent sandwich (HC1) instead of one common variance
        Jr = Js * r[:, None]
        cov_s = Ainv @ (Jr.T @ Jr) @ Ainv * (r.size / dof)
    cov = cov_s / np.outer(cn, cn)
    sd_wr, sd_z = np.sqrt(max(cov[0, 0], 0.0)), np.sqrt(max(cov[1, 1], 0.0))
    # residual RMS per channel, absolute and relative, corrected for the fitted parameters
    dof_scale = r.size / dof
    rms = np.sqrt(np.mean(np.abs(R) ** 2, axis=0) * dof_scale)
    rel_rms = np.sqrt(np.mean(np.abs(R / Y) ** 2, axis=0) * dof_scale)
    # the mode's peak (|A| / (2 zeta wr^2)) against the noise there: a noise bump fitted as a mode scores low
    k_pk = int(np.argmin(np.abs(w - wr)))
    noise_pk = rms if S is None else S[m][k_pk]
    peak_snr = float(np.max(np.abs(A) / (2 * zeta * wr**2) / noise_pk))
    return ModeFit(
        frequency_hz=float(wr / (2 * np.pi)),
        damping=zeta,
        frequency_sd_hz=float(sd_wr / (2 * np.pi)),
        damping_sd=float(sd_z),
        chi2_per_dof=chi2 if S is not None else float("nan"),
        n_lines=n,
        residual_rms=rms,
        residual_rel_rms=rel_rms,
        peak_snr=peak_snr,
        band_hz=(float(band[0]), float(band[1])),
    )


def _magnitude_curve(level: FRFLevel) -> np.ndarray:
    """Channel-averaged receptance magnitude, each channel normalized by its maximum."""
    H, _ = _receptance(level)
    a = np.abs(H).reshape(H.shape[0], -1)
    a = a / np.maximum(a.max(axis=0), np.finfo(float).tiny)
    return a.mean(axis=1)


def _half_power_zeta(f: np.ndarray, a: np.ndarray, k: int) -> float:
    """Damping from the half-power width around peak index k (linear interpolation)."""
    half = a[k] / np.sqrt(2)
    lo = k
    while lo > 0 and a[lo] > half:
        lo -= 1
    hi = k
    while hi < a.size - 1 and a[hi] > half:
        hi += 1
    got_lo, got_hi = a[lo] <= half, a[hi] <= half
    if got_lo and got_hi:
        fl = f[lo] + (half - a[lo]) * (f[lo + 1] - f[lo]) / (a[lo + 1] - a[lo])
        fh = f[hi - 1] + (half - a[hi - 1]) * (f[hi] - f[hi - 1]) / (a[hi] - a[hi - 1])
        span = fh - fl
    elif got_lo or got_hi:  # one side inside the data: use it twice
        span = 2 * (f[hi] - f[k] if got_hi else f[k] - f[lo])
    else:
        span = f[-1] - f[0]
    df = np.median(np.diff(f))
    return float(max(span, df) / (2 * f[k]))


def find_modes(level: FRFLevel, prominence_decades: float = 0.3, min_snr: float = 5.0) -> np.ndarray:
    """Resonance frequencies (Hz) picked as peaks of the channel-averaged receptance magnitude.

    A peak must stand ``prominence_decades`` above its surroundings in log10
    magnitude (0.3: a factor 2) and, when standard errors are given, exceed
    ``min_snr`` times its standard error on at least one channel (a noise
    bump in a resonance's far tail is not a mode). Pass ``modes_hz`` to
    :func:`level_dependence` instead when the modes are known (identification)
    or close together.
    """
    from scipy.signal import find_peaks

    a = _magnitude_curve(level)
    k, _ = find_peaks(np.log10(np.maximum(a, np.finfo(float).tiny)), prominence=prominence_decades)
    if k.size == 0:
        # one resonance filling the band (narrow stepped-sine sweeps) has no prominence on both sides
        j = int(np.argmax(a))
        if 0 < j < a.size - 1 and a[j] > 2 * min(a[0], a[-1]):
            k = np.array([j])
    if level.std_error is not None and k.size:
        snr = np.abs(level.frf[k]) / level.std_error[k]
        k = k[snr.reshape(k.size, -1).max(axis=1) >= min_snr]
    return level.frequency_hz[k]


# ----------------------------------------------------------- level dependence
@dataclass(frozen=True)
class ModeChange:
    """How one modal quantity of one mode changes with level.

    ``values``/``sds`` per level (ascending level); ``slope_per_decade`` of the
    weighted line against log10(level) with ``z`` its significance (sigma);
    ``scatter_z`` judges the spread about that line (non-monotonic changes).
    """

    mode: int
    frequency_hz: float
    quantity: str  # "frequency" or "damping"
    levels: tuple[float, ...]
    values: tuple[float, ...]
    sds: tuple[float, ...]
    slope_per_decade: float
    z: float
    scatter_z: float
    ratio: float  # value at the highest level / value at the lowest
    flagged: bool

    def to_dict(self) -> dict:
        return {
            "mode": self.mode,
            "frequency_hz": self.frequency_hz,
            "quantity": self.quantity,
            "levels": list(self.levels),
            "values": list(self.values),
            "sds": list(self.sds),
            "slope_per_decade": self.slope_per_decade,
            "z": self.z,
            "scatter_z": self.scatter_z,
            "ratio": self.ratio,
            "relative_change": self.ratio - 1.0,
            "flagged": self.flagged,
        }


@dataclass(frozen=True)
class LevelPair:
    """Model-free comparison of one level with the lowest one (log-ratio metric)."""

    level_low: float
    level_high: float
    n_values: int
    sd: float  # square deviation delta = eps^H eps / N between the two FRFs
    noise_sd: float  # delta expected from noise (+ repeatability); NaN if no noise floor
    z: float
    flagged: bool
    #: the line where the two FRFs differ most against their noise (sum over channels of |eps|^2 / var), Hz
    peak_hz: float = float("nan")

    def to_dict(self) -> dict:
        return {k: getattr(self, k)
                for k in ("level_low", "level_high", "n_values", "sd", "noise_sd", "z", "flagged", "peak_hz")}


@dataclass(frozen=True)
class LevelDependence:
    """Result of :func:`level_dependence` (levels ascending)."""

    flagged: bool
    levels: tuple[float, ...]
    labels: tuple[str, ...]
    unit: str
    modes_hz: tuple[float, ...]
    changes: tuple[ModeChange, ...]
    pairs: tuple[LevelPair, ...]
    fits: tuple[tuple[ModeFit, ...], ...]  # [level][mode]
    noise: str  # where the noise floor came from
    z_threshold: float
    evidence: tuple[str, ...]

    def to_dict(self) -> dict:
        return {
            "flagged": self.flagged,
            "levels": list(self.levels),
            "labels": list(self.labels),
            "unit": self.unit,
            "modes_hz": list(self.modes_hz),
            "changes": [c.to_dict() for c in self.changes],
            "pairs": [p.to_dict() for p in self.pairs],
            "fits": [
                [
                    {
                        "frequency_hz": m.frequency_hz,
                        "frequency_sd_hz": m.frequency_sd_hz,
                        "damping": m.damping,
                        "damping_sd": m.damping_sd,
                        "peak_snr": m.peak_snr,
                        "n_lines": m.n_lines,
                        "band_hz": list(m.band_hz),
                    }
                    for m in per_level
                ]
                for per_level in self.fits
            ],
            "noise": self.noise,
            "z_threshold": self.z_threshold,
            "evidence": list(self.evidence),
        }


def _trend(u: np.ndarray, x: np.ndarray, s: np.ndarray) -> tuple[float, float, float]:
    """Weighted line x ~ a + b u: (b, z of b, z of the scatter about the line)."""
    wts = 1.0 / s**2
    if u.size == 2:
        b = (x[1] - x[0]) / (u[1] - u[0])
        z = (x[1] - x[0]) / np.sqrt(s[0] ** 2 + s[1] ** 2)
        return float(b), float(z), float("nan")
    ub = np.sum(wts * u) / np.sum(wts)
    xb = np.sum(wts * x) / np.sum(wts)
    suu = np.sum(wts * (u - ub) ** 2)
    b = np.sum(wts * (u - ub) * (x - xb)) / suu
    z = b * np.sqrt(suu)
    r = x - xb - b * (u - ub)
    return float(b), float(z), _chi2_z(float(np.sum(wts * r**2)), u.size - 2)


def _fmt_pct(x: float) -> str:
    return f"{100 * x:.3g} %"


def level_dependence(
    levels: Sequence[FRFLevel],
    modes_hz: Sequence[float] | None = None,
    *,
    z_threshold: float = 5.0,
    band_zeta: float = 5.0,
    frequency_repeatability: float = 0.0,
    damping_repeatability: float = 0.0,
    scatter_delta: float = 0.0,
    max_relative_noise: float = 0.3,
    min_snr: float = 5.0,
) -> LevelDependence:
    """Does each mode's natural frequency and damping change with excitation level beyond noise?

    Parameters
    ----------
    levels : sequence of FRFLevel
        The same article and channels at two or more distinct levels (one unit).
    modes_hz : sequence of float, optional
        Approximate natural frequencies, Hz; default :func:`find_modes` on the lowest level.
    z_threshold : float
        Significance (sigma) above which a trend or a model-free difference is flagged.
    band_zeta : float
        Each mode is fitted on ``f_r (1 +- band_zeta * zeta)`` (zeta from the
        half-power width, the largest over the levels, so all levels use one band),
        cut halfway to the neighbouring modes.
    frequency_repeatability, damping_repeatability : float
        Relative test-to-test scatter (1 sigma) of f_n and zeta between repeat
        tests at one level (e.g. from the ensemble); added in quadrature to the
        noise. 0: noise only.
    scatter_delta : float
        Test-to-test square deviation (log-ratio metric, :func:`pairwise_sd`)
        between repeat tests. The model-free check allows it in full: a
        difference between levels of that size is explained by repeatability,
        and only the excess is judged against the noise.
    max_relative_noise : float
        Lines whose relative standard error exceeds this are left out of the
        model-free check (the log ratio is not Gaussian there: antiresonances).
    min_snr : float
        A mode whose fitted peak is less than ``min_snr`` times the noise there
        (standard error, or fit residual RMS) at any level is left out, and the
        evidence says so.

    Returns
    -------
    LevelDependence
    """
    positive = (("z_threshold", z_threshold), ("band_zeta", band_zeta), ("max_relative_noise", max_relative_noise))
    for key, val in positive:
        if not (np.isfinite(val) and val > 0):
            raise CalibrationError(f"level_dependence: {key} must be finite and > 0, got {val}")
    for key, val in (
        ("frequency_repeatability", frequency_repeatability),
        ("damping_repeatability", damping_repeatability),
        ("scatter_delta", scatter_delta),
        ("min_snr", min_snr),
    ):
        if not (np.isfinite(val) and val >= 0):
            raise CalibrationError(f"level_dependence: {key} must be finite and >= 0, got {val}")
    levels = sorted(levels, key=lambda d: d.level)
    if len(levels) < 2:
        raise CalibrationError("level dependence needs FRFs at two or more levels")
    names = [d.name for d in levels]
    lv = np.array([d.level for d in levels])
    if np.any(np.diff(lv) <= 0):
        raise CalibrationError(f"two FRF sets have the same level {lv}: {names}")
    units = {d.unit for d in levels}
    if len(units) != 1:
        raise CalibrationError(f"levels are given in different units {sorted(units)}: {names}")
    shapes = {d.frf.shape[1:] for d in levels}
    if len(shapes) != 1:
        raise CalibrationError(f"the levels have different channel sets {sorted(shapes)}: {names}")
    if modes_hz is None:
        modes = find_modes(levels[0], min_snr=min_snr)
        if modes.size == 0:
            raise CalibrationError(f"{names[0]}: no resonance peak found; pass modes_hz")
    else:
        modes = np.sort(np.asarray(modes_hz, float))
    # damping guess per mode: half-power width, the widest over the levels
    zeta0 = np.zeros(modes.size)
    for d in levels:
        a = _magnitude_curve(d)
        for r, fr in enumerate(modes):
            k = int(np.argmin(np.abs(d.frequency_hz - fr)))
            # the local maximum nearest to the given frequency
            while 0 < k < a.size - 1 and max(a[k - 1], a[k + 1]) > a[k]:
                k = k - 1 if a[k - 1] > a[k + 1] else k + 1
            zeta0[r] = max(zeta0[r], _half_power_zeta(d.frequency_hz, a, k))
    bands = []
    for r, fr in enumerate(modes):
        lo, hi = fr * (1 - band_zeta * zeta0[r]), fr * (1 + band_zeta * zeta0[r])
        if r > 0:
            lo = max(lo, 0.5 * (modes[r - 1] + fr))
        if r < modes.size - 1:
            hi = min(hi, 0.5 * (modes[r + 1] + fr))
        bands.append((lo, hi))

    # a mode whose local fit cannot be made at some level (too few lines in its band, no resonance inside
    # it) is left out with the reason, and the others are checked: one crowded band does not void the check
    fits, failed = [], {}
    for d in levels:
        Y, S = _receptance(d)
        Y = Y.reshape(Y.shape[0], -1)
        S = None if S is None else S.reshape(S.shape[0], -1)
        z0 = np.clip(zeta0, 1e-5, 0.2)
        row = []
        for r, fr in enumerate(modes):
            try:
                row.append(_fit_mode(d.frequency_hz, Y, S, fr, z0[r], bands[r], f"{d.name}, mode {r + 1}"))
            except CalibrationError as exc:
                failed.setdefault(r, str(exc))
                row.append(None)
        fits.append(tuple(row))
    # a "mode" that does not stand min_snr above the noise at every level is a noise bump: dropped
    snr = np.array([[np.nan if fl[r] is None else fl[r].peak_snr for fl in fits] for r in range(modes.size)])
    weak = np.array([r in failed or snr[r].min() < min_snr for r in range(modes.size)])
    dropped = [
        f"mode near {modes[r]:.5g} Hz left out: {failed[r]}" if r in failed else
        f"peak near {modes[r]:.5g} Hz left out: modal peak only {snr[r].min():.3g}x the noise (< {min_snr:g})"
        for r in np.nonzero(weak)[0]
    ]
    if weak.all():
        raise CalibrationError(f"no resonance could be checked in {names}: {'; '.join(dropped)}")
    modes = modes[~weak]
    fits = [tuple(fl[r] for r in np.nonzero(~weak)[0]) for fl in fits]
    has_se = all(d.std_error is not None for d in levels)
    noise = "per-line standard errors" if has_se else "local fit residual (no standard errors)"
    if frequency_repeatability or damping_repeatability or scatter_delta:
        noise += " + test-to-test repeatability"

    u = np.log10(lv)
    changes = []
    unit = levels[0].unit
    for r in range(modes.size):
        for q, rep in (("frequency", frequency_repeatability), ("damping", damping_repeatability)):
            at = [fl[r] for fl in fits]
            x = np.array([m.frequency_hz if q == "frequency" else m.damping for m in at])
            s = np.array([m.frequency_sd_hz if q == "frequency" else m.damping_sd for m in at])
            s = np.sqrt(s**2 + (rep * x) ** 2)
            s = np.maximum(s, 1e-12 * np.abs(x))
            b, z, sz = _trend(u, x, s)
            changes.append(
                ModeChange(
                    mode=r + 1,
                    frequency_hz=float(fits[0][r].frequency_hz),
                    quantity=q,
                    levels=tuple(lv.tolist()),
                    values=tuple(x.tolist()),
                    sds=tuple(s.tolist()),
                    slope_per_decade=b,
                    z=z,
                    scatter_z=sz,
                    ratio=float(x[-1] / x[0]),
                    flagged=bool(abs(z) > z_threshold),
                )
            )

    # model-free: every level against the lowest on the lines they share
    pairs = []
    ref = levels[0]
    for i, d in enumerate(levels[1:], start=1):
        ia, ib = _common_lines(ref.frequency_hz, d.frequency_hz)
        if ia.size == 0:
            continue
        Ha, Hb = ref.frf[ia], d.frf[ib]
        Sa, Sb = _noise_of(ref, fits[0], ia), _noise_of(d, fits[i], ib)
        rel2 = (Sa / np.abs(Ha)) ** 2 + (Sb / np.abs(Hb)) ** 2
        keep = np.sqrt(rel2) <= max_relative_noise
        if keep.sum() == 0:
            continue
        eps = log_deviation(Hb[keep], Ha[keep])
        var = rel2[keep] / LN10**2
        sd = square_deviation(eps)
        # repeatability is a systematic difference between tests, not independent per line:
        # it is an allowance subtracted from the statistic, which is then judged against noise
        t = float(np.sum(2 * (np.abs(eps) ** 2 - scatter_delta) / var))
        z = _chi2_z(max(t, 0.0), 2 * eps.size)
        # where the difference is: the line with the largest noise-normalised excess, over its channels
        per_line = np.zeros(keep.shape[0])
        np.add.at(per_line, np.nonzero(keep)[0], 2 * (np.abs(eps) ** 2 - scatter_delta) / var)
        peak_hz = float(ref.frequency_hz[ia][int(np.argmax(per_line))])
        pairs.append(
            LevelPair(
                level_low=float(ref.level),
                level_high=float(d.level),
                n_values=int(eps.size),
                sd=sd,
                noise_sd=float(np.mean(var) + scatter_delta),
                z=z,
                flagged=bool(z > z_threshold),
                peak_hz=peak_hz,
            )
        )

    flagged_modes = [c for c in changes if c.flagged]
    flagged = bool(flagged_modes or any(p.flagged for p in pairs))
    ev = []
    span = f"{lv[0]:.3g}-{lv[-1]:.3g} {unit}"
    for r in range(modes.size):
        cf, cz = changes[2 * r], changes[2 * r + 1]
        zs = cz.values
        head = f"mode {r + 1} at {cf.values[0]:.5g} Hz"
        damp = (
            f"damping {_fmt_pct(zs[0])} -> {_fmt_pct(zs[-1])} over {span} (x{cz.ratio:.3g}, {abs(cz.z):.3g} sigma"
            + (")" if cz.flagged else ", not significant)")
        )
        freq = (
            f"frequency {100 * (cf.ratio - 1):+.3g} % ({cf.values[0]:.5g} -> {cf.values[-1]:.5g} Hz,"
            f" {abs(cf.z):.3g} sigma"
            + (")" if cf.flagged else ", not significant)")
        )
        parts = [damp, freq] if cz.flagged or not cf.flagged else [freq, damp]
        line = f"{head}: " + "; ".join(parts)
        # a monotonic change that is not straight in log(level) is still a trend; only a
        # change of direction beyond noise is worth a note (repeat tests tell the two causes apart)
        notes = [
            c
            for c in (cf, cz)
            if np.isfinite(c.scatter_z) and c.scatter_z > z_threshold and np.unique(np.sign(np.diff(c.values))).size > 1
        ]
        for c in notes:
            line += (
                f"; {c.quantity} scatters about its trend by {c.scatter_z:.3g} sigma"
                " (not monotonic in level: test-to-test variation or nonlinearity)"
            )
        ev.append(line)
    for p in pairs:
        if np.isfinite(p.z):
            ev.append(
                f"FRF at {p.level_high:.3g} vs {p.level_low:.3g} {unit}: SD {p.sd:.3g} vs {p.noise_sd:.3g} from noise"
                f" ({p.z:.3g} sigma{'' if p.flagged else ', within noise'})"
                + (f", largest at {p.peak_hz:.5g} Hz" if p.flagged else "")
            )
    ev.insert(
        0,
        (
            f"level dependent: {', '.join(sorted({f'mode {c.mode} {c.quantity}' for c in flagged_modes}))}"
            if flagged_modes
            else "level dependent (model-free FRF difference)" if flagged else "no level dependence beyond noise"
        )
        + f" ({len(levels)} levels, {span}; noise from {noise}; threshold {z_threshold:g} sigma)",
    )
    ev.extend(dropped)
    return LevelDependence(
        flagged=flagged,
        levels=tuple(lv.tolist()),
        labels=tuple(names),
        unit=unit,
        modes_hz=tuple(float(fits[0][r].frequency_hz) for r in range(modes.size)),
        changes=tuple(changes),
        pairs=tuple(pairs),
        fits=tuple(fits),
        noise=noise,
        z_threshold=z_threshold,
        evidence=tuple(ev),
    )


def _common_lines(fa: np.ndarray, fb: np.ndarray, rtol: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the lines two sorted frequency vectors share (within ``rtol``)."""
    j = np.clip(np.searchsorted(fb, fa), 0, fb.size - 1)
    j0 = np.clip(j - 1, 0, fb.size - 1)
    j = np.where(np.abs(fb[j0] - fa) < np.abs(fb[j] - fa), j0, j)
    ok = np.abs(fb[j] - fa) <= rtol * fa
    return np.nonzero(ok)[0], j[ok]


def _noise_of(d: FRFLevel, fits: tuple[ModeFit, ...], idx: np.ndarray) -> np.ndarray:
    """Per-line noise (FRF units) on lines idx: the standard errors, or from the fit residual.

    Without standard errors the residual of the local fits says how large the noise
    is but not how it is spread over the lines; the larger of the two simple models
    is taken on every line (absolute: the residual RMS; relative: the relative
    residual RMS times |H|), so the floor is not underestimated whichever holds.
    """
    if d.std_error is not None:
        return d.std_error[idx]
    shape = d.frf.shape[1:]
    absolute = np.sqrt(np.mean([f.residual_rms**2 for f in fits], axis=0)).reshape(shape)
    relative = np.sqrt(np.mean([f.residual_rel_rms**2 for f in fits], axis=0)).reshape(shape)
    w = 2 * np.pi * d.frequency_hz[idx]
    return np.maximum(
        absolute[None] * (w ** quantity_power(d.quantity))[:, None, None], relative[None] * np.abs(d.frf[idx])
    )


# ------------------------------------------------------------------ distortion
@dataclass(frozen=True)
class DistortedLine:
    frequency_hz: float
    channel: str
    thd: float
    floor: float
    mode: int  # 1-based, 0 when not attributed
    relation: str  # "resonance", "superharmonic 1/2", "superharmonic 1/3" or ""

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in ("frequency_hz", "channel", "thd", "floor", "mode", "relation")}


@dataclass(frozen=True)
class Distortion:
    """Result of :func:`distortion`."""

    flagged: bool
    threshold: float
    floor: tuple[float, ...]  # per channel
    channels: tuple[str, ...]
    lines: tuple[DistortedLine, ...]
    max_thd: tuple[float, ...]  # per channel
    evidence: tuple[str, ...]

    def to_dict(self) -> dict:
        return {
            "flagged": self.flagged,
            "threshold": self.threshold,
            "floor": list(self.floor),
            "channels": list(self.channels),
            "lines": [x.to_dict() for x in self.lines],
            "max_thd": list(self.max_thd),
            "evidence": list(self.evidence),
        }


def distortion(
    frequency_hz,
    thd,
    *,
    channels: Sequence[str] | None = None,
    threshold: float = 0.05,
    floor=None,
    floor_factor: float = 3.0,
    modes_hz: Sequence[float] | None = None,
    damping: Sequence[float] | None = None,
    label: str = "",
) -> Distortion:
    """Flag lines whose harmonic distortion exceeds a threshold and the noise floor.

    Parameters
    ----------
    frequency_hz : (n_f,) float
        Lines, Hz.
    thd : (n_f, n_ch) float
        Total harmonic distortion per line and channel, fraction (``Run.thd``:
        sensors then drives).
    channels : sequence of str, optional
        Channel names for the words (default ``ch0..``).
    threshold : float
        THD (fraction) above which a line is distorted (0.05 = 5 %).
    floor : float or (n_ch,) float, optional
        THD that noise alone produces on each channel (fraction). Default: the
        channel's median THD over the lines (distortion is local to resonances,
        so the median line is a noise line); pass it when distortion is broad.
    floor_factor : float
        A line must also exceed ``floor_factor * floor``.
    modes_hz, damping : sequences, optional
        Natural frequencies (Hz) and damping ratios to attribute flagged lines
        to: at a resonance (within ``max(3 zeta, 0.005)`` relative, or 1.5 line
        spacings on a coarse grid), or at 1/2 or 1/3 of one (superharmonic
        resonance of a polynomial stiffness).
    label : str
        Name of the run for the words.
    """
    f = np.asarray(frequency_hz, float).ravel()
    T = np.asarray(thd, float)
    if T.ndim == 1:
        T = T[:, None]
    name = label or "run"
    if T.ndim != 2 or T.shape[0] != f.size:
        raise CalibrationError(f"{name}: thd must be (n_f={f.size}, n_channels), got {np.shape(thd)}")
    n_ch = T.shape[1]
    chans = tuple(channels) if channels is not None else tuple(f"ch{c}" for c in range(n_ch))
    if len(chans) != n_ch:
        raise CalibrationError(f"{name}: {len(chans)} channel names for {n_ch} THD columns")
    if not (threshold > 0):
        raise CalibrationError(f"{name}: THD threshold must be > 0, got {threshold}")
    finite = np.isfinite(T)
    if floor is None:
        fl = np.array([np.median(T[finite[:, c], c]) if finite[:, c].any() else np.nan for c in range(n_ch)])
    else:
        fl = np.broadcast_to(np.asarray(floor, float), (n_ch,)).copy()
    modes = np.asarray(modes_hz if modes_hz is not None else [], float)
    zeta = np.asarray(damping, float) if damping is not None else np.zeros(modes.size)
    if zeta.size != modes.size:
        raise CalibrationError(f"{name}: {zeta.size} damping values for {modes.size} modes")
    tol = np.maximum(3 * zeta, 0.005)

    spacing = np.gradient(f) if f.size > 1 else np.zeros(1)

    def attribute(i: int) -> tuple[int, str]:
        fk = f[i]
        line_tol = 1.5 * abs(spacing[i]) / fk  # a coarse grid cannot land closer than its spacing
        for k, rel in ((1, "resonance"), (2, "superharmonic 1/2"), (3, "superharmonic 1/3")):
            d = np.abs(fk * k / modes - 1) if modes.size else np.array([])
            if d.size and d.min() <= max(tol[np.argmin(d)], line_tol):
                return int(np.argmin(d)) + 1, rel
        return 0, ""

    lines = []
    bad = finite & (T > threshold) & (T > floor_factor * np.nan_to_num(fl, nan=0.0)[None, :])
    for k, c in zip(*np.nonzero(bad)):
        mode, rel = attribute(int(k))
        lines.append(DistortedLine(float(f[k]), chans[c], float(T[k, c]), float(fl[c]), mode, rel))
    ev = []
    for c in range(n_ch):
        rows = [x for x in lines if x.channel == chans[c]]
        if not rows:
            continue
        worst = max(rows, key=lambda x: x.thd)
        where = sorted({(x.mode, x.relation) for x in rows if x.mode})
        at = "; ".join(f"{rel} of mode {m} ({modes[m - 1]:.5g} Hz)" for m, rel in where) or "not at a known mode"
        ev.append(
            f"{name} {chans[c]}: THD above {_fmt_pct(threshold)} on {len(rows)} line(s), up to {_fmt_pct(worst.thd)}"
            f" at {worst.frequency_hz:.5g} Hz (floor {_fmt_pct(fl[c])}); {at}"
        )
    if not lines:
        ev.append(
            f"{name}: THD below {_fmt_pct(threshold)} (or within {floor_factor:g}x the noise floor) on every line"
        )
    return Distortion(
        flagged=bool(lines),
        threshold=float(threshold),
        floor=tuple(fl.tolist()),
        channels=chans,
        lines=tuple(lines),
        max_thd=tuple(float(np.max(T[finite[:, c], c])) if finite[:, c].any() else float("nan") for c in range(n_ch)),
        evidence=tuple(ev),
    )


def distortion_of_run(run, **kwargs) -> Distortion:
    """:func:`distortion` of a run file (all lines; channel names: sensors then drives)."""
    names = [s.name for s in run.sensors] + [d.name for d in run.drives]
    # every line, flagged ones included: a line flagged for THD is the evidence looked for
    return distortion(run.frequency_hz, run.thd, channels=names, label=str(run.path), **kwargs)


# ------------------------------------------------------------- sweep direction
@dataclass(frozen=True)
class SweepBand:
    """A contiguous band of lines where the up and down sweeps differ beyond noise."""

    f_low_hz: float
    f_high_hz: float
    n_lines: int
    max_relative_difference: float
    max_z: float
    peak_up_hz: float
    peak_down_hz: float

    def to_dict(self) -> dict:
        keys = ("f_low_hz", "f_high_hz", "n_lines", "max_relative_difference", "max_z", "peak_up_hz", "peak_down_hz")
        return {k: getattr(self, k) for k in keys}


@dataclass(frozen=True)
class SweepDirection:
    """Result of :func:`sweep_direction`."""

    flagged: bool
    n_lines: int
    z_overall: float
    bands: tuple[SweepBand, ...]
    noise: str
    z_threshold: float
    evidence: tuple[str, ...]

    def to_dict(self) -> dict:
        return {
            "flagged": self.flagged,
            "n_lines": self.n_lines,
            "z_overall": self.z_overall,
            "bands": [b.to_dict() for b in self.bands],
            "noise": self.noise,
            "z_threshold": self.z_threshold,
            "evidence": list(self.evidence),
        }


def sweep_direction(
    up: FRFLevel, down: FRFLevel, *, z_threshold: float = 5.0, scatter_delta: float = 0.0
) -> SweepDirection:
    """Up versus down sweep over the same lines: differences beyond noise (jumps).

    Parameters
    ----------
    up, down : FRFLevel
        The two sweeps (same channels, shared lines). When their ``sweep`` order
        is known it must be "up" and "down" respectively.
    z_threshold : float
        Per-line significance (sigma) above which a line differs.
    scatter_delta : float
        Test-to-test square deviation (log-ratio metric) added to the noise.

    Notes
    -----
    Per line, ``2 |H_up - H_down|^2 / (s_up^2 + s_down^2)`` is chi-square with
    2 x n_channels degrees of freedom under noise. Without standard errors the
    relative noise is estimated from the median squared relative difference
    (the jump region must then cover less than half the lines).
    """
    if not (z_threshold > 0 and np.isfinite(scatter_delta) and scatter_delta >= 0):
        raise CalibrationError(
            f"sweep_direction: need z_threshold > 0 and scatter_delta >= 0, got {z_threshold}, {scatter_delta}"
        )
    for d, want in ((up, "up"), (down, "down")):
        if d.sweep not in ("unknown", want):
            raise CalibrationError(f"{d.name}: given as the {want} sweep but its lines were measured {d.sweep}")
    if up.frf.shape[1:] != down.frf.shape[1:]:
        raise CalibrationError(
            f"{up.name} and {down.name}: different channel sets {up.frf.shape[1:]} vs {down.frf.shape[1:]}"
        )
    ia, ib = _common_lines(up.frequency_hz, down.frequency_hz)
    if ia.size < 3:
        raise CalibrationError(f"{up.name} and {down.name} share only {ia.size} lines")
    f = up.frequency_hz[ia]
    Hu, Hd = up.frf[ia].reshape(ia.size, -1), down.frf[ib].reshape(ib.size, -1)
    Hm = 0.5 * (np.abs(Hu) + np.abs(Hd))
    d2 = np.abs(Hu - Hd) ** 2
    if up.std_error is not None and down.std_error is not None:
        var = up.std_error[ia].reshape(ia.size, -1) ** 2 + down.std_error[ib].reshape(ib.size, -1) ** 2
        noise = "per-line standard errors"
    else:
        # |d|^2/s^2 is exponential (chi2 with 2 dof / 2) per channel: median = s^2 ln 2
        rel2 = np.median(d2 / Hm**2) / np.log(2)
        var = rel2 * Hm**2
        noise = "median up/down difference (no standard errors)"
    var = var + scatter_delta * LN10**2 * Hm**2
    if scatter_delta:
        noise += " + test-to-test repeatability"
    t_line = np.sum(2 * d2 / var, axis=1)
    dof = 2 * Hu.shape[1]
    z_line = np.array([_chi2_z(float(t), dof) for t in t_line])
    z_all = _chi2_z(float(t_line.sum()), dof * ia.size)
    bad = z_line > z_threshold
    bands = []
    a_up, a_dn = np.abs(Hu).sum(axis=1), np.abs(Hd).sum(axis=1)
    for k, j in true_runs(bad):
        w = max(j - k + 1, 2)  # look a band-width either side for the two peaks
        lo, hi = max(k - w, 0), min(j + w, ia.size - 1) + 1
        rel = np.sqrt(d2[k : j + 1] / Hm[k : j + 1] ** 2).max()
        bands.append(
            SweepBand(
                f_low_hz=float(f[k]),
                f_high_hz=float(f[j]),
                n_lines=j - k + 1,
                max_relative_difference=float(rel),
                max_z=float(z_line[k : j + 1].max()),
                peak_up_hz=float(f[lo + np.argmax(a_up[lo:hi])]),
                peak_down_hz=float(f[lo + np.argmax(a_dn[lo:hi])]),
            )
        )
    ev = []
    for b in bands:
        kind = (
            " (up-sweep peak above the down-sweep peak: hardening)"
            if b.peak_up_hz > b.peak_down_hz
            else " (up-sweep peak below the down-sweep peak: softening)"
            if b.peak_up_hz < b.peak_down_hz
            else ""
        )
        ev.append(
            f"up vs down sweep differ at {b.f_low_hz:.5g}-{b.f_high_hz:.5g} Hz ({b.n_lines} line(s), up to"
            f" {_fmt_pct(b.max_relative_difference)}, {b.max_z:.3g} sigma); peaks up {b.peak_up_hz:.5g} Hz,"
            f" down {b.peak_down_hz:.5g} Hz{kind}"
        )
    if not bands:
        ev.append(
            f"up and down sweeps agree within noise on {ia.size} lines (overall {z_all:.3g} sigma; noise from {noise})"
        )
    return SweepDirection(
        flagged=bool(bands),
        n_lines=int(ia.size),
        z_overall=z_all,
        bands=tuple(bands),
        noise=noise,
        z_threshold=z_threshold,
        evidence=tuple(ev),
    )


# -------------------------------------------------------------------- verdict
@dataclass(frozen=True)
class Nonlinearity:
    """Is the test article nonlinear? The combined verdict of the three checks.

    ``verdict`` is "nonlinear" when any check is flagged, else "linear".
    ``linear_effects_admissible`` is False when nonlinear: the residual must then
    not be explained by a linear candidate effect (spring, mass) in its place.
    ``modes`` lists the level-dependence rows that are flagged (mode, quantity,
    by how much, significance, levels).
    """

    flagged: bool
    verdict: str
    modes: tuple[ModeChange, ...]
    level: LevelDependence | None = None
    distortion: Distortion | None = None
    sweep: SweepDirection | None = None
    evidence: tuple[str, ...] = field(default_factory=tuple)

    @property
    def linear_effects_admissible(self) -> bool:
        return not self.flagged

    def to_dict(self) -> dict:
        return {
            "flagged": self.flagged,
            "verdict": self.verdict,
            "linear_effects_admissible": self.linear_effects_admissible,
            "modes": [m.to_dict() for m in self.modes],
            "level": None if self.level is None else self.level.to_dict(),
            "distortion": None if self.distortion is None else self.distortion.to_dict(),
            "sweep": None if self.sweep is None else self.sweep.to_dict(),
            "evidence": list(self.evidence),
        }


def nonlinearity(
    level: LevelDependence | None = None,
    distortion: Distortion | None = None,
    sweep: SweepDirection | None = None,
) -> Nonlinearity:
    """Combine the checks that were run into one :class:`Nonlinearity` verdict."""
    checks = [c for c in (level, distortion, sweep) if c is not None]
    if not checks:
        raise CalibrationError("no nonlinearity check to combine: give level, distortion and/or sweep results")
    flagged = any(c.flagged for c in checks)
    ev = []
    for what, c in (("level dependence", level), ("harmonic distortion", distortion), ("sweep direction", sweep)):
        if c is not None:
            ev.append(f"{what}: {'FLAGGED' if c.flagged else 'not flagged'}")
            ev.extend("  " + e for e in c.evidence)
    if flagged:
        ev.append(
            "verdict: nonlinear -- the residual is not a linear effect; no added spring or mass is accepted in its"
            " place (calibrate per level, or model the nonlinear element)"
        )
    else:
        ev.append("verdict: linear -- no check exceeds the noise and repeatability floor")
    modes = tuple(c for c in level.changes if c.flagged) if level is not None else ()
    return Nonlinearity(
        flagged=flagged,
        verdict="nonlinear" if flagged else "linear",
        modes=modes,
        level=level,
        distortion=distortion,
        sweep=sweep,
        evidence=tuple(ev),
    )
