"""One sparse factorization interface for symmetric positive definite matrices.

Every shift-invert and static solve of frfcal (``normal_modes``, the
calibration surrogate's basis) factorizes K - sigma M (or K + s M) through
:func:`factorize`.  Backends (``backend="auto"`` tries cholmod, cholespy, superlu):

``cholmod``
    The system's CHOLMOD (supernodal Cholesky, METIS ordering, the system
    BLAS), called through ctypes where its library loads and its structures
    are the expected ones (:mod:`femodel._cholmod`: the GIL released, wide
    solves split over the cores, the analysis can run ahead,
    :func:`analyze_ahead`), else through scikit-sparse (which needs SuiteSparse
    headers to build, Debian ``libsuitesparse-dev``); the only backend whose
    symbolic analysis is reused across factorizations of the same pattern
    (``cache``).
``cholespy``
    CHOLMOD bundled in the cholespy wheel (Linux x86-64, macOS, Windows); its wheel
    links the reference BLAS, so it is slower than the system's.  Its extension
    exports CHOLMOD's API, which :mod:`femodel._cholmod` calls through ctypes
    where the structures check out (the analysis then kept in ``cache`` and
    run ahead, the GIL released, wide solves split over the cores); else
    cholespy's own interface.
``pardiso``
    Intel MKL PARDISO through pypardiso (pip wheels for Linux/x86-64 and
    Windows: ``pip install 'frfcal[pardiso]'``, ~1 GB with MKL); real symmetric positive definite
    mode on the upper triangle.  Only when named: its solves at the ill-conditioned
    shifts of free-free models are not accurate enough for Lanczos (docs/femodel.md).
``superlu``
    SciPy's SuperLU, always present: LU with MMD on A^T + A and diagonal
    pivoting (no row exchanges for a definite matrix, so the ordering holds).

The environment variable ``FRFCAL_SPARSE_BACKEND`` (``auto``, ``cholmod``,
``pardiso``, ``cholespy`` or ``superlu``) fixes what ``backend="auto"``
means, e.g. ``FRFCAL_SPARSE_BACKEND=superlu`` runs everything on the SciPy-only
path with the fast backends installed.  An explicit ``backend=`` argument
wins over the variable.
"""

from __future__ import annotations

import functools
import os
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.sparse as sp

from femodel._model import ModelError

#: Environment variable naming the backend ``backend="auto"`` uses.
ENV_VAR = "FRFCAL_SPARSE_BACKEND"
#: Every backend, in the order ``available_backends`` lists them.
PREFERENCE = ("cholmod", "cholespy", "pardiso", "superlu")
#: The backends ``auto`` tries, in order.  pardiso is left out: on the free-free 200k-DOF
#: subframe at the -1 Hz shift its solves are not reproducible (threads) and ~2e-7
#: unsymmetric, and 30 modes came out up to 6e-4 off (others: 1e-10); see docs/femodel.md.
AUTO = ("cholmod", "cholespy", "superlu")


class FactorizationError(ModelError):
    """The matrix could not be factorized (singular, or not positive definite for a Cholesky backend)."""


class NotPositiveDefiniteError(FactorizationError):
    """A Cholesky backend found a non-positive pivot."""


@dataclass(frozen=True)
class BackendInfo:
    """What :func:`available_backends` reports about one backend.

    Attributes
    ----------
    name : str
        ``cholmod``, ``pardiso``, ``cholespy`` or ``superlu``.
    available : bool
        Importable (and, for pardiso, its MKL library loads).
    detail : str
        Package and version, or why it is unavailable and how to install it.
    symbolic_reuse : bool
        Whether a ``cache`` keeps the symbolic analysis between factorizations.
    """

    name: str
    available: bool
    detail: str
    symbolic_reuse: bool = False


@dataclass(frozen=True)
class Factorization:
    """A factorization of an (n, n) SPD matrix A, callable as ``solve(F)``.

    Attributes
    ----------
    solve : callable
        ``solve(F)`` returns A^-1 F for F of shape (n,) or (n, k), as a
        C-contiguous float64 array of F's shape.
    backend : str
        The backend that factorized A.
    factor_time_s : float
        Wall time of the factorization (symbolic + numeric), s.
    symbolic_reused : bool
        True when the symbolic analysis came from ``cache``.
    """

    solve: Callable[[np.ndarray], np.ndarray]
    backend: str
    factor_time_s: float
    symbolic_reused: bool = False

    def __call__(self, F) -> np.ndarray:
        return self.solve(F)


def _version(dist: str) -> str | None:
    from importlib import metadata

    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


def _probe(name: str) -> BackendInfo:
    if name == "superlu":
        import scipy

        return BackendInfo("superlu", True, f"scipy {scipy.__version__} SuperLU (always available)")
    if name == "cholmod":
        from femodel import _cholmod as direct

        if direct.available():
            return BackendInfo("cholmod", True, direct.DETAIL, True)
        try:
            import sksparse.cholmod  # noqa: F401
        except ImportError as exc:
            return BackendInfo("cholmod", False, f"scikit-sparse not importable ({exc}); it builds against "
                               "SuiteSparse headers: apt-get install libsuitesparse-dev, then "
                               "pip install 'frfcal[cholmod]'", True)
        return BackendInfo("cholmod", True, f"scikit-sparse {_version('scikit-sparse')} (CHOLMOD, system BLAS)", True)
    if name == "pardiso":
        try:
            _pardiso_solver_class()
        except ImportError as exc:
            return BackendInfo("pardiso", False, f"pypardiso/MKL not usable ({exc}): pip install 'frfcal[pardiso]'")
        return BackendInfo("pardiso", True, f"pypardiso {_version('pypardiso')} (MKL {_version('mkl')} PARDISO)")
    if name == "cholespy":
        try:
            import cholespy  # noqa: F401
        except ImportError as exc:
            return BackendInfo("cholespy", False, f"cholespy not importable ({exc}): pip install 'frfcal[fast]'")
        from femodel import _cholmod as direct

        lib, detail = direct.bundled()
        if lib is not None:
            return BackendInfo("cholespy", True, f"cholespy {_version('cholespy')}: {detail}, reference BLAS", True)
        return BackendInfo("cholespy", True, f"cholespy {_version('cholespy')} (bundled CHOLMOD, reference BLAS)")
    raise FactorizationError(f"unknown sparse backend {name!r}; choose one of {', '.join(('auto',) + PREFERENCE)}")


@functools.lru_cache(maxsize=1)
def _pardiso_solver_class():
    """pypardiso's solver class once its MKL runtime is known to load (ImportError otherwise)."""
    from pypardiso import PyPardisoSolver

    PyPardisoSolver(mtype=2)  # loads mkl_rt: ImportError when pip's mkl wheel is missing
    return PyPardisoSolver


def available_backends() -> tuple[BackendInfo, ...]:
    """Every backend in order of preference, with whether it is usable here."""
    return tuple(_probe(name) for name in PREFERENCE)


def default_backend() -> str:
    """The backend ``backend="auto"`` uses: ``FRFCAL_SPARSE_BACKEND`` if set, else the first available of :data:`AUTO`.

    Raises
    ------
    FactorizationError
        The variable names an unknown backend or one that is not installed.
    """
    forced = os.environ.get(ENV_VAR, "").strip().lower()
    if forced and forced != "auto":
        info = _probe(forced)
        if not info.available:
            raise FactorizationError(f"{ENV_VAR}={forced}: {info.detail}")
        return forced
    for name in AUTO:
        if _probe(name).available:
            return name
    return "superlu"


def _as_csc(A) -> sp.csc_matrix:
    A = sp.csc_matrix(A, dtype=float)
    if A.shape[0] != A.shape[1]:
        raise FactorizationError(f"factorize needs a square matrix, got {A.shape}")
    if not A.has_canonical_format:
        A = A.copy()
        A.sum_duplicates()
    return A


def _contiguous(F) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(F, dtype=float))


def _pattern_hit(cache: dict | None, key: str, A: sp.csc_matrix):
    """``cache[key]`` = (indptr, indices, analysis) when it was made for A's pattern, else None."""
    hit = None if cache is None else cache.get(key)
    if hit is not None and np.array_equal(hit[0], A.indptr) and np.array_equal(hit[1], A.indices):
        return hit
    return None


def _direct_library(name: str):
    """(True, library) when backend ``name`` runs through :mod:`femodel._cholmod` (library None: the
    system's CHOLMOD; cholespy's bundled one for ``cholespy``), else (False, None)."""
    from femodel import _cholmod as direct

    if name == "cholmod":
        return direct.available(), None
    if name == "cholespy":
        lib = direct.bundled()[0]
        return lib is not None, lib
    return False, None


def _cholmod(A: sp.csc_matrix, cache: dict | None):
    from femodel import _cholmod as direct

    if _direct_library("cholmod")[0]:
        try:
            return _cholmod_direct(A, cache, direct, None, "cholmod")
        except direct.NotPositiveDefinite as exc:
            raise NotPositiveDefiniteError(f"CHOLMOD: {exc}") from None
        except direct.CholmodError as exc:
            if not _sksparse_importable():
                raise FactorizationError(f"CHOLMOD: {exc}") from None
            # e.g. a factor too large for CHOLMOD's int indices: scikit-sparse's call, as before this path
    return _cholmod_sksparse(A, cache)


def _sksparse_importable() -> bool:
    try:
        import sksparse.cholmod  # noqa: F401
    except ImportError:
        return False
    return True


def _cholmod_direct(A: sp.csc_matrix, cache: dict | None, direct, lib, key: str):
    """CHOLMOD through ctypes (:mod:`femodel._cholmod`; ``lib`` None: the system's library): the GIL released,
    wide solves split over the cores. ``cache[key]`` holds the analysis (one key per library: a factor
    belongs to the library that made it)."""
    symbolic, reused = None, False
    hit = _pattern_hit(cache, key, A)
    if hit is not None:
        symbolic = hit[2]
        if isinstance(symbolic, Future):  # analysed ahead (analyze_ahead): wait for it
            try:
                symbolic = symbolic.result()
            except direct.CholmodError:
                symbolic = None
            if cache is not None and symbolic is not None:
                cache[key] = (hit[0], hit[1], symbolic)
        if not isinstance(symbolic, direct.Symbolic):
            symbolic = None
        reused = symbolic is not None
    if symbolic is None:
        symbolic = direct.Symbolic(A.indptr, A.indices, A.shape[0], lib)
        if cache is not None:
            cache[key] = (A.indptr.copy(), A.indices.copy(), symbolic)
    return symbolic.factor(A).solve, reused


def analyze_ahead(A, cache: dict) -> bool:
    """Start CHOLMOD's symbolic analysis of A's pattern on a background thread.

    A later :func:`factorize` of a matrix with this pattern and the same
    ``cache`` waits for it and does only the numeric factorization. The
    analysis (METIS, one core: about 2 s at 200k DOF) runs with the GIL
    released, so the caller's next work (e.g. the campaign's identification)
    runs beside it. Only with a CHOLMOD called through ctypes
    (:mod:`femodel._cholmod`: the system's when ``backend="auto"`` means
    cholmod, cholespy's bundled one when it means cholespy); otherwise nothing
    is started.

    Parameters
    ----------
    A : (n, n) sparse
        The matrix, or any matrix of its pattern (values are not read).
    cache : dict
        The cache later passed to :func:`factorize`.

    Returns
    -------
    bool
        Whether an analysis was started (or one of this pattern is already cached).
    """
    from femodel import _cholmod as direct

    try:
        name = default_backend()
    except FactorizationError:
        return False
    usable, lib = _direct_library(name)
    if not usable:
        return False
    A = _as_csc(A)
    if _pattern_hit(cache, name, A) is not None:
        return True
    indptr, indices, n = A.indptr.copy(), A.indices.copy(), A.shape[0]
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="frfcal-analyze")
    future = pool.submit(direct.Symbolic, indptr, indices, n, lib)
    pool.shutdown(wait=False)
    cache[name] = (indptr, indices, future)
    return True


def _cholmod_sksparse(A: sp.csc_matrix, cache: dict | None):
    from sksparse.cholmod import CholmodNotPositiveDefiniteError, analyze

    symbolic, reused = None, False
    hit = _pattern_hit(cache, "cholmod", A)
    if hit is not None and hasattr(hit[2], "cholesky"):
        symbolic, reused = hit[2], True
    if symbolic is None:
        # supernodal LL^T always: CHOLMOD's "auto" mode takes a simplicial LDL^T for small
        # matrices, which factorizes indefinite ones without complaint (negative D).
        # Ordering: CHOLMOD's default (AMD and METIS tried, the lesser fill kept).
        symbolic = analyze(A, mode="supernodal")
        if cache is not None:
            cache["cholmod"] = (A.indptr.copy(), A.indices.copy(), symbolic)
    try:
        f = symbolic.cholesky(A)  # numeric factorization on the (stored) analysis
    except CholmodNotPositiveDefiniteError as exc:
        raise NotPositiveDefiniteError(f"CHOLMOD: {exc}") from None
    # C order out: the results meet CSR @ dense products, which would copy F-ordered operands each time
    return (lambda F: np.ascontiguousarray(f(np.asfortranarray(F, dtype=float)))), reused


def _pardiso(A: sp.csc_matrix):
    cls = _pardiso_solver_class()
    solver = cls(mtype=2)  # real symmetric positive definite: PARDISO reads the upper triangle (CSR)
    U = sp.triu(A, format="csr")
    U.sort_indices()
    try:
        solver.factorize(U)
    except Exception as exc:  # noqa: BLE001 - pypardiso raises its PyPardisoError with MKL's code
        code = getattr(exc, "value", None)
        if code == -4:
            raise NotPositiveDefiniteError(f"PARDISO: zero or negative pivot ({exc})") from None
        raise FactorizationError(f"PARDISO factorization failed: {exc}") from None

    def solve(F):
        F = np.asarray(F, dtype=float)
        return np.ascontiguousarray(solver.solve(U, F))

    return solve


def _cholespy(A: sp.csc_matrix, cache: dict | None = None):
    from femodel import _cholmod as direct

    usable, lib = _direct_library("cholespy")
    if usable:  # its CHOLMOD through ctypes: the analysis kept in ``cache``, the GIL released
        try:
            return _cholmod_direct(A, cache, direct, lib, "cholespy")
        except direct.NotPositiveDefinite as exc:
            raise NotPositiveDefiniteError(f"cholespy's CHOLMOD: {exc}") from None
        except direct.CholmodError:
            pass  # cholespy's own interface, as before this path
    return _cholespy_own(A), False


def _cholespy_own(A: sp.csc_matrix):
    from cholespy import CholeskySolverD, MatrixType

    n = A.shape[0]
    # the lower triangle is what CHOLMOD reads (stype -1); passing it alone halves the copy
    L = sp.tril(A, format="csc")
    L.sort_indices()
    try:
        solver = CholeskySolverD(n, L.indptr.astype(np.int32), L.indices.astype(np.int32),
                                 np.ascontiguousarray(L.data), MatrixType.CSC)
    except (RuntimeError, ValueError) as exc:
        raise NotPositiveDefiniteError(f"cholespy: {exc}") from None

    def solve(F):
        b = _contiguous(F)
        x = np.empty_like(b)
        solver.solve(b, x)
        return x

    return solve


def _superlu(A: sp.csc_matrix):
    import scipy.sparse.linalg as spla

    # diag_pivot_thresh=0: take the diagonal pivot whenever it is nonzero.  With SuperLU's
    # default (1.0) a definite matrix with a wide spread of diagonal entries (in-lbf-s
    # shell models next to stiff RBE2/MPC rows) gets row exchanges that wreck the
    # symmetric ordering: the 51k-DOF bwb model grew to 8.6 GB and did not finish in 39 min.
    try:
        lu = spla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                       options={"SymmetricMode": True})
    except RuntimeError as exc:
        raise FactorizationError(f"SuperLU: the matrix is singular ({exc})") from None
    return lambda F: np.ascontiguousarray(lu.solve(np.asarray(F, dtype=float)))


def factorize(A, *, backend: str = "auto", cache: dict | None = None) -> Factorization:
    """Factorize a sparse symmetric positive definite matrix.

    Parameters
    ----------
    A : (n, n) sparse or dense, float
        Symmetric positive definite (both triangles stored).
    backend : {"auto", "cholmod", "pardiso", "cholespy", "superlu"}
        ``auto``: ``FRFCAL_SPARSE_BACKEND`` if set, else the first available in
        :data:`AUTO`; if that Cholesky backend finds A not positive
        definite, SuperLU (which factorizes any nonsingular matrix) is used.
        A named backend raises instead.
    cache : dict, optional
        Caller-owned store for the symbolic analysis (fill-reducing ordering,
        supernodes) of the last pattern seen; a later call on a matrix with
        the same pattern does only the numeric factorization.  Used by the
        ``cholmod`` backend and by ``cholespy`` through ctypes (the others
        ignore it).

    Returns
    -------
    Factorization
        Callable: ``fac(F)`` = A^-1 F for F of shape (n,) or (n, k).

    Raises
    ------
    NotPositiveDefiniteError
        A named Cholesky backend found a non-positive pivot.
    FactorizationError
        A is not square, singular, or the backend is unknown or not installed.
    """
    name = default_backend() if backend == "auto" else backend
    info = _probe(name)
    if not info.available:
        raise FactorizationError(f"sparse backend {name!r} is not available: {info.detail}")
    A = _as_csc(A)
    t0 = time.perf_counter()
    reused = False
    try:
        if name == "cholmod":
            solve, reused = _cholmod(A, cache)
        elif name == "pardiso":
            solve = _pardiso(A)
        elif name == "cholespy":
            solve, reused = _cholespy(A, cache)
        else:
            solve = _superlu(A)
    except NotPositiveDefiniteError:
        if backend != "auto":
            raise
        name, solve = "superlu", _superlu(A)
    return Factorization(solve=solve, backend=name, factor_time_s=time.perf_counter() - t0, symbolic_reused=reused)
