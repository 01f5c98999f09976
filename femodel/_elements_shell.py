"""Vectorized CQUAD4 / CTRIA3 shell element kernels (stiffness and mass).

Formulation (chosen to behave like Nastran's QUAD4/TRIA3, never copied from it):

* **Element frame.** Nodes are projected onto the mean plane through the
  centroid; the normal of a quad is the cross product of its diagonals
  (``G1->G3 x G2->G4``), of a triangle ``G1G2 x G1G3``.  The element x axis is
  the side G1->G2 projected onto that plane (Nastran's THETA = 0 material
  axis), y = z x x.  ``dm``, ``db`` and ``ds`` are given in this frame.
* **Warping.** Each projected point is tied to its grid by a rigid offset
  ``-h n`` (``h`` the signed distance of the grid from the mean plane), the
  usual rigid-link warping correction; rigid-body motion stays exactly
  stress-free.
* **Membrane.** Quad: bilinear isoparametric plus the two incompatible
  bubble modes per direction (Wilson's QM6 in Taylor's patch-test-passing
  form), 2x2 Gauss, condensed.  On a rectangle this reproduces a Nastran
  QUAD4 membrane stiffness published by reverse engineering to 4 digits.
  Triangle: constant strain.
* **Bending / transverse shear.** Reissner-Mindlin plate with independent
  rotations; quad: bilinear rotations, 2x2 Gauss bending, MITC4 assumed
  transverse shear strains (Bathe & Dvorkin 1985); triangle: constant
  curvature, MITC3 assumed shear (Lee & Bathe 2004).  The transverse shear
  flexibility is augmented by MacNeal's residual bending flexibility
  ``L^2 / (12 D)`` (see ``RESIDUAL_BENDING_COEFF``), which removes the excess
  stiffness of the linear plate and reproduces Nastran's coarse-mesh
  frequencies.
* **Drilling.** Penalty ``1e-6 K6ROT dm[2,2] * integral (theta_z - omega)^2 dA``
  with ``omega = (dv/dx - du/dy)/2`` the in-plane rotation of the membrane
  field (the K6ROT definition of the Nastran manuals); 2x2 Gauss (quad) /
  3-point (triangle) so that no spurious drilling mechanism remains.
* **Mass.** Lumped: ``mu * area / nn`` on each node's translations, no rotary
  inertia (Nastran's default); coupled (PARAM,COUPMASS): consistent
  translational mass from the bilinear/linear shape functions.

Sign conventions for plate rotations follow Nastran: the through-thickness
displacement is ``u = z theta_y``, ``v = -z theta_x``; curvatures
``kx = d theta_y/dx``, ``ky = -d theta_x/dy``, ``kxy = d theta_y/dy - d theta_x/dx``;
transverse shear ``gxz = dw/dx + theta_y``, ``gyz = dw/dy - theta_x``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ElementGeometryError", "shell_stiffness", "shell_mass", "shell_frames", "laminate_abd", "orthotropic_q"]

_G = 1.0 / np.sqrt(3.0)
_QUAD_XI = np.array([-1.0, 1.0, 1.0, -1.0])
_QUAD_ETA = np.array([-1.0, -1.0, 1.0, 1.0])
_QUAD_GAUSS = [(-_G, -_G), (_G, -_G), (_G, _G), (-_G, _G)]  # weights 1
_TRI_GAUSS = [(1.0 / 6.0, 1.0 / 6.0), (2.0 / 3.0, 1.0 / 6.0), (1.0 / 6.0, 2.0 / 3.0)]  # weights 1/6


class ElementGeometryError(ValueError):
    """Degenerate, inverted or badly shaped elements (lists the offending elements)."""


def _inv2(a: np.ndarray) -> np.ndarray:
    """Closed-form inverse of a stack of 2x2 matrices (numpy's per-matrix LAPACK calls are slow)."""
    det = a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] * a[..., 1, 0]
    out = np.empty_like(a)
    out[..., 0, 0] = a[..., 1, 1]
    out[..., 1, 1] = a[..., 0, 0]
    out[..., 0, 1] = -a[..., 0, 1]
    out[..., 1, 0] = -a[..., 1, 0]
    return out / det[..., None, None]


def _spd_solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve a stack of small SPD systems a x = b by a vectorized Cholesky (loops over the size only)."""
    m = a.shape[-1]
    low = np.zeros_like(a)
    for j in range(m):
        d = a[:, j, j] - np.sum(low[:, j, :j] ** 2, axis=1)
        low[:, j, j] = np.sqrt(d)
        for i in range(j + 1, m):
            low[:, i, j] = (a[:, i, j] - np.sum(low[:, i, :j] * low[:, j, :j], axis=1)) / low[:, j, j]
    y = np.empty_like(b)
    for i in range(m):
        y[:, i] = (b[:, i] - np.einsum("nk,nkr->nr", low[:, i, :i], y[:, :i])) / low[:, i, i, None]
    x = np.empty_like(b)
    for i in reversed(range(m)):
        x[:, i] = (y[:, i] - np.einsum("nk,nkr->nr", low[:, i + 1:, i], x[:, i + 1:])) / low[:, i, i, None]
    return x


def describe_bad(bad: np.ndarray, ids, what: str, kind: str) -> str:
    bad = np.flatnonzero(bad)
    if ids is not None:
        labels = [str(np.asarray(ids)[i]) for i in bad[:20]]
        who = "element ids"
    else:
        labels = [str(i) for i in bad[:20]]
        who = "element indices"
    more = "" if bad.size <= 20 else f" (and {bad.size - 20} more)"
    return f"{kind}: {bad.size} element(s) {what}; {who} {', '.join(labels)}{more}"


def check_xyz(xyz: np.ndarray, nn_allowed: tuple[int, ...], kind: str) -> np.ndarray:
    xyz = np.asarray(xyz, dtype=float)
    if xyz.ndim != 3 or xyz.shape[2] != 3 or xyz.shape[1] not in nn_allowed:
        raise ValueError(
            f"{kind}: xyz must have shape (n, nn, 3) with nn in {nn_allowed}, got {xyz.shape}"
        )
    if not np.all(np.isfinite(xyz)):
        raise ElementGeometryError(describe_bad(~np.isfinite(xyz).all(axis=(1, 2)), None,
                                             "have non-finite coordinates", kind))
    return xyz


def shell_frames(xyz: np.ndarray, ids=None):
    """Element frames, projected in-plane coordinates and warp offsets.

    Parameters
    ----------
    xyz : ndarray, shape (n, nn, 3)
        Node coordinates in basic [m]; nn = 3 (CTRIA3) or 4 (CQUAD4).
    ids : array_like of int, optional
        Element ids used in error messages.

    Returns
    -------
    rot : ndarray, shape (n, 3, 3)
        Rows are the element x, y, z (normal) axes in basic.
    xy : ndarray, shape (n, nn, 2)
        Projected node coordinates in the element frame, origin at the centroid [m].
    h : ndarray, shape (n, nn)
        Signed distance of each grid from the mean plane along the normal [m].
    """
    nn = xyz.shape[1]
    kind = "CQUAD4" if nn == 4 else "CTRIA3"
    c = xyz.mean(axis=1)
    if nn == 4:
        nrm = np.cross(xyz[:, 2] - xyz[:, 0], xyz[:, 3] - xyz[:, 1])
    else:
        nrm = np.cross(xyz[:, 1] - xyz[:, 0], xyz[:, 2] - xyz[:, 0])
    nlen = np.linalg.norm(nrm, axis=1)
    scale = np.max(np.linalg.norm(xyz - c[:, None, :], axis=2), axis=1)
    bad = ~(nlen > 1e-12 * np.maximum(scale, 1e-300) ** 2)
    if bad.any():
        raise ElementGeometryError(describe_bad(bad, ids, "have zero area (coincident or collinear grids)", kind))
    ez = nrm / nlen[:, None]
    side = xyz[:, 1] - xyz[:, 0]
    side = side - np.sum(side * ez, axis=1)[:, None] * ez
    slen = np.linalg.norm(side, axis=1)
    bad = ~(slen > 1e-12 * scale)
    if bad.any():
        raise ElementGeometryError(describe_bad(bad, ids, "have coincident grids G1 and G2", kind))
    ex = side / slen[:, None]
    ey = np.cross(ez, ex)
    rot = np.stack([ex, ey, ez], axis=1)
    rel = xyz - c[:, None, :]
    local = np.einsum("nij,nkj->nki", rot, rel)
    return rot, local[:, :, :2].copy(), local[:, :, 2].copy()


def _quad_derivs(xi: float, eta: float):
    """Shape functions and natural derivatives of the bilinear quad at one point."""
    n = 0.25 * (1 + _QUAD_XI * xi) * (1 + _QUAD_ETA * eta)
    dxi = 0.25 * _QUAD_XI * (1 + _QUAD_ETA * eta)
    deta = 0.25 * _QUAD_ETA * (1 + _QUAD_XI * xi)
    return n, np.stack([dxi, deta])  # (4,), (2, 4)


def _jacobian(dnat: np.ndarray, xy: np.ndarray):
    """Batched 2-D Jacobian J[a, b] = d x_b / d nat_a, its determinant and inverse."""
    jac = np.einsum("ak,nkb->nab", dnat, xy)
    det = jac[:, 0, 0] * jac[:, 1, 1] - jac[:, 0, 1] * jac[:, 1, 0]
    inv = np.empty_like(jac)
    inv[:, 0, 0] = jac[:, 1, 1]
    inv[:, 1, 1] = jac[:, 0, 0]
    inv[:, 0, 1] = -jac[:, 0, 1]
    inv[:, 1, 0] = -jac[:, 1, 0]
    inv /= det[:, None, None]
    return jac, det, inv


def _membrane_b(dxy: np.ndarray, nn: int) -> np.ndarray:
    """(n, 3, 6nn) membrane strain-displacement matrix from Cartesian derivatives (n, 2, nn)."""
    b = np.zeros((dxy.shape[0], 3, 6 * nn))
    b[:, 0, 0::6] = dxy[:, 0]
    b[:, 1, 1::6] = dxy[:, 1]
    b[:, 2, 0::6] = dxy[:, 1]
    b[:, 2, 1::6] = dxy[:, 0]
    return b


def _bending_b(dxy: np.ndarray, nn: int) -> np.ndarray:
    """(n, 3, 6nn) curvature-displacement matrix (Nastran rotation signs)."""
    b = np.zeros((dxy.shape[0], 3, 6 * nn))
    b[:, 0, 4::6] = dxy[:, 0]
    b[:, 1, 3::6] = -dxy[:, 1]
    b[:, 2, 4::6] = dxy[:, 1]
    b[:, 2, 3::6] = -dxy[:, 0]
    return b


def _drill_b(n_shape: np.ndarray, dxy: np.ndarray, nn: int) -> np.ndarray:
    """(n, 6nn) row giving theta_z - (dv/dx - du/dy)/2 at a point."""
    b = np.zeros((dxy.shape[0], 6 * nn))
    b[:, 5::6] = n_shape
    b[:, 1::6] = -0.5 * dxy[:, 0]
    b[:, 0::6] = 0.5 * dxy[:, 1]
    return b


def _covariant_shear(n_shape, dnat_row, xnat, nn):
    """(n, 6nn) covariant transverse shear w_a + beta . x_a at a point.

    ``n_shape`` (nn,), ``dnat_row`` (nn,) derivative along natural direction a,
    ``xnat`` (n, 2) = d(x, y)/da at the point; beta = (theta_y, -theta_x).
    """
    b = np.zeros((xnat.shape[0], 6 * nn))
    b[:, 2::6] = dnat_row[None, :]
    b[:, 4::6] = n_shape[None, :] * xnat[:, 0:1]
    b[:, 3::6] = -n_shape[None, :] * xnat[:, 1:2]
    return b


def _btdb(b: np.ndarray, d: np.ndarray, w: np.ndarray) -> np.ndarray:
    """sum_n w * B^T D B, batched: b (n, r, m), d (n, r, r), w (n,) -> (n, m, m)."""
    db = np.matmul(d, b)
    return np.matmul(np.swapaxes(b, 1, 2), db * w[:, None, None])


def _cols(nn: int, comps) -> np.ndarray:
    """Element DOF indices (6 per grid) of the given local components, grid-major."""
    return np.array([6 * i + c for i in range(nn) for c in comps])


# local components each term acts on: u v w theta_x theta_y theta_z = 0..5
_MEM, _PLATE, _DRILL, _COUP = (0, 1), (2, 3, 4), (0, 1, 5), (0, 1, 2, 3, 4)


def _mitc4_tying(xy):
    """MITC4 covariant shear rows at the tying points, (n, 12) each on the plate DOF (w, theta_x, theta_y)."""
    cp = _cols(4, _PLATE)
    # gamma_xi at (0, -1) and (0, +1); gamma_eta at (-1, 0), (+1, 0)
    tying = {}
    for key, (xi, eta, a) in {"A": (0.0, -1.0, 0), "C": (0.0, 1.0, 0), "D": (-1.0, 0.0, 1), "B": (1.0, 0.0, 1)}.items():
        nsh, dn = _quad_derivs(xi, eta)
        jac, _, _ = _jacobian(dn, xy)
        tying[key] = _covariant_shear(nsh, dn[a], jac[:, a, :], 4)[:, cp]
    return tying


def _mitc4_bs(tying, inv, xi, eta):
    """(n, 2, 12) MITC4 assumed transverse shear strains (gxz, gyz) at (xi, eta) on the plate DOF."""
    g_xi = 0.5 * (1 - eta) * tying["A"] + 0.5 * (1 + eta) * tying["C"]
    g_eta = 0.5 * (1 - xi) * tying["D"] + 0.5 * (1 + xi) * tying["B"]
    return np.einsum("nab,nbm->nam", inv, np.stack([g_xi, g_eta], axis=1))


def _quad_local(xy, dm, db, ds, kdrill, ids, dmb=None):
    """Local stiffness terms of CQUAD4 as (matrix, column indices) pairs on their own DOF subsets."""
    n = xy.shape[0]
    cm, cp, cd, cc = _cols(4, _MEM), _cols(4, _PLATE), _cols(4, _DRILL), _cols(4, _COUP)
    km = np.zeros((n, 8, 8))
    kb = np.zeros((n, 12, 12))
    ks = np.zeros((n, 12, 12))
    kd = np.zeros((n, 12, 12))
    # membrane incompatible modes (Wilson QM6 with Taylor's centroid-Jacobian form):
    # u, v += a (1 - xi^2) + b (1 - eta^2), condensed after integration
    _, d0 = _quad_derivs(0.0, 0.0)
    _, det0, inv0 = _jacobian(d0, xy)
    kua = np.zeros((n, 8, 4))
    kaa = np.zeros((n, 4, 4))
    if dmb is not None:
        kc = np.zeros((n, 20, 20))
        kuac = np.zeros((n, 20, 4))
        kab = np.zeros((n, 4, 20))
    tying = _mitc4_tying(xy)
    for xi, eta in _QUAD_GAUSS:
        nsh, dn = _quad_derivs(xi, eta)
        _, det, inv = _jacobian(dn, xy)
        if np.any(det <= 0):
            raise ElementGeometryError(describe_bad(det <= 0, ids,
                                                 "are inverted, concave or have a re-entrant corner "
                                                 "(non-positive Jacobian; check grid order)", "CQUAD4"))
        dxy = np.einsum("nab,bk->nak", inv, dn)
        bm_full = _membrane_b(dxy, 4)
        bm = bm_full[:, :, cm]
        km += _btdb(bm, dm, det)
        dinc = np.einsum("nab,bk->nak", inv0, np.diag([-2.0 * xi, -2.0 * eta])) * (det0 / det)[:, None, None]
        ba = np.zeros((n, 3, 4))
        ba[:, 0, 0:2] = dinc[:, 0]
        ba[:, 1, 2:4] = dinc[:, 1]
        ba[:, 2, 0:2] = dinc[:, 1]
        ba[:, 2, 2:4] = dinc[:, 0]
        dba = np.matmul(dm, ba) * det[:, None, None]
        kua += np.matmul(np.swapaxes(bm, 1, 2), dba)
        kaa += np.matmul(np.swapaxes(ba, 1, 2), dba)
        bb_full = _bending_b(dxy, 4)
        kb += _btdb(bb_full[:, :, cp], db, det)
        if dmb is not None:
            bmc, bbc = bm_full[:, :, cc], bb_full[:, :, cc]
            cbb = np.matmul(dmb, bbc) * det[:, None, None]
            kc += np.matmul(np.swapaxes(bmc, 1, 2), cbb)
            kab += np.matmul(np.swapaxes(ba, 1, 2), cbb)
            kuac += np.matmul(np.swapaxes(bmc, 1, 2), dba)
        ks += _btdb(_mitc4_bs(tying, inv, xi, eta), ds, det)
        bd = _drill_b(nsh, dxy, 4)[:, cd]
        kd += np.einsum("ni,nj->nij", bd, bd * (kdrill * det)[:, None])
    terms = [(kb, cp), (ks, cp), (kd, cd)]
    if dmb is None:
        km = km - np.matmul(kua, _spd_solve(kaa, np.swapaxes(kua, 1, 2)))
        return [(km, cm)] + terms + [None]
    # condense the bubbles out of the coupled membrane-bending system
    sol = _spd_solve(kaa, np.concatenate([np.swapaxes(kua, 1, 2), kab], axis=2))
    xm, xb = sol[:, :, :8], sol[:, :, 8:]
    km = km - np.matmul(kua, xm)
    half = kc - np.matmul(kuac, xb)
    kcp = half + np.swapaxes(half, 1, 2) - np.matmul(np.swapaxes(kab, 1, 2), xb)
    return [(km, cm)] + terms + [(kcp, cc)]


def _tri_shape(r, s):
    return np.array([1.0 - r - s, r, s])


def _mitc3_bs(xy, inv):
    """(n, 2, 9) MITC3 assumed transverse shear strains at the 3 Gauss points, on the plate DOF."""
    cp = _cols(3, _PLATE)
    dn = np.array([[-1.0, 1.0, 0.0], [-1.0, 0.0, 1.0]])
    jac = np.einsum("ak,nkb->nab", dn, xy)

    def cov(r, s, a):
        return _covariant_shear(_tri_shape(r, s), dn[a], jac[:, a, :], 3)[:, cp]

    e1 = cov(0.5, 0.0, 0)
    e2 = cov(0.0, 0.5, 1)
    c = e2 - e1 - cov(0.5, 0.5, 1) + cov(0.5, 0.5, 0)
    return [np.einsum("nab,nbm->nam", inv, np.stack([e1 + c * s, e2 - c * r], axis=1)) for r, s in _TRI_GAUSS]


def _tri_local(xy, dm, db, ds, kdrill, ids, dmb=None):
    """Local stiffness terms of CTRIA3 as (matrix, column indices) pairs on their own DOF subsets."""
    n = xy.shape[0]
    cm, cp, cd, cc = _cols(3, _MEM), _cols(3, _PLATE), _cols(3, _DRILL), _cols(3, _COUP)
    dn = np.array([[-1.0, 1.0, 0.0], [-1.0, 0.0, 1.0]])
    _, det, inv = _jacobian(dn, xy)
    if np.any(det <= 0):
        raise ElementGeometryError(describe_bad(det <= 0, ids, "have non-positive area", "CTRIA3"))
    area = 0.5 * det
    dxy = np.einsum("nab,bk->nak", inv, dn)
    bm = _membrane_b(dxy, 3)
    bb = _bending_b(dxy, 3)
    km = _btdb(bm[:, :, cm], dm, area)
    kb = _btdb(bb[:, :, cp], db, area)
    coupling = None
    if dmb is not None:
        half = np.matmul(np.swapaxes(bm[:, :, cc], 1, 2), np.matmul(dmb, bb[:, :, cc])) * area[:, None, None]
        coupling = (half + np.swapaxes(half, 1, 2), cc)
    ks = np.zeros((n, 9, 9))
    kd = np.zeros((n, 9, 9))
    for (r, s), bs in zip(_TRI_GAUSS, _mitc3_bs(xy, inv)):
        ks += _btdb(bs, ds, det / 6.0)
        bd = _drill_b(_tri_shape(r, s), dxy, 3)[:, cd]
        kd += np.einsum("ni,nj->nij", bd, bd * (kdrill * det / 6.0)[:, None])
    return [(km, cm), (kb, cp), (ks, cp), (kd, cd), coupling]


def bending_lengths(xy: np.ndarray) -> np.ndarray:
    """(n, 2) element lengths along the element x and y axes [m].

    Quad: mean of the two sides G1G2/G4G3 and G1G4/G2G3; triangle: extent of
    the projected nodes along x and y divided by sqrt(2) (a triangle covers
    half its bounding box; with this length MITC3 converges at second order on
    the simply supported plate instead of locking or over-softening).
    """
    if xy.shape[1] == 4:
        a = 0.5 * (np.linalg.norm(xy[:, 1] - xy[:, 0], axis=1) + np.linalg.norm(xy[:, 2] - xy[:, 3], axis=1))
        b = 0.5 * (np.linalg.norm(xy[:, 3] - xy[:, 0], axis=1) + np.linalg.norm(xy[:, 2] - xy[:, 1], axis=1))
        return np.stack([a, b], axis=1)
    return (xy.max(axis=1) - xy.min(axis=1)) / np.sqrt(2.0)


def _effective_shear(ds: np.ndarray, db: np.ndarray, lengths: np.ndarray, coeff: float) -> np.ndarray:
    """Transverse shear stiffness in series with the residual bending flexibility.

    ``ds_eff = (ds^-1 + coeff / 12 * diag(a^2 / D11, b^2 / D22))^-1`` with
    ``a, b`` the element lengths along x and y.  With ``coeff = 1`` a linear
    (Timoshenko) element with a hinged end reproduces the exact cubic
    (Euler-Bernoulli) stiffness: this is MacNeal's residual bending
    flexibility.  Infinite entries of ``ds`` mean shear-rigid; elements
    without bending stiffness get no transverse shear stiffness.
    """
    n = ds.shape[0]
    out = np.zeros((n, 2, 2))
    dbd = np.stack([db[:, 0, 0], db[:, 1, 1]], axis=1)
    plate = np.all(dbd > 0, axis=1)
    rigid = ~np.all(np.isfinite(ds), axis=(1, 2))
    flex = np.zeros((n, 2, 2))
    flex[plate, 0, 0] = coeff * lengths[plate, 0] ** 2 / (12.0 * dbd[plate, 0])
    flex[plate, 1, 1] = coeff * lengths[plate, 1] ** 2 / (12.0 * dbd[plate, 1])
    soft = plate & ~rigid
    if soft.any():
        flex[soft] += _inv2(ds[soft])
    fdet = flex[:, 0, 0] * flex[:, 1, 1] - flex[:, 0, 1] * flex[:, 1, 0]
    ok = plate & (np.abs(fdet) > 0)
    out[ok] = _inv2(flex[ok])
    # shear-rigid plate without the residual term: a stiff penalty (1e4 x bending scale)
    pen = plate & ~ok
    out[pen, 0, 0] = 1e4 * 12.0 * dbd[pen, 0] / lengths[pen, 0] ** 2
    out[pen, 1, 1] = 1e4 * 12.0 * dbd[pen, 1] / lengths[pen, 1] ** 2
    keep = ~plate
    out[keep] = np.where(np.isfinite(ds[keep]), ds[keep], 0.0)
    return out


#: Elements per batch in the element-to-basic transformation: the batched
#: (batch, 6nn, 6nn) intermediates then stay in cache (about 4x faster than
#: one pass over all elements at 200k DOF).
_BATCH = 512


def _congruence(terms, rot: np.ndarray, h: np.ndarray, out: np.ndarray) -> np.ndarray:
    """T^T K T of compact local terms into basic, written to ``out`` (n, 6nn, 6nn).

    ``terms`` is a list of (k, cols): k (n, c, c) on the element DOF subset
    ``cols`` (the same local components at every grid, grid-major); they are
    summed.  The map T from basic grid DOF to local DOF of the projected
    points is block-diagonal per grid, ``t_i = S_i diag(R, R)``: the rotation
    R (rows of ``rot``) on translations and rotations, and the rigid warp
    offset ``S_i`` (u_p = u - h theta_y, v_p = v + h theta_x in the element
    frame).  So the product is taken in two sparse steps: S^T K S as row and
    column updates in the local frame, then R^T B R on each 3x3 block
    (64 small products instead of two dense 24x24 ones).  The result is made
    exactly symmetric by mirroring the upper triangle.
    """
    n, nn = h.shape
    nd = 6 * nn
    iu, ju = np.triu_indices(nd, 1)
    # flat positions of each term's compact entries in the (6nn, 6nn) local matrix
    flat = [(cols[:, None] * nd + cols[None, :]).ravel() for _, cols in terms]
    warp = any(bool(np.any(cols % 6 < 2)) for _, cols in terms)
    for s0 in range(0, n, _BATCH):
        sl = slice(s0, min(n, s0 + _BATCH))
        m = sl.stop - sl.start
        loc = np.zeros((m, nd * nd))
        for i, ((k, _), idx) in enumerate(zip(terms, flat)):
            if i == 0:
                loc[:, idx] = k[sl].reshape(m, -1)
            else:
                loc[:, idx] += k[sl].reshape(m, -1)
        loc = loc.reshape(m, nn, 6, nn, 6)
        hh = h[sl]
        if warp and np.any(hh != 0):
            hc = hh[:, None, None, :]
            loc[..., 4] -= hc * loc[..., 0]
            loc[..., 3] += hc * loc[..., 1]
            hr = hh[:, :, None, None]
            loc[:, :, 4] -= hr * loc[:, :, 0]
            loc[:, :, 3] += hr * loc[:, :, 1]
        r = rot[sl]
        x = np.matmul(loc.reshape(m, nd * 2 * nn, 3), r)
        blk = out[sl]
        np.matmul(np.swapaxes(r, 1, 2)[:, None], x.reshape(m, 2 * nn, 3, nd), out=blk.reshape(m, 2 * nn, 3, nd))
        # exact symmetry: mirror the upper triangle
        blk[:, ju, iu] = blk[:, iu, ju]
    return out


RESIDUAL_BENDING_COEFF = 1.0
"""Coefficient of the residual bending flexibility put in series with the
transverse shear (MacNeal's correction of the too-stiff linear plate; 1 makes
a hinged linear element exact for a linearly varying moment).  With it the
shell decks femap_exhaust, dakota_cylinder and nx_sine_solids agree with
Nastran within 1 % (docs/validation.md, Shells and solids)."""


def shell_stiffness(xyz, dm, db, ds, k6rot, ids=None, residual_bending=True, dmb=None) -> dict[str, np.ndarray]:
    """Stiffness of CQUAD4 / CTRIA3 shells, split by constitutive term.

    Parameters
    ----------
    xyz : array_like, shape (n, nn, 3)
        Grid coordinates in basic [m]; nn = 4 (CQUAD4) or 3 (CTRIA3), in
        connectivity order.
    dm : array_like, shape (n, 3, 3)
        Membrane stiffness (material matrix times thickness) [N/m], in the
        element frame (x along G1->G2 projected on the mean plane).
    db : array_like, shape (n, 3, 3)
        Bending stiffness D (12 I / t^3 already applied) [N m].
    ds : array_like, shape (n, 2, 2)
        Transverse shear stiffness (G * TS/T * t) [N/m]; zeros for a
        shear-rigid plate are not allowed by this formulation (use a large
        value instead).
    k6rot : float
        Nastran PARAM,K6ROT (dimensionless); 0 gives no drilling stiffness.
    ids : array_like of int, shape (n,), optional
        Element ids used in error messages.
    residual_bending : bool, default True
        Put the residual bending flexibility ``RESIDUAL_BENDING_COEFF * L_i^2 /
        (12 D_ii)`` (L_i the element length along axis i) in series with the transverse shear (as Nastran's QUAD4
        does in spirit; without it coarse meshes are 2-120 % too stiff).  With it
        the ``shear`` term depends on ``ds`` and ``db`` (homogeneous of degree
        one in both together, e.g. exact under scaling of E, but not a
        monomial in the thickness); False makes it exactly linear in ``ds``
        at the price of a much stiffer coarse-mesh plate.
    dmb : array_like, shape (n, 3, 3), optional
        Membrane-bending coupling matrix B [N] (PSHELL MID4 times t^2, a
        laminate's B, or ``z0 * A`` for a normal offset), with membrane
        strain ``e(z) = e0 + z k`` and z along the element normal.  When
        given, a ``coupling`` term is returned as well.

    Returns
    -------
    dict of str to ndarray, each shape (n, 6nn, 6nn)
        ``membrane`` (homogeneous of degree one in dm; the quad's condensed
        incompatible modes make it exactly linear under scalar scaling of dm),
        ``bending`` (linear in db), ``shear`` (linear in ds, see
        ``residual_bending``) and ``drill`` (linear in dm[2,2] and K6ROT), in
        basic coordinates, DOF per grid T1 T2 T3 R1 R2 R3; with ``dmb`` also
        ``coupling`` (linear in dmb for triangles; for quads it also holds the
        bending correction from the condensed membrane bubbles, quadratic in
        dmb).  Their sum is the element stiffness.

    Raises
    ------
    ElementGeometryError
        Zero-area, inverted or re-entrant elements (listed by id or index).
    """
    return _shell_stiffness(xyz, dm, db, ds, k6rot, ids, residual_bending, dmb)


def _shell_stiffness(xyz, dm, db, ds, k6rot, ids=None, residual_bending=True, dmb=None, merge=None):
    """:func:`shell_stiffness` with ``merge`` (see :func:`shell_stiffness_batches`): terms that scale alike summed."""
    xyz = check_xyz(xyz, (3, 4), "shell")
    n, nn = xyz.shape[:2]
    out: dict[str, np.ndarray] = {}
    for sl, blocks in shell_stiffness_batches(xyz, dm, db, ds, k6rot, ids, residual_bending, dmb, merge):
        for name, blk in blocks.items():
            if name not in out:
                out[name] = np.empty((n, 6 * nn, 6 * nn))
            out[name][sl] = blk
    return out


def shell_stiffness_batches(xyz, dm, db, ds, k6rot, ids=None, residual_bending=True, dmb=None, merge=None,
                            bounds=(), select=None):
    """:func:`shell_stiffness` in batches of elements (for assembly without the full (n, 6nn, 6nn) arrays).

    Yields ``(slice, {name: ndarray (m, 6nn, 6nn)})`` per batch of elements;
    the arrays are only valid until the next batch.  ``merge`` maps an
    output name to the term names summed into it (e.g. ``{"membrane":
    ("membrane", "drill")}`` for terms that scale alike); other terms come
    on their own.  No batch straddles an element index in ``bounds``;
    ``select(slice) -> bool`` skips the batches it rejects (the others are
    computed exactly as without it).  A geometry error is raised with the
    complete list of offending elements.
    """
    xyz = check_xyz(xyz, (3, 4), "shell")
    n, nn = xyz.shape[:2]
    dm = np.broadcast_to(np.asarray(dm, dtype=float), (n, 3, 3))
    db = np.broadcast_to(np.asarray(db, dtype=float), (n, 3, 3))
    ds = np.broadcast_to(np.asarray(ds, dtype=float), (n, 2, 2))
    k6rot = float(k6rot)
    if k6rot < 0:
        raise ValueError(f"PARAM,K6ROT must be >= 0, got {k6rot}")
    rot, xy, h = shell_frames(xyz, ids)
    coeff = RESIDUAL_BENDING_COEFF if residual_bending else 0.0
    ds = _effective_shear(ds, db, bending_lengths(xy), coeff)
    kdrill = 1e-6 * k6rot * dm[:, 2, 2]
    if dmb is not None:
        dmb = np.broadcast_to(np.asarray(dmb, dtype=float), (n, 3, 3))
    kernel = _quad_local if nn == 4 else _tri_local
    merged = {name for names in (merge or {}).values() for name in names}
    groups = dict(merge or {})
    for name in _TERM_NAMES:
        if name not in merged and name not in groups:
            groups[name] = (name,)
    nd = 6 * nn
    for sl in _batch_slices(n, 8 * _BATCH, bounds):
        if select is not None and not select(sl):
            continue
        try:
            # contiguous batches: the kernels are about twice as fast as on broadcast views
            local = kernel(xy[sl], np.ascontiguousarray(dm[sl]), np.ascontiguousarray(db[sl]),
                           np.ascontiguousarray(ds[sl]), kdrill[sl], None if ids is None else np.asarray(ids)[sl],
                           None if dmb is None else np.ascontiguousarray(dmb[sl]))
        except ElementGeometryError:
            if sl.start == 0 and sl.stop == n:
                raise
            kernel(xy, dm, db, ds, kdrill, ids, dmb)  # raises with the complete list
            raise
        terms = dict(zip(_TERM_NAMES, local))
        m = sl.stop - sl.start
        blocks = {}
        for name, members in groups.items():
            parts = [terms[t] for t in members if terms.get(t) is not None]
            if parts:
                blocks[name] = _congruence(parts, rot[sl], h[sl], np.empty((m, nd, nd)))
        yield sl, blocks


_TERM_NAMES = ("membrane", "bending", "shear", "drill", "coupling")


def _batch_slices(n: int, step: int, bounds=()):
    """Slices of at most ``step`` elements covering 0..n, cut at every index in ``bounds``."""
    cuts = sorted({0, n} | {int(b) for b in bounds if 0 < int(b) < n})
    for a, b in zip(cuts[:-1], cuts[1:]):
        for s0 in range(a, b, step):
            yield slice(s0, min(b, s0 + step))


def unit_shear(xyz, ids=None) -> tuple[np.ndarray, np.ndarray]:
    """Transverse shear stiffness per direction for unit shear stiffness, in basic.

    Returns the two (n, 6nn, 6nn) matrices of the shear term for
    ``ds = diag(1, 0)`` and ``ds = diag(0, 1)`` (no residual bending
    flexibility), i.e. the shear term of :func:`shell_stiffness` with
    ``ds = diag(a, b)`` and ``residual_bending=False`` is ``a U0 + b U1``.
    """
    xyz = check_xyz(xyz, (3, 4), "shell")
    n, nn = xyz.shape[:2]
    rot, xy, h = shell_frames(xyz, ids)
    cp = _cols(nn, _PLATE)
    nd = 6 * nn
    out = (np.empty((n, nd, nd)), np.empty((n, nd, nd)))
    for sl in _batch_slices(n, 8 * _BATCH):
        m = sl.stop - sl.start
        ks = np.zeros((2, m, cp.size, cp.size))
        if nn == 4:
            x = xy[sl]
            tying = _mitc4_tying(x)
            for xi, eta in _QUAD_GAUSS:
                _, dn = _quad_derivs(xi, eta)
                _, det, inv = _jacobian(dn, x)
                if np.any(det <= 0):
                    shell_stiffness(xyz, np.eye(3), np.eye(3), np.eye(2), 0.0, ids)  # raises the full message
                bs = _mitc4_bs(tying, inv, xi, eta) * np.sqrt(det)[:, None, None]
                for d in range(2):
                    ks[d] += bs[:, d, :, None] * bs[:, d, None, :]
        else:
            dn = np.array([[-1.0, 1.0, 0.0], [-1.0, 0.0, 1.0]])
            _, det, inv = _jacobian(dn, xy[sl])
            if np.any(det <= 0):
                shell_stiffness(xyz, np.eye(3), np.eye(3), np.eye(2), 0.0, ids)  # raises the full message
            w = np.sqrt(det / 6.0)[:, None, None]
            for bs in _mitc3_bs(xy[sl], inv):
                bs = bs * w
                for d in range(2):
                    ks[d] += bs[:, d, :, None] * bs[:, d, None, :]
        for d in range(2):
            _congruence([(ks[d], cp)], rot[sl], h[sl], out[d][sl])
    return out


def orthotropic_q(e1, e2, nu12, g12) -> np.ndarray:
    """Plane-stress stiffness of an orthotropic ply in its own axes (MAT8) [Pa].

    Parameters
    ----------
    e1, e2 : float
        Young's moduli along and across the fibres [Pa].
    nu12 : float
        Major Poisson ratio.
    g12 : float
        In-plane shear modulus [Pa].

    Returns
    -------
    ndarray, shape (3, 3)
        Q in strain order (e11, e22, g12), engineering shear strain.
    """
    nu21 = nu12 * e2 / e1
    den = 1.0 - nu12 * nu21
    if not den > 0:
        raise ValueError(f"orthotropic ply: 1 - nu12 nu21 = {den:g} must be positive")
    return np.array([[e1 / den, nu12 * e2 / den, 0.0], [nu12 * e2 / den, e2 / den, 0.0], [0.0, 0.0, g12]])


def laminate_abd(thickness, theta_deg, q_ply, g_ply=None, z0=None):
    """Classical lamination theory: shell constitutive input of a ply stack (PCOMP).

    Parameters
    ----------
    thickness : array_like, shape (n_ply,)
        Ply thicknesses [m], bottom (most negative z) first.
    theta_deg : array_like, shape (n_ply,)
        Ply angles from the element material x axis [deg].
    q_ply : array_like, shape (n_ply, 3, 3)
        Plane-stress ply stiffness in ply axes [Pa] (``orthotropic_q`` or
        the isotropic plane-stress matrix).
    g_ply : array_like, shape (n_ply, 2), optional
        Transverse shear moduli (G13, G23) per ply [Pa]; ``inf`` marks a
        shear-rigid ply (e.g. MAT8 G1Z blank).  Without ``g_ply`` the
        laminate gets no transverse shear stiffness (``ds`` = 0).
    z0 : float, optional
        Distance from the reference plane to the bottom surface [m]
        (Nastran PCOMP Z0); default ``-total / 2``.

    Returns
    -------
    dm, dmb, db : ndarray, shape (3, 3)
        A [N/m], B [N], D [N m] with membrane strain ``e0 + z k``.
    ds : ndarray, shape (2, 2)
        Transverse shear stiffness [N/m], diagonal: per direction i the
        energy-consistent value ``1 / integral(Q_i(z)^2 / (D_i^2 G_i(z)) dz)``
        with ``Q_i`` the first moment of the bending stress about the
        neutral surface (the equilibrium shear distribution).  It gives
        5/6 G t for a homogeneous plate and the core-dominated stiffness of a
        sandwich.
    """
    t = np.asarray(thickness, dtype=float).ravel()
    th = np.radians(np.asarray(theta_deg, dtype=float).ravel())
    q = np.asarray(q_ply, dtype=float).reshape(-1, 3, 3)
    if not (t.size == th.size == q.shape[0]) or t.size == 0:
        raise ValueError(f"laminate: {t.size} thicknesses, {th.size} angles, {q.shape[0]} ply matrices")
    if np.any(~(t > 0)):
        raise ValueError(f"laminate: ply thicknesses must be positive, got {t.tolist()}")
    total = t.sum()
    zb = -0.5 * total if z0 is None else float(z0)
    z = zb + np.concatenate([[0.0], np.cumsum(t)])
    m, n = np.cos(th), np.sin(th)
    # engineering strain transformation element -> ply axes
    te = np.zeros((t.size, 3, 3))
    te[:, 0] = np.stack([m * m, n * n, m * n], axis=1)
    te[:, 1] = np.stack([n * n, m * m, -m * n], axis=1)
    te[:, 2] = np.stack([-2 * m * n, 2 * m * n, m * m - n * n], axis=1)
    qbar = np.einsum("kji,kjl,klm->kim", te, q, te)
    h1 = z[1:] - z[:-1]
    h2 = 0.5 * (z[1:] ** 2 - z[:-1] ** 2)
    h3 = (z[1:] ** 3 - z[:-1] ** 3) / 3.0
    dm = np.einsum("k,kij->ij", h1, qbar)
    dmb = np.einsum("k,kij->ij", h2, qbar)
    db = np.einsum("k,kij->ij", h3, qbar)
    ds = np.zeros((2, 2))
    if g_ply is not None:
        g = np.asarray(g_ply, dtype=float).reshape(-1, 2)
        if g.shape[0] != t.size or np.any(~(g > 0)):
            raise ValueError(f"laminate: need {t.size} positive (G13, G23) pairs, got {g.tolist()}")
        # ply shear compliance in element axes: gamma_ply = r gamma_element
        comp = np.zeros((t.size, 2, 2))
        comp[:, 0, 0] = np.where(np.isfinite(g[:, 0]), 1.0 / g[:, 0], 0.0)
        comp[:, 1, 1] = np.where(np.isfinite(g[:, 1]), 1.0 / g[:, 1], 0.0)
        r = np.stack([np.stack([m, n], axis=1), np.stack([-n, m], axis=1)], axis=1)
        comp = np.einsum("kji,kjl,klm->kim", r, comp, r)  # element-axis compliance per ply (r orthogonal)
        xg, wg = np.polynomial.legendre.leggauss(4)
        for i in range(2):
            e = qbar[:, i, i]
            zn = dmb[i, i] / dm[i, i]
            dstar = db[i, i] - 2 * zn * dmb[i, i] + zn * zn * dm[i, i]
            flex, q0 = 0.0, 0.0
            for k in range(t.size):
                zz = 0.5 * (z[k] + z[k + 1]) + 0.5 * h1[k] * xg
                qz = q0 + e[k] * (0.5 * ((zz - zn) ** 2 - (z[k] - zn) ** 2))
                flex += 0.5 * h1[k] * np.sum(wg * qz ** 2) * comp[k, i, i] / dstar ** 2
                q0 = q0 + e[k] * 0.5 * ((z[k + 1] - zn) ** 2 - (z[k] - zn) ** 2)
            ds[i, i] = 1.0 / flex if flex > 0 else np.inf
    return dm, dmb, db, ds


def shell_mass(xyz, mu, coupled: bool, ids=None) -> np.ndarray:
    """Mass of CQUAD4 / CTRIA3 shells.

    Parameters
    ----------
    xyz : array_like, shape (n, nn, 3)
        Grid coordinates in basic [m]; nn = 4 or 3.
    mu : array_like, shape (n,)
        Mass per unit area ``rho t + nsm`` [kg/m^2].
    coupled : bool
        False: lumped, ``mu A / nn`` on each grid's T1 T2 T3 (Nastran default).
        True: consistent translational mass (PARAM,COUPMASS), no rotary inertia.
    ids : array_like of int, optional
        Element ids used in error messages.

    Returns
    -------
    ndarray, shape (n, 6nn, 6nn)
        Element mass in basic coordinates [kg], DOF per grid T1 T2 T3 R1 R2 R3.
    """
    xyz = check_xyz(xyz, (3, 4), "shell")
    n, nn = xyz.shape[:2]
    mu = np.broadcast_to(np.asarray(mu, dtype=float), (n,))
    _, xy, _ = shell_frames(xyz, ids)
    mnn = np.zeros((n, nn, nn))
    if nn == 4:
        for xi, eta in _QUAD_GAUSS:
            nsh, dn = _quad_derivs(xi, eta)
            _, det, _ = _jacobian(dn, xy)
            if np.any(det <= 0):
                raise ElementGeometryError(describe_bad(det <= 0, ids, "are inverted or re-entrant "
                                                     "(non-positive Jacobian)", "CQUAD4"))
            mnn += (mu * det)[:, None, None] * np.outer(nsh, nsh)[None]
    else:
        _, det, _ = _jacobian(np.array([[-1.0, 1.0, 0.0], [-1.0, 0.0, 1.0]]), xy)
        if np.any(det <= 0):
            raise ElementGeometryError(describe_bad(det <= 0, ids, "have non-positive area", "CTRIA3"))
        cons = (np.ones((3, 3)) + np.eye(3)) / 24.0
        mnn = (mu * det)[:, None, None] * cons[None]
    if not coupled:
        total = mnn.sum(axis=(1, 2))
        mnn = np.zeros_like(mnn)
        idx = np.arange(nn)
        mnn[:, idx, idx] = (total / nn)[:, None]
    m = np.zeros((n, 6 * nn, 6 * nn))
    for d in range(3):
        m[:, d::6, d::6] = mnn
    return m
