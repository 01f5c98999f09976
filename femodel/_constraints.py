"""Rigid elements (RBE2, RBE3), single-point constraints and AUTOSPC as one sparse map.

The result is T (n_g, n_a) with u_g = T u_a: rows of dependent DOF of rigid
elements hold their dependence on independent DOF (chains resolved), and
columns of SPC'd DOF and of DOF that carry neither stiffness nor mass are
dropped.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from femodel._dofs import DofMap
from femodel._elements_line import rigid_offset
from femodel._model import FEModel, ModelError

#: Relative size below which a stiffness diagonal counts as zero for AUTOSPC.
AUTOSPC_RTOL = 1e-12


def _lambda6(cd_axes, i):
    lam = np.eye(6)
    if cd_axes is not None:
        lam[:3, :3] = cd_axes[i]
        lam[3:, 3:] = cd_axes[i]
    return lam


def _lam6_many(cd_axes, idx: np.ndarray) -> np.ndarray:
    """(m, 6, 6) block-diagonal CD rotations of grids ``idx`` (u_basic = lam u_cd)."""
    out = np.broadcast_to(np.eye(6), (idx.size, 6, 6)).copy()
    if cd_axes is not None:
        out[:, :3, :3] = cd_axes[idx]
        out[:, 3:, 3:] = cd_axes[idx]
    return out


def rigid_rows(model: FEModel, cd_axes=None):
    """Dependent-DOF equations of all rigid elements (vectorized per element).

    Returns
    -------
    dep : (k,) int64
        g-set index of each dependent DOF.
    R : csr_matrix (k, n_g)
        u_g[dep] = R @ u_g (R refers to other g-set DOF, possibly dependent ones).

    Raises
    ------
    ModelError
        A DOF made dependent by two rigid elements (both named), a degenerate RBE3.
    """
    if cd_axes is None and np.any(model.cd != 0):
        cd_axes = model.cd_axes()
    n_g = 6 * model.n_grids
    owner = np.full(n_g, -1, np.int64)
    names: list[str] = []
    dep_parts, ri, rj, rv = [], [], [], []
    n_dep = 0

    def claim(dofs: np.ndarray, who: str):
        nonlocal n_dep
        taken = owner[dofs] >= 0
        dup_in_self = np.unique(dofs).size != dofs.size
        if np.any(taken) or dup_in_self:
            d = int(dofs[taken][0]) if np.any(taken) else int(dofs[0])
            g, c = divmod(d, 6)
            other = names[owner[d]] if owner[d] >= 0 else who
            raise ModelError(f"GRID {int(model.grid_ids[g])} component {c + 1} is dependent in both {other} and {who}")
        names.append(who)
        owner[dofs] = len(names) - 1
        dep_parts.append(dofs)
        first = n_dep
        n_dep += dofs.size
        return first

    def emit(first: int, coef: np.ndarray, cols: np.ndarray):
        """coef (k, p) dependence of k new dependent DOF on g-set columns cols (k, p) or (p,)."""
        k, p = coef.shape
        cols = np.broadcast_to(cols, (k, p))
        keep = np.abs(coef) > 1e-14 * np.maximum(1.0, np.abs(coef).max(axis=1, keepdims=True))
        rows = np.broadcast_to((first + np.arange(k))[:, None], (k, p))
        ri.append(rows[keep])
        rj.append(cols[keep])
        rv.append(coef[keep])

    for r in model.rbe2:
        who = f"RBE2 {r.eid}"
        n = int(model.grid_index(r.gn, what=f"{who} GN")[0])
        m = model.grid_index(np.array(r.gm, np.int64), what=f"{who} GM")
        if np.any(m == n):
            raise ModelError(f"{who}: GN {r.gn} also listed as dependent")
        comps = np.array([int(c) - 1 for c in r.components], np.int64)
        if comps.size == 0 or m.size == 0:
            continue
        rig = rigid_offset(model.xyz[m] - model.xyz[n])  # u_m = u_n + th_n x (x_m - x_n)
        a = np.swapaxes(_lam6_many(cd_axes, m), 1, 2) @ rig @ _lam6_many(cd_axes, np.array([n]))[0]
        coef = a[:, comps, :].reshape(-1, 6)  # (m * n_comp, 6)
        dofs = (6 * m[:, None] + comps[None, :]).ravel()
        first = claim(dofs, who)
        emit(first, coef, 6 * n + np.arange(6))

    for r in model.rbe3:
        who = f"RBE3 {r.eid}"
        ref = int(model.grid_index(r.refgrid, what=f"{who} REFGRID")[0])
        xr = model.xyz[ref]
        grids, comps, weights = [], [], []
        for w, cs, gs in r.groups:
            gi = model.grid_index(np.array(gs, np.int64), what=f"{who} grid")
            for c in cs:
                grids.append(gi)
                comps.append(np.full(gi.size, int(c) - 1))
                weights.append(np.full(gi.size, float(w)))
        if not grids:
            raise ModelError(f"{who}: no independent grids")
        grids = np.concatenate(grids)
        comps = np.concatenate(comps)
        weights = np.concatenate(weights)
        uniq = np.unique(grids)
        lc = np.mean(np.linalg.norm(model.xyz[uniq] - xr, axis=1))
        # Rotational weights are scaled by Lc^2 (Lc: mean distance of the
        # independent grids from the reference grid), as Nastran documents.
        wscaled = np.where(comps >= 3, weights * lc**2, weights)
        rig = rigid_offset(model.xyz[grids] - xr)
        G = (np.swapaxes(_lam6_many(cd_axes, grids), 1, 2) @ rig)[np.arange(grids.size), comps]  # (p, 6)
        A = G.T @ (wscaled[:, None] * G)
        try:
            cond = np.linalg.cond(A)
        except np.linalg.LinAlgError:
            cond = np.inf
        if not np.isfinite(cond) or cond > 1e12:
            raise ModelError(f"{who}: the independent grids/components do not determine all six motions of REFGRID {r.refgrid}")
        X = np.linalg.solve(A, G.T * wscaled[None, :])  # u_ref_basic = X u_ind
        Y = _lam6_many(cd_axes, np.array([ref]))[0].T @ X
        rc = np.array([int(c) - 1 for c in r.refc], np.int64)
        if rc.size == 0:
            continue
        first = claim(6 * ref + rc, who)
        emit(first, Y[rc], 6 * grids + comps)

    for sid, terms in getattr(model, "mpc", ()):
        who = f"MPC {sid}"
        g = model.grid_index(np.array([t[0] for t in terms], np.int64), what=f"{who} grid")
        dofs = 6 * g + np.array([t[1] - 1 for t in terms], np.int64)
        a = np.array([t[2] for t in terms], float)
        first = claim(dofs[:1], who)
        # sum a_i u_i = 0 with the first DOF dependent: u_1 = -sum_{i>1} (a_i / a_1) u_i
        if dofs.size > 1:
            emit(first, (-a[1:] / a[0])[None, :], dofs[1:])

    dep = np.concatenate(dep_parts) if dep_parts else np.zeros(0, np.int64)
    if ri:
        R = sp.csr_matrix((np.concatenate(rv), (np.concatenate(ri), np.concatenate(rj))), shape=(dep.size, n_g))
    else:
        R = sp.csr_matrix((dep.size, n_g))
    R.sum_duplicates()
    return dep, R


def constraint_transformation(model: FEModel, gset: DofMap, kg, mg):
    """The map u_g = T u_a and its parts.

    Returns
    -------
    T : csr (n_g, n_a)
    aset : DofMap
    autospc : DofMap
        DOF removed for having no stiffness (Nastran's AUTOSPC on the diagonal).
    selection : (n_a,) int
        g-set row of each independent DOF (T = P + D, P this selection).
    dep : (k,) int
        g-set rows of rigid-element dependent DOF.
    ddep : csr (k, n_a)
        Their rows of T (D is zero elsewhere).

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
            # chains (a dependent DOF referring to another dependent DOF): substitute
            # u_d = Rdi u_i + Rdd u_d repeatedly; an acyclic chain of depth k
            # settles after k sweeps, a cycle never does
            Rdd = Rdd.tocsr()
            C = Rdi.tocsr()
            for _ in range(64):
                nxt = (Rdi + Rdd @ C).tocsr()
                diff = abs(nxt - C)
                C = nxt
                if diff.nnz == 0 or diff.max() == 0.0:
                    break
            else:
                raise ModelError("rigid elements/MPCs form a circular chain of dependencies (or one deeper than 64)")
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

    # AUTOSPC: independent DOF without stiffness
    kept_idx = indep[keep]
    if dep.size == 0:
        kd = kg.diagonal()[kept_idx]
    else:
        # diag(T^T A T) with T = P + D (D: rows of dependent DOF only)
        Dk = C[:, np.flatnonzero(keep)].tocsr()

        def tdiag(a):
            a = sp.csr_matrix(a)
            d0 = a.diagonal()[kept_idx]
            cross = np.asarray(a[dep][:, kept_idx].multiply(Dk).sum(axis=0)).ravel()
            quad = np.asarray((a[dep][:, dep] @ Dk).multiply(Dk).sum(axis=0)).ravel()
            return d0 + 2.0 * cross + quad

        kd = tdiag(kg)
    is_rot = gset.component[kept_idx] >= 4
    empty = np.zeros(kept_idx.size, bool)
    for sel in (is_rot, ~is_rot):
        if not np.any(sel):
            continue
        kmax = np.abs(kd[sel]).max() if np.any(sel) else 0.0
        ktol = AUTOSPC_RTOL * kmax if kmax > 0 else 0.0
        # as Nastran's AUTOSPC: a DOF without stiffness is constrained (its mass,
        # if any, would only produce a spurious zero-frequency mode)
        empty[sel] = np.abs(kd[sel]) <= ktol
    auto = gset.subset(kept_idx[empty])
    final = np.flatnonzero(keep)[~empty]
    T = T[:, final].tocsr()
    aset = gset.subset(indep[final])
    selection = indep[final]
    ddep = C[:, final].tocsr() if dep.size else sp.csr_matrix((0, final.size))
    return T, aset, auto, selection, dep, ddep
