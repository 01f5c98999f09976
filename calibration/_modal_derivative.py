"""Exact FRF derivatives of the modal-damped reduced model in its own modal coordinates (Nelson's expansion).

The reduced model's FRF is the modal sum (docs/calibration.md, Surrogate)

    H(w) = q(w) sum_k u_k v_k r_k(w),   r_k = 1 / (lambda_k - w^2 + i w c_k),   c_k = 2 zeta_k omega_k,

u_k = C T x_k, v_k = x_k^T T^T B. For a change of the reduced matrices with
A_j = X^T dK_r/dp_j X and B_j = X^T dM_r/dp_j X (p_j a parameter or a
candidate's magnitude), the eigenvalue and eigenvector derivatives are
d lambda_jk = A_jkk - lambda_k B_jkk and dX_j = X G_j with

    G_jlk = (A_jlk - lambda_k B_jlk) / (lambda_k - lambda_l)  (l != k),   G_jkk = -B_jkk / 2

(the reduced basis is complete, so the expansion is exact), and with the
damping ratios held, dc_jk = zeta_k d lambda_jk / omega_k. Then

    dH_j = q sum_k [ r_k ((u G_j)_k v_k + u_k (G_j^T v)_k) - r_k^2 (d lambda_jk + i w dc_jk) u_k v_k ]

Per line this is the row ``[r q, r^2 q, i w r^2 q]`` (3m values) times one
real (3m, n o i) matrix that does not depend on frequency: 3 m n n_out n_in
multiply-adds per line for n derivatives, where the divided-difference form
(the m x m matrix between diag(r) and diag(r) at every frequency) costs
m^2 n n_in; at r = 100-180 reduced modes and 9-11 outputs that is a tenth.

Pairs of one degenerate group (|lambda_k - lambda_l| <= 1e-9 of the larger)
take the limit of their divided differences instead: G_lk = -B_lk / 2 (what
X^T M X = I fixes; the rest only rotates the pair) and the coupling
A_lk - lambda B_lk beside d lambda in the r^2 terms. Rigid modes (whose FRF
term q / (-w^2) does not depend on lambda) are one such group without the r^2
terms. For close, not degenerate pairs the large G_lk of the two orderings
cancel in the sum, to round-off of about eps 2 zeta / (relative gap) of the
derivative at the pair's resonance; A and B are symmetrized first, since only
their symmetric parts cancel (a rigid pair's A_lk is pure round-off: left
unsymmetric, a 1e-8 asymmetry over a 1e-7 gap put a frame candidate's derivative 7x off).
"""

from __future__ import annotations

import numpy as np

from calibration._metric import LN10, log_deviation
from calibration._surrogate import Surrogate, modal_omegas, quantity_factor, reduced_modes, reduced_term_stack
from calibration._threads import data_threads, thread_map

#: Values (lines x channel pairs) per slice of the rows: the unit of work of a thread and of the TSQR
#: leaves (2 x this rows of ~30 columns stay in a 2 MB cache).
CHUNK_VALUES = 4096


def parameter_derivatives(sur: Surrogate, p, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A_j = X^T dK_r/dp_j X and B_j = X^T dM_r/dp_j X for every parameter: two (n_p, m, m) arrays."""
    m = X.shape[1]
    out = []
    for stack, dc in ((sur.K, sur.K.coefficient_jacobian(p)), (sur.M, sur.M.coefficient_jacobian(p))):
        D = np.zeros((dc.shape[1], m, m))
        moves = np.flatnonzero(np.any(dc != 0, axis=0))  # a density moves no stiffness term, a modulus no mass
        terms = reduced_term_stack(stack)
        parts = [c for c in np.array_split(moves, min(data_threads(), moves.size)) if c.size] if moves.size else []
        for c, Dc in zip(parts, thread_map(lambda c: X.T @ np.tensordot(dc[:, c].T, terms, axes=1) @ X, parts)):
            D[c] = Dc
        out.append(D)
    return out[0], out[1]


def eigen_derivatives(lam: np.ndarray, A: np.ndarray, B: np.ndarray, rigid_hz: float):
    """(D (n, m, m), G (n, m, m)) of the module docstring from A, B (n, m, m) at eigenvalues ``lam``.

    ``D`` holds the first-order change of the eigenvalues, D_jkk = d lambda_jk = A_jkk - lambda_k B_jkk, and,
    inside a degenerate group, the coupling A_jlk - lambda B_jlk the group's divided differences tend to;
    ``G`` the eigenvector coefficients outside the groups and -B_jlk / 2 inside them (the part
    X^T M X = I fixes; the rest of a degenerate pair's G only rotates the pair). Rigid modes (below
    ``rigid_hz``, where the model's FRF term is q / (-w^2) whatever lambda) are one group with D = 0.
    A and B are symmetrized first: their rigid-mode entries are round-off, and only their symmetric
    part cancels in the pairs' sums.
    """
    om, rigid = modal_omegas(lam, rigid_hz)
    gap = lam[None, :] - lam[:, None]  # (l, k): lambda_k - lambda_l
    scale = np.maximum(np.abs(lam)[None, :], np.abs(lam)[:, None]) + (2 * np.pi * rigid_hz) ** 2
    group = (np.abs(gap) <= 1e-9 * scale) | (rigid[:, None] & rigid[None, :])  # diagonal included
    with np.errstate(divide="ignore"):
        inv = np.where(group, 0.0, 1.0 / np.where(group, 1.0, gap))
    in_d = group & ~rigid[:, None] & ~rigid[None, :]
    n = A.shape[0]
    G = np.empty_like(A)
    D = np.zeros_like(A)
    for j in range(n):  # one parameter at a time: (m, m) temporaries stay in cache
        a = A[j] + A[j].T  # 2 x the symmetric part
        b = B[j] + B[j].T if np.any(B[j]) else None
        if b is not None:
            a -= lam[None, :] * b  # 2 (A_lk - lambda_k B_lk)
        a *= 0.5
        np.multiply(a, inv, out=G[j])
        if b is not None:
            G[j][group] = -0.25 * b[group]
        D[j][in_d] = a[in_d]
    return D, G


def damping_factor(zeta: np.ndarray, om: np.ndarray, rigid: np.ndarray) -> np.ndarray:
    """zeta_k / omega_k (0 for rigid modes): dc_k = zeta_k d lambda_k / omega_k (c_k = 2 zeta_k omega_k, zeta held)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(rigid, 0.0, zeta / np.where(rigid, 1.0, om))


def pair_products(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """S (m, n_out n_in): S_k,(o,i) = u_ok v_ki, so that H = (r q) @ S per line."""
    return (u.T[:, :, None] * v[:, None, :]).reshape(u.shape[1], -1)


def derivative_factor(u: np.ndarray, v: np.ndarray, G: np.ndarray, D: np.ndarray, zw: np.ndarray) -> np.ndarray:
    """The real (3m, n n_out n_in) matrix R with dH (lines, n n_out n_in) = L @ R, L from :func:`line_factor`.

    Parameters
    ----------
    u : (n_out, m) C T X;  v : (m, n_in) X^T T^T B
    G, D : (n, m, m) of :func:`eigen_derivatives`
    zw : (m,) :func:`damping_factor`
    """
    n, m = D.shape[:2]
    # stacked matrix products (BLAS per parameter), not einsum: its C loops took 3-4x longer (stop 30)
    UG = np.matmul(u, G).transpose(0, 2, 1)  # (j, k, o): (u G_j)_ok
    GV = np.matmul(G.transpose(0, 2, 1), v)  # (j, k, i): (G_j^T v)_ki
    P = UG[:, :, :, None] * v[None, :, None, :] + u.T[None, :, :, None] * GV[:, :, None, :]  # (j, k, o, i)
    UD = np.matmul(u, D).transpose(0, 2, 1)  # (j, k, o): d lambda_jk u_ok, plus a degenerate group's coupling
    D1 = UD[:, :, :, None] * v[None, :, None, :]
    R = np.concatenate([P.reshape(n, m, -1), -D1.reshape(n, m, -1), -(zw[None, :, None, None] * D1).reshape(n, m, -1)],
                       axis=1)
    return np.ascontiguousarray(R.transpose(1, 0, 2).reshape(3 * m, -1))


def line_factor(w: np.ndarray, lam_c: np.ndarray, c_k: np.ndarray, quantity: str):
    """Per line (w in rad/s): r (f, m), r q (f, m) and L = [r q, r^2 q, i w r^2 q] (f, 3m)."""
    r = 1.0 / (lam_c[None, :] - w[:, None] ** 2 + 1j * w[:, None] * c_k[None, :])
    rq = r * quantity_factor(w, quantity)[:, None]
    r2q = rq * r
    return r, rq, np.concatenate([rq, r2q, (1j * w)[:, None] * r2q], axis=1)


def modal_factors(sur: Surrogate, lam, X, zeta, D, G, outputs=None, inputs=None) -> dict:
    """The line-independent factors at the modes (lam, X) with damping ``zeta`` (m,) for the derivative
    directions (D, G) of :func:`eigen_derivatives` (damping ratios held), on the surrogate's ``outputs`` and
    ``inputs`` (index arrays; default all): om, rigid, zeta, S (:func:`pair_products`), R
    (:func:`derivative_factor`) and the modal sum's lam_c, c_k (0 for rigid modes) for :func:`line_factor`."""
    om, rigid = modal_omegas(lam, sur.rigid_hz)
    u = (sur.outputs if outputs is None else sur.outputs[np.asarray(outputs)]) @ X
    v = X.T @ (sur.inputs if inputs is None else sur.inputs[:, np.asarray(inputs)])
    return dict(om=om, rigid=rigid, zeta=zeta, S=pair_products(u, v),
                R=derivative_factor(u, v, G, D, damping_factor(zeta, om, rigid)),
                lam_c=np.where(rigid, 0.0, om**2), c_k=np.where(rigid, 0.0, 2 * zeta * om))


def derivative_rows(L: np.ndarray, R: np.ndarray, c: np.ndarray, mask, out: np.ndarray | None = None) -> np.ndarray:
    """Real rows (n, 2 n_v) of the derivatives of the residual: [Re(dH c), Im(dH c)] over the compared values.

    ``dH = L @ R`` (lines, n, n_oi); ``c`` (lines, n_oi) complex: d eps / dH with the value weights and the
    1/sqrt(N) of the stacked residual; ``mask`` (lines, n_oi) bool or None; values frequency-major.
    """
    n_f, n_oi = c.shape
    n = R.shape[1] // n_oi
    dre = (np.ascontiguousarray(L.real) @ R).reshape(n_f, n, n_oi)
    dim = (np.ascontiguousarray(L.imag) @ R).reshape(n_f, n, n_oi)
    return complex_rows(dre, dim, c, mask, out)


def complex_rows(dre, dim, c, mask, out=None) -> np.ndarray:
    """[Re((dre + i dim) c), Im(...)] as (n, 2 n_v) rows over the compared values, (dre, dim) (lines, n, n_oi)."""
    n_f, n, n_oi = dre.shape
    n_v = n_f * n_oi if mask is None else int(mask.sum())
    out = np.empty((n, 2 * n_v)) if out is None else out
    cre, cim = c.real[:, None, :], c.imag[:, None, :]
    re = (dre * cre - dim * cim).transpose(1, 0, 2)  # (n, f, o i)
    im = (dre * cim + dim * cre).transpose(1, 0, 2)
    if mask is None:
        out[:, :n_v] = re.reshape(n, n_v)
        out[:, n_v:] = im.reshape(n, n_v)
    else:
        out[:, :n_v] = re[:, mask]
        out[:, n_v:] = im[:, mask]
    return out


class FRFRows:
    """The stacked residual rows of log deviations of a surrogate against data sets, by line slices.

    The residual of :class:`calibration.Objective` and of the raw-line
    objective is ``[Re eps; Im eps] / sqrt(N)`` (each data set's values,
    frequency-major, weighted); its rows for one data set are built here on
    slices of its lines, side by side on :func:`data_threads` threads, with
    the derivative rows of :func:`derivative_rows` above the residual row.

    Parameters
    ----------
    sur : Surrogate
    data : sequence of FitData
    outputs, inputs : per data set, index arrays into the surrogate's outputs and inputs
    sqrt_w : (N,) value weights of all data sets or None
    quantity : str
    """

    def __init__(self, sur: Surrogate, data, outputs, inputs, sqrt_w, quantity: str):
        self.sur, self.data, self.quantity = sur, list(data), quantity
        self.outputs, self.inputs, self.sqrt_w = list(outputs), list(inputs), sqrt_w
        self.n_values = sum(d.n_values for d in self.data)
        offs = np.cumsum([0] + [d.n_values for d in self.data])
        self.value_slices = [slice(int(a), int(b)) for a, b in zip(offs[:-1], offs[1:])]
        # per data set, the number of compared values before each line (masked lines hold fewer)
        self.line_offsets = [np.concatenate([[0], np.cumsum(
            np.full(d.frf.shape[0], d.frf.shape[1] * d.frf.shape[2]) if d.mask is None else
            d.mask.reshape(d.frf.shape[0], -1).sum(axis=1))]) for d in self.data]

    def line_chunks(self, a: int) -> list:
        """Line slices of data set ``a`` holding about :data:`CHUNK_VALUES` values each (together at least
        as many slices as threads)."""
        off = self.line_offsets[a]
        n_f = off.size - 1
        k = min(max(int(np.ceil(off[-1] / CHUNK_VALUES)), -(-data_threads() // len(self.data)), 1), max(n_f, 1))
        edges = np.searchsorted(off, np.linspace(0, off[-1], k + 1)[1:-1])
        edges = np.unique(np.concatenate([[0], edges, [n_f]]))
        return [slice(int(i), int(j)) for i, j in zip(edges[:-1], edges[1:]) if j > i]

    def factors(self, a: int, lam, X, zeta, D, G) -> dict:
        """Data set ``a``'s :func:`modal_factors`."""
        return modal_factors(self.sur, lam, X, zeta, D, G, self.outputs[a], self.inputs[a])

    def rows(self, a: int, f: dict, lines: slice, extra_rows: int = 0, extra=None) -> np.ndarray:
        """Rows of data set ``a`` on ``lines``: (n + extra_rows + 1, 2 n_v); the n derivative rows of ``f["R"]``,
        then ``extra_rows`` rows filled by ``extra(r, rq, w, c, mask, out)`` (e.g. damping unknowns), then the
        residual row. Columns: the real parts of the slice's values, then their imaginary parts."""
        d = self.data[a]
        w = 2 * np.pi * d.freq_hz[lines]
        n_f = w.size
        r, rq, L = line_factor(w, f["lam_c"], f["c_k"], self.quantity)
        S = f["S"]
        n_oi = S.shape[1]
        H = rq @ S  # (f, o i)
        mask = None if d.mask is None else d.mask[lines].reshape(n_f, n_oi)
        s = 1.0 / np.sqrt(self.n_values)
        c = s / (H * LN10)  # d eps / dH, the 1/sqrt(N) of the stacked residual folded in
        e = log_deviation(H, d.frf[lines].reshape(n_f, n_oi))
        if self.sqrt_w is not None:
            off = self.line_offsets[a]
            vals = self.sqrt_w[self.value_slices[a]][off[lines.start]:off[lines.stop]]
            if mask is None:
                sw = vals.reshape(n_f, n_oi)
            else:
                sw = np.zeros((n_f, n_oi))
                sw[mask] = vals
            c, e = c * sw, e * sw
        n = f["R"].shape[1] // n_oi
        n_v = n_f * n_oi if mask is None else int(mask.sum())
        out = np.empty((n + extra_rows + 1, 2 * n_v))
        derivative_rows(L, f["R"], c, mask, out[:n])
        if extra_rows:
            extra(r, rq, w, c, mask, out[n:n + extra_rows])
        e = e.ravel() if mask is None else e[mask]
        out[-1, :n_v], out[-1, n_v:] = e.real * s, e.imag * s
        return out

    def _per_slice(self, fn) -> list:
        """Per data set, the list of ``fn(a, lines)`` over its line slices, run on the data threads."""
        tasks = [(a, sl) for a in range(len(self.data)) for sl in self.line_chunks(a)]
        parts = thread_map(lambda t: fn(*t), tasks)
        return [[r for (b, _), r in zip(tasks, parts) if b == a] for a in range(len(self.data))]

    def all_rows(self, build) -> list:
        """Per data set, ``build(a, lines)`` over its line slices (threads), joined: Re parts, then Im parts."""
        out = []
        for mine in self._per_slice(build):
            halves = [r.shape[1] // 2 for r in mine]
            out.append(np.concatenate([r[:, :h] for r, h in zip(mine, halves)]
                                      + [r[:, h:] for r, h in zip(mine, halves)], axis=1))
        return out

    def compressed(self, build) -> list:
        """Per data set the triangle R (k+1, k+1) of the QR factorization of its rows' transpose
        ``[J_a f_a]`` (R^T R = [J_a f_a]^T [J_a f_a]; the rows themselves if fewer): each line slice's rows
        built and factorized on its thread, the slices' triangles factorized together (TSQR)."""

        def leaf(a, lines):
            rows = build(a, lines)
            return np.linalg.qr(rows.T, mode="r") if rows.shape[1] > rows.shape[0] else rows.T

        out = []
        for mine in self._per_slice(leaf):
            R = np.vstack(mine)
            out.append(np.linalg.qr(R, mode="r") if R.shape[0] > R.shape[1] else R)
        return out

    def assembled(self, per_set, columns, n_unknowns: int):
        """(r, J) of the whole problem from per-set rows (k_a + 1, 2 N_a) placed in their ``columns``."""
        n = self.n_values
        res, J = np.empty(2 * n), np.zeros((2 * n, n_unknowns))
        for a, (rows, sl) in enumerate(zip(per_set, self.value_slices)):
            n_v = sl.stop - sl.start
            for part, at in ((slice(0, n_v), sl), (slice(n_v, 2 * n_v), slice(n + sl.start, n + sl.stop))):
                res[at] = rows[-1, part]
                J[at, columns[a]] = rows[:-1, part].T
        return res, J


def surrogate_frf_jacobian(
    sur: Surrogate,
    p,
    freq_hz,
    zeta0: float = 0.01,
    quantity: str = "accelerance",
    outputs=None,
    modes=None,
) -> tuple[np.ndarray, np.ndarray]:
    """FRF and its exact derivative with respect to p (uniform damping zeta0).

    Parameters
    ----------
    modes : (lam, X), optional
        :func:`reduced_modes` at p when the caller has them already (no second eigensolution).

    Returns
    -------
    H : (n_f, n_out, n_in) complex
    dH : (n_p, n_f, n_out, n_in) complex, dH/dp_j

    Notes
    -----
    Nelson's expansion in the reduced modes (this module's kernel):
    per line one row of 3m values times one real (3m, n_p n_out n_in) matrix,
    n_out / m of the cost of the divided-difference form it replaced, and the
    same derivative (checked against central differences in the tests).
    """
    p = np.asarray(p, dtype=float)
    lam, X = reduced_modes(sur, p) if modes is None else modes
    w = 2 * np.pi * np.asarray(freq_hz, dtype=float)
    D, G = eigen_derivatives(lam, *parameter_derivatives(sur, p, X), sur.rigid_hz)
    f = modal_factors(sur, lam, X, np.full(lam.size, zeta0), D, G, outputs)
    _, rq, L = line_factor(w, f["lam_c"], f["c_k"], quantity)
    n_f, n_in = w.size, sur.inputs.shape[1]
    n_out = f["S"].shape[1] // n_in
    H = (rq @ f["S"]).reshape(n_f, n_out, n_in)
    dH = np.ascontiguousarray(L.real) @ f["R"] + 1j * (np.ascontiguousarray(L.imag) @ f["R"])  # (f, j o i)
    dH = dH.reshape(n_f, -1, n_out, n_in).transpose(1, 0, 2, 3)  # (j, f, o, i)
    return H, dH
