"""Parametric FE model: K(p), M(p) and their exact derivatives on the independent DOF.

The assembly keeps K and M as sums of fixed g-set matrices, each proportional
to a monomial of card values (membrane ~ E t, bending ~ E t^3, shell mass
~ rho t, a CONM2 mass, a spring rate). With P = P0 (1 + p) each term scales
with prod_j (1 + p_j)^e_kj. Terms with the same exponent row are summed,
reduced by the constraint transformation T once (T^T A T) and kept as
:class:`~femodel.AffineMatrix` terms. All terms of K (and of M) are mapped into
one shared CSR pattern, so K(p) at a new p is a weighted sum of ``data``
vectors: no reassembly, no sparse-matrix algebra.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from femodel._affine import AffineMatrix
from femodel._params import ParameterError, ParameterSet, read_parameters


@dataclass(frozen=True, eq=False)
class _Pattern:
    """Shared CSR pattern and, per term, where its entries go in it."""

    indptr: np.ndarray
    indices: np.ndarray
    shape: tuple[int, int]
    positions: tuple  # per term: (nnz_k,) int positions in the shared data array

    def combine(self, weights, matrices) -> sp.csr_matrix:
        data = np.zeros(self.indices.shape[0])
        for w, m, pos in zip(weights, matrices, self.positions):
            if w != 0.0:
                data[pos] += w * m.data
        return sp.csr_matrix((data, self.indices, self.indptr), shape=self.shape)


#: Term entries merged per chunk of rows in :func:`_shared_pattern` (keeps the
#: temporaries small enough to be reused by the allocator instead of faulted in).
_PATTERN_CHUNK = 1 << 20


def _shared_pattern(matrices) -> _Pattern:
    """Union CSR pattern of canonical CSR terms and each term's positions in it.

    Works on chunks of rows. In a chunk every term's keys ``row * n_col + col``
    are already sorted, so a stable argsort of their concatenation merges
    sorted runs; the union is the distinct keys and a term entry's position is
    the rank of its key.
    """
    n = matrices[0].shape
    n_rows = int(n[0])
    ncol = np.int64(n[1])
    indptrs = [np.asarray(m.indptr, dtype=np.int64) for m in matrices]
    total = np.zeros(n_rows + 1, dtype=np.int64)
    for ip in indptrs:
        total += ip
    n_entries = int(total[-1])
    # union size <= entries; positions and indices fit int32 when the entries do
    dtype = np.int32 if max(n_entries, int(n[1])) < 2**31 else np.int64
    cuts = np.unique(np.concatenate([[0], np.searchsorted(total, np.arange(1, n_entries // _PATTERN_CHUNK + 1)
                                                            * _PATTERN_CHUNK), [n_rows]]))
    positions = [np.empty(m.indices.shape[0], dtype=dtype) for m in matrices]
    counts = np.zeros(n_rows, dtype=np.int64)

    def merge(spans):
        """Union keys of the row chunks ``spans``; positions counted from the first of them."""
        parts = []
        base = 0
        # work arrays reused by every chunk (fresh memory is expensive to fault in)
        size = int(max((total[r1] - total[r0] for r0, r1 in spans), default=0))
        keys_buf = np.empty(size, dtype=np.int64)
        sk_buf = np.empty(size, dtype=np.int64)
        new_buf = np.empty(size, dtype=bool)
        rank_buf = np.empty(size, dtype=dtype)
        pos_buf = np.empty(size, dtype=dtype)
        for r0, r1 in spans:
            n_chunk = int(total[r1] - total[r0])
            if n_chunk == 0:
                continue
            row_key = np.arange(r1 - r0, dtype=np.int64) * ncol
            keys = keys_buf[:n_chunk]
            s0 = 0
            for m, ip in zip(matrices, indptrs):
                a, b = int(ip[r0]), int(ip[r1])
                if b > a:
                    np.add(np.repeat(row_key, np.diff(ip[r0:r1 + 1])), m.indices[a:b], out=keys[s0:s0 + b - a])
                s0 += b - a
            order = np.argsort(keys, kind="stable")
            sk = np.take(keys, order, out=sk_buf[:n_chunk])
            new = new_buf[:n_chunk]
            new[0] = True
            np.not_equal(sk[1:], sk[:-1], out=new[1:])
            ukeys = sk[new]
            rank = np.cumsum(new, dtype=dtype, out=rank_buf[:n_chunk])
            rank += base - 1
            pos = pos_buf[:n_chunk]
            pos[order] = rank
            del order
            s0 = 0
            for out, ip in zip(positions, indptrs):
                a, b = int(ip[r0]), int(ip[r1])
                out[a:b] = pos[s0:s0 + b - a]
                s0 += b - a
            rows, cols = np.divmod(ukeys, ncol)
            parts.append(cols.astype(dtype))
            counts[r0:r1] = np.bincount(rows, minlength=r1 - r0)
            base += ukeys.shape[0]
        return parts, base

    spans = [(r0, r1) for r0, r1 in zip(cuts[:-1].tolist(), cuts[1:].tolist()) if r1 > r0]
    if len(spans) >= 4:
        # two threads, each on half the rows (disjoint outputs); the second half's positions shift by the first's union
        h = len(spans) // 2
        with ThreadPoolExecutor(max_workers=1) as pool:
            second = pool.submit(merge, spans[h:])
            parts, n_first = merge(spans[:h])
            parts2, _ = second.result()
        r_mid = spans[h][0]
        for out, ip in zip(positions, indptrs):
            out[int(ip[r_mid]):] += n_first
        parts += parts2
    else:
        parts, _ = merge(spans)
    indices = np.concatenate(parts) if parts else np.zeros(0, dtype=dtype)
    indptr = np.zeros(n_rows + 1, dtype=dtype)
    np.cumsum(counts, out=indptr[1:])
    return _Pattern(indptr, indices, n, tuple(positions))


def _canonical(m) -> sp.csr_matrix:
    m = sp.csr_matrix(m)
    m.sum_duplicates()
    m.sort_indices()
    return m


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
        asm = self.assembly
        fe = asm.model
        amap = _selection_map(asm.T)
        for i, t in enumerate(terms):
            j = n_old + i
            if isinstance(t, ElementFactor):
                mats, a, b, r = _subset_terms(asm, self.parameters, t)
                for m, ar, br, rr in zip(mats, a, b, r):
                    if m.nnz:
                        added[t.kind].append((m, _pad(ar, n_new), _pad(br, n_new), rr, j))
                if not added[t.kind] or added[t.kind][-1][4] != j:
                    raise ParameterError(f"{where}with_terms: element subset {t.name!r} has no {t.kind} terms")
                continue
            for kind, m_g in t.g_matrices(fe).items():
                m = _to_aset(asm, amap, _canonical(m_g), drop_zeros=True)
                m.eliminate_zeros()
                if m.nnz == 0:
                    raise ParameterError(f"{where}with_terms: term {t.name!r} acts only on constrained DOF")
                zero = np.zeros(n_new)
                added[kind].append((_canonical(m), zero, zero, 0.0, j))
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


def _extended_pattern(pat: "_Pattern", new_mats) -> "_Pattern":
    """The shared pattern with new (canonical) terms merged in; old terms' positions carried over."""
    if not new_mats:
        return pat
    base = sp.csr_matrix((np.ones(pat.indices.shape[0]), pat.indices, pat.indptr), shape=pat.shape)
    merged = _shared_pattern([base] + list(new_mats))
    first = merged.positions[0]
    old = tuple(first[np.asarray(q)] for q in pat.positions)
    return _Pattern(merged.indptr, merged.indices, merged.shape, old + tuple(merged.positions[1:]))


def _element_terms(model) -> tuple:
    """The K and M g-set terms of a model's elements (what :func:`femodel.assemble` collects)."""
    from femodel import _assembly as A

    col = A._Collector(6 * model.n_grids)
    cd_axes = A._cd_transform(model)
    wt = float(model.wtmass)
    A._add_bars(model, col, cd_axes, wt)
    A._add_rods(model, col, cd_axes, wt)
    A._add_springs(model, col)
    A._add_bushes(model, col, cd_axes)
    A._add_conm2(model, col, cd_axes, wt)
    A._add_shells(model, col, cd_axes, wt)
    A._add_solids(model, col, cd_axes, wt)
    return col.terms()


def _subset_terms(assembly, params: ParameterSet, factor):
    """(a-set matrices, a rows, b rows, ratios) of the K or M terms of an element subset.

    The subset's elements are assembled alone on the full model's grids and
    reduced with the full model's constraint transformation; coefficients
    (including the shell shear series) are those of the same parameters.
    """
    sub = factor.submodel(assembly.model)
    sub_asm = replace(assembly, model=sub, terms=_element_terms(sub))
    source = params.source
    if factor.kind == "M":
        return _grouped_terms(sub_asm, params, "M", source)
    prepared = _shell_shear_elements(sub, params, _key_index(params))
    series, _ = _shell_shear_series(sub_asm, params, prepared)
    return _with_series(*_grouped_terms(sub_asm, params, "K", source, _shell_shear_corrections(prepared)), series)


# ----------------------------------------------------------------------------
# construction
# ----------------------------------------------------------------------------
def _factor_key(key) -> tuple[str, int, str]:
    """Normalize an assembly factor key to the parameter-file spelling."""
    card, cid, fld = key
    if card == "PELAS" and fld == "K1":
        fld = "K"
    return (card, int(cid), fld)


def _nominal_from_model(params: ParameterSet, fe, source) -> list[np.ndarray]:
    """SI nominal values from the FE model's tables (WTMASS applied to masses)."""
    where = f"{source}: " if source else ""
    wt = float(fe.wtmass)

    def table(group, name, prm, key):
        tab = group.get(name)
        if tab is None or len(tab) == 0 or key[1] not in set(tab.ids.tolist()):
            raise ParameterError(f"{where}parameter {prm.name!r}: card {key[0]} {key[1]} (field {key[2]}) is not in the deck")
        return tab, int(np.flatnonzero(tab.ids == key[1])[0])

    out = []
    for prm in params.parameters:
        vals = []
        for key in prm.keys:
            card, cid, fld = key
            if card == "MAT1":
                tab, r = table(fe.materials, "MAT1", prm, key)
                v = tab["E"][r] if fld == "E" else tab["RHO"][r] * wt
            elif card == "PSHELL":
                tab, r = table(fe.properties, "PSHELL", prm, key)
                v = tab["t"][r]
            elif card == "CONM2":
                tab, r = table(fe.elements, "CONM2", prm, key)
                v = tab["mass"][r] * wt
            elif card == "PBUSH":
                tab, r = table(fe.properties, "PBUSH", prm, key)
                v = tab["k"][r, int(fld[1]) - 1]
            elif card == "CELAS2":
                tab, r = table(fe.elements, "CELAS2", prm, key)
                v = tab["k"][r]
            elif card == "PELAS":
                table(fe.properties, "PELAS", prm, key)
                el = fe.elements.get("CELAS1")
                ks = np.array([]) if el is None else el["k"][el["pid"] == cid]
                if ks.size == 0:
                    raise ParameterError(f"{where}parameter {prm.name!r}: PELAS {cid} is used by no CELAS1")
                if not np.allclose(ks, ks[0], rtol=1e-12, atol=0.0):
                    raise ParameterError(
                        f"{where}parameter {prm.name!r}: PELAS {cid} springs mix translational and rotational "
                        "components; its SI value is ambiguous"
                    )
                v = ks[0]
            else:  # pragma: no cover - guarded by SUPPORTED_FIELDS
                raise ParameterError(f"{where}parameter {prm.name!r}: unsupported card {card}")
            v = float(v)
            if not (np.isfinite(v) and v > 0.0):
                raise ParameterError(
                    f"{where}parameter {prm.name!r}: {card} {cid} field {fld} is {v!r} (SI); a scaled "
                    "parameter needs a positive nominal value"
                )
            vals.append(v)
        out.append(np.array(vals))
    return out


def _key_index(params: ParameterSet) -> dict:
    key_index = params.key_to_index()
    # a MAT1 E parameter also moves G (G follows E, or is scaled with it on write-back)
    for (card, cid, fld), j in list(key_index.items()):
        if card == "MAT1" and fld == "E":
            key_index.setdefault(("MAT1", cid, "G"), j)
    return key_index


#: Distinct series ratios kept exactly per (shear, bending) exponent group; an
#: irregular mesh with more is binned in log(r) and the coefficient error bound
#: is reported as ``ParametricModel.series_error_bound``.
MAX_SERIES_TERMS_PER_GROUP = 64


def _series_error(r, r_rep, a, b, lower, upper) -> float:
    """Max relative coefficient error over the bounds when ratios ``r`` use ``r_rep``.

    c/u = (1 + r) / (1 + r z) with z = u/v = prod (1 + p_j)^(a_j - b_j).
    """
    d = np.asarray(a, float) - np.asarray(b, float)
    lo = np.where(d >= 0, (1.0 + lower) ** d, (1.0 + upper) ** d)
    hi = np.where(d >= 0, (1.0 + upper) ** d, (1.0 + lower) ** d)
    err = 0.0
    for z in (np.prod(lo), np.prod(hi)):
        exact = (1.0 + r) / (1.0 + r * z)
        approx = (1.0 + r_rep) / (1.0 + r_rep * z)
        err = max(err, float(np.max(np.abs(approx / exact - 1.0))))
    return err


def _selection_map(T) -> np.ndarray:
    """Per g-set row of T: its a-set column if the row is a unit selection, -1 if empty, -2 otherwise."""
    T = sp.csr_matrix(T)
    nnz = np.diff(T.indptr)
    amap = np.full(T.shape[0], -2, dtype=np.int64)
    amap[nnz == 0] = -1
    one = np.flatnonzero(nnz == 1)
    unit = T.data[T.indptr[one]] == 1.0
    amap[one[unit]] = T.indices[T.indptr[one[unit]]]
    return amap


def _to_aset(assembly, amap, m_g, drop_zeros: bool = False) -> sp.csr_matrix:
    """A canonical g-set CSR matrix as T^T A T on the a-set.

    Where every involved row of T is a unit selection (or empty) and the
    selection keeps the g-set order, the entries map straight to a-set
    indices (already in canonical order; exact zeros removed with
    ``drop_zeros``); otherwise the matrix is reduced.
    """
    n_a = assembly.T.shape[1]
    kept_rows = np.flatnonzero(amap >= 0)
    if kept_rows.size and np.all(np.diff(amap[kept_rows]) > 0):
        # order-keeping selection: a row's kept entries stay sorted, rows keep their order
        row_len = np.diff(m_g.indptr)
        if np.all(amap[row_len > 0] >= -1):
            ac = amap.astype(np.int32)[m_g.indices] if n_a < 2**31 else amap[m_g.indices]
            if ac.size == 0 or ac.min() >= -1:
                keep = ac >= 0
                keep &= np.repeat(amap >= 0, row_len)
                if drop_zeros:
                    keep &= m_g.data != 0.0
                count = np.zeros(n_a, dtype=np.int64)
                n_keep = int(np.count_nonzero(keep))
                if n_keep < keep.size // 8:  # few entries kept (e.g. a lumped mass on full blocks)
                    at = np.flatnonzero(keep)
                    rows = np.searchsorted(m_g.indptr, at, side="right") - 1
                    count[amap[kept_rows]] = np.bincount(rows, minlength=m_g.shape[0])[kept_rows]
                else:
                    cs = np.zeros(keep.size + 1, dtype=np.int64)
                    np.cumsum(keep, out=cs[1:])
                    count[amap[kept_rows]] = cs[m_g.indptr[kept_rows + 1]] - cs[m_g.indptr[kept_rows]]
                    at = keep
                indptr = np.zeros(n_a + 1, dtype=m_g.indptr.dtype)
                np.cumsum(count, out=indptr[1:])
                return sp.csr_matrix((m_g.data[at], ac[at].astype(m_g.indices.dtype), indptr), shape=(n_a, n_a))
    rows = np.repeat(np.arange(m_g.shape[0]), np.diff(m_g.indptr))
    ar, ac = amap[rows], amap[m_g.indices]
    if np.all(ar >= -1) and np.all(ac >= -1):
        keep = (ar >= 0) & (ac >= 0)
        ar, ac = ar[keep], ac[keep]
        if ar.size < 2 or np.all((np.diff(ar) > 0) | ((np.diff(ar) == 0) & (np.diff(ac) > 0))):
            indptr = np.concatenate([[0], np.cumsum(np.bincount(ar, minlength=n_a))])
            m = sp.csr_matrix((m_g.data[keep], ac.astype(m_g.indices.dtype), indptr.astype(m_g.indptr.dtype)),
                              shape=(n_a, n_a))
            if drop_zeros:
                m.eliminate_zeros()
            return m
        m = sp.csr_matrix((m_g.data[keep], (ar, ac)), shape=(n_a, n_a))
        if drop_zeros:
            m.eliminate_zeros()
    else:
        m = assembly.reduce(m_g)
    return _canonical(m)


#: Element matrices scattered per call of ``np.add.at`` in :class:`_SubsetScatter`.
_SCATTER_CHUNK = 2048
_FAR = np.int64(1) << 40  # sentinel slot offset: entries on removed DOF


class _SubsetScatter:
    """Grid-pair blocks of a fixed element set, for summing selections of its elements.

    :meth:`matrix` gives exactly what ``BlockPattern(nodes[sel], n_grids).matrix(ke)``
    gives (same pattern, every entry summed in the same order), optionally
    mapped straight to the a-set as :func:`_to_aset` maps it where T is an
    order-keeping selection, without finding the selection's blocks again:
    they are marked among the blocks of the whole set. Six DOF per grid.

    Parameters
    ----------
    nodes : (n_el, nn) int
        Grid rows of the elements.
    n_grids : int
    """

    def __init__(self, nodes: np.ndarray, n_grids: int):
        self.nodes = np.asarray(nodes, dtype=np.int64)
        self.n_grids = int(n_grids)
        n, nn = self.nodes.shape
        keys = (self.nodes[:, :, None] * self.n_grids + self.nodes[:, None, :]).reshape(n, nn * nn)
        ublocks, inv = np.unique(keys, return_inverse=True)
        self.inv = inv.reshape(n, nn * nn)
        self.brow = ublocks // self.n_grids
        self.bcol = ublocks % self.n_grids
        self.bptr = np.concatenate([[0], np.cumsum(np.bincount(self.brow, minlength=self.n_grids))])
        self._set_map(np.arange(6 * self.n_grids, dtype=np.int64), 6 * self.n_grids)

    def _set_map(self, amap: np.ndarray, n_out: int) -> None:
        kept = (amap >= 0).reshape(self.n_grids, 6)
        self.amap = amap
        self.n_out = int(n_out)
        self.krow = np.flatnonzero(kept.ravel())
        self.width = kept.sum(axis=1)[self.bcol]  # kept columns of each block
        jrank = np.cumsum(kept, axis=1) - 1
        self.jrank = np.where(kept, jrank, _FAR).ravel()  # rank of a kept DOF among its grid's kept DOF

    def to_aset(self, amap: np.ndarray, n_a: int):
        """The same element set with output on the a-set, or None where that is not a plain selection.

        ``amap`` as :func:`_selection_map`; the direct map needs every DOF of
        the elements to be kept (>= 0) or removed (-1), and the kept DOF in
        g-set order (then the rows and columns stay sorted).
        """
        amap = np.asarray(amap, dtype=np.int64)
        dofs = (6 * self.nodes[:, :, None] + np.arange(6)).ravel()
        kept = amap[amap >= 0]
        if np.any(amap[dofs] < -1) or np.any(np.diff(kept) <= 0):
            return None
        out = object.__new__(_SubsetScatter)
        out.__dict__.update(self.__dict__)
        out._set_map(np.where(amap >= 0, amap, -1), n_a)
        return out

    def matrix(self, sel: np.ndarray, element_matrices) -> sp.csr_matrix:
        """Sum of the element matrices of entries ``sel`` (m,) (element indices, repeats allowed).

        ``element_matrices(lo, hi)`` returns the (hi - lo, 6nn, 6nn) matrices of
        entries lo..hi of ``sel``; they are summed in entry order.
        """
        d = 6
        m, nn = sel.shape[0], self.nodes.shape[1]
        nb = self.brow.shape[0]
        inv = self.inv[sel]
        mark = np.zeros(nb, dtype=bool)
        mark[inv.ravel()] = True
        # csw[k]: output entries per row in the selected blocks before block k
        csw = np.zeros(nb + 1, dtype=np.int64)
        np.cumsum(np.where(mark, self.width, 0), out=csw[1:])
        row_len = csw[self.bptr[1:]] - csw[self.bptr[:-1]]
        out_len = np.zeros(self.n_out, dtype=np.int64)
        out_len[self.amap[self.krow]] = row_len[self.krow // 6]
        indptr = np.zeros(self.n_out + 1, dtype=np.int64)
        np.cumsum(out_len, out=indptr[1:])
        nnz = int(indptr[-1])
        idx_t = np.int32 if max(nnz, self.n_out) < 2**31 - 1 else np.int64
        row_start = np.full(6 * self.n_grids, _FAR, dtype=np.int64)
        row_start[self.krow] = indptr[self.amap[self.krow]]
        i = np.arange(d)
        k = np.flatnonzero(mark)
        br = self.brow[k]
        cols = (6 * self.bcol[k])[:, None] + i[None, :]  # (K, d)
        pos = (row_start[(6 * br)[:, None] + i[None, :]][:, :, None]
               + (csw[k] - csw[self.bptr[br]])[:, None, None] + self.jrank[cols][:, None, :])  # (K, d, d)
        ok = pos < _FAR
        indices = np.empty(nnz, idx_t)
        indices[pos[ok]] = np.broadcast_to(self.amap[cols][:, None, :], pos.shape)[ok]
        del pos, ok
        data = None
        for lo in range(0, m, _SCATTER_CHUNK):
            hi = min(m, lo + _SCATTER_CHUNK)
            nod = self.nodes[sel[lo:hi]]
            dofs = 6 * nod[:, :, None] + i[None, None, :]  # (c, nn, d)
            rows = row_start[dofs]
            # slot of (node a, row i, node b, col j) = start of row (a, i) + offset of block (a, b) + rank of col j
            off = ((csw[inv[lo:hi]].reshape(hi - lo, nn, nn) - csw[self.bptr[nod]][:, :, None])[:, :, :, None]
                   + self.jrank[dofs][:, None, :, :])  # (c, nn, nn, d)
            emap = np.empty((hi - lo, nn, d, nn, d), dtype=np.intp)
            np.add(rows[:, :, :, None, None], off[:, :, None, :, :], out=emap)
            if np.any(rows >= _FAR) or np.any(off >= _FAR):
                np.minimum(emap, nnz, out=emap)  # entries on removed DOF -> one spare slot
            ke = np.ascontiguousarray(element_matrices(lo, hi), dtype=float)
            if data is None and hi == m:
                data = np.bincount(emap.ravel(), weights=ke.ravel(), minlength=nnz + 1)
            else:
                if data is None:
                    data = np.zeros(nnz + 1)
                np.add.at(data, emap.ravel(), ke.ravel())
        if data is None:
            data = np.zeros(nnz + 1)
        return sp.csr_matrix((data[:nnz], indices, indptr), shape=(self.n_out, self.n_out))


def _shell_shear_series(assembly, params: ParameterSet, prepared: list):
    """Exact parametric form of shell transverse shear with residual bending flexibility.

    The shell kernel puts the transverse shear stiffness G ts t of each element
    in series with the residual bending flexibility L_i^2 / (12 D_ii), so the
    shear term is a rational function of t (and of E when the bending and
    shear materials carry different parameters) rather than a monomial. For
    the elements where it matters this returns

    * ``corrections``: (exponent row, g-set matrix) pairs that remove the
      nominal shear from the assembly's monomial terms, and
    * ``series``: (a row, b row, ratio, a-set matrix) terms with the exact
      coefficient of :class:`SeriesAffineMatrix`, elements grouped by equal
      (rows, ratio) per direction.

    ``prepared`` is :func:`_shell_shear_elements` of the assembly's model (formed here when None).
    """
    if prepared is None:
        prepared = _shell_shear_elements(assembly.model, params, key_index)
    n_par = len(params)
    amap = _selection_map(assembly.T)
    series, errors = [], []
    for n, unit, ratio, scatter, urows_t, gtinv, tinv, ea_t in prepared:
        direct = scatter.to_aset(amap, assembly.T.shape[1])

        def contrib(sel):
            """(elements, element-matrix callback) of entries ``sel`` (sorted) of the (direction, element) list."""
            d, e = np.divmod(sel, n)
            cut = int(np.searchsorted(d, 1))

            def ke(lo, hi):
                out = np.empty((hi - lo,) + unit[0].shape[1:])
                a, b = min(lo, cut), min(hi, cut)
                np.take(unit[0], e[a:b], axis=0, out=out[:b - a])
                a, b = max(lo, cut), max(hi, cut)
                np.take(unit[1], e[a:b], axis=0, out=out[hi - lo - (b - a):])
                return out

            return e, ke

        rinv = np.tile(gtinv.ravel()[tinv], 2)
        for g in range(urows_t.shape[0]):
            members = np.flatnonzero(rinv == g)
            if members.size == 0:
                continue
            logr = np.log(ratio[members])
            levels, linv = np.unique(np.round(logr, 12), return_inverse=True)
            linv = linv.ravel()
            if levels.size > MAX_SERIES_TERMS_PER_GROUP:
                # irregular mesh: bin log(r); the representative ratio is the bin's log-midpoint
                edges = np.linspace(logr.min(), logr.max(), MAX_SERIES_TERMS_PER_GROUP + 1)
                linv = np.clip(np.searchsorted(edges, logr, side="right") - 1, 0, MAX_SERIES_TERMS_PER_GROUP - 1)
            border = np.argsort(linv, kind="stable")
            _, bstart = np.unique(linv[border], return_index=True)
            bstop = np.append(bstart[1:], border.size)
            for b0_, b1_ in zip(bstart, bstop):
                sel = members[border[b0_:b1_]]
                lr = np.log(ratio[sel])
                r_rep = float(np.exp(0.5 * (lr.min() + lr.max())))
                if lr.max() - lr.min() > 1e-11:
                    errors.append(_series_error(ratio[sel], r_rep, urows_t[g, :n_par], urows_t[g, n_par:],
                                                params.lower, params.upper))
                els, ke = contrib(sel)
                m_a = direct.matrix(els, ke) if direct is not None else _to_aset(assembly, amap, scatter.matrix(els, ke))
                series.append((urows_t[g, :n_par], urows_t[g, n_par:], r_rep, m_a))
    return series, float(max(errors, default=0.0))


def _shell_shear_corrections(prepared: list) -> list:
    """(exponent row, g-set matrix) pairs that remove the nominal shell shear from the monomial terms.

    The assembly puts each element's nominal shear in the monomial term of its
    a row (G t or E t); :func:`_shell_shear_series` carries it instead.
    """
    corrections = []
    for n, unit, ratio, scatter, urows_t, gtinv, tinv, ea_t in prepared:
        urows_a, ginv = np.unique(ea_t, axis=0, return_inverse=True)
        inv = ginv.ravel()[tinv]
        for g in range(urows_a.shape[0]):
            sel = np.flatnonzero(inv == g)
            if sel.size == 0:
                continue

            def ke(lo, hi, sel=sel):
                k = np.take(unit[0], sel[lo:hi], axis=0)
                k += np.take(unit[1], sel[lo:hi], axis=0)
                return np.negative(k, out=k)

            corrections.append((urows_a[g], scatter.matrix(sel, ke)))
    return corrections


def _shell_shear_elements(fe, params: ParameterSet, key_index: dict) -> list:
    """The model-only part of :func:`_shell_shear_series` (no assembly needed).

    Per shell card with elements whose shear is a series term: (n elements,
    [w0_x U_x, w0_y U_y] element matrices (n, 6nn, 6nn) in the grids' CD
    systems, ratios r (2n,), their :class:`_SubsetScatter`, the distinct
    (a, b) exponent rows, the row of each (jt, ja, jb) triple, the triple of
    each element, the a rows of the triples).
    """
    from femodel._assembly import _to_cd
    from femodel._elements_shell import RESIDUAL_BENDING_COEFF, _bending_lengths, _unit_shear, shell_frames

    coeff = float(RESIDUAL_BENDING_COEFF)
    prop = fe.properties.get("PSHELL")
    mat = fe.materials.get("MAT1")
    n_par = len(params)
    if coeff == 0.0 or prop is None or mat is None:
        return []
    cd_axes = fe.cd_axes() if np.any(fe.cd != 0) else None
    out = []
    for card in ("CQUAD4", "CTRIA3"):
        tab = fe.elements.get(card)
        if tab is None or len(tab) == 0:
            continue
        pr = prop.rows(tab["pid"])
        m2, m3 = prop["mid2"][pr], prop["mid3"][pr]
        pids = tab["pid"]

        def jrow(keys):
            return np.array([key_index.get(k, -1) for k in keys], dtype=np.int64)

        jt = jrow([("PSHELL", int(q), "T") for q in pids])
        jb = jrow([("MAT1", int(m), "E") for m in m2])
        ja = np.where(m3 > 0, jrow([("MAT1", int(m), "E") for m in m3]), jb)
        need = (m2 > 0) & ((jt >= 0) | (ja != jb))
        if not np.any(need):
            continue
        idx = np.flatnonzero(need)
        n = idx.size
        t_p = prop["t"][pr][idx]
        t_el = tab["t"][idx]
        t = np.where(np.all(np.isnan(t_el), axis=1), t_p,
                     np.nanmean(np.where(np.isnan(t_el), t_p[:, None], t_el), axis=1))
        rows2 = mat.rows(m2[idx])
        E2, nu2 = mat["E"][rows2], mat["NU"][rows2]
        dbd = E2 / (1.0 - nu2**2) * prop["bending_ratio"][pr][idx] * t**3 / 12.0
        has3 = m3[idx] > 0
        a0 = np.empty(n)
        if np.any(has3):
            rows3 = mat.rows(m3[idx][has3])
            a0[has3] = mat["G"][rows3] * prop["ts_t"][pr][idx][has3] * t[has3]
        if np.any(~has3):  # MID3 blank: the assembly's stiff shear penalty, 1e3 G2 t
            a0[~has3] = 1e3 * mat["G"][rows2[~has3]] * t[~has3]
        nodes = fe.grid_index(tab["nodes"][idx].ravel()).reshape(n, -1)
        xyz = fe.xyz[nodes]
        _, xy, _ = shell_frames(xyz, tab.ids[idx])
        L = _bending_lengths(xy)
        # the shear term per direction for unit shear stiffness (only the shear kernel is evaluated)
        unit = [_to_cd(u, nodes, cd_axes, 6) for u in _unit_shear(xyz, tab.ids[idx])]
        # exponent rows depend on (jt, ja, jb) only: form them per distinct triple
        code = np.column_stack([jt[idx], ja[idx], jb[idx]])
        triples, tinv = np.unique(code, axis=0, return_inverse=True)
        tinv = tinv.ravel()
        ea_t = np.zeros((triples.shape[0], n_par))
        eb_t = np.zeros((triples.shape[0], n_par))
        for e_, col, w_ in ((ea_t, 0, 1), (ea_t, 1, 1), (eb_t, 0, 3), (eb_t, 2, 1)):
            ok = triples[:, col] >= 0
            np.add.at(e_, (np.flatnonzero(ok), triples[ok, col]), w_)
        w0s, ratios = [], []
        for i in range(2):
            b0 = 12.0 * dbd / (coeff * L[:, i] ** 2)
            w0s.append(1.0 / (1.0 / a0 + 1.0 / b0))
            ratios.append(a0 / b0)
        ratio = np.concatenate(ratios)
        # element shear matrices w0 U_i (in place: the unit matrices are not needed otherwise)
        for i in range(2):
            unit[i] *= w0s[i][:, None, None]
        scatter = _SubsetScatter(nodes, fe.n_grids)
        urows_t, gtinv = np.unique(np.column_stack([ea_t, eb_t]), axis=0, return_inverse=True)
        out.append((n, unit, ratio, scatter, urows_t, gtinv, tinv, ea_t))
    return out


def _grouped_terms(assembly, params: ParameterSet, kind: str, source, extra=(), series=()):
    """Sum g-set terms of one kind by exponent row; reduce each sum by T once.

    ``extra`` holds (exponent row, g-set matrix) additions to the monomial
    groups; ``series`` holds (a row, b row, ratio, g-set matrix) series terms.
    """
    key_index = _key_index(params)
    groups: dict[tuple, object] = {}
    for term in assembly.terms:
        if term.kind != kind:
            continue
        e = np.zeros(len(params), dtype=np.int64)
        for key, expo in term.factors:
            j = key_index.get(_factor_key(key))
            if j is not None:
                e[j] += int(expo)
        row = tuple(e.tolist())
        groups[row] = term.matrix if row not in groups else groups[row] + term.matrix
    for erow, m in extra:
        row = tuple(int(x) for x in erow)
        groups[row] = m if row not in groups else groups[row] + m
    if not groups:
        groups[tuple([0] * len(params))] = sp.csr_matrix((assembly.T.shape[0],) * 2)
    rows = sorted(groups)
    amap = _selection_map(assembly.T)
    # assembly.reduce sums with the dependent-DOF products, which drops exact zeros; keep that pattern
    drop_zeros = assembly.selection is None or (assembly.dependent is not None and assembly.dependent.size > 0)
    mats = [_to_aset(assembly, amap, _canonical(groups[r]), drop_zeros) for r in rows]
    a = np.array(rows, dtype=float).reshape(len(rows), len(params))
    b = a.copy()
    ratio = np.zeros(len(rows))
    return _with_series(mats, a, b, ratio, series)


def _with_series(mats, a, b, ratio, series):
    """Append (a row, b row, ratio, a-set matrix) series terms to grouped terms."""
    if series:  # already on the a-set
        mats = list(mats) + [m for _, _, _, m in series]
        a = np.vstack([a, np.array([s_[0] for s_ in series])])
        b = np.vstack([b, np.array([s_[1] for s_ in series])])
        ratio = np.concatenate([ratio, [s_[2] for s_ in series]])
    return mats, a, b, ratio


def _check_element_thickness(params: ParameterSet, fe, source) -> None:
    """A PSHELL T parameter cannot move elements that give their own T1..T4."""
    where = f"{source}: " if source else ""
    for prm in params.parameters:
        if prm.card != "PSHELL":
            continue
        for card in ("CQUAD4", "CTRIA3"):
            tab = fe.elements.get(card)
            if tab is None or len(tab) == 0 or "t" not in tab.fields:
                continue
            own = np.isin(tab["pid"], prm.ids) & np.any(~np.isnan(tab["t"]), axis=1)
            if np.any(own):
                raise ParameterError(
                    f"{where}parameter {prm.name!r}: {card} {tab.ids[own][:5].tolist()} give their own corner "
                    f"thicknesses T1..T4, which PSHELL {list(prm.ids)} T does not scale"
                )


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
