"""FRF quantities: their names, the response each one divides by force, and the factor between them.

With the time dependence e^{+i w t} (docs/conventions.md) a response of
displacement x has velocity i w x and acceleration -w^2 x, so::

    receptance  = x / F            (m/N)
    mobility    = i w  x receptance ((m/s)/N)
    accelerance = -w^2 x receptance ((m/s^2)/N)

i.e. H_q(w) = q(w) H_receptance(w) with q = (i w)^k, k = 0, 1, 2.
"""

from __future__ import annotations

import numpy as np

from labdata._errors import LabDataError

__all__ = [
    "FRF_QUANTITIES",
    "RESPONSE_QUANTITY",
    "CHANNEL_UNITS",
    "frf_quantity_of",
    "quantity_power",
    "quantity_factor",
    "check_frf_quantity",
]

#: The FRF quantities, in this order everywhere (the default, accelerance, first).
FRF_QUANTITIES: tuple[str, ...] = ("accelerance", "mobility", "receptance")

#: The response quantity measured for each FRF quantity (the input is always force).
RESPONSE_QUANTITY: dict[str, str] = {
    "accelerance": "acceleration",
    "mobility": "velocity",
    "receptance": "displacement",
}

#: SI unit of every quantity a channel may measure (layout files and acquisition).
CHANNEL_UNITS: dict[str, str] = {
    "acceleration": "m/s^2",
    "velocity": "m/s",
    "displacement": "m",
    "force": "N",
    "voltage": "V",
}

_POWER = {"receptance": 0, "mobility": 1, "accelerance": 2}
_FRF_OF = {v: k for k, v in RESPONSE_QUANTITY.items()}


def check_frf_quantity(quantity: str, where: str = "quantity") -> str:
    """Return ``quantity`` if it is one of :data:`FRF_QUANTITIES`.

    Raises
    ------
    LabDataError
        ``"<where> must be one of (...), got '<quantity>'"``.
    """
    if quantity not in _POWER:
        raise LabDataError(f"{where} must be one of {FRF_QUANTITIES}, got {quantity!r}")
    return quantity


def frf_quantity_of(response_quantity: str) -> str:
    """The FRF quantity of a response over force: ``"acceleration"`` -> ``"accelerance"``, etc.

    Raises
    ------
    LabDataError
        For a quantity that is not a motion (force, voltage, anything else).
    """
    try:
        return _FRF_OF[response_quantity]
    except (KeyError, TypeError):
        raise LabDataError(
            f"response quantity must be one of {tuple(_FRF_OF)}, got {response_quantity!r}"
        ) from None


def quantity_power(quantity: str) -> int:
    """k in q = (i w)^k: 0 for receptance, 1 for mobility, 2 for accelerance."""
    return _POWER[check_frf_quantity(quantity)]


def quantity_factor(quantity: str, omega) -> np.ndarray:
    """The factor q(w) with H_quantity = q(w) H_receptance.

    Parameters
    ----------
    quantity : {"accelerance", "mobility", "receptance"}
    omega : array_like
        Circular frequency, rad/s, any shape.

    Returns
    -------
    ndarray, complex, shape of ``omega``
        ``-w^2`` (accelerance), ``i w`` (mobility) or ``1`` (receptance), exact
        (no complex power is taken).
    """
    k = quantity_power(quantity)
    w = np.asarray(omega, dtype=float)
    if k == 0:
        return np.ones_like(w) + 0j
    if k == 1:
        return 1j * w
    return -(w**2) + 0j
