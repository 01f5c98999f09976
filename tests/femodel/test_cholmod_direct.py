"""CHOLMOD through ctypes (femodel._cholmod): the same solutions as SuperLU, split solves equal to whole ones,
pivots and layouts checked, the analysis run ahead and reused, the GIL released."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import scipy.sparse as sp

from femodel import NotPositiveDefiniteError, analyze_ahead, factorize
from femodel import _cholmod as direct
from femodel._factor import ENV_VAR

SYSTEM = pytest.mark.skipif(not direct.available(), reason=f"the system's CHOLMOD not usable: {direct.DETAIL}")
LIBRARIES = [pytest.param(None, marks=SYSTEM, id="system"),
             pytest.param("bundled", marks=pytest.mark.skipif(direct.bundled()[0] is None,
                                                              reason=f"cholespy's CHOLMOD: {direct.bundled()[1]}"),
                          id="cholespy")]


def _lib(which):
    return None if which is None else direct.bundled()[0]


def _plate(n=60, shift=1e-3):
    """2-D 5-point Laplacian + shift I (SPD, n^2 unknowns)."""
    T = sp.diags([2.0 * np.ones(n), -np.ones(n - 1), -np.ones(n - 1)], [0, -1, 1])
    eye = sp.identity(n)
    return (sp.kron(T, eye) + sp.kron(eye, T) + shift * sp.identity(n * n)).tocsc()


@pytest.mark.parametrize("which", LIBRARIES)
def test_direct_solves_match_superlu_whole_and_split(which, monkeypatch):
    A = _plate()
    n = A.shape[0]
    rng = np.random.default_rng(5)
    X = rng.standard_normal((n, 40))
    B = np.ascontiguousarray(A @ X)
    sym = direct.Symbolic(A.indptr, A.indices, n, _lib(which))
    num = sym.factor(A)
    ref = factorize(A, backend="superlu")(B)
    monkeypatch.setenv("FRFCAL_THREADS", "1")  # one block
    whole = num.solve(B)
    monkeypatch.setenv("FRFCAL_THREADS", "3")  # three blocks of 13-14 columns on three threads
    split = num.solve(B)
    assert whole.flags.c_contiguous and split.shape == (n, 40)
    np.testing.assert_allclose(whole, X, rtol=0, atol=1e-9)
    np.testing.assert_allclose(split, whole, rtol=0, atol=1e-12 * np.abs(whole).max())
    np.testing.assert_allclose(whole, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    x0 = num.solve(B[:, 0])
    assert x0.shape == (n,)
    np.testing.assert_allclose(x0, whole[:, 0], rtol=0, atol=1e-12 * np.abs(whole).max())
    assert num.solve(np.zeros((n, 0))).shape == (n, 0)
    with pytest.raises(ValueError, match=f"order {n}"):
        num.solve(np.ones(n - 1))


@pytest.mark.parametrize("which", LIBRARIES)
def test_a_non_positive_pivot_is_named_and_auto_falls_back_to_superlu(which, monkeypatch):
    monkeypatch.delenv(ENV_VAR, raising=False)
    A = _plate(20).tolil()
    A[7, 7] = -5.0  # indefinite
    A = A.tocsc()
    with pytest.raises(NotPositiveDefiniteError, match="not positive definite"):
        factorize(A, backend="cholmod" if which is None else "cholespy")
    fac = factorize(A)  # auto: LU instead
    assert fac.backend == "superlu"


@pytest.mark.parametrize("which", LIBRARIES)
def test_the_analysis_run_ahead_is_reused_by_factorize(which, monkeypatch):
    backend = "cholmod" if which is None else "cholespy"
    monkeypatch.setenv(ENV_VAR, backend)
    A = _plate(80)
    cache: dict = {}
    assert analyze_ahead(A, cache)
    assert not isinstance(cache[backend][2], direct.Symbolic)  # a future until factorize takes it
    A2 = A.copy()
    A2.data = A2.data * 1.5  # other values, same pattern
    fac = factorize(A2, cache=cache)
    assert fac.backend == backend and fac.symbolic_reused
    assert isinstance(cache[backend][2], direct.Symbolic)
    b = np.ones(A.shape[0])
    np.testing.assert_allclose(A2 @ fac(b), b, rtol=0, atol=1e-9)


@SYSTEM
def test_nothing_runs_ahead_where_another_backend_is_chosen(monkeypatch):
    monkeypatch.setenv(ENV_VAR, "superlu")
    cache: dict = {}
    assert not analyze_ahead(_plate(10), cache)
    assert cache == {}


@SYSTEM
def test_an_unknown_common_layout_disables_the_path(monkeypatch):
    """A library whose cholmod_start writes other defaults at the offsets set here is not used."""
    offset, ctype, value = direct._LAYOUT[6]  # supernodal: CHOLMOD_AUTO
    monkeypatch.setattr(direct, "_LAYOUT", direct._LAYOUT[:6] + ((offset, ctype, value + 7),) + direct._LAYOUT[7:])
    lib, detail = direct._load()
    assert lib is None and f"byte {offset}" in detail and "unknown layout" in detail


@SYSTEM
def test_the_path_can_be_switched_off(monkeypatch):
    monkeypatch.setenv(direct.ENV_VAR, "0")
    lib, detail = direct._load()
    assert lib is None and direct.ENV_VAR in detail


@SYSTEM
def test_concurrent_callers_of_one_factor_get_their_own_answers():
    A = _plate(50)
    n = A.shape[0]
    num = direct.Symbolic(A.indptr, A.indices, n).factor(A)
    rng = np.random.default_rng(9)
    X = [rng.standard_normal((n, 30)) for _ in range(4)]
    out: dict = {}

    def run(i):
        out[i] = num.solve(A @ X[i])

    threads = [threading.Thread(target=run, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for i in range(4):
        np.testing.assert_allclose(out[i], X[i], rtol=0, atol=1e-9)


@SYSTEM
def test_the_gil_is_released_while_cholmod_works():
    """A Python thread keeps counting while the main thread is inside CHOLMOD (through scikit-sparse, which
    holds the GIL, its longest stall was 65 % of the time inside)."""
    A = _plate(300)  # 90,000 unknowns: the analysis and factorization take 0.2-1 s
    n = A.shape[0]
    counts = []
    stop = threading.Event()

    def count():
        while not stop.is_set():
            counts.append(time.perf_counter())

    t = threading.Thread(target=count)
    t.start()
    try:
        time.sleep(0.02)
        t0 = time.perf_counter()
        num = direct.Symbolic(A.indptr, A.indices, n).factor(A)
        num.solve(np.ones((n, 4)))
        t1 = time.perf_counter()
    finally:
        stop.set()
        t.join()
    inside = [c for c in counts if t0 < c < t1]
    gaps = np.diff([t0, *inside, t1])
    assert gaps.max() < 0.3 * (t1 - t0) + 0.03, f"counter stalled {gaps.max():.3f} s of {t1 - t0:.3f} s"
