"""A reduced surrogate that absorbs added term families without a new basis.

When diagnosis adds term families to a parametric model
(:meth:`femodel.ParametricModel.with_terms`), the surrogate of the old model
is kept and extended:

* the basis T (modes, static corrections, enrichment; M-orthonormal at the
  basis point) is kept;
* for every new term A_new, static corrections (K + s M)^-1 A_new T are
  added: the response of the structure to the loads the new spring, mass or
  element-subset change exerts on every basis shape (the first-order change
  of those shapes, as the derivative enrichment of :func:`build_surrogate`).
  A new term is local, so these loads have low rank (a spring between two
  DOF: one vector); they are compressed by an SVD before the solve and the
  result is M-orthonormalized against T and compressed again;
* every term of the extended model is projected on [T, W]: the old reduced
  terms are reused as the T-T block, only the W blocks are formed.

No modes are recomputed and nothing is reassembled; the cost is one
factorization of K + s M (or the caller's solver) and products of the
(local) sparse terms with the few new vectors.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from calibration._errors import CalibrationError
from calibration._surrogate import FRFModel, Surrogate, _factor, _local_terms, _shifted, _sym, m_orthonormalized
from calibration._threads import thread_map


def _range_basis(A: np.ndarray, rtol: float) -> np.ndarray:
    """Orthonormal basis of the column space of ``A`` (singular values above ``rtol`` x the largest)."""
    if A.size == 0:
        return A[:, :0]
    U, s, _ = np.linalg.svd(A, full_matrices=False)
    if s.size == 0 or s[0] == 0.0:
        return A[:, :0]
    return U[:, s > rtol * s[0]]


def _term_loads(A, T: np.ndarray, rtol: float) -> tuple[np.ndarray, np.ndarray]:
    """A low-rank basis of the loads ``A T`` of one (local, sparse) term: (rows, basis (rows, k)),
    the loads being zero off ``rows``."""
    A = sp.csr_matrix(A)
    rows = np.flatnonzero(np.diff(A.indptr))
    if rows.size == 0:
        return rows, np.zeros((0, 0))
    local = np.asarray(A[rows] @ T)  # (rows, r)
    return rows, _range_basis(local, rtol)


def extended_surrogate(
    sur: Surrogate,
    basis: np.ndarray,
    model: FRFModel,
    *,
    shift_hz: float | None = None,
    solve=None,
    load_rtol: float = 1e-8,
    vector_rtol: float = 1e-10,
    with_basis: bool = True,
) -> tuple[Surrogate, np.ndarray | None]:
    """Extend a surrogate with the term families added to its model.

    Parameters
    ----------
    sur : Surrogate
        Surrogate of the model before the terms were added.
    basis : (n, r) ndarray
        Its basis T (as returned by :func:`build_surrogate`).
    model : FRFModel
        The extended model: K, M of :meth:`femodel.ParametricModel.with_terms`
        (the old terms first, in the old order, then the new ones), the same
        inputs and outputs. Its new parameters are appended after the old ones.
    shift_hz : float, optional
        Shift s = (2 pi shift_hz)^2 of the static solves (K + s M); needed
        when ``solve`` is not given. Use the one of the basis build (default
        there: max(band low / 4, band high / 50)).
    solve : callable, optional
        ``solve(F) = (K + s M)^-1 F`` at the basis point, (n, k) -> (n, k);
        e.g. the solver of an earlier build. Formed here when None.
    load_rtol : float
        Relative singular-value cut of each new term's loads.
    vector_rtol : float
        Relative cut (on the M-norm squared) of the new vectors after
        M-orthonormalization against T.
    with_basis : bool
        Return the extended basis; False: None in its place (a caller that
        needs only the surrogate saves an (n, r + k) copy).

    Returns
    -------
    surrogate : Surrogate
        Exact in all parameters for the extended basis; ``p_basis`` is the
        old basis point with the new parameters at 0 (the deck as it is);
        ``n_static`` counts the new vectors too.
    basis : (n, r + k) ndarray or None
        The M-orthonormal extended basis [T, W] (None with ``with_basis=False``).

    Raises
    ------
    CalibrationError
        A model whose first terms and parameters do not match the surrogate's,
        a basis of the wrong shape, or no solver.
    """
    t0 = time.perf_counter()
    T = np.asarray(basis, dtype=float)
    n = model.K.shape[0]
    r = sur.size
    if T.shape != (n, r):
        raise CalibrationError(f"basis is {T.shape}, expected ({n}, {r}) for this model and surrogate")
    n_old, n_new = sur.n_params, model.n_params
    if n_new < n_old:
        raise CalibrationError(f"the extended model has {n_new} parameters, fewer than the surrogate's {n_old}")
    if tuple(model.parameter_names[:n_old]) != tuple(sur.parameter_names):
        raise CalibrationError(f"the extended model's first parameters {list(model.parameter_names[:n_old])} "
                               f"are not the surrogate's {list(sur.parameter_names)}")
    new_terms = {}
    for kind, A, Ar in (("K", model.K, sur.K), ("M", model.M, sur.M)):
        k_old = len(Ar.matrices)
        if len(A.matrices) < k_old or A.exponents.shape[1] != n_new:
            raise CalibrationError(f"extended {kind} has {len(A.matrices)} terms / {A.exponents.shape[1]} "
                                   f"parameters; the surrogate has {k_old} terms")
        if not np.array_equal(A.exponents[:k_old, :n_old], Ar.exponents) or np.any(A.exponents[:k_old, n_old:]):
            raise CalibrationError(f"extended {kind}: the first {k_old} terms are not the surrogate's "
                                   "(with_terms keeps the old terms first, in order)")
        new_terms[kind] = list(A.matrices[k_old:])
    p_b = np.concatenate([sur.p_basis, np.zeros(n_new - n_old)])
    M0 = model.mass(p_b)
    if solve is None:  # K(p_b) is needed only to factorize
        if shift_hz is None or not shift_hz > 0:
            raise CalibrationError("extended_surrogate needs shift_hz > 0 (the basis build's shift) or solve")
        s = (2 * np.pi * float(shift_hz)) ** 2
        solve = _factor(_shifted(model.stiffness(p_b), M0, s))
    t1 = time.perf_counter()
    loads = [_term_loads(A, T, load_rtol) for kind in ("K", "M") for A in new_terms[kind]]
    if loads and sum(q.shape[1] for _, q in loads):
        # the loads live on the rows the new terms touch: compress them there, not on n-row blocks
        at = np.unique(np.concatenate([rows for rows, _ in loads]))
        local = np.zeros((at.size, sum(q.shape[1] for _, q in loads)))
        col = 0
        for rows, q in loads:
            local[np.searchsorted(at, rows), col:col + q.shape[1]] = q
            col += q.shape[1]
        Q = _range_basis(local, load_rtol)
        F = np.zeros((n, Q.shape[1]))
        F[at] = Q
    else:
        F = np.zeros((n, 0))
    X = solve(F) if F.shape[1] else F
    t2 = time.perf_counter()
    Kr, Mr, inputs, outputs, Te, k = bordered(sur, T, model, X, p_b, M0, vector_rtol, with_basis=with_basis)
    t3 = time.perf_counter()
    timings = dict(sur.timings_s)
    timings.update({"extend: factor": t1 - t0, "extend: statics": t2 - t1,
                    "extend: orthonormalize and project": t3 - t2})
    out = replace(
        sur,
        K=Kr,
        M=Mr,
        inputs=inputs,
        outputs=outputs,
        p_basis=p_b,
        n_static=sur.n_static + k,
        parameter_names=tuple(model.parameter_names),
        timings_s=timings,
    )
    return out, Te


def bordered(sur: Surrogate, T: np.ndarray, model: FRFModel, X: np.ndarray, p_b, M0, vector_rtol: float,
             *, with_basis: bool = True, column_scaled: bool = False, min_novelty: float = 0.0):
    """The reduced model on [T, W]: ``X`` (n, k) made M-orthonormal against ``T`` and among itself, every term
    of ``model`` projected on the new columns only (the T-T blocks are the surrogate's; terms beyond the
    surrogate's are projected whole).

    ``T`` is M-orthonormal at ``p_b`` (``M0`` = M(p_b)). ``vector_rtol`` cuts the eigenvalues of the new
    columns' Gram matrix relative to the largest; with ``column_scaled`` each column is first scaled to unit
    M-norm (so the cut is per direction, not dominated by the largest column), and columns that keep less
    than ``min_novelty`` of their M-norm after the projection off T are dropped (they lie in T already).

    Returns (Kr, Mr, inputs, outputs, basis [T, W'] or None, k) with k the number of columns added.
    """
    MX = M0 @ X
    before = np.sqrt(np.einsum("ij,ij->j", X, MX)) if column_scaled else None
    # twice (T is M-orthonormal at p_b) when the basis is returned; once when it is not: the round-off T
    # part one pass leaves is removed by the reduced congruence below, which then needs no n-row product
    # (two (n, r) x (r, k) products and a sparse M product less: 0.3-0.5 s of an extension at 200k DOF)
    for _ in range(2 if with_basis else 1):
        X = X - T @ (T.T @ MX)
        MX = M0 @ X
    if X.shape[1] and column_scaled:
        after = np.sqrt(np.einsum("ij,ij->j", X, MX))
        novel = after > min_novelty * np.maximum(before, np.finfo(float).tiny)
        X, MX = X[:, novel] / after[novel], MX[:, novel] / after[novel]
    if X.shape[1]:
        G = _sym(X.T @ MX)
        w, V = np.linalg.eigh(G)
        keep = w > vector_rtol * max(w.max(initial=0.0), np.finfo(float).tiny)
        W = X @ (V[:, keep] / np.sqrt(w[keep]))
    else:
        W = X
    k = W.shape[1]

    def extend(A, Ar):
        """[T, W]^T A_k [T, W] for every term, the T-T block from the old surrogate.

        A sparse term touches only its own rows (:func:`_local_terms`): the
        products run on those rows of T and W, not on full-size blocks. The
        terms are shared out over the cores (:func:`thread_map`: the sparse
        products and BLAS release the GIL; one thread in a worker process):
        the whole of :func:`bordered` with 27 new columns at 200k DOF took
        0.64 s instead of 0.88 s (docs/calibration.md, stop 40)."""
        k_old = len(Ar.matrices)

        def one(item):
            i, (rows, mk) = item
            Tl, Wl = (T, W) if rows is None else (T[rows], W[rows])
            mW = np.asarray(mk @ Wl)
            ww = Wl.T @ mW
            tw = Tl.T @ mW
            tt = np.asarray(Ar.matrices[i]) if i < k_old else np.asarray(Tl.T @ (mk @ Tl))
            return _sym(np.block([[tt, tw], [tw.T, ww]]))

        return replace(A, matrices=tuple(thread_map(one, list(enumerate(_local_terms(A))))))

    Kr = extend(model.K, sur.K)
    Mr = extend(model.M, sur.M)
    B = model.inputs.toarray() if sp.issparse(model.inputs) else np.asarray(model.inputs, float)
    C = model.outputs.toarray() if sp.issparse(model.outputs) else np.asarray(model.outputs, float)
    Kr, Mr, ok, F = _new_columns_orthonormalized(Kr, Mr, T, W, p_b)
    if not ok:  # T itself was not M-orthonormal: the whole basis (n-sized, (r + k)^2 per row)
        Kr, Mr, Te = m_orthonormalized(Kr, Mr, np.hstack([T, W]), p_b, "raise vector_rtol")
        return Kr, Mr, np.asarray(Te.T @ B), np.asarray(C @ Te), Te, k
    # T kept as it is: its rows of the reduced inputs and outputs are the surrogate's (T^T B, C T); the new
    # columns W' = T F_T + W F_W (W' = W when F is None) need only W^T B and C W, not W' itself
    WB, CW = np.asarray(W.T @ B), np.asarray(C @ W)
    r = T.shape[1]
    if F is None:
        new_in, new_out, Wn = WB, CW, W
    else:
        new_in = F[:r].T @ sur.inputs + F[r:].T @ WB
        new_out = sur.outputs @ F[:r] + CW @ F[r:]
        Wn = T @ F[:r] + W @ F[r:] if with_basis else None
    inputs = np.vstack([sur.inputs, new_in])
    outputs = np.hstack([sur.outputs, new_out])
    return Kr, Mr, inputs, outputs, (np.hstack([T, Wn]) if with_basis else None), k


def _new_columns_orthonormalized(Kr, Mr, T: np.ndarray, W: np.ndarray, p, tol: float = 1e-12):
    """Reduced terms on [T, W'] made M-orthonormal at p by re-forming only the new columns W' (n, k).

    T (r columns) is M-orthonormal already: when the T-T block of the
    Cholesky factor L of M_r(p) is the identity within ``tol`` (the tolerance
    within which :func:`m_orthonormalized` leaves a basis as it is), it is
    taken as the identity, so the congruence L^-1 keeps T and the new columns
    are W' = [T, W] F with F = (L^-1)[r:]^T (r + k, k), instead of the
    (r + k, r + k) product of the whole basis. Returns (Kr, Mr, ok, F):
    F None when all of L is the identity within ``tol`` (W' = W); ok False
    when the T-T block is not (then the caller orthonormalizes the whole
    basis). W' itself is left to the caller, which may need only its rows
    at the inputs and outputs.
    """
    from calibration._surrogate import _congruent

    r = T.shape[1]
    try:
        L = np.linalg.cholesky(_sym(Mr.at(p)))
    except np.linalg.LinAlgError:
        return Kr, Mr, False, None  # m_orthonormalized raises the error that names the remedy
    eye = np.eye(L.shape[0])
    if np.abs(L - eye).max() <= tol:
        return Kr, Mr, True, None
    if np.abs(L[:r, :r] - eye[:r, :r]).max() > tol:
        return Kr, Mr, False, None
    L = L.copy()
    L[:r, :r] = eye[:r, :r]
    Li = sla.solve_triangular(L, eye, lower=True)  # its first r rows are exactly [I, 0]
    return _congruent(Kr, Li), _congruent(Mr, Li), True, np.ascontiguousarray(Li[r:].T)
