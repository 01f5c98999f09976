"""Frequency-domain subspace identification kernels (McKelvey, Akcay & Ljung 1996).

The continuous-time problem is solved through the scaled bilinear map

    s = alpha (z - 1) / (z + 1),   alpha = 2 / T,

which sends the imaginary axis s = i omega onto the unit circle,
z = exp(i theta) with theta = 2 arctan(omega / alpha). A continuous-time model
of order n is *exactly* a discrete-time model of order n in z, so the FRF
samples are used unchanged, only their frequencies are mapped. Choosing
alpha = sqrt(omega_lo omega_hi) spreads the band symmetrically around
theta = pi/2, so the powers z^k that make up the data matrices stay of unit
modulus and well conditioned even at orders ~100 (raw powers of i omega would
span 10^(2 n) over a 100-550 Hz band).

All kernels take arrays in rad/s (stated per function) and return arrays.

References
----------
T. McKelvey, H. Akcay, L. Ljung, "Subspace-based multivariable system
identification from frequency response data", IEEE TAC 41(7), 960-979, 1996.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
from scipy.linalg.blas import zherk

from ._errors import IdentificationError


def bilinear_alpha(omega_lo: float, omega_hi: float) -> float:
    """Bilinear-map scale ``alpha = 2/T = sqrt(omega_lo * omega_hi)`` [rad/s].

    A band starting at DC uses ``omega_lo = omega_hi / 1000`` instead of 0.
    """
    if not omega_hi > 0:
        raise IdentificationError(f"band upper edge must be > 0 rad/s, got {omega_hi}")
    lo = max(float(omega_lo), 1e-3 * float(omega_hi))
    return float(np.sqrt(lo * omega_hi))


def unit_circle(omega: np.ndarray, alpha: float) -> np.ndarray:
    """Map ``s = i omega`` [rad/s] to ``z = (alpha + i omega)/(alpha - i omega)`` on the unit circle."""
    return np.exp(2j * np.arctan(np.asarray(omega, dtype=float) / alpha))


def to_continuous(Ad: np.ndarray, Bd: np.ndarray, Cd: np.ndarray, Dd: np.ndarray, alpha: float):
    """Exact inverse bilinear map of a discrete model in ``z`` to continuous ``(A, B, C, D)``.

    With ``s = alpha (z-1)/(z+1)``: ``A = alpha (Ad - I)(Ad + I)^-1``,
    ``B = sqrt(2 alpha) (Ad + I)^-1 Bd``, ``C = sqrt(2 alpha) Cd (Ad + I)^-1``,
    ``D = Dd - Cd (Ad + I)^-1 Bd``.
    """
    n = Ad.shape[0]
    P = Ad + np.eye(n)
    Pi = np.linalg.inv(P)
    A = alpha * (Ad - np.eye(n)) @ Pi
    r = np.sqrt(2.0 * alpha)
    return A, r * Pi @ Bd, r * Cd @ Pi, Dd - Cd @ Pi @ Bd


def to_discrete(A: np.ndarray, B: np.ndarray, C: np.ndarray, D: np.ndarray, alpha: float):
    """Exact bilinear map of a continuous model to ``z`` (inverse of :func:`to_continuous`)."""
    n = A.shape[0]
    Q = np.linalg.inv(alpha * np.eye(n) - A)
    r = np.sqrt(2.0 * alpha)
    return (alpha * np.eye(n) + A) @ Q, r * Q @ B, r * C @ Q, D + C @ Q @ B


def subspace_basis(z: np.ndarray, H: np.ndarray, block_rows: int) -> tuple[np.ndarray, np.ndarray]:
    """Column space of the extended observability matrix from FRF samples.

    Forms McKelvey's data matrices ``Y = [z_k^j H_k]`` and ``U = [z_k^j I]``
    (``j = 0..q-1``), takes real and imaginary parts side by side, and removes
    the input part by an LQ factorization: ``[U; Y] = L Q``, so that the
    column space of ``L22`` is that of ``O_q``. Only a thin QR of a
    ``(2 n_f n_in) x q (n_in + n_out)`` matrix is computed, never the product
    of the large Hankel-like matrices.

    Parameters
    ----------
    z : ndarray, complex (n_f,)
        Unit-circle frequencies (see :func:`unit_circle`).
    H : ndarray, complex (n_f, p, m)
        FRF samples, already scaled per output.
    block_rows : int
        Number of block rows ``q``; ``q * p`` must exceed the order.

    Returns
    -------
    basis : ndarray, (q p, q p)
        Left singular vectors of ``L22``, best first.
    singular_values : ndarray, (q p,)
    """
    nf, p, m = H.shape
    q = int(block_rows)
    zp = z[:, None] ** np.arange(q)[None, :]  # (nf, q), |z| = 1: well conditioned
    # [U; Y]^T built directly: rows (line, input), columns (block row, input | output)
    ZT = np.empty((2, nf, m, q * (m + p)))
    for part, take in ((0, np.real), (1, np.imag)):
        ZT[part, :, :, : q * m] = take(zp[:, None, :, None] * np.eye(m)[None, :, None, :]).reshape(nf, m, q * m)
        ZT[part, :, :, q * m :] = take(zp[:, None, :, None] * H.transpose(0, 2, 1)[:, :, None, :]).reshape(nf, m, q * p)
    R = np.linalg.qr(ZT.reshape(2 * nf * m, q * (m + p)), mode="r")  # Q is never formed
    L22 = R[q * m :, q * m :].T
    basis, sv, _ = np.linalg.svd(L22, full_matrices=False)
    return basis, sv


def realize(basis: np.ndarray, singular_values: np.ndarray, order: int, p: int):
    """Discrete ``(Ad, Cd)`` of order ``n`` from the observability basis by shift invariance."""
    n = int(order)
    O = basis[:, :n] * np.sqrt(singular_values[:n])[None, :]
    Cd = O[:p, :]
    Ad = np.linalg.lstsq(O[:-p, :], O[p:, :], rcond=None)[0]
    return Ad, Cd


def real_modal_form(A: np.ndarray, B: np.ndarray | None, C: np.ndarray):
    """Similarity transform to real block-diagonal (modal) form.

    Each complex pair ``sigma +/- i omega_d`` becomes the 2x2 block
    ``[[sigma, omega_d], [-omega_d, sigma]]``; each real pole a 1x1 block.
    Blocks are ordered by ``omega_d`` (real poles first).

    Returns
    -------
    Am, Bm, Cm : the transformed matrices (``Bm`` is None when ``B`` is None)
    blocks : list of slices, one per pole (pair) in order
    """
    n = A.shape[0]
    lam, X = np.linalg.eig(A)
    keep = np.flatnonzero(lam.imag >= 0)
    keep = keep[np.lexsort((lam.real[keep], lam.imag[keep]))]
    cols: list[np.ndarray] = []
    blocks: list[slice] = []
    Am = np.zeros((n, n))
    for i in keep:
        v = X[:, i]
        j = len(cols)
        if lam[i].imag == 0.0:
            u = v.real / np.linalg.norm(v.real)
            cols.append(u)
            Am[j, j] = lam[i].real
            blocks.append(slice(j, j + 1))
        else:
            # the phase of v is free: pick the one making Re v and Im v orthogonal
            phi = 0.5 * np.angle(np.sum(v * v))
            v = v * np.exp(-1j * phi)
            sc = np.sqrt(2.0) / np.linalg.norm(v)
            cols.extend([v.real * sc, v.imag * sc])
            s, w = lam[i].real, lam[i].imag
            Am[j : j + 2, j : j + 2] = [[s, w], [-w, s]]
            blocks.append(slice(j, j + 2))
    if len(cols) != n:
        raise IdentificationError(
            f"state matrix of order {n} could not be brought to modal form "
            f"({len(cols)} states found): eigenvalues are not in conjugate pairs"
        )
    T = np.column_stack(cols)
    Bm = None if B is None else np.linalg.solve(T, B)
    return Am, Bm, C @ T, blocks


def _separable(W: np.ndarray):
    """``(a, c)`` if ``W[k, i, j] == a[i] * c[j]`` for every line ``k``, else None."""
    w0 = W[0]
    if not np.allclose(W, w0[None], rtol=1e-12, atol=0):
        return None
    a = w0[:, 0]
    c = w0[0, :] / w0[0, 0]
    if not np.allclose(w0, np.outer(a, c), rtol=1e-12, atol=0):
        return None
    return a, c


def _solve_normal(N: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve a symmetric positive semi-definite system with equilibration; pseudo-inverse if singular."""
    d = np.sqrt(np.abs(np.diag(N)))
    d[d == 0] = 1.0
    Ns = N / np.outer(d, d)
    try:
        cho = sla.cho_factor(Ns, check_finite=False)
        x = sla.cho_solve(cho, rhs / d[:, None], check_finite=False)
    except np.linalg.LinAlgError:
        x = sla.lstsq(Ns, rhs / d[:, None], lapack_driver="gelsd", check_finite=False)[0]
    return x / d[:, None]


def _gram(M: np.ndarray) -> np.ndarray:
    """``M^H M`` of a complex (k, n) array by a Hermitian rank-k update (half the flops of a GEMM, no
    conjugated copy)."""
    U = np.triu(zherk(1.0, M, trans=2, lower=0))
    return U + np.triu(U, 1).conj().T


def _pole_regressor(omega, A, C):
    """(X^-1, C X, G) of ``A = X diag(lam) X^-1``, ``G = 1 / (i omega - lam)`` (n_f, n): what the normal
    systems of one ``A, C`` share whatever their weights."""
    lam, X = np.linalg.eig(A)
    return np.linalg.inv(X), C @ X, 1.0 / (1j * omega[:, None] - lam[None, :])


class _NormalSystem:
    """Structured normal equations of the ``B, D`` least-squares fit.

    In a diagonalizing basis ``A = X diag(lam) X^-1`` the regressor of line k
    is ``C X diag(g_k) X^-1`` with ``g_k = 1/(i omega_k - lam)``. With output
    weights ``a`` (same on every line) the normal matrix is
    ``X^-H [(X^H C^T a^2 C X) .* (G^H G)] X^-1``: O(n_f n^2) work instead of
    O(n_f n_out n^2) for a QR of the stacked regressor. With per-line weights
    ``w (n_f, p)`` it is one complex GEMM of the weighted regressor. Unknowns
    are ``[B (n rows); D (p rows)]``, one column per input sharing the weights.
    """

    def __init__(self, omega, A, C, a=None, w=None, poles=None):
        nf = omega.size
        p, n = C.shape
        self.n, self.p = n, p
        # the part that does not depend on the weights: shared by the systems of one fit (one per input)
        self.Xi, self.Ct, self.G = poles if poles is not None else _pole_regressor(omega, A, C)
        if w is None:
            self.w2 = np.broadcast_to((a**2)[None, :], (nf, p))
            V = self.Ct.conj().T * (a**2)[None, :]
            Nbb = (V @ self.Ct) * (self.G.conj().T @ self.G)
        else:
            # sum over outputs i of (Ct_i^H Ct_i) .* (G^H diag(w_:i^2) G): p Hermitian rank-k updates of (nf, n)
            # instead of one GEMM of the (nf p, n) weighted regressor, which is never formed (this product 4-7x
            # faster alone at 3321 lines, 16 outputs, n = 50-100; a whole identification 13-15 %; equal to 1e-15)
            self.w2 = w**2
            Nbb = np.zeros((n, n), complex)
            for i in range(p):
                Nbb += np.outer(self.Ct[i].conj(), self.Ct[i]) * _gram(self.G * w[:, i : i + 1])
        Nbb = self.Xi.conj().T @ Nbb @ self.Xi
        P = self.G.conj().T @ self.w2  # (n, p): sum_k conj(g_kr) w_ki^2
        Nbd = self.Xi.conj().T @ (self.Ct.conj().T * P)
        N = np.zeros((n + p, n + p))
        N[:n, :n] = Nbb.real
        N[:n, n:] = Nbd.real
        N[n:, :n] = Nbd.real.T
        N[n:, n:] = np.diag(self.w2.sum(axis=0))
        self.N = N

    def rhs(self, E):
        """``Re(J^H E)`` for data or residual ``E`` (nf, p, m)."""
        WE = self.w2[:, :, None] * E  # (nf, p, m)
        Q = np.einsum("kr,kpm->rpm", self.G.conj(), WE, optimize=True)  # (n, p, m)
        rb = self.Xi.conj().T @ np.einsum("pr,rpm->rm", self.Ct.conj(), Q, optimize=True)
        rd = WE.sum(axis=0)
        return np.vstack([rb.real, rd.real])

    def model(self, x):
        """FRF of unknowns ``x`` at the lines: (nf, p, m)."""
        Bt = self.Xi @ x[: self.n]
        return np.einsum("pr,kr,rm->kpm", self.Ct, self.G, Bt, optimize=True) + x[self.n :][None]

    def solve(self, H):
        """Least-squares ``x`` with one step of iterative refinement on the residual."""
        x = _solve_normal(self.N, self.rhs(H))
        return x + _solve_normal(self.N, self.rhs(H - self.model(x)))


def _fit_bd_separable(omega, H, a, A, C):
    """Fast ``B, D`` fit for output weights ``a`` (same on every line and input)."""
    ns = _NormalSystem(omega, A, C, a=a)
    x = ns.solve(H)
    return x[: ns.n], x[ns.n :]


def importance(omega: np.ndarray, H: np.ndarray, a: np.ndarray, A: np.ndarray, C: np.ndarray, blocks) -> np.ndarray:
    """Relative increase of the weighted residual when a block (pole) is removed and B, D refitted.

    Uses the exact least-squares downdate ``dSSR = x_S^T [(N^-1)_SS]^-1 x_S``
    (summed over inputs) instead of refitting once per pole.

    Parameters
    ----------
    omega : (n_f,) rad/s; H : (n_f, p, m)
    a : (p,) output weights, or (n_f, p, m) per-line weights (1/standard error)
    A : (n, n) modal form; C : (p, n); blocks : list of slices of the states

    Returns
    -------
    ndarray (n_blocks,)
        ``dSSR / SSR``; >> 1 for a pole the data need, << 1 for one fitting noise.
    """
    a = np.asarray(a, dtype=float)
    if a.ndim == 1:
        systems = [(_NormalSystem(omega, A, C, a=a), H, np.broadcast_to(a[None, :, None], H.shape))]
    else:  # per-line weights (n_f, p, m): one normal system per input, as in fit_bd
        poles = _pole_regressor(omega, A, C)
        systems = [(_NormalSystem(omega, A, C, w=a[:, :, j], poles=poles), H[:, :, j : j + 1], a[:, :, j : j + 1])
                   for j in range(H.shape[2])]
    ssr = 0.0
    dssr = np.zeros(len(blocks))
    for ns, Hj, Wj in systems:
        x = ns.solve(Hj)
        ssr += float(np.sum(np.abs((Hj - ns.model(x)) * Wj) ** 2))
        d = np.sqrt(np.abs(np.diag(ns.N)))
        d[d == 0] = 1.0
        Ninv = np.linalg.pinv(ns.N / np.outer(d, d), hermitian=True) / np.outer(d, d)
        for i, b in enumerate(blocks):
            xs = x[b, :]
            dssr[i] += float(np.sum(xs * np.linalg.solve(Ninv[b, b], xs)))
    return dssr / max(ssr, np.finfo(float).tiny)


def fit_bd(omega: np.ndarray, H: np.ndarray, W: np.ndarray, A: np.ndarray, C: np.ndarray):
    """Least-squares ``B, D`` for fixed modal-form ``A, C``: min sum |W (C(iwI-A)^-1 B + D - H)|^2.

    Parameters
    ----------
    omega : (n_f,) rad/s
    H : (n_f, p, m) complex data
    W : (n_f, p, m) real positive weights (1/standard error)
    A : (n, n) real block-diagonal modal form (see :func:`real_modal_form`)
    C : (p, n)

    Returns
    -------
    B : (n, m), D : (p, m)

    Notes
    -----
    Weights that factor as ``W[k, i, j] = a[i] c[j]`` (per-output noise
    levels, the default) use fast structured normal equations; general
    per-line weights build the normal matrix with one GEMM per input.
    """
    nf, p, m = H.shape
    n = A.shape[0]
    sep = _separable(W)
    if sep is not None:
        return _fit_bd_separable(omega, H, sep[0], A, C)
    B = np.empty((n, m))
    D = np.empty((p, m))
    poles = _pole_regressor(omega, A, C)
    for j in range(m):
        ns = _NormalSystem(omega, A, C, w=W[:, :, j], poles=poles)
        x = ns.solve(H[:, :, j : j + 1])
        B[:, j] = x[:n, 0]
        D[:, j] = x[n:, 0]
    return B, D


def fit_cd(omega: np.ndarray, H: np.ndarray, W: np.ndarray, A: np.ndarray, B: np.ndarray):
    """Least-squares ``C, D`` for fixed modal-form ``A, B`` (the dual of :func:`fit_bd`).

    Cheap: the regressor has ``2 n_f n_in`` rows.
    """
    C, D = fit_bd(omega, H.transpose(0, 2, 1), W.transpose(0, 2, 1), A.T, B.T)
    return C.T, D.T
