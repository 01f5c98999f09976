"""Every installed sparse backend solves SPD systems to round-off; auto, the env var and errors behave."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

import femodel
from femodel import FactorizationError, NotPositiveDefiniteError, available_backends, default_backend, factorize
from femodel._factor import AUTO, ENV_VAR, PREFERENCE

BACKENDS = [b.name for b in available_backends() if b.available]
AUTO_CHOICE = next(n for n in AUTO if n in BACKENDS)


def _plate_laplacian(n=40, shift=1e-3):
    """2-D 5-point Laplacian + shift I: SPD, n^2 unknowns, known smallest eigenvalue."""
    T = sp.diags([2.0 * np.ones(n), -np.ones(n - 1), -np.ones(n - 1)], [0, -1, 1])
    eye = sp.identity(n)
    return (sp.kron(T, eye) + sp.kron(eye, T) + shift * sp.identity(n * n)).tocsc()


def test_superlu_is_always_available_and_last():
    infos = available_backends()
    assert [b.name for b in infos] == list(PREFERENCE)
    assert infos[-1].name == "superlu" and infos[-1].available
    assert all(b.detail for b in infos)


@pytest.mark.parametrize("backend", BACKENDS)
def test_backends_solve_spd_systems_to_round_off(backend):
    A = _plate_laplacian()
    n = A.shape[0]
    rng = np.random.default_rng(3)
    X = rng.standard_normal((n, 5))
    B = A @ X
    fac = factorize(A, backend=backend)
    assert fac.backend == backend
    # cond(A) ~ 8 / 1e-3: the solution is good to ~1e-16 * 8e3
    np.testing.assert_allclose(fac(B), X, rtol=0, atol=1e-10)
    x1 = fac(B[:, 0])
    assert x1.shape == (n,) and x1.flags.c_contiguous
    np.testing.assert_allclose(x1, X[:, 0], rtol=0, atol=1e-10)


@pytest.mark.parametrize("backend", BACKENDS)
def test_every_backend_gives_the_same_modes(backend):
    """A fixed-free spring-mass chain has closed-form frequencies; each backend reproduces them."""
    n, k, m = 900, 1.0e6, 2.0
    main = np.full(n, 2 * k)
    main[-1] = k
    K = sp.diags([main, -k * np.ones(n - 1), -k * np.ones(n - 1)], [0, -1, 1], format="csr")
    M = sp.identity(n, format="csr") * m
    j = np.arange(1, 11)
    exact = np.sqrt(4 * k / m) * np.sin((2 * j - 1) * np.pi / (2 * (2 * n + 1))) / (2 * np.pi)
    modes = femodel.normal_modes(K, M, 10, solver=backend)
    np.testing.assert_allclose(modes.frequencies_hz, exact, rtol=1e-9)


@pytest.mark.parametrize("backend", [b for b in BACKENDS if b != "superlu"])
def test_cholesky_backends_refuse_indefinite_and_auto_falls_back(backend, monkeypatch):
    A = (_plate_laplacian(20) - 0.5 * sp.identity(400)).tocsc()  # lowest eigenvalue ~ -0.48
    with pytest.raises(NotPositiveDefiniteError):
        factorize(A, backend=backend)
    monkeypatch.setenv(ENV_VAR, backend)
    fac = factorize(A)  # auto: LU handles the indefinite (nonsingular) matrix
    assert fac.backend == "superlu"
    b = np.ones(400)
    np.testing.assert_allclose(A @ fac(b), b, atol=1e-10)


def test_env_var_selects_and_names_a_missing_backend(monkeypatch):
    monkeypatch.setenv(ENV_VAR, "superlu")
    assert default_backend() == "superlu"
    assert factorize(_plate_laplacian(10)).backend == "superlu"
    monkeypatch.setenv(ENV_VAR, "umfpack")
    with pytest.raises(FactorizationError, match="unknown sparse backend 'umfpack'"):
        default_backend()
    missing = [b for b in available_backends() if not b.available]
    if missing:
        monkeypatch.setenv(ENV_VAR, missing[0].name)
        with pytest.raises(FactorizationError, match=f"{ENV_VAR}={missing[0].name}: .*pip install"):
            factorize(_plate_laplacian(10))
    monkeypatch.delenv(ENV_VAR)
    assert default_backend() == AUTO_CHOICE
    assert "pardiso" not in AUTO  # only when named (inaccurate solves at free-free shifts)


def test_singular_matrix_is_a_clear_error():
    A = _plate_laplacian(10, shift=0.0).tolil()
    A[5, :] = 0.0
    A[:, 5] = 0.0
    with pytest.raises(FactorizationError, match="singular"):
        factorize(A.tocsc(), backend="superlu")
    with pytest.raises(FactorizationError, match="square"):
        factorize(sp.random(4, 5, density=0.5, format="csc"), backend="superlu")


@pytest.mark.skipif("cholmod" not in BACKENDS, reason="scikit-sparse (CHOLMOD) not installed")
def test_cholmod_reuses_the_symbolic_analysis_for_the_same_pattern():
    A = _plate_laplacian(30)
    cache = {}
    first = factorize(A, backend="cholmod", cache=cache)
    A2 = A.copy()
    A2.data *= 2.0
    second = factorize(A2, backend="cholmod", cache=cache)
    assert not first.symbolic_reused and second.symbolic_reused
    b = np.ones(A.shape[0])
    np.testing.assert_allclose(second(b), 0.5 * first(b), rtol=1e-12)


def test_frfcal_info_names_the_backend_in_use(capsys, monkeypatch):
    import json

    from frfcal.cli import main

    monkeypatch.delenv(ENV_VAR, raising=False)
    assert main(["info", "--no-scan", "--json"]) == 0
    sparse = json.loads(capsys.readouterr().out)["sparse"]
    assert sparse["in_use"] == AUTO_CHOICE and sparse["forced_by"] is None
    assert list(sparse["backends"]) == list(PREFERENCE)
    monkeypatch.setenv(ENV_VAR, "superlu")
    assert main(["info", "--no-scan"]) == 0
    assert f"sparse factorization: superlu ({ENV_VAR}=superlu)" in capsys.readouterr().out
    monkeypatch.setenv(ENV_VAR, "umfpack")
    assert main(["info", "--no-scan"]) == 0
    assert "sparse factorization: unusable setting: unknown sparse backend 'umfpack'" in capsys.readouterr().out
