"""Stabilization diagram: poles across model orders and their consistency."""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from ._errors import IdentificationError
from ._identify import Identification, identification_of_order, data_basis, choose_block_rows, prepare_data, block_modal
from ._poles import Poles, label_poles, mac
from ._subspace import real_modal_form, realize


@dataclass(frozen=True)
class Stabilization:
    """Poles of a sequence of model orders sharing one subspace factorization.

    Attributes
    ----------
    orders : tuple of int
    poles : tuple of Poles, one per order
    shapes : tuple of complex arrays (n_out, n_poles), one per order
        Mode shape (``C x``) of every pole, for MAC checks.
    stable_frequency, stable_damping, stable_shape : tuple of bool arrays
        Per order, per pole: whether the nearest pole of the previous order
        agrees within ``tol_frequency`` (relative), ``tol_damping`` (relative)
        and has MAC >= ``min_mac``. All False at the first order.
    singular_values : ndarray
    band_hz : (lo, hi)
    tolerances : dict
    """

    orders: tuple[int, ...]
    poles: tuple[Poles, ...]
    shapes: tuple[np.ndarray, ...]
    stable_frequency: tuple[np.ndarray, ...]
    stable_damping: tuple[np.ndarray, ...]
    stable_shape: tuple[np.ndarray, ...]
    singular_values: np.ndarray
    band_hz: tuple[float, float]
    tolerances: dict

    def stable(self, index: int) -> np.ndarray:
        """Poles of ``orders[index]`` stable in frequency, damping and shape and labelled physical."""
        return (
            self.stable_frequency[index]
            & self.stable_damping[index]
            & self.stable_shape[index]
            & self.poles[index].physical
        )

    def persistent(self, index: int, n_orders: int = 3) -> np.ndarray:
        """Physical poles of ``orders[index]`` fully stable over the ``n_orders`` orders up to it.

        Follows each pole back through the nearest-frequency chain; this is the
        automatic physical-pole selection of the diagram.
        """
        if index < n_orders - 1:
            raise IdentificationError(f"persistent: need {n_orders} orders up to index {index}")
        keep = self.stable(index).copy()
        f = self.poles[index].frequency_hz
        for i in np.flatnonzero(keep):
            fi = f[i]
            for j in range(index - 1, index - n_orders, -1):
                fj = self.poles[j].frequency_hz
                if fj.size == 0:
                    keep[i] = False
                    break
                k = int(np.argmin(np.abs(fj - fi)))
                ok = self.stable_frequency[j][k] and self.stable_damping[j][k] and self.stable_shape[j][k]
                ok = ok or j == index - n_orders + 1 and abs(fj[k] - fi) <= self.tolerances["frequency"] * fi
                if not ok:
                    keep[i] = False
                    break
                fi = fj[k]
        return keep


def _order_poles(data, basis, sv, n: int, zeta_max: float):
    """(Poles, shapes ``C x`` (n_out, n_poles)) of order ``n`` from the shift invariance alone (no ``B, D``
    fit), labelled without the fit-based test."""
    p = data.H.shape[1]
    Ad, Cd = realize(basis, sv, n, p)
    eye = np.eye(n)
    Pi = np.linalg.inv(Ad + eye)
    A = data.alpha * (Ad - eye) @ Pi
    C = (Cd @ Pi) / data.out_scale[:, None]
    lam, X = np.linalg.eig(A)
    keep = np.flatnonzero(lam.imag >= 0)
    keep = keep[np.argsort(np.abs(lam[keep]))]
    lam, sh = lam[keep], C @ X[:, keep]
    inf = np.full(lam.size, np.inf)
    labs = label_poles(lam, inf, inf, lam.real > 0, data.band_hz, zeta_max, 0.0, 0.0)
    return Poles(lam, labs, np.full(lam.size, np.nan), np.full(lam.size, np.nan)), sh


def stabilization(
    freq_hz,
    H,
    orders,
    *,
    band_hz=None,
    weights=None,
    quantity: str = "accelerance",
    valid=None,
    block_rows: int | None = None,
    enforce_stability: bool = True,
    zeta_max: float = 0.2,
    min_contribution: float = 0.05,
    min_importance: float = 1.0,
    tol_frequency: float = 0.005,
    tol_damping: float = 0.05,
    min_mac: float = 0.95,
    labels: bool = True,
) -> Stabilization:
    """Identify a sequence of orders and check pole consistency across them.

    One McKelvey factorization (with ``block_rows`` sized for the largest
    order) serves every order; each order then gets its own ``B, D``
    least-squares fit and pole labels as in :func:`identify` (no ``C``
    refinement, for speed).

    Parameters
    ----------
    orders : sequence of int
        Increasing state dimensions.
    tol_frequency, tol_damping : float
        Relative change allowed for a pole to count as stable.
    min_mac : float
        MAC with the nearest previous pole for shape stability.
    labels : bool
        True: every order is identified (``B, D`` fit) and labelled as in
        :func:`identify`. False (cheap, for pictures): the poles of each order
        come from the shift invariance alone (no ``B, D`` fit), and the
        fit-based test (``negligible``: contribution, importance) is not made:
        "physical" then means in band, stable and ``0 < zeta <= zeta_max``;
        contribution and importance are NaN. About 3x cheaper.
    Other parameters as in :func:`identify`.
    """
    ords = tuple(int(o) for o in orders)
    if not ords or any(o < 1 for o in ords) or any(b <= a for a, b in zip(ords, ords[1:])):
        raise IdentificationError(f"orders must be increasing positive integers, got {list(orders)!r}")
    data = prepare_data(freq_hz, H, band_hz=band_hz, weights=weights, valid=valid, quantity=quantity)
    q = choose_block_rows(data, ords[-1], block_rows)
    basis, sv = data_basis(data, q)
    poles, shapes, sf, sd, ss = [], [], [], [], []
    prev: Identification | None = None
    prev_shapes = None
    for n in ords:
        if labels:
            ident = identification_of_order(
                data, basis, sv, n, q, enforce_stability, zeta_max, min_contribution, min_importance, refine=0
            )
            Am, Bm, Cm, blocks = real_modal_form(ident.model.A, ident.model.B, ident.model.C)
            sh, _ = block_modal(Am, Bm, Cm, blocks)
            sh = sh if len(blocks) else np.zeros((ident.model.n_out, 0), complex)
        else:
            poles_n, sh = _order_poles(data, basis, sv, n, zeta_max)
            ident = SimpleNamespace(poles=poles_n)
        f = ident.poles.frequency_hz
        z = ident.poles.damping
        npol = f.size
        a = np.zeros(npol, bool)
        b = np.zeros(npol, bool)
        c = np.zeros(npol, bool)
        if prev is not None and len(prev.poles):
            fp = prev.poles.frequency_hz
            zp = prev.poles.damping
            for i in range(npol):
                k = int(np.argmin(np.abs(fp - f[i])))
                a[i] = abs(fp[k] - f[i]) <= tol_frequency * f[i]
                b[i] = abs(zp[k] - z[i]) <= tol_damping * abs(z[i])
                c[i] = mac(sh[:, i], prev_shapes[:, k])[0, 0] >= min_mac
        poles.append(ident.poles)
        shapes.append(sh)
        sf.append(a)
        sd.append(b)
        ss.append(c)
        prev, prev_shapes = ident, sh
    return Stabilization(
        orders=ords,
        poles=tuple(poles),
        shapes=tuple(shapes),
        stable_frequency=tuple(sf),
        stable_damping=tuple(sd),
        stable_shape=tuple(ss),
        singular_values=sv,
        band_hz=data.band_hz,
        tolerances={"frequency": tol_frequency, "damping": tol_damping, "mac": min_mac},
    )
