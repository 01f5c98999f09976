"""Modal refit of an identified model: physical poles refined, out-of-band modes as residual poles.

The subspace step places the poles; its state-space model then holds only
what the chosen order leaves room for. Modes just outside the analysed band
(a lightly damped mode a few percent above the top line, elastic modes below
the first line) shape the in-band FRF in a way no constant ``D`` reproduces,
and an order chosen for its physical poles has no states to spare for them:
on a shell model with modes 3 % above the data and two below it, the
subspace model misfit its own lines 1000x above their noise.

The refit (a frequency-domain LSFD with variable projection):

1. Basis: each physical pole's pair ``R/(s - lam) + conj(R)/(s - conj lam)``
   and fixed *residual poles* outside the band, at
   ``f_hi x (1.02, 1.06, 1.15, 1.35, 1.8)`` and ``f_lo x (0.4, 0.6, 0.8,
   0.92)`` with 2 % damping, plus a constant.
2. Residues free per channel pair (weighted linear least squares);
   the physical poles (frequency, damping) refined by Levenberg-Marquardt on
   the projected residual (Kaufman's variable-projection Jacobian).
3. Realization: each physical residue at rank one (its leading singular
   pair: mode shape x participation), each residual pole at rank
   ``min(n_out, n_in, 3)`` (copies of the pole 0.2 % apart); then
   ``C, D`` and ``B, D`` refitted once more with the rank-one structure.

The refit replaces the subspace model only where it lowers the weighted
residual over the band, and is not tried on fewer than 8 real values per
channel pair and unknown (a 41-line stepped sine of one mode: the residual
poles would fit its distortion and move the pole). The record is
``Identification.settings["modal_refit"]``.
"""

from __future__ import annotations

import numpy as np

from ._identify import block_poles
from ._subspace import fit_bd, fit_cd, real_modal_form

UPPER = (1.02, 1.06, 1.15, 1.35, 1.8)
LOWER = (0.4, 0.6, 0.8, 0.92)
ZETA_RESIDUAL = 0.02
MIN_LINES_PER_UNKNOWN = 8  # real values per channel pair over the unknowns of its least-squares fit


def residual_poles(band_hz) -> np.ndarray:
    """The fixed residual poles (Im > 0) [rad/s] of a band."""
    lo, hi = float(band_hz[0]), float(band_hz[1])
    w = 2 * np.pi * np.array([hi * u for u in UPPER] + ([lo * u for u in LOWER] if lo > 0 else []))
    return -ZETA_RESIDUAL * w + 1j * w * np.sqrt(1 - ZETA_RESIDUAL**2)


class _Projection:
    """Weighted LSFD of every channel pair on the basis of given poles (Im > 0) plus a constant."""

    def __init__(self, s, H, W):
        self.s, self.H, self.W = s, H, W
        nf, p, m = H.shape
        self.pairs = [(o, i) for o in range(p) for i in range(m)]
        self.y = [np.concatenate([(H[:, o, i] * W[:, o, i]).real, (H[:, o, i] * W[:, o, i]).imag])
                  for o, i in self.pairs]

    def basis(self, lam):
        s = self.s[:, None]
        a, b = 1.0 / (s - lam[None, :]), 1.0 / (s - np.conj(lam)[None, :])
        Phi = np.empty((self.s.size, 2 * lam.size + 1), complex)
        Phi[:, 0 : 2 * lam.size : 2] = a + b
        Phi[:, 1 : 2 * lam.size : 2] = 1j * (a - b)
        Phi[:, -1] = 1.0
        return Phi, a, b

    def solve(self, lam, n_free: int = 0):
        """Coefficients per pair, the weighted SSR and (with ``n_free`` > 0) the normal equations of the
        first ``n_free`` poles' (log -Re, relative Im) parameters: (x list, ssr, JTJ, JTr)."""
        Phi, a, b = self.basis(lam)
        xs, ssr = [], 0.0
        npar = 2 * n_free
        JTJ, JTr = np.zeros((npar, npar)), np.zeros(npar)
        for (o, i), y in zip(self.pairs, self.y):
            w = self.W[:, o, i]
            Aw = Phi * w[:, None]
            Ar = np.concatenate([Aw.real, Aw.imag])
            Q, R = np.linalg.qr(Ar)
            qy = Q.T @ y
            x = np.linalg.lstsq(R, qy, rcond=1e-12)[0]
            r = Ar @ x - y
            ssr += float(r @ r)
            xs.append(x)
            if npar:
                Rc = x[0 : 2 * n_free : 2] + 1j * x[1 : 2 * n_free : 2]
                a2, b2 = a[:, :n_free] ** 2, b[:, :n_free] ** 2
                d_sigma = Rc * a2 + np.conj(Rc) * b2  # d(term)/d sigma, per pole
                d_omega = 1j * (Rc * a2 - np.conj(Rc) * b2)
                lam_f = lam[:n_free]
                G = np.empty((self.s.size, npar), complex)
                G[:, 0::2] = d_sigma * lam_f.real[None, :]  # d/d log(-sigma) = sigma d/d sigma
                G[:, 1::2] = d_omega * lam_f.imag[None, :]  # d/d (omega/omega0) at the current point
                G *= w[:, None]
                Gr = np.concatenate([G.real, G.imag])
                J = Gr - Q @ (Q.T @ Gr)  # Kaufman: (I - P) dA/dp x
                JTJ += J.T @ J
                JTr += J.T @ r
        return xs, ssr, JTJ, JTr


#: Largest relative change of a physical pole's frequency over the whole refit (each step: 1 %).
MAX_POLE_DRIFT = 0.02
#: Largest factor by which a physical pole's decay rate (its damping) may change over the whole refit.
MAX_DAMPING_FACTOR = 4.0


def _lm(proj, lam_phys, lam_res, band_omega, zeta_max, max_iter, tol):
    """Levenberg-Marquardt on the physical poles; returns (lam_phys, per-pair coefficients there, ssr0, ssr,
    iterations)."""
    n = lam_phys.size

    def params_to_lam(lam0, dp):
        # a pole refines its mode; it does not leave it: travel to another mode (a weak mode's pole drifting
        # 1 % per step toward a strong mode the subspace missed) or widen into a broad term that soaks up that
        # mode's tail (0.2 % -> 11 % damping in 5 steps); an outside panel lost its 118 Hz mode so (stop 33)
        sig = np.clip(lam0.real * np.exp(dp[0::2]), lam_phys.real * MAX_DAMPING_FACTOR,
                      lam_phys.real / MAX_DAMPING_FACTOR)
        om = np.clip(lam0.imag * (1 + dp[1::2]), lam_phys.imag * (1 - MAX_POLE_DRIFT),
                     lam_phys.imag * (1 + MAX_POLE_DRIFT))
        return sig + 1j * om

    lam = lam_phys.copy()
    xs, ssr0, JTJ, JTr = proj.solve(np.concatenate([lam, lam_res]), n)
    ssr, mu, it = ssr0, 1e-3, 0
    for it in range(1, max_iter + 1):
        d = np.sqrt(np.maximum(np.diag(JTJ), 1e-300))
        improved = False
        for _ in range(8):
            Ns = JTJ / np.outer(d, d) + mu * np.eye(2 * n)
            try:
                dp = -np.linalg.solve(Ns, JTr / d) / d
            except np.linalg.LinAlgError:
                mu *= 10
                continue
            dp[1::2] = np.clip(dp[1::2], -0.01, 0.01)  # a pole moves at most 1 % per step
            dp[0::2] = np.clip(dp[0::2], -1.0, 1.0)
            new = params_to_lam(lam, dp)
            z = -new.real / np.abs(new)
            f_ok = (new.imag >= band_omega[0]) & (new.imag <= band_omega[1])
            if np.all(f_ok) and np.all(z < zeta_max) and np.all(z > 0):
                xs_new, ssr_new, JTJn, JTrn = proj.solve(np.concatenate([new, lam_res]), n)
                if ssr_new < ssr:
                    dec = (ssr - ssr_new) / ssr
                    lam, xs, ssr, JTJ, JTr = new, xs_new, ssr_new, JTJn, JTrn
                    mu = max(mu / 3, 1e-9)
                    improved = True
                    break
            mu *= 4
        if not improved or dec < tol:
            break
    return lam, xs, ssr0, ssr, it


def _realize(lam, residues):
    """Real (A, B, C) of poles ``lam`` (Im > 0), each with its residue matrix (k, p, m) at rank one (the
    leading singular pair), brought to the library's real modal form."""
    k, p, m = residues.shape
    A, B, C = np.zeros((2 * k, 2 * k)), np.zeros((2 * k, m)), np.zeros((p, 2 * k))
    for j, (lm, R) in enumerate(zip(lam, residues)):
        U, S, Vh = np.linalg.svd(R)
        c, b = U[:, 0] * np.sqrt(S[0]), Vh[0, :] * np.sqrt(S[0])
        sl = slice(2 * j, 2 * j + 2)
        A[sl, sl] = [[lm.real, -lm.imag], [lm.imag, lm.real]]  # z' = lam z + b u, y = 2 Re(c z)
        B[sl] = np.vstack([b.real, b.imag])
        C[:, sl] = np.column_stack([2 * c.real, -2 * c.imag])
    return real_modal_form(A, B, C)


def modal_refit(data, lam_phys, zeta_max: float = 0.2, max_iter: int = 30, tol: float = 1e-4):
    """Refit on ``data`` (identification orientation) with the physical poles ``lam_phys`` (Im > 0).

    Returns
    -------
    (A, B, C, D, blocks, physical_mask, info), or a string saying why no refit was made (no physical
    pole; fewer than ``MIN_LINES_PER_UNKNOWN`` real values per channel pair and unknown).
    ``physical_mask`` marks the blocks of the refined physical poles; ``info``
    records the residual poles, the iterations and the weighted SSR.
    """
    lam_phys = np.asarray(lam_phys, complex)
    if lam_phys.size == 0:
        return "no physical pole"
    nf, p, m = data.H.shape
    rank = int(min(p, m, 3))
    lam_res = residual_poles(data.band_hz)
    n_basis = 2 * (lam_phys.size + lam_res.size) + 1
    if 2 * nf < MIN_LINES_PER_UNKNOWN * n_basis:
        # on a handful of lines the residual poles would fit whatever the modes leave (distortion, noise)
        return (f"too few lines: {nf} lines give {2 * nf} values per channel pair for {n_basis} unknowns "
                f"(needs {MIN_LINES_PER_UNKNOWN}x)")
    proj = _Projection(1j * data.omega, data.H, data.W)
    band_omega = (2 * np.pi * data.band_hz[0], 2 * np.pi * data.band_hz[1])
    lam, xs, ssr0, ssr, it = _lm(proj, lam_phys, lam_res, band_omega, zeta_max, max_iter, tol)
    k = lam.size + lam_res.size
    R = np.zeros((k, p, m), complex)
    for (o, i), x in zip(proj.pairs, xs):  # the constant (x[-1]) is refitted with D below
        R[:, o, i] = x[0 : 2 * k : 2] + 1j * x[1 : 2 * k : 2]
    # a residual pole stands for several modes: its residue keeps ``rank`` singular pairs, each on a copy
    # of the pole 0.2 % apart (a real modal form needs distinct eigenvalues)
    lam_r, R_r = list(lam), list(R[: lam.size])
    for g, lr in enumerate(lam_res):
        U, S, Vh = np.linalg.svd(R[lam.size + g])
        for j in range(min(rank, S.size)):
            lam_r.append(complex(lr.real * (1 + 0.002 * j), lr.imag * (1 + 0.002 * j)))
            R_r.append((U[:, j : j + 1] * S[j]) @ Vh[j : j + 1, :])
    A, B, C, blocks = _realize(np.array(lam_r), np.array(R_r))
    C, D = fit_cd(data.omega, data.H, data.W, A, B)
    B, D = fit_bd(data.omega, data.H, data.W, A, C)
    lam_blocks = block_poles(A, blocks)
    phys = np.zeros(len(blocks), bool)
    for lp in lam:
        phys[int(np.argmin(np.abs(lam_blocks - lp)))] = True
    info = {"residual_poles_hz": [round(float(abs(x)) / (2 * np.pi), 3) for x in lam_res],
            "residual_rank": rank, "iterations": int(it), "lsfd_ssr_start": float(ssr0), "lsfd_ssr": float(ssr),
            "max_pole_shift_rel": float(np.max(np.abs(lam - lam_phys) / np.abs(lam_phys)))}
    return A, B, C, D, blocks, phys, info
