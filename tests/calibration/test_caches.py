"""Caches the calibration keeps: on its own FRFModel (factorization) and in AffineMatrix.cache (local terms)."""

import pickle

import numpy as np

from calibration import build_surrogate
from tests.calibration._models import beam_model


def test_factor_cache_is_an_explicit_slot_that_stays_in_process():
    model, _ = beam_model(n_el=12, sensors=[0, 3, 6, 9, 12])
    assert model.factor_cache == {}
    slot = model.factor_cache
    slot["kept"] = True  # what a cycle stores there (symbolic factorization, pattern union) stays for the next
    sur1, T1 = build_surrogate(model, np.zeros(7), (20.0, 400.0))
    assert model.factor_cache is slot and slot["kept"]
    assert not any(k.startswith("_") for k in vars(model))  # nothing written behind the dataclass's back
    # the local term tables are kept with the full-order matrices they come from
    assert "calibration.local_halves" in model.K.cache and "calibration.local_halves" in model.M.cache
    sur2, T2 = build_surrogate(model, np.zeros(7), (20.0, 400.0))
    np.testing.assert_allclose(sur2.K.at(np.zeros(7)), sur1.K.at(np.zeros(7)), rtol=1e-12, atol=1e-9)
    shipped = pickle.loads(pickle.dumps(model))
    assert shipped.factor_cache == {} and model.factor_cache  # not sent to worker processes
    assert shipped.input_names == model.input_names


def test_local_term_tables_are_scipys_submatrix_and_lower_half():
    """The NumPy-built local tables equal scipy's fancy indexing and tril + diag/2, entry for entry:
    a term touching a scattered set of rows (some rows only through their column), with explicit
    duplicates summed and an unsorted row."""
    import scipy.sparse as sp

    from calibration._surrogate import _local_term, _lower_half

    rng = np.random.default_rng(3)
    n = 40
    rows = np.array([2, 5, 6, 11, 30, 39])
    dense = np.zeros((n, n))
    block = rng.standard_normal((rows.size, rows.size))
    dense[np.ix_(rows, rows)] = block + block.T
    dense[7, 30] = dense[30, 7] = 0.5  # row 7 enters only through these two entries
    A = sp.coo_matrix(dense)
    # a duplicate split into two halves, in a non-canonical CSR
    dup = sp.coo_matrix((np.r_[A.data, [1.0, -1.0]], (np.r_[A.row, [5, 5]], np.r_[A.col, [6, 6]])), shape=(n, n))
    m = sp.csr_matrix(dup)
    m.indices[m.indptr[2]:m.indptr[3]] = m.indices[m.indptr[2]:m.indptr[3]][::-1].copy()
    m.data[m.indptr[2]:m.indptr[3]] = m.data[m.indptr[2]:m.indptr[3]][::-1].copy()
    m.has_sorted_indices = False
    got_rows, local = _local_term(m)
    want_rows = np.flatnonzero(np.any(dense != 0, axis=0) | np.any(dense != 0, axis=1))
    np.testing.assert_array_equal(got_rows, want_rows)
    assert 7 in got_rows
    want = sp.csr_matrix(dense)[want_rows][:, want_rows]
    np.testing.assert_array_equal(local.toarray(), want.toarray())
    assert local.has_sorted_indices and local.has_canonical_format
    half = _lower_half(local)
    ref = sp.tril(want, k=-1) + sp.diags(0.5 * want.diagonal())
    np.testing.assert_array_equal(half.toarray(), ref.toarray())
    np.testing.assert_array_equal((half + half.T).toarray(), want.toarray())
