"""Shell transverse shear in series with the residual bending flexibility: exact series terms.

The shell kernel's shear term is a rational function of the thickness (and
of E when bending and shear materials carry different parameters); here it
is split off the monomial terms and carried as
:class:`~femodel.SeriesAffineMatrix` terms, elements grouped by equal ratio.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from femodel._params import ParameterSet
from femodel._pattern import _selection_map, _to_aset


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

    ``prepared`` is :func:`_shell_shear_elements` of the assembly's model.
    """
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
    from femodel._assembly import to_cd
    from femodel._elements_shell import RESIDUAL_BENDING_COEFF, bending_lengths, shell_frames, unit_shear
    from femodel._model import Table

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
        own = np.isin(tab["pid"], prop.ids)  # PSHELL elements only: a PCOMP laminate has no shear series
        if not np.all(own):
            tab = Table(tab.card, tab.ids[own], {key: v[own] for key, v in tab.fields.items()})
            if len(tab) == 0:
                continue
        pr = prop.rows(tab["pid"], owners=tab.ids)
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
        L = bending_lengths(xy)
        # the shear term per direction for unit shear stiffness (only the shear kernel is evaluated)
        unit = [to_cd(u, nodes, cd_axes, 6) for u in unit_shear(xyz, tab.ids[idx])]
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

