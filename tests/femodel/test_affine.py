"""AffineMatrix: exact parameter functions, derivatives and projection."""

import numpy as np
import pytest
import scipy.sparse as sp

from femodel import AffineMatrix


def _random_terms(rng, n=12, n_terms=4):
    mats = []
    for _ in range(n_terms):
        a = sp.random(n, n, density=0.3, random_state=rng, format="csr")
        mats.append((a + a.T).tocsr())
    return tuple(mats)


def test_coefficients_are_monomials_in_one_plus_p():
    rng = np.random.default_rng(0)
    exps = np.array([[1, 1], [1, 3], [0, 0], [0, 1]])
    a = AffineMatrix(_random_terms(rng), exps)
    p = np.array([0.1, -0.2])
    expected = np.array([1.1 * 0.8, 1.1 * 0.8**3, 1.0, 0.8])
    np.testing.assert_allclose(a.coefficients(p), expected, rtol=1e-15)
    dense = sum(c * m.toarray() for c, m in zip(expected, a.matrices))
    np.testing.assert_allclose(a.at(p).toarray(), dense, rtol=1e-14, atol=1e-14)


def test_derivative_matches_central_difference_to_truncation_error():
    rng = np.random.default_rng(1)
    exps = np.array([[1, 3, 0], [2, 0, 1], [0, 0, 0], [1, 1, 1]])
    a = AffineMatrix(_random_terms(rng), exps)
    p = np.array([0.05, -0.1, 0.2])
    for j in range(3):
        for h in (1e-2, 1e-3):
            dp = np.zeros(3)
            dp[j] = h
            fd = (a.at(p + dp) - a.at(p - dp)).toarray() / (2 * h)
            err = np.abs(fd - a.derivative(p, j).toarray()).max()
            # central differences of a cubic: error = h^2/6 * third derivative
            assert err < 2.0 * h**2 * np.abs(a.at(p).toarray()).max() + 1e-12


def test_projection_commutes_with_evaluation():
    rng = np.random.default_rng(2)
    a = AffineMatrix(_random_terms(rng), np.array([[1, 0], [1, 3], [0, 1], [0, 0]]))
    basis = rng.standard_normal((12, 5))
    red = a.projected(basis)
    p = np.array([-0.15, 0.2])
    np.testing.assert_allclose(red.at(p), basis.T @ a.at(p) @ basis, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(red.derivative(p, 1), basis.T @ a.derivative(p, 1) @ basis, rtol=1e-12, atol=1e-12)


def test_bad_input_is_named():
    rng = np.random.default_rng(3)
    a = AffineMatrix(_random_terms(rng, n_terms=2), np.array([[1], [0]]))
    with pytest.raises(ValueError, match="expected 1 normalized parameters"):
        a.at(np.zeros(2))
    with pytest.raises(ValueError, match="non-positive physical value"):
        a.at(np.array([-1.0]))
    with pytest.raises(ValueError, match="exponents must be"):
        AffineMatrix(_random_terms(rng, n_terms=2), np.array([[1]]))


def test_cache_slot_is_per_instance_and_not_part_of_the_value():
    """``cache`` holds derived data only: a new object (``replace`` too) starts empty, eq/repr ignore it."""
    import pickle
    from dataclasses import replace

    rng = np.random.default_rng(3)
    a = AffineMatrix(_random_terms(rng, n=5, n_terms=2), np.array([[1, 0], [0, 1]]))
    a.cache["rows"] = [np.arange(5)]
    b = replace(a, matrices=tuple(2.0 * m for m in a.matrices))
    assert b.cache == {} and b.cache is not a.cache
    assert AffineMatrix(a.matrices, a.exponents).cache == {}
    assert "cache" not in repr(a) and "rows" not in repr(a)
    c = pickle.loads(pickle.dumps(a))
    np.testing.assert_array_equal(c.cache["rows"][0], np.arange(5))  # derived from the same terms, so it travels
    np.testing.assert_allclose(c.at([0.5, 0.0]).toarray(), a.at([0.5, 0.0]).toarray(), rtol=0, atol=0)


@pytest.mark.parametrize("chunk", [1 << 20, 64], ids=["one-chunk", "threaded-chunks"])
def test_union_pattern_places_every_entry_of_each_matrix(monkeypatch, chunk):
    """The union of two patterns (one reaching outside the other) and each matrix's positions in it rebuild
    both matrices exactly, explicit zeros kept; on one chunk and on the two-thread chunked merge."""
    import femodel._pattern as pattern
    from femodel import union_pattern

    monkeypatch.setattr(pattern, "_PATTERN_CHUNK", chunk)
    n = 300
    A = sp.random(n, n, density=0.04, random_state=3, format="csr")
    B = sp.random(n, n, density=0.02, random_state=4, format="csr")
    K = sp.csr_matrix(A + A.T + sp.identity(n))
    M = sp.csr_matrix(B + B.T)
    M.data[::7] = 0.0  # explicit zeros are entries
    K.sort_indices()
    M.sort_indices()
    indptr, indices, (pk, pm) = union_pattern(K, M)
    U = sp.csr_matrix((np.ones(indices.size), indices, indptr), shape=(n, n))
    assert U.has_sorted_indices
    assert U.nnz == (abs(sp.csr_matrix((np.ones(K.nnz), K.indices, K.indptr), shape=(n, n)))
                     + sp.csr_matrix((np.ones(M.nnz), M.indices, M.indptr), shape=(n, n))).nnz
    for X, pos in ((K, pk), (M, pm)):
        data = np.zeros(indices.size)
        data[pos] = X.data
        np.testing.assert_array_equal(sp.csr_matrix((data, indices, indptr), shape=(n, n)).toarray(), X.toarray())
        rows = np.repeat(np.arange(n), np.diff(indptr))
        np.testing.assert_array_equal(rows[pos], np.repeat(np.arange(n), np.diff(X.indptr)))
        np.testing.assert_array_equal(indices[pos], X.indices)
    with pytest.raises(ValueError, match="canonical CSR"):
        union_pattern(K, sp.csc_matrix(M))
