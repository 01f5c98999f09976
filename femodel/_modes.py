"""Lowest normal modes by shift-invert Lanczos on a sparse Cholesky (or LU) factorization (femodel._factor)."""

from __future__ import annotations

import os
import time
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from femodel._dofs import DofMap
from femodel._factor import PREFERENCE, FactorizationError, NotPositiveDefiniteError, factorize
from femodel._model import ModelError


def start_vector(n: int) -> np.ndarray:
    """The Lanczos start vector of every ARPACK call in frfcal: fixed pseudo-random (seeded by ``n``).

    ARPACK's own default is a random start, so two runs of the same solve differed in the last digits
    (1e-9 relative in frequencies) and everything downstream (layouts, fingerprints, calibrations) was
    not reproducible bit for bit. A seeded normal vector has, with probability one, a component along
    every eigenvector, as the random one has.
    """
    return np.random.default_rng(n).standard_normal(n)

#: Below this frequency a mode counts as a rigid-body mode (Hz).
RIGID_TOL_HZ = 1e-2
#: Dense generalized eigensolver below this many DOF.
DENSE_MAX_DOF = 600


@dataclass(frozen=True)
class Modes:
    """Normal modes.

    Attributes
    ----------
    frequencies_hz : (n_modes,) float
        Natural frequencies, Hz, ascending; a tiny negative eigenvalue from
        round-off appears as a negative frequency.
    shapes : (n_dof, n_modes) float
        Mass-normalized mode shapes (phi^T M phi = I).
    n_rigid : int
        Modes below ``rigid_tol_hz`` (rigid-body modes).
    generalized_mass : (n_modes,) float
        diag(phi^T M phi) of the returned shapes (1 up to round-off).
    solver : str
        Which eigensolver and factorization ran.
    shift_hz : float
        The (negative for "below zero") shift used.
    factor_time_s, solve_time_s : float
        Wall time of the factorization and of the Lanczos iteration.
    n_threads : int or None
        BLAS/OpenMP thread limit in force (None: not limited).
    dofs : DofMap or None
        Row labels of ``shapes`` when known.
    """

    frequencies_hz: np.ndarray
    shapes: np.ndarray
    n_rigid: int
    generalized_mass: np.ndarray
    solver: str
    shift_hz: float = 0.0
    factor_time_s: float = 0.0
    solve_time_s: float = 0.0
    n_threads: int | None = None
    rigid_tol_hz: float = RIGID_TOL_HZ
    dofs: DofMap | None = None

    @property
    def n_modes(self) -> int:
        return int(self.frequencies_hz.shape[0])

    @property
    def omega(self) -> np.ndarray:
        """Circular frequencies, rad/s."""
        return 2 * np.pi * self.frequencies_hz


@contextmanager
def _limit_threads(n):
    if n is None:
        yield None
        return
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        yield None
        return
    with threadpool_limits(limits=int(n)):
        yield int(n)


_SOLVER_LABEL = {
    "cholmod": "CHOLMOD Cholesky (scikit-sparse)",
    "pardiso": "MKL PARDISO Cholesky (pypardiso)",
    "cholespy": "CHOLMOD Cholesky (cholespy)",
    "superlu": "SuperLU MMD_AT_PLUS_A",
}


def _solver_label(backend: str) -> str:
    """The factorization named in ``Modes.solver``: which CHOLMOD binding for ``cholmod``."""
    from femodel._factor import _direct_library

    if _direct_library(backend)[0]:
        return {"cholmod": "CHOLMOD Cholesky (system library through ctypes)",
                "cholespy": "CHOLMOD Cholesky (cholespy's bundled library through ctypes)"}[backend]
    return _SOLVER_LABEL[backend]


def _factorize(A: sp.csc_matrix, solver: str):
    """Return (solve(b), backend name) for K - sigma M; see :func:`femodel._factor.factorize`."""
    if solver not in ("auto",) + PREFERENCE:
        raise ModelError(f"unknown solver {solver!r}; choose 'auto', 'dense' or one of {', '.join(PREFERENCE)}")
    try:
        fac = factorize(A, backend=solver)
    except NotPositiveDefiniteError:
        raise ModelError("K - shift*M is not positive definite: choose a shift below the lowest eigenvalue") from None
    except FactorizationError as exc:
        raise ModelError(f"K - shift*M cannot be factorized: {exc}; a DOF has neither stiffness nor mass, "
                         "or the shift is an eigenvalue") from None
    return fac.solve, fac.backend


def normal_modes(K, M, n_modes: int, *, shift_hz=None, solver: str = "auto", n_threads: int | None = 2,
                 rigid_tol_hz: float = RIGID_TOL_HZ, tol: float = 1e-8, dofs: DofMap | None = None) -> Modes:
    """Lowest ``n_modes`` of K phi = w^2 M phi.

    Shift-invert Lanczos (ARPACK through scipy's ``eigsh`` in mode "normal")
    with our own factorization of K - sigma M (:func:`femodel._factor.factorize`:
    CHOLMOD, PARDISO or cholespy when installed, else SuperLU; environment
    variable ``FRFCAL_SPARSE_BACKEND`` overrides "auto").  Small problems
    (<= 600 DOF) use a dense generalized eigensolver.

    Parameters
    ----------
    K, M : (n, n) sparse or dense
        Symmetric stiffness (positive semi-definite) and mass (semi-definite;
        massless DOF are fine).
    n_modes : int
    shift_hz : float, optional
        Shift frequency f; sigma = sign(f) (2 pi f)^2, so a negative value
        shifts below zero.  Default -1 Hz: slightly below zero so that
        free-free models factorize (the Cholesky path needs sigma < 0).
    solver : {"auto", "cholmod", "pardiso", "cholespy", "superlu", "dense"}
        Factorization backend; "auto" is the first available (or the one
        ``FRFCAL_SPARSE_BACKEND`` names) and falls back to SuperLU when K -
        sigma M is not positive definite.
    n_threads : int or None
        BLAS/OpenMP thread limit for the factorization (threadpoolctl); the
        Lanczos iteration itself runs on one thread.  None leaves the
        libraries alone.  Default 2 (this machine's cores).
    rigid_tol_hz : float
        Modes below this frequency count as rigid-body modes.
    tol : float
        ARPACK relative tolerance on the Ritz values of the shift-inverted
        operator. The default 1e-8 gives frequencies to ~1e-9 relative (vs
        1e-10: 20 % fewer solves; at 200k DOF, 30 modes, Lanczos 8.0 s instead
        of 10.0 s with the same frequencies to 1e-11).
    dofs : DofMap, optional
        Row labels carried into the result.

    Returns
    -------
    Modes
    """
    import scipy.sparse.linalg as spla

    K = sp.csc_matrix(K, dtype=float)
    M = sp.csc_matrix(M, dtype=float)
    n = K.shape[0]
    if K.shape != (n, n) or M.shape != (n, n):
        raise ModelError(f"K {K.shape} and M {M.shape} must be square and of equal size")
    if n_modes < 1:
        raise ModelError(f"n_modes must be >= 1, got {n_modes}")
    shift = -1.0 if shift_hz is None else float(shift_hz)
    sigma = np.sign(shift) * (2 * np.pi * shift) ** 2
    k = min(int(n_modes), n)
    with _limit_threads(n_threads) as nt:
        t0 = time.perf_counter()
        if solver == "dense" or n <= DENSE_MAX_DOF or k >= n - 1:
            import scipy.linalg as sl

            A = (K - sigma * M).toarray()
            Md = M.toarray()
            try:
                # mu = 1/(lambda - sigma); K - sigma M positive definite for sigma < 0
                mu, vec = sl.eigh(Md, A)
                t1 = time.perf_counter()
                order = np.argsort(-mu)
                mu, vec = mu[order], vec[:, order]
                top = np.abs(mu).max() if mu.size else 0.0
                finite = mu > 1e-13 * top if top > 0 else np.zeros(mu.shape, bool)
                mu, vec = mu[finite][:k], vec[:, finite][:, :k]
                name = "dense generalized eigh (shift-inverted)"
            except np.linalg.LinAlgError:
                # K - sigma M indefinite (round-off in single-precision input): QZ on (K, M)
                lam_all, vec = sl.eig(K.toarray(), Md)
                t1 = time.perf_counter()
                fin = np.isfinite(lam_all)
                top = np.abs(lam_all[fin].real).max() if np.any(fin) else 0.0
                ok = fin & (np.abs(lam_all.imag) <= 1e-8 * max(top, 1e-300))
                lam_all, vec = lam_all.real[ok], vec[:, ok].real
                order = np.argsort(lam_all)[:k]
                mu = 1.0 / (lam_all[order] - sigma)
                vec = vec[:, order]
                name = "dense generalized QZ (scipy.linalg.eig)"
            lam = sigma + 1.0 / mu
            t2 = time.perf_counter()
        else:
            t0 = time.perf_counter()
            A = (K - sigma * M).tocsc()
            solve, fname = _factorize(A, solver)
            t1 = time.perf_counter()
            op = spla.LinearOperator((n, n), matvec=lambda b: solve(np.asarray(b, dtype=float)), dtype=float)
            ncv = min(n, max(2 * k + 1, k + 20))
            # The Lanczos phase is vector work and single-RHS triangular solves:
            # extra BLAS threads only spin (measured here: 27k DOF, 30 modes,
            # 12-17 s with 2 threads vs 1.8 s with 1), so it runs on one thread.
            with _limit_threads(1 if n_threads is not None else None):
                lam, vec = spla.eigsh(K, k=k, M=M, sigma=sigma, which="LM", OPinv=op, mode="normal", ncv=ncv, tol=tol,
                                      v0=start_vector(n))
            t2 = time.perf_counter()
            name = f"shift-invert Lanczos (ARPACK) with {_solver_label(fname)}"
    order = np.argsort(lam)
    lam, vec = lam[order], vec[:, order]
    gm = np.einsum("ij,ij->j", vec, M @ vec)
    bad = gm <= 0
    if np.any(bad):
        raise ModelError("a computed mode has zero generalized mass (massless mechanism)")
    vec = vec / np.sqrt(gm)[None, :]
    freqs = np.sign(lam) * np.sqrt(np.abs(lam)) / (2 * np.pi)
    if np.any(freqs < -rigid_tol_hz):
        bad = freqs[freqs < -rigid_tol_hz]
        raise ModelError(
            f"negative eigenvalues (frequencies {np.round(bad[:3], 4).tolist()} Hz): K is not positive "
            "semi-definite on the DOF that carry mass (single-precision or inconsistent matrices, or a "
            "mechanism without mass); constrain the model or check the matrices"
        )
    gm2 = np.einsum("ij,ij->j", vec, M @ vec)
    return Modes(
        frequencies_hz=freqs,
        shapes=vec,
        n_rigid=int(np.sum(np.abs(freqs) < rigid_tol_hz)),
        generalized_mass=gm2,
        solver=name,
        shift_hz=shift,
        factor_time_s=t1 - t0,
        solve_time_s=t2 - t1,
        n_threads=nt,
        rigid_tol_hz=rigid_tol_hz,
        dofs=dofs,
    )


def solve_modes(model_or_assembly, n_modes: int, **kwargs) -> Modes:
    """Modes of an FEModel or Assembly on its independent DOF (``Modes.dofs`` = a-set).

    Keyword arguments go to :func:`normal_modes`.  Expand shapes to the g-set
    with ``assembly.expand(modes.shapes)``.
    """
    from femodel._assembly import Assembly, assemble
    from femodel._model import FEModel

    if isinstance(model_or_assembly, FEModel):
        asm = assemble(model_or_assembly)
    elif isinstance(model_or_assembly, Assembly):
        asm = model_or_assembly
    else:
        raise ModelError(f"solve_modes needs an FEModel or Assembly, got {type(model_or_assembly).__name__}")
    kwargs.setdefault("dofs", asm.aset)
    return normal_modes(asm.stiffness(), asm.mass(), n_modes, **kwargs)


def default_threads() -> int:
    """Thread limit used by the CLI: the machine's cores, at most 4."""
    return max(1, min(4, os.cpu_count() or 1))
