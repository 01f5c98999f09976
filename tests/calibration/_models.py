"""Small manufactured parametric models for the calibration tests.

A free-free Euler-Bernoulli steel beam (bending, 2 DOF per node) in four
segments, three with their own thickness parameter (the fourth only follows
E and rho, which keeps E, rho and the thicknesses identifiable), a lumped
mass and a spring-mass "bushing" resonator: seven parameters with the
exponents a shell model has (E t^3 bending, rho t mass).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from calibration import FRFModel
from femodel import AffineMatrix

PARAMS = ("E", "rho", "t1", "t2", "t3", "m_lump", "k_bush")


def beam_model(n_el: int = 40, length_m: float = 1.2, sensors=None, drive: int = 5, scale_length: float = 1.0):
    """Return (FRFModel, sensor node list). ``scale_length`` lets a test express the
    same beam in mm-t-s (lengths x1000, mass t, so K in N/mm, M in t) and convert back."""
    E, rho, b, t = 210e9, 7850.0, 0.04, 0.01
    L = length_m / n_el
    n_nodes = n_el + 1
    n = 2 * n_nodes + 1  # + resonator mass DOF
    seg_of = np.minimum((np.arange(n_el) * 4) // n_el, 3)
    EI = E * b * t**3 / 12
    rA = rho * b * t
    ke = EI / L**3 * np.array(
        [[12, 6 * L, -12, 6 * L], [6 * L, 4 * L**2, -6 * L, 2 * L**2],
         [-12, -6 * L, 12, -6 * L], [6 * L, 2 * L**2, -6 * L, 4 * L**2]]
    )
    me = rA * L / 420 * np.array(
        [[156, 22 * L, 54, -13 * L], [22 * L, 4 * L**2, 13 * L, -3 * L**2],
         [54, 13 * L, 156, -22 * L], [-13 * L, -3 * L**2, -22 * L, 4 * L**2]]
    )
    Kterms, Mterms, Kexp, Mexp = [], [], [], []
    for s in range(4):
        rows, cols, kv, mv = [], [], [], []
        for e in np.flatnonzero(seg_of == s):
            dofs = np.array([2 * e, 2 * e + 1, 2 * e + 2, 2 * e + 3])
            rows.append(np.repeat(dofs, 4))
            cols.append(np.tile(dofs, 4))
            kv.append(ke.ravel())
            mv.append(me.ravel())
        r, c = np.concatenate(rows), np.concatenate(cols)
        Kterms.append(sp.csr_matrix((np.concatenate(kv), (r, c)), shape=(n, n)))
        Mterms.append(sp.csr_matrix((np.concatenate(mv), (r, c)), shape=(n, n)))
        ek = np.zeros(7); ek[0] = 1
        em = np.zeros(7); em[1] = 1
        if s < 3:
            ek[2 + s] = 3
            em[2 + s] = 1
        Kexp.append(ek); Mexp.append(em)
    lump_node = int(0.7 * n_el)
    Mterms.append(sp.csr_matrix(([0.3], ([2 * lump_node], [2 * lump_node])), shape=(n, n)))
    em = np.zeros(7); em[5] = 1; Mexp.append(em)
    bush_node = int(0.35 * n_el)
    m_res, f_res = 0.1, 150.0
    k = (2 * np.pi * f_res) ** 2 * m_res
    i, j = 2 * bush_node, n - 1
    Kterms.append(sp.csr_matrix(([k, -k, -k, k], ([i, i, j, j], [i, j, i, j])), shape=(n, n)))
    ek = np.zeros(7); ek[6] = 1; Kexp.append(ek)
    Mterms.append(sp.csr_matrix(([m_res], ([n - 1], [n - 1])), shape=(n, n)))
    Mexp.append(np.zeros(7))
    if sensors is None:
        sensors = [0, 3, 8, 12, 17, 21, 26, 30, 34, 40]
    C = sp.csr_matrix(
        (np.ones(len(sensors)), (np.arange(len(sensors)), [2 * s for s in sensors])), shape=(len(sensors), n)
    )
    Bv = np.zeros((n, 1)); Bv[2 * drive, 0] = 1.0
    model = FRFModel(
        K=AffineMatrix(tuple(Kterms), np.array(Kexp)),
        M=AffineMatrix(tuple(Mterms), np.array(Mexp)),
        inputs=Bv,
        outputs=C,
        input_names=("drive",),
        output_names=tuple(f"acc{s}" for s in sensors),
        parameter_names=PARAMS,
    )
    return model, sensors


def frame_sensor_model(pm):
    """(grids, dirs, FRFModel) of the diagnosis tests' frame set-up: every 8th grid of the parametric model
    ``pm`` (first 10), skewed unit directions (seeded, mostly +z), drives at sensors 0 and 5."""
    import femodel

    gids = np.asarray(pm.assembly.model.grid_ids)
    grids = [int(g) for g in gids[::8]][:10]
    d = np.random.default_rng(1).normal(size=(len(grids), 3)) + [0, 0, 2]
    dirs = d / np.linalg.norm(d, axis=1, keepdims=True)
    C = femodel.sensor_matrix(pm.assembly, grids, dirs)
    return grids, dirs, FRFModel(pm.K, pm.M, C[[0, 5]].T, C, parameter_names=pm.names, parametric=pm)
