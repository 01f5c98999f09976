"""Levenberg-Marquardt multi-start calibration on the surrogate (paper Sec. 2.2, 2.3.3).

The residual is the real-stacked log-ratio deviation ``[Re eps; Im eps]/sqrt(N)``
(so ``sum r^2`` is the square deviation delta of Eq. 2.5) over all data sets,
with the exact Jacobian ``d eps/dp = (dH^A/dp) / (H^A ln 10)`` (the derivative of
:func:`surrogate_frf`, :mod:`calibration._modal_derivative`). Minimization is scipy's trust-region
reflective least-squares (a bounded Levenberg-Marquardt) from the nominal
point plus Latin-hypercube starts inside the bounds. Each start runs through
the executor; every outcome is kept. The multi-start stops early once the
starts run so far make more minima unlikely (:func:`enough_starts`, Boender
and Rinnooy Kan's Bayesian stopping rule), unless ``adaptive_starts`` is off.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, fields, replace

import numpy as np

from calibration._errors import CalibrationError
from calibration._executor import SerialExecutor
from calibration._metric import log_deviation, square_deviation
from calibration._modal_derivative import FRFRows, eigen_derivatives, parameter_derivatives
from calibration._surrogate import BASIS_FACTOR, Surrogate, reduced_modes, surrogate_frf
from calibration._threads import blas_threads


#: Convergence tolerance (xtol, ftol, gtol) of the damping-continuation stages before the last.
STAGE_TOL = 1e-4

#: Two starts ended in the same minimum when their final square deviations agree to this relative
#: tolerance (the 21 starts of the 200k benchmark agree to 1e-9; a different basin differs by percents) ...
SAME_MINIMUM_RTOL = 1e-6
#: ... or to this fraction of the largest square deviation at a start (noise-free data: the minima are
#: round-off, 1e-12 against 1e-2 at the start, and their relative differences mean nothing).
SAME_MINIMUM_ATOL = 1e-8


def distinct_minima(sds, rtol: float = SAME_MINIMUM_RTOL, atol: float = 0.0) -> int:
    """Number of distinct minima among the starts' final square deviations (non-finite ones, failed
    starts, left out): the sorted values split where two neighbours differ by more than ``rtol`` x the
    larger plus ``atol``. Starts in one valley of a parameter combination the data do not see end at
    different p with the same value; they count as one minimum (what the multi-start looks for is the
    lowest value)."""
    v = np.sort(np.asarray([x for x in sds if np.isfinite(x)], dtype=float))
    if v.size == 0:
        return 0
    return 1 + int(np.sum(np.diff(v) > rtol * np.abs(v[1:]) + atol))


def same_minimum_atol(sd_starts) -> float:
    """The absolute tolerance of :func:`distinct_minima` for starts whose square deviations at the start
    are ``sd_starts``: :data:`SAME_MINIMUM_ATOL` x the largest finite one (0 without any)."""
    s0 = [x for x in sd_starts if np.isfinite(x)]
    return SAME_MINIMUM_ATOL * max(s0) if s0 else 0.0


def enough_starts(n: int, w: int) -> bool:
    """Boender and Rinnooy Kan's Bayesian stopping rule for multi-start (Math. Programming 37, 1987):
    after ``n`` successful starts that found ``w`` distinct minima, the posterior expectation of the
    number of minima is w (n - 1) / (n - w - 2); stop when it is below w + 1/2 (no further minimum is
    expected). One minimum needs 8 starts that all end in it, two need 17, three 30."""
    if w < 1 or n <= w + 2:
        return False
    return w * (n - 1) / (n - w - 2) < w + 0.5


#: Starts the rule needs at least (all in one minimum) before it can stop the multi-start.
MIN_STARTS = next(n for n in range(1, 100) if enough_starts(n, 1))


def stopping_point(sds, sd_starts=None, rtol: float = SAME_MINIMUM_RTOL) -> int | None:
    """The smallest number k of leading starts (in start order) after which :func:`enough_starts` says
    stop, counting the successful ones; None if it never does on ``sds``. With ``sd_starts`` (the square
    deviations at the starts) the absolute tolerance of :func:`distinct_minima` is
    :data:`SAME_MINIMUM_ATOL` x the largest of the first k (each prefix judged on itself alone)."""
    sds = list(sds)
    for k in range(1, len(sds) + 1):
        ok = [x for x in sds[:k] if np.isfinite(x)]
        if enough_starts(len(ok), distinct_minima(ok, rtol, same_minimum_atol((sd_starts or [])[:k]))):
            return k
    return None


@dataclass(frozen=True)
class FitData:
    """Test FRFs that a model is fitted to / compared with.

    Parameters
    ----------
    freq_hz : (n_f,) Hz
    frf : (n_f, n_out, n_in) complex, SI, same quantity as the model evaluation
    outputs : tuple of str
        Output channel names (rows of ``frf``); they must be outputs of the surrogate.
    inputs : tuple of str, optional
        Drive names (columns); default: the surrogate's inputs in order.
    mask : (n_f, n_out, n_in) bool, optional
        Elements that take part (default all). Cross-validation splits use it.
    article : str
        Test article label, for reports.
    weights : (n_f,) or (n_f, n_out, n_in) float, optional
        Non-negative weight of each line, or of each value, in the square deviation (default 1).
        The deviation becomes sum(w |eps|^2) / sum(w); e.g.
        :func:`log_frequency_weights` turns an uneven line grid into the
        paper's fixed-samples-per-half-bandwidth measure.
    """

    freq_hz: np.ndarray
    frf: np.ndarray
    outputs: tuple
    inputs: tuple = ()
    mask: np.ndarray | None = None
    article: str = ""
    weights: np.ndarray | None = None

    def __post_init__(self) -> None:
        f = np.asarray(self.freq_hz, dtype=float)
        H = np.asarray(self.frf, dtype=complex)
        if H.ndim != 3 or H.shape[0] != f.size or H.shape[1] != len(self.outputs):
            raise CalibrationError(
                f"FitData{' ' + self.article if self.article else ''}: frf shape {H.shape} does not match "
                f"{f.size} frequencies x {len(self.outputs)} outputs"
            )
        if f.size == 0:
            raise CalibrationError(f"FitData {self.article}: no frequency lines in the band")
        bad = ~np.isfinite(H)
        if self.mask is not None:
            bad &= np.asarray(self.mask, bool)
        if bad.any():
            fi, oi, _ = np.nonzero(bad)
            raise CalibrationError(
                f"test data{' of ' + self.article if self.article else ''}: NaN/inf at "
                f"{f[fi[0]]:.3f} Hz on channel {self.outputs[oi[0]]!r} ({bad.sum()} values); "
                "flag those lines invalid in the run file"
            )
        object.__setattr__(self, "freq_hz", f)
        object.__setattr__(self, "frf", H)
        object.__setattr__(self, "outputs", tuple(self.outputs))
        if self.mask is not None:
            m = np.asarray(self.mask, dtype=bool)
            if m.shape != H.shape:
                raise CalibrationError(f"FitData mask shape {m.shape} != frf shape {H.shape}")
            object.__setattr__(self, "mask", m)
        if self.weights is not None:
            w = np.asarray(self.weights, dtype=float)
            if w.shape not in (f.shape, H.shape) or not np.all(np.isfinite(w)) or np.any(w < 0) or not np.any(w > 0):
                raise CalibrationError(
                    f"FitData {self.article}: weights must be {f.size} (one per line) or {H.shape} (one per value) "
                    "finite non-negative values, not all zero")
            object.__setattr__(self, "weights", w)

    @property
    def n_values(self) -> int:
        return int(self.frf.size if self.mask is None else self.mask.sum())

    def masked(self, mask: np.ndarray) -> "FitData":
        """The same data restricted to ``mask`` (and'ed with the current mask)."""
        m = np.asarray(mask, bool) if self.mask is None else (self.mask & np.asarray(mask, bool))
        return FitData(self.freq_hz, self.frf, self.outputs, self.inputs, m, self.article, self.weights)

    def value_weights(self) -> np.ndarray | None:
        """sqrt of the line weights spread over the values that take part (masked, raveled), or None."""
        if self.weights is None:
            return None
        w = np.sqrt(self.weights)
        w = w if w.ndim == 3 else np.broadcast_to(w[:, None, None], self.frf.shape)
        return (w if self.mask is None else w[self.mask]).ravel()


def log_frequency_weights(freq_hz) -> np.ndarray:
    """Line weights for an uneven grid that make a sum over lines a quadrature in log f.

    The paper samples the band geometrically (a fixed number of samples per
    half-power bandwidth 2 zeta f, :func:`half_bandwidth_frequencies`), i.e.
    uniformly in log f. Measured lines are uneven (dense at resonances); the
    weight of line k is its share of log f, ``(log f[k+1] - log f[k-1]) / 2``
    (one-sided at the ends), scaled to mean 1, so that the weighted deviation
    over measured lines estimates the paper's metric without resampling the
    data.
    """
    f = np.asarray(freq_hz, dtype=float)
    if f.size < 2:
        return np.ones(f.size)
    order = np.argsort(f)
    lf = np.log(f[order])
    edges = np.concatenate([[lf[0]], 0.5 * (lf[1:] + lf[:-1]), [lf[-1]]])
    w = np.empty(f.size)
    w[order] = np.diff(edges)
    w = np.clip(w, 0.0, None)
    return w / w.mean() if w.sum() > 0 else np.ones(f.size)


def thinned_lines(data: FitData, grid_hz) -> FitData:
    """The lines of ``data`` nearest (in log f) to each point of ``grid_hz``, once each, weighted by their share of
    log f (:func:`log_frequency_weights`).

    A continuation stage at a wide damping zeta varies on the scale of its half-power bandwidth 2 zeta f; raw
    lines (dense at the resonances, hundreds per stage) then carry far more values than that stage resolves.
    Thinned to its half-bandwidth grid (:func:`half_bandwidth_frequencies`), the stage keeps the quadrature of
    log f that the weights give the full set, with about as many lines as the equalized target has there.
    Lines are taken, not averaged: the values stay measured values (noise included).
    """
    f = np.asarray(data.freq_hz, float)
    g = np.asarray(grid_hz, float)
    if g.ndim != 1 or g.size == 0 or not np.all(np.isfinite(g)) or np.any(g <= 0):
        raise CalibrationError(f"thinned_lines{' ' + data.article if data.article else ''}: grid_hz must be a "
                               "non-empty 1-D array of positive frequencies")
    order = np.argsort(f)
    lf = np.log(f[order])
    pos = np.clip(np.searchsorted(lf, np.log(g)), 1, lf.size - 1) if lf.size > 1 else np.zeros(g.size, int)
    if lf.size > 1:
        left = np.log(g) - lf[pos - 1] < lf[pos] - np.log(g)
        pos = np.where(left, pos - 1, pos)
    keep = np.unique(order[pos])
    if keep.size >= f.size:
        return data
    return replace(data, freq_hz=f[keep], frf=np.asarray(data.frf)[keep],
                   mask=None if data.mask is None else np.asarray(data.mask)[keep],
                   weights=log_frequency_weights(f[keep]))


def value_weights(data) -> np.ndarray | None:
    """sqrt of the line weights of data sets over their compared values, scaled to mean square 1 (None: all 1)."""
    if all(d.weights is None for d in data):
        return None
    w = np.concatenate([np.ones(d.n_values) if d.weights is None else d.value_weights() for d in data])
    return w / np.sqrt(np.mean(w**2))


def stacked_residual(eps, deps=None, sqrt_w=None):
    """Real residual ``[Re e; Im e]/sqrt(N)`` (and Jacobian ``(2N, n)``) of weighted log deviations.

    ``eps`` (N,) complex, ``deps`` (n, N) complex derivatives, ``sqrt_w`` (N,)
    value weights or None; ``sum(r**2)`` is the weighted square deviation.
    """
    if sqrt_w is not None:
        eps = eps * sqrt_w
        deps = None if deps is None else deps * sqrt_w[None, :]
    s = 1.0 / np.sqrt(eps.size)
    r = np.concatenate([eps.real, eps.imag]) * s
    if deps is None:
        return r
    return r, np.concatenate([deps.real, deps.imag], axis=1).T * s


class Objective:
    """Residual and Jacobian of the square deviation of a surrogate against data sets.

    Parameters
    ----------
    surrogate : Surrogate
    data : sequence of FitData
    zeta0 : float
        Uniform modal damping ratio of the model (the equalized test damping).
    quantity : str
        FRF quantity of the data ("accelerance", "mobility", "receptance").
    """

    def __init__(self, surrogate: Surrogate, data, zeta0: float = 0.01, quantity: str = "accelerance"):
        self.sur = surrogate
        self.data = list(data)
        if not self.data:
            raise CalibrationError("calibration needs at least one data set")
        self.zeta0 = float(zeta0)
        self.quantity = quantity
        self._out = [surrogate.output_index(d.outputs) for d in self.data]
        self._in = []
        for d in self.data:
            if d.inputs:
                lookup = {n: i for i, n in enumerate(surrogate.input_names)}
                missing = [n for n in d.inputs if n not in lookup]
                if missing:
                    raise CalibrationError(f"drives {missing} are not inputs of the model {list(surrogate.input_names)}")
                self._in.append(np.array([lookup[n] for n in d.inputs]))
            else:
                if d.frf.shape[2] != surrogate.inputs.shape[1]:
                    raise CalibrationError(
                        f"data has {d.frf.shape[2]} drives, model has {surrogate.inputs.shape[1]}: name them"
                    )
                self._in.append(np.arange(d.frf.shape[2]))
        self.n_values = sum(d.n_values for d in self.data)
        if self.n_values == 0:
            raise CalibrationError("no data values selected for calibration")
        self._sqrt_w = value_weights(self.data)
        self._frows = FRFRows(surrogate, self.data, self._out, self._in, self._sqrt_w, quantity)
        self._memo_p = None
        self._memo = None
        self._modes_p = None
        self._modes = None

    def modes(self, p):
        """:func:`reduced_modes` at p, kept for the last p: the minimizer asks for the residual and then
        the Jacobian at the same point, and every data set shares them."""
        p = np.asarray(p, dtype=float)
        if self._modes_p is None or not np.array_equal(p, self._modes_p):
            self._modes = reduced_modes(self.sur, p)
            self._modes_p = p.copy()
        return self._modes

    def deviation(self, p) -> list:
        """eps per data set (complex, masked elements only)."""
        out = []
        modes = self.modes(p)
        for d, oi, ii in zip(self.data, self._out, self._in):
            H = surrogate_frf(self.sur, p, d.freq_hz, self.zeta0, self.quantity, outputs=oi, modes=modes)[:, :, ii]
            e = log_deviation(H, d.frf)
            out.append(e if d.mask is None else e[d.mask])
        return out

    def _weighted(self, eps: list) -> np.ndarray:
        """Raveled eps of every data set times sqrt(line weight) (weights normalized to mean 1)."""
        e = np.concatenate([x.ravel() for x in eps])
        return e if self._sqrt_w is None else e * self._sqrt_w

    def sd(self, p) -> float:
        return square_deviation(self._weighted(self.deviation(p)))

    def evaluate(self, p):
        """(r, J): real residual (2N,) and Jacobian (2N, n_p).

        The Jacobian is the exact derivative of the uniformly damped modal sum (c_k = 2 zeta0 omega_k follows
        each mode), built per data set by line slices on :func:`calibration._threads.data_threads` threads
        (:class:`calibration._modal_derivative.FRFRows`).
        """
        p = np.asarray(p, dtype=float)
        if self._memo_p is not None and np.array_equal(p, self._memo_p):
            return self._memo
        rows = self._frows.all_rows(self._build(p))
        memo = self._frows.assembled(rows, [np.arange(self.sur.n_params)] * len(self.data), self.sur.n_params)
        self._memo_p, self._memo = p.copy(), memo
        return memo

    @property
    def n_p(self) -> int:
        return self.sur.n_params

    @property
    def n_unknowns(self) -> int:
        return self.sur.n_params

    def compressed_blocks(self, p):
        """Per data set (columns, R): the triangle of the QR factorization of its rows [J_a f_a] (TSQR over
        line slices, :meth:`calibration._modal_derivative.FRFRows.compressed`); see :func:`_compressed_blocks`."""
        p = np.asarray(p, dtype=float)
        cols = np.arange(self.sur.n_params)
        return [(cols, R) for R in self._frows.compressed(self._build(p))]

    def _build(self, p):
        """``build(a, lines)``: the rows (n_p + 1, 2 n_v) of data set ``a`` on a line slice at p."""
        lam, X = self.modes(p)
        D, G = eigen_derivatives(lam, *parameter_derivatives(self.sur, p, X), self.sur.rigid_hz)
        zeta = np.full(lam.size, self.zeta0)
        facs = [self._frows.factors(a, lam, X, zeta, D, G) for a in range(len(self.data))]
        return lambda a, lines: self._frows.rows(a, facs[a], lines)

    def residual(self, p):
        """Real residual (2N,) only: no Jacobian (trial points of the minimizer are often rejected)."""
        p = np.asarray(p, dtype=float)
        if self._memo_p is not None and np.array_equal(p, self._memo_p):
            return self._memo[0]
        return stacked_residual(np.concatenate([x.ravel() for x in self.deviation(p)]), sqrt_w=self._sqrt_w)

    def jacobian(self, p):
        return self.evaluate(p)[1]


def _compressed_blocks(obj, ridge=None):
    """(fun, jac) of ``obj``'s least squares compressed block by block (``obj.compressed_blocks``:
    :meth:`Objective.compressed_blocks`, :meth:`calibration._refine.ModalDampingObjective.compressed_blocks`).

    The rows of one data set touch only p and that data set's damping unknowns: each block [J_a f_a] is
    QR-factorized on its own columns (n_p + n_a + 1 wide instead of all n_p + sum n_a unknowns), and the
    triangles, placed in their columns, stacked. Sum over the blocks of R_a^T R_a is [J f]^T [J f], so the
    cost, gradient, Gauss-Newton matrix and column norms are the dense problem's (as
    :func:`calibration._refine._compressed`),
    without forming the dense Jacobian, whose damping columns are mostly zeros (outside case 2: 3 articles
    x 19 damping unknowns, 63 columns of which 25 are non-zero in any row). ``ridge``: (w, anchor) adds the
    rows w (p - anchor) (the ``hold`` of :func:`refine`; weights from :func:`_hold_weights`).
    """
    memo = {}
    n_x, n_p = obj.n_unknowns, obj.n_p

    def at(x):
        x = np.asarray(x, float)
        if memo.get("x") is None or not np.array_equal(memo["x"], x):
            Js, fs = [], []
            for cols, R in obj.compressed_blocks(x):
                k = cols.size
                J, f = R[:, :k], R[:, k]
                Jf = np.zeros((J.shape[0], n_x))
                Jf[:, cols] = J
                Js.append(Jf)
                fs.append(f)
            if ridge is not None:
                w, anchor = ridge
                Js.append(np.hstack([np.diag(w), np.zeros((n_p, n_x - n_p))]))
                fs.append(w * (x[:n_p] - anchor))
            memo.update(x=x.copy(), f=np.concatenate(fs), J=np.vstack(Js))
        return memo

    return (lambda x: at(x)["f"]), (lambda x, *_: at(x)["J"])


class CompressedObjective:
    """An objective with ``compressed_blocks`` seen through :func:`_compressed_blocks`: its ``residual`` and
    ``jacobian`` are the compressed problem's (same cost, gradient, Gauss-Newton matrix, singular values),
    for minimizers that take an objective (:func:`run_start` wraps every such objective in it)."""

    def __init__(self, obj):
        self.obj = obj
        self.residual, self.jacobian = _compressed_blocks(obj)

    def sd(self, x) -> float:
        return float(np.sum(self.residual(x) ** 2))


@dataclass(frozen=True)
class StartOutcome:
    """What one start of the minimizer did.

    Attributes
    ----------
    start, p : (n_p,) normalized parameters at the start and at the end
    sd_start, sd : square deviation at the start and at the end
    converged : bool (scipy status > 0)
    message : str
    iterations : int (Jacobian evaluations)
    evaluations : int (residual evaluations)
    jacobian_rank : int (numerical rank of the final Jacobian, rtol 1e-8)
    condition : float (2-norm condition number of the final Jacobian)
    time_s : float
    """

    start: np.ndarray
    p: np.ndarray
    sd_start: float
    sd: float
    converged: bool
    message: str
    iterations: int
    evaluations: int
    jacobian_rank: int
    condition: float
    time_s: float

    def to_dict(self) -> dict:
        return {
            "start": self.start.tolist(),
            "p": self.p.tolist(),
            "sd_start": self.sd_start,
            "sd": self.sd,
            "converged": self.converged,
            "message": self.message,
            "iterations": self.iterations,
            "evaluations": self.evaluations,
            "jacobian_rank": self.jacobian_rank,
            "condition": self.condition,
            "time_s": self.time_s,
        }


@dataclass(frozen=True)
class Calibration:
    """Outcome of a multi-start calibration.

    Attributes
    ----------
    p : (n_p,) best normalized parameters
    sd : float, square deviation at p (calibration data)
    sd_nominal : float, square deviation at the first start (the nominal point)
    outcomes : tuple of StartOutcome, nominal first
    best : int, index of the chosen start
    parameter_names : tuple of str
    starts_planned : int, the starts there were to run (``len(outcomes)`` unless the
        stopping rule ended the multi-start early; 0 in results stored before it)
    """

    p: np.ndarray
    sd: float
    sd_nominal: float
    outcomes: tuple
    best: int
    parameter_names: tuple
    starts_planned: int = 0

    @property
    def distinct_minima(self) -> int:
        """Distinct minima the starts ended in (:func:`distinct_minima`)."""
        atol = same_minimum_atol([o.sd_start for o in self.outcomes])
        return distinct_minima([o.sd for o in self.outcomes], atol=atol)

    @property
    def stopped_early(self) -> bool:
        """The stopping rule ended the multi-start before every planned start ran."""
        return 0 < len(self.outcomes) < self.starts_planned

    def describe_starts(self) -> str:
        """How many starts ran and why, for the log."""
        n = len(self.outcomes)
        w = self.distinct_minima
        if self.stopped_early:
            return (f"{n} of {self.starts_planned} starts: stopped by the Bayesian rule after {n} starts found "
                    f"{w} distinct minim{'um' if w == 1 else 'a'}")
        return f"{n} starts, {w} distinct minim{'um' if w == 1 else 'a'}"

    def to_dict(self) -> dict:
        return {
            "p": self.p.tolist(),
            "sd": self.sd,
            "sd_nominal": self.sd_nominal,
            "best_start": self.best,
            "parameter_names": list(self.parameter_names),
            "starts_planned": self.starts_planned,
            "distinct_minima": self.distinct_minima,
            "starts": [o.to_dict() for o in self.outcomes],
        }


def latin_hypercube_starts(lower, upper, n: int, seed: int | None = 0) -> np.ndarray:
    """``n`` Latin-hypercube points inside [lower, upper]: (n, n_p)."""
    from scipy.stats import qmc

    lower = np.asarray(lower, float)
    upper = np.asarray(upper, float)
    if n <= 0:
        return np.zeros((0, lower.size))
    u = qmc.LatinHypercube(d=lower.size, seed=seed).random(n)
    return qmc.scale(u, lower, upper)


def check_bounds(lower, upper, n_p):
    lower = np.asarray(lower, float)
    upper = np.asarray(upper, float)
    if lower.shape != (n_p,) or upper.shape != (n_p,):
        raise CalibrationError(f"bounds must have {n_p} entries, got {lower.shape}, {upper.shape}")
    if np.any(lower >= upper) or np.any(lower <= -1):
        bad = np.flatnonzero((lower >= upper) | (lower <= -1)).tolist()
        raise CalibrationError(f"parameter bounds invalid (need -1 < lower < upper) for parameters {bad}")
    return lower, upper


def single_thread():
    """Context limiting BLAS to one thread (parallelism comes from the executor; avoids oversubscription)."""
    return blas_threads(1)


def run_start(args) -> StartOutcome:
    """Minimize from one start (module-level so worker processes can run it).

    ``args`` = (objectives, x0, lower, upper, max_nfev, xtol); see :func:`_run_start`.
    """
    with single_thread():
        return _run_start(args)


def _run_start(args) -> StartOutcome:
    """Minimize from one start (module-level so worker processes can run it).

    ``args`` = (objectives, x0, lower, upper, max_nfev, xtol): ``objectives`` is
    one Objective or a sequence run in turn (damping continuation), each
    starting where the previous one stopped; the outcome reports the last.
    """
    from scipy.optimize import least_squares

    objs, x0, lower, upper, max_nfev, xtol = args
    if not isinstance(objs, (list, tuple)):  # one objective (Objective or any with residual/jacobian)
        objs = [objs]
    # a tall problem is solved in its compressed form (same steps, cost, singular values): the solver's SVD at
    # every iteration is then (n+1) x n, not (values x n), and the dense Jacobian is never formed
    objs = [CompressedObjective(o) if hasattr(o, "compressed_blocks") and o.n_values >= 4 * (o.n_unknowns + 1)
            else o for o in objs]
    t0 = time.perf_counter()
    x0 = np.clip(np.asarray(x0, float), lower, upper)
    x = x0
    its = nfev = 0
    res = None
    try:
        for k, obj in enumerate(objs):
            # a continuation stage only hands its end point to the next, narrower one:
            # it needs no tight convergence (STAGE_TOL); the last stage runs to xtol
            last = k == len(objs) - 1
            res = least_squares(
                obj.residual,
                x,
                jac=obj.jacobian,
                bounds=(lower, upper),
                method="trf",
                x_scale="jac",
                xtol=xtol if last else max(xtol, STAGE_TOL),
                ftol=1e-12 if last else STAGE_TOL,
                gtol=1e-12 if last else STAGE_TOL,
                max_nfev=max_nfev,
            )
            x = np.asarray(res.x)
            its += int(res.njev or 0)
            nfev += int(res.nfev)
    except CalibrationError as exc:  # e.g. reduced mass not definite far out
        sd0 = float(np.sum(objs[-1].residual(x0) ** 2)) if res is None else np.inf
        return StartOutcome(x0, x, sd0, np.inf, False, str(exc), its, nfev, 0, np.inf, time.perf_counter() - t0)
    obj = objs[-1]
    sd0 = float(np.sum(obj.residual(x0) ** 2))
    J = obj.jacobian(x)
    s = np.linalg.svd(J, compute_uv=False)
    rank = int(np.sum(s > 1e-8 * s[0])) if s.size and s[0] > 0 else 0
    cond = float(s[0] / s[-1]) if s.size and s[-1] > 0 else np.inf
    return StartOutcome(
        start=x0,
        p=x,
        sd_start=sd0,
        sd=float(2 * res.cost),
        converged=bool(res.status > 0),
        message=str(res.message),
        iterations=its,
        evaluations=nfev,
        jacobian_rank=rank,
        condition=cond,
        time_s=time.perf_counter() - t0,
    )


@dataclass(frozen=True)
class FitOptions:
    """Settings of the multi-start Levenberg-Marquardt (:func:`calibrate`).

    Attributes
    ----------
    n_starts : int
        Number of Latin-hypercube starts besides the first (paper: 20).
    seed : int or None
        Seed of the Latin hypercube.
    quantity : str
        FRF quantity of the data ("accelerance", "mobility", "receptance").
    max_nfev : int
        Residual evaluations allowed per start (per continuation stage).
    xtol : float
        Relative parameter-step tolerance of the minimizer.
    adaptive_starts : bool
        Stop the multi-start early by :func:`enough_starts` (the starts run in start order; the
        result is the best of the leading starts at which the rule stops, whatever the executor):
        8 starts when all end in one minimum. False: run every start.
    """

    n_starts: int = 20
    seed: int | None = 0
    quantity: str = "accelerance"
    max_nfev: int = 100
    xtol: float = 1e-10
    adaptive_starts: bool = True

    def __post_init__(self):
        if self.n_starts < 0:
            raise CalibrationError(f"FitOptions.n_starts must be >= 0, got {self.n_starts}")
        if self.max_nfev < 1:
            raise CalibrationError(f"FitOptions.max_nfev must be >= 1, got {self.max_nfev}")


@dataclass(frozen=True)
class CycleOptions(FitOptions):
    """Settings of :func:`calibrate_cycles`: the multi-start's (:class:`FitOptions`) plus re-basis cycles.

    Attributes
    ----------
    max_cycles : int
        Cycles at most (1 = keep the first basis).
    tol : float
        Stop when max |dp| between cycles is below this (normalized p).
    basis_factor : float
        Modes up to ``basis_factor`` x band top enter the basis, beside the loads' statics and their first
        moments (default 1.25; docs/calibration.md, stop 38).
    enrich : bool
        Parameter-derivative enrichment of the basis.
    refresh : bool
        A new basis starts from the previous one by one block inverse
        iteration instead of a fresh Lanczos solution.
    basis_tol : float or None
        Re-basis only when the basis is inadequate at the new point: before
        each further cycle the energy-norm Ritz residuals eta of the in-band
        modes (:func:`calibration._surrogate.basis_residuals`; eta / 2 is about
        the relative frequency error of each Ritz mode) are computed at p, and
        the cycles end when every Ritz frequency error is at most ``basis_tol``
        times the half-power bandwidth 2 zeta0 f (eta <= 4 basis_tol zeta0):
        a new basis would give the same surrogate there up to that. None:
        re-basis whenever p moved by more than ``tol``.
    rebasis : {"iterated", "kept", "solved", "corrected", "compressed"}
        The enrichment of a refreshed basis (:func:`calibration.build_surrogate`):
        the inverse-iterated old basis, the old enrichment columns, or new
        derivative solves at p; or "corrected": no rebuild, the old basis plus
        the solved residuals of its modes and static solutions at p
        (:func:`calibration._correct.corrected_surrogate`); "compressed": that,
        cut back to a cold build's vectors at p (:func:`calibration._correct.compressed`).
        The library default stays "iterated"; the campaign's is "compressed".
    """

    max_cycles: int = 4
    tol: float = 1e-4
    basis_factor: float = BASIS_FACTOR
    enrich: bool = True
    refresh: bool = True
    basis_tol: float | None = None
    rebasis: str = "iterated"

    def fit(self) -> FitOptions:
        """The multi-start part."""
        return FitOptions(self.n_starts, self.seed, self.quantity, self.max_nfev, self.xtol, self.adaptive_starts)


def _options(cls, options, legacy: dict, where: str):
    """``options`` updated with the legacy keyword arguments (the former long argument lists)."""
    names = {f.name for f in fields(cls)}
    unknown = sorted(set(legacy) - names)
    if unknown:
        raise TypeError(f"{where}() got unexpected keyword argument(s) {unknown}")
    base = cls() if options is None else options
    if not isinstance(base, cls):
        raise TypeError(f"{where}(): options must be a {cls.__name__}, got {type(base).__name__}")
    return replace(base, **legacy) if legacy else base


def calibrate(
    surrogate: Surrogate,
    data,
    lower,
    upper,
    zeta0: float = 0.01,
    options: FitOptions | None = None,
    *,
    executor=None,
    p_start=None,
    continuation=(),
    **legacy,
) -> Calibration:
    """Multi-start bounded Levenberg-Marquardt on the surrogate.

    Parameters
    ----------
    surrogate : Surrogate
    data : sequence of FitData
        Test FRFs (usually the damping-equalized identified model on the
        half-bandwidth grid).
    lower, upper : (n_p,) normalized bounds
    zeta0 : float
        Model modal damping (= the equalization damping).
    options : FitOptions, optional
        Starts, seed, quantity, evaluations, tolerance (default
        ``FitOptions()``). Their names are also accepted as keyword
        arguments (``n_starts=0``), which update ``options``.
    executor : Executor, optional
        Default: serial.
    p_start : (n_p,), optional
        The deterministic first start (default zeros, the nominal point).
    continuation : sequence of (zeta, data)
        Damping continuation: stages with larger damping run first from every
        start (model damping ``zeta``, test data equalized to the same
        ``zeta``, e.g. on a half-bandwidth grid for that ``zeta``). Wider
        resonances make the log-ratio metric smooth over a wider basin, so
        starts far from the optimum do not stall with a mode on the wrong
        side of a test resonance; the final stage is (zeta0, data).

    Returns
    -------
    Calibration
    """
    o = _options(FitOptions, options, legacy, "calibrate")
    n_p = surrogate.n_params
    lower, upper = check_bounds(lower, upper, n_p)
    objs = [Objective(surrogate, d, z, o.quantity) for z, d in continuation]
    objs.append(Objective(surrogate, data, zeta0, o.quantity))
    first = np.zeros(n_p) if p_start is None else np.asarray(p_start, float)
    starts = np.vstack([first[None, :], latin_hypercube_starts(lower, upper, o.n_starts, o.seed)])
    executor = executor or SerialExecutor()
    jobs = [(objs, x0, lower, upper, o.max_nfev, o.xtol) for x0 in starts]
    outcomes = _multistart(executor, jobs) if o.adaptive_starts else executor.map(run_start, jobs)
    sds = np.array([o.sd for o in outcomes])
    best = int(np.nanargmin(sds))
    return Calibration(
        p=outcomes[best].p,
        sd=outcomes[best].sd,
        sd_nominal=outcomes[0].sd_start,
        outcomes=tuple(outcomes),
        best=best,
        parameter_names=surrogate.parameter_names,
        starts_planned=len(jobs),
    )


def _multistart(executor, jobs: list) -> list:
    """The starts' outcomes in start order, up to where :func:`stopping_point` says stop.

    The starts run in batches over the executor's workers: first as many as the rule needs at
    least (:data:`MIN_STARTS`, rounded up to whole rounds of the workers), then one round at a time. Starts a batch
    ran beyond the stopping point are dropped, so the result does not depend on the number of workers.
    """
    width = max(int(getattr(executor, "width", 1) or 1), 1)
    first = -(-MIN_STARTS // width) * width
    outcomes: list = []
    while len(outcomes) < len(jobs):
        k = len(outcomes)
        size = first if k == 0 else width
        outcomes += list(executor.map(run_start, jobs[k:k + size]))
        stop = stopping_point([o.sd for o in outcomes], [o.sd_start for o in outcomes])
        if stop is not None:
            return outcomes[:stop]
    return outcomes


@dataclass(frozen=True)
class CycleResult:
    """Calibration with re-basis cycles.

    Attributes
    ----------
    calibration : Calibration
        The multi-start calibration of the first cycle (all start outcomes).
    p : (n_p,) final normalized parameters
    sd : float, final square deviation on the calibration data
    surrogate : Surrogate built at the final basis point
    cycles : tuple of dict, per cycle: p, sd, basis size, max parameter change, times
    basis : (n, r) ndarray or None
        The full-order M-orthonormal basis of ``surrogate`` (kept for later
        re-basis cycles and for stages that extend the model; not serialized).
    refinement : calibration._refine.Refinement or None
        The raw-line refinement that followed (then ``p`` and ``surrogate``
        are the refined ones and ``sd`` stays the equalized-stage SD).
    """

    calibration: Calibration
    p: np.ndarray
    sd: float
    surrogate: Surrogate
    cycles: tuple
    basis: np.ndarray | None = field(default=None, repr=False, compare=False)
    refinement: object | None = None

    def to_dict(self) -> dict:
        out = {"p": self.p.tolist(), "sd": self.sd, "cycles": list(self.cycles),
               "multistart": self.calibration.to_dict()}
        if self.refinement is not None:
            out["refinement"] = self.refinement.to_dict()
        return out


_CYCLE_POSITIONAL = ("n_starts", "seed", "executor", "quantity", "max_cycles", "tol", "basis_factor", "surrogate",
                     "log", "continuation", "enrich", "max_nfev", "basis", "refresh")


def calibrate_cycles(
    model,
    data,
    band_hz,
    lower,
    upper,
    zeta0: float = 0.01,
    *positional,
    options: CycleOptions | None = None,
    executor=None,
    surrogate: Surrogate | None = None,
    basis=None,
    continuation=(),
    log=None,
    **legacy,
) -> CycleResult:
    """Calibrate; re-build the basis at the calibrated point and refine until p stops moving.

    Cycle 1 is the full multi-start on a basis at the nominal point (or the
    given ``surrogate``). Each further cycle recomputes the basis at the
    current p and runs one start from it; cycles stop when
    ``max |dp| < options.tol`` or after ``options.max_cycles``.
    ``continuation`` applies to cycle 1 (see :func:`calibrate`). With
    ``options.refresh`` a new basis starts from the previous one (``basis``,
    the (n, r) basis of ``surrogate`` when that is given) by one block inverse
    iteration instead of a fresh Lanczos solution (see :func:`build_surrogate`).

    Parameters
    ----------
    model : FRFModel
    data : sequence of FitData
    band_hz : (lo, hi) Hz
    lower, upper : (n_p,) normalized bounds
    zeta0 : float
        Model modal damping (= the equalization damping).
    options : CycleOptions, optional
        Multi-start and cycle settings (default ``CycleOptions()``); their
        names are also accepted as keyword arguments, which update it.
    executor : Executor, optional
        Runs the multi-start of cycle 1 (default serial).
    surrogate, basis : Surrogate and its (n, r) basis, optional
        The cycle-1 surrogate (default: built at the nominal point).
    continuation : sequence of (zeta, data)
    log : callable, optional
        Progress messages.
    *positional
        The former positional arguments after ``zeta0`` (n_starts, seed,
        executor, quantity, max_cycles, tol, ...), still accepted; prefer
        ``options``.

    Returns
    -------
    CycleResult
        Keeps the final surrogate and its basis.
    """
    from calibration._correct import rebased
    from calibration._surrogate import basis_residuals, build_surrogate

    if len(positional) > len(_CYCLE_POSITIONAL):
        raise TypeError(f"calibrate_cycles() takes at most {6 + len(_CYCLE_POSITIONAL)} positional arguments")
    named = dict(executor=executor, surrogate=surrogate, basis=basis, continuation=continuation, log=log)
    for name, value in zip(_CYCLE_POSITIONAL, positional):
        if name in named:
            named[name] = value
        else:
            if name in legacy:
                raise TypeError(f"calibrate_cycles() got multiple values for argument {name!r}")
            legacy[name] = value
    o = _options(CycleOptions, options, legacy, "calibrate_cycles")
    executor, surrogate, basis, continuation, log = (named[k] for k in
                                                     ("executor", "surrogate", "basis", "continuation", "log"))
    fit = o.fit()
    say = log or (lambda msg: None)
    t0 = time.perf_counter()
    if surrogate is None:
        surrogate, basis = build_surrogate(model, np.zeros(model.n_params), band_hz, o.basis_factor, enrich=o.enrich)
    t1 = time.perf_counter()
    say(f"cycle 1: basis {surrogate.size} ({len(surrogate.basis_frequencies_hz)} modes), "
        f"{'up to ' if o.adaptive_starts and o.n_starts + 1 > MIN_STARTS else ''}{o.n_starts + 1} starts")
    cal = calibrate(surrogate, data, lower, upper, zeta0, fit, executor=executor, continuation=continuation)
    t2 = time.perf_counter()
    say(f"cycle 1: {cal.describe_starts()} ({t2 - t1:.1f} s)")
    cycles = [{"cycle": 1, "p": cal.p.tolist(), "sd": cal.sd, "basis_size": surrogate.size,
               "basis_s": t1 - t0, "fit_s": t2 - t1, "max_dp": float(np.max(np.abs(cal.p)))}]
    p, sd = cal.p, cal.sd
    for k in range(2, o.max_cycles + 1):
        if o.basis_tol is not None and basis is not None:
            chk = basis_residuals(model, surrogate, basis, p, band_hz, 4 * o.basis_tol * zeta0)
            cycles[-1]["basis_check"] = chk.to_dict()
            say(f"cycle {k}: basis at p: {chk.describe()}" + (": kept, cycles end" if chk.adequate else ""))
            if chk.adequate:
                break
        ta = time.perf_counter()
        surrogate, basis, corr = rebased(model, surrogate, basis, p, band_hz, o.basis_factor, o.enrich, o.rebasis,
                                         o.refresh)
        tb = time.perf_counter()
        if corr is not None:
            say(f"cycle {k}: basis corrected at p: {corr.describe()}")
        sub = calibrate(surrogate, data, lower, upper, zeta0, replace(fit, n_starts=0), p_start=p)
        tc = time.perf_counter()
        dp = float(np.max(np.abs(sub.p - p)))
        cycles.append({"cycle": k, "p": sub.p.tolist(), "sd": sub.sd, "basis_size": surrogate.size,
                       "basis_s": tb - ta, "fit_s": tc - tb, "max_dp": dp,
                       **({} if corr is None else {"correction": corr.to_dict()})})
        say(f"cycle {k}: sd {sub.sd:.4g}, max |dp| {dp:.2e}")
        p, sd = sub.p, sub.sd
        if dp < o.tol:
            break
    return CycleResult(cal, p, sd, surrogate, tuple(cycles), basis)
