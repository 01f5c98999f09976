"""Reduced surrogate of a parametric FE model and its FRFs with modal damping.

Basis (built once per calibration cycle at a point p_b):

* the undamped modes of (K(p_b), M(p_b)) up to ``basis_factor`` times the top
  of the band (paper Eq. 2.16), and
* static correction vectors (K(p_b) + s M(p_b))^-1 f for every drive load
  vector and every sensor output vector. The small positive shift
  ``s = (2 pi shift_hz)^2`` makes the operator definite for free-free models;
  the rigid-body part of these vectors is already in the mode set and is
  removed by the M-orthonormalization. They carry the residual flexibility
  of the truncated modes, i.e. the "D term" of the drive/sensor FRFs.

T is M-orthonormalized; every AffineMatrix term is projected, so the reduced
``K_r(p) = T^T K(p) T`` and ``M_r(p)`` are *exact* functions of p for the fixed
basis (not the first-order Taylor form of paper Eq. 2.20).

FRF at p: solve the small eigenproblem K_r X = M_r X diag(lambda), X^T M_r X = I.
The viscous damping of paper Eq. 2.14 built from *all* reduced modes is
diagonal in those modes, so the reduced damped FRF is exactly the modal sum

    H(w) = sum_k q(w) (C T x_k)(x_k^T T^T B) / (lambda_k - w^2 + i w c_k),
    c_k = 2 zeta_k omega_k,  omega_k = sqrt(lambda_k),

with q = -w^2 (accelerance), i w (mobility) or 1 (receptance). Rigid modes
(omega_k below ``rigid_hz``) get c_k = 0, as Eq. 2.14 gives for omega_k = 0.

Jacobian: we differentiate this H(p) exactly, *including* the change of the
damping matrix V(p) through the modes (c_k follows omega_k, the damping ratio
held), by Nelson's expansion of the eigenvector derivatives in the reduced
modes (exact, the reduced basis being complete): see
:mod:`calibration._modal_derivative`, which the calibration objectives, the
raw-line refinement and the diagnosis's candidate derivatives share.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from femodel import AffineMatrix, FactorizationError, analyze_ahead as _analyze_pattern_ahead, factorize, union_pattern

from calibration._errors import CalibrationError
from calibration._threads import blas_threads as _blas_threads  # module-local name as before; shared with _fit.single_thread
from labdata import FRF_QUANTITIES
from labdata import quantity_factor as _quantity_factor

_QUANTITIES = FRF_QUANTITIES
#: Models up to this many DOF are solved dense (all modes, a dense Cholesky): a cold rebuild costs little there.
DENSE_BELOW = 1500
#: Default mode cut-off of a basis, as a multiple of the band top: with the loads' statics and their first
#: moments, modes to 1.25 x band top match the full model as modes to 2 x did without the moments
#: (docs/calibration.md, stop 38).
BASIS_FACTOR = 1.25


@dataclass(frozen=True)
class FRFModel:
    """A parametric full-order FE model with its drive and sensor vectors.

    Parameters
    ----------
    K, M : AffineMatrix
        Stiffness (N/m) and mass (kg) of the independent DOF, (n, n), SI.
    inputs : (n, n_in) array or sparse
        Load vectors: unit force at each drive DOF in the drive direction.
    outputs : (n_out, n) array or sparse
        Sensor rows: displacement of each sensor along its direction.
    input_names, output_names : tuple of str
        Channel names, in column/row order.
    parameter_names : tuple of str
        Names of the normalized parameters p (P = P0 (1 + p)).
    parametric : femodel.ParametricModel, optional
        When given, its fast shared-pattern ``stiffness``/``mass``/``dK``/``dM``
        are used for the full-order work (same values as K, M).

    Attributes
    ----------
    factor_cache : dict
        Symbolic factorization and sparsity-union data that
        :func:`build_surrogate` reuses across cycles while K's and M's
        patterns stay the same.  Not part of the value (excluded from
        comparison and repr, empty on every new instance) and not pickled:
        it stays in the process that filled it.
    """

    K: AffineMatrix
    M: AffineMatrix
    inputs: object
    outputs: object
    input_names: tuple = ()
    output_names: tuple = ()
    parameter_names: tuple = ()
    parametric: object = None
    factor_cache: dict = field(default_factory=dict, init=False, compare=False, repr=False)

    def __post_init__(self) -> None:
        n = self.K.shape[0]
        if self.M.shape != (n, n):
            raise CalibrationError(f"K is {self.K.shape} but M is {self.M.shape}")
        if self.K.n_params != self.M.n_params:
            raise CalibrationError(
                f"K has {self.K.n_params} parameters but M has {self.M.n_params}"
            )
        if self.inputs.shape[0] != n or self.outputs.shape[1] != n:
            raise CalibrationError(
                f"inputs {self.inputs.shape} / outputs {self.outputs.shape} do not match {n} DOF"
            )
        if not self.input_names:
            object.__setattr__(self, "input_names", tuple(f"in{i}" for i in range(self.inputs.shape[1])))
        if not self.output_names:
            object.__setattr__(
                self, "output_names", tuple(f"out{i}" for i in range(self.outputs.shape[0]))
            )
        if not self.parameter_names:
            object.__setattr__(self, "parameter_names", tuple(f"p{j}" for j in range(self.K.n_params)))

    @property
    def n_params(self) -> int:
        return self.K.n_params

    def __getstate__(self):  # the factorization cache (see _factor) stays in this process
        return {**self.__dict__, "factor_cache": {}}

    def stiffness(self, p):
        return self.parametric.stiffness(p) if self.parametric is not None else self.K.at(p)

    def mass(self, p):
        return self.parametric.mass(p) if self.parametric is not None else self.M.at(p)

    def dK(self, p, j):
        return self.parametric.dK(p, j) if self.parametric is not None else self.K.derivative(p, j)

    def dM(self, p, j):
        return self.parametric.dM(p, j) if self.parametric is not None else self.M.derivative(p, j)


@dataclass(frozen=True)
class Surrogate:
    """Reduced model, exact in p for a fixed basis.

    Attributes
    ----------
    K, M : AffineMatrix
        Reduced (r, r) stiffness and mass terms, SI.
    inputs : (r, n_in) ndarray
        ``T^T B``.
    outputs : (n_out, r) ndarray
        ``C T``.
    p_basis : (n_p,) ndarray
        Normalized parameters at which the basis was computed.
    basis_frequencies_hz : (n_modes,) ndarray
        Full-model natural frequencies of the modes in the basis.
    n_static : int
        Number of static correction vectors and their first moments kept after orthonormalization (they
        follow the modes in the basis).
    n_enrich : int
        Number of parameter-derivative enrichment vectors kept.
    rigid_hz : float
        Modes below this frequency are rigid (no damping).
    output_names, input_names, parameter_names : tuple of str
    timings_s : dict
        Wall time of the build steps.
    """

    K: AffineMatrix
    M: AffineMatrix
    inputs: np.ndarray
    outputs: np.ndarray
    p_basis: np.ndarray
    basis_frequencies_hz: np.ndarray
    n_static: int
    rigid_hz: float
    n_enrich: int
    output_names: tuple
    input_names: tuple
    parameter_names: tuple
    timings_s: dict = field(default_factory=dict)

    @property
    def size(self) -> int:
        return self.K.shape[0]

    @property
    def n_params(self) -> int:
        return self.K.n_params

    def output_index(self, names) -> np.ndarray:
        """Row indices of the named output channels (CalibrationError on unknown names)."""
        lookup = {n: i for i, n in enumerate(self.output_names)}
        missing = [n for n in names if n not in lookup]
        if missing:
            raise CalibrationError(f"output channels {missing} are not in the surrogate {list(self.output_names)}")
        return np.array([lookup[n] for n in names], dtype=int)


# ----------------------------------------------------------------------------- full-order solves


def _factor(A, cache: dict | None = None):
    """solve(F) for symmetric positive definite A through :func:`femodel.factorize` (backend "auto").

    ``cache`` (a dict kept by the caller, e.g. on the :class:`FRFModel`) holds
    the symbolic analysis (fill-reducing ordering and supernodes) of the last
    pattern seen, for the backend that can reuse it (scikit-sparse's CHOLMOD).
    K(p) + s M(p) keeps its sparsity pattern for every p, so later
    factorizations at new parameter points are numeric only: at 200k DOF the
    analysis is about 3.5 s of a 6 s factorization.  A matrix that a
    Cholesky backend finds indefinite in floating point is LU-factorized.
    """
    try:
        fac = factorize(A, cache=cache)
    except FactorizationError as exc:
        raise CalibrationError(f"stiffness (+ shift) cannot be factorized: {exc}") from exc
    if cache is not None:
        cache["factor_s"] = fac.factor_time_s
    return fac.solve


def _canonical_csr(A) -> sp.csr_matrix:
    A = sp.csr_matrix(A)
    if not A.has_canonical_format:
        A = A.copy()
        A.sum_duplicates()
    return A


def _shifted(K, M, s: float, cache: dict | None = None) -> sp.csc_matrix:
    """K + s M on the union of the two patterns, explicit zeros kept.

    ``scipy``'s sparse sum drops entries that cancel, so K(p) + s M(p) would
    change its pattern between parameter points (at the nominal point some
    shell-shear corrections cancel exactly) and defeat the reuse of the
    symbolic factorization. The union pattern and where K's and M's entries
    land in it are kept in ``cache`` while K's and M's patterns stay the same.
    The matrix is symmetric, so the CSR arrays serve as CSC.
    """
    K = _canonical_csr(K)
    M = _canonical_csr(M)
    hit = None if cache is None else cache.get("union")
    if hit is not None:
        kp, ki, mp, mi, U, pos_k, pos_m = hit
        if not (np.array_equal(kp, K.indptr) and np.array_equal(ki, K.indices)
                and np.array_equal(mp, M.indptr) and np.array_equal(mi, M.indices)):
            hit = None
    if hit is None:
        # where K's and M's entries land in the union of their patterns (a merge of sorted keys on two
        # threads: 0.25 s at 200k DOF, where the union's entry ranks picked out by sparse products took 0.6-1 s)
        indptr, indices, (pos_k, pos_m) = union_pattern(K, M)
        U = sp.csr_matrix((np.zeros(indices.shape[0]), indices, indptr), shape=K.shape)
        if U.nnz == K.nnz:  # M's pattern inside K's: the union is K's pattern
            pos_k = None
        if cache is not None:
            cache["union"] = (K.indptr.copy(), K.indices.copy(), M.indptr.copy(), M.indices.copy(), U, pos_k, pos_m)
    if pos_k is None:  # U is K's pattern
        data = K.data.copy()
    else:
        data = np.zeros(U.nnz)
        data[pos_k] = K.data
    data[pos_m] += s * M.data
    return sp.csc_matrix((data, U.indices, U.indptr), shape=U.shape)


def _m_orthonormal(Z: np.ndarray, Ms, Q: np.ndarray, MQ: np.ndarray, floor: float = 1e-10):
    """Z = Q C + Zn B with Zn M-orthonormal and M-orthogonal to Q (M-orthonormal, ``MQ`` = M Q).

    Two rounds, each a projection off Q and a Gram-eigenvector normalization with a fresh M Z (updated
    products drift as Z shrinks under the projection; twice is enough, as in classical Gram-Schmidt).
    Directions of Z whose M-norm after the first projection is below ``floor`` times the largest column
    norm of Z are dropped (a Krylov block that brings nothing new).

    Returns
    -------
    Zn : (n, k) ndarray, MZn : M Zn, C : (q, z) ndarray, B : (k, z) ndarray
    """
    C = np.zeros((Q.shape[1], Z.shape[1]))
    B = np.eye(Z.shape[1])
    scale = None
    for rnd in range(2):
        if Q.shape[1]:
            D = MQ.T @ Z
            Z = Z - Q @ D
            C += D @ B
        MZ = Ms @ Z
        G = _sym(Z.T @ MZ)
        g, U = np.linalg.eigh(G)
        if scale is None:  # the columns' squared M-norms before the projection (Pythagoras)
            scale = float(np.max(np.sum(C * C, axis=0) + np.diag(G), initial=0.0))
        keep = g > (floor**2 * scale if rnd == 0 else 1e-14 * max(g.max(initial=0.0), 0.0))
        keep &= g > 0
        V = U[:, keep] / np.sqrt(g[keep])
        Z, MZ = Z @ V, MZ @ V  # (the second round's V is near the identity: MZ V is M Z to round-off)
        B = (np.sqrt(g[keep])[:, None] * U[:, keep].T) @ B
    return Z, MZ, C, B


def _shift_invert_modes(Ks, Ms, s, solve, max_hz: float, max_modes: int, block: int = 8, tol: float = 1e-5,
                        max_cols: int = 120):
    """Block Lanczos on (K + s M)^-1 M with an existing solver for K + s M: the modes up to ``max_hz``.

    The factorization of the static solves is reused, so one factorization
    serves modes, statics and enrichment. The operator is symmetric in the
    M inner product; its largest eigenvalues 1 / (lambda + s) are the lowest
    modes. The Krylov space grows by blocks of ``block`` columns, each a
    solve of ``block`` right-hand sides (a block solve costs a quarter of as
    many single ones per column: at 200k DOF 72 block columns took 2.6-3.0 s
    where ARPACK's 37 single-vector steps took 4.2 s for the same 14 modes),
    kept M-orthonormal by full reorthogonalization. The start block is a
    seeded random block smoothed by two solves (no rough high-frequency
    content in the Ritz vectors). After every block, Rayleigh-Ritz on the
    projected operator: a Ritz pair has converged when its residual, read
    from the Krylov relation, is at most ``tol`` times its eigenvalue (as
    ARPACK's test). The run ends when every Ritz value below the cut and the
    first one above it have converged. When the space reaches ``max_cols``
    columns, the leading converged pairs are locked and a new run starts
    from the next Ritz vectors with the locked ones deflated, so nothing is
    computed twice; also when a cluster of found modes (e.g. the rigid-body
    modes) is as large as the block, which a block Krylov space cannot
    resolve beyond its width.

    ``tol`` = 1e-5: these vectors span a reduction basis (the surrogate
    solves its own eigenproblem in it), so the span matters, not eigenpair
    digits; the frequencies agree with ARPACK's within 4e-12 (200k DOF).
    """
    n = Ks.shape[0]
    cut = (2 * np.pi * max_hz) ** 2
    limit = min(max_modes, n - 2)
    block = max(1, min(block, limit))
    max_cols = max(2 * block, min(max_cols, n))
    F = np.zeros((n, 0))
    MF = np.zeros((n, 0))
    lams = np.zeros(0)
    rng = np.random.default_rng(n)
    Qa = np.empty((n, max_cols), order="F")  # F order: the leading columns are one contiguous block for BLAS
    MQa = np.empty((n, max_cols), order="F")
    start = None
    stalls = 0
    again = False  # a run looking for more copies of a cluster as wide as the block
    while F.shape[1] < limit:
        X = rng.standard_normal((n, block))
        if F.shape[1]:  # off the found modes before the smoothing, which would amplify them
            X -= F @ (MF.T @ X)
        X = solve(Ms @ solve(Ms @ X))
        if start is not None:
            X = np.hstack([start, X[:, : max(0, block - start.shape[1])]])
        X, MX, _, _ = _m_orthonormal(X, Ms, F, MF)
        if X.shape[1] == 0:
            break  # the space is exhausted: every mode is found
        m, j0 = X.shape[1], 0
        Qa[:, :m], MQa[:, :m] = X, MX
        H = np.zeros((0, 0))
        while True:
            Z = solve(MQa[:, j0:m])
            if F.shape[1]:  # the locked modes deflated (twice, as the reorthogonalization)
                for _ in range(2):
                    Z -= F @ (MF.T @ Z)
            Zn, MZn, C, B = _m_orthonormal(Z, Ms, Qa[:, :m], MQa[:, :m])
            Hn = np.zeros((m, m))
            Hn[:j0, :j0] = H
            Hn[:, j0:] = C
            Hn[j0:, :] = C.T
            H = _sym(Hn)  # the projected operator Q^T M (K + s M)^-1 M Q
            th, Y = np.linalg.eigh(H)
            th, Y = th[::-1], Y[:, ::-1]
            res = np.linalg.norm(B @ Y[j0:, :], axis=0)  # || W x - theta x ||_M of each Ritz pair
            conv = res <= tol * np.abs(th)
            lead = int(np.argmin(conv)) if not conv.all() else conv.size
            lam = np.full(th.shape, np.inf)  # theta = 0: a massless direction, no finite mode
            lam[th > 0] = 1.0 / th[th > 0] - s
            below = int(np.count_nonzero(lam <= cut))
            exhausted = Zn.shape[1] == 0
            if exhausted:  # the Krylov space is invariant: its Ritz pairs are exact
                lead = int(np.count_nonzero(th > 0))
            done = lead > below or exhausted
            if done or m + Zn.shape[1] > max_cols or F.shape[1] + lead >= limit:
                take = min(lead, limit - F.shape[1])
                F = np.hstack([F, Qa[:, :m] @ Y[:, :take]])
                MF = np.hstack([MF, MQa[:, :m] @ Y[:, :take]])
                lams = np.concatenate([lams, lam[:take]])
                start = Qa[:, :m] @ Y[:, take:take + block] if not done and take < m else None
                break
            Qa[:, m:m + Zn.shape[1]], MQa[:, m:m + Zn.shape[1]] = Zn, MZn
            j0, m = m, m + Zn.shape[1]
        stalls = stalls + 1 if take == 0 else 0
        if stalls >= 2:
            raise CalibrationError(f"block Lanczos: no mode converged in two runs of {max_cols} vectors "
                                   f"(tolerance {tol:g}); {F.shape[1]} modes found")
        if not done:
            continue
        if again and not np.any(lam[:take] <= cut):
            break  # the new run found no further copy
        if not _cluster_at_width(lams[lams <= cut], s, block):
            break
        again, start = True, None  # a cluster as wide as the block: a new run (deflated) looks for more copies
    order = np.argsort(lams)
    lams, F = lams[order], F[:, order]
    keep = lams <= cut
    freqs = np.sqrt(np.clip(lams[keep], 0.0, None)) / (2 * np.pi)
    return freqs, F[:, keep]


def _cluster_at_width(lam: np.ndarray, s: float, width: int, rtol: float = 1e-6) -> bool:
    """Whether ``width`` or more of the eigenvalues ``lam`` coincide (relative to lambda + s); with
    ``width`` 1, whether there is any."""
    if lam.size < width or lam.size == 0:
        return False
    if width <= 1:
        return True
    th = np.sort(1.0 / (lam + s))
    close = np.diff(th) <= rtol * th[1:]
    run = 1
    for c in close:
        run = run + 1 if c else 1
        if run >= width:
            return True
    return False


def _dense_shift_inverted(K: np.ndarray, M: np.ndarray, s: float):
    """All finite modes of a small dense pencil whose M may be singular, and a solver for K + s M.

    Massless DOF (a lumped-mass beam's rotations, Nastran's default) make M
    singular, so ``eigh(K, M)`` (which needs M definite) cannot be used. As
    Nastran's shift-invert does, the pencil is turned around at the shift:
    with K + s M = L L^T (definite for any free-free structure whose rigid
    motions carry mass) the symmetric problem L^-1 M L^-T y = mu y gives
    lambda = 1/mu - s and phi = L^-T y / sqrt(mu) (so phi^T M phi = 1). The
    massless DOF have mu = 0 (infinite frequency) and are dropped.

    Returns
    -------
    lam : (m,) ascending eigenvalues (rad/s)^2 of the finite modes
    X : (n, m) mass-normalized shapes
    solve : callable, solve(F) = (K + s M)^-1 F
    """
    try:
        L = np.linalg.cholesky(K + s * M)
    except np.linalg.LinAlgError:
        raise CalibrationError(
            f"K + s M (s = {s:.4g}) is not positive definite: the model has a mechanism that carries no "
            "mass, or a negative stiffness") from None
    A = sla.solve_triangular(L, sla.solve_triangular(L, M, lower=True).T, lower=True)
    mu, Y = np.linalg.eigh(_sym(A))
    finite = mu > 1e-12 * max(mu.max(), 0.0)
    mu, Y = mu[finite][::-1], Y[:, finite][:, ::-1]
    X = sla.solve_triangular(L, Y, lower=True, trans="T") / np.sqrt(mu)[None, :]
    lam = 1.0 / mu - s
    cf = (L, True)
    solve = lambda F: sla.cho_solve(cf, np.asarray(F.toarray() if sp.issparse(F) else F))  # noqa: E731
    return lam, X, solve


def full_modes(K, M, max_hz: float, shift_hz: float, max_modes: int = 600, dense_below: int = DENSE_BELOW,
               cache: dict | None = None):
    """Undamped modes of (K, M) up to ``max_hz`` and a solver for K + s M.

    Parameters
    ----------
    K, M : (n, n) sparse or dense
    max_hz : float
        Highest natural frequency wanted (Hz).
    shift_hz : float
        Shift s = (2 pi shift_hz)^2 > 0 of the static solves (K + s M is
        definite also for free-free models); the Lanczos shift-invert runs at
        sigma = -s with the same factorization.
    max_modes : int
        Safety cap on the number of modes.
    cache : dict, optional
        Keeps the symbolic factorization for later calls on the same pattern.

    Returns
    -------
    freqs_hz : (m,) ndarray
    shapes : (n, m) ndarray, mass-normalized
    solve : callable, solve(F) = (K + s M)^-1 F for (n, k) arrays
    """
    n = K.shape[0]
    s = (2 * np.pi * shift_hz) ** 2
    if n <= dense_below:
        Kd = K.toarray() if sp.issparse(K) else np.asarray(K)
        Md = M.toarray() if sp.issparse(M) else np.asarray(M)
        lam, X, solve = _dense_shift_inverted(Kd, Md, s)
        keep = lam <= (2 * np.pi * max_hz) ** 2
        lam = np.clip(lam[keep], 0.0, None)
        return np.sqrt(lam) / (2 * np.pi), X[:, keep], solve
    Ks = sp.csr_matrix(K)  # (CSR matvecs in the Lanczos loop; symmetric, so the same operator)
    Ms = sp.csr_matrix(M)
    solve = _factor(_shifted(Ks, Ms, s, cache), cache)
    freqs, Phi = _shift_invert_modes(Ks, Ms, s, solve, max_hz, max_modes)
    return freqs, Phi, solve


def refreshed_modes(K, M, T_old, max_hz: float, shift_hz: float, extra=None, cache: dict | None = None):
    """Modes of (K, M) up to ``max_hz`` from one block inverse iteration on an old basis.

    Returns the triple of :func:`full_modes`, the rest of the inverse-iterated
    basis (M-orthonormal Ritz vectors above ``max_hz``, reused as enrichment),
    ``M @ shapes`` and ``M @`` that rest. With ``extra`` (n, k) given,
    ``(K + s M)^-1 extra`` is solved in the same block solve and returned as a
    seventh item.
    """
    s = (2 * np.pi * shift_hz) ** 2
    n = K.shape[0]
    if n <= DENSE_BELOW:
        f, Phi, solve = full_modes(K, M, max_hz, shift_hz)
        out = (f, Phi, solve, None, M @ Phi, None)
        return out if extra is None else (*out, solve(extra))
    solve = _factor(_shifted(K, M, s, cache), cache)
    r_old = T_old.shape[1]
    Q = solve(M @ T_old if extra is None else np.hstack([M @ T_old, extra]))
    if extra is not None:
        Q, X_extra = Q[:, :r_old], np.ascontiguousarray(Q[:, r_old:])
    # Rayleigh-Ritz on span(Q), rank-cut on its Gram matrix: Z^T (Q^T M Q) Z = I
    MQ = M @ Q
    g, U = np.linalg.eigh(_sym(Q.T @ MQ))
    if g.size == 0 or g.max() <= 0:
        raise CalibrationError("block inverse iteration returned a null basis")
    Y = U[:, g > 1e-12 * g.max()] / np.sqrt(g[g > 1e-12 * g.max()])
    lam, V = np.linalg.eigh(_sym(Y.T @ (Q.T @ (K @ Q)) @ Y))
    keep = lam <= (2 * np.pi * max_hz) ** 2
    Q = Q @ (Y @ V)
    MQ = MQ @ (Y @ V)
    lam = np.clip(lam[keep], 0.0, None)
    out = (np.sqrt(lam) / (2 * np.pi), np.ascontiguousarray(Q[:, keep]), solve, np.ascontiguousarray(Q[:, ~keep]),
           np.ascontiguousarray(MQ[:, keep]), np.ascontiguousarray(MQ[:, ~keep]))
    return out if extra is None else (*out, X_extra)


def assembled(model: FRFModel, p) -> tuple:
    """K(p), M(p) of the full model; the last point's pair is kept in ``model.factor_cache``.

    A basis check, the re-basis that may follow it and the damping carried
    to the new basis all need the full matrices at the same point (0.35 s
    to assemble at 200k DOF); they are made once.
    """
    p = np.asarray(p, float)
    hit = model.factor_cache.get("assembled")
    if hit is not None and np.array_equal(hit[0], p):
        return hit[1], hit[2]
    model.factor_cache.pop("assembled", None)
    K, M = model.stiffness(p), model.mass(p)
    model.factor_cache["assembled"] = (p.copy(), K, M)
    return K, M


def analyze_ahead(model: FRFModel, p) -> bool:
    """Start the symbolic analysis of the first basis's factorization on a background thread.

    :func:`build_surrogate` at any point of ``model`` factorizes K + s M, whose
    pattern does not depend on p; its CHOLMOD analysis (METIS on one core,
    about 2 s at 200k DOF) can therefore run while the caller does other work
    (the campaign: the identification, which then has the other core). K(p)
    and M(p) are assembled here and kept for a basis built at the same p
    (:func:`assembled`). Nothing is started for models small enough for the
    dense path or when the sparse backend is not the ctypes CHOLMOD path
    (:func:`femodel.analyze_ahead`).

    Returns
    -------
    bool
        Whether the analysis runs (or is already cached).
    """
    if model.K.shape[0] <= DENSE_BELOW:
        return False
    K, M = assembled(model, p)
    return _analyze_pattern_ahead(_shifted(sp.csr_matrix(K), sp.csr_matrix(M), 1.0, model.factor_cache),
                                  model.factor_cache)


def build_surrogate(
    model: FRFModel,
    p,
    band_hz,
    basis_factor: float = BASIS_FACTOR,
    shift_hz: float | None = None,
    max_modes: int = 600,
    enrich: bool = True,
    enrich_tol: float = 1e-4,
    enrich_factor: float = 1.25,
    previous_basis: np.ndarray | None = None,
    rebasis: str = "iterated",
    previous_layout: tuple[int, int] | None = None,
) -> tuple[Surrogate, np.ndarray]:
    """Reduction basis at ``p`` and the exact-in-p reduced model.

    Parameters
    ----------
    model : FRFModel
    p : (n_p,) array
        Normalized parameters of the basis point.
    band_hz : (low, high)
        Calibration band in Hz; modes up to ``basis_factor * high`` enter the basis.
    basis_factor : float
        Mode cut-off as a multiple of the band top (>= 1.2 recommended).
    shift_hz : float, optional
        Static-correction / shift-invert shift (default: :func:`default_shift_hz`).
    max_modes : int
        Cap on the number of modes.
    enrich : bool
        Add parameter-derivative enrichment vectors
        (K + s M)^-1 (dK/dp_j - lambda_i dM/dp_j) phi_i for the elastic modes up to
        ``enrich_factor`` x band top and every parameter (the first-order change of those
        mode shapes), compressed by an M-weighted SVD. This keeps the fixed-basis
        surrogate accurate for local (e.g. single-plate thickness) changes.
    enrich_tol : float
        Relative singular-value cut (on M-norm squared) for the compression.
    enrich_factor : float
        Modes up to ``enrich_factor`` x band top are enriched.
    previous_basis : (n, r) ndarray, optional
        A basis from an earlier cycle. The modes at ``p`` are then obtained by
        one block inverse iteration ``(K + s M)^-1 M T`` and Rayleigh-Ritz on
        the result (one factorization, no Lanczos run). The old basis holds
        the modes plus their first-order parameter corrections, so one step
        converges the in-band modes; everything else is rebuilt as usual.
    rebasis : {"iterated", "kept", "solved"}
        What serves as the enrichment of a basis rebuilt from ``previous_basis``
        (the modes and statics are always the new point's):

        * ``"iterated"``: the inverse-iterated rest of the old basis (no
          derivative solves). It holds the new point's modes but smooths the
          old derivative vectors by one more solve, so it degrades fast away
          from its point (docs/calibration.md, basis adequacy);
        * ``"kept"``: the old basis's enrichment columns themselves, unchanged
          (first-order mode corrections at the old point; no new solves; needs
          ``previous_layout``);
        * ``"solved"``: the enrichment solves of a cold build, at ``p`` with
          the factorization the inverse iteration made (modes up to
          ``enrich_factor`` x band top, every parameter).
    previous_layout : (n_modes, n_static), optional
        Leading column groups of ``previous_basis`` (its modes, then its
        statics; the rest is its enrichment), as in its surrogate's
        ``basis_frequencies_hz`` and ``n_static``. Needed for ``rebasis="kept"``.

    Returns
    -------
    surrogate : Surrogate
    basis : (n, r) ndarray
        The M-orthonormal basis T (not kept in the surrogate, which stays small
        enough to ship to worker processes).
    """
    p = np.asarray(p, dtype=float)
    if p.shape != (model.n_params,):
        raise CalibrationError(f"expected {model.n_params} parameters, got shape {p.shape}")
    if rebasis not in ("iterated", "kept", "solved"):
        raise CalibrationError(f"rebasis must be 'iterated', 'kept' or 'solved', got {rebasis!r}")
    if rebasis == "kept" and previous_basis is not None and previous_layout is None:
        raise CalibrationError("rebasis='kept' needs previous_layout (n_modes, n_static) of the previous basis")
    low, high = float(band_hz[0]), float(band_hz[1])
    if not 0 <= low < high:
        raise CalibrationError(f"band_hz: need 0 <= low < high, got {band_hz}")
    if shift_hz is None:
        shift_hz = default_shift_hz(band_hz)
    rigid_hz = max(1e-3 * max(low, 1.0), 1e-6 * high)  # below it a mode counts as rigid (no enrichment)
    cache = model.factor_cache
    cache.pop("factor_s", None)
    cache.pop("last_solve", None)  # the previous basis point's factor: free it before the new one is made
    # the local term tables (projection, derivative loads) are built on a second core
    # while this one factors and runs Lanczos; first build only (cached on the matrices)
    from concurrent.futures import ThreadPoolExecutor

    side = ThreadPoolExecutor(max_workers=1)
    warm = side.submit(lambda: (_local_halves(model.K), _local_halves(model.M)))
    side.shutdown(wait=False)  # the task runs on; warm.result() joins it
    t0 = time.perf_counter()
    K0, M0 = assembled(model, p)
    t1 = time.perf_counter()
    carried = Mcarried = None
    B = model.inputs.toarray() if sp.issparse(model.inputs) else np.asarray(model.inputs, float)
    C = model.outputs.toarray() if sp.issparse(model.outputs) else np.asarray(model.outputs, float)
    loads = np.hstack([B, C.T])
    if previous_basis is None:
        freqs, Phi, solve = full_modes(K0, M0, basis_factor * high, shift_hz, max_modes=max_modes, cache=cache)
        MPhi = M0 @ Phi
        static = None
    else:  # statics in the same block solve as the inverse iteration
        freqs, Phi, solve, carried, MPhi, Mcarried, static = refreshed_modes(
            K0, M0, previous_basis, basis_factor * high, shift_hz, extra=loads, cache=cache)
    t2 = time.perf_counter()
    # kept for basis_residuals (the adequacy test of this basis at later points); freed by the next build
    cache["last_solve"] = (p.copy(), float((2 * np.pi * shift_hz) ** 2), solve)
    sel = np.zeros(0, dtype=int)  # the modes whose derivative loads are solved (none where the old basis serves)
    iterated = enrich and carried is not None and rebasis == "iterated"
    kept = enrich and previous_basis is not None and rebasis == "kept"
    if enrich and not iterated and not kept:
        sel = np.flatnonzero((freqs <= enrich_factor * high) & (freqs > rigid_hz))
    W = None
    if static is None and sel.size == 0:
        static = solve(loads)
    t3 = time.perf_counter()
    E = None
    if iterated:  # the inverse-iterated old basis already spans the mode corrections: keep it
        E = carried
    elif kept:
        # the old enrichment columns as they are: the first-order mode corrections at the old point
        skip = int(previous_layout[0]) + int(previous_layout[1])
        E = np.ascontiguousarray(previous_basis[:, skip:]) if previous_basis.shape[1] > skip else None
    elif sel.size:
        lam = (2 * np.pi * freqs[sel]) ** 2
        warm.result()
        # the statics (when not solved yet) lead the block: W = [statics, enrichment] comes out of one solve,
        # with no block copied on fresh pages to join them (docs/calibration.md, stop 39)
        lead = loads if static is None else np.zeros((loads.shape[0], 0))
        rhs = _derivative_loads(model, p, Phi[:, sel], lam, lead=lead)
        if rhs.shape[1] > lead.shape[1] or static is None:
            X = solve(rhs)
            del rhs  # freed for the blocks below (fresh pages are the dear part of them)
            W = X if static is None else np.hstack([static, X])
            static = W[:, :loads.shape[1]]
            del X
    t4 = time.perf_counter()
    if W is None:
        W = static if E is None else np.hstack([static, E])
    MW = np.hstack([M0 @ static, Mcarried]) if E is not None and E is carried else None
    del E, carried, Mcarried
    A = _complement_coefficients(W, Phi, MPhi, M0, [static.shape[1], W.shape[1] - static.shape[1]],
                                 [1e-10, enrich_tol], MW)
    del MW
    n_static, n_enrich = A[0].shape[1], A[1].shape[1]
    A = np.hstack(A)
    WA = W @ A
    T = np.hstack([Phi, WA - Phi @ (MPhi.T @ WA)])
    del W, WA
    t5 = time.perf_counter()
    # the loads' first moments, after the statics (the layout stays modes, statics, enrichment)
    Tm = _moment_directions(T, solve(M0 @ static), M0)
    split = Phi.shape[1] + n_static
    T = np.hstack([T[:, :split], Tm, T[:, split:]])
    n_static += Tm.shape[1]
    t6 = time.perf_counter()
    warm.result()
    with ThreadPoolExecutor(max_workers=2) as pool, _blas_threads(1):
        Kr = _projected(model.K, T, pool)
        Mr = _projected(model.M, T, pool)
    Kr, Mr, T = m_orthonormalized(Kr, Mr, T, p, "raise enrich_tol or lower basis_factor")
    t7 = time.perf_counter()
    sur = Surrogate(
        K=Kr,
        M=Mr,
        inputs=np.asarray(T.T @ B),
        outputs=np.asarray(C @ T),
        p_basis=p.copy(),
        basis_frequencies_hz=freqs,
        n_static=n_static,
        n_enrich=n_enrich,
        rigid_hz=rigid_hz,
        output_names=tuple(model.output_names),
        input_names=tuple(model.input_names),
        parameter_names=tuple(model.parameter_names),
        timings_s={"assemble": t1 - t0, "modes": t2 - t1, "factor (part of modes)": cache.get("factor_s", 0.0),
                   "statics": t3 - t2, "enrichment solves": t4 - t3,
                   "orthonormalize": t5 - t4, "moments": t6 - t5, "project": t7 - t6},
    )
    return sur, T


def default_shift_hz(band_hz) -> float:
    """The static-correction shift of a basis for ``band_hz``: band low / 4, at least band top / 50 (Hz)."""
    return max(float(band_hz[0]) / 4.0, float(band_hz[1]) / 50.0)


def basis_layout(sur: Surrogate) -> tuple[int, int]:
    """(n_modes, n_static): the leading column groups of the basis of ``sur`` (the rest is enrichment).

    The basis is [modes, statics, enrichment] made M-orthonormal group by
    group; the final congruence by a lower-triangular factor keeps every
    leading group's span.
    """
    return len(sur.basis_frequencies_hz), int(sur.n_static)


@dataclass(frozen=True)
class BasisCheck:
    """Adequacy of a fixed reduction basis at a parameter point (:func:`basis_residuals`).

    Attributes
    ----------
    p : (n_p,) the point checked
    freqs_hz : (m,) Ritz frequencies of the checked modes at ``p``
    eta : (m,) relative energy-norm residual of each (about twice its relative frequency error)
    tol : float or None, the tolerance it was judged against
    time_s : float, wall time of the check
    cpu_s : float, CPU time of the check (this process, all threads)
    exact_norm : bool
        True when the norm's factorization was made at ``p``; False when the
        one of the basis point was reused (then eta is within the ratio of
        the stiffness coefficients between the two points of its value).
    """

    p: np.ndarray
    freqs_hz: np.ndarray
    eta: np.ndarray
    tol: float | None
    time_s: float
    exact_norm: bool
    cpu_s: float = 0.0

    @property
    def eta_max(self) -> float:
        return float(self.eta.max()) if self.eta.size else 0.0

    @property
    def adequate(self) -> bool:
        return self.tol is not None and self.eta_max <= self.tol

    def describe(self) -> str:
        worst = int(np.argmax(self.eta)) if self.eta.size else None
        where = "" if worst is None else f" (mode at {self.freqs_hz[worst]:.1f} Hz)"
        verdict = "" if self.tol is None else (" <= " if self.adequate else " > ") + f"{self.tol:g}"
        return f"largest Ritz residual {self.eta_max:.2e}{where}{verdict} ({self.time_s:.1f} s)"

    def to_dict(self) -> dict:
        return {"eta_max": self.eta_max, "tol": self.tol, "adequate": self.adequate, "time_s": self.time_s,
                "cpu_s": self.cpu_s,
                "freqs_hz": self.freqs_hz.tolist(), "eta": self.eta.tolist(), "exact_norm": self.exact_norm}


def basis_residuals(model: FRFModel, sur: Surrogate, basis: np.ndarray, p, band_hz, tol: float | None = None,
                    factor: float = 1.25) -> BasisCheck:
    """How well a fixed basis still holds the modes at ``p``: energy-norm Ritz residuals of the in-band modes.

    For each elastic mode of the surrogate at ``p`` up to ``factor`` x band
    top (Ritz pair lambda, phi = T x, phi^T M phi = 1) the full-order residual
    r = K(p) phi - lambda M(p) phi is measured in the norm of (K + s M)^-1:

        eta = r^T (K + s M)^-1 r / lambda

    Rayleigh-Ritz gives Ritz values that err by second order in the basis
    error, and eta is that order: the relative error of the Ritz eigenvalue is
    about eta (the Ritz frequency about eta / 2; measured at 200k DOF with a
    cold basis at p as reference: eta 3.5e-4, 1.2e-3, 6.8e-3 gave relative
    frequency errors 1.8e-4, 6.0e-4, 3.4e-3), and the relative energy error of
    the mode shape about sqrt(eta). The Euclidean norm of r does not serve:
    it is dominated by the high-frequency content of r and reads ~1 for every
    basis. The cost is two sparse products with (n, m) blocks and m solves
    with the factorization kept from the basis build (at the basis point,
    so within the ratio of the stiffness coefficients between the two points
    of the norm at p); without a kept one, K(p) + s M(p) is factorized.

    Parameters
    ----------
    model : FRFModel (the full-order model of ``sur``)
    sur : Surrogate
    basis : (n, r) ndarray, the basis of ``sur``
    p : (n_p,) point to check
    band_hz : (low, high)
    tol : float, optional
        Judge adequate when every eta is at most this.
    factor : float
        Modes up to this multiple of the band top are checked.
    """
    t0, c0 = time.perf_counter(), time.process_time()
    p = np.asarray(p, float)
    lam, X = reduced_modes(sur, p)
    fhz = np.sqrt(np.clip(lam, 0.0, None)) / (2 * np.pi)
    sel = np.flatnonzero((fhz > sur.rigid_hz) & (fhz <= factor * float(band_hz[1])))
    K, M = assembled(model, p)
    kept = model.factor_cache.get("last_solve")
    if kept is not None:
        p_b, s, solve = kept
        exact = bool(np.array_equal(p_b, p))
    else:
        s = (2 * np.pi * default_shift_hz(band_hz)) ** 2
        if K.shape[0] <= DENSE_BELOW:
            Kd = K.toarray() if sp.issparse(K) else np.asarray(K)
            Md = M.toarray() if sp.issparse(M) else np.asarray(M)
            solve = _dense_shift_inverted(Kd, Md, s)[2]
        else:
            solve = _factor(_shifted(sp.csr_matrix(K), sp.csr_matrix(M), s, model.factor_cache), model.factor_cache)
        exact = True
    Phi = np.asarray(basis) @ X[:, sel]
    R = np.asarray(K @ Phi) - np.asarray(M @ Phi) * lam[sel][None, :]
    eta = np.einsum("ij,ij->j", R, np.asarray(solve(R))) / lam[sel] if sel.size else np.zeros(0)
    return BasisCheck(p.copy(), fhz[sel], np.abs(eta), tol, time.perf_counter() - t0, exact,
                      time.process_time() - c0)


def m_orthonormalized(Kr: AffineMatrix, Mr: AffineMatrix, T: np.ndarray, p, remedy: str):
    """Reduced terms and basis made exactly M-orthonormal at p by a congruence in reduced space.

    With M_r(p) = L L^T, the basis T L^-T and the terms L^-1 (.) L^-T; no
    n-sized work but the one product T L^-T. A reduced mass that is not
    definite means the basis is numerically dependent (``remedy`` says what to change).
    """
    try:
        L = np.linalg.cholesky(_sym(Mr.at(p)))
    except np.linalg.LinAlgError:
        raise CalibrationError(
            f"reduction basis at p={np.round(np.asarray(p, float), 4)} is numerically dependent "
            f"(reduced mass not definite); {remedy}") from None
    if np.abs(L - np.eye(L.shape[0])).max() > 1e-12:
        Li = sla.solve_triangular(L, np.eye(L.shape[0]), lower=True)
        Kr, Mr, T = _congruent(Kr, Li), _congruent(Mr, Li), T @ Li.T
    return Kr, Mr, T


def _complement_coefficients(W, Phi, MPhi, M, sizes, tols, MW=None) -> list:
    """Coefficients of M-orthonormal complements of column groups of W, from one Gram matrix.

    W = [W_1, W_2, ...] (column groups of ``sizes``). Group g is made
    M-orthogonal to Phi (M-orthonormal, ``MPhi = M Phi``) and to the groups
    before it, and cut where the eigenvalues of its Gram matrix fall below
    ``tols[g]`` times their largest. Columns keep their size, so an
    enrichment vector counts by how far its mode shape moves per unit
    parameter. (Unit-norm columns were tried at 200k DOF: 85 instead of 49
    enrichment vectors, LM twice as slow, and still three cycles.)

    Returns A_g (k, k_g) such that the complement basis is
    ``(W - Phi MPhi^T W) A_g``. All of it runs on the (k, k) Gram matrix of W
    and its (m, k) overlap with Phi: one sparse product ``M W`` (none when
    ``MW`` is given) and two GEMMs at full size, instead of repeated
    Gram-Schmidt passes over (n, k) blocks.
    """
    k = W.shape[1]
    P = MPhi.T @ W
    G = W.T @ (M @ W if MW is None else MW) - P.T @ P  # Gram of W minus its Phi part
    G = _sym(G)
    out, done = [], np.zeros((k, 0))
    start = 0
    for size, tol in zip(sizes, tols):
        idx = np.arange(start, start + size)
        start += size
        Ag = np.zeros((k, size))
        Ag[idx, np.arange(size)] = 1.0
        if size == 0:
            out.append(Ag)
            continue
        if done.shape[1]:  # remove the earlier groups (M-orthonormal in these coordinates)
            Ag = Ag - done @ (done.T @ (G @ Ag))
        Gg = Ag.T @ G @ Ag
        w, U = np.linalg.eigh(_sym(Gg))
        if w.size == 0 or w.max() <= 0:
            out.append(np.zeros((k, 0)))
            continue
        keep = w > tol * w.max()
        Ag = Ag @ (U[:, keep] / np.sqrt(w[keep]))
        out.append(Ag)
        done = np.hstack([done, Ag])
    return out


def _moment_directions(T: np.ndarray, V: np.ndarray, M, floor: float = 1e-24, tol: float = 1e-10) -> np.ndarray:
    """The M-orthonormal directions of V outside the M-orthonormal basis T, on V's own scale.

    V holds the first moments ``A^-1 M A^-1 b`` of the loads (A = K + s M):
    the dynamic part of the residual flexibility of the modes above the
    basis's cut-off, which the statics ``A^-1 b`` miss in the band. Beside
    the modes and statics their new directions are small in the M-norm (Gram
    eigenvalues ~1e-12 of a unit column at 200k DOF) but they are local
    deformations at the loaded points that the FRFs there need: they let the
    modes stop at 1.25 x band top where 2 x was needed without them
    (docs/calibration.md, stop 38). So each column is scaled to unit M-norm,
    projected off T twice at full size (not through a Gram difference, which
    would lose these directions to cancellation), and the directions are
    cut relative to their own largest Gram eigenvalue (``tol``) and below
    ``floor`` (of a unit column; what is left of a column inside T's span
    after rounding is ~1e-30). On the 1603-DOF beam of the tests the two
    directions kept have Gram eigenvalues ~1e-19 and bring the largest FRF
    log error at 1.25 x band top from 1.7e-4 to 5.0e-5 (2 x band top:
    5.3e-5); at 200k DOF all 20 are kept (largest 8.7e-13).
    """
    if V.shape[1] == 0:
        return np.zeros((T.shape[0], 0))
    MV = M @ V
    norms = np.sqrt(np.abs(np.einsum("ij,ij->j", V, MV)))
    ok = norms > 0
    Y = V[:, ok] / norms[ok][None, :]
    # the M-projection off span(T) with T's own Gram: T is M-orthonormal only to the accuracy of its modes
    MT = np.asarray(M @ T)
    G = sla.cho_factor(_sym(T.T @ MT))
    for _ in range(2):
        Y = Y - T @ sla.cho_solve(G, MT.T @ Y)
    w, U = np.linalg.eigh(_sym(Y.T @ (M @ Y)))
    if w.size == 0 or w.max() <= floor:
        return np.zeros((T.shape[0], 0))
    keep = (w > tol * w.max()) & (w > floor)
    return Y @ (U[:, keep] / np.sqrt(w[keep]))


def _congruent(A: AffineMatrix, Li: np.ndarray) -> AffineMatrix:
    """``Li A_k Li^T`` for every (dense, reduced) term of A."""
    return replace(A, matrices=tuple(_sym(Li @ np.asarray(m) @ Li.T) for m in A.matrices))


def _local_terms(A: AffineMatrix) -> list:
    """Per term: (rows, A_k[rows][:, rows]) for sparse terms, (None, A_k) for dense ones (kept in ``A.cache``).

    The terms are symmetric, so their non-zero columns are their non-zero rows
    and ``A_k T`` needs only ``T[rows]`` (contiguous, cache-friendly).
    """
    cached = A.cache.get("calibration.local_rows")
    if cached is None:
        cached = [_local_term(m) if sp.issparse(m) else (None, np.asarray(m)) for m in A.matrices]
        A.cache["calibration.local_rows"] = cached
    return cached


def _local_term(m) -> tuple:
    """(rows, m[rows][:, rows]) of a sparse term, rows = its non-zero rows and columns.

    Made with NumPy on the CSR arrays (every entry lies in a kept row and
    column, so the entries stay as they are and only the column numbers are
    renumbered) instead of scipy's fancy indexing: with :func:`_lower_half`,
    0.4 s instead of 0.8 s for the K and M terms at 200k DOF, on the thread
    that runs beside the first basis build's main-thread sparse work.
    """
    m = _canonical_csr(m)
    n = m.shape[0]
    counts = np.diff(m.indptr)
    used = counts > 0
    used[m.indices] = True
    rows = np.flatnonzero(used)
    renumber = np.full(n, -1, dtype=m.indices.dtype)
    renumber[rows] = np.arange(rows.size, dtype=m.indices.dtype)
    indptr = np.zeros(rows.size + 1, dtype=m.indptr.dtype)
    np.cumsum(counts[rows], out=indptr[1:])
    local = sp.csr_matrix((m.data, renumber[m.indices], indptr), shape=(rows.size, rows.size))
    local.has_sorted_indices = m.has_sorted_indices  # an increasing renumbering keeps the order
    return rows, local


def _derivative_loads(model: FRFModel, p, Phi: np.ndarray, lam: np.ndarray, lead=None) -> np.ndarray:
    """``(dK/dp_j - lambda_i dM/dp_j) phi_i`` for every acting parameter j and mode i: (n, n_acting * m).

    Built term by term from the local AffineMatrix terms (each touches only its
    own rows), not from full-size dK/dp_j matrices. Parameters whose
    derivative vanishes at p get no columns. ``lead`` (n, k), optional:
    columns put before them in the same (Fortran-ordered) block.
    """
    n, m = Phi.shape
    lead = np.zeros((n, 0)) if lead is None else lead
    k0 = lead.shape[1]
    dcs = [(A, scale, A.coefficient_jacobian(p)) for A, scale in ((model.K, None), (model.M, lam))]
    acting = np.flatnonzero(np.any(np.vstack([dc for _, _, dc in dcs]) != 0, axis=0))
    col = np.full(model.n_params, -1)
    col[acting] = np.arange(acting.size)
    # Fortran order, the solver's: a C-ordered (n, 136) block cost 0.2-0.7 s more to solve at 200k DOF
    # (its transposed copy, on fresh pages); columns acting-parameter-major as before: view[:, i, j]
    rhs = np.zeros((n, k0 + acting.size * m), order="F")
    rhs[:, :k0] = lead
    view = rhs[:, k0:].reshape(n, m, acting.size, order="F")
    for A, scale, dc in dcs:
        for (rows, mk), d in zip(_local_terms(A), dc):
            js = np.flatnonzero(d)
            if js.size == 0:
                continue
            Y = mk @ (Phi if rows is None else Phi[rows])  # (rows, m)
            if scale is not None:
                Y = -Y * scale[None, :]
            if rows is None:
                view += Y[:, :, None] * d[None, None, acting]
            else:
                for j in js:
                    view[rows, :, col[j]] += d[j] * Y
    return rhs


def _local_halves(A: AffineMatrix) -> list:
    """Per term: (rows, H_k) with H_k = strict lower triangle + half the diagonal of the local
    term (so A_k = H_k + H_k^T), or (None, A_k) for dense terms (kept in ``A.cache``)."""
    cached = A.cache.get("calibration.local_halves")
    if cached is None:
        cached = []
        for rows, mk in _local_terms(A):
            if rows is None:
                cached.append((None, mk))
            else:
                cached.append((rows, _lower_half(mk)))
        A.cache["calibration.local_halves"] = cached
    return cached


def _lower_half(m: sp.csr_matrix) -> sp.csr_matrix:
    """Strict lower triangle plus half the diagonal of a canonical CSR matrix (NumPy on its arrays, in
    place of scipy's ``tril`` plus ``diags``)."""
    row = np.repeat(np.arange(m.shape[0], dtype=m.indices.dtype), np.diff(m.indptr))
    keep = m.indices <= row
    data = m.data[keep]
    data[m.indices[keep] == row[keep]] *= 0.5
    indptr = np.zeros(m.shape[0] + 1, dtype=m.indptr.dtype)
    np.cumsum(np.bincount(row[keep], minlength=m.shape[0]), out=indptr[1:])
    return sp.csr_matrix((data, m.indices[keep], indptr), shape=m.shape)


def _project_term(T: np.ndarray, item) -> np.ndarray:
    rows, mk = item
    if rows is None:
        r = T.T @ (mk @ T)
        return _sym(r)
    Tr = T[rows]
    r = Tr.T @ (mk @ Tr)
    return r + r.T


def _projected(A: AffineMatrix, T: np.ndarray, pool=None) -> AffineMatrix:
    """``T^T A_k T`` for every term, touching only the rows where a (local) term is non-zero.

    Same result as :meth:`AffineMatrix.projected`, at a fraction of the cost:
    the dense product costs (rows of A_k) x r^2 instead of n x r^2 per term
    (parameter terms are local), and the sparse product uses only the lower
    half H_k of the symmetric term: ``T^T A_k T = X + X^T`` with ``X = T^T H_k T``.
    With ``pool`` (a thread pool) the terms are shared out over its threads:
    scipy's sparse products and BLAS release the GIL (run with one BLAS thread).
    """
    from functools import partial

    items = _local_halves(A)
    work = partial(_project_term, T)
    reduced = list(pool.map(work, items)) if pool is not None else [work(it) for it in items]
    return replace(A, matrices=tuple(reduced))  # same kind: series (shell shear) coefficients stay exact


def _sym(A: np.ndarray) -> np.ndarray:
    return 0.5 * (A + A.T)


# ----------------------------------------------------------------------------- reduced FRFs


def reduced_modes(sur: Surrogate, p) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues lambda (rad^2/s^2, ascending) and M_r-normalized vectors X (r, r) at p."""
    Kr = sur.K.at(p)
    Mr = sur.M.at(p)
    try:
        lam, X = sla.eigh(Kr, Mr)
    except np.linalg.LinAlgError as exc:
        raise CalibrationError(f"reduced mass matrix not positive definite at p={np.round(p, 4)}") from exc
    return lam, X


def reduced_term_stack(A: AffineMatrix) -> np.ndarray:
    """The dense reduced terms of ``A`` as one (n_terms, r, r) array (kept in ``A.cache``)."""
    stack = A.dense_stack()
    if stack is None:
        raise CalibrationError("a surrogate's terms are dense (reduced) matrices, these are sparse")
    return stack


def quantity_factor(w: np.ndarray, quantity: str) -> np.ndarray:
    """q(w) with H_quantity = q H_receptance (:func:`labdata.quantity_factor`); w in rad/s."""
    if quantity in _QUANTITIES:
        return _quantity_factor(quantity, w)
    raise CalibrationError(f"FRF quantity must be one of {_QUANTITIES}, got {quantity!r}")


def modal_omegas(lam: np.ndarray, rigid_hz: float) -> tuple[np.ndarray, np.ndarray]:
    om = np.sqrt(np.clip(lam, 0.0, None))
    rigid = om < 2 * np.pi * rigid_hz
    om = np.where(rigid, 0.0, om)
    return om, rigid


def modal_frf(
    lam: np.ndarray,
    phi_out: np.ndarray,
    phi_in: np.ndarray,
    freq_hz: np.ndarray,
    zeta,
    quantity: str = "accelerance",
    rigid_hz: float = 0.0,
) -> np.ndarray:
    """Modal-sum FRF with viscous modal damping (Eq. 2.14 diagonalized).

    Parameters
    ----------
    lam : (m,) eigenvalues omega_k^2 (rad^2/s^2)
    phi_out : (n_out, m) output participation ``C x_k``
    phi_in : (m, n_in) input participation ``x_k^T B``
    freq_hz : (n_f,) Hz
    zeta : float or (m,) damping ratio per mode
    quantity : "accelerance" | "mobility" | "receptance"

    Returns
    -------
    (n_f, n_out, n_in) complex FRF, SI (e.g. (m/s^2)/N).
    """
    w = 2 * np.pi * np.asarray(freq_hz, dtype=float)
    om, rigid = modal_omegas(lam, rigid_hz)
    zeta = np.broadcast_to(np.asarray(zeta, dtype=float), om.shape)
    c = np.where(rigid, 0.0, 2 * zeta * om)
    lam_c = np.where(rigid, 0.0, om**2)
    r = 1.0 / (lam_c[None, :] - w[:, None] ** 2 + 1j * w[:, None] * c[None, :])  # (n_f, m)
    q = quantity_factor(w, quantity)
    H = np.einsum("om,fm,mi->foi", phi_out, r * q[:, None], phi_in, optimize=True)
    return H


def surrogate_frf(
    sur: Surrogate,
    p,
    freq_hz,
    zeta=0.01,
    quantity: str = "accelerance",
    outputs=None,
    modes=None,
) -> np.ndarray:
    """FRF of the surrogate at p: (n_f, n_out, n_in) complex.

    Parameters
    ----------
    zeta : float or (r,) array
        Damping ratio of every reduced mode (ascending frequency order).
    outputs : index array, optional
        Rows of ``sur.outputs`` to evaluate (default all).
    modes : (lam, X), optional
        :func:`reduced_modes` at p when the caller has them already.
    """
    lam, X = reduced_modes(sur, p) if modes is None else modes
    Co = sur.outputs if outputs is None else sur.outputs[np.asarray(outputs)]
    return modal_frf(lam, Co @ X, X.T @ sur.inputs, freq_hz, zeta, quantity, sur.rigid_hz)


def full_order_frf(model: FRFModel, p, freq_hz, zeta=0.01, quantity="accelerance") -> np.ndarray:
    """Reference FRF of the full model with Eq. 2.14 damping from *all* its modes (dense; small models only)."""
    n = model.K.shape[0]
    if n > 4000:
        raise CalibrationError(f"full_order_frf is a dense reference for small models; model has {n} DOF")
    K = model.K.at(p)
    M = model.M.at(p)
    K = K.toarray() if sp.issparse(K) else np.asarray(K)
    M = M.toarray() if sp.issparse(M) else np.asarray(M)
    f = np.asarray(freq_hz, float)
    lam, X, _ = _dense_shift_inverted(K, M, (2 * np.pi * max(0.25 * f.min(), 1.0)) ** 2)  # M may be singular
    B = model.inputs.toarray() if sp.issparse(model.inputs) else np.asarray(model.inputs, float)
    C = model.outputs.toarray() if sp.issparse(model.outputs) else np.asarray(model.outputs, float)
    return modal_frf(lam, C @ X, X.T @ B, f, zeta, quantity, rigid_hz=1e-3 * max(f.min(), 1.0))
