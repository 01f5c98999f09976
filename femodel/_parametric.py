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

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from femodel._affine import AffineMatrix
from femodel._params import ParameterError, ParameterSet, read_parameters


@dataclass(frozen=True)
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


def _shared_pattern(matrices) -> _Pattern:
    n = matrices[0].shape
    pat = None
    for m in matrices:
        s = sp.csr_matrix((np.ones(m.nnz), m.indices, m.indptr), shape=m.shape)
        pat = s if pat is None else pat + s
    pat = pat.tocsr()
    pat.sort_indices()
    ncol = np.int64(n[1])
    rows = np.repeat(np.arange(n[0], dtype=np.int64), np.diff(pat.indptr))
    keys = rows * ncol + pat.indices
    positions = []
    for m in matrices:
        r = np.repeat(np.arange(n[0], dtype=np.int64), np.diff(m.indptr))
        pos = np.searchsorted(keys, r * ncol + m.indices)
        positions.append(pos.astype(np.int32 if keys.shape[0] < 2**31 else np.int64))
    return _Pattern(pat.indptr.copy(), pat.indices.copy(), n, tuple(positions))


def _canonical(m) -> sp.csr_matrix:
    m = sp.csr_matrix(m)
    m.sum_duplicates()
    m.sort_indices()
    return m


@dataclass(frozen=True)
class ParametricModel:
    """K(p) and M(p) of a deck as exact functions of normalized parameters.

    Attributes
    ----------
    parameters : ParameterSet
    nominal : (n_params,) float
        P0 of each parameter in SI (for a group, the value of its first id).
    nominal_values : tuple of (n_ids,) float arrays
        P0 of every card id of each parameter, SI.
    K, M : AffineMatrix
        Stiffness (N/m, N m/rad) and mass (kg, kg m^2) on the independent
        DOF, (n_a, n_a), as sums of fixed terms times monomials in (1 + p).
    aset : DofMap
        The independent DOF (rows of K and M).
    assembly : Assembly
        The nominal assembly (g-set terms, T, FE model).
    bdf : Path
        The deck.
    units : str
        The deck's unit system.
    """

    parameters: ParameterSet
    nominal: np.ndarray
    nominal_values: tuple
    K: AffineMatrix
    M: AffineMatrix
    aset: object
    assembly: object
    bdf: Path
    units: str
    _kpat: _Pattern
    _mpat: _Pattern

    @property
    def n_params(self) -> int:
        return len(self.parameters)

    @property
    def lower(self) -> np.ndarray:
        """Lower bounds on p, (n_params,)."""
        return self.parameters.lower

    @property
    def upper(self) -> np.ndarray:
        """Upper bounds on p, (n_params,)."""
        return self.parameters.upper

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
            return self.parameters.index(j)
        if not 0 <= int(j) < self.n_params:
            raise ParameterError(f"parameter index {j} out of range 0..{self.n_params - 1}")
        return int(j)

    def physical(self, p) -> dict[str, float]:
        """Physical values P = P0 (1 + p) in SI, by parameter name (first id of a group)."""
        p = self._p(p)
        return {name: float(v) for name, v in zip(self.parameters.names, self.nominal * (1.0 + p))}

    def normalized(self, values) -> np.ndarray:
        """The p that gives physical ``values`` ({name: SI value}; missing names stay at 0)."""
        p = np.zeros(self.n_params)
        for name, v in values.items():
            j = self.parameters.index(name)
            p[j] = float(v) / self.nominal[j] - 1.0
        return p

    def _p(self, p) -> np.ndarray:
        p = np.asarray(p, dtype=float)
        if p.shape != (self.n_params,):
            raise ParameterError(f"expected {self.n_params} normalized parameters, got shape {p.shape}")
        return p

    def write_bdf(self, out_path, p, *, added_cards=()) -> Path:
        """Write the deck with the physical values at p (one flattened file, exact values)."""
        from femodel._writeback import write_bdf

        p = self._p(p)
        values = {}
        for prm, p0, pj in zip(self.parameters.parameters, self.nominal_values, p):
            for key, v0 in zip(prm.keys, p0):
                values[key] = float(v0) * (1.0 + pj)
        return write_bdf(self.bdf, out_path, values, units=self.units, added_cards=added_cards)


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


def _grouped_terms(assembly, params: ParameterSet, kind: str, source):
    """Sum g-set terms of one kind by exponent row; reduce each sum by T once."""
    key_index = params.key_to_index()
    # a MAT1 E parameter also moves G (G follows E, or is scaled with it on write-back)
    for (card, cid, fld), j in list(key_index.items()):
        if card == "MAT1" and fld == "E":
            key_index.setdefault(("MAT1", cid, "G"), j)
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
    if not groups:
        groups[tuple([0] * len(params))] = sp.csr_matrix((assembly.T.shape[0],) * 2)
    rows = sorted(groups)
    mats = [_canonical(assembly.reduce(groups[r])) for r in rows]
    return mats, np.array(rows, dtype=float).reshape(len(rows), len(params))


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
    if assembly is None:
        fe = read_bdf(bdf, units=units, allow_unsupported=allow_unsupported)
        assembly = assemble(fe)
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
                f"{str(source) + ': ' if source else ''}parameter {prm.name!r} ({prm.card} {list(prm.ids)} {prm.field}) does not enter K or M: "
                "no element uses it"
            )

    kmats, kexp = _grouped_terms(assembly, params, "K", source)
    mmats, mexp = _grouped_terms(assembly, params, "M", source)
    K = AffineMatrix(tuple(kmats), kexp)
    M = AffineMatrix(tuple(mmats), mexp)
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
        _kpat=_shared_pattern(kmats),
        _mpat=_shared_pattern(mmats),
    )
