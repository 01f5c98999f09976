"""Eigensolver paths agree; rigid-body modes are detected; bad requests are clear."""

from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.sparse as sp

import femodel
from femodel._factor import available_backends

BACKENDS = [b.name for b in available_backends() if b.available]
LABEL = {"cholmod": "CHOLMOD", "pardiso": "PARDISO", "cholespy": "cholespy", "superlu": "SuperLU"}


def _chain(n=400, free=True):
    """Spring-mass chain with known eigenvalues (fixed-free or free-free)."""
    k, m = 1.0e6, 2.0
    main = np.full(n, 2 * k)
    if free:
        main[0] = main[-1] = k
    else:
        main[-1] = k
    K = sp.diags([main, -k * np.ones(n - 1), -k * np.ones(n - 1)], [0, -1, 1], format="csr")
    M = sp.identity(n, format="csr") * m
    return K, M, k, m


def _chain_fixed_free_exact(n, k, m, count):
    j = np.arange(1, count + 1)
    return np.sqrt(4 * k / m) * np.sin((2 * j - 1) * np.pi / (2 * (2 * n + 1))) / (2 * np.pi)


@pytest.mark.parametrize("solver", ["dense", "auto"] + BACKENDS)
def test_solvers_match_analytic_chain(solver):
    n = 700
    K, M, k, m = _chain(n, free=False)
    modes = femodel.normal_modes(K, M, 12, solver=solver)
    np.testing.assert_allclose(modes.frequencies_hz, _chain_fixed_free_exact(n, k, m, 12), rtol=1e-9)
    assert modes.n_rigid == 0
    if solver in LABEL:
        assert LABEL[solver] in modes.solver


def test_free_free_chain_has_one_rigid_mode():
    K, M, _, _ = _chain(900, free=True)
    modes = femodel.normal_modes(K, M, 5)
    assert modes.n_rigid == 1
    assert abs(modes.frequencies_hz[0]) < 1e-6
    # the rigid mode is uniform translation, mass-normalized
    phi = modes.shapes[:, 0]
    np.testing.assert_allclose(np.abs(phi), 1 / np.sqrt(2.0 * 900), rtol=1e-6)


def test_massless_dof_are_fine():
    """A DOF with stiffness but no mass (as DMIG MAAX omits) does not produce spurious modes."""
    K, M, k, m = _chain(700, free=False)
    M = M.tolil()
    M[5, 5] = 0.0
    modes = femodel.normal_modes(K, M.tocsr(), 6, solver="superlu")
    dense = femodel.normal_modes(K, M.tocsr(), 6, solver="dense")
    np.testing.assert_allclose(modes.frequencies_hz, dense.frequencies_hz, rtol=1e-9)


def test_bad_requests():
    K, M, _, _ = _chain(10)
    with pytest.raises(femodel.ModelError, match="n_modes"):
        femodel.normal_modes(K, M, 0)
    with pytest.raises(femodel.ModelError, match="square"):
        femodel.normal_modes(K, M[:5, :5], 2)
    with pytest.raises(femodel.ModelError, match="FEModel or Assembly"):
        femodel.solve_modes("model.bdf", 3)


def test_cli_modes_json_and_text(capsys):
    from frfcal.cli import main
    from tests.conftest import reference_path

    deck = reference_path("nastran", "cofe_three_element_types", "noReduction-000.dat")
    assert main(["modes", str(deck), "--n", "4", "--units", "consistent", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    for key in ("frequencies_hz", "n_rigid", "solver", "timing_s", "n_dof", "units", "threads"):
        assert key in out
    np.testing.assert_allclose(out["frequencies_hz"], [0.198798, 0.397449, 0.705477, 0.860346], rtol=1e-5)
    assert out["n_rigid"] == 0
    assert main(["modes", str(deck), "--n", "3", "--units", "consistent"]) == 0
    text = capsys.readouterr().out
    assert "rigid-body modes: 0" in text and "solver:" in text


def test_cli_modes_matrices_and_errors(capsys, tmp_path):
    from frfcal.cli import main
    from tests.conftest import reference_path

    pch = reference_path("nastran", "swept_plane_dmig", "sol103_swept_plane.pch")
    assert main(["modes", "--matrices", str(pch), "--n", "5", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["n_rigid"] == 3 and out["n_massless"] == 4
    bad = tmp_path / "bad.bdf"
    bad.write_text("BEGIN BULK\nGRID,1,,0.,0.,0.\nCQUAD8,1,1,1,1,1,1\nENDDATA\n")
    assert main(["modes", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "CQUAD8 x1" in err and len(err.strip().splitlines()) == 1


def test_indefinite_stiffness_is_an_error_not_a_frequency():
    K, M, _, _ = _chain(20, free=False)
    K = K.tolil()
    K[3, 3] = -5.0e6  # makes K indefinite
    with pytest.raises(femodel.ModelError, match="negative eigenvalues"):
        femodel.normal_modes(K.tocsr(), M, 4)


def test_cli_modes_op4_clamped(capsys):
    from frfcal.cli import main
    from tests.conftest import reference_path

    op4 = reference_path("nastran", "op4_craig_bampton_n11", "se_test_n11.op4")
    assert main(["modes", "--matrices", str(op4), "--clamp-grids", "--n", "3", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    np.testing.assert_allclose(out["frequencies_hz"], [365.26, 370.233, 381.422], rtol=2e-5)
    assert out["n_dof"] == 39


@pytest.mark.parametrize("solver", BACKENDS)
def test_sparse_solve_is_reproducible_bit_for_bit(solver):
    """The Lanczos start vector is fixed (femodel.start_vector): the same solve gives the same bits
    (with ARPACK's random start the frequencies differed by ~1e-9, and pretest layouts, stage fingerprints
    and calibrations with them)."""
    K, M, _, _ = _chain(4000, free=False)
    a = femodel.normal_modes(K, M, 10, solver=solver)
    b = femodel.normal_modes(K, M, 10, solver=solver)
    assert LABEL[solver] in a.solver and "Lanczos" in a.solver
    assert np.array_equal(a.frequencies_hz, b.frequencies_hz)
    assert np.array_equal(a.shapes, b.shapes)
