"""Vectorized sparse assembly of K and M as sums of parameter-scaled terms.

Each element family is evaluated for all its elements at once; the element
matrices are rotated to the grids' displacement (CD) systems and scattered
COO -> CSR.  Matrices are kept split into :class:`MatrixTerm` objects, each
proportional to a known monomial of card values (E, RHO, T, M, K, ...), so
that a parametric model can rescale them exactly without reassembly.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from femodel._dofs import DofMap
from femodel._model import FEModel, ModelError, Table

Factors = tuple


@dataclass(frozen=True)
class MatrixTerm:
    """One fixed sparse term of K or M.

    Parameters
    ----------
    kind : str
        "K" or "M".
    factors : tuple of ((card, id, field), exponent)
        Sorted; the term is proportional to prod(value ** exponent) of these
        card fields (empty: a constant term, e.g. non-structural mass).
    matrix : scipy.sparse.csr_matrix, (n_g, n_g)
        Symmetric, SI, g-set DOF, WTMASS applied, at the deck's values.
    label : str
        What it is, e.g. "MAT1 3 E: PBAR 1 axial+bending".
    """

    kind: str
    factors: Factors
    matrix: sp.csr_matrix
    label: str


@dataclass(frozen=True)
class Assembly:
    """Assembled model: g-set terms plus the transformation to independent DOF.

    Attributes
    ----------
    model : FEModel
    gset : DofMap
        Six DOF per grid (grid order of ``model.grid_ids``), in each grid's CD system.
    terms : tuple of MatrixTerm
    T : csr_matrix (n_g, n_a)
        u_g = T u_a: rigid-element dependent DOF eliminated, SPC'd and
        AUTOSPC'd DOF removed.
    aset : DofMap
        The independent DOF (columns of T).
    autospc : DofMap
        DOF removed because they had neither stiffness nor mass.
    timings : dict
        Seconds: "elements_s" (kernels and block scatter), "merge_s" (summing
        terms with equal factors), "constraints_s" (T and AUTOSPC), "total_s".
    """

    model: FEModel
    gset: DofMap
    terms: tuple
    T: sp.csr_matrix
    aset: DofMap
    autospc: DofMap
    timings: dict = field(default_factory=dict)
    selection: np.ndarray | None = None
    dependent: np.ndarray | None = None
    dependent_rows: sp.csr_matrix | None = None

    def _sum(self, kind: str) -> sp.csr_matrix:
        n = len(self.gset)
        mats = [t.matrix for t in self.terms if t.kind == kind]
        return _tree_sum(mats).tocsr() if mats else sp.csr_matrix((n, n))

    @cached_property
    def _kg(self) -> sp.csr_matrix:
        return self._sum("K")

    @cached_property
    def _mg(self) -> sp.csr_matrix:
        return self._sum("M")

    def stiffness_g(self) -> sp.csr_matrix:
        """Sum of the stiffness terms, (n_g, n_g), N/m (N m/rad for rotations)."""
        return self._kg

    def mass_g(self) -> sp.csr_matrix:
        """Sum of the mass terms, (n_g, n_g), kg (kg m^2 for rotations)."""
        return self._mg

    def reduce(self, matrix_g) -> sp.csr_matrix:
        """T^T A T for a g-set matrix, symmetrized.

        Uses T = P + D (P selects the independent DOF, D holds the few rows of
        rigid-element dependent DOF): T^T A T = A[s, s] + X + X^T + D_d^T A[d, d] D_d
        with X = A[s, d] D_d, which avoids two full sparse products.
        """
        a = sp.csr_matrix(matrix_g)
        if self.selection is None:
            r = (self.T.T @ (a @ self.T)).tocsr()
            return (0.5 * (r + r.T)).tocsr()
        s = self.selection
        r = a[s][:, s].tocsr()
        dep = self.dependent
        if dep is not None and dep.size:
            dd = self.dependent_rows
            a_sd = a[s][:, dep]
            x = (a_sd @ dd).tocsr()
            y = (dd.T @ (a[dep][:, dep] @ dd)).tocsr()
            r = (r + x + x.T + 0.5 * (y + y.T)).tocsr()
        r.sort_indices()
        return r

    @cached_property
    def _ka(self) -> sp.csr_matrix:
        return self.reduce(self._kg)

    @cached_property
    def _ma(self) -> sp.csr_matrix:
        return self.reduce(self._mg)

    def stiffness(self) -> sp.csr_matrix:
        """Stiffness on the independent DOF, (n_a, n_a)."""
        return self._ka

    def mass(self) -> sp.csr_matrix:
        """Mass on the independent DOF, (n_a, n_a)."""
        return self._ma

    def expand(self, u_a: np.ndarray) -> np.ndarray:
        """Independent-DOF vectors (n_a, ...) to the g-set (n_g, ...)."""
        return self.T @ u_a


class BlockPattern:
    """Fixed CSR pattern of a set of elements and the scatter map into it.

    The pattern is built once on the grid level (unique grid pairs of the
    elements, n_el * nn^2 keys); the map takes every entry of the stacked
    element matrices (n_el, nn*dpn, nn*dpn) straight to its slot in the CSR
    data array, so summing a term is a single ``np.bincount`` and every term
    on the same elements shares ``indices``/``indptr``.

    Parameters
    ----------
    nodes : (n_el, nn) int
        Grid row indices of the element nodes.
    n_grids : int
    dof_per_node : int
        6 (T1..R3) or 3 (T1..T3; solids).
    """

    def __init__(self, nodes: np.ndarray, n_grids: int, dof_per_node: int = 6):
        self.nodes = np.asarray(nodes, dtype=np.int64)
        self.n_grids = int(n_grids)
        self.dpn = int(dof_per_node)
        self._subsets: dict = {}
        self.map = None  # built on first use

    def _build(self) -> None:
        d = self.dpn
        n, nn = self.nodes.shape
        keys = (self.nodes[:, :, None] * self.n_grids + self.nodes[:, None, :]).ravel()
        ublocks, inv = np.unique(keys, return_inverse=True)
        brow = ublocks // self.n_grids
        bcol = ublocks % self.n_grids
        nb = ublocks.size
        bptr = np.concatenate([[0], np.cumsum(np.bincount(brow, minlength=self.n_grids))])
        cnt = np.diff(bptr)
        row_len = np.zeros((self.n_grids, 6), np.int64)
        row_len[:, :d] = (cnt * d)[:, None]
        self.indptr = np.concatenate([[0], np.cumsum(row_len.ravel())])
        self.nnz = int(self.indptr[-1])
        idx_t = np.int32 if self.nnz < 2**31 - 1 else np.int64
        k = np.arange(nb)
        i = np.arange(d)
        # slot of (block k, local row i, local col j) in the CSR data
        pos = (
            self.indptr[(6 * brow)[:, None, None] + i[None, :, None]]
            + ((k - bptr[brow]) * d)[:, None, None]
            + i[None, None, :]
        ).astype(idx_t)
        self.indices = np.empty(self.nnz, idx_t)
        self.indices[pos.ravel()] = np.broadcast_to((6 * bcol)[:, None, None] + i[None, None, :], pos.shape).ravel()
        # element entry (e, a, i, b, j) -> slot of (block inv[e, a, b], row i, col j), formed straight in
        # its final layout (intp: np.bincount would otherwise convert the map on every call)
        row0 = self.indptr[6 * self.nodes[:, :, None] + i[None, None, :]]  # (n, nn, d)
        off = (inv.reshape(n, nn, nn) - bptr[self.nodes][:, :, None]) * d  # (n, nn, nn)
        emap = np.empty((n, nn, d, nn, d), dtype=np.intp)
        np.add(row0[:, :, :, None, None], off[:, :, None, :, None], out=emap)
        emap += i[None, None, None, None, :]
        self.map = emap.ravel()

    def subset(self, sel) -> "BlockPattern":
        """The pattern of the selected elements (boolean mask or slice), cached."""
        if isinstance(sel, slice):
            start, stop, step = sel.indices(self.nodes.shape[0])
            if start == 0 and stop == self.nodes.shape[0] and step == 1:
                return self
            key = ("slice", start, stop, step)
        else:
            sel = np.asarray(sel)
            if sel.dtype == bool and sel.all():
                return self
            key = hash(sel.tobytes())
        if key not in self._subsets:
            self._subsets[key] = BlockPattern(self.nodes[sel], self.n_grids, self.dpn)
        return self._subsets[key]

    def accumulate(self, data: np.ndarray, ke: np.ndarray, start: int) -> None:
        """Add element matrices ke (m, nn*dpn, nn*dpn) of elements start..start+m to CSR ``data`` (nnz,)."""
        if self.map is None:
            self._build()
        e = ke.shape[1] * ke.shape[2]
        np.add.at(data, self.map[start * e:(start + ke.shape[0]) * e], np.ascontiguousarray(ke, dtype=float).ravel())

    def csr(self, data: np.ndarray) -> sp.csr_matrix:
        """The (n_g, n_g) CSR matrix with ``data`` on this pattern."""
        if self.map is None:
            self._build()
        n_g = 6 * self.n_grids
        return sp.csr_matrix((data, self.indices, self.indptr), shape=(n_g, n_g))

    def matrix(self, ke: np.ndarray) -> sp.csr_matrix:
        """Sum element matrices ke (n_el, nn*dpn, nn*dpn) into an (n_g, n_g) CSR matrix."""
        if self.map is None:
            self._build()
        data = np.bincount(self.map, weights=np.ascontiguousarray(ke, dtype=float).ravel(), minlength=self.nnz)
        n_g = 6 * self.n_grids
        return sp.csr_matrix((data, self.indices, self.indptr), shape=(n_g, n_g))


def _tree_sum(mats: list):
    """Sum sparse matrices pairwise (cost ~ total nnz x log(count), not count x nnz)."""
    mats = list(mats)
    while len(mats) > 1:
        nxt = [mats[i] + mats[i + 1] for i in range(0, len(mats) - 1, 2)]
        if len(mats) % 2:
            nxt.append(mats[-1])
        mats = nxt
    return mats[0]


class _Collector:
    """Accumulates term matrices per (kind, factors) and their labels."""

    def __init__(self, n: int):
        self.n = n
        self.parts: dict[tuple, list] = {}
        self.labels: dict[tuple, list] = {}

    def _store(self, kind, factors, label, m):
        key = (kind, tuple(sorted(factors)))
        self.parts.setdefault(key, []).append(m)
        lab = self.labels.setdefault(key, [])
        if label not in lab:
            lab.append(label)

    def note(self, kind: str, factors, label: str):
        """Add a label to the term (kind, factors) without a matrix (its part was summed into another add)."""
        lab = self.labels.setdefault((kind, tuple(sorted(factors))), [])
        if label not in lab:
            lab.append(label)

    def add(self, kind: str, factors, label: str, ke: np.ndarray, pattern: "BlockPattern", scale=None,
            symmetric: bool = False):
        """Element matrices ke (n_el, d, d) on ``pattern`` (same elements), scaled per element.

        ``symmetric=True``: the kernel already returns symmetric ke (up to round-off),
        so the symmetrizing copy is skipped.
        """
        if ke.shape[0] == 0:
            return
        if scale is not None:
            ke = ke * np.asarray(scale, dtype=float)[:, None, None]
        if not symmetric:
            ke = 0.5 * (ke + np.swapaxes(ke, 1, 2))
        self._store(kind, factors, label, pattern.matrix(ke))

    def add_csr(self, kind: str, factors, label: str, m: sp.csr_matrix):
        """An already summed (n, n) CSR term."""
        self._store(kind, factors, label, m)

    def add_dofs(self, kind: str, factors, label: str, ke: np.ndarray, dofs: np.ndarray, scale=None):
        """Element matrices ke (n_el, d, d) on explicit g-set DOF (n_el, d) (scalar springs)."""
        if scale is not None:
            ke = ke * np.asarray(scale, dtype=float)[:, None, None]
        d = dofs.shape[1]
        rows = np.broadcast_to(dofs[:, :, None], (dofs.shape[0], d, d)).ravel()
        cols = np.broadcast_to(dofs[:, None, :], (dofs.shape[0], d, d)).ravel()
        m = sp.csr_matrix((ke.ravel(), (rows, cols)), shape=(self.n, self.n))
        m.sum_duplicates()
        self._store(kind, factors, label, m)

    def terms(self) -> tuple:
        out = []
        for key in sorted(self.parts, key=lambda k: (k[0], str(k[1]))):
            kind, factors = key
            m = _tree_sum(self.parts[key]).tocsr()
            m.sort_indices()
            fac = ", ".join(f"{a[0]} {a[1]} {a[2]}" + (f"^{e}" if e != 1 else "") for a, e in factors) or "constant"
            out.append(MatrixTerm(kind, factors, m, f"{kind} ~ {fac}: " + "; ".join(self.labels[key])))
        return tuple(out)


def _cd_transform(model: FEModel):
    """Per-grid 3x3 CD axes (None when every grid uses basic)."""
    if not np.any(model.cd != 0):
        return None
    return model.cd_axes()


def to_cd(ke: np.ndarray, node_rows: np.ndarray, cd_axes, dof_per_node: int) -> np.ndarray:
    """Rotate element matrices from basic to the grids' CD systems (3x3 block-wise)."""
    if cd_axes is None:
        return ke
    n, nn = node_rows.shape
    blocks = dof_per_node // 3
    lam = cd_axes[node_rows]  # (n, nn, 3, 3): u_basic = lam u_cd
    touched = np.any(np.abs(lam - np.eye(3)) > 0, axis=(1, 2, 3))
    if not np.any(touched):
        return ke
    out = ke.copy()
    sub = ke[touched]
    m = sub.shape[0]
    B = nn * blocks
    lb = np.repeat(lam[touched], blocks, axis=1)  # (m, B, 3, 3) per 3-DOF block
    k6 = sub.reshape(m, B, 3, B, 3).transpose(0, 1, 3, 2, 4)  # (m, B, B, 3, 3)
    k6 = np.swapaxes(lb, 2, 3)[:, :, None] @ k6 @ lb[:, None, :]
    out[touched] = k6.transpose(0, 1, 3, 2, 4).reshape(m, B * 3, B * 3)
    return out


def _dofs(node_rows: np.ndarray, comps=(0, 1, 2, 3, 4, 5)) -> np.ndarray:
    c = np.asarray(comps)
    return (6 * node_rows[:, :, None] + c[None, None, :]).reshape(node_rows.shape[0], -1)


def _mat(model: FEModel, mids, what: str):
    """(E, G, NU, RHO, g_follows_e) for MAT1 ids."""
    mat = model.materials.get("MAT1")
    if mat is None or len(mat) == 0:
        raise ModelError(f"{what} references MAT1 {sorted(set(np.asarray(mids).tolist()))[:5]} but there is no MAT1")
    try:
        r = mat.rows(mids)
    except ModelError as exc:
        raise ModelError(f"{what}: {exc}") from None
    return mat["E"][r], mat["G"][r], mat["NU"][r], mat["RHO"][r], mat["g_follows_e"][r]


def _g_factor(mid: int, follows: bool):
    return (("MAT1", int(mid), "E"), 1) if follows else (("MAT1", int(mid), "G"), 1)


def assemble(model: FEModel) -> Assembly:
    """Assemble the model's K and M terms and the constraint transformation.

    Parameters
    ----------
    model : FEModel

    Returns
    -------
    Assembly
    """
    from femodel._constraints import constraint_transformation

    t0 = time.perf_counter()
    gset = DofMap.for_grids(model.grid_ids)
    col = _Collector(len(gset))
    cd_axes = _cd_transform(model)
    wt = float(model.wtmass)
    try:
        add_elements(model, col, cd_axes, wt)
    except ModelError as exc:
        where = f" in {model.path}" if model.path and str(model.path) not in str(exc) else ""
        raise ModelError(f"{exc}{where}") from None
    t1 = time.perf_counter()
    terms = col.terms()
    t2 = time.perf_counter()
    n = len(gset)
    kl = [t.matrix for t in terms if t.kind == "K"]
    kg = _tree_sum(kl).tocsr() if kl else sp.csr_matrix((n, n))
    # T needs the stiffness only (AUTOSPC); the mass sum is formed when first asked for (Assembly.mass_g)
    T, aset, auto, selection, dep, ddep = constraint_transformation(model, gset, kg, None)
    t3 = time.perf_counter()
    asm = Assembly(
        model=model,
        gset=gset,
        terms=terms,
        T=T,
        aset=aset,
        autospc=auto,
        timings={"elements_s": t1 - t0, "merge_s": t2 - t1, "constraints_s": t3 - t2, "total_s": t3 - t0},
        selection=selection,
        dependent=dep,
        dependent_rows=ddep,
    )
    # seed the cached stiffness sum with the matrix already formed
    asm.__dict__["_kg"] = kg
    return asm


# ---------------------------------------------------------------- element families
def add_elements(model, col, cd_axes, wt) -> None:
    """Every element family's K and M terms into ``col`` (the order fixes the order of the terms)."""
    _add_bars(model, col, cd_axes, wt)
    _add_rods(model, col, cd_axes, wt)
    _add_springs(model, col)
    _add_bushes(model, col, cd_axes)
    _add_conm2(model, col, cd_axes, wt)
    _add_shells(model, col, cd_axes, wt)
    _add_solids(model, col, cd_axes, wt)
    _add_conm1(model, col, cd_axes, wt)
    _add_scalar_masses(model, col, wt)


def _add_bars(model, col, cd_axes, wt):
    from femodel._elements_line import beam_matrices

    for card in ("CBAR", "CBEAM"):
        tab = model.elements.get(card)
        if tab is None or len(tab) == 0:
            continue
        prop = model.properties.get("PBAR")
        if prop is None:
            raise ModelError(f"{card} elements reference properties but no PBAR/PBARL/PBEAM/PBEAML is defined")
        try:
            pr = prop.rows(tab["pid"], owners=tab.ids)
        except ModelError as exc:
            raise ModelError(f"{card}: {exc}") from None
        mids = prop["mid"][pr]
        E, G, _, rho, follows = _mat(model, mids, card)
        nodes = model.grid_index(tab["nodes"].ravel(), what=f"{card} grid").reshape(-1, 2)
        # a PBAR without shear factors: its terms carry the section fields A, I1, I2, J as factors too
        # (exact monomials of them; the parametric model uses them when a parameter names one)
        sectioned = (prop["card"][pr] == "PBAR") & ~_shear_flexible(prop["k1"][pr]) & ~_shear_flexible(prop["k2"][pr])
        out = beam_matrices(
            model.xyz[nodes[:, 0]], model.xyz[nodes[:, 1]], tab["v"], tab["wa"], tab["wb"],
            prop["A"][pr], prop["I1"][pr], prop["I2"][pr], prop["J"][pr], E, G, prop["k1"][pr], prop["k2"][pr],
            coupled=model.coupmass, torsion_inertia=(card == "CBEAM"), ids=tab.ids, what=card,
            pins=tab.fields.get("pins"), section_parts=sectioned,
        )
        parts = None
        if "stiffness_E_parts" in out:
            parts = [to_cd(out["stiffness_E_parts"][k], nodes, cd_axes, 6) for k in range(3)]
        pat = BlockPattern(nodes, model.n_grids)
        kE = to_cd(out["stiffness_E"], nodes, cd_axes, 6)
        kG = to_cd(out["stiffness_G"], nodes, cd_axes, 6)
        mu = to_cd(out["mass_unit"], nodes, cd_axes, 6)
        mt = to_cd(out["mass_torsion_unit"], nodes, cd_axes, 6) if "mass_torsion_unit" in out else None
        pids = tab["pid"]
        pcard = prop["card"][pr]
        A = prop["A"][pr]
        nsm = prop["nsm"][pr]
        for pid in np.unique(pids):
            sel = pids == pid
            mid = int(mids[sel][0])
            lab = f"{card} {pcard[sel][0]} {int(pid)}"
            if sectioned[sel][0]:  # one PBAR: every element of the pid is sectioned or none
                sec = prop["A"][pr], prop["I1"][pr], prop["I2"][pr]
                for k, fld in enumerate(("A", "I1", "I2")):
                    col.add("K", [(("MAT1", mid, "E"), 1), (("PBAR", int(pid), fld), 1)],
                            lab + (" axial", " bending 1", " bending 2")[k], parts[k][sel], pat.subset(sel),
                            E[sel] * sec[k][sel])
                col.add("K", [_g_factor(mid, bool(follows[sel][0])), (("PBAR", int(pid), "J"), 1)], lab + " torsion",
                        kG[sel], pat.subset(sel), G[sel])
                col.add("M", [(("MAT1", mid, "RHO"), 1), (("PBAR", int(pid), "A"), 1)], lab + " mass", mu[sel],
                        pat.subset(sel), wt * rho[sel] * A[sel])
            else:
                col.add("K", [(("MAT1", mid, "E"), 1)], lab + " axial+bending", kE[sel], pat.subset(sel), E[sel])
                col.add("K", [_g_factor(mid, bool(follows[sel][0]))], lab + " torsion", kG[sel], pat.subset(sel),
                        G[sel])
                col.add("M", [(("MAT1", mid, "RHO"), 1)], lab + " mass", mu[sel], pat.subset(sel),
                        wt * rho[sel] * A[sel])
            if mt is not None:
                col.add("M", [(("MAT1", mid, "RHO"), 1)], lab + " torsional inertia", mt[sel], pat.subset(sel), wt * rho[sel])
            if np.any(nsm[sel] != 0):
                col.add("M", [], lab + " NSM", mu[sel], pat.subset(sel), wt * nsm[sel])


def _shear_flexible(k) -> np.ndarray:
    """Sections with a shear factor K1/K2 (Timoshenko: phi > 0), as :func:`beam_matrices` reads them."""
    k = np.asarray(k, float)
    return np.isfinite(k) & (k > 0)


def _add_rods(model, col, cd_axes, wt):
    from femodel._elements_line import rod_matrices

    for card in ("CROD", "CONROD", "CTUBE"):
        tab = model.elements.get(card)
        if tab is None or len(tab) == 0:
            continue
        if card in ("CROD", "CTUBE"):
            pcard = "PROD" if card == "CROD" else "PTUBE"
            prop = model.properties.get(pcard)
            if prop is None:
                raise ModelError(f"{card} elements but no {pcard} defined")
            try:
                pr = prop.rows(tab["pid"], owners=tab.ids)
            except ModelError as exc:
                raise ModelError(f"{card}: {exc}") from None
            mids, A, J, nsm = prop["mid"][pr], prop["A"][pr], prop["J"][pr], prop["nsm"][pr]
            groups = tab["pid"]
            pname = lambda p, c=card, q=pcard: f"{c} {q} {int(p)}"  # noqa: E731
        else:
            mids, A, J, nsm = tab["mid"], tab["A"], tab["J"], tab["nsm"]
            groups = tab.ids
            pname = lambda e: f"CONROD {int(e)}"  # noqa: E731
        E, G, _, rho, follows = _mat(model, mids, card)
        nodes = model.grid_index(tab["nodes"].ravel(), what=f"{card} grid").reshape(-1, 2)
        out = rod_matrices(model.xyz[nodes[:, 0]], model.xyz[nodes[:, 1]], A, J, coupled=model.coupmass, ids=tab.ids)
        pat = BlockPattern(nodes, model.n_grids)
        kE = to_cd(out["stiffness_E"], nodes, cd_axes, 6)
        kG = to_cd(out["stiffness_G"], nodes, cd_axes, 6)
        mu = to_cd(out["mass_unit"], nodes, cd_axes, 6)
        # group by material (CONROD carries its own section, so per material); a CROD's terms also carry its
        # PROD's A (axial, mass) and J (torsion) as factors, so they group by property
        keys = groups if card == "CROD" else mids
        for key in np.unique(keys):
            sel = keys == key
            mid = int(mids[sel][0])
            sec = (lambda f: [(("PROD", int(key), f), 1)]) if card == "CROD" else (lambda f: [])
            lab = ", ".join(sorted({pname(g) for g in groups[sel]})[:3]) + (" ..." if len(set(groups[sel].tolist())) > 3 else "")
            col.add("K", [(("MAT1", mid, "E"), 1)] + sec("A"), lab + " axial", kE[sel], pat.subset(sel), E[sel])
            if np.any(J[sel] != 0):
                col.add("K", [_g_factor(mid, bool(follows[sel][0]))] + sec("J"), lab + " torsion", kG[sel],
                        pat.subset(sel), G[sel])
            col.add("M", [(("MAT1", mid, "RHO"), 1)] + sec("A"), lab + " mass", mu[sel], pat.subset(sel),
                    wt * rho[sel] * A[sel])
            if np.any(nsm[sel] != 0):
                col.add("M", [], lab + " NSM", mu[sel], pat.subset(sel), wt * nsm[sel])


def _add_springs(model, col):
    for card in ("CELAS1", "CELAS2"):
        tab = model.elements.get(card)
        if tab is None or len(tab) == 0:
            continue
        # scalar springs connect g-set DOF directly (components are in CD)
        dofs, ke = _scalar_pairs(model, tab, card)
        k = tab["k"]
        for i in range(len(tab)):
            if card == "CELAS1":
                pid = int(tab["pid"][i])
                fac, lab = [(("PELAS", pid, "K1"), 1)], f"CELAS1 PELAS {pid}"
            else:
                fac, lab = [(("CELAS2", int(tab.ids[i]), "K"), 1)], f"CELAS2 {int(tab.ids[i])}"
            col.add_dofs("K", fac, lab, ke[i : i + 1], dofs[i : i + 1], np.array([k[i]]))


def _scalar_pairs(model, tab, card) -> tuple[np.ndarray, np.ndarray]:
    """g-set DOF (n, 2) and the unit element matrices (n, 2, 2) of scalar elements (CELAS, CMASS) joining
    two components in CD, or one to ground (its DOF repeated, the matrix's other entries zero)."""
    g = np.asarray(tab["nodes"], np.int64)
    c = tab["components"].astype(np.int64)
    n = len(tab)
    dofs = np.zeros((n, 2), np.int64)
    ke = np.zeros((n, 2, 2))
    for j in range(2):
        held = g[:, j] != 0
        if np.any(held):
            gi = model.grid_index(g[held, j], what=f"{card} grid")
            dofs[held, j] = 6 * gi + c[held, j] - 1
    both = (g[:, 0] != 0) & (g[:, 1] != 0)
    ke[both] = [[1.0, -1.0], [-1.0, 1.0]]
    only = ~both
    first = g[:, 0] != 0
    dofs[only & ~first, 0] = dofs[only & ~first, 1]
    dofs[only, 1] = dofs[only, 0]
    ke[only, 0, 0] = 1.0
    return dofs, ke


def _add_scalar_masses(model, col, wt):
    for card in ("CMASS1", "CMASS2"):
        tab = model.elements.get(card)
        if tab is None or len(tab) == 0:
            continue
        dofs, me = _scalar_pairs(model, tab, card)
        m = tab["m"]
        for i in range(len(tab)):
            if card == "CMASS1":
                pid = int(tab["pid"][i])
                fac, lab = [(("PMASS", pid, "M"), 1)], f"CMASS1 PMASS {pid}"
            else:
                fac, lab = [(("CMASS2", int(tab.ids[i]), "M"), 1)], f"CMASS2 {int(tab.ids[i])}"
            col.add_dofs("M", fac, lab, me[i : i + 1], dofs[i : i + 1], np.array([wt * m[i]]))


def _add_conm1(model, col, cd_axes, wt):
    tab = model.elements.get("CONM1")
    if tab is None or len(tab) == 0:
        return
    nodes = model.grid_index(tab["nodes"][:, 0], what="CONM1 grid")[:, None]
    m6 = to_cd(tab["mass6"], nodes, cd_axes, 6)
    pat = BlockPattern(nodes, model.n_grids)
    for i, eid in enumerate(tab.ids.tolist()):
        col.add("M", [], f"CONM1 {eid}", m6[i : i + 1], pat.subset(slice(i, i + 1)), [wt])


def _add_bushes(model, col, cd_axes):
    from femodel._elements_line import bush_matrices

    tab = model.elements.get("CBUSH")
    if tab is None or len(tab) == 0:
        return
    prop = model.properties.get("PBUSH")
    if prop is None:
        raise ModelError("CBUSH elements but no PBUSH defined")
    try:
        pr = prop.rows(tab["pid"], owners=tab.ids)
    except ModelError as exc:
        raise ModelError(f"CBUSH: {exc}") from None
    raw = tab["nodes"]
    grounded = raw[:, 1] == 0
    na = model.grid_index(raw[:, 0], what="CBUSH grid")
    nb = np.where(grounded, na, model.grid_index(np.where(grounded, raw[:, 0], raw[:, 1]), what="CBUSH grid"))
    nodes = np.column_stack([na, nb])
    kk = bush_matrices(model.xyz[na], model.xyz[nb], tab["axes"], tab["s"], grounded)
    pat = BlockPattern(nodes, model.n_grids)
    kvals = prop["k"][pr]
    pids = tab["pid"]
    for i in range(6):
        ke = to_cd(kk[i], nodes, cd_axes, 6)
        for pid in np.unique(pids):
            sel = (pids == pid) & (kvals[:, i] != 0)
            if np.any(sel):
                col.add("K", [(("PBUSH", int(pid), f"K{i + 1}"), 1)], f"CBUSH PBUSH {int(pid)} K{i + 1}", ke[sel], pat.subset(sel), kvals[sel, i])


def _add_conm2(model, col, cd_axes, wt):
    from femodel._elements_line import conm2_matrices

    tab = model.elements.get("CONM2")
    if tab is None or len(tab) == 0:
        return
    nodes = model.grid_index(tab["nodes"][:, 0], what="CONM2 grid")[:, None]
    m_unit, mi = conm2_matrices(tab["offset"], tab["inertia"])
    m_unit = to_cd(m_unit, nodes, cd_axes, 6)
    mi = to_cd(mi, nodes, cd_axes, 6)
    pat = BlockPattern(nodes, model.n_grids)
    mass = tab["mass"]
    for i, eid in enumerate(tab.ids.tolist()):
        one = pat.subset(slice(i, i + 1))
        col.add("M", [(("CONM2", eid, "M"), 1)], f"CONM2 {eid} mass", m_unit[i : i + 1], one, [wt * mass[i]])
        if np.any(mi[i] != 0):
            col.add("M", [], f"CONM2 {eid} inertia", mi[i : i + 1], one, [wt])


def _plane_stress(E, nu):
    c = (E / (1.0 - nu**2))[:, None, None]
    d = np.zeros((E.shape[0], 3, 3))
    d[:, 0, 0] = d[:, 1, 1] = 1.0
    d[:, 0, 1] = d[:, 1, 0] = nu
    d[:, 2, 2] = 0.5 * (1.0 - nu)
    return c * d


#: Shell elements of one card from which the property groups are formed on two threads.
_PARALLEL_MIN_ELEMENTS = 4096


def _add_shells(model, col, cd_axes, wt):
    cards = [c for c in ("CQUAD4", "CTRIA3") if c in model.elements and len(model.elements[c])]
    if not cards:
        return
    try:
        from femodel._elements_shell import shell_stiffness_batches, shell_mass, shell_stiffness
    except ImportError as exc:  # pragma: no cover - the kernel module ships with femodel
        raise ModelError(f"shell elements present but the shell kernels are unavailable: {exc}") from None
    prop = model.properties.get("PSHELL")
    pcomp = model.properties.get("PCOMP")
    for card in cards:
        tab = model.elements[card]
        if pcomp is not None and len(pcomp):
            lam = np.isin(tab["pid"], pcomp.ids)
            if np.any(lam):
                sub = Table(tab.card, tab.ids[lam], {key: v[lam] for key, v in tab.fields.items()})
                _add_pcomp(model, col, cd_axes, wt, card, sub, pcomp, shell_stiffness, shell_mass)
                if np.all(lam):
                    continue
                tab = Table(tab.card, tab.ids[~lam], {key: v[~lam] for key, v in tab.fields.items()})
        if prop is None:
            raise ModelError(f"{card} elements reference PSHELL {sorted(set(tab['pid'].tolist()))[:5]} but no PSHELL is defined")
        perm = np.argsort(tab["pid"], kind="stable")
        if np.any(perm != np.arange(len(tab))):
            # group elements by property so that each group is a contiguous slice (views, no copies)
            tab = Table(tab.card, tab.ids[perm], {key: v[perm] for key, v in tab.fields.items()})
        try:
            pr = prop.rows(tab["pid"], owners=tab.ids)
        except ModelError as exc:
            raise ModelError(f"{card}: {exc}") from None
        nodes = model.grid_index(tab["nodes"].ravel(), what=f"{card} grid").reshape(len(tab), -1)
        xyz = model.xyz[nodes]
        if np.any(tab["zoffs"] != 0):
            bad = tab.ids[tab["zoffs"] != 0][:5].tolist()
            raise ModelError(f"{card} {bad}: ZOFFS offsets are not supported")
        t_p = prop["t"][pr]
        t_el = tab["t"]
        t = np.where(np.all(np.isnan(t_el), axis=1), t_p, np.nanmean(np.where(np.isnan(t_el), t_p[:, None], t_el), axis=1))
        if np.any(~(t > 0)):
            raise ModelError(f"{card} {tab.ids[~(t > 0)][:5].tolist()}: thickness must be positive (PSHELL T or T1..T4)")
        n = len(tab)
        m1, m2, m3 = prop["mid1"][pr], prop["mid2"][pr], prop["mid3"][pr]
        ratio, tst, nsm = prop["bending_ratio"][pr], prop["ts_t"][pr], prop["nsm"][pr]
        dm = np.zeros((n, 3, 3))
        db = np.zeros((n, 3, 3))
        ds = np.zeros((n, 2, 2))
        rho = np.zeros(n)
        has1 = m1 > 0
        if np.any(has1):
            E1, G1, nu1, r1, _ = _mat(model, m1[has1], f"{card} PSHELL MID1")
            dm[has1] = _plane_stress(E1, nu1) * t[has1, None, None]
            rho[has1] = r1
        has2 = m2 > 0
        if np.any(has2):
            E2, G2, nu2, _, _ = _mat(model, m2[has2], f"{card} PSHELL MID2")
            db[has2] = _plane_stress(E2, nu2) * (ratio[has2] * t[has2] ** 3 / 12.0)[:, None, None]
        has3 = m3 > 0
        if np.any(has3):
            E3, G3, _, _, f3 = _mat(model, m3[has3], f"{card} PSHELL MID3")
            ds[has3] = np.eye(2)[None] * (G3 * tst[has3] * t[has3])[:, None, None]
        rigid_shear = has2 & ~has3
        if np.any(rigid_shear):
            # MID3 blank: no transverse shear flexibility; a stiff penalty stands in for it
            _, G2r, _, _, _ = _mat(model, m2[rigid_shear], f"{card} PSHELL MID2")
            ds[rigid_shear] = np.eye(2)[None] * (1e3 * G2r * t[rigid_shear])[:, None, None]
        pids = tab["pid"]
        upids, first, counts = np.unique(pids, return_index=True, return_counts=True)
        pat = BlockPattern(nodes, model.n_grids)
        sub = [pat.subset(slice(int(i0), int(i0 + c))) for i0, c in zip(first, counts)]
        has_nsm = [bool(np.any(nsm[int(i0):int(i0 + c)] != 0)) for i0, c in zip(first, counts)]
        wnsm = wt * nsm
        data: dict = {}

        def acc(g, name, ke, start):
            if (g, name) not in data:
                if sub[g].map is None:
                    sub[g]._build()
                data[(g, name)] = np.zeros(sub[g].nnz)
            sub[g].accumulate(data[(g, name)], ke, start)

        # element matrices are formed, rotated and scattered batch by batch (no (n, 24, 24) arrays);
        # membrane and drilling scale alike (E1 t): transformed and scattered as one term
        mscale = wt * rho * t

        def scatter_groups(groups):
            """Form and scatter the batches of the property groups ``groups`` (each in element order)."""
            for sl, blocks in shell_stiffness_batches(xyz, dm, db, ds, model.k6rot, ids=tab.ids,
                                                       merge={"membrane": ("membrane", "drill")}, bounds=first,
                                                       select=lambda sl: group_of[sl.start] in groups):
                g = int(group_of[sl.start])
                start = sl.start - int(first[g])
                nod = nodes[sl]
                for name, ke in blocks.items():
                    acc(g, name, to_cd(ke, nod, cd_axes, 6), start)
                mu_unit = to_cd(shell_mass(xyz[sl], np.ones(sl.stop - sl.start), model.coupmass, ids=tab.ids[sl]),
                                 nod, cd_axes, 6)
                for name, scale in (("mass", mscale), ("nsm", wnsm)):
                    if name == "nsm" and not has_nsm[g]:
                        continue
                    ke = mu_unit * np.asarray(scale[sl], dtype=float)[:, None, None]
                    acc(g, name, 0.5 * (ke + np.swapaxes(ke, 1, 2)), start)

        group_of = np.repeat(np.arange(upids.size), counts)
        # property groups write to their own data arrays: two threads take about half the elements each
        # (numpy releases the GIL in the kernels; every array is summed in the same order as on one thread)
        half = {int(g) for g in np.flatnonzero(np.cumsum(counts) - 0.5 * counts <= 0.5 * n)}
        rest = set(range(upids.size)) - half
        if n >= _PARALLEL_MIN_ELEMENTS and half and rest:
            with ThreadPoolExecutor(max_workers=1) as pool:
                other = pool.submit(scatter_groups, rest)
                try:
                    scatter_groups(half)
                except BaseException:
                    wait([other])
                    raise
                other.result()
        else:
            scatter_groups(set(range(upids.size)))
        mat = model.materials.get("MAT1")
        for g, (pid, i0) in enumerate(zip(upids, first)):
            lab = f"{card} PSHELL {int(pid)}"
            T = ("PSHELL", int(pid), "T")

            def term(name):
                return sub[g].csr(data[(g, name)])

            if m1[i0] > 0:
                f = [(("MAT1", int(m1[i0]), "E"), 1), (T, 1)]
                col.add_csr("K", f, lab + " membrane", term("membrane"))
                col.note("K", f, lab + " drilling")
                col.add_csr("M", [(("MAT1", int(m1[i0]), "RHO"), 1), (T, 1)], lab + " mass", term("mass"))
            if m2[i0] > 0:
                col.add_csr("K", [(("MAT1", int(m2[i0]), "E"), 1), (T, 3)], lab + " bending", term("bending"))
                if m3[i0] > 0:
                    r3 = mat.rows([m3[i0]])[0]
                    gf = _g_factor(int(m3[i0]), bool(mat["g_follows_e"][r3]))
                    col.add_csr("K", [gf, (T, 1)], lab + " transverse shear", term("shear"))
                else:
                    col.add_csr("K", [(("MAT1", int(m2[i0]), "E"), 1), (T, 1)],
                                lab + " transverse shear (rigid penalty)", term("shear"))
            if has_nsm[g]:
                col.add_csr("M", [], lab + " NSM", term("nsm"))


def _rotate_laminate(dm, dmb, db, ds, theta_deg):
    """Constitutive matrices from material axes (at THETA) to the element axes."""
    th = np.radians(theta_deg)
    c, s = np.cos(th), np.sin(th)
    te = np.zeros((th.size, 3, 3))
    te[:, 0] = np.stack([c * c, s * s, c * s], axis=1)
    te[:, 1] = np.stack([s * s, c * c, -c * s], axis=1)
    te[:, 2] = np.stack([-2 * c * s, 2 * c * s, c * c - s * s], axis=1)
    r = np.zeros((th.size, 2, 2))
    r[:, 0] = np.stack([c, s], axis=1)
    r[:, 1] = np.stack([-s, c], axis=1)
    tt = np.swapaxes(te, 1, 2)
    return tt @ dm @ te, tt @ dmb @ te, tt @ db @ te, np.swapaxes(r, 1, 2) @ ds @ r


def _add_pcomp(model, col, cd_axes, wt, card, tab, pcomp, shell_stiffness, shell_mass):
    """CQUAD4/CTRIA3 on PCOMP laminates: constant terms (no card-field monomial describes a laminate)."""
    if np.any(tab["mcid"] >= 0):
        bad = tab.ids[tab["mcid"] >= 0][:5].tolist()
        raise ModelError(f"{card} {bad}: MCID material axes with PCOMP are not supported (use THETA)")
    if np.any(tab["zoffs"] != 0):
        raise ModelError(f"{card} {tab.ids[tab['zoffs'] != 0][:5].tolist()}: ZOFFS offsets are not supported")
    r = pcomp.rows(tab["pid"], owners=tab.ids)
    dm, dmb, db, ds = _rotate_laminate(pcomp["dm"][r], pcomp["dmb"][r], pcomp["db"][r], pcomp["ds"][r], tab["theta"])
    # shear-rigid plies (MAT8 G1Z/G2Z blank): a stiff penalty, as for PSHELL without MID3
    pen = 1e3 * dm[:, 2, 2]
    ds = np.where(np.isfinite(ds), ds, pen[:, None, None] * np.eye(2)[None])
    nodes = model.grid_index(tab["nodes"].ravel(), what=f"{card} grid").reshape(len(tab), -1)
    xyz = model.xyz[nodes]
    coupled_b = bool(np.any(np.abs(dmb) > 0))
    k = shell_stiffness(xyz, dm, db, ds, model.k6rot, ids=tab.ids, dmb=dmb if coupled_b else None)
    m = shell_mass(xyz, pcomp["mu"][r], model.coupmass, ids=tab.ids)
    pat = BlockPattern(nodes, model.n_grids)
    pids = ",".join(str(int(p)) for p in np.unique(tab["pid"])[:5])
    for key, ke in k.items():
        col.add("K", [], f"{card} PCOMP {pids} {key}", to_cd(ke, nodes, cd_axes, 6), pat, symmetric=True)
    col.add("M", [], f"{card} PCOMP {pids} mass", to_cd(m, nodes, cd_axes, 6), pat, [wt] * len(tab))


def _iso_c(E, nu):
    lam = E * nu / ((1 + nu) * (1 - 2 * nu))
    mu = E / (2 * (1 + nu))
    c = np.zeros((E.shape[0], 6, 6))
    for i in range(3):
        for j in range(3):
            c[:, i, j] = lam
        c[:, i, i] = lam + 2 * mu
        c[:, 3 + i, 3 + i] = mu
    return c


def _add_solids(model, col, cd_axes, wt):
    names = [k for k, t in model.elements.items() if t.card in ("CTETRA", "CPENTA", "CHEXA", "CPYRAM") and len(t)]
    if not names:
        return
    from femodel._elements_solid import solid_mass, solid_stiffness

    prop = model.properties.get("PSOLID")
    if prop is None:
        raise ModelError("solid elements but no PSOLID defined")
    for name in names:
        tab = model.elements[name]
        try:
            pr = prop.rows(tab["pid"], owners=tab.ids)
        except ModelError as exc:
            raise ModelError(f"{tab.card}: {exc}") from None
        mids = prop["mid"][pr]
        E, G, nu, rho, _ = _mat(model, mids, f"{tab.card} PSOLID")
        nodes = model.grid_index(tab["nodes"].ravel(), what=f"{tab.card} grid").reshape(len(tab), -1)
        xyz = model.xyz[nodes]
        c_unit = _iso_c(np.ones_like(E), nu)
        k = solid_stiffness(xyz, c_unit, ids=tab.ids)
        m = solid_mass(xyz, np.ones(len(tab)), model.coupmass, ids=tab.ids)
        k = to_cd(k, nodes, cd_axes, 3)
        m = to_cd(m, nodes, cd_axes, 3)
        pat = BlockPattern(nodes, model.n_grids, 3)
        for mid in np.unique(mids):
            sel = mids == mid
            lab = f"{tab.card} PSOLID {','.join(str(int(p)) for p in np.unique(tab['pid'][sel])[:3])}"
            col.add("K", [(("MAT1", int(mid), "E"), 1)], lab + " stiffness", k[sel], pat.subset(sel), E[sel])
            col.add("M", [(("MAT1", int(mid), "RHO"), 1)], lab + " mass", m[sel], pat.subset(sel), wt * rho[sel])
