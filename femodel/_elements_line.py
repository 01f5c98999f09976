"""Line and point element kernels: CBAR/CBEAM, CROD/CONROD, CBUSH, CONM2.

Every kernel is vectorized over elements and returns element matrices in
basic coordinates with node DOF order T1 T2 T3 R1 R2 R3 (per node).  Each
returns its matrices split by the physical factor they are proportional to,
so that a parametric model can scale them exactly.
"""

from __future__ import annotations

import numpy as np

from femodel._model import ModelError


def skew(w: np.ndarray) -> np.ndarray:
    """(n, 3) -> (n, 3, 3) cross-product matrices, S(w) x = w x x."""
    z = np.zeros(w.shape[0])
    return np.stack(
        [
            np.stack([z, -w[:, 2], w[:, 1]], axis=1),
            np.stack([w[:, 2], z, -w[:, 0]], axis=1),
            np.stack([-w[:, 1], w[:, 0], z], axis=1),
        ],
        axis=1,
    )


def rigid_offset(w: np.ndarray) -> np.ndarray:
    """(n, 6, 6) matrix taking grid motion to the motion of a point at offset w (basic).

    u_point = u_grid + theta x w, theta_point = theta_grid.
    """
    n = w.shape[0]
    out = np.broadcast_to(np.eye(6), (n, 6, 6)).copy()
    out[:, :3, 3:] = -skew(w)
    return out


def frame_axes(x_a: np.ndarray, x_b: np.ndarray, v: np.ndarray, what: str = "element", ids=None):
    """Element axes (n, 3, 3) (rows ex, ey, ez in basic) and lengths (n,).

    ex runs from end A to end B; ey lies in the plane of ex and the orientation
    vector v; ez = ex x ey.
    """
    d = x_b - x_a
    length = np.linalg.norm(d, axis=1)
    if np.any(length <= 0):
        bad = ids[length <= 0][:5].tolist() if ids is not None else "?"
        raise ModelError(f"{what} {bad}: zero length")
    ex = d / length[:, None]
    ez = np.cross(ex, v)
    nz = np.linalg.norm(ez, axis=1)
    if np.any(nz <= 1e-10 * np.linalg.norm(v, axis=1)):
        bad = ids[nz <= 1e-10 * np.linalg.norm(v, axis=1)][:5].tolist() if ids is not None else "?"
        raise ModelError(f"{what} {bad}: orientation vector is parallel to the element axis (or zero)")
    ez = ez / nz[:, None]
    ey = np.cross(ez, ex)
    return np.stack([ex, ey, ez], axis=1), length


def _transform(local: np.ndarray, T: np.ndarray) -> np.ndarray:
    return np.einsum("nji,njk,nkl->nil", T, local, T, optimize=True)


def beam_transformation(axes: np.ndarray, wa: np.ndarray, wb: np.ndarray) -> np.ndarray:
    """(n, 12, 12): grid DOF (basic) -> element-local end DOF (with rigid offsets)."""
    n = axes.shape[0]
    R = np.zeros((n, 12, 12))
    for k in range(4):
        R[:, 3 * k : 3 * k + 3, 3 * k : 3 * k + 3] = axes
    O = np.zeros((n, 12, 12))
    O[:, :6, :6] = rigid_offset(wa)
    O[:, 6:, 6:] = rigid_offset(wb)
    return R @ O


def beam_local_stiffness(length, A, I1, I2, J, phi1, phi2):
    """Local 12x12 stiffness split in (axial+bending per unit E, torsion per unit G).

    Timoshenko bending with shear parameters ``phi = 12 E I / (k A G L^2)``
    (zero for Euler-Bernoulli); plane 1 (v, theta_z) uses I1, plane 2
    (w, theta_y) uses I2.

    Returns
    -------
    ke_E, ke_G : (n, 12, 12)
        Stiffness divided by E and by G respectively.
    """
    n = length.shape[0]
    L = length
    kE = np.zeros((n, 12, 12))
    kG = np.zeros((n, 12, 12))
    a = A / L
    for i, j, s in ((0, 0, 1), (6, 6, 1), (0, 6, -1), (6, 0, -1)):
        kE[:, i, j] = s * a
    t = J / L
    for i, j, s in ((3, 3, 1), (9, 9, 1), (3, 9, -1), (9, 3, -1)):
        kG[:, i, j] = s * t
    # plane 1: v (1, 7), theta_z (5, 11)
    for (dv1, dr1, dv2, dr2), I, phi, sg in (((1, 5, 7, 11), I1, phi1, 1.0), ((2, 4, 8, 10), I2, phi2, -1.0)):
        c = I / ((1.0 + phi) * L**3)
        idx = (dv1, dr1, dv2, dr2)
        mat = np.zeros((n, 4, 4))
        mat[:, 0, 0] = 12
        mat[:, 0, 1] = sg * 6 * L
        mat[:, 0, 2] = -12
        mat[:, 0, 3] = sg * 6 * L
        mat[:, 1, 1] = (4 + phi) * L**2
        mat[:, 1, 2] = -sg * 6 * L
        mat[:, 1, 3] = (2 - phi) * L**2
        mat[:, 2, 2] = 12
        mat[:, 2, 3] = -sg * 6 * L
        mat[:, 3, 3] = (4 + phi) * L**2
        mat = np.triu(mat) + np.transpose(np.triu(mat, 1), (0, 2, 1))
        mat *= c[:, None, None]
        for p in range(4):
            for q in range(4):
                kE[:, idx[p], idx[q]] += mat[:, p, q]
    return kE, kG


def beam_local_mass(length, mu, coupled: bool, torsion_inertia=None):
    """Local 12x12 mass for mass per length ``mu`` (kg/m).

    Lumped (default): half of mu L translational at each end, no rotary
    inertia, as Nastran's CBAR.  Coupled: consistent Euler-Bernoulli mass
    without torsional inertia.  ``torsion_inertia`` (n,) kg m (rho J per
    length) adds lumped (or consistent, when coupled) torsional inertia.
    """
    n = length.shape[0]
    L = length
    m = np.zeros((n, 12, 12))
    if not coupled:
        for d in (0, 1, 2, 6, 7, 8):
            m[:, d, d] = 0.5 * mu * L
        if torsion_inertia is not None:
            m[:, 3, 3] = m[:, 9, 9] = 0.5 * torsion_inertia * L
        return m
    c = mu * L
    for i, j, v in ((0, 0, 2), (6, 6, 2), (0, 6, 1), (6, 0, 1)):
        m[:, i, j] = c * v / 6.0
    for (dv1, dr1, dv2, dr2), sg in (((1, 5, 7, 11), 1.0), ((2, 4, 8, 10), -1.0)):
        idx = (dv1, dr1, dv2, dr2)
        mat = np.zeros((n, 4, 4))
        mat[:, 0, 0] = 156
        mat[:, 0, 1] = sg * 22 * L
        mat[:, 0, 2] = 54
        mat[:, 0, 3] = -sg * 13 * L
        mat[:, 1, 1] = 4 * L**2
        mat[:, 1, 2] = sg * 13 * L
        mat[:, 1, 3] = -3 * L**2
        mat[:, 2, 2] = 156
        mat[:, 2, 3] = -sg * 22 * L
        mat[:, 3, 3] = 4 * L**2
        mat = np.triu(mat) + np.transpose(np.triu(mat, 1), (0, 2, 1))
        mat *= (c / 420.0)[:, None, None]
        for p in range(4):
            for q in range(4):
                m[:, idx[p], idx[q]] += mat[:, p, q]
    if torsion_inertia is not None:
        ct = torsion_inertia * L
        for i, j, v in ((3, 3, 2), (9, 9, 2), (3, 9, 1), (9, 3, 1)):
            m[:, i, j] = ct * v / 6.0
    return m


def release_pins(k: np.ndarray, pins: np.ndarray) -> np.ndarray:
    """Statically condense released end DOF (pin flags) out of local 12x12 matrices.

    Parameters
    ----------
    k : (n, 12, 12)
        Local stiffness (element axes, after offsets).
    pins : (n, 12) bool
        Released local DOF (PA digits for 0-5, PB digits for 6-11).

    Returns
    -------
    (n, 12, 12) with the released DOF carrying no stiffness:
    k - k[:, r] k[r, r]^+ k[r, :] (pseudo-inverse: a fully released block,
    e.g. torsion at both ends, drops out).
    """
    out = k.copy()
    if not np.any(pins):
        return out
    codes, inv = np.unique(pins, axis=0, return_inverse=True)
    inv = np.asarray(inv).ravel()
    for ci, code in enumerate(codes):
        r = np.flatnonzero(code)
        if r.size == 0:
            continue
        sel = inv == ci
        kk = k[sel]
        krr = kk[:, r][:, :, r]
        kr_ = kk[:, r, :]
        out[sel] = kk - np.swapaxes(kr_, 1, 2) @ np.linalg.pinv(krr, hermitian=True) @ kr_
    return out


def beam_matrices(x_a, x_b, v, wa, wb, A, I1, I2, J, E, G, k1, k2, *, coupled, torsion_inertia, ids=None, what="CBAR",
                  pins=None, section_parts=None):
    """CBAR/CBEAM element matrices in basic coordinates.

    Parameters
    ----------
    x_a, x_b : (n, 3) grid positions, m (basic)
    v : (n, 3) orientation vector (basic)
    wa, wb : (n, 3) end offsets, m (basic)
    A, I1, I2, J : (n,) section area m^2, area moments m^4 (I1 for plane 1), torsion constant m^4
    E, G : (n,) moduli, Pa
    k1, k2 : (n,) shear factors; NaN for Euler-Bernoulli
    coupled : bool
        Consistent (True) or lumped (False) mass.
    torsion_inertia : bool
        Add rho J torsional inertia (CBEAM) or not (CBAR).
    pins : (n, 12) bool, optional
        Pin flags (released local end DOF), condensed out of the stiffness;
        the mass is left as is.
    section_parts : (n,) bool, optional
        Also return the E part split by section property for these elements
        (Euler-Bernoulli: phi = 0 there; zeros for the others):
        "stiffness_E_parts" (3, n, 12, 12), the stiffness per unit E and per
        unit A (axial), I1 (bending plane 1) and I2 (bending plane 2); their
        sum weighted by (A, I1, I2) is "stiffness_E". The blocks are
        uncoupled, so each part's pins are condensed alone, exactly.

    Returns
    -------
    dict
        "stiffness_E": (n,12,12) stiffness / E (shear parameter fixed at the
        nominal E/G), "stiffness_G": torsion / G, "mass_unit": mass per unit
        mass-per-length (multiply by rho A + nsm), "mass_torsion_unit": mass per unit
        rho (torsional inertia J), "length": (n,).
    """
    xa_e = x_a + wa
    xb_e = x_b + wb
    axes, length = frame_axes(xa_e, xb_e, v, what, ids)
    with np.errstate(divide="ignore", invalid="ignore"):
        phi1 = np.where(np.isfinite(k1) & (k1 > 0), 12 * E * I1 / (k1 * A * G * length**2), 0.0)
        phi2 = np.where(np.isfinite(k2) & (k2 > 0), 12 * E * I2 / (k2 * A * G * length**2), 0.0)
    phi1 = np.nan_to_num(phi1)
    phi2 = np.nan_to_num(phi2)
    kE, kG = beam_local_stiffness(length, A, I1, I2, J, phi1, phi2)
    if pins is not None:
        # axial, torsion and the two bending planes are uncoupled blocks of the
        # local matrix, so condensing the E and G parts separately is exact
        kE = release_pins(kE, pins)
        kG = release_pins(kG, pins)
    T = beam_transformation(axes, wa, wb)
    ones = np.ones_like(length)
    m_unit = beam_local_mass(length, ones, coupled)
    out = {
        "stiffness_E": _transform(kE, T),
        "stiffness_G": _transform(kG, T),
        "mass_unit": _transform(m_unit, T),
        "length": length,
    }
    s = np.zeros(0, np.int64) if section_parts is None else np.flatnonzero(section_parts)
    if s.size:
        if np.any(phi1[s] != 0) or np.any(phi2[s] != 0):
            raise ModelError(f"{what}: section parts of shear-flexible (K1/K2) sections are not monomials of A, I1, I2")
        zero, one = np.zeros(s.size), np.ones(s.size)
        parts = np.zeros((3,) + kE.shape)
        for k, sec in enumerate(((one, zero, zero), (zero, one, zero), (zero, zero, one))):
            kp, _ = beam_local_stiffness(length[s], *sec, zero, zero, zero)
            parts[k, s] = _transform(release_pins(kp, pins[s]) if pins is not None else kp, T[s])
        out["stiffness_E_parts"] = parts
    if torsion_inertia:
        mt = beam_local_mass(length, np.zeros_like(length), coupled, torsion_inertia=J)
        out["mass_torsion_unit"] = _transform(mt, T)
    return out


def rod_matrices(x_a, x_b, A, J, *, coupled, ids=None):
    """CROD/CONROD: axial (per unit E) and torsion (per unit G) stiffness, mass per unit mu.

    Returns dict "stiffness_E", "stiffness_G", "mass_unit" of shape (n, 12, 12) in basic.
    Mass: lumped half mu L per end, or consistent (2,1;1,2) mu L / 6 in all
    three translations (Nastran's coupled rod mass); no torsional inertia.
    """
    d = x_b - x_a
    L = np.linalg.norm(d, axis=1)
    if np.any(L <= 0):
        raise ModelError(f"CROD/CONROD {ids[L <= 0][:5].tolist() if ids is not None else ''}: zero length")
    e = d / L[:, None]
    ee = np.einsum("ni,nj->nij", e, e)
    n = L.shape[0]
    kE = np.zeros((n, 12, 12))
    kG = np.zeros((n, 12, 12))
    a = (A / L)[:, None, None] * ee
    t = (J / L)[:, None, None] * ee
    kE[:, :3, :3] = a
    kE[:, 6:9, 6:9] = a
    kE[:, :3, 6:9] = -a
    kE[:, 6:9, :3] = -a
    kG[:, 3:6, 3:6] = t
    kG[:, 9:12, 9:12] = t
    kG[:, 3:6, 9:12] = -t
    kG[:, 9:12, 3:6] = -t
    m = np.zeros((n, 12, 12))
    I3 = np.eye(3)
    if coupled:
        for (i, j), v in (((0, 0), 2), ((6, 6), 2), ((0, 6), 1), ((6, 0), 1)):
            m[:, i : i + 3, j : j + 3] = (L * v / 6.0)[:, None, None] * I3
    else:
        m[:, :3, :3] = (0.5 * L)[:, None, None] * I3
        m[:, 6:9, 6:9] = (0.5 * L)[:, None, None] * I3
    return {"stiffness_E": kE, "stiffness_G": kG, "mass_unit": m, "length": L}


def bush_matrices(x_a, x_b, axes, s, grounded):
    """CBUSH stiffness per unit of each PBUSH K_i, in basic.

    Parameters
    ----------
    x_a, x_b : (n, 3) grid positions (x_b ignored where grounded)
    axes : (n, 3, 3) element axes, rows in basic
    s : (n,) spring location along A-B (0 at A)
    grounded : (n,) bool, GB blank

    Returns
    -------
    (6, n, 12, 12) : stiffness for K_i = 1 for i = 1..6 (rows/cols 6-11 are GB).
    """
    n = x_a.shape[0]
    xs = x_a + s[:, None] * (x_b - x_a)
    Oa = rigid_offset(xs - x_a)
    Ob = rigid_offset(xs - x_b)
    R6 = np.zeros((n, 6, 6))
    R6[:, :3, :3] = axes
    R6[:, 3:, 3:] = axes
    Ta = R6 @ Oa  # grid A dof -> local spring dof
    Tb = R6 @ Ob
    Tb = np.where(grounded[:, None, None], 0.0, Tb)
    B = np.concatenate([-Ta, Tb], axis=2)  # relative deformation (n, 6, 12)
    out = np.einsum("nki,nkj->knij", B, B)
    return out


def conm2_matrices(offset, inertia):
    """CONM2 mass per unit M (n, 6, 6) and inertia part (n, 6, 6), in basic at the grid.

    Parameters
    ----------
    offset : (n, 3) CG offset from the grid, m (basic)
    inertia : (n, 3, 3) inertia tensor about the CG, kg m^2 (basic)
    """
    B = np.zeros((offset.shape[0], 3, 6))
    B[:, :, :3] = np.eye(3)
    B[:, :, 3:] = -skew(offset)
    m_unit = np.einsum("nki,nkj->nij", B, B)
    mi = np.zeros_like(m_unit)
    mi[:, 3:, 3:] = inertia
    return m_unit, mi
