"""The Modal Assurance Criterion, with its edge cases decided once."""

from __future__ import annotations

import numpy as np

from labdata._errors import LabDataError

__all__ = ["mac"]


def _columns(x, name: str) -> np.ndarray:
    a = np.asarray(x)
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2:
        raise LabDataError(f"MAC: {name} must be (n_dof,) or (n_dof, n_modes), got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.number):
        raise LabDataError(f"MAC: {name} must be numeric, got dtype {a.dtype}")
    return a


def mac(phi_a, phi_b) -> np.ndarray:
    """Modal Assurance Criterion between the columns of two shape matrices.

    ``MAC_ij = |a_i^H b_j|^2 / ((a_i^H a_i)(b_j^H b_j))`` (Allemang & Brown 1982).

    Parameters
    ----------
    phi_a : array_like, shape (n_dof, n_a) or (n_dof,)
    phi_b : array_like, shape (n_dof, n_b) or (n_dof,)
        Real or complex shapes at the same DOF, in any units and scaling; a
        1-D array is one shape (one column).

    Returns
    -------
    ndarray, float, shape (n_a, n_b)
        Values in [0, 1] (rounding above 1 is clipped). Always 2-D, also for
        1-D inputs. Invariant to any complex scaling of either column.

    Notes
    -----
    Edge cases, the same for every layer:

    * a zero column (or one with a non-finite entry) has no direction: its MAC
      with anything is 0, never NaN, so pairing never picks it;
    * ``n_a = 0`` or ``n_b = 0`` gives an empty ``(n_a, n_b)`` array;
    * row counts that differ, or arrays of more than two dimensions, raise.

    Raises
    ------
    LabDataError
        Naming both shapes.
    """
    a = _columns(phi_a, "phi_a")
    b = _columns(phi_b, "phi_b")
    if a.shape[0] != b.shape[0]:
        raise LabDataError(
            f"MAC needs shapes at the same DOF: phi_a has shape {a.shape}, phi_b {b.shape} "
            f"({a.shape[0]} and {b.shape[0]} rows)"
        )
    cross = np.abs(a.conj().T @ b) ** 2
    na = np.sum(np.abs(a) ** 2, axis=0)
    nb = np.sum(np.abs(b) ** 2, axis=0)
    denom = np.outer(na, nb)
    ok = np.isfinite(denom) & (denom > 0) & np.isfinite(cross)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        out = np.where(ok, cross / np.where(ok, denom, 1.0), 0.0)
    return np.minimum(out.astype(float, copy=False), 1.0)
