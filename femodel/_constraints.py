"""Rigid elements (RBE2, RBE3), single-point constraints and AUTOSPC as one sparse map.

The result is T (n_g, n_a) with u_g = T u_a: rows of dependent DOF of rigid
elements hold their dependence on independent DOF (chains resolved), and
columns of SPC'd DOF and of DOF that carry neither stiffness nor mass are
dropped.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from femodel._dofs import DofMap
from femodel._elements_line import rigid_offset
from femodel._model import FEModel, ModelError

#: Relative size below which a diagonal counts as zero for AUTOSPC.
AUTOSPC_RTOL = 1e-12


def _lambda6(cd_axes, i):
    lam = np.eye(6)
    if cd_axes is not None:
        lam[:3, :3] = cd_axes[i]
        lam[3:, 3:] = cd_axes[i]
    return lam


def rigid_rows(model: FEModel, cd_axes=None):
    """Dependent-DOF equations of all rigid elements.

    Returns
    -------
    dep : (k,) int64
        g-set index of each dependent DOF.
    R : csr_matrix (k, n_g)
        u_g[dep] = R @ u_g (R refers to other g-set DOF, possibly dependent ones).
    """
    if cd_axes is None and np.any(model.cd != 0):
        cd_axes = model.cd_axes()
    rows_dep, ri, rj, rv = [], [], [], []
    owner: dict[int, str] = {}

    def claim(dof, who):
        if dof in owner:
            g, c = divmod(dof, 6)
            raise ModelError(
                f"GRID {int(model.grid_ids[g])} component {c + 1} is dependent in both {owner[dof]} and {who}"
            )
        owner[dof] = who

    for r in model.rbe2:
        who = f"RBE2 {r.eid}"
        n = int(model.grid_index(r.gn, what=f"{who} GN")[0])
        lam_n = _lambda6(cd_axes, n)
        comps = [int(c) - 1 for c in r.components]
        for gm in r.gm:
            m = int(model.grid_index(gm, what=f"{who} GM")[0])
            if m == n:
                raise ModelError(f"{who}: GN {r.gn} also listed as dependent")
            rig = rigid_offset((model.xyz[n] - model.xyz[m])[None])[0]  # u_m = u_n + th_n x (x_m - x_n)
            # rigid_offset(w) maps grid motion to a point at +w; here the point is x_m relative to x_n
            rig = rigid_offset((model.xyz[m] - model.xyz[n])[None])[0]
            a = _lambda6(cd_axes, m).T @ rig @ lam_n
            for c in comps:
                dof = 6 * m + c
                claim(dof, who)
                k = len(rows_dep)
                rows_dep.append(dof)
                nz = np.flatnonzero(np.abs(a[c]) > 1e-14 * max(1.0, np.abs(a[c]).max()))
                ri.extend([k] * nz.size)
                rj.extend((6 * n + nz).tolist())
                rv.extend(a[c, nz].tolist())

    for r in model.rbe3:
        who = f"RBE3 {r.eid}"
        ref = int(model.grid_index(r.refgrid, what=f"{who} REFGRID")[0])
        xr = model.xyz[ref]
        grids, comps, weights = [], [], []
        for w, cs, gs in r.groups:
            for g in gs:
                gi = int(model.grid_index(g, what=f"{who} grid")[0])
                for c in cs:
                    grids.append(gi)
                    comps.append(int(c) - 1)
                    weights.append(w)
        if not grids:
            raise ModelError(f"{who}: no independent grids")
        grids = np.array(grids)
        comps = np.array(comps)
        weights = np.array(weights, float)
        uniq = np.unique(grids)
        lc = np.mean(np.linalg.norm(model.xyz[uniq] - xr, axis=1))
        # Rotational weights are scaled by Lc^2 (Lc: mean distance of the
        # independent grids from the reference grid), as Nastran documents.
        wscaled = np.where(comps >= 3, weights * lc**2, weights)
        G = np.zeros((grids.size, 6))
        for k, (gi, c) in enumerate(zip(grids, comps)):
            rig = rigid_offset((model.xyz[gi] - xr)[None])[0]
            G[k] = (_lambda6(cd_axes, gi).T @ rig)[c]
        A = G.T @ (wscaled[:, None] * G)
        try:
            cond = np.linalg.cond(A)
        except np.linalg.LinAlgError:
            cond = np.inf
        if not np.isfinite(cond) or cond > 1e12:
            raise ModelError(f"{who}: the independent grids/components do not determine all six motions of REFGRID {r.refgrid}")
        X = np.linalg.solve(A, G.T * wscaled[None, :])  # u_ref_basic = X u_ind
        Y = _lambda6(cd_axes, ref).T @ X
        for cstr in r.refc:
            c = int(cstr) - 1
            dof = 6 * ref + c
            claim(dof, who)
            k = len(rows_dep)
            rows_dep.append(dof)
            for coef, gi, cc in zip(Y[c], grids, comps):
                if coef != 0.0:
                    ri.append(k)
                    rj.append(6 * gi + cc)
                    rv.append(coef)
    n_g = 6 * model.n_grids
    R = sp.csr_matrix((rv, (ri, rj)), shape=(len(rows_dep), n_g))
    R.sum_duplicates()
    return np.array(rows_dep, np.int64), R


def constraint_transformation(model: FEModel, gset: DofMap, kg, mg):
    """T (n_g, n_a), the independent DofMap, the DofMap of AUTOSPC'd DOF, and the
    g-set indices of the a-set when T is a plain selection (no rigid elements), else None.

    Raises
    ------
    ModelError
        An SPC on a rigid-element dependent DOF, a circular rigid chain, or
        conflicting dependencies.
    """
    n_g = len(gset)
    dep, R = rigid_rows(model)
    is_dep = np.zeros(n_g, bool)
    is_dep[dep] = True
    indep = np.flatnonzero(~is_dep)
    col_of = np.full(n_g, -1, np.int64)
    col_of[indep] = np.arange(indep.size)
    if dep.size:
        Rc = R.tocsc()
        Rdd = Rc[:, dep]
        Rdi = Rc[:, indep]
        if Rdd.nnz:
            A = (sp.identity(dep.size, format="csc") - Rdd).tocsc()
            try:
                lu = spla.splu(A)
            except RuntimeError:
                raise ModelError("rigid elements form a circular chain of dependencies") from None
            C = sp.csr_matrix(lu.solve(Rdi.toarray())) if dep.size * indep.size < 5e7 else _sparse_solve(A, Rdi)
        else:
            C = Rdi.tocsr()
        C.eliminate_zeros()
        # assemble T rows: identity for independent, C for dependent
        Ci = C.tocoo()
        rows = np.concatenate([indep, dep[Ci.row]])
        cols = np.concatenate([np.arange(indep.size), Ci.col])
        vals = np.concatenate([np.ones(indep.size), Ci.data])
        T = sp.csr_matrix((vals, (rows, cols)), shape=(n_g, indep.size))
    else:
        T = sp.identity(n_g, format="csr")

    # SPC and GRID PS
    spc = np.zeros(n_g, bool)
    if model.spc_grid.size:
        gi = model.grid_index(model.spc_grid, what="SPC grid")
        spc[6 * gi + model.spc_component.astype(np.int64) - 1] = True
    spc |= model.ps.ravel()
    bad = spc & is_dep
    if np.any(bad):
        b = np.flatnonzero(bad)[:5]
        lst = [(int(gset.grid[i]), int(gset.component[i])) for i in b]
        raise ModelError(f"SPC on DOF that rigid elements make dependent (grid, component): {lst}")
    keep = ~spc[indep]

    # AUTOSPC: independent DOF with neither stiffness nor mass
    kept_idx = indep[keep]
    if dep.size == 0:
        kd = kg.diagonal()[kept_idx]
        md = mg.diagonal()[kept_idx]
    else:
        Tk = T[:, keep] if not np.all(keep) else T
        kd = np.asarray((Tk.multiply(kg @ Tk)).sum(axis=0)).ravel()
        md = np.asarray((Tk.multiply(mg @ Tk)).sum(axis=0)).ravel()
    is_rot = gset.component[kept_idx] >= 4
    empty = np.zeros(kept_idx.size, bool)
    for sel in (is_rot, ~is_rot):
        if not np.any(sel):
            continue
        kmax = np.abs(kd[sel]).max() if np.any(sel) else 0.0
        mmax = np.abs(md[sel]).max() if np.any(sel) else 0.0
        ktol = AUTOSPC_RTOL * kmax if kmax > 0 else 0.0
        mtol = AUTOSPC_RTOL * mmax if mmax > 0 else 0.0
        empty[sel] = (np.abs(kd[sel]) <= ktol) & (np.abs(md[sel]) <= mtol)
    auto = gset.subset(kept_idx[empty])
    final = np.flatnonzero(keep)[~empty]
    T = T[:, final].tocsr()
    aset = gset.subset(indep[final])
    selection = indep[final] if dep.size == 0 else None
    return T, aset, auto, selection


def _sparse_solve(A, B):
    lu = spla.splu(A.tocsc())
    cols = []
    B = B.tocsc()
    for j in range(B.shape[1]):
        b = B[:, [j]].toarray().ravel()
        if not b.any():
            cols.append(sp.csc_matrix((A.shape[0], 1)))
            continue
        cols.append(sp.csc_matrix(lu.solve(b)[:, None]))
    return sp.hstack(cols).tocsr()
