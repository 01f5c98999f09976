"""Screening of candidate effects against the residual of a calibrated model (issue 14).

A candidate effect (a sensor mass, a contact spring, a spring to ground, a
stiffness or mass factor on a few elements, ...) enters the parametric model
as one new term with a normalized magnitude c (c = 0: the model as it is).
What this module needs of a candidate is the derivative of the full-order
stiffness and mass with respect to c at the calibrated point,
:class:`CandidateTerm` (dK, dM; local sparse matrices).

Linear screening (:func:`screen`)
---------------------------------
On the equalized (smooth) metric of :class:`calibration.Objective`, with the
real stacked residual r (2N,) at the calibrated p (re-fitted first on the
same data), the Jacobian J_p of the existing parameters and the candidate's
first-order sensitivity j_c = dr/dc at c = 0, the score of a candidate is the
fraction of the residual it explains *beyond what the existing parameters
re-fitted with it explain*: with P the orthogonal projection on range(J_p)
(the residual is already weighted as the objective weights it),

    r' = (I - P) r,   j' = (I - P) j_c,
    c* = -(j'.r') / |j'|^2 clipped to [lower, upper],
    explained = (-2 c* j'.r' - c*^2 |j'|^2) / |r|^2,

the decrease of the linearized square deviation when c and p move together
(for an unclipped c*: (j'.r')^2 / (|j'|^2 |r|^2)). A spring or mass whose
best c* is negative is clipped to 0 and explains nothing.

j_c is exact to first order and costs no full-size work: the reduced model
on the basis T (modes and the static corrections of the drives and sensors)
represents the drive responses U = T x and the adjoint sensor responses, so
dH/dc = -Y^T (dK - w^2 dM) U needs only the rows of T at the few DOF the
candidate touches: in the reduced modes X at p, with Phi_c = T[rows] X,

    A_c = Phi_c^T dK_loc Phi_c,  B_c = Phi_c^T dM_loc Phi_c  (m x m),

and the exact derivative of the modally damped reduced FRF (Nelson's
expansion of :mod:`calibration._modal_derivative`, as for the parameters,
damping following the modes) for these A_c, B_c. Candidates are processed in chunks whose scratch arrays stay
below ``chunk_bytes``.

Nonlinear check
---------------
An effect that moves modes by several half-power bandwidths makes the
log-ratio metric strongly nonlinear in c. The top ``n_check`` candidates are
therefore re-fitted: the surrogate is extended by the static corrections of
the candidate's loads (:func:`extend_with_candidates`, through
:func:`calibration.extended_surrogate`) and [p, c] is minimized from
[p, c*] (optionally through damping-continuation stages), giving the SD
after the fit and the explained fraction 1 - SD_new / SD_baseline.

Significance
------------
For a residual that is white noise, (j'.r')^2 / |j'|^2 is |r'|^2 / (n - k)
times a chi-square variable with one degree of freedom (n real residuals, k
the rank of J_p); a random direction explains |r'|^2 / ((n - k) |r|^2) on
average. A candidate is *significant* when its explained fraction exceeds
that times the chi-square quantile at ``alpha / (n_candidates n_stages)``
(Bonferroni over the candidates and the damping stages). A residual that is
model error, not noise, is correlated over lines, and so is the error of an
equalized target resynthesized from identified modes: then the test says
only that the candidate explains more than white noise would, and the
decision belongs to acceptance (:func:`accept`: hold-out and
cross-validation beyond their scatter, the noise floor).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.sparse as sp

from calibration._errors import CalibrationError
from calibration._extend import extended_surrogate
from calibration._fit import Objective, StartOutcome, check_bounds, run_start
from calibration._modal_derivative import eigen_derivatives
from calibration._threads import blas_threads
from calibration._surrogate import (
    FRFModel,
    Surrogate,
    _factor,
    _local_terms,
    _shifted,
    reduced_modes,
)


@dataclass(frozen=True)
class CandidateTerm:
    """What the screening kernels need of one candidate effect.

    Parameters
    ----------
    name : str
        Candidate name (the name of its model term).
    dK, dM : (n, n) sparse or None
        dK/dc and dM/dc at the calibrated point on the model's independent
        DOF (N/m and kg per unit c), c the candidate's normalized magnitude
        (the p of its term; c = 0 is the model without it). At least one.
    lower, upper : float
        Bounds on c (>= 0 for springs and masses; factor terms may be
        negative; > -1 in any case).
    """

    name: str
    dK: object
    dM: object
    lower: float
    upper: float
    rows: np.ndarray = field(init=False, repr=False, compare=False)
    local: tuple = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        mats = {}
        for kind, A in (("dK", self.dK), ("dM", self.dM)):
            if A is None:
                continue
            A = sp.csr_matrix(A, dtype=float)
            if A.shape[0] != A.shape[1]:
                raise CalibrationError(f"candidate {self.name!r}: {kind} is {A.shape}, not square")
            if np.any(A.data == 0):  # a copy first: never touch the caller's arrays (a shared pattern)
                A = A.copy()
                A.eliminate_zeros()
            mats[kind] = A
        if not mats or all(A.nnz == 0 for A in mats.values()):
            raise CalibrationError(f"candidate {self.name!r}: neither dK nor dM has a non-zero entry")
        shapes = {A.shape for A in mats.values()}
        if len(shapes) > 1:
            raise CalibrationError(f"candidate {self.name!r}: dK and dM shapes differ {sorted(shapes)}")
        lo, hi = float(self.lower), float(self.upper)
        if not (np.isfinite(lo) and np.isfinite(hi) and -1.0 < lo < hi):
            raise CalibrationError(f"candidate {self.name!r}: bounds need -1 < lower < upper, got [{lo}, {hi}]")
        # the rows and columns the candidate touches, and its matrices on them, from the non-zeros alone: a
        # candidate is a few entries of an n-row matrix, and every pass over its n + 1 row pointers costs
        # 0.2-0.7 ms at 200,000 DOF (1,300 candidates: 1-2 s of a diagnosis's term derivatives before)
        coo = {k: (np.searchsorted(A.indptr, np.arange(A.nnz), side="right") - 1, A.indices, A.data)
               for k, A in mats.items()}
        rows = np.unique(np.concatenate([np.concatenate([r, c]) for r, c, _ in coo.values()]))
        local = tuple(None if kind not in coo else sp.csr_matrix(
            (coo[kind][2], (np.searchsorted(rows, coo[kind][0]), np.searchsorted(rows, coo[kind][1]))),
            shape=(rows.size, rows.size)) for kind in ("dK", "dM"))
        object.__setattr__(self, "dK", mats.get("dK"))
        object.__setattr__(self, "dM", mats.get("dM"))
        object.__setattr__(self, "lower", lo)
        object.__setattr__(self, "upper", hi)
        object.__setattr__(self, "rows", rows)
        object.__setattr__(self, "local", local)

    @property
    def size(self) -> int:
        return int(self.rows.size)


def _bytes_per_candidate(m: int, n_oi: int, n_res: int) -> int:
    """Scratch bytes of one candidate in :func:`_candidate_block`: its A, B, G (m x m), its columns of the
    derivative factor (3m x n_oi per data set), the real and imaginary derivative values and their weighted
    rows (:func:`calibration._modal_derivative.derivative_rows`) and its column of the stacked Jacobian and
    of its projection, each of n_res = 2N reals."""
    return 24 * m * m + 24 * m * n_oi + 40 * n_res


class _Modal:
    """The reduced modal quantities at p that every candidate's derivative shares."""

    def __init__(self, sur: Surrogate, basis: np.ndarray, p, data, zeta: float, quantity: str):
        self.obj = Objective(sur, data, zeta, quantity)
        lam, X = reduced_modes(sur, p)
        self.lam, self.X = lam, X
        self.m = X.shape[1]
        self.zeta = np.full(self.m, float(zeta))
        self.rigid_hz = sur.rigid_hz
        self.n_values = self.obj.n_values
        self.n_oi = sum(d.frf.shape[1] * d.frf.shape[2] for d in self.obj.data)


def _modal_matrices(modal: _Modal, basis: np.ndarray, cands) -> tuple[np.ndarray, np.ndarray]:
    """A_c, B_c = (T[rows] X)^T dK_loc, dM_loc (T[rows] X) for every candidate: (n_c, m, m) each."""
    m = modal.m
    A = np.zeros((len(cands), m, m))
    Bm = np.zeros((len(cands), m, m))
    for k, c in enumerate(cands):
        Phi = basis[c.rows] @ modal.X  # (rows, m)
        dK, dM = c.local
        if dK is not None:
            A[k] = Phi.T @ (dK @ Phi)
        if dM is not None:
            Bm[k] = Phi.T @ (dM @ Phi)
    return A, Bm


def _candidate_block(modal: _Modal, basis: np.ndarray, cands) -> np.ndarray:
    """Real stacked Jacobian d r / d c of the objective's residual for a chunk of candidates: (2N, n_c).

    The candidates' magnitudes are derivative directions like the parameters'
    (:mod:`calibration._modal_derivative`, damping ratios held), built on the
    objective's line slices and threads (:class:`calibration._modal_derivative.FRFRows`)."""
    A, Bm = _modal_matrices(modal, basis, cands)
    D, G = eigen_derivatives(modal.lam, A, Bm, modal.rigid_hz)
    frows = modal.obj._frows
    facs = [frows.factors(a, modal.lam, modal.X, modal.zeta, D, G) for a in range(len(modal.obj.data))]
    per_set = frows.all_rows(lambda a, lines: frows.rows(a, facs[a], lines))
    n_c = len(cands)
    return frows.assembled(per_set, [np.arange(n_c)] * len(per_set), n_c)[1]


def _chunks(modal: _Modal, n_c: int, chunk_bytes: float) -> int:
    per = _bytes_per_candidate(modal.m, modal.n_oi, 2 * modal.n_values)
    return int(max(1, min(n_c, chunk_bytes // per)))


def candidate_jacobian(sur: Surrogate, basis, p, data, zeta: float, candidates, *, quantity: str = "accelerance",
                       chunk_bytes: float = 2.5e8) -> np.ndarray:
    """First-order sensitivity of the objective's residual to every candidate at c = 0.

    Parameters
    ----------
    sur : Surrogate
        The calibrated model's surrogate.
    basis : (n, r) ndarray
        Its basis T (as returned by :func:`calibration.build_surrogate`).
    p : (n_p,) normalized parameters of the existing model.
    data : sequence of FitData
        Equalized test FRFs (as :class:`calibration.Objective` takes them).
    zeta : float
        Uniform model damping (= the equalization damping of ``data``).
    candidates : sequence of CandidateTerm
    quantity : str
        FRF quantity of the data.
    chunk_bytes : float
        Scratch memory bound of one chunk of candidates (bytes).

    Returns
    -------
    (2N, n_c) ndarray
        d r / d c_k, r the real stacked weighted residual of
        :meth:`calibration.Objective.evaluate` (same rows).
    """
    cands = _checked(candidates, basis, sur)
    modal = _Modal(sur, basis, np.asarray(p, float), data, zeta, quantity)
    step = _chunks(modal, len(cands), chunk_bytes)
    return np.hstack([_candidate_block(modal, basis, cands[i:i + step]) for i in range(0, len(cands), step)])


def _checked(candidates, basis, sur) -> list:
    cands = list(candidates)
    if not cands:
        raise CalibrationError("screening needs at least one candidate")
    basis = np.asarray(basis)
    if basis.ndim != 2 or basis.shape[1] != sur.size:
        raise CalibrationError(f"basis is {basis.shape}, expected (n, {sur.size}) for this surrogate")
    names = [c.name for c in cands]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise CalibrationError(f"candidate names repeated: {dup}")
    for c in cands:
        if not isinstance(c, CandidateTerm):
            raise CalibrationError(f"candidates must be CandidateTerm, got {type(c).__name__}")
        n = (c.dK if c.dK is not None else c.dM).shape[0]
        if n != basis.shape[0]:
            raise CalibrationError(f"candidate {c.name!r} acts on {n} DOF, the basis has {basis.shape[0]}")
    return cands


# ----------------------------------------------------------------------------- extension by candidates

#: Relative singular-value cut of a candidate's loads (``dK T``, ``dM T``) in its extension: the static
#: corrections of the weaker load directions change the reduced FRF below any noise. Measured on the
#: 200,000-DOF example subframe (docs/diagnosis.md, "Extension size"): for its 390-pair gap at 10 and 100x
#: the true contact rate, a cut of 1e-4 keeps 23 of 58 new vectors (time 4 -> 2 s), the in-band frequencies
#: within 1e-5 of the full-order model's and the reduced FRF within a square log deviation of 1e-7 of the
#: 1e-8 cut's (the data's floor there: 2e-4). The final answer of a diagnosis is refined on the exact
#: extended deck with its own basis (``refine_cycles``), not on this extension.
CANDIDATE_LOAD_RTOL = 1e-4


def _with_linear_terms(A, new_mats: list, n_new: int):
    """An ExtendedAffineMatrix: the terms of ``A`` (any affine kind) then ``c_j * D_j`` for (D_j, j) in new_mats."""
    from femodel import ExtendedAffineMatrix

    t = len(A.matrices)
    a = np.zeros((t + len(new_mats), n_new))
    a[:t, :A.n_params] = A.exponents
    b = a.copy()
    series = getattr(A, "series_exponents", None)
    ratio = np.zeros(t + len(new_mats))
    if series is not None:
        b[:t, :A.n_params] = series
        ratio[:t] = np.asarray(A.series_ratio, float)
    lin = -np.ones(t + len(new_mats), dtype=np.int64)
    old_lin = getattr(A, "linear", None)
    if old_lin is not None:
        lin[:t] = np.asarray(old_lin, dtype=np.int64)
    for k, (_, j) in enumerate(new_mats):
        lin[t + k] = j
    mats = tuple(A.matrices) + tuple(D for D, _ in new_mats)
    out = ExtendedAffineMatrix(mats, a, b, ratio, lin)
    # the per-term row tables of the old terms are the base's (computed once, shared by every extension)
    extra = ExtendedAffineMatrix(tuple(D for D, _ in new_mats), a[t:], b[t:], ratio[t:], lin[t:]) if new_mats else None
    out.cache["calibration.local_rows"] = list(_local_terms(A)) + (list(_local_terms(extra)) if extra else [])
    return out


class _LinearExtension:
    """Fast K(p), M(p) and derivatives of :func:`extended_model` (the ``parametric`` of its FRFModel).

    The existing part comes from the base model (its shared-pattern assembly
    when it has one); the candidates add ``c_j dK_j``, ``c_j dM_j``.
    """

    def __init__(self, base: FRFModel, newK: list, newM: list):
        self.base, self.n_old = base, base.n_params
        self.newK, self.newM = newK, newM

    def _add(self, A, new, p):
        for D, j in new:
            if p[j] != 0.0:
                A = A + p[j] * D
        return A

    def stiffness(self, p):
        p = np.asarray(p, float)
        return sp.csr_matrix(self._add(self.base.stiffness(p[:self.n_old]), self.newK, p))

    def mass(self, p):
        p = np.asarray(p, float)
        return sp.csr_matrix(self._add(self.base.mass(p[:self.n_old]), self.newM, p))

    def _d(self, p, j, new, old):
        if j < self.n_old:
            return old(np.asarray(p, float)[:self.n_old], j)
        for D, k in new:
            if k == j:
                return D
        n = self.base.K.shape[0]
        return sp.csr_matrix((n, n))

    def dK(self, p, j):
        return self._d(p, j, self.newK, self.base.dK)

    def dM(self, p, j):
        return self._d(p, j, self.newM, self.base.dM)


def extended_model(model: FRFModel, candidates) -> FRFModel:
    """The model with every candidate as a term ``c dK`` / ``c dM`` linear in a new parameter c.

    The derivative matrices are the candidates' at the calibrated point, so
    this is the first-order form of the candidate terms in c with the
    existing parameters' dependence of the term (e.g. of an element-subset
    factor on E) frozen there; :meth:`femodel.ParametricModel.with_terms`
    gives the exact one.
    """
    cands = list(candidates)
    n_old = model.n_params
    n_new = n_old + len(cands)
    newK = [(c.dK, n_old + k) for k, c in enumerate(cands) if c.dK is not None]
    newM = [(c.dM, n_old + k) for k, c in enumerate(cands) if c.dM is not None]
    return FRFModel(
        _with_linear_terms(model.K, newK, n_new),
        _with_linear_terms(model.M, newM, n_new),
        model.inputs,
        model.outputs,
        input_names=model.input_names,
        output_names=model.output_names,
        parameter_names=tuple(model.parameter_names) + tuple(c.name for c in cands),
        parametric=_LinearExtension(model, newK, newM),
    )


def shifted_solver(model: FRFModel, p, shift_hz: float):
    """``solve(F) = (K(p) + s M(p))^-1 F``, s = (2 pi shift_hz)^2: one factorization to share between extensions.

    The model keeps its last factorization (``factor_cache["last_solve"]``, as :func:`calibration.build_surrogate`
    leaves it): at the same point and shift it is returned, not formed again (2-3 s at 200,000 DOF)."""
    if not shift_hz > 0:
        raise CalibrationError(f"shift_hz must be > 0, got {shift_hz}")
    s = (2 * np.pi * float(shift_hz)) ** 2
    p = np.asarray(p, float)
    kept = model.factor_cache.get("last_solve")
    if kept is not None and kept[1] == s and np.array_equal(kept[0], p):
        return kept[2]
    model.factor_cache.pop("last_solve", None)  # the previous point's factor: freed before the new one is made
    solve = _factor(_shifted(model.stiffness(p), model.mass(p), s, model.factor_cache), model.factor_cache)
    model.factor_cache["last_solve"] = (p.copy(), s, solve)
    return solve


def extend_with_candidates(sur: Surrogate, basis, model, candidates, *, shift_hz: float | None = None,
                           solve=None, with_basis: bool = True,
                           load_rtol: float = CANDIDATE_LOAD_RTOL) -> tuple[Surrogate, np.ndarray]:
    """Extend a surrogate by candidate terms (the static corrections of their loads), for a re-fit of [p, c].

    Parameters
    ----------
    sur : Surrogate
    basis : (n, r) ndarray, its basis
    model : FRFModel
        Either the model of ``sur`` (the candidates enter through
        :func:`extended_model`, linear in c with their derivatives at the
        calibrated point) or an already extended model whose last
        ``len(candidates)`` parameters are the candidates (e.g. from
        :meth:`femodel.ParametricModel.with_terms`: exact in c and p).
    candidates : sequence of CandidateTerm
    shift_hz, solve
        As :func:`calibration.extended_surrogate` (``solve`` at ``sur.p_basis``,
        e.g. from :func:`shifted_solver`, is shared between calls).
    with_basis : bool
        False: None in place of the basis (:func:`calibration.extended_surrogate`).
    load_rtol : float
        Relative singular-value cut of each candidate's loads (:data:`CANDIDATE_LOAD_RTOL`).

    Returns
    -------
    (Surrogate, (n, r + k) ndarray)
        The extended surrogate (parameters: the existing ones, then one per
        candidate) and its basis.
    """
    cands = list(candidates)
    if model.n_params == sur.n_params:
        if solve is None and shift_hz is not None and shift_hz > 0:
            # K + s M of the base model at the basis point (the new magnitudes are 0 there): its factorization
            # is cached on the model and shared by every extension, not formed again for each
            solve = shifted_solver(model, sur.p_basis, shift_hz)
        model = extended_model(model, cands)
    elif model.n_params != sur.n_params + len(cands):
        raise CalibrationError(f"model has {model.n_params} parameters: expected the surrogate's {sur.n_params} "
                               f"or {sur.n_params + len(cands)} with the {len(cands)} candidates")
    return extended_surrogate(sur, basis, model, shift_hz=shift_hz, solve=solve, with_basis=with_basis,
                              load_rtol=load_rtol)


# ----------------------------------------------------------------------------- screening


@dataclass(frozen=True)
class CandidateCheck:
    """Nonlinear re-fit of [p, c] with one candidate on its extended surrogate.

    Attributes
    ----------
    name : str
    index : int, position in the screened candidates
    c : float, fitted normalized magnitude
    p : (n_p,) re-fitted existing parameters
    sd : float, square deviation after the fit (same data as the baseline)
    explained : float, 1 - sd / sd_baseline
    converged : bool, the fit's last stage stopped on its tolerances (not on its evaluation budget),
        after ``continued`` further rounds of the budget on the last stage
    time_s : float, extension and fit
    explained_linear : float, the candidate's linear (first-order) explained fraction
    continued : int, further rounds of the last stage run because the fit had not converged
    surrogate : Surrogate or None, the extended surrogate the check fitted on (kept in this process so that
        :func:`fit_with` going on from the check does not build it again; not in :meth:`to_dict`)
    """

    name: str
    index: int
    c: float
    p: np.ndarray
    sd: float
    explained: float
    converged: bool
    time_s: float
    explained_linear: float = 0.0
    continued: int = 0
    surrogate: Surrogate | None = field(default=None, repr=False, compare=False)

    @property
    def score(self) -> float:
        """The ranking score: the nonlinear explained fraction of a converged fit; of a fit that stopped on
        its budget, the larger of that fraction (a lower bound: the fit had not reached its minimum) and the
        linear one (the first-order estimate at c = 0)."""
        return self.explained if self.converged else max(self.explained, self.explained_linear)

    def to_dict(self) -> dict:
        return {"name": self.name, "index": self.index, "c": self.c, "p": self.p.tolist(), "sd": self.sd,
                "explained": self.explained, "converged": self.converged, "time_s": self.time_s,
                "explained_linear": self.explained_linear, "continued": self.continued, "score": self.score}


@dataclass(frozen=True)
class Screening:
    """Outcome of :func:`screen`.

    Attributes
    ----------
    names : tuple of str, the candidates in input order
    stage_zeta : (n_s,) damping of the screening stages (continuation stages, then the final one)
    stage_explained : (n_s, n_c) linear explained fraction of every stage's residual
    stage_sd : (n_s,) baseline SD of every stage (existing parameters re-fitted)
    explained : (n_c,) the candidate's best linear explained fraction over the stages
    c_linear : (n_c,) linearized magnitude c* (clipped to the bounds) at that stage
    significant : (n_c,) bool, explained above the noise threshold at some stage
    noise_explained : (n_s,) expected explained fraction of a random direction if the residual were white noise
    threshold : (n_s,) significance thresholds on the stages' explained fractions
    checks : tuple of CandidateCheck, the nonlinear re-fits of the top candidates (best first)
    order : (n_c,) int
        Ranking: the checked candidates by their score
        (:attr:`CandidateCheck.score`: the nonlinear explained fraction of
        a converged check, the larger of it and the linear one for a check
        that stopped on its budget), then the others by the linear one.
    p_start : (n_p,) the given p ; sd_start : float, SD there (final data)
    p_baseline : (n_p,) p re-fitted alone on the final data ; sd_baseline : float, SD there
    n_residuals : int, real residuals of the final stage (2 x compared complex values)
    rank_p : int, numerical rank of the existing parameters' Jacobian
    timings_s : dict, wall time of the steps (and process CPU time, "cpu: ..."; both include BLAS threads)
    zoomed : tuple of str, the candidates added by the zoom (at the end of ``names``; included above)
    """

    names: tuple
    stage_zeta: np.ndarray
    stage_explained: np.ndarray
    stage_sd: np.ndarray
    explained: np.ndarray
    c_linear: np.ndarray
    significant: np.ndarray
    noise_explained: np.ndarray
    threshold: np.ndarray
    checks: tuple
    order: np.ndarray
    p_start: np.ndarray
    sd_start: float
    p_baseline: np.ndarray
    sd_baseline: float
    n_residuals: int
    rank_p: int
    timings_s: dict
    zoomed: tuple = ()

    @property
    def best(self) -> str:
        """Name of the top-ranked candidate."""
        return self.names[int(self.order[0])]

    def check(self, name: str) -> CandidateCheck | None:
        """The nonlinear check of a candidate, None if it was not checked."""
        for c in self.checks:
            if c.name == name:
                return c
        return None

    def to_dict(self) -> dict:
        return {
            "candidates": [{"name": n, "explained": float(e), "c_linear": float(c), "significant": bool(s),
                            "stage_explained": self.stage_explained[:, i].tolist()}
                           for i, (n, e, c, s) in enumerate(zip(self.names, self.explained, self.c_linear,
                                                                self.significant))],
            "ranking": [self.names[i] for i in self.order],
            "checks": [c.to_dict() for c in self.checks],
            "stage_zeta": self.stage_zeta.tolist(),
            "stage_sd": self.stage_sd.tolist(),
            "noise_explained": self.noise_explained.tolist(),
            "threshold": self.threshold.tolist(),
            "sd_start": self.sd_start,
            "sd_baseline": self.sd_baseline,
            "p_baseline": self.p_baseline.tolist(),
            "n_residuals": self.n_residuals,
            "rank_p": self.rank_p,
            "timings_s": dict(self.timings_s),
            "zoomed": list(self.zoomed),
        }


def _fit(objs, x0, lower, upper, max_nfev: int, xtol: float = 1e-8) -> StartOutcome:
    return run_start((list(objs), x0, lower, upper, max_nfev, xtol))


@dataclass(frozen=True)
class _Linear:
    """Linear scores of one screening stage."""

    p: np.ndarray
    sd: float
    explained: np.ndarray
    c: np.ndarray
    noise: float
    n_res: int
    rank: int


class _LinearStage:
    """One screening stage at its baseline (p0, zeta): the residual, the existing parameters' range and the
    reduced modes, kept so that candidates added later (the zoom) are scored on the same footing."""

    def __init__(self, sur, basis, p0, sd0, data, zeta, quantity, chunk_bytes):
        obj = Objective(sur, data, zeta, quantity)
        r, Jp = obj.evaluate(p0)
        self.rr = float(r @ r)
        U, s, _ = np.linalg.svd(Jp / np.maximum(np.linalg.norm(Jp, axis=0), np.finfo(float).tiny)[None, :],
                                full_matrices=False)
        self.rank = int(np.sum(s > 1e-10 * s[0])) if s.size and s[0] > 0 else 0
        self.Q = U[:, :self.rank]
        self.r_perp = r - self.Q @ (self.Q.T @ r)
        self.modal = _Modal(sur, basis, p0, data, zeta, quantity)
        self.basis, self.chunk_bytes = basis, chunk_bytes
        self.p, self.sd, self.n_res = p0, sd0, int(r.size)
        dof = max(r.size - self.rank, 1)
        self.noise = float(self.r_perp @ self.r_perp) / dof / self.rr if self.rr > 0 else 0.0

    def score(self, cands) -> tuple[np.ndarray, np.ndarray]:
        """(explained fractions, linearized magnitudes clipped to the bounds) of ``cands``."""
        step = _chunks(self.modal, len(cands), self.chunk_bytes)
        dot = np.zeros(len(cands))
        nn = np.zeros(len(cands))
        Q = self.Q
        for i in range(0, len(cands), step):
            J = _candidate_block(self.modal, self.basis, cands[i:i + step])
            J -= Q @ (Q.T @ J)
            dot[i:i + step] = J.T @ self.r_perp
            nn[i:i + step] = np.einsum("ij,ij->j", J, J)
        lo = np.array([c.lower for c in cands])
        hi = np.array([c.upper for c in cands])
        with np.errstate(divide="ignore", invalid="ignore"):
            c_star = np.where(nn > 0, -dot / np.where(nn > 0, nn, 1.0), 0.0)
        c_lin = np.clip(c_star, lo, hi)
        gain = -2 * c_lin * dot - c_lin**2 * nn
        tiny = np.finfo(float).tiny
        explained = np.clip(gain, 0.0, None) / max(self.rr, tiny) if self.rr > 0 else np.zeros(len(cands))
        return explained, c_lin


def _linear_stage(sur, basis, p0, sd0, data, zeta, quantity, cands, chunk_bytes) -> tuple[_Linear, _LinearStage]:
    """Explained fractions and linearized magnitudes of every candidate at (p0, zeta) on ``data``."""
    st = _LinearStage(sur, basis, p0, sd0, data, zeta, quantity, chunk_bytes)
    explained, c_lin = st.score(cands)
    return _Linear(p0, sd0, explained, c_lin, st.noise, st.n_res, st.rank), st


def screen(
    sur: Surrogate,
    basis,
    p,
    data,
    zeta: float,
    candidates,
    lower,
    upper,
    *,
    quantity: str = "accelerance",
    model: FRFModel | None = None,
    n_check: int = 10,
    shift_hz: float | None = None,
    solve=None,
    continuation=(),
    refit: bool = True,
    max_nfev: int = 40,
    alpha: float = 0.01,
    chunk_bytes: float = 2.5e8,
    executor=None,
    continue_checks: int = 1,
    groups=None,
    zoom=None,
    zoom_rounds: int = 3,
    regions=None,
) -> Screening:
    """Rank candidate effects by the fraction of the residual they explain beyond the existing parameters.

    Parameters
    ----------
    sur : Surrogate
        Surrogate of the calibrated model (exact derivatives in p).
    basis : (n, r) ndarray
        Its basis T.
    p : (n_p,) calibrated normalized parameters.
    data : sequence of FitData
        Equalized test FRFs at damping ``zeta`` (the smooth metric).
    zeta : float
        Model damping = equalization damping of ``data``.
    candidates : sequence of CandidateTerm
    lower, upper : (n_p,) bounds of the existing parameters.
    quantity : str
        FRF quantity of the data.
    model : FRFModel, optional
        The full-order model of ``sur``; needed for the nonlinear check
        (``n_check`` > 0): the candidates' static corrections.
    n_check : int
        Candidates (best linear scores, explained > 0) re-fitted nonlinearly.
    shift_hz, solve
        Shift of the static solves (the basis build's) or a solver of
        K + s M at ``sur.p_basis`` (see :func:`shifted_solver`); one is needed
        for the nonlinear check.
    continuation : sequence of (zeta, data)
        Damping-continuation stages (wider damping first, data equalized at
        that damping), as :func:`calibration.calibrate` takes them. Every
        stage is screened linearly (its own baseline re-fit, started from the
        previous stage's); a candidate scores its best stage. An effect that
        moves modes by more than a half-power bandwidth at ``zeta`` (where
        the log-ratio metric is far from linear in c) is found at a wider
        damping. The nonlinear re-fits run through the stages.
    refit : bool
        Re-fit p alone on every stage's data first (from ``p``) so the
        baseline is the existing parameters' own optimum on that data.
    max_nfev : int
        Residual evaluations per fit stage.
    alpha : float
        Family-wise false-alarm probability of the significance test
        (Bonferroni over candidates and stages).
    chunk_bytes : float
        Memory bound of the scratch arrays of one chunk of candidates (bytes);
        the chunk holds about ``16 n_f n_in (3 r + 5 n_out) + 48 r^2 + 32 N`` bytes
        per candidate (r basis size, N compared values).
    executor : optional
        Runs the nonlinear re-fits (:func:`calibration.run_start`, one per
        checked candidate) in parallel, as the multi-start does
        (:func:`calibration.make_executor`); the extensions are built here,
        the fits are independent. None: one after the other in this process.
        The outcome does not depend on it.
    continue_checks : int
        A nonlinear check whose last stage stopped on its evaluation budget
        (``max_nfev``) is continued on the last stage from where it stopped,
        up to this many further rounds of the budget. A check still not
        converged is ranked by :attr:`CandidateCheck.score` (its stalled
        fraction is a lower bound of what the candidate explains; the
        linear fraction is the first-order estimate).
    groups : sequence, optional
        A label per candidate (e.g. its family). Besides the ``n_check``
        best overall, the best linear candidate of every group (explained
        > 0) is re-fitted nonlinearly: the first-order score errs
        differently per kind of effect (a common mass that the existing
        parameters largely absorb scores half its re-fitted fraction),
        and a family of hundreds of near-duplicates must not crowd the
        others out of the checks. None: the ``n_check`` best only.
    zoom : callable, optional
        ``zoom(names, explained) -> sequence of (CandidateTerm, group label, parent name)``:
        after the linear stages, called with the names of the candidates
        screened so far and their linear explained fractions; the new
        candidates it returns (e.g. a point family's candidates at the grids
        near its best ones, :func:`femodel.zoom_candidates`) are scored on
        every stage at the same baselines and join the ranking, the
        significance test and the nonlinear checks as any other candidate.
        Called again with the grown list until it returns nothing or
        ``zoom_rounds`` times. The label is the new candidate's group (ignored
        without ``groups``), the parent the screened candidate it refines: a
        zoom chain (a candidate and all zoomed from it, transitively) is one
        place, and only its best takes one of the nonlinear checks.
    zoom_rounds : int
        At most this many calls of ``zoom``.
    regions : sequence, optional
        Per candidate None or ``(label, places)``: candidates with one label
        are alternatives of one region (e.g. a contact gap's cells, the
        windows straddling their boundaries and the unions of them), each
        acting on the set ``places`` (e.g. its grids). A region takes one of
        the ``n_check`` slots, as a zoom chain does (its best linear
        member), and when it does, its alternatives that the linear score
        cannot rank against that member are checked with it, outside the
        budget: of the members whose places strictly enclose the best's, the
        two largest (the unions around it) and the best linear other, and
        the best linear member partly overlapping it (neither inside nor
        around it); at most 4 per region. Overlapping near-duplicates then cannot
        crowd the rest out of the checks, and a union whose linear score
        trails its parts (a whole closed gap: the first-order score of a
        large change errs most) still gets the nonlinear check that ranks
        it. Zoomed candidates are regions of their own.

    Returns
    -------
    Screening

    Raises
    ------
    CalibrationError
        No candidates, a candidate of the wrong size or repeated names,
        bounds that do not match, or a nonlinear check without ``model``
        or without ``shift_hz``/``solve``.
    """
    from scipy.stats import chi2

    t0, c0 = time.perf_counter(), time.process_time()
    basis = np.asarray(basis, float)
    cands = _checked(candidates, basis, sur)
    lower, upper = check_bounds(lower, upper, sur.n_params)
    p_in = np.clip(np.asarray(p, float), lower, upper)
    n_check = int(min(max(n_check, 0), len(cands)))
    if n_check and model is None:
        raise CalibrationError("screen: the nonlinear check (n_check > 0) needs the full-order model")
    if n_check and solve is None and not (shift_hz is not None and shift_hz > 0):
        raise CalibrationError("screen: the nonlinear check needs shift_hz > 0 (the basis build's) or solve")
    stages = [(float(z), list(d)) for z, d in continuation] + [(float(zeta), list(data))]
    sd_start = Objective(sur, stages[-1][1], zeta, quantity).sd(p_in)
    labels = None if groups is None else list(groups)
    if labels is not None and len(labels) != len(cands):
        raise CalibrationError(f"screen: {len(labels)} group labels for {len(cands)} candidates")
    n_first = len(cands)
    if regions is not None:
        regions = list(regions)
        if len(regions) != n_first:
            raise CalibrationError(f"screen: {len(regions)} regions for {n_first} candidates")
        for k, g in enumerate(regions):
            if g is not None and not (isinstance(g, (tuple, list)) and len(g) == 2):
                raise CalibrationError(f"screen: the region of candidate {cands[k].name!r} must be None or "
                                       f"(label, places), got {g!r}")
    lin, prepared = [], []
    t_fit = t_lin = 0.0
    p_s = p_in
    for z, d in stages:
        ta = time.perf_counter()
        obj = Objective(sur, d, z, quantity)
        if refit:
            out = _fit([obj], p_s, lower, upper, max_nfev)
            p_s, sd_s = out.p, out.sd
        else:
            sd_s = obj.sd(p_s)
        tb = time.perf_counter()
        lx, st = _linear_stage(sur, basis, p_s, sd_s, d, z, quantity, cands, chunk_bytes)
        lin.append(lx)
        prepared.append(st)
        t_fit += tb - ta
        t_lin += time.perf_counter() - tb
    E = np.array([x.explained for x in lin])  # (n_s, n_c)
    C = np.array([x.c for x in lin])
    tz, cz = time.perf_counter(), time.process_time()
    zoomed, parent = [], {}  # parent: zoomed candidate's index -> the name it was zoomed from
    if zoom is not None:
        names = {c.name for c in cands}
        for _ in range(max(int(zoom_rounds), 0)):
            got = list(zoom(tuple(c.name for c in cands), E.max(axis=0)) or ())
            if not got:
                break
            got = [tuple(g) for g in got]
            if any(len(g) != 3 for g in got):
                raise CalibrationError("screen: zoom must return (CandidateTerm, group label, parent name) tuples")
            new = [t for t, _, _ in got]
            for t in new:
                if not isinstance(t, CandidateTerm):
                    raise CalibrationError(f"screen: zoom returned {type(t).__name__}, not CandidateTerm")
            new = _checked(new, basis, sur)
            again = sorted({t.name for t in new} & names)
            if again:
                raise CalibrationError(f"screen: zoom returned candidates screened already: {again[:5]}")
            bad = sorted({par for _, _, par in got if par not in names})
            if bad:
                raise CalibrationError(f"screen: zoom names parents that were not screened: {bad[:5]}")
            for k, (_, _, par) in enumerate(got):
                parent[len(cands) + k] = par
            names |= {t.name for t in new}
            scores = [st.score(new) for st in prepared]
            E = np.hstack([E, np.array([e for e, _ in scores])])
            C = np.hstack([C, np.array([c for _, c in scores])])
            cands += new
            zoomed += [t.name for t in new]
            if labels is not None:
                labels += [lab for _, lab, _ in got]
    t2, c2 = time.perf_counter(), time.process_time()
    best_stage = np.argmax(E, axis=0)
    explained = E[best_stage, np.arange(len(cands))]
    c_lin = C[best_stage, np.arange(len(cands))]
    q = float(chi2.isf(alpha / (len(cands) * len(stages)), 1))
    noise = np.array([x.noise for x in lin])
    threshold = noise * q
    significant = np.any(E > threshold[:, None], axis=0)

    checks = []
    by_score = np.argsort(-explained, kind="stable")
    # a zoom chain (a sampled candidate and every candidate zoomed from it or its descendants) is one place
    # refined: only its best takes a check, so near-duplicates of one region do not crowd the others out
    root = {k: k for k in range(len(cands))}
    # the alternatives of one region are one place too (see ``regions``): their first member is the root
    members = _regions(regions, n_first, root)
    pos = {c.name: k for k, c in enumerate(cands)}
    for k, par in parent.items():
        root[k] = root[pos[par]]
    top, chains = [], set()
    for i in by_score:
        if len(top) == n_check or not explained[i] > 0:
            break
        if root[int(i)] not in chains:
            chains.add(root[int(i)])
            top.append(int(i))
    if n_check and labels is not None:
        seen = {labels[i] for i in top}
        for i in by_score:
            if labels[i] not in seen and explained[i] > 0 and root[int(i)] not in chains:
                seen.add(labels[i])
                chains.add(root[int(i)])
                top.append(int(i))
    extra = _companions(top, members, explained)  # [(companion, the checked member it goes with)]
    if top:
        if solve is None:
            solve = shifted_solver(model, sur.p_basis, shift_hz)
        start = lin[0].p  # the nonlinear fits run through the stages from the first stage's baseline

        def run(idx, c0s):
            jobs = []

            def built():  # each check's extension is built here while the executor runs the checks built before
                for i, c0 in zip(idx, c0s):
                    jobs.append(_check_job(sur, basis, model, cands[i], stages, quantity, start, c0, lower, upper,
                                           max_nfev, solve))
                    yield jobs[-1][0]

            if executor is None:
                outs = [(run_start(job), jobs[-1][1]) for job in built()]
            else:
                tf = time.perf_counter()
                fits = executor.map(run_start, built())
                # the pool's wall time beyond the extensions, spread over the checks
                share = max(time.perf_counter() - tf - sum(t for _, t in jobs), 0.0) / len(jobs)
                outs = [(o, t + share) for o, (_, t) in zip(fits, jobs)]
            outs = [list(o) + [0] for o in outs]
            for _ in range(max(int(continue_checks), 0)):
                todo = [k for k, (out, _, _) in enumerate(outs) if not out.converged and np.isfinite(out.sd)]
                if not todo:
                    break
                # the last stage again from where it stopped (its objective on the candidate's extended surrogate)
                more = [((jobs[k][0][0][-1],), outs[k][0].p, *jobs[k][0][2:]) for k in todo]
                tf = time.perf_counter()
                fits = [run_start(a) for a in more] if executor is None else list(executor.map(run_start, more))
                share = (time.perf_counter() - tf) / len(todo)
                for k, o in zip(todo, fits):
                    old = outs[k][0]
                    if o.sd <= old.sd:  # the outcome's own time is added by _checked_fit
                        outs[k][0], spent = o, old.time_s
                    else:  # keep the better point; the continuation counts as run
                        outs[k][0], spent = replace(old, converged=o.converged), o.time_s
                    outs[k][1] += spent if executor is None else share
                    outs[k][2] += 1
            return [replace(_checked_fit(cands[i], i, out, lin[-1].sd, t_ext), explained_linear=float(explained[i]),
                            continued=n_more, surrogate=job[0][0][-1].sur)
                    for i, (out, t_ext, n_more), job in zip(idx, outs, jobs)]

        checks += run(top, [c_lin[i] for i in top])
        if extra:
            # a region's alternatives after its checked member, each from the better (lower SD at the start) of
            # its own linear magnitude and the member's checked change carried over to it (_carried): a union
            # around a closed part starts at the same stiffness, not at a linear magnitude that may be ~0
            got = {c.index: c for c in checks}
            checks += run([k for k, _ in extra],
                          [(float(c_lin[k]), _carried(cands[i], got[i].c, cands[k])) for k, i in extra])
    t3, c3 = time.perf_counter(), time.process_time()
    checks.sort(key=lambda c: -c.score)
    checked = [c.index for c in checks]
    done = set(checked)
    rest = [int(i) for i in np.argsort(-explained, kind="stable") if int(i) not in done]
    return Screening(
        names=tuple(c.name for c in cands),
        stage_zeta=np.array([z for z, _ in stages]),
        stage_explained=E,
        stage_sd=np.array([x.sd for x in lin]),
        explained=explained,
        c_linear=c_lin,
        significant=significant,
        noise_explained=noise,
        threshold=threshold,
        checks=tuple(checks),
        order=np.array(checked + rest, dtype=int),
        p_start=p_in,
        sd_start=sd_start,
        p_baseline=lin[-1].p,
        sd_baseline=lin[-1].sd,
        n_residuals=lin[-1].n_res,
        rank_p=lin[-1].rank,
        timings_s={"baseline refits": t_fit, "linear screening": t_lin,
                   "linear per candidate and stage": t_lin / ((len(cands) - len(zoomed)) * len(stages)),
                   "zoom": t2 - tz, "nonlinear checks": t3 - t2, "total": t3 - t0,
                   "cpu: baseline and linear": cz - c0, "cpu: zoom": c2 - cz, "cpu: nonlinear checks": c3 - c2},
        zoomed=tuple(zoomed),
    )


def _regions(regions, n_first: int, root: dict) -> dict:
    """Index -> (the indices of its region, in order; {index: frozenset of its places}) for the candidates of
    a region (:func:`screen`'s ``regions``); every member's ``root`` set to the region's first member."""
    if regions is None:
        return {}
    by_label: dict = {}
    for k, g in enumerate(regions[:n_first]):
        if g is not None:
            by_label.setdefault(g[0], []).append(k)
    out = {}
    for ks in by_label.values():
        places = {k: frozenset(regions[k][1]) for k in ks}
        for k in ks:
            root[k] = ks[0]
            out[k] = (ks, places)
    return out


def _companions(top: list, members: dict, explained) -> list:
    """The alternatives checked with each region's checked member (:func:`screen`'s ``regions``): of the members
    whose places strictly enclose its places the two largest and the best linear other, then the best linear
    member that partly overlaps it (neither inside nor around it, explained > 0): at most 4. Not already in
    ``top``; in order, as (companion index, member index)."""
    done, out = set(top), []
    for i in list(top):
        if i not in members:
            continue
        ks, places = members[i]
        me = places[i]
        around = [k for k in ks if me < places[k]]
        # the two largest around it (the unions: of its stretch, of the whole part pair) and the best linear
        # other: a small cell lies inside many windows, and those are checked as the partly overlapping one's
        big = sorted(around, key=lambda k: (-len(places[k]), -explained[k]))[:2]
        around = big + sorted((k for k in around if k not in big), key=lambda k: -explained[k])[:1]
        partly = [k for k in ks if places[k] & me and not places[k] <= me and not me < places[k]
                  and explained[k] > 0]
        for k in around + sorted(partly, key=lambda k: -explained[k])[:1]:
            if k not in done:
                done.add(k)
                out.append((k, i))
    return out


def _carried(member: CandidateTerm, c: float, other: CandidateTerm) -> float | None:
    """The magnitude of ``other`` closest to ``member`` at ``c``: the least-squares c' of c' dA_other ~ c dA_member
    (A = K where both change it, else M; Frobenius): for nested contact terms with one common rate per pair,
    c times the share of ``other``'s pairs that ``member`` holds (the same total stiffness on the shared pairs).
    None when they share no matrix kind or do not overlap."""
    for a, b in ((member.dK, other.dK), (member.dM, other.dM)):
        if a is None or b is None:
            continue
        a, b = sp.csr_matrix(a), sp.csr_matrix(b)
        bb = float(b.multiply(b).sum())
        ab = float(a.multiply(b).sum())
        if bb > 0 and ab != 0:
            return float(c) * ab / bb
        return None
    return None


def _check_job(sur, basis, model, cand, stages, quantity, p0, c0, lower, upper, max_nfev, solve, xtol=1e-8):
    """Extend by one candidate; return (the :func:`run_start` arguments of the [p, c] re-fit from [p0, c0]
    through the stages, wall time of the extension). ``c0`` may be a tuple of alternative starts (None
    skipped): the fit starts from the one with the lower SD on the first stage."""
    t0 = time.perf_counter()
    # one BLAS thread: the extension's products are small (the candidate's rows, a few dozen new columns) and
    # run while the pool's workers fit the checks built before; with two threads against two busy workers an
    # extension at 200k DOF took 6x the wall time (stop 28: 4 extensions 92.7 s against 15.5 s; 9.4 s and
    # 9.3 s with the cores free, twice the CPU)
    with blas_threads(1):
        sur_e, _ = extend_with_candidates(sur, basis, model, [cand], solve=solve, with_basis=False)
    objs = [Objective(sur_e, d, z, quantity) for z, d in stages]
    lo = np.r_[lower, cand.lower]
    hi = np.r_[upper, cand.upper]
    starts = [np.clip(np.r_[p0, c], lo, hi) for c in (np.atleast_1d(np.asarray(c0, dtype=object)).tolist())
              if c is not None and np.isfinite(float(c))]
    # several starts of c (alternatives): the one with the lower SD on the first stage, where the fit starts
    x0 = starts[0] if len(starts) == 1 else min(starts, key=lambda x: objs[0].sd(x))
    return (objs, x0, lo, hi, max_nfev, xtol), time.perf_counter() - t0


def _checked_fit(cand, index, out, sd0, t_ext) -> CandidateCheck:
    """The CandidateCheck of a re-fit outcome (``t_ext``: the extension's wall time, added to the fit's)."""
    explained = 1.0 - out.sd / sd0 if sd0 > 0 else 0.0
    return CandidateCheck(cand.name, index, float(out.p[-1]), out.p[:-1].copy(), float(out.sd), float(explained),
                          out.converged, float(t_ext + out.time_s))


# ----------------------------------------------------------------------------- recalibration with candidates


@dataclass(frozen=True)
class CandidateFit:
    """Calibration of the existing parameters together with chosen candidates.

    Attributes
    ----------
    names : tuple of str, the candidates (in order; their parameters follow the existing ones)
    p : (n_p,) existing parameters ; c : (k,) candidate magnitudes
    sd : float, square deviation on the fitted data at (p, c)
    sd_start : float, square deviation at the start (c = c0)
    surrogate : Surrogate, the extended surrogate (parameters [p, c])
    basis : (n, r + m) ndarray or None, its basis (None when fitted ``with_basis=False``)
    lower, upper : (n_p + k,) bounds of [p, c]
    converged : bool ; time_s : float
    """

    names: tuple
    p: np.ndarray
    c: np.ndarray
    sd: float
    sd_start: float
    surrogate: Surrogate = field(repr=False)
    basis: np.ndarray = field(repr=False)
    lower: np.ndarray = field(repr=False)
    upper: np.ndarray = field(repr=False)
    converged: bool = True
    time_s: float = 0.0

    @property
    def x(self) -> np.ndarray:
        """[p, c]: the parameter vector of ``surrogate``."""
        return np.concatenate([self.p, self.c])

    @property
    def n_added(self) -> int:
        return int(self.c.size)

    def to_dict(self) -> dict:
        return {"names": list(self.names), "p": self.p.tolist(), "c": self.c.tolist(), "sd": self.sd,
                "sd_start": self.sd_start, "converged": self.converged, "time_s": self.time_s}


def fit_with(
    sur: Surrogate,
    basis,
    model: FRFModel,
    candidates,
    data,
    zeta: float,
    lower,
    upper,
    *,
    p0,
    c0=None,
    continuation=(),
    quantity: str = "accelerance",
    shift_hz: float | None = None,
    solve=None,
    max_nfev: int = 100,
    xtol: float = 1e-10,
    warm: CandidateCheck | None = None,
    with_basis: bool = True,
) -> CandidateFit:
    """Recalibrate the existing parameters with chosen candidates (one or several together).

    Parameters
    ----------
    sur, basis : the calibrated model's surrogate and its basis T.
    model : FRFModel
        The model of ``sur`` (candidates enter linearly with their derivative
        matrices, :func:`extended_model`) or the model already extended by
        exactly these candidates (e.g. from ``with_terms``; exact).
    candidates : sequence of CandidateTerm
    data : sequence of FitData, equalized at ``zeta``.
    zeta : float
    lower, upper : (n_p,) bounds of the existing parameters.
    p0 : (n_p,) start of the existing parameters (the calibrated point).
    c0 : (k,) start of the magnitudes (default 0 clipped to the bounds; the
        screening's c* or nonlinear c is a better start).
    continuation : sequence of (zeta, data), damping stages run first.
    quantity, shift_hz, solve, max_nfev, xtol
        As :func:`screen` / :func:`calibration.calibrate`.
    warm : CandidateCheck, optional
        The screening's nonlinear check of the one candidate fitted here. If
        it converged, the fit starts at its (p, c) and skips the continuation
        stages: the check ran them from (p0, c*) on the same data and the same
        extension, so its end point is already in the final stage's basin;
        only the final stage runs on, to ``xtol``. Otherwise (not converged,
        other candidates) it is ignored. With ``with_basis=False`` its extended
        surrogate (:attr:`CandidateCheck.surrogate`) is used as it is: the
        extension is not built again.
    with_basis : bool
        False: the fit's ``basis`` is None (a caller that needs only the
        surrogate, for hold-out and cross-validation, saves the (n, r + k)
        copy and, going on from a check, the extension).

    Returns
    -------
    CandidateFit
        Holds the extended surrogate and its bounds, so that hold-out SD
        (:func:`calibration.holdout_sd`), cross-validation
        (:func:`calibration.cross_validate`) and the raw-line refinement
        (:func:`calibration.refine`) run on it at ``fit.x``.
    """
    t0 = time.perf_counter()
    basis = np.asarray(basis, float)
    cands = _checked(candidates, basis, sur)
    lower, upper = check_bounds(lower, upper, sur.n_params)
    lo = np.r_[lower, [c.lower for c in cands]]
    hi = np.r_[upper, [c.upper for c in cands]]
    c0 = np.zeros(len(cands)) if c0 is None else np.asarray(c0, float)
    if c0.shape != (len(cands),):
        raise CalibrationError(f"fit_with: c0 has shape {c0.shape}, expected ({len(cands)},)")
    x0 = np.clip(np.r_[np.asarray(p0, float), c0], lo, hi)
    sur_e = None
    if (warm is not None and warm.converged and len(cands) == 1 and warm.name == cands[0].name
            and warm.p.shape == (sur.n_params,)):
        x0 = np.clip(np.r_[warm.p, warm.c], lo, hi)
        continuation = ()
        kept = warm.surrogate
        if (not with_basis and kept is not None
                and tuple(kept.parameter_names) == tuple(sur.parameter_names) + (cands[0].name,)):
            sur_e, basis_e = kept, None
    if sur_e is None:
        if solve is None and not (shift_hz is not None and shift_hz > 0):
            raise CalibrationError("fit_with needs shift_hz > 0 (the basis build's) or solve")
        sur_e, basis_e = extend_with_candidates(sur, basis, model, cands, shift_hz=shift_hz, solve=solve,
                                                with_basis=with_basis)
    objs = [Objective(sur_e, d, z, quantity) for z, d in continuation] + [Objective(sur_e, data, zeta, quantity)]
    out = run_start((objs, x0, lo, hi, max_nfev, xtol))
    n_p = sur.n_params
    return CandidateFit(
        names=tuple(c.name for c in cands),
        p=out.p[:n_p].copy(),
        c=out.p[n_p:].copy(),
        sd=float(out.sd),
        sd_start=float(out.sd_start),
        surrogate=sur_e,
        basis=basis_e,
        lower=lo,
        upper=hi,
        converged=bool(out.converged),
        time_s=time.perf_counter() - t0,
    )
