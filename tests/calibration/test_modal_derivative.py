"""The Nelson-form FRF derivative kernel against central differences of the modal sum itself.

A reduced model in its own modal coordinates: K_r = diag(lambda), M_r = I, with
six rigid modes whose eigenvalues are round-off (+-1e-7, as a free-free
solver leaves them), an exactly repeated elastic pair (a symmetric
structure's), a close pair and well separated modes; perturbations A, B
random symmetric with the rigid block of A at round-off level and slightly
unsymmetric (as Phi^T dK Phi comes out). The reference is the FRF of the
perturbed model, solved again, at +-h.
"""

import numpy as np
import pytest
import scipy.linalg as sla

from calibration._modal_derivative import (
    damping_factor,
    derivative_factor,
    eigen_derivatives,
    line_factor,
    pair_products,
)
from calibration._surrogate import modal_frf, modal_omegas

RIGID_HZ = 0.01
ZETA = 0.01


def _model(seed=0):
    rng = np.random.default_rng(seed)
    f_el = np.array([40.0, 55.0, 55.0, 71.0, 71.0 * (1 + 3e-6), 90.0, 130.0, 260.0, 400.0])
    lam = np.concatenate([rng.uniform(-1e-7, 1e-7, 6), (2 * np.pi * f_el) ** 2])
    m = lam.size
    A = rng.standard_normal((m, m)) * np.sqrt(np.outer(lam.clip(1), lam.clip(1))) * 0.05
    A = A + A.T
    A[:6, :6] = rng.standard_normal((6, 6)) * 1e-8  # a stiffness term strains no rigid mode: round-off
    B = rng.standard_normal((m, m)) * 0.05
    B = B + B.T
    u = rng.standard_normal((4, m))
    v = rng.standard_normal((m, 2))
    return lam, A, B, u, v


def _frf(lam, u, v, f):
    return modal_frf(lam, u, v, f, ZETA, "accelerance", RIGID_HZ)


@pytest.mark.parametrize("which", ["stiffness", "mass", "both"])
def test_derivative_of_degenerate_rigid_and_close_modes(which):
    lam, A, B, u, v = _model()
    A = A if which != "mass" else np.zeros_like(A)
    B = B if which != "stiffness" else np.zeros_like(B)
    f = np.concatenate([np.linspace(5.0, 450.0, 700), [55.0, 71.0]])
    om, rigid = modal_omegas(lam, RIGID_HZ)
    assert rigid.sum() == 6
    D, G = eigen_derivatives(lam, A[None], B[None], RIGID_HZ)
    R = derivative_factor(u, v, G, D, damping_factor(np.full(lam.size, ZETA), om, rigid))
    _, rq, L = line_factor(2 * np.pi * f, np.where(rigid, 0.0, om**2), np.where(rigid, 0.0, 2 * ZETA * om),
                           "accelerance")
    dH = (L @ R).reshape(f.size, 4, 2)
    np.testing.assert_allclose((rq @ pair_products(u, v)).reshape(f.size, 4, 2), _frf(lam, u, v, f), rtol=1e-12)

    def solved(c):
        mu, Y = sla.eigh(np.diag(lam) + c * A, np.eye(lam.size) + c * B)
        return _frf(mu, u @ Y, Y.T @ v, f)

    err = []
    for h in (1e-6, 1e-7):
        fd = (solved(h) - solved(-h)) / (2 * h)
        err.append(np.max(np.abs(dH - fd) / np.abs(fd).max(axis=(1, 2))[:, None, None]))
    # per line, relative to the line's largest derivative: the divided-difference form agrees within the
    # central difference's own error, which shrinks with h (it is not a wrong derivative)
    assert err[1] < 2e-4, err
