"""Parametric FE model: K(p), M(p) and their exact derivatives on the independent DOF.

The assembly keeps K and M as sums of fixed g-set matrices, each proportional
to a monomial of card values (membrane ~ E t, bending ~ E t^3, shell mass
~ rho t, a CONM2 mass, a spring rate). With P = P0 (1 + p) each term scales
with prod_j (1 + p_j)^e_kj. Terms with the same exponent row are summed,
reduced by the constraint transformation T once (T^T A T) and kept as
:class:`~femodel.AffineMatrix` terms. All terms of K (and of M) are mapped into
one shared CSR pattern, so K(p) at a new p is a weighted sum of ``data``
vectors: no reassembly, no sparse-matrix algebra.

The concerns live in private modules: the shared pattern and the a-set map
(:mod:`femodel._pattern`), parameter bookkeeping and grouping
(:mod:`femodel._grouping`), the shell-shear series (:mod:`femodel._shellshear`);
added term families in :mod:`femodel._terms`.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from femodel._affine import AffineMatrix
from femodel._grouping import (
    _check_element_thickness,
    _check_pcomp_materials,
    _factor_key,
    _grouped_terms,
    _key_index,
    _local_subset_terms,
    _nominal_from_model,
    _subset_terms,
    _with_series,
)
from femodel._params import ParameterError, ParameterSet, read_parameters
from femodel._pattern import _Pattern, _canonical, _extended_pattern, _selection_map, _shared_pattern, _to_aset
from femodel._shellshear import (  # noqa: F401  (MAX_SERIES_TERMS_PER_GROUP: re-exported)
    MAX_SERIES_TERMS_PER_GROUP,
    _shell_shear_corrections,
    _shell_shear_elements,
    _shell_shear_series,
)


@dataclass(frozen=True)
class SeriesAffineMatrix(AffineMatrix):
    """An :class:`AffineMatrix` whose terms may be two monomials in series.

    Term k scales with

        c_k(p) = (1 + r_k) u v / (v + r_k u),   u = prod_j (1 + p_j)^a_kj,
                                                v = prod_j (1 + p_j)^b_kj,

    i.e. the stiffness of two springs in series, 1/c = (1/u + r/v)/(1 + r),
    normalized so that c_k(0) = 1. With r_k = 0 the term is the monomial u.
    Shell transverse shear with the residual bending flexibility is such a
    term: u ~ G t (shear), v ~ E t^3 / L^2 (residual bending), r = u0/v0.

    Parameters
    ----------
    matrices, exponents
        As :class:`AffineMatrix` (``exponents`` holds a_kj).
    series_exponents : (n_terms, n_params) array
        b_kj (ignored where r_k = 0).
    series_ratio : (n_terms,) array
        r_k >= 0.
    """

    series_exponents: np.ndarray = None
    series_ratio: np.ndarray = None

    def __post_init__(self) -> None:
        super().__post_init__()
        n = len(self.matrices)
        b = self.exponents.copy() if self.series_exponents is None else np.asarray(self.series_exponents, float)
        r = np.zeros(n) if self.series_ratio is None else np.asarray(self.series_ratio, float)
        if b.shape != self.exponents.shape or r.shape != (n,) or np.any(r < 0):
            raise ValueError("SeriesAffineMatrix: series_exponents must match exponents and series_ratio be (n_terms,) >= 0")
        object.__setattr__(self, "series_exponents", b)
        object.__setattr__(self, "series_ratio", r)

    def _uv(self, p):
        q = (1.0 + p)[None, :]
        return np.prod(q**self.exponents, axis=1), np.prod(q**self.series_exponents, axis=1)

    def coefficients(self, p) -> np.ndarray:
        p = self._check(p)
        u, v = self._uv(p)
        r = self.series_ratio
        return (1.0 + r) * u * v / (v + r * u)

    def coefficient_jacobian(self, p) -> np.ndarray:
        p = self._check(p)
        u, v = self._uv(p)
        r = self.series_ratio
        c = (1.0 + r) * u * v / (v + r * u)
        # dc/dp_j = c^2/(1+r) (a_j/u + r b_j/v) / (1 + p_j)
        g = (self.exponents / u[:, None] + (r / v)[:, None] * self.series_exponents) / (1.0 + p)[None, :]
        return (c**2 / (1.0 + r))[:, None] * g

    def projected(self, basis) -> "SeriesAffineMatrix":
        reduced = AffineMatrix.projected(self, basis)
        return SeriesAffineMatrix(reduced.matrices, self.exponents.copy(), self.series_exponents.copy(),
                                  self.series_ratio.copy())


@dataclass(frozen=True, eq=False)
class ParametricModel:
    """K(p) and M(p) of a deck as exact functions of normalized parameters.

    The parameters are the deck fields of ``parameters`` (P = P0 (1 + p))
    followed by the added term families of ``terms`` (see
    :mod:`femodel._terms` and :meth:`with_terms`).

    Attributes
    ----------
    parameters : ParameterSet
        Parameters that scale fields of the deck's cards.
    nominal : (n_params,) float
        P0 of each deck parameter in SI (for a group, the value of its first
        id); for an added term its value at p = 0 (0 for an added spring or
        mass, 1 for an element-subset factor).
    nominal_values : tuple of (n_ids,) float arrays
        P0 of every card id of each deck parameter, SI.
    K, M : AffineMatrix
        Stiffness (N/m, N m/rad) and mass (kg, kg m^2) on the independent
        DOF, (n_a, n_a), as sums of fixed terms times monomials in (1 + p)
        (an :class:`~femodel.ExtendedAffineMatrix` once terms are added).
    aset : DofMap
        The independent DOF (rows of K and M).
    assembly : Assembly
        The nominal assembly (g-set terms, T, FE model).
    bdf : Path
        The deck.
    units : str
        The deck's unit system.
    series_error_bound : float
        0 when every shell-shear series term is exact (structured meshes,
        at most ``MAX_SERIES_TERMS_PER_GROUP`` distinct element ratios per
        group); otherwise the largest relative error of a binned series
        coefficient anywhere within the parameter bounds.
    terms : tuple
        Added term families (:class:`~femodel.AddedSpring`,
        :class:`~femodel.AddedMass`, :class:`~femodel.ElementFactor`), in
        parameter order after the deck parameters.
    """

    parameters: ParameterSet
    nominal: np.ndarray
    nominal_values: tuple
    K: AffineMatrix = field(repr=False)
    M: AffineMatrix = field(repr=False)
    aset: object = field(repr=False)
    assembly: object = field(repr=False)
    bdf: Path = None
    units: str = "si"
    series_error_bound: float = 0.0
    _kpat: _Pattern = field(default=None, repr=False)
    _mpat: _Pattern = field(default=None, repr=False)
    terms: tuple = ()

    @property
    def n_params(self) -> int:
        return len(self.parameters) + len(self.terms)

    @property
    def names(self) -> tuple[str, ...]:
        """Parameter names: the deck parameters, then the added terms."""
        return tuple(self.parameters.names) + tuple(t.name for t in self.terms)

    @property
    def lower(self) -> np.ndarray:
        """Lower bounds on p, (n_params,)."""
        return np.concatenate([self.parameters.lower, [float(t.lower) for t in self.terms]])

    @property
    def upper(self) -> np.ndarray:
        """Upper bounds on p, (n_params,)."""
        return np.concatenate([self.parameters.upper, [float(t.upper) for t in self.terms]])

    def stiffness(self, p) -> sp.csr_matrix:
        """K(p), (n_a, n_a) CSR on the shared pattern."""
        return self._kpat.combine(self.K.coefficients(p), self.K.matrices)

    def mass(self, p) -> sp.csr_matrix:
        """M(p), (n_a, n_a) CSR on the shared pattern."""
        return self._mpat.combine(self.M.coefficients(p), self.M.matrices)

    def dK(self, p, j: int) -> sp.csr_matrix:
        """dK/dp_j at p (exact), (n_a, n_a)."""
        return self._kpat.combine(self.K.coefficient_jacobian(p)[:, self._j(j)], self.K.matrices)

    def dM(self, p, j: int) -> sp.csr_matrix:
        """dM/dp_j at p (exact), (n_a, n_a)."""
        return self._mpat.combine(self.M.coefficient_jacobian(p)[:, self._j(j)], self.M.matrices)

    def modes(self, p, n_modes: int, **kwargs):
        """Normal modes of K(p), M(p) (:func:`femodel.normal_modes`; shapes on the a-set)."""
        from femodel._modes import normal_modes

        kwargs.setdefault("dofs", self.aset)
        return normal_modes(self.stiffness(p), self.mass(p), n_modes, **kwargs)

    def _j(self, j) -> int:
        if isinstance(j, str):
            names = self.names
            if j not in names:
                raise ParameterError(f"no parameter named {j!r} (have {', '.join(names)})")
            return names.index(j)
        if not 0 <= int(j) < self.n_params:
            raise ParameterError(f"parameter index {j} out of range 0..{self.n_params - 1}")
        return int(j)

    def physical(self, p) -> dict[str, float]:
        """Physical values by parameter name, SI.

        P = P0 (1 + p) for a deck parameter (first id of a group); the
        magnitude ``scale * p`` for an added spring (N/m, N m/rad) or mass
        (kg); the factor 1 + p for an element subset.
        """
        p = self._p(p)
        n0 = len(self.parameters)
        out = {name: float(v) for name, v in zip(self.parameters.names, self.nominal[:n0] * (1.0 + p[:n0]))}
        for t, pj in zip(self.terms, p[n0:]):
            out[t.name] = t.value(pj)
        return out

    def normalized(self, values) -> np.ndarray:
        """The p that gives physical ``values`` ({name: SI value}; missing names stay at 0)."""
        p = np.zeros(self.n_params)
        n0 = len(self.parameters)
        for name, v in values.items():
            j = self._j(name)
            p[j] = float(v) / self.nominal[j] - 1.0 if j < n0 else self.terms[j - n0].normalized(v)
        return p

    def _p(self, p) -> np.ndarray:
        p = np.asarray(p, dtype=float)
        if p.shape != (self.n_params,):
            raise ParameterError(f"expected {self.n_params} normalized parameters, got shape {p.shape}")
        return p

    def write_bdf(self, out_path, p, *, added_cards=()) -> Path:
        """Write the deck with the physical values at p (one flattened file, exact values).

        Added terms are written as new cards with fresh ids (CELAS2, CONM2,
        copied PSHELL/PBAR/... and MAT1 cards, elements re-pointed) in
        fixed format; see :func:`femodel.write_bdf`.
        """
        from femodel._writeback import write_bdf

        p = self._p(p)
        n0 = len(self.parameters)
        values = {}
        for prm, p0, pj in zip(self.parameters.parameters, self.nominal_values, p[:n0]):
            for key, v0 in zip(prm.keys, p0):
                values[key] = float(v0) * (1.0 + pj)
        added = [(t, t.value(pj)) for t, pj in zip(self.terms, p[n0:])]
        return write_bdf(self.bdf, out_path, values, units=self.units, added_cards=added_cards, added_terms=added)

    def with_terms(self, terms) -> "ParametricModel":
        """A new model with added term families (this one is unchanged).

        Parameters
        ----------
        terms : sequence of AddedSpring, AddedMass or ElementFactor
            Appended as parameters after the existing ones, in this order.
            Names must be new; element subsets of all factor terms disjoint.

        Returns
        -------
        ParametricModel
            K and M gain the terms' matrices (on the same a-set: the deck's
            constraints apply to them) with exact derivatives; the existing
            terms and their shared sparse pattern are reused, not rebuilt.

        Raises
        ------
        ParameterError
            An unknown family, a repeated name, a grid or element not in the
            deck, overlapping element subsets, or a term that acts only on
            constrained DOF.
        """
        from femodel._terms import TERM_FAMILIES, ElementFactor

        terms = tuple(terms)
        where = f"{self.bdf}: " if self.bdf else ""
        names = list(self.names)
        for t in terms:
            if not isinstance(t, TERM_FAMILIES):
                raise ParameterError(f"{where}with_terms: {t!r} is not one of "
                                     f"{', '.join(c.__name__ for c in TERM_FAMILIES)}")
            if t.name in names:
                raise ParameterError(f"{where}with_terms: parameter name {t.name!r} is already used")
            names.append(t.name)
        owner: dict[int, str] = {}
        for t in self.terms + terms:
            if isinstance(t, ElementFactor):
                for e in t.elements:
                    if e in owner:
                        raise ParameterError(f"{where}with_terms: element {e} is in both {owner[e]!r} and "
                                             f"{t.name!r} (element subsets must be disjoint)")
                    owner[e] = t.name
        n_old, n_new = self.n_params, self.n_params + len(terms)
        parts = {"K": _widened(self.K, n_new), "M": _widened(self.M, n_new)}
        added = {"K": [], "M": []}
        for i, t in enumerate(terms):
            j = n_old + i
            for kind, parts_t in self._term_parts(t, "with_terms").items():
                for m, ar, br, rr in parts_t:
                    added[kind].append((m, _pad(ar, n_new), _pad(br, n_new), rr, j))
        out = {}
        for kind, (mats, a, b, r, lin) in parts.items():
            new = added[kind]
            mats = list(mats) + [x[0] for x in new]
            a = np.vstack([a] + [x[1][None] for x in new])
            b = np.vstack([b] + [x[2][None] for x in new])
            r = np.concatenate([r, [x[3] for x in new]])
            lin = np.concatenate([lin, np.array([x[4] for x in new], dtype=np.int64)])
            pat = self._kpat if kind == "K" else self._mpat
            out[kind] = (_extended_affine(mats, a, b, r, lin), _extended_pattern(pat, [x[0] for x in new]))
        return replace(self, K=out["K"][0], M=out["M"][0], _kpat=out["K"][1], _mpat=out["M"][1],
                       nominal=np.concatenate([self.nominal, [float(t.nominal) for t in terms]]),
                       terms=self.terms + terms)

    def _amap(self) -> np.ndarray:
        """The g-set to a-set selection map of the assembly's T (computed once per model)."""
        amap = self.__dict__.get("_amap_cache")
        if amap is None:
            amap = _selection_map(self.assembly.T)
            object.__setattr__(self, "_amap_cache", amap)
        return amap

    def _term_parts(self, term, what: str) -> dict:
        """The a-set pieces of one added term: {kind: [(matrix, a, b, ratio), ...]}.

        ``matrix`` is canonical CSR (n_a, n_a); ``a``, ``b``, ``ratio`` are the
        series/monomial exponents of the term's coefficient in the deck
        parameters (zero rows for an added spring or mass, whose coefficient
        is its own p alone). Shared by :meth:`with_terms` and
        :meth:`term_derivative`, so both see the same matrices.
        """
        from femodel._terms import ElementFactor, _g_csr

        where = f"{self.bdf}: " if self.bdf else ""
        asm = self.assembly
        out: dict = {}
        if isinstance(term, ElementFactor):
            mats, a, b, r = _subset_terms(asm, self.parameters, term, self._amap())
            pieces = [(m, ar, br, float(rr)) for m, ar, br, rr in zip(mats, a, b, r) if m.nnz]
            if not pieces:
                raise ParameterError(f"{where}{what}: element subset {term.name!r} has no {term.kind} terms")
            return {term.kind: pieces}
        zero = np.zeros(len(self.parameters))
        amap = self._amap()
        n_a = int(asm.T.shape[1])
        for kind, (rows, cols, vals) in term.g_entries(asm.model).items():
            ar, ac = amap[rows], amap[cols]
            if np.all(ar >= -1) and np.all(ac >= -1):
                # unit selections or removed DOF: the entries map straight to the a-set (no n_g-sized matrix;
                # the same entries as the reduction, _to_aset's few-rows path)
                keep = (ar >= 0) & (ac >= 0) & (vals != 0.0)
                m = sp.coo_matrix((vals[keep], (ar[keep], ac[keep])), shape=(n_a, n_a)).tocsr()
            else:  # dependent DOF (rigid elements, MPC): reduced by T
                m_g = _g_csr({kind: (rows, cols, vals)}, asm.model)[kind]
                m = _to_aset(asm, amap, _canonical(m_g), drop_zeros=True)
            m.eliminate_zeros()
            if m.nnz == 0:
                raise ParameterError(f"{where}{what}: term {term.name!r} acts only on constrained DOF")
            out[kind] = [(_canonical(m), zero, zero, 0.0)]
        return out

    def term_derivative(self, term, p) -> dict:
        """dK/dp_term and dM/dp_term of a term not (yet) in the model, at p_term = 0.

        Equals ``self.with_terms([term]).dK(np.r_[p, 0], self.n_params)`` (and ``dM``)
        without building the extended model: the term's a-set matrices are
        formed as :meth:`with_terms` forms them, and for an element subset
        weighted with their coefficients at ``p``.

        Parameters
        ----------
        term : AddedSpring, AddedMass or ElementFactor
        p : (n_params,) float
            This model's normalized parameters.

        Returns
        -------
        dict
            {"K": csr (n_a, n_a) or None, "M": csr (n_a, n_a) or None}: N/m
            (N m/rad) and kg (kg m^2) per unit p of the term; None where the
            term has no such part (a spring has no M, a mass no K).

        Raises
        ------
        ParameterError
            Not a term family, a grid or element not in the deck, an element
            subset overlapping one already in the model, or a term acting
            only on constrained DOF.
        """
        from femodel._terms import TERM_FAMILIES, ElementFactor

        where = f"{self.bdf}: " if self.bdf else ""
        if not isinstance(term, TERM_FAMILIES):
            raise ParameterError(f"{where}term_derivative: {term!r} is not one of "
                                 f"{', '.join(c.__name__ for c in TERM_FAMILIES)}")
        p = self._p(p)
        if isinstance(term, ElementFactor):
            self._check_disjoint(term)
        out = {"K": None, "M": None}
        lift = None
        if isinstance(term, ElementFactor):
            # summed on the subset's own grids, then placed on the a-set once (same entries as the full-size sum)
            local = _local_subset_terms(self.assembly, self.parameters, term, self._amap())
            if local is not None:
                (mats, a, b, r), lift = local
                parts = {term.kind: [(m, ar, br, float(rr)) for m, ar, br, rr in zip(mats, a, b, r) if m.nnz]}
                if not parts[term.kind]:
                    raise ParameterError(f"{where}term_derivative: element subset {term.name!r} has no "
                                         f"{term.kind} terms")
        if lift is None:
            parts = self._term_parts(term, "term_derivative")
        for kind, pieces in parts.items():
            if isinstance(term, ElementFactor):
                total = self._weighted_sum(pieces, p)
            else:
                total = pieces[0][0]
                for m, _, _, _ in pieces[1:]:
                    total = total + m
            out[kind] = sp.csr_matrix(total) if lift is None else lift(total)
        return out

    def term_derivatives(self, terms, p) -> list:
        """:meth:`term_derivative` of many terms at ``p``: a list of the same dicts, in order.

        Element subsets (ElementFactor, e.g. the candidate element clusters of
        a diagnosis) of one kind are assembled together in one pass, each on
        its own copy of its grids (block diagonal, one block per subset; the
        same entries as one by one, at a fraction of the fixed per-subset
        cost). Every other term, and a subset the batch cannot take (not
        disjoint from the model's subsets, rigid-element or MPC dependent DOF
        on its grids, no terms of its kind), goes through
        :meth:`term_derivative`, which raises the error that names the fault.
        """
        from femodel._grouping import _diagonal_block, _local_subset_batch
        from femodel._terms import ElementFactor

        terms = list(terms)
        p = self._p(p)
        out: list = [None] * len(terms)
        for kind in ("K", "M"):
            idx = []
            for i, t in enumerate(terms):
                if isinstance(t, ElementFactor) and t.kind == kind:
                    try:
                        self._check_disjoint(t)
                    except ParameterError:
                        continue
                    idx.append(i)
            if len(idx) < 2:
                continue
            batch = _local_subset_batch(self.assembly, self.parameters, [terms[i] for i in idx], self._amap())
            first = next((b for b in batch if b is not None), None)
            if first is None:
                continue
            (mats, a, b, r), _, _ = first
            pieces = [(m, ar, br, float(rr)) for m, ar, br, rr in zip(mats, a, b, r) if m.nnz]
            if not pieces:
                continue
            total = sp.csr_matrix(self._weighted_sum(pieces, p))
            for i, got in zip(idx, batch):
                if got is None:
                    continue
                _, (offset, size), lift = got
                block = _diagonal_block(total, offset, size)
                if block.nnz:
                    out[i] = {"K": None, "M": None, kind: lift(block)}
        return [o if o is not None else self.term_derivative(t, p) for o, t in zip(out, terms)]

    def _weighted_sum(self, pieces, p):
        """Sum of an element subset's pieces [(matrix, a row, b row, ratio)] with their coefficients at ``p``."""
        n0 = len(self.parameters)
        mats = [m for m, _, _, _ in pieces]
        a = np.zeros((len(pieces), self.n_params))
        b = np.zeros((len(pieces), self.n_params))
        a[:, :n0] = np.array([x[1] for x in pieces])
        b[:, :n0] = np.array([x[2] for x in pieces])
        r = np.array([x[3] for x in pieces])
        coef = SeriesAffineMatrix(tuple(mats), a, b, r).coefficients(p)
        total = mats[0] * coef[0]
        for m, c in zip(mats[1:], coef[1:]):
            total = total + m * c
        return total

    def _check_disjoint(self, term) -> None:
        """ParameterError when an element subset shares an element with one already in the model."""
        from femodel._terms import ElementFactor

        mine = set(term.elements)
        for t in self.terms:
            if isinstance(t, ElementFactor) and mine.intersection(t.elements):
                e = min(mine.intersection(t.elements))
                where = f"{self.bdf}: " if self.bdf else ""
                raise ParameterError(f"{where}term_derivative: element {e} is in both {t.name!r} and "
                                     f"{term.name!r} (element subsets must be disjoint)")


def _pad(row, n: int) -> np.ndarray:
    out = np.zeros(n)
    out[:len(row)] = row
    return out


def _widened(A, n: int):
    """(matrices, a, b, ratio, linear) of an affine matrix with exponent columns padded to ``n`` parameters."""
    t = len(A.matrices)
    a = np.zeros((t, n))
    a[:, :A.n_params] = A.exponents
    b = a.copy()
    series = getattr(A, "series_exponents", None)
    if series is not None:
        b[:, :A.n_params] = series
    ratio = np.asarray(getattr(A, "series_ratio", None) if series is not None else np.zeros(t), dtype=float)
    lin = getattr(A, "linear", None)
    lin = -np.ones(t, dtype=np.int64) if lin is None else np.asarray(lin, dtype=np.int64)
    return list(A.matrices), a, b, ratio, lin


def _extended_affine(mats, a, b, r, lin):
    from femodel._terms import ExtendedAffineMatrix

    return ExtendedAffineMatrix(tuple(mats), a, b, r, lin)


# ----------------------------------------------------------------------------
# construction
# ----------------------------------------------------------------------------


def parametric_model(params, bdf=None, *, units: str | None = None, allow_unsupported: bool = False,
                     assembly=None) -> ParametricModel:
    """Build the :class:`ParametricModel` of a deck and a parameter set.

    Parameters
    ----------
    params : ParameterSet or path-like
        Parameters (or a TOML parameter file, see ``docs/parameters.md``).
    bdf : path-like, optional
        The deck; defaults to the ``[model] bdf`` of the parameter file.
    units : str, optional
        The deck's unit system; defaults to ``[model] units``, else "si".
    allow_unsupported : bool
        Passed to :func:`femodel.read_bdf`.
    assembly : Assembly, optional
        A nominal assembly of the same deck, to reuse instead of reading and
        assembling again.

    Returns
    -------
    ParametricModel

    Raises
    ------
    ParameterError
        A parameter naming a missing card or field, a non-positive nominal
        value, or a parameter that does not enter K or M.
    """
    from femodel._assembly import assemble
    from femodel._reader import read_bdf

    if not isinstance(params, ParameterSet):
        params = read_parameters(params)
    source = params.source
    bdf = Path(bdf) if bdf is not None else params.bdf
    if bdf is None:
        raise ParameterError(f"{source or 'parameters'}: no deck given and no [model] bdf in the parameter file")
    units = units or params.units or "si"
    key_index = _key_index(params)
    # independent parts run on two threads (numpy releases the GIL in its loops); every array is
    # formed exactly as on one thread
    with ThreadPoolExecutor(max_workers=1) as pool:
        if assembly is None:
            fe = read_bdf(bdf, units=units, allow_unsupported=allow_unsupported)
            # the shell shear series' element matrices need the model only: formed while it is assembled
            shear_elements = pool.submit(_shell_shear_elements, fe, params, key_index)
            assembly = assemble(fe)
        else:
            shear_elements = pool.submit(_shell_shear_elements, assembly.model, params, key_index)
        fe = assembly.model
        nominal_values = _nominal_from_model(params, fe, source)

        used = set()
        for term in assembly.terms:
            for key, _ in term.factors:
                used.add(_factor_key(key))
        for prm in params.parameters:
            keys = set(prm.keys)
            if prm.card == "MAT1" and prm.field == "E":
                keys |= {("MAT1", i, "G") for i in prm.ids}
            if not keys & used:
                raise ParameterError(
                    f"{str(source) + ': ' if source else ''}parameter {prm.name!r} ({prm.card} {list(prm.ids)} "
                    f"{prm.field}) does not enter K or M: no element uses it"
                )

        _check_element_thickness(params, fe, source)
        _check_pcomp_materials(params, fe, source)
        prepared = shear_elements.result()

        def stiffness_monomials():
            return _grouped_terms(assembly, params, "K", source, _shell_shear_corrections(prepared))

        kmono = pool.submit(stiffness_monomials)
        mmats, ma, _, _ = _grouped_terms(assembly, params, "M", source)
        mpat = _shared_pattern(mmats)
        series, series_error = _shell_shear_series(assembly, params, prepared)
        kmats, ka, kb, kr = _with_series(*kmono.result(), series)
        del prepared
        kpat = _shared_pattern(kmats)
    K = SeriesAffineMatrix(tuple(kmats), ka, kb, kr) if series else AffineMatrix(tuple(kmats), ka)
    M = AffineMatrix(tuple(mmats), ma)
    return ParametricModel(
        parameters=params,
        nominal=np.array([v[0] for v in nominal_values]),
        nominal_values=tuple(nominal_values),
        K=K,
        M=M,
        aset=assembly.aset,
        assembly=assembly,
        bdf=Path(bdf),
        units=units,
        series_error_bound=series_error,
        _kpat=kpat,
        _mpat=mpat,
    )
