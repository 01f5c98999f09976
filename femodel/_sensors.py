"""Observation (sensor) matrices and rigid-body mass properties."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from femodel._model import ModelError


def sensor_matrix(assembly, grids, directions) -> sp.csr_matrix:
    """Rows taking independent DOF u_a to displacements along given directions.

    Parameters
    ----------
    assembly : Assembly
    grids : (n_sensors,) int
        Grid ids.
    directions : (n_sensors, 3) float
        Direction vectors in the basic coordinate system (normalized here).

    Returns
    -------
    csr_matrix (n_sensors, n_a)
        y = C u_a, the translation of each grid along its direction, in the
        independent DOF (rotated into the grid's CD system and followed
        through rigid elements; SPC'd components contribute nothing).

    Raises
    ------
    ModelError
        A grid not in the model (named), a zero or malformed direction.
    """
    model = assembly.model
    grids = np.atleast_1d(np.asarray(grids, dtype=np.int64))
    d = np.asarray(directions, dtype=float)
    if d.ndim == 1:
        d = np.broadcast_to(d, (grids.size, 3))
    if d.shape != (grids.size, 3):
        raise ModelError(f"directions must be (n_sensors, 3) = ({grids.size}, 3), got {d.shape}")
    norm = np.linalg.norm(d, axis=1)
    if np.any(~(norm > 0)):
        raise ModelError(f"sensor directions must be non-zero; bad rows {np.flatnonzero(~(norm > 0)).tolist()}")
    d = d / norm[:, None]
    gi = model.grid_index(grids, what="sensor grid")
    if np.any(model.cd != 0):
        lam = model.cd_axes()[gi]  # u_basic = lam u_cd
        coef = np.einsum("nji,nj->ni", lam, d)
    else:
        coef = d
    rows = np.repeat(np.arange(grids.size), 3)
    cols = (6 * gi[:, None] + np.arange(3)[None, :]).ravel()
    Cg = sp.csr_matrix((coef.ravel(), (rows, cols)), shape=(grids.size, len(assembly.gset)))
    return (Cg @ assembly.T).tocsr()


@dataclass(frozen=True)
class MassProperties:
    """Rigid-body mass properties (SI, basic coordinates).

    Attributes
    ----------
    mass : float
        Total mass, kg (from the translational rigid-body block).
    cg : (3,) float
        Centre of gravity, m.
    inertia : (3, 3) float
        Inertia tensor about the CG, kg m^2 (positive diagonal, products with
        the minus sign, i.e. the tensor itself).
    rigid_body_mass : (6, 6) float
        D^T M D about the basic origin, D the six rigid-body vectors.
    """

    mass: float
    cg: np.ndarray
    inertia: np.ndarray
    rigid_body_mass: np.ndarray


def rigid_body_vectors(model, ref=(0.0, 0.0, 0.0)) -> np.ndarray:
    """(n_g, 6) g-set rigid-body motions: unit translations and rotations about ``ref`` (basic)."""
    n = model.n_grids
    r = model.xyz - np.asarray(ref, dtype=float)[None, :]
    D = np.zeros((n, 6, 6))
    D[:, :3, :3] = np.eye(3)
    D[:, 3:, 3:] = np.eye(3)
    # u = t + theta x r = t - S(r) theta
    z = np.zeros(n)
    S = np.stack([np.stack([z, -r[:, 2], r[:, 1]], 1), np.stack([r[:, 2], z, -r[:, 0]], 1), np.stack([-r[:, 1], r[:, 0], z], 1)], 1)
    D[:, :3, 3:] = -S
    if np.any(model.cd != 0):
        lam = model.cd_axes()
        D[:, :3, :] = np.einsum("nji,njk->nik", lam, D[:, :3, :])
        D[:, 3:, :] = np.einsum("nji,njk->nik", lam, D[:, 3:, :])
    return D.reshape(6 * n, 6)


def mass_properties(assembly) -> MassProperties:
    """Total mass, centre of gravity and inertia about the CG of the g-set mass matrix.

    Parameters
    ----------
    assembly : Assembly

    Returns
    -------
    MassProperties
    """
    D = rigid_body_vectors(assembly.model)
    Mrb = D.T @ (assembly.mass_g() @ D)
    Mrb = 0.5 * (Mrb + Mrb.T)
    m = float(np.mean(np.diag(Mrb)[:3]))
    if m <= 0:
        raise ModelError("model has no mass")
    # Mrb[:3, 3:] = -m S(cg)
    B = -Mrb[:3, 3:] / m
    cg = np.array([B[2, 1], B[0, 2], B[1, 0]])
    S = np.array([[0, -cg[2], cg[1]], [cg[2], 0, -cg[0]], [-cg[1], cg[0], 0]])
    inertia = Mrb[3:, 3:] - m * (S.T @ S)
    return MassProperties(mass=m, cg=cg, inertia=0.5 * (inertia + inertia.T), rigid_body_mass=Mrb)
