"""Manufactured mode-shape problems with known physics for the pretest tests."""

from __future__ import annotations

import numpy as np


def plate_modes(nx: int = 13, ny: int = 9, n_modes: int = 8, a: float = 1.0, b: float = 0.7,
                noise: float = 0.0, seed: int = 0):
    """Simply supported plate: phi_mn = sin(m pi x/a) sin(n pi y/b), modes ordered by (m/a)^2 + (n/b)^2.

    Returns (phi (n_points, n_modes), xyz (n_points, 3), (m, n) pairs).  A
    little noise breaks the plate's symmetry ties when asked.
    """
    x, y = np.meshgrid(np.linspace(0.04 * a, 0.96 * a, nx), np.linspace(0.05 * b, 0.95 * b, ny))
    x, y = x.ravel(), y.ravel()
    pairs = sorted(((m, n) for m in range(1, 12) for n in range(1, 12)), key=lambda p: (p[0] / a) ** 2 + (p[1] / b) ** 2)
    pairs = pairs[:n_modes]
    phi = np.column_stack([np.sin(m * np.pi * x / a) * np.sin(n * np.pi * y / b) for m, n in pairs])
    if noise:
        phi = phi + noise * np.random.default_rng(seed).standard_normal(phi.shape)
    return phi, np.column_stack([x, y, np.zeros_like(x)]), pairs


def chain_system(n: int = 8, k: float = 1.0e4, m: float = 0.5, seed: int = 3):
    """A free-fixed spring-mass chain with slightly random masses; (K, M) dense."""
    rng = np.random.default_rng(seed)
    masses = m * (1 + 0.3 * rng.random(n))
    K = np.zeros((n, n))
    for i in range(n):
        K[i, i] += k
        if i + 1 < n:
            K[i, i] += k
            K[i + 1, i + 1] += 0.0
            K[i, i + 1] -= k
            K[i + 1, i] -= k
    return K, np.diag(masses)


def naive_efi(phi: np.ndarray, n_keep: int, groups=None) -> np.ndarray:
    """Textbook EfI: recompute Q^-1 and every group's det(I - E_g) from scratch each step."""
    n = phi.shape[0]
    groups = np.arange(n) if groups is None else np.asarray(groups)
    labels = np.unique(groups)
    active = list(range(labels.size))
    while len(active) > n_keep:
        rows = np.flatnonzero(np.isin(groups, labels[active]))
        qinv = np.linalg.inv(phi[rows].T @ phi[rows])
        scores = []
        for g in active:
            b = phi[groups == labels[g]]
            scores.append(np.linalg.det(np.eye(b.shape[0]) - b @ qinv @ b.T))
        active.pop(int(np.argmax(scores)))
    return np.array(sorted(active))
