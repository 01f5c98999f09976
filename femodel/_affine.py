"""Matrices that are exact, known functions of normalized parameters.

A parametric FE model writes its stiffness and mass as

    A(p) = sum_k c_k(p) A_k,    c_k(p) = prod_j (1 + p_j) ** e_kj,

where the ``A_k`` are fixed sparse matrices assembled once at the nominal
point and ``e_kj`` are small integer exponents (a membrane term of a shell
scales with E*t, so it has exponent 1 on the E parameter and 1 on the t
parameter; a bending term with E*t**3 has 1 and 3). With P = P0 (1 + p), as in
the method paper, every derivative is exact and a projection ``T^T A_k T``
onto a fixed reduction basis keeps the reduced matrix exact in p.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp


@dataclass(frozen=True)
class AffineMatrix:
    """A(p) = sum_k c_k(p) A_k with monomial coefficients in (1 + p).

    Parameters
    ----------
    matrices : tuple of (n, n) sparse or dense arrays
        The fixed terms ``A_k`` (SI units), evaluated at the nominal point.
    exponents : (n_terms, n_params) int array
        ``e_kj``: the power of (1 + p_j) that term k scales with.

    Attributes
    ----------
    cache : dict
        Scratch space for data derived from the terms alone (e.g. per-term
        tables of the rows a local term touches), filled by whoever needs it
        under a key it owns.  Not part of the value: excluded from
        comparison and repr, and a new, empty dict on every instance
        (``dataclasses.replace`` included), so derived data never outlives
        the terms it was computed from.  Holds only what a pure function of
        ``matrices`` and ``exponents`` would return.
    """

    matrices: tuple
    exponents: np.ndarray
    cache: dict = field(default_factory=dict, init=False, compare=False, repr=False)

    def __post_init__(self) -> None:
        exps = np.asarray(self.exponents, dtype=float)
        if exps.ndim != 2 or exps.shape[0] != len(self.matrices):
            raise ValueError(
                f"AffineMatrix: exponents must be (n_terms={len(self.matrices)}, n_params), "
                f"got shape {exps.shape}"
            )
        shapes = {m.shape for m in self.matrices}
        if len(shapes) > 1:
            raise ValueError(f"AffineMatrix: terms have different shapes {sorted(shapes)}")
        object.__setattr__(self, "exponents", exps)

    @property
    def n_params(self) -> int:
        return self.exponents.shape[1]

    @property
    def shape(self) -> tuple[int, int]:
        return self.matrices[0].shape

    def _check(self, p) -> np.ndarray:
        p = np.asarray(p, dtype=float)
        if p.shape != (self.n_params,):
            raise ValueError(f"expected {self.n_params} normalized parameters, got shape {p.shape}")
        if np.any(1.0 + p <= 0.0):
            bad = np.flatnonzero(1.0 + p <= 0.0).tolist()
            raise ValueError(f"normalized parameters {bad} give a non-positive physical value (p <= -1)")
        return p

    def coefficients(self, p) -> np.ndarray:
        """c_k(p), shape (n_terms,)."""
        p = self._check(p)
        return np.prod((1.0 + p)[None, :] ** self.exponents, axis=1)

    def coefficient_jacobian(self, p) -> np.ndarray:
        """dc_k/dp_j, shape (n_terms, n_params)."""
        p = self._check(p)
        c = self.coefficients(p)
        return c[:, None] * self.exponents / (1.0 + p)[None, :]

    def dense_stack(self) -> np.ndarray | None:
        """The terms as one (n_terms, n, n) array when every one is dense, else None (either kept in ``cache``)."""
        if "femodel.dense_stack" not in self.cache:
            dense = not any(sp.issparse(m) for m in self.matrices)
            self.cache["femodel.dense_stack"] = (np.stack([np.asarray(m, dtype=float) for m in self.matrices])
                                                 if dense else None)
        return self.cache["femodel.dense_stack"]

    def _combine(self, weights: np.ndarray):
        stack = self.dense_stack()
        if stack is not None:  # one BLAS contraction instead of a Python sum of n_terms scaled copies
            return np.tensordot(np.asarray(weights, dtype=float), stack, axes=1)
        out = None
        for w, m in zip(weights, self.matrices):
            if w == 0.0:
                continue
            out = w * m if out is None else out + w * m
        if out is None:
            out = self.matrices[0] * 0.0
        return out.tocsr() if sp.issparse(out) else out

    def at(self, p):
        """A(p)."""
        return self._combine(self.coefficients(p))

    def derivative(self, p, j: int):
        """dA/dp_j at p (exact)."""
        return self._combine(self.coefficient_jacobian(p)[:, j])

    def projected(self, basis) -> "AffineMatrix":
        """The same function of p with every term reduced to ``basis.T @ A_k @ basis`` (dense)."""
        reduced = []
        for m in self.matrices:
            tm = m @ basis
            r = np.asarray(basis.T @ tm)
            reduced.append(0.5 * (r + r.T))
        return AffineMatrix(tuple(reduced), self.exponents.copy())
