"""Damping equalization (paper Eq. 2.7-2.13)."""

from __future__ import annotations

import numpy as np

from ._errors import IdentificationError
from ._statespace import StateSpace
from ._subspace import real_modal_form


def _block_eigenvalues(Am: np.ndarray, blocks) -> np.ndarray:
    lam = np.empty(len(blocks), dtype=complex)
    for i, b in enumerate(blocks):
        if b.stop - b.start == 1:
            lam[i] = Am[b.start, b.start]
        else:
            lam[i] = complex(Am[b.start, b.start], Am[b.start, b.start + 1])
    return lam


def _match(lam: np.ndarray, targets: np.ndarray, what: str) -> np.ndarray:
    mask = np.zeros(lam.size, dtype=bool)
    for t in np.asarray(targets, dtype=complex).reshape(-1):
        t = complex(t.real, abs(t.imag))
        d = np.abs(lam - t)
        i = int(np.argmin(d))
        if d[i] > 1e-6 * max(abs(t), 1.0):
            raise IdentificationError(f"equalized: {what} pole {t} is not a pole of the model")
        mask[i] = True
    return mask


def equalized(model_or_identification, zeta0: float, physical=None, *, definition: str = "modal") -> StateSpace:
    """Model with every physical pole set to damping ratio ``zeta0`` (paper Eq. 2.11-2.13).

    The model is brought to real modal form (the real counterpart of the
    diagonal realization of Eq. 2.8-2.9); in each physical 2x2 block the
    damped frequency ``Im(lambda)`` is kept and the real part is reset.
    ``B``, ``C`` (in modal coordinates, Eq. 2.12) and ``D`` are unchanged.
    Real poles and poles not selected (residual, spurious) are left alone:
    equalizing a real pole would turn it into an integrator.

    Parameters
    ----------
    model_or_identification : StateSpace or Identification
    zeta0 : float
        Common damping ratio, 0 <= zeta0 < 1.
    physical : optional
        Which poles to equalize: ``None`` uses the labels of an
        ``Identification`` (``"physical"``), and for a bare ``StateSpace``
        every stable complex pole; a boolean mask over the model's poles (one
        entry per real pole or conjugate pair, sorted as ``Identification.poles``);
        or an array of the complex eigenvalues [rad/s] to equalize.
    definition : {"modal", "paper"}
        ``"modal"``: the new pole has ``-Re/|lambda| = zeta0`` exactly, i.e.
        ``lambda = omega_d (-zeta0/sqrt(1-zeta0^2) + i)``. ``"paper"``: Eq. 2.11
        literally, ``lambda = omega_d (-zeta0 + i)``, which has
        ``-Re/|Im| = zeta0`` (Eq. 2.10); the two differ by O(zeta0^2).

    Returns
    -------
    StateSpace
        Real model in modal form, same quantity.
    """
    model = getattr(model_or_identification, "model", model_or_identification)
    if not isinstance(model, StateSpace):
        raise IdentificationError(
            f"equalized needs a StateSpace or an Identification, got {type(model_or_identification).__name__}"
        )
    z0 = float(zeta0)
    if not (0.0 <= z0 < 1.0):
        raise IdentificationError(f"equalized: zeta0 must be in [0, 1), got {zeta0!r}")
    if definition not in ("modal", "paper"):
        raise IdentificationError(f"equalized: definition must be 'modal' or 'paper', got {definition!r}")
    Am, Bm, Cm, blocks = real_modal_form(model.A, model.B, model.C)
    lam = _block_eigenvalues(Am, blocks)
    if physical is None:
        poles = getattr(model_or_identification, "poles", None)
        if poles is not None:
            mask = _match(lam, poles.eigenvalues[poles.physical], "physical")
        else:
            mask = (lam.imag > 0) & (lam.real <= 0)
    else:
        sel = np.asarray(physical)
        if sel.dtype == bool:
            if sel.shape != lam.shape:
                raise IdentificationError(
                    f"equalized: physical mask has {sel.size} entries, model has {lam.size} poles (pairs)"
                )
            mask = sel.copy()
        else:
            mask = _match(lam, sel, "requested")
    for i, b in enumerate(blocks):
        if not mask[i]:
            continue
        if b.stop - b.start != 2:
            raise IdentificationError(f"equalized: pole {lam[i]} is real and cannot be equalized")
        wd = Am[b.start, b.start + 1]
        sigma = -wd * (z0 / np.sqrt(1.0 - z0 * z0) if definition == "modal" else z0)
        Am[b.start, b.start] = sigma
        Am[b.start + 1, b.start + 1] = sigma
    return StateSpace(Am, Bm, Cm, model.D, model.quantity)
