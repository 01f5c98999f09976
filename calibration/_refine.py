"""Refinement on the measured lines: from the equalized optimum to the noise floor.

The paper's stage fits the surrogate with one damping ratio zeta0 to the
*identified* test model equalized to zeta0 (Eq. 2.11-2.13). That metric is
smooth, which is why the multi-start works, but its target carries the
identification's misfit (band edges, the mass line, a missed or spurious
pole), and the optimum follows that misfit away from the truth. This module
takes the equalized optimum and refines it against the measured lines
themselves, in a short damping continuation that ends on the raw data:

stage ``s`` (damping floor ``zeta_s``, decreasing to 0)
    target  T_s = H_raw + H_id(max(zeta_id, zeta_s)) - H_id(zeta_id)
    model   surrogate with per-mode damping max(zeta_k, zeta_s)

where ``H_id(.)`` is the identified model with its physical poles' damping
replaced, and ``zeta_k`` is the identified damping mapped to the FE modes by
MAC (the FE modes no test mode pairs with take the median identified
damping). The identification enters only through the *change* of damping of
its own poles, so its fit residual passes through unchanged: the target of
every stage is the raw data with the damping of the measured modes raised.
The last stage (``zeta_s = 0``) is the raw data against the model with the
identified damping: its optimum is the least-squares estimate on the
measurements, which reaches the noise floor when the model class holds the
truth. Stages with a damping floor are weighted as a quadrature in log f
(:func:`log_frequency_weights`), so an uneven grid dense at resonances
measures what the paper's half-bandwidth sampling measures; the last stage
weights every measured line alike (or by its standard error, when given).

The per-mode damping follows each FE mode through the refinement (modes are
tracked by their overlap with the modes at the start point, so a crossing
does not swap dampings), and the Jacobian is exact for that model: with
A_j = X^T dK_r/dp_j X, B_j = X^T dM_r/dp_j X in the reduced modal
coordinates, d lambda_k = A_kk - lambda_k B_kk, dc_k = zeta_k d lambda_k /
omega_k and dX = X G_j (G_lk = (A_lk - lambda_k B_lk) / (lambda_k - lambda_l),
G_kk = -B_kk / 2; the reduced basis is complete, so the expansion is exact).
Degenerate groups (|lambda_k - lambda_l| tiny, the rigid modes) take the limit
of their divided differences (:mod:`calibration._modal_derivative`, which
builds these rows for this objective, the equalized one and the diagnosis's
candidates).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from calibration._errors import CalibrationError
from calibration._fit import FitData, _compressed_blocks, log_frequency_weights, stacked_residual, value_weights
from calibration._metric import log_deviation, square_deviation
from calibration._threads import blas_threads
from calibration._modal_derivative import FRFRows, complex_rows, eigen_derivatives, parameter_derivatives
from calibration._surrogate import (
    Surrogate,
    modal_omegas,
    quantity_factor,
    reduced_modes,
)
from calibration._damping import IdentifiedModes, mapped_damping, median_damping

#: Default damping floors of the refinement stages, as multiples of zeta0 (the last, 0, is the raw data).
DEFAULT_FLOORS = (1.0, 0.3, 0.1, 0.0)


def debiased_target(raw: FitData, identification, channels, zeta_floor: float) -> FitData:
    """The raw lines with the damping of the identified modes raised to ``zeta_floor``.

    ``T = H_raw + H_id(max(zeta_id, zeta_floor)) - H_id(zeta_id)`` on the raw
    lines: only the identified physical poles whose damping is below the
    floor are changed, every other part of the identified model (residual
    poles, D term) cancels, and so does its misfit to the data.

    Parameters
    ----------
    raw : FitData
        Measured lines (frf rows = ``raw.outputs``).
    identification : identification.Identification
        Identified model of the same article; its output rows are ``channels``.
    channels : sequence of str
        Output names of the identified model's rows.
    zeta_floor : float
        Damping floor (0 returns ``raw`` unchanged).
    """
    if zeta_floor <= 0:
        return raw
    from identification import equalized

    lookup = {n: i for i, n in enumerate(channels)}
    missing = [n for n in raw.outputs if n not in lookup]
    if missing:
        raise CalibrationError(f"article {raw.article!r}: channels {missing} are not outputs of its identified model")
    rows = [lookup[n] for n in raw.outputs]
    poles = identification.poles
    lam = poles.eigenvalues[poles.physical]
    low = lam[pole_damping(lam) < zeta_floor]
    H_id = identification.model.frf(raw.freq_hz)[:, rows]
    H_eq = equalized(identification, zeta_floor, physical=low).frf(raw.freq_hz)[:, rows]
    if raw.inputs and H_id.shape[2] != raw.frf.shape[2]:
        raise CalibrationError(
            f"article {raw.article!r}: identified model has {H_id.shape[2]} inputs, data {raw.frf.shape[2]}")
    return replace(raw, frf=raw.frf + (H_eq - H_id))


def pole_damping(lam) -> np.ndarray:
    lam = np.asarray(lam, complex)
    return -lam.real / np.maximum(np.abs(lam), 1e-300)


class ModalDampingObjective:
    """Residual and exact Jacobian of the (weighted) square deviation with per-mode damping.

    Parameters
    ----------
    surrogate : Surrogate
    data : sequence of FitData
    zeta : sequence of (r,) arrays
        Damping ratio of each reduced mode at ``p_ref`` for each data set (e.g.
        mapped from that article's identified modes).
    p_ref : (n_p,)
        Point where ``zeta`` was assigned; modes are tracked from there.
    floor : float
        Damping floor: the model uses max(zeta_k, floor).
    quantity : str
    fit_damping : sequence of int arrays, optional
        Per data set, the reduced modes (indices at ``p_ref``) whose damping
        is estimated with the parameters: the unknowns are then
        ``x = [p, log zeta_sel(set 1), log zeta_sel(set 2), ...]`` (nuisance
        parameters; identified damping is a noisy estimate, and its error
        would otherwise bias p near every resonance). ``x0``/bounds come from
        :meth:`damping_start`.
    """

    def __init__(self, surrogate: Surrogate, data, zeta, p_ref, floor: float = 0.0,
                 quantity: str = "accelerance", fit_damping=None):
        self.sur = surrogate
        self.data = list(data)
        self.quantity = quantity
        if len(zeta) != len(self.data):
            raise CalibrationError(f"{len(zeta)} damping vectors for {len(self.data)} data sets")
        self.zeta = [np.maximum(np.asarray(z, float), floor) for z in zeta]
        self.n_p = surrogate.n_params
        self.fit = [np.zeros(0, int) for _ in self.data] if fit_damping is None else \
            [np.asarray(i, int) for i in fit_damping]
        self._offsets = np.cumsum([0] + [i.size for i in self.fit])
        _, self._X_ref = reduced_modes(surrogate, np.asarray(p_ref, float))
        self._out = [surrogate.output_index(d.outputs) for d in self.data]
        lookup = {n: i for i, n in enumerate(surrogate.input_names)}
        self._in = []
        for d in self.data:
            names = d.inputs or surrogate.input_names
            missing = [n for n in names if n not in lookup]
            if missing:
                raise CalibrationError(f"drives {missing} are not inputs of the model {list(surrogate.input_names)}")
            self._in.append(np.array([lookup[n] for n in names]))
        self._sqrt_w = value_weights(self.data)
        self.n_values = sum(d.n_values for d in self.data)
        self._frows = FRFRows(surrogate, self.data, self._out, self._in, self._sqrt_w, quantity)
        self._memo_p = None
        self._memo = None

    @property
    def n_unknowns(self) -> int:
        return self.n_p + int(self._offsets[-1])

    def damping_start(self, factor: float = 4.0):
        """(x0, lower, upper) of the damping unknowns: log of the given damping, +- log(factor)."""
        x0 = np.concatenate([np.log(z[i]) for z, i in zip(self.zeta, self.fit)]) if self._offsets[-1] else \
            np.zeros(0)
        return x0, x0 - np.log(factor), x0 + np.log(factor)

    def damping_at(self, x) -> list:
        """Per data set, the damping of the reduced modes at p_ref for unknowns ``x``."""
        x = np.asarray(x, float)
        out = []
        for a, (z, i) in enumerate(zip(self.zeta, self.fit)):
            if i.size:
                z = z.copy()
                z[i] = np.exp(x[self.n_p + self._offsets[a]:self.n_p + self._offsets[a + 1]])
            out.append(z)
        return out

    def _tracked(self, x):
        """Reduced modes at p and, per data set, each mode's damping and reference index (tracked from p_ref)."""
        from scipy.optimize import linear_sum_assignment

        p = x[:self.n_p]
        lam, X = reduced_modes(self.sur, p)
        overlap = np.abs(self._X_ref.T @ (self.sur.M.at(p) @ X))  # (ref, now)
        best = np.argmax(overlap, axis=0)
        if np.unique(best).size != best.size:  # a crossing or a near-degenerate pair: assign globally
            _, best = linear_sum_assignment(-overlap.T)
        return lam, X, [z[best] for z in self.damping_at(x)], best

    def _frf(self, lam, X, zeta, d, oi, ii, w):
        om, rigid = modal_omegas(lam, self.sur.rigid_hz)
        c = np.where(rigid, 0.0, 2 * zeta * om)
        lam_c = np.where(rigid, 0.0, om**2)
        r = 1.0 / (lam_c[None, :] - w[:, None] ** 2 + 1j * w[:, None] * c[None, :])
        q = quantity_factor(w, self.quantity)
        u = self.sur.outputs[oi] @ X
        v = X.T @ self.sur.inputs[:, ii]
        H = np.einsum("om,fm,mi->foi", u, r * q[:, None], v, optimize=True)
        return H, r, q, u, v, om, rigid

    def deviation(self, p) -> list:
        lam, X, zetas, _ = self._tracked(self._x(p))
        out = []
        for d, oi, ii, z in zip(self.data, self._out, self._in, zetas):
            H = self._frf(lam, X, z, d, oi, ii, 2 * np.pi * d.freq_hz)[0]
            e = log_deviation(H, d.frf)
            out.append((e if d.mask is None else e[d.mask]).ravel())
        return out

    def _x(self, x):
        """The unknowns; a bare p (no damping part) takes the damping as given."""
        x = np.asarray(x, float)
        if x.size == self.n_p and self.n_unknowns > self.n_p:
            x = np.concatenate([x, self.damping_start()[0]])
        return x

    def residual(self, p):
        p = self._x(p)
        if self._memo_p is not None and np.array_equal(p, self._memo_p):
            return self._memo[0]
        return stacked_residual(np.concatenate(self.deviation(p)), sqrt_w=self._sqrt_w)

    def sd(self, p) -> float:
        """Weighted square deviation sum(w |eps|^2)/sum(w)."""
        return float(np.sum(self.residual(p) ** 2))

    def sd_unweighted(self, p) -> float:
        """Plain Eq. 2.23 square deviation over the values (every line alike)."""
        return square_deviation(np.concatenate(self.deviation(p)))

    def _build(self, x):
        """``build(a, lines)``: the rows of data set ``a`` on a line slice (:meth:`FRFRows.rows`): the derivatives
        by p, then by the data set's own damping unknowns, then the residual."""
        lam, X, zetas, best = self._tracked(x)
        D, G = eigen_derivatives(lam, *parameter_derivatives(self.sur, x[:self.n_p], X), self.sur.rigid_hz)
        where = np.empty(lam.size, int)
        where[best] = np.arange(lam.size)  # reference mode -> current index
        facs = [self._frows.factors(a, lam, X, zetas[a], D, G) for a in range(len(self.data))]
        fits = [where[i] for i in self.fit]

        def build(a, lines):
            f, fit = facs[a], fits[a]

            def damping(r, rq, w, c, mask, out):  # d H / d log zeta_k = -q u_k v_k r_k^2 (i w 2 zeta_k omega_k)
                g = -(rq * r)[:, fit] * (1j * w[:, None] * (2 * f["zeta"][fit] * f["om"][fit]
                                                            * ~f["rigid"][fit])[None, :])
                Sf = f["S"][fit][None]
                complex_rows(g.real[:, :, None] * Sf, g.imag[:, :, None] * Sf, c, mask, out)

            return self._frows.rows(a, f, lines, fit.size, damping)

        return build

    def _article_rows(self, x):
        """Per data set the real array (n_p + n_fit_a + 1, 2 N_a): rows the derivatives of the (weighted)
        residual by p and by the data set's own damping unknowns (the other data sets' damping does not touch
        its values), last row the residual; columns the real parts of its values, then the imaginary parts
        (frequency-major, as :meth:`evaluate` stacks them). Built by line slices on :func:`data_threads`
        threads (:class:`FRFRows`), so no (unknowns x values) complex array is formed."""
        return self._frows.all_rows(self._build(x))

    def compressed_blocks(self, x):
        """:meth:`blocks` with each data set's rows replaced by the triangle R of their QR factorization (same
        R^T R = [J_a f_a]^T [J_a f_a]: see :func:`_compressed_blocks`), by TSQR over the line slices
        (:meth:`FRFRows.compressed`): the tall rows never exist in full."""
        x = self._x(x)
        return [(self._columns(a), R) for a, R in enumerate(self._frows.compressed(self._build(x)))]

    def _columns(self, a):
        return np.concatenate([np.arange(self.n_p), self.n_p + np.arange(self._offsets[a], self._offsets[a + 1])])

    def evaluate(self, p):
        """(r, J): real residual (2N,) and its exact Jacobian (2N, n_p)."""
        x = self._x(p)
        if self._memo_p is not None and np.array_equal(x, self._memo_p):
            return self._memo
        memo = self._frows.assembled(self._article_rows(x), [self._columns(a) for a in range(len(self.data))],
                                     self.n_unknowns)
        self._memo_p, self._memo = x.copy(), memo
        return memo

    def blocks(self, x):
        """The residual and Jacobian in row blocks, one per data set: a list of (cols, rows), ``rows`` the
        (len(cols) + 1, 2 N_a) array ``[J_a f_a]^T``: ``J_a`` the only non-zero columns ``cols`` of the data
        set's rows of :meth:`evaluate`'s Jacobian (p and its own damping unknowns), ``f_a`` its rows of the
        residual (Re before Im). The dense Jacobian is n_p + all damping unknowns wide, most of it zeros
        when several articles each estimate their own damping. (``rows.T`` is Fortran-ordered, as LAPACK
        takes it.)"""
        x = self._x(x)
        return [(self._columns(a), rows) for a, rows in enumerate(self._article_rows(x))]

    def jacobian(self, p):
        return self.evaluate(p)[1]


@dataclass(frozen=True)
class RefineStage:
    """One stage of the refinement: damping floor, start and end, SD (weighted as fitted)."""

    floor: float
    p_start: np.ndarray
    p: np.ndarray
    sd_start: float
    sd: float
    evaluations: int
    time_s: float
    message: str
    cpu_s: float | None = None  # CPU time of the process (wall time misleads on a shared machine)

    def to_dict(self) -> dict:
        return {"zeta_floor": self.floor, "p": self.p.tolist(), "sd_start": self.sd_start, "sd": self.sd,
                "evaluations": self.evaluations, "time_s": self.time_s, "cpu_s": self.cpu_s,
                "message": self.message}


@dataclass(frozen=True)
class Refinement:
    """Result of :func:`refine`.

    Attributes
    ----------
    p : (n_p,) refined normalized parameters
    sd_raw : float
        Eq. 2.23 square deviation of the model (identified damping) on the raw
        calibration lines at ``p``, every line alike.
    sd_raw_start : float
        The same at the start point (the equalized optimum).
    stages : tuple of RefineStage
    damping : tuple of dict per data set: the MAC pairs used (fe_hz, test_hz, mac, zeta)
    zeta : tuple of (r,) arrays, the per-mode damping of each data set, assigned at ``p_zeta``
    p_zeta : (n_p,) the point where ``zeta`` was assigned (the start point)
    articles : tuple of dict
        With several articles in a member: each article's own raw-line
        estimate started from ``p`` (article, p, sd_raw_calibration, sd_holdout).
    fit_modes : tuple of int arrays
        Per data set, the reduced modes (indices at ``p_zeta``) whose damping
        the last stage estimated.
    basis_checks : tuple of dict
        The basis adequacy checks of the re-basis cycles that followed
        (:meth:`calibration.BasisCheck.to_dict`), when the campaign ran them.
    unpaired : tuple of lists of dict
        Per data set, the FE modes in the band that no identified mode pairs
        with (``fe_hz``, ``zeta_start``: the median identified damping they
        started from, ``zeta_fitted``): the identification missed them (a
        mode these drives and channels hardly excite or see, or one it merged
        with a neighbour), so their damping comes from the raw lines alone.
    """

    p: np.ndarray
    sd_raw: float
    sd_raw_start: float
    stages: tuple
    damping: tuple
    zeta: tuple = field(repr=False, default=())
    p_zeta: np.ndarray | None = field(repr=False, default=None)
    articles: tuple = ()
    basis_checks: tuple = ()
    fit_modes: tuple = field(repr=False, default=())
    unpaired: tuple = ()

    def to_dict(self) -> dict:
        return {"p": self.p.tolist(), "sd_raw": self.sd_raw, "sd_raw_start": self.sd_raw_start,
                "stages": [s.to_dict() for s in self.stages], "damping_pairs": list(self.damping),
                "unpaired_in_band": [list(u) for u in self.unpaired],
                "articles": list(self.articles), "basis_checks": list(self.basis_checks)}

    def describe_unpaired(self, names=None) -> list[str]:
        """One line per data set with FE modes in the band that no identified mode pairs with (none: []);
        with ``names`` of several data sets each line starts with its name."""
        out = []
        for k, u in enumerate(self.unpaired):
            if u:
                who = f"{names[k]}: " if names is not None and len(names) > 1 and k < len(names) else ""
                out.append(f"{who}FE mode(s) in the band with no identified partner: "
                           + ", ".join(f"{q['fe_hz']:.1f} Hz" for q in u)
                           + " (the identification did not find them: weakly excited or seen by these drives and "
                             "channels, or merged with a neighbour); their damping is estimated from the raw lines "
                             "alone, from the median identified " + f"{100 * u[0]['zeta_start']:.3g} %: "
                           + ", ".join(f"{100 * q['zeta_fitted']:.3g} %" for q in u))
        return out


def article_damping(sur: Surrogate, p, modes: IdentifiedModes, mac_min: float = 0.6, band_hz=None):
    """Per-reduced-mode damping at p from one article's identified modes (MAC-paired), the pairs, and
    the reduced modes whose damping the raw stage estimates (every FE mode within the band +- 5 %, paired
    or not; without ``band_hz`` the paired ones).

    Unpaired FE modes take the median identified damping: an unobserved or
    out-of-band mode's damping barely shows in the band, and the median is a
    better guess for it than the equalization's zeta0.
    """
    zeta, pairs, _, _ = mapped_damping(sur, p, modes, median_damping(modes, 0.01), mac_min, band_hz)
    lam, _ = reduced_modes(sur, p)
    fe_hz = np.sqrt(np.clip(lam, 0, None)) / (2 * np.pi)
    paired = [int(np.argmin(np.abs(fe_hz - q["fe_hz"]))) for q in pairs]
    if band_hz is not None:
        # the FE modes in the band (+- 5 %), paired or missed by the identification; a paired mode outside keeps
        # its identified damping: the band's lines hardly see it, and a fitted value there absorbed what the
        # basis's static part leaves undamped (the higher modes' damping), fitting the calibration channels and
        # mispredicting the hold-out ones near the band top (docs/calibration.md, stop 41)
        lo, hi = band_hz
        near = np.flatnonzero((fe_hz > sur.rigid_hz) & (fe_hz >= 0.95 * lo) & (fe_hz <= 1.05 * hi))
        paired = sorted(near.tolist())
    return zeta, pairs, np.array(paired, int)


def carried_damping(old: Surrogate, basis_old, zeta, fit, p_zeta, new: Surrogate, basis_new, p, mass,
                    min_overlap: float = 0.5):
    """Per-mode damping of a refinement carried to a new basis at ``p`` (after a re-basis).

    The damping a refinement estimated belongs to the modes of its surrogate
    at ``p_zeta``; those are tracked to ``p`` on the old surrogate (reduced-mass
    overlap, as :class:`ModalDampingObjective` does) and then paired with the
    modes of the new surrogate at ``p`` by the full-order mass overlap
    ``(T_new x_new)^T M(p) (T_old x_old)`` (one assignment, over the modes up
    to twice the frequency of the highest estimated one). Modes of the new
    basis without a partner above ``min_overlap`` take the median damping.
    Starting the re-based raw stage from the estimated damping (instead of
    mapping the identified damping again) starts it where the last one ended
    up to the basis change, so it does not wander along directions the data
    cannot resolve.

    Parameters
    ----------
    old, new : Surrogate
    basis_old, basis_new : (n, r_old), (n, r_new) their bases
    zeta : sequence of (r_old,) arrays, the damping per data set at ``p_zeta``
    fit : sequence of int arrays, per data set the estimated modes (indices at ``p_zeta``)
    p_zeta, p : (n_p,)
    mass : (n, n) sparse, M(p)

    Returns
    -------
    zeta_new : list of (r_new,) arrays, damping of the new surrogate's modes at ``p``
    fit_new : list of int arrays, the new indices of the estimated modes
    """
    from scipy.optimize import linear_sum_assignment

    p = np.asarray(p, float)
    _, X_ref = reduced_modes(old, np.asarray(p_zeta, float))
    lam_old, X_old = reduced_modes(old, p)
    track = np.abs(X_ref.T @ (old.M.at(p) @ X_old))  # (ref, now)
    _, ref_of = linear_sum_assignment(-track.T)  # old mode now k <- ref mode ref_of[k]
    lam_new, X_new = reduced_modes(new, p)
    # only modes up to twice the highest estimated one are paired (the rest keep the median, as unpaired
    # modes do): two (n, m) shapes instead of the (r_new, r_old) cross product of the bases
    fitted_lam = [lam_old[np.isin(ref_of, np.asarray(f, int))] for f in fit]
    top = 4 * max([float(v.max()) for v in fitted_lam if v.size] + [float(np.min(lam_old))])
    so, sn = np.flatnonzero(lam_old <= top), np.flatnonzero(lam_new <= top)
    O = np.abs((basis_new @ X_new[:, sn]).T @ (mass @ (basis_old @ X_old[:, so])))  # (new, old now)
    r_, c_ = linear_sum_assignment(-O)
    good = O[r_, c_] >= min_overlap
    rows, cols = sn[r_[good]], so[c_[good]]
    zeta_new, fit_new = [], []
    for z, f in zip(zeta, fit):
        z = np.asarray(z, float)
        zn = np.full(X_new.shape[1], float(np.median(z)))
        zn[rows] = z[ref_of[cols]]
        fitted = set(np.asarray(f, int).tolist())
        fit_new.append(np.array(sorted(int(r) for r, c in zip(rows, cols) if ref_of[c] in fitted), int))
        zeta_new.append(zn)
    return zeta_new, fit_new


def _compressed(fun, jac):
    """(fun, jac) of a tall least-squares problem as the (n+1)-row problem with the same cost, gradient,
    Gauss-Newton matrix and column norms at every point.

    With the QR factorization [J f] = Q R (R upper triangular, (n+1) x (n+1)), f~ = R[:, n] and
    J~ = R[:, :n] give |f~| = |f|, J~^T f~ = J^T f and J~^T J~ = J^T J, all that the trust-region steps of
    ``least_squares(method="trf")`` (and its ``x_scale="jac"``) use: the iterates are those of the full
    problem up to round-off, and each iteration's SVD is of an (n+1) x n matrix instead of the
    (values x n) Jacobian (on a 5-article MIMO ensemble with per-article damping unknowns that SVD was 60 %
    of the refinement's time). Both functions evaluate the Jacobian (a point's f~ needs it); a problem with
    fewer than 4 (n+1) rows is passed through.
    """
    memo = {}

    def at(x):
        x = np.asarray(x, float)
        if memo.get("x") is None or not np.array_equal(memo["x"], x):
            J = np.asarray(jac(x), float)
            f = np.asarray(fun(x), float)
            n = J.shape[1]
            if J.shape[0] < 4 * (n + 1):
                memo.update(x=x.copy(), f=f, J=J)
            else:
                R = np.linalg.qr(np.column_stack([J, f]), mode="r")
                memo.update(x=x.copy(), f=R[:, n].copy(), J=np.ascontiguousarray(R[:, :n]))
        return memo

    return (lambda x: at(x)["f"]), (lambda x, *_: at(x)["J"])


def _hold_weights(obj, x0, hold: float):
    """The ridge weights ``hold * s_max * ||J_j||`` of :func:`refine`'s ``hold`` from the p columns of ``obj``'s
    Jacobian at ``x0`` (``s_max`` the largest singular value of their unit-column form)."""
    J0 = np.vstack([rows[:obj.n_p].T for _, rows in obj.blocks(x0)])
    d = np.linalg.norm(J0, axis=0)
    d = np.where(d > 0, d, 1.0)
    s_max = np.linalg.svd(J0 / d, compute_uv=False)[0]
    return hold * s_max * d


def refine(
    surrogate: Surrogate,
    p_start,
    raw,
    identifications,
    modes,
    lower,
    upper,
    zeta0: float = 0.01,
    floors=None,
    quantity: str = "accelerance",
    mac_min: float = 0.6,
    band_hz=None,
    max_nfev: int = 60,
    xtol: float = 1e-10,
    line_weights=None,
    zeta=None,
    fit_damping: bool = True,
    fit_modes=None,
    hold: float | None = None,
) -> Refinement:
    """Refine an equalized calibration on the raw lines (damping continuation down to the raw data).

    Parameters
    ----------
    surrogate : Surrogate (basis near ``p_start``)
    p_start : (n_p,) start point (the equalized optimum)
    raw : sequence of FitData
        Measured in-band lines of each article, calibration channels.
    identifications : sequence of identification.Identification, one per data set
        (each with ``channels``: pass as (identification, channel_names) pairs).
    modes : sequence of IdentifiedModes, one per data set (damping mapping).
    lower, upper : (n_p,) bounds
    zeta0 : float, the equalization damping; floors are multiples of it.
    floors : sequence of float, optional
        Damping floors as multiples of zeta0, decreasing, ending in 0
        (default :data:`DEFAULT_FLOORS`).
    line_weights : sequence of (n_f,) arrays or None, optional
        Weights of the last (raw) stage per data set, e.g. 1/sigma^2 of the
        log deviation from per-line standard errors; default every line alike.
    zeta : sequence of (r,) arrays, optional
        Per-mode damping at ``p_start`` for each data set (default: mapped
        from ``modes`` by MAC).
    fit_damping : bool
        In the last (raw) stage, estimate the damping of every FE mode in
        the band (+- 5 %) together with p (nuisance unknowns within a factor
        4 of the identified, or median identified, value). The identified
        damping is a noisy estimate; held fixed, its error leaves a
        systematic misfit at every resonance that p would partly absorb. A
        paired mode outside the band keeps its identified damping (see
        :func:`article_damping`).
    fit_modes : sequence of int arrays, optional
        With ``zeta`` given: per data set, the reduced modes (indices at
        ``p_start``) whose damping the last stage estimates (e.g. carried
        with ``zeta`` from an earlier refinement by :func:`carried_damping`).
        Without it a given ``zeta`` is held fixed.
    hold : float, optional
        Hold the directions the data cannot resolve at ``p_start``: a ridge
        ``hold * s_max * ||J_j|| (p_j - p_start_j)`` is added to the residual
        (``J`` the Jacobian in p at the start, ``s_max`` the largest singular
        value of its unit-column form). A parameter combination whose relative
        singular value ``s / s_max`` is well above ``hold`` keeps its fit
        (it moves by ``1 / (1 + (hold s_max / s)^2)`` of its free step), one
        far below stays at the start. For the re-basis stages, whose start is
        already an optimum: without it the raw stage moves the unresolved
        parameters by up to half their range on each new basis (the metric is
        flat there), so the new basis is never adequate at the result.

    Returns
    -------
    Refinement
    """
    from scipy.optimize import least_squares

    raw = list(raw)
    if not (len(raw) == len(identifications) == len(modes)):
        raise CalibrationError("refine: one identification and one mode set per data set")
    floors = tuple(DEFAULT_FLOORS if floors is None else floors)
    if not floors or floors[-1] != 0 or any(b > a for a, b in zip(floors, floors[1:])):
        raise CalibrationError(f"refine: floors must decrease and end in 0, got {floors}")
    p = np.clip(np.asarray(p_start, float), lower, upper)
    p0 = p.copy()  # the damping of each mode is assigned here and tracked from here
    pairs_all, paired = [], []
    if zeta is None:
        zeta = []
        for m in modes:
            z, pairs, idx = article_damping(surrogate, p, m, mac_min, band_hz)
            zeta.append(z)
            pairs_all.append(pairs)
            paired.append(idx)
    elif fit_modes is not None:
        paired = [np.asarray(i, int) for i in fit_modes]
        pairs_all = [article_damping(surrogate, p, m, mac_min, band_hz)[1] for m in modes]  # for the report
    else:
        paired = [np.zeros(0, int) for _ in raw]
    zeta = [np.asarray(z, float) for z in zeta]
    raw_obj = ModalDampingObjective(
        surrogate,
        [d if w is None else replace(d, weights=w) for d, w in zip(raw, line_weights or [None] * len(raw))],
        zeta, p, 0.0, quantity, fit_damping=paired if fit_damping else None)
    plain = ModalDampingObjective(surrogate, [replace(d, weights=None) for d in raw], zeta, p, 0.0, quantity)
    sd_raw_start = plain.sd_unweighted(p)
    stages = []
    with blas_threads(1):  # small dense problems: extra BLAS threads only spin
        for fl in floors:
            t0, c0 = time.perf_counter(), time.process_time()
            zf = fl * zeta0
            if zf > 0:
                data = [replace(debiased_target(d, ident, chans, zf), weights=log_frequency_weights(d.freq_hz))
                        for d, (ident, chans) in zip(raw, identifications)]
                obj = ModalDampingObjective(surrogate, data, zeta, p0, zf, quantity)
            else:
                obj = raw_obj
            last = fl == floors[-1]
            sd0 = obj.sd(p)
            x0, lo, hi = p, lower, upper
            if obj.n_unknowns > obj.n_p:
                z0, zlo, zhi = obj.damping_start()
                x0, lo, hi = np.concatenate([p, z0]), np.concatenate([lower, zlo]), np.concatenate([upper, zhi])
            fun, jac = _compressed_blocks(obj, (_hold_weights(obj, x0, hold), p0) if hold else None)
            res = least_squares(fun, x0, jac=jac, bounds=(lo, hi), method="trf",
                                x_scale="jac", xtol=xtol if last else 1e-6, ftol=1e-12 if last else 1e-6,
                                gtol=1e-12 if last else 1e-6, max_nfev=max_nfev)
            x = np.asarray(res.x)
            if obj.n_unknowns > obj.n_p:
                zeta = obj.damping_at(x)
            stages.append(RefineStage(zf, p.copy(), x[:obj.n_p].copy(), sd0, obj.sd(x) if hold else float(2 * res.cost),
                                      int(res.nfev), time.perf_counter() - t0, str(res.message),
                                      time.process_time() - c0))
            p = x[:obj.n_p].copy()
    plain = ModalDampingObjective(surrogate, [replace(d, weights=None) for d in raw], zeta, p0, 0.0, quantity)
    lam0, _ = reduced_modes(surrogate, p0)
    fe0 = np.sqrt(np.clip(lam0, 0, None)) / (2 * np.pi)
    for pairs, z in zip(pairs_all, zeta):  # report the damping the model ends with
        for q in pairs:
            q["zeta_fitted"] = float(z[int(np.argmin(np.abs(fe0 - q["fe_hz"])))])
    unpaired = []
    for pairs, idx, z, m in zip(pairs_all, paired, zeta, modes):  # in-band FE modes no identified mode pairs with
        taken = {int(np.argmin(np.abs(fe0 - q["fe_hz"]))) for q in pairs}
        start = median_damping(m, 0.01)
        unpaired.append([{"fe_hz": float(fe0[k]), "zeta_start": start, "zeta_fitted": float(z[k])}
                         for k in np.asarray(idx, int).tolist() if k not in taken])
    # only where the raw stage estimated their damping (otherwise they kept the median, as every unpaired mode)
    return Refinement(p=p, sd_raw=plain.sd_unweighted(p), sd_raw_start=sd_raw_start, stages=tuple(stages),
                      damping=tuple(pairs_all), zeta=tuple(zeta), p_zeta=p0,
                      fit_modes=tuple(paired) if fit_damping else tuple(np.zeros(0, int) for _ in raw),
                      unpaired=tuple(unpaired) if pairs_all and fit_damping else ())
