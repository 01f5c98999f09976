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


def free_free(
    in_band_hz: tuple[float, ...] = (
        104.0, 131.0, 158.0, 176.0, 203.0, 241.0, 262.0, 297.0, 318.0,
        355.0, 383.0, 412.3, 447.0, 486.0, 521.0, 548.0, 583.0,
    ),
    out_of_band_hz: tuple[float, ...] = (62.0, 84.0, 618.0, 700.0, 850.0),
    zeta_range: tuple[float, float] = (5e-4, 3e-3),
    n_out: int = 20,
    n_in: int = 2,
    n_rigid: int = 6,
    data_hz: tuple[float, float] = (90.0, 600.0),
    n_lines: int = 2000,
    noise: float = 0.01,
    seed: int = 0,
) -> Truth:
    """Free-free structure in accelerance: rigid-body mass line, lightly damped modes in and out of band.

    Modal model with random mass-normalized shapes at the ``n_out`` sensors
    (the inputs act at the first ``n_in`` sensors, so the FRF is reciprocal).
    ``n_rigid`` rigid-body modes at 0 Hz give the mass line: their accelerance
    ``-omega^2 phi phi^T / (-omega^2) = phi phi^T`` is constant, as measured
    above the suspension modes. Each elastic mode has its own damping ratio,
    drawn log-uniformly in ``zeta_range``. Modes ``out_of_band_hz`` lie
    outside the data (``data_hz``, geometric grid of ``n_lines``) but their
    residual terms shape the data near the edges. Complex Gaussian noise of
    relative level ``noise`` per element. ``f_n, zeta, shapes`` of the
    returned truth are those of the in-band modes only (sorted by frequency).
    """
    rng = np.random.default_rng(seed)
    f_el = np.array(sorted(in_band_hz) + sorted(out_of_band_hz), dtype=float)
    n_el = f_el.size
    zeta = np.exp(rng.uniform(np.log(zeta_range[0]), np.log(zeta_range[1]), n_el))
    phi = rng.standard_normal((n_out, n_el)) * 0.3
    phi_rb = rng.standard_normal((n_out, n_rigid)) * 0.3
    f = np.geomspace(data_hz[0], data_hz[1], n_lines)
    w = 2 * np.pi * f
    wn = 2 * np.pi * f_el
    den = wn[None, :] ** 2 - w[:, None] ** 2 + 2j * zeta[None, :] * wn[None, :] * w[:, None]
    H = -(w**2)[:, None, None] * np.einsum("om,fm,im->foi", phi, 1.0 / den, phi[:n_in])
    H = H + (phi_rb @ phi_rb[:n_in].T)[None, :, :]  # rigid-body mass line
    sigma = noise * np.abs(H) + 1e-3 * noise * np.sqrt(np.mean(np.abs(H) ** 2))
    Hn = H + sigma / np.sqrt(2) * (rng.standard_normal(H.shape) + 1j * rng.standard_normal(H.shape))
    k = len(in_band_hz)
    order = np.argsort(f_el[:k])
    return Truth(f, Hn, H, sigma, f_el[:k][order], zeta[:k][order], phi[:, :k][:, order], np.eye(0), np.eye(0))


def planar_frame(seed: int = 0, lines_per_hz: float = 4.0, noise: float = 0.007):
    """A planar frame as a lab measures it: 15 out-of-plane sensors driven out of plane (16 modes,
    40-360 Hz), 3 in-plane sensors driven in plane (4 modes: 69, 83.6, 152, 241 Hz), the two planes
    uncoupled (the cross pairs hold noise only); uniform grid 32-375 Hz of ``lines_per_hz`` lines per Hz
    (about one line per half-power bandwidth at 0.15 % damping, 84 Hz); damping 0.05-0.3 % out of plane,
    0.1-0.25 % in plane; noise ``noise`` x |H| plus 1e-3 x the median out-of-plane |H|.

    Returns (freq_hz, H_noisy, H, f_in_plane, zeta_in_plane, f_out_of_plane, zeta_out_of_plane).
    """
    rng = np.random.default_rng(seed)
    f = np.arange(32.0, 375.0, 1.0 / lines_per_hz)
    fo = np.sort(rng.uniform(40, 360, 16))
    fi = np.array([69.0, 83.6, 152.0, 241.0])
    zo = np.exp(rng.uniform(np.log(5e-4), np.log(3e-3), fo.size))
    zi = np.exp(rng.uniform(np.log(1e-3), np.log(2.5e-3), fi.size))
    po, qo = rng.normal(size=(fo.size, 15)), rng.normal(size=(fo.size,))
    pi, qi = rng.normal(size=(fi.size, 3)), rng.normal(size=(fi.size,))
    w = 2 * np.pi * f
    H = np.zeros((f.size, 18, 2), complex)
    for fn, z, p, q, outs, inp in [(fo, zo, po, qo, slice(0, 15), 0), (fi, zi, pi, qi, slice(15, 18), 1)]:
        wn = 2 * np.pi * fn
        g = -w[:, None] ** 2 / (wn[None] ** 2 - w[:, None] ** 2 + 2j * z[None] * wn[None] * w[:, None])
        H[:, outs, inp] = np.einsum("fm,mo,m->fo", g, p, q)
    sig = np.sqrt((noise * np.abs(H)) ** 2 + (1e-3 * np.median(np.abs(H[:, :15, 0]))) ** 2)
    Hn = H + sig / np.sqrt(2) * (rng.normal(size=H.shape) + 1j * rng.normal(size=H.shape))
    return f, Hn, H, fi, zi, fo, zo
