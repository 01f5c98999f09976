"""Vectorized solid element kernels: CTETRA(4), CPYRAM(5), CPENTA(6), CHEXA(8).

Formulation:

* CTETRA 4: linear tetrahedron (constant strain).
* CPYRAM 5: conforming rational pyramid (Bedrosian 1992): base shape
  functions ``((1-z+xi_i xi)(1-z+eta_i eta)) / (4 (1-z))``, apex ``z``; faces
  match linear tetrahedra and bilinear hexahedra exactly.  Integrated with a
  3x3x3 Gauss rule on the cube collapsed onto the pyramid (Duffy map).
* CPENTA 6: linear wedge, 3-point triangle x 2-point Gauss rule.
* CHEXA 8: trilinear hexahedron with the three incompatible bubble modes per
  direction (Wilson; Taylor, Beresford & Wilson 1976 correction so the patch
  test passes), condensed statically. This removes the shear locking of the
  fully integrated brick in bending, which Nastran's HEXA avoids too.

Node order is Nastran's connectivity order (CTETRA G1-G4; CPYRAM base
G1-G4 then apex G5; CPENTA G1-G3 then G4-G6; CHEXA G1-G4 then G5-G8).
Stiffness and mass are in basic coordinates, DOF per grid T1 T2 T3.
Strain order in ``c`` is Nastran's: xx, yy, zz, xy, yz, zx with engineering
shear strains.

Mass: consistent (PARAM,COUPMASS) from the same shape functions; lumped is the
row sum of the consistent matrix on the diagonal, which for these linear
elements is each grid's share of the volume (V/4 per tetra node, V/8 per node
of a parallelepiped brick).
"""

from __future__ import annotations

import numpy as np

from femodel._elements_shell import ElementGeometryError, check_xyz, describe_bad

__all__ = ["solid_stiffness", "solid_mass", "SOLID_NAMES"]

SOLID_NAMES = {4: "CTETRA", 5: "CPYRAM", 6: "CPENTA", 8: "CHEXA"}

_G = 1.0 / np.sqrt(3.0)
_HEX_NAT = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                     [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=float)
_PYR_BASE = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=float)


def _gauss_1d(order: int):
    x, w = np.polynomial.legendre.leggauss(order)
    return x, w


def _rule_hex(order: int):
    x, w = _gauss_1d(order)
    pts = np.array([(a, b, c) for a in x for b in x for c in x])
    wts = np.array([wa * wb * wc for wa in w for wb in w for wc in w])
    return pts, wts


def _shape_hex(p):
    xi, eta, zeta = p
    nat = _HEX_NAT
    n = 0.125 * (1 + nat[:, 0] * xi) * (1 + nat[:, 1] * eta) * (1 + nat[:, 2] * zeta)
    dn = 0.125 * np.stack([
        nat[:, 0] * (1 + nat[:, 1] * eta) * (1 + nat[:, 2] * zeta),
        nat[:, 1] * (1 + nat[:, 0] * xi) * (1 + nat[:, 2] * zeta),
        nat[:, 2] * (1 + nat[:, 0] * xi) * (1 + nat[:, 1] * eta),
    ])
    return n, dn


def _shape_tet(p):
    r, s, t = p
    n = np.array([1 - r - s - t, r, s, t])
    dn = np.array([[-1.0, 1, 0, 0], [-1.0, 0, 1, 0], [-1.0, 0, 0, 1]])
    return n, dn


def _shape_penta(p):
    r, s, z = p
    tri = np.array([1 - r - s, r, s])
    dtri = np.array([[-1.0, 1, 0], [-1.0, 0, 1]])
    lo, hi = 0.5 * (1 - z), 0.5 * (1 + z)
    n = np.concatenate([tri * lo, tri * hi])
    dn = np.stack([
        np.concatenate([dtri[0] * lo, dtri[0] * hi]),
        np.concatenate([dtri[1] * lo, dtri[1] * hi]),
        np.concatenate([-0.5 * tri, 0.5 * tri]),
    ])
    return n, dn


def _shape_pyram(p):
    """Rational pyramid on base [-1,1]^2 at z=0, apex (0,0,1)."""
    xi, eta, z = p
    q = 1.0 - z
    a = q + _PYR_BASE[:, 0] * xi
    b = q + _PYR_BASE[:, 1] * eta
    nb = a * b / (4 * q)
    n = np.append(nb, z)
    dxi = _PYR_BASE[:, 0] * b / (4 * q)
    deta = _PYR_BASE[:, 1] * a / (4 * q)
    # d/dz of a*b/(4q) with da/dz = db/dz = -1, dq/dz = -1
    dz = (-(a + b) * q + a * b) / (4 * q * q)
    dn = np.stack([np.append(dxi, 0.0), np.append(deta, 0.0), np.append(dz, 1.0)])
    return n, dn


def _rule_tet():
    a, b = 0.5854101966249685, 0.1381966011250105
    pts = np.array([[b, b, b], [a, b, b], [b, a, b], [b, b, a]])
    return pts, np.full(4, 1.0 / 24.0)


def _rule_penta():
    tri = [(1 / 6, 1 / 6), (2 / 3, 1 / 6), (1 / 6, 2 / 3)]
    pts = np.array([(r, s, z) for r, s in tri for z in (-_G, _G)])
    return pts, np.full(6, 1.0 / 6.0)


def _rule_pyram(order: int = 3):
    """Duffy-collapsed Gauss rule: xi = (1-z) a, eta = (1-z) b, z = (1+c)/2."""
    x, w = _gauss_1d(order)
    pts, wts = [], []
    for a, wa in zip(x, w):
        for b, wb in zip(x, w):
            for c, wc in zip(x, w):
                z = 0.5 * (1 + c)
                pts.append(((1 - z) * a, (1 - z) * b, z))
                wts.append(wa * wb * wc * 0.5 * (1 - z) ** 2)
    return np.array(pts), np.array(wts)


_ELEMENTS = {
    4: (_shape_tet, _rule_tet),
    5: (_shape_pyram, _rule_pyram),
    6: (_shape_penta, _rule_penta),
    8: (_shape_hex, lambda: _rule_hex(2)),
}


def _jac3(dn: np.ndarray, xyz: np.ndarray):
    """Batched Jacobian J[a, b] = d x_b / d nat_a, its determinant and inverse (adjugate form)."""
    jac = np.einsum("ak,nkb->nab", dn, xyz)
    adj = np.empty_like(jac)
    for i in range(3):
        for j in range(3):
            r = [k for k in range(3) if k != j]
            c = [k for k in range(3) if k != i]
            minor = jac[:, r[0], c[0]] * jac[:, r[1], c[1]] - jac[:, r[0], c[1]] * jac[:, r[1], c[0]]
            adj[:, i, j] = (-1) ** (i + j) * minor
    det = np.einsum("nj,jn->n", jac[:, 0, :], adj[:, :, 0].T)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = adj / det[:, None, None]
    return jac, det, inv


def _strain_b(dxyz: np.ndarray) -> np.ndarray:
    """(n, 6, 3nn) strain-displacement matrix from Cartesian derivatives (n, 3, nn)."""
    n, _, nn = dxyz.shape
    b = np.zeros((n, 6, 3 * nn))
    b[:, 0, 0::3] = dxyz[:, 0]
    b[:, 1, 1::3] = dxyz[:, 1]
    b[:, 2, 2::3] = dxyz[:, 2]
    b[:, 3, 0::3] = dxyz[:, 1]
    b[:, 3, 1::3] = dxyz[:, 0]
    b[:, 4, 1::3] = dxyz[:, 2]
    b[:, 4, 2::3] = dxyz[:, 1]
    b[:, 5, 0::3] = dxyz[:, 2]
    b[:, 5, 2::3] = dxyz[:, 0]
    return b


def _check_det(det, ids, nn):
    bad = ~(det > 0)
    if bad.any():
        raise ElementGeometryError(describe_bad(
            bad, ids, "are degenerate or inverted (non-positive Jacobian at an integration "
            "point; check grid order and coincident grids)", SOLID_NAMES[nn]))


def _btdb(b, c, w):
    return np.matmul(np.swapaxes(b, 1, 2), np.matmul(c, b) * w[:, None, None])


def solid_stiffness(xyz, c, ids=None) -> np.ndarray:
    """Stiffness of linear solid elements.

    Parameters
    ----------
    xyz : array_like, shape (n, nn, 3)
        Grid coordinates in basic [m]; nn = 4 (CTETRA), 5 (CPYRAM),
        6 (CPENTA) or 8 (CHEXA), Nastran connectivity order.
    c : array_like, shape (n, 6, 6)
        Material stiffness in basic [Pa], strain order xx, yy, zz, xy, yz, zx
        (engineering shear).
    ids : array_like of int, shape (n,), optional
        Element ids used in error messages.

    Returns
    -------
    ndarray, shape (n, 3nn, 3nn)
        Element stiffness [N/m], DOF per grid T1 T2 T3; linear in ``c``.

    Raises
    ------
    ElementGeometryError
        Degenerate or inverted elements (listed by id or index).
    """
    xyz = check_xyz(xyz, tuple(_ELEMENTS), "solid")
    n, nn = xyz.shape[:2]
    c = np.broadcast_to(np.asarray(c, dtype=float), (n, 6, 6))
    shape, rule = _ELEMENTS[nn]
    pts, wts = rule()
    k = np.zeros((n, 3 * nn, 3 * nn))
    if nn == 8:
        return _hex8_incompatible(xyz, c, ids)
    for p, w in zip(pts, wts):
        _, dn = shape(p)
        _, det, inv = _jac3(dn, xyz)
        _check_det(det, ids, nn)
        dxyz = np.einsum("nab,bk->nak", inv, dn)
        k += _btdb(_strain_b(dxyz), c, det * w)
    return 0.5 * (k + np.swapaxes(k, 1, 2))


def _hex8_incompatible(xyz, c, ids):
    """Trilinear brick + 9 incompatible modes (Taylor's patch-test-passing form), condensed."""
    n = xyz.shape[0]
    pts, wts = _rule_hex(2)
    _, dn0 = _shape_hex((0.0, 0.0, 0.0))
    _, det0, inv0 = _jac3(dn0, xyz)
    _check_det(det0, ids, 8)
    kuu = np.zeros((n, 24, 24))
    kua = np.zeros((n, 24, 9))
    kaa = np.zeros((n, 9, 9))
    for p, w in zip(pts, wts):
        _, dn = _shape_hex(p)
        _, det, inv = _jac3(dn, xyz)
        _check_det(det, ids, 8)
        dxyz = np.einsum("nab,bk->nak", inv, dn)
        bu = _strain_b(dxyz)
        # bubbles P_i = 1 - nat_i^2; natural derivatives -2 nat_i on the diagonal.
        # Taylor: Cartesian derivatives through the centroid Jacobian, scaled by det0/det,
        # which makes the bubble strains integrate to zero (patch test).
        dbub = np.diag(-2.0 * np.asarray(p))
        dcart = np.einsum("nab,bk->nak", inv0, dbub) * (det0 / det)[:, None, None]
        ba = _strain_b(dcart)
        cb = np.matmul(c, bu)
        wdet = (det * w)[:, None, None]
        kuu += np.matmul(np.swapaxes(bu, 1, 2), cb) * wdet
        kua += np.matmul(np.swapaxes(cb, 1, 2), ba) * wdet
        kaa += np.matmul(np.swapaxes(ba, 1, 2), np.matmul(c, ba)) * wdet
    k = kuu - np.matmul(kua, np.linalg.solve(kaa, np.swapaxes(kua, 1, 2)))
    return 0.5 * (k + np.swapaxes(k, 1, 2))


def solid_mass(xyz, rho, coupled: bool, ids=None) -> np.ndarray:
    """Mass of linear solid elements.

    Parameters
    ----------
    xyz : array_like, shape (n, nn, 3)
        Grid coordinates in basic [m]; nn in {4, 5, 6, 8}.
    rho : array_like, shape (n,)
        Mass density [kg/m^3].
    coupled : bool
        True: consistent mass (PARAM,COUPMASS); False: lumped (row sums).
    ids : array_like of int, optional
        Element ids used in error messages.

    Returns
    -------
    ndarray, shape (n, 3nn, 3nn)
        Element mass [kg], DOF per grid T1 T2 T3; total per direction rho V.
    """
    xyz = check_xyz(xyz, tuple(_ELEMENTS), "solid")
    n, nn = xyz.shape[:2]
    rho = np.broadcast_to(np.asarray(rho, dtype=float), (n,))
    shape, rule = _ELEMENTS[nn]
    pts, wts = rule() if nn != 8 else _rule_hex(2)
    mnn = np.zeros((n, nn, nn))
    for p, w in zip(pts, wts):
        nsh, dn = shape(p)
        _, det, _ = _jac3(dn, xyz)
        _check_det(det, ids, nn)
        mnn += (rho * det * w)[:, None, None] * np.outer(nsh, nsh)[None]
    if not coupled:
        diag = mnn.sum(axis=2)
        mnn = np.zeros_like(mnn)
        idx = np.arange(nn)
        mnn[:, idx, idx] = diag
    m = np.zeros((n, 3 * nn, 3 * nn))
    for d in range(3):
        m[:, d::3, d::3] = mnn
    return m
