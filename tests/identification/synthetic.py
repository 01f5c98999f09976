"""Manufactured truth for identification tests: a mistuned ring (closely spaced modes)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla


@dataclass(frozen=True)
class Truth:
    freq_hz: np.ndarray  # (n_f,)
    H: np.ndarray  # (n_f, n_out, n_in) noisy accelerance
    H_clean: np.ndarray
    sigma: np.ndarray  # (n_f, n_out, n_in) noise standard deviation per element
    f_n: np.ndarray  # (n_modes,) undamped natural frequencies [Hz]
    zeta: np.ndarray  # (n_modes,)
    shapes: np.ndarray  # (n_out, n_modes) real mass-normalized mode shapes at the outputs
    M: np.ndarray
    K: np.ndarray


def ring(
    n_mass: int = 20,
    inputs: tuple[int, ...] = (0, 3),
    f_lo: float = 120.0,
    f_hi: float = 520.0,
    zeta: float = 1e-3,
    mistuning: float = 0.03,
    n_lines: int = 2000,
    band: tuple[float, float] = (100.0, 550.0),
    noise: float = 0.005,
    seed: int = 0,
) -> Truth:
    """Ring of masses with ground springs: cyclic symmetry gives pairs of close modes.

    Mass mistuning splits each double mode into two modes a few half-power
    bandwidths apart. FRFs are accelerance at every mass (n_out = n_mass) for
    forces at ``inputs``, with modal viscous damping ``zeta`` (paper Eq. 2.14),
    on a geometric grid of ``n_lines`` over ``band``, plus complex Gaussian
    noise of relative level ``noise``.
    """
    rng = np.random.default_rng(seed)
    w_lo, w_hi = 2 * np.pi * f_lo, 2 * np.pi * f_hi
    kg = w_lo**2
    kc = (w_hi**2 - w_lo**2) / 4.0
    K = np.zeros((n_mass, n_mass))
    for i in range(n_mass):
        j = (i + 1) % n_mass
        K[i, i] += kg + 2 * kc
        K[i, j] -= kc
        K[j, i] -= kc
    m = 1.0 + mistuning * rng.uniform(-1, 1, n_mass)
    M = np.diag(m)
    w2, X = sla.eigh(K, M)  # mass-normalized
    wn = np.sqrt(w2)
    zetas = np.full(n_mass, zeta)
    f = np.geomspace(band[0], band[1], n_lines)
    w = 2 * np.pi * f
    Xin = X[inputs, :]  # (n_in, n_modes)
    den = wn[None, :] ** 2 - w[:, None] ** 2 + 2j * zetas[None, :] * wn[None, :] * w[:, None]
    # accelerance = -w^2 * receptance
    H = -(w**2)[:, None, None] * np.einsum("om,fm,im->foi", X, 1.0 / den, Xin)
    sigma = noise * np.abs(H) + 1e-3 * noise * np.sqrt(np.mean(np.abs(H) ** 2))
    Hn = H + sigma / np.sqrt(2) * (rng.standard_normal(H.shape) + 1j * rng.standard_normal(H.shape))
    return Truth(f, Hn, H, sigma, wn / (2 * np.pi), zetas, X, M, K)
