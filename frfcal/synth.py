"""Synthetic truth data for chain tests: run files, UFF58 files and the noiseless truth of a model.

A "campaign" of test articles is manufactured from a Nastran deck and a
parameter file, independently of the calibration path it is meant to test
(no reduced surrogate, no identified model):

1. **Articles.** The population offsets p_pop (given, or random 5-15 % in
   magnitude with random signs) plus per-article Gaussian scatter give each
   article's normalized parameters p_a (clipped into the parameter bounds).
2. **Full-order modes.** K(p_a), M(p_a) from :func:`femodel.parametric_model`;
   every normal mode up to ``mode_factor`` x band top by
   :func:`femodel.normal_modes` (sparse shift-invert Lanczos; dense below 600
   DOF), rigid-body modes included (they give the accelerance mass line).
3. **Residual of the higher modes, exactly.** With a positive shift s,
   R_1 = sum_{k>cut} phi_k phi_k^T B / (lambda_k + s) is one sparse solve of
   (K + sM) on the load projected onto the higher modes. The higher modes at
   frequency w follow from the series
   sum_{k>cut} phi phi^T B / (lambda_k - w^2) = sum_j (s + w^2)^j R_{j+1},
   R_{j+1} = (K + sM)^-1 M R_j, whose ratio r = (s + w_max^2)/(lambda_{cut+1} + s)
   is below 1/mode_factor^2 (plus a little); terms are added until
   r^n / (1 - r) < 1e-10, so the higher modes enter exactly (undamped: their
   damping shifts the band response by about 2 zeta w/w_k of their small share).
4. **Damping.** Modal viscous damping zeta_k per elastic mode, log-uniform in
   ``zeta_range`` and drawn once per mode index for the population; each
   article multiplies it by a log-normal factor (5 % rms). Rigid modes are
   undamped.
5. **FRFs.** e^{+i w t}; receptance
   H_x(w) = C [sum_k phi_k phi_k^T / (lambda_k - w^2 + 2 i zeta_k w_k w) + R(w)] B,
   accelerance = -w^2 H_x, arrays (n_freq, n_out, n_in), SI (m/s^2/N).
6. **Lines.** Each article gets its own adaptive-sweep-like grid: ``base_lines``
   log-spaced lines over ``data_hz`` plus ``lines_per_bandwidth`` lines per
   half-power bandwidth 2 zeta_k f_k over +-3 bandwidths around each of its
   modes in range.
7. **Noise.** Complex circular Gaussian noise with standard deviation
   sigma = sqrt((s_c |H|)^2 + floor_cd^2): s_c drawn per article and sensor
   from ``noise_range``, floor_cd = ``noise_floor`` x the median |H| of that
   FRF (sensor, drive) over the band. sigma is written as the run file's per-line standard error.

Outputs per article: an HDF5 run file (``acquisition.runfile``), a binary
UFF58 file (``acquisition.export_uff``), and one ``truth.npz`` with the
noiseless and noisy FRFs, sigma, p, modal frequencies and damping of every
article. See ``docs/synth.md``.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from frfcal.effects import Effect, EffectError, resolve_articles
from labdata import FRF_QUANTITIES, quantity_factor

#: rigid-body threshold (Hz), as femodel's
_RIGID_HZ = 1e-2
#: relative truncation of the higher-mode series
_SERIES_TOL = 1e-10
#: log-normal rms of the article-to-article damping factor
_ZETA_SCATTER = 0.05


class SynthError(ValueError):
    """Invalid input to the generator (the message names the argument or channel)."""


@dataclass(frozen=True)
class SynthChannel:
    """A sensor or drive point: a name, an FE grid and a direction.

    Parameters
    ----------
    name : str
        Channel name in the run file (e.g. ``"acc3"``, ``"force1"``).
    grid : int
        FE grid id.
    direction : (3,) float
        Direction in the model's basic coordinates (normalized here; may point
        along -Z etc.). Response: the acceleration along it; drive: a unit
        force along it.
    """

    name: str
    grid: int
    direction: tuple[float, float, float]

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name.strip():
            raise SynthError(f"channel name must be a non-empty string, got {self.name!r}")
        d = np.asarray(self.direction, dtype=float)
        if d.shape != (3,) or not np.all(np.isfinite(d)) or not np.linalg.norm(d) > 0:
            raise SynthError(f"channel {self.name!r}: direction must be a non-zero 3-vector, got {self.direction!r}")
        object.__setattr__(self, "direction", tuple(float(x) for x in d / np.linalg.norm(d)))
        object.__setattr__(self, "grid", int(self.grid))


@dataclass(frozen=True)
class ArticleTruth:
    """The exact FRF model of one article: modes up to the cut plus the higher-mode series.

    Attributes
    ----------
    p : (n_params,) float
        Normalized parameters of the article.
    frequencies_hz : (n_modes,) float
        Natural frequencies of the kept modes (rigid modes are exactly 0), Hz.
    zeta : (n_modes,) float
        Modal damping ratios (0 for rigid modes).
    n_rigid : int
    out_modal : (n_out, n_modes) float
        C Phi (m per unit modal coordinate).
    in_modal : (n_modes, n_in) float
        Phi^T B.
    shift : float
        s of the residual series, rad^2/s^2.
    residual : (n_terms, n_out, n_in) float
        C R_j: the higher modes' receptance at w is sum_j (s + w^2)^j residual[j], m/N.
    cut_hz : float
        Highest kept mode frequency bound; ``next_hz`` the first mode above it.
    next_hz : float
    series_ratio : float
        r = (s + w_max^2)/(lambda_next + s) at the top of the data range.
    modes_time_s, residual_time_s : float
        Wall time of the eigensolution(s) and of the factorization + series solves.
    """

    p: np.ndarray
    frequencies_hz: np.ndarray
    zeta: np.ndarray
    n_rigid: int
    out_modal: np.ndarray
    in_modal: np.ndarray
    shift: float
    residual: np.ndarray
    cut_hz: float
    next_hz: float
    series_ratio: float
    modes_time_s: float = 0.0
    residual_time_s: float = 0.0

    def frf(self, f_hz, quantity: str = "accelerance", *, include_residual: bool = True) -> np.ndarray:
        """FRF at ``f_hz`` (n_f,), Hz -> (n_f, n_out, n_in) complex, SI, e^{+i w t}."""
        f = np.atleast_1d(np.asarray(f_hz, dtype=float))
        w = 2 * np.pi * f
        wk = 2 * np.pi * self.frequencies_hz
        den = wk[None, :] ** 2 - w[:, None] ** 2 + 2j * self.zeta[None, :] * wk[None, :] * w[:, None]
        H = np.einsum("om,fm,mi->foi", self.out_modal, 1.0 / den, self.in_modal)
        if include_residual and self.residual.size:
            powers = (self.shift + w[:, None] ** 2) ** np.arange(self.residual.shape[0])[None, :]
            H = H + np.einsum("fj,joi->foi", powers, self.residual)
        if quantity not in FRF_QUANTITIES:
            raise SynthError(f"quantity must be one of {FRF_QUANTITIES}, got {quantity!r}")
        if quantity == "receptance":
            return H
        return quantity_factor(quantity, w)[:, None, None] * H


def modes_up_to(K, M, f_cut_hz: float, *, dofs=None, n_start: int = 24):
    """All normal modes of (K, M) up to ``f_cut_hz`` and the first mode above it.

    Returns ``(modes, next_hz)``: a :class:`femodel.Modes` restricted to
    f <= f_cut_hz (rigid-body frequencies set to exactly 0) and the frequency of
    the first computed mode above the cut (``inf`` when the model has none,
    i.e. every finite mode is kept).
    """
    from dataclasses import replace

    import femodel

    n_dof = K.shape[0]
    n = min(n_start, n_dof)
    while True:
        modes = femodel.normal_modes(K, M, n, dofs=dofs, tol=1e-10)
        f = modes.frequencies_hz
        exhausted = modes.n_modes < n or n >= n_dof
        if f[-1] > f_cut_hz or exhausted:
            break
        # the mode count grows about linearly with frequency for shells, slower for beams: overshoot a little
        grow = f_cut_hz / f[-1] if f[-1] > 0 else 2.0
        n = min(max(int(math.ceil(1.3 * n * grow)) + 4, 2 * n if f[-1] <= 0 else n + 8), n_dof)
    keep = f <= f_cut_hz
    above = f[~keep]
    next_hz = float(above[0]) if above.size else math.inf
    freqs = np.where(np.abs(f[keep]) < _RIGID_HZ, 0.0, f[keep])
    return replace(modes, frequencies_hz=freqs, shapes=modes.shapes[:, keep],
                   generalized_mass=modes.generalized_mass[keep]), next_hz


def article_truth(K, M, C, B, p, *, f_cut_hz: float, f_max_hz: float, zeta_of_mode, shift_hz: float,
                  dofs=None, zeta_of_frequency=None) -> ArticleTruth:
    """Exact FRF model of one article (kernel on matrices).

    Parameters
    ----------
    K, M : (n, n) sparse
        Stiffness and mass, SI (M may be singular: massless rotations).
    C : (n_out, n) sparse
        Output rows (displacement along each sensor direction).
    B : (n, n_in) float or sparse
        Unit-force load vectors of the drives.
    p : (n_params,) float
        Recorded in the result.
    f_cut_hz : float
        Modes up to this frequency are kept as modes.
    f_max_hz : float
        Highest frequency the result will be evaluated at (sets the series length).
    zeta_of_mode : callable
        ``zeta_of_mode(n_elastic) -> (n_elastic,)`` damping of the elastic modes in order.
    zeta_of_frequency : callable, optional
        ``zeta_of_frequency(f_hz) -> (n_elastic,)``: damping from the elastic modes' frequencies; used in
        place of ``zeta_of_mode`` when given.
    shift_hz : float
        Shift of the residual series, s = (2 pi shift_hz)^2 > 0.

    Returns
    -------
    ArticleTruth
    """
    t0 = time.perf_counter()
    modes, next_hz = modes_up_to(K, M, f_cut_hz, dofs=dofs)
    t1 = time.perf_counter()
    if next_hz <= f_max_hz * 1.2:
        raise SynthError(
            f"the first mode above the cut ({next_hz:.4g} Hz) is within 1.2 x the top of the data range "
            f"({f_max_hz:.4g} Hz): raise mode_factor"
        )
    Phi = modes.shapes
    f = modes.frequencies_hz
    rigid = f == 0.0
    zeta = np.zeros(f.size)
    zeta[~rigid] = zeta_of_mode(int(np.sum(~rigid))) if zeta_of_frequency is None else zeta_of_frequency(f[~rigid])
    B = B.toarray() if sp.issparse(B) else np.asarray(B, dtype=float)
    s = (2 * np.pi * shift_hz) ** 2
    w_max2 = (2 * np.pi * f_max_hz) ** 2
    M = sp.csr_matrix(M)
    # With every finite mode kept (a small model), R_1 still holds the frequency-independent flexibility of
    # the massless DOF (infinite eigenvalues; nothing when sensors and drives see only DOF with mass).
    ratio = (s + w_max2) / ((2 * np.pi * next_hz) ** 2 + s) if np.isfinite(next_hz) else 0.0
    n_terms = max(1, int(math.ceil(math.log(_SERIES_TOL * (1 - ratio)) / math.log(ratio)))) if ratio > 0 else 1
    import femodel

    solve = femodel.factorize(sp.csc_matrix(K) + s * sp.csc_matrix(M))  # the project's sparse backend

    def project(x):  # remove the kept modes: x - Phi Phi^T M x
        return x - Phi @ (Phi.T @ (M @ x))

    # load without its kept-mode content (B - M Phi Phi^T B), so nothing cancels
    R = project(solve(B - M @ (Phi @ (Phi.T @ B))))
    residual = [C @ R]
    for _ in range(n_terms - 1):
        R = project(solve(M @ R))
        residual.append(C @ R)
    res = np.array(residual)
    return ArticleTruth(
        p=np.asarray(p, dtype=float), frequencies_hz=f, zeta=zeta, n_rigid=int(rigid.sum()),
        out_modal=np.asarray(C @ Phi), in_modal=Phi.T @ B, shift=s, residual=res,
        cut_hz=float(f_cut_hz), next_hz=next_hz, series_ratio=float(ratio),
        modes_time_s=t1 - t0, residual_time_s=time.perf_counter() - t1,
    )


def line_grid(data_hz, base_lines: int, modes_hz, zeta, lines_per_bandwidth: float) -> np.ndarray:
    """Sweep lines (Hz, ascending): log-spaced base lines plus dense lines around each mode.

    ``lines_per_bandwidth`` lines per half-power bandwidth 2 zeta_k f_k over
    +-3 bandwidths around every mode with f_k in ``data_hz`` (zeta_k > 0).
    """
    lo, hi = float(data_hz[0]), float(data_hz[1])
    parts = [np.geomspace(lo, hi, int(base_lines))]
    m = int(round(3 * lines_per_bandwidth))
    for fk, zk in zip(np.asarray(modes_hz, float), np.asarray(zeta, float)):
        if zk > 0 and lo <= fk <= hi:
            bw = 2 * zk * fk
            parts.append(fk + np.arange(-m, m + 1) * bw / lines_per_bandwidth)
    f = np.sort(np.concatenate(parts))
    f = f[(f >= lo) & (f <= hi)]
    keep = np.concatenate([[True], np.diff(f) > 1e-9 * f[1:]])
    return f[keep]


def complex_log10_sd(h_model, h_test) -> float:
    """Square deviation mean |log10(h_model / h_test)|^2 (principal branch), Eq. 2.5/2.23."""
    eps = np.log(np.asarray(h_model) / np.asarray(h_test)) / np.log(10.0)
    return float(np.mean(np.abs(eps) ** 2))


# ----------------------------------------------------------------------------
# campaign
# ----------------------------------------------------------------------------
@dataclass(frozen=True)
class SynthCampaign:
    """What :func:`synthesize` wrote.

    Attributes
    ----------
    run_paths : tuple of Path
        One HDF5 run file per article (``acquisition.runfile``; accelerance,
        per-line std_error = noise sigma).
    uff_paths : tuple of Path
        One binary UFF58 file per article (empty when ``write_uff=False``).
    truth_path : Path
        ``truth.npz``: per article ``i``: ``frequency_hz_i`` (n_f,),
        ``truth_i``/``noisy_i`` (n_f, n_out, n_in) complex accelerance,
        ``sigma_i`` (n_f, n_out, n_in), ``modes_hz_i``, ``zeta_i``; and
        ``p_true``, ``p_population``, ``articles``, ``parameter_names``,
        ``sensors``, ``drives``, ``band_hz``, ``data_hz``, ``noise_rel``
        (n_articles, n_out), ``noise_floor_abs`` (n_articles, n_out, n_in);
        with effects also ``effects`` (a JSON string: the list of :attr:`effects`).
    articles : tuple of str
    p_true : (n_articles, n_params) float
        Normalized parameters of each article.
    p_population : (n_params,) float
        The offsets before article scatter.
    parameter_names : tuple of str
    sensors, drives : tuple of SynthChannel
    band_hz, data_hz : (float, float)
    bdf, parameters : Path
        The deck and parameter file used (``parameters`` None if a ParameterSet
        without a source file was given).
    units : str
    timings : dict
        Wall times, s: ``model`` (parametric model, 0 when one was passed),
        ``modes`` and ``residual`` (lists, per article), ``files`` (run, UFF and
        truth files). Load-dependent; for benchmarks.
    effects : tuple of dict
        The undeclared effects (:meth:`frfcal.effects.Effect.record`: family,
        term, name, value, unit, grids/dofs or elements, description,
        articles); empty without effects.
    effect_terms : tuple of frfcal.effects.Effect
        The same effects as objects (:meth:`article_effects`).
    """

    run_paths: tuple[Path, ...]
    uff_paths: tuple[Path, ...]
    truth_path: Path
    articles: tuple[str, ...]
    p_true: np.ndarray
    p_population: np.ndarray
    parameter_names: tuple[str, ...] = ()
    sensors: tuple[SynthChannel, ...] = ()
    drives: tuple[SynthChannel, ...] = ()
    band_hz: tuple[float, float] = (0.0, 0.0)
    data_hz: tuple[float, float] = (0.0, 0.0)
    bdf: Path | None = None
    parameters: Path | None = None
    units: str = "si"
    timings: dict = field(default_factory=dict, compare=False)
    effects: tuple[dict, ...] = ()
    effect_terms: tuple = field(default=(), compare=False)
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def truth(self) -> dict:
        """The arrays of ``truth.npz`` (loaded once)."""
        if "npz" not in self._cache:
            with np.load(self.truth_path, allow_pickle=False) as z:
                self._cache["npz"] = {k: z[k] for k in z.files}
        return self._cache["npz"]

    def _selection(self, channels, band_hz, articles):
        z = self.truth()
        names = [str(x) for x in z["sensors"]]
        channels = names if channels is None else [channels] if isinstance(channels, str) else list(channels)
        missing = [c for c in channels if c not in names]
        if missing:
            raise SynthError(f"{self.truth_path}: unknown channel(s) {missing}; sensors are {names}")
        idx = [names.index(c) for c in channels]
        lo, hi = self.band_hz if band_hz is None else (float(band_hz[0]), float(band_hz[1]))
        arts = range(len(self.articles)) if articles is None else \
            [self.articles.index(a) if isinstance(a, str) else int(a) for a in articles]
        return idx, lo, hi, list(arts)

    def signal_pairs(self, article, channels=None, band_hz=None) -> np.ndarray:
        """(n_channels, n_drives) bool: pairs whose median |H_true|/sigma over the band is >= 3.

        A pair the structure does not couple (a vertical sensor under a lateral
        drive of a planar frame) holds noise only; the campaign leaves such
        pairs out (calibration._signal), and so do the floors here.
        """
        z = self.truth()
        idx, lo, hi, (i,) = self._selection(channels, band_hz, [article])
        f = z[f"frequency_hz_{i}"]
        sel = (f >= lo) & (f <= hi)
        return np.median(np.abs(z[f"truth_{i}"][sel][:, idx]) / z[f"sigma_{i}"][sel][:, idx], axis=0) >= 3.0

    def floor_sd(self, channels=None, band_hz=None, articles=None, signal_only: bool = True) -> float:
        """SD (Eq. 2.23) of the truth against its own noisy data: the floor any model can reach.

        mean |log10(H_true / H_noisy)|^2 over the complex values of the named
        sensor channels (default all), all drives, lines within ``band_hz``
        (default the synthesis band), pooled over ``articles`` (default all).
        With ``signal_only`` the pairs without signal (:meth:`signal_pairs`) are
        left out, as the campaign does. For noise of relative rms s it is about
        s^2 / ln(10)^2.
        """
        z = self.truth()
        idx, lo, hi, arts = self._selection(channels, band_hz, articles)
        eps2 = []
        for i in arts:
            f = z[f"frequency_hz_{i}"]
            sel = (f >= lo) & (f <= hi)
            t, n = z[f"truth_{i}"][sel][:, idx], z[f"noisy_{i}"][sel][:, idx]
            e = np.abs(np.log(t / n)) ** 2
            if signal_only:
                e = e[:, self.signal_pairs(i, [str(z["sensors"][k]) for k in idx], (lo, hi))]
            eps2.append(e.ravel())
        eps2 = np.concatenate(eps2)
        if eps2.size == 0:
            raise SynthError(f"{self.truth_path}: no lines within {lo}-{hi} Hz")
        return float(np.mean(eps2) / np.log(10.0) ** 2)

    def article_effects(self, article) -> tuple:
        """The :class:`frfcal.effects.Effect` objects an article (index or name) has."""
        (i,) = self._selection(None, None, [article])[3]
        return tuple(e for e in self.effect_terms if e.applies_to(i, self.articles[i]))

    def model_sd(self, p, article, channels=None, band_hz=None, signal_only: bool = True, *, terms=(),
                 values=()) -> float:
        """SD of the deck at normalized ``p`` *with the article's true damping* against its noisy data.

        The model is solved here exactly as the truth was (full-order modes,
        the same per-mode damping, the exact higher-mode series), so the only
        difference from :meth:`floor_sd` is p: this is the hold-out error of a
        calibrated p with the damping question taken out.

        Without ``terms`` this is the calibration model, i.e. the deck WITHOUT
        any undeclared effect. ``terms`` (femodel term objects) at physical
        ``values`` (SI, or the factor 1 + p) extend it
        (:meth:`femodel.ParametricModel.with_terms`): with the article's own
        effects (:meth:`article_effects`) at their values and its p_true the
        result is the floor of that article. Each elastic mode takes the
        damping of the truth's elastic mode nearest in frequency (log scale):
        the same as by mode index when the modes correspond, and not shifted
        when the mode count below the cut differs from the truth's (a term
        that lifts rigid-body modes to a few Hz shifted every in-band mode's
        damping by one index each when it was taken by index: the deck with a
        contact candidate that did so printed 65 x the floor, 5.9 x with the
        damping matched).
        """
        import femodel

        z = self.truth()
        idx, lo, hi, (i,) = self._selection(channels, band_hz, [article])
        if "pm" not in self._cache:
            self._cache["pm"] = femodel.parametric_model(self.parameters, self.bdf, units=self.units)
        pm = self._cache["pm"]
        terms, values = tuple(terms), tuple(values)
        if len(terms) != len(values):
            raise SynthError(f"model_sd: {len(terms)} terms but {len(values)} values")
        if terms:
            key = ("pm",) + tuple(repr(t) for t in terms)
            if key not in self._cache:
                self._cache[key] = pm.with_terms(terms)
            p = np.concatenate([np.asarray(p, float), [t.normalized(v) for t, v in zip(terms, values)]])
            pm = self._cache[key]
        C = femodel.sensor_matrix(pm.assembly, [self.sensors[k].grid for k in idx],
                                  [self.sensors[k].direction for k in idx])
        B = femodel.sensor_matrix(pm.assembly, [c.grid for c in self.drives],
                                  [c.direction for c in self.drives]).T.toarray()
        zeta_true = z[f"zeta_{i}"][z[f"modes_hz_{i}"] > 0]
        f_all = z[f"frequency_hz_{i}"]
        top = float(np.max(z[f"modes_hz_{i}"]))

        f_true = z[f"modes_hz_{i}"][z[f"modes_hz_{i}"] > 0]

        def zeta_of_mode(n):  # the truth's damping by mode index (and its last value beyond)
            return np.concatenate([zeta_true, np.full(max(0, n - zeta_true.size), zeta_true[-1])])[:n]

        def zeta_of_frequency(f):  # the damping of the truth's elastic mode nearest in frequency
            f = np.asarray(f, float)
            if f_true.size != zeta_true.size or f_true.size == 0:
                return zeta_of_mode(f.size)
            return zeta_true[np.argmin(np.abs(np.log(f[:, None] / f_true[None, :])), axis=1)]

        p = np.asarray(p, float)
        tr = article_truth(pm.stiffness(p), pm.mass(p), C, B, p, f_cut_hz=top, f_max_hz=float(f_all.max()),
                           zeta_of_mode=zeta_of_mode, shift_hz=float(self.data_hz[0]), dofs=pm.aset,
                           zeta_of_frequency=zeta_of_frequency)
        sel = (f_all >= lo) & (f_all <= hi)
        H = tr.frf(f_all[sel], "accelerance")
        e = np.abs(np.log(H / z[f"noisy_{i}"][sel][:, idx])) ** 2
        if signal_only:
            e = e[:, self.signal_pairs(i, [str(z["sensors"][k]) for k in idx], (lo, hi))]
        return float(np.mean(e) / np.log(10.0) ** 2)

    def write_campaign(self, path, *, bdf=None, parameters=None, units=None, calibrate, holdout=(),
                       band_hz=None, drives=None, **sections) -> Path:
        """Write a campaign TOML for ``frfcal calibrate`` (docs/campaign.md) over these run files.

        Parameters
        ----------
        path : path-like
            The campaign file; all paths in it are relative to its folder.
        bdf, parameters, units : optional
            Deck, parameter file and unit system (default: those synthesized from).
        calibrate, holdout : sequences of str
            Sensor channel names for calibration and hold-out validation.
        band_hz : (float, float), optional
            Calibration band (default: the synthesis band).
        drives : sequence of str, optional
            Drive channel names (default: all, i.e. the key is omitted).
        **sections : dict
            Further tables by name, e.g. ``calibration={"starts": 2}``,
            ``output={"dir": "out", "figures": False}``.

        Returns
        -------
        Path
        """
        path = Path(path)
        base = path.resolve().parent
        parameters = parameters if parameters is not None else self.parameters
        if parameters is None:
            raise SynthError("write_campaign: no parameter file known; pass parameters=")
        bdf = bdf if bdf is not None else self.bdf
        units = units or self.units
        lo, hi = self.band_hz if band_hz is None else band_hz
        names = [s.name for s in self.sensors]
        for c in list(calibrate) + list(holdout):
            if names and c not in names:
                raise SynthError(f"write_campaign: channel {c!r} is not a synthesized sensor ({names})")

        def rel(p):
            return Path(os.path.relpath(Path(p).resolve(), base)).as_posix()

        doc = {"model": {"parameters": rel(parameters), "units": units}}
        if bdf is not None:
            doc["model"]["bdf"] = rel(bdf)
        runs = [{"path": rel(r), "article": a} for r, a in zip(self.run_paths, self.articles)]
        doc["channels"] = {"calibrate": list(calibrate), "holdout": list(holdout)}
        if drives is not None:
            doc["channels"]["drives"] = list(drives)
        doc["band"] = {"low_hz": float(lo), "high_hz": float(hi)}
        for name, table in sections.items():
            if not isinstance(table, dict):
                raise SynthError(f"write_campaign: section {name!r} must be a dict of keys, got {type(table).__name__}")
            doc[name] = table
        text = [_toml_table("model", doc.pop("model"))]
        for r in runs:
            text.append(_toml_table("run", r, array=True))
        for name, table in doc.items():
            text.append(_toml_table(name, table))
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("# synthetic campaign written by frfcal.synth\n\n" + "\n".join(text))
        return path


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        if not np.isfinite(v):
            raise SynthError(f"write_campaign: non-finite value {v}")
        return repr(float(v))
    if isinstance(v, (str, Path)):
        return json.dumps(str(v))
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise SynthError(f"write_campaign: cannot write {v!r} ({type(v).__name__}) to TOML")


def _toml_table(name: str, table: dict, array: bool = False) -> str:
    head = f"[[{name}]]" if array else f"[{name}]"
    return head + "\n" + "".join(f"{k} = {_toml_value(v)}\n" for k, v in table.items() if v is not None)


def _population(rng, pm, offsets) -> np.ndarray:
    """Population offsets: given by name (others 0), or random 5-15 % with random signs."""
    lower, upper = pm.lower, pm.upper
    names = pm.parameters.names
    if offsets is None:
        p = rng.uniform(0.05, 0.15, len(names)) * rng.choice([-1.0, 1.0], len(names))
        return np.clip(p, 0.9 * lower, 0.9 * upper)  # random offsets stay inside 90 % of the bounds
    unknown = sorted(set(offsets) - set(names))
    if unknown:
        raise SynthError(f"offsets: unknown parameter(s) {unknown}; parameters are {list(names)}")
    p = np.array([float(offsets.get(n, 0.0)) for n in names])
    bad = [n for n, x, lo, hi in zip(names, p, lower, upper) if not lo < x < hi]
    if bad:
        raise SynthError(f"offsets: {bad} outside the parameter bounds")
    return p


def synthesize(bdf, parameters, out_dir, *, sensors, drives, band_hz, units=None, n_articles: int = 3,
               offsets=None, scatter: float = 0.003, zeta_range=(5e-4, 3e-3), noise_range=(0.005, 0.01),
               noise_floor: float = 1e-3, mode_factor: float = 3.0, data_hz=None, lines_per_bandwidth: float = 4,
               base_lines: int = 300, seed: int = 0, write_uff: bool = True, article_prefix: str = "A",
               parametric=None, effects=None) -> SynthCampaign:
    """Manufacture a test campaign (run files, UFF58, truth) from a deck at known parameters.

    Parameters
    ----------
    bdf : path-like
        Nastran deck.
    parameters : path-like or femodel.ParameterSet
        Parameter file (docs/parameters.md).
    out_dir : path-like
        Output folder: ``<article>.h5``, ``<article>.uff``, ``truth.npz``.
    sensors, drives : sequences of SynthChannel
        Response points (accelerometers) and drive points (unit forces).
    band_hz : (float, float)
        Calibration band, Hz (> 0).
    units : str, optional
        Deck unit system (default: the parameter file's, else si).
    n_articles : int
    offsets : dict name -> p, optional
        Population offsets; default random 5-15 % magnitude with random sign
        per parameter (kept within 90 % of the bounds).
    scatter : float
        Per-article rms scatter of p around the population (absolute, in p).
    zeta_range : (float, float)
        Modal damping range (log-uniform per mode), fraction of critical.
    noise_range : (float, float)
        Range of the per-article, per-sensor relative noise rms.
    noise_floor : float
        Absolute noise floor as a fraction of each FRF's (sensor, drive) median |H| in the band.
    mode_factor : float
        Modes up to mode_factor x band top are kept as modes; higher ones enter
        through the exact residual series.
    data_hz : (float, float), optional
        Swept range; default the band widened by 10 % each side.
    lines_per_bandwidth : float
        Lines per half-power bandwidth around each mode.
    base_lines : int
        Log-spaced base lines over ``data_hz``.
    seed : int
        Everything random derives from it (same seed, same files).
    write_uff : bool
    article_prefix : str
        Articles are named ``<prefix>1``, ``<prefix>2``, ...
    parametric : femodel.ParametricModel, optional
        A parametric model of the same deck and parameters, to reuse.
    effects : sequence of frfcal.effects.Effect (or of tuples of them), optional
        Undeclared effects (docs/synth.md; tuples, as
        :func:`frfcal.effects.standard_effects` gives them, are flattened): an article's truth is the model
        extended by the terms of the effects it has
        (:meth:`femodel.ParametricModel.with_terms`) at p_true and the
        effects' values; the parameter file (the calibration model) lacks
        them. Recorded in ``truth.npz`` (``effects``, JSON), in each run
        file's plan (``effects``: those of that article) and on the result.
        Modes that a spring to ground lifts from zero frequency (a
        suspension or stinger mode) are taken to be the lowest elastic modes
        and get the top of ``zeta_range``; the structure's modes keep their
        damping by mode index.

    Returns
    -------
    SynthCampaign
    """
    import femodel
    from acquisition import ChannelSpec, export_uff
    from acquisition.runfile import LineQuality, create_run

    sensors, drives = tuple(sensors), tuple(drives)
    for what, chans in (("sensors", sensors), ("drives", drives)):
        if not chans:
            raise SynthError(f"{what}: at least one channel is needed")
        if not all(isinstance(c, SynthChannel) for c in chans):
            raise SynthError(f"{what}: expected SynthChannel entries")
    names = [c.name for c in sensors + drives]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise SynthError(f"duplicate channel names {dup}")
    lo, hi = float(band_hz[0]), float(band_hz[1])
    if not 0 < lo < hi:
        raise SynthError(f"band_hz must be 0 < low < high, got {band_hz!r}")
    d_lo, d_hi = (0.9 * lo, 1.1 * hi) if data_hz is None else (float(data_hz[0]), float(data_hz[1]))
    if not 0 < d_lo <= lo or d_hi < hi:
        raise SynthError(f"data_hz {(d_lo, d_hi)} must be positive and cover band_hz {(lo, hi)}")
    if mode_factor * hi < 1.5 * d_hi:
        raise SynthError(f"mode_factor {mode_factor}: modes up to {mode_factor * hi:.4g} Hz must reach 1.5 x the "
                         f"top of the data range ({d_hi:.4g} Hz)")
    if not 0 < zeta_range[0] <= zeta_range[1] < 0.5:
        raise SynthError(f"zeta_range must be 0 < low <= high < 0.5, got {zeta_range!r}")
    if not 0 <= noise_range[0] <= noise_range[1]:
        raise SynthError(f"noise_range must be 0 <= low <= high, got {noise_range!r}")
    if n_articles < 1 or base_lines < 2 or lines_per_bandwidth <= 0 or scatter < 0 or noise_floor < 0:
        raise SynthError("n_articles >= 1, base_lines >= 2, lines_per_bandwidth > 0, scatter >= 0 and "
                         "noise_floor >= 0 are required")

    t_start = time.perf_counter()
    pm = parametric if parametric is not None else femodel.parametric_model(parameters, bdf, units=units)
    t_model = time.perf_counter() - t_start
    known = set(np.asarray(pm.assembly.model.grid_ids).tolist())
    for what, chans in (("sensor", sensors), ("drive", drives)):
        for c in chans:
            if c.grid not in known:
                raise SynthError(f"{what} {c.name!r}: grid {c.grid} is not in {pm.bdf}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    asm = pm.assembly
    try:
        C = femodel.sensor_matrix(asm, [c.grid for c in sensors], [c.direction for c in sensors])
        B = femodel.sensor_matrix(asm, [c.grid for c in drives], [c.direction for c in drives]).T.toarray()
    except femodel.ModelError as exc:
        raise SynthError(f"{pm.bdf}: {exc}") from None

    ss = np.random.SeedSequence(int(seed))
    s_pop, s_zeta, *s_art = ss.spawn(2 + n_articles)
    p_pop = _population(np.random.default_rng(s_pop), pm, offsets)
    art_rng = [np.random.default_rng(s) for s in s_art]
    p_true = np.array([np.clip(p_pop + scatter * r.standard_normal(pm.n_params), 0.95 * pm.lower, 0.95 * pm.upper)
                       for r in art_rng])
    articles = tuple(f"{article_prefix}{i + 1}" for i in range(n_articles))
    effects = tuple(e for item in (effects or ()) for e in ((item,) if isinstance(item, Effect) else tuple(item)))
    try:
        effect_keys = resolve_articles(effects, articles) if effects else [()] * n_articles
    except EffectError as exc:
        raise SynthError(str(exc)) from None
    models = {(): pm}
    n_rigid = {}

    def model_of(key):
        if key not in models:
            try:
                models[key] = pm.with_terms([effects[k].term for k in key])
            except femodel.ParameterError as exc:
                raise SynthError(f"effects: {exc}") from None
        return models[key]

    def rigid_count(key, p):  # only asked for models with springs to ground
        if key not in n_rigid:
            m = model_of(key)
            n_rigid[key] = int(np.sum(modes_up_to(m.stiffness(p), m.mass(p), _RIGID_HZ, dofs=m.aset)[0]
                                      .frequencies_hz == 0.0))
        return n_rigid[key]

    rz = np.random.default_rng(s_zeta)
    zeta_pool = []  # population damping per elastic mode index, drawn as needed (deterministic order)

    def population_zeta(n):
        while len(zeta_pool) < n:
            zeta_pool.append(float(np.exp(rz.uniform(np.log(zeta_range[0]), np.log(zeta_range[1])))))
        return np.array(zeta_pool[:n])

    truths = []
    for a, r in enumerate(art_rng):
        variation = r.standard_normal(4096)  # one factor per mode index, independent of how many modes

        key = effect_keys[a]
        pma = model_of(key)
        pa = np.concatenate([p_true[a], [effects[k].p for k in key]])
        lifted = 0
        if any(_grounds(effects[k].term) for k in key):
            lifted = max(0, rigid_count((), p_true[a]) - rigid_count(key, pa))

        def zeta_of_mode(n, variation=variation, lifted=lifted):
            if n - lifted > variation.size:
                raise SynthError(f"{n} elastic modes below the cut: more than the generator supports (4096)")
            z = population_zeta(n - lifted) * np.exp(_ZETA_SCATTER * variation[:n - lifted])
            return np.concatenate([np.full(lifted, float(zeta_range[1])), z]) if lifted else z

        truths.append(article_truth(pma.stiffness(pa), pma.mass(pa), C, B, pa,
                                    f_cut_hz=mode_factor * hi, f_max_hz=d_hi, zeta_of_mode=zeta_of_mode,
                                    shift_hz=d_lo, dofs=pm.aset))

    sens_spec = [ChannelSpec(name=c.name, role="response", quantity="acceleration", unit="m/s^2",
                             physical=f"synth/{i}", grid=c.grid, direction=c.direction)
                 for i, c in enumerate(sensors)]
    drive_spec = [ChannelSpec(name=c.name, role="force", quantity="force", unit="N",
                              physical=f"synth/{len(sensors) + i}", grid=c.grid, direction=c.direction)
                  for i, c in enumerate(drives)]
    n_out, n_in = len(sensors), len(drives)
    records = [e.record(articles) for e in effects]
    t_files = time.perf_counter()
    npz: dict[str, np.ndarray] = {}
    runs, uffs = [], []
    noise_rel = np.zeros((n_articles, n_out))
    floor_abs = np.zeros((n_articles, n_out, n_in))
    for a, (name, tr, r) in enumerate(zip(articles, truths, art_rng)):
        elastic = tr.frequencies_hz > 0
        f = line_grid((d_lo, d_hi), base_lines, tr.frequencies_hz[elastic], tr.zeta[elastic], lines_per_bandwidth)
        H = tr.frf(f, "accelerance")
        band = (f >= lo) & (f <= hi)
        noise_rel[a] = r.uniform(noise_range[0], noise_range[1], n_out)
        floor_abs[a] = noise_floor * np.median(np.abs(H[band]), axis=0)
        sigma = np.sqrt((noise_rel[a][None, :, None] * np.abs(H)) ** 2 + floor_abs[a][None] ** 2)
        noise = sigma * (r.standard_normal(H.shape) + 1j * r.standard_normal(H.shape)) / np.sqrt(2.0)
        Hn = H + noise
        plan = {"generator": "frfcal.synth", "seed": int(seed), "article_index": a, "band_hz": [lo, hi],
                "data_hz": [d_lo, d_hi], "n_lines": int(f.size), "p_true": p_true[a].tolist(),
                "parameter_names": list(pm.parameters.names)}
        if effects:
            plan["effects"] = [records[k] for k in effect_keys[a]]
        path = out / f"{name}.h5"
        with create_run(path, article=name, sensors=sens_spec, drives=drive_spec, quantity="accelerance",
                        plan=plan, hardware={"driver": "frfcal.synth (synthetic truth data)"}, overwrite=True) as w:
            w.append_lines(f, Hn, [LineQuality(force_n=np.ones(n_in), std_error=sigma[k], thd=np.zeros(n_out + n_in),
                                               flags=0, n_blocks=1, time_s=float(k), settle_time_s=0.0,
                                               settle_metric=0.0) for k in range(f.size)])
        runs.append(path)
        if write_uff:
            upath = out / f"{name}.uff"
            export_uff(path, upath)
            uffs.append(upath)
        npz.update({f"frequency_hz_{a}": f, f"truth_{a}": H, f"noisy_{a}": Hn, f"sigma_{a}": sigma,
                    f"modes_hz_{a}": tr.frequencies_hz, f"zeta_{a}": tr.zeta})
    npz.update({
        "articles": np.array(articles), "parameter_names": np.array(pm.parameters.names),
        "p_true": p_true, "p_population": p_pop, "sensors": np.array([c.name for c in sensors]),
        "drives": np.array([c.name for c in drives]), "band_hz": np.array([lo, hi]),
        "data_hz": np.array([d_lo, d_hi]), "noise_rel": noise_rel, "noise_floor_abs": floor_abs,
    })
    if effects:
        npz["effects"] = np.array(json.dumps(records))
    truth_path = out / "truth.npz"
    np.savez_compressed(truth_path, **npz)
    timings = {"model": t_model if parametric is None else 0.0, "modes": [t.modes_time_s for t in truths],
               "residual": [t.residual_time_s for t in truths], "files": time.perf_counter() - t_files}
    params_path = getattr(pm.parameters, "source", None)
    if params_path is None and not isinstance(parameters, femodel.ParameterSet):
        params_path = parameters
    return SynthCampaign(
        run_paths=tuple(runs), uff_paths=tuple(uffs), truth_path=truth_path, articles=articles, p_true=p_true,
        p_population=p_pop, parameter_names=tuple(pm.parameters.names), sensors=sensors, drives=drives,
        band_hz=(lo, hi), data_hz=(d_lo, d_hi), bdf=Path(pm.bdf),
        parameters=Path(params_path) if params_path is not None else None, units=pm.units, timings=timings,
        effects=tuple(records), effect_terms=effects,
    )


def _grounds(term) -> bool:
    """Whether a term is a spring with a pair to ground (it may lift rigid-body modes)."""
    from femodel._terms import AddedSpring

    return isinstance(term, AddedSpring) and any(d[2] == 0 for d in term.dofs)
