"""Layout quality metrics: Fisher information, autoMAC and per-mode observability."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from labdata import mac
from pretest._errors import PretestError

__all__ = ["LayoutMetrics", "mac", "automac", "layout_metrics"]


def automac(phi: np.ndarray) -> np.ndarray:
    """AutoMAC of the columns of ``phi`` (shape (n_dof, n_modes)) -> (n_modes, n_modes)."""
    return mac(phi, phi)


@dataclass(frozen=True)
class LayoutMetrics:
    """Quality of a sensor layout for a set of target modes.

    Attributes
    ----------
    n_channels : int
        Rows of the layout (single-axis channels).
    n_modes : int
        Target modes.
    fim_log10_det : float
        ``log10 det(Phi_s^T Phi_s)`` (``-inf`` if singular).  Depends on the
        mode normalization; compare layouts for the same modes only.
    fim_condition : float
        2-norm condition number of the Fisher information ``Phi_s^T Phi_s``
        with each mode scaled to unit norm at the sensors (``inf`` if singular).
    automac : ndarray, shape (n_modes, n_modes)
    automac_max_offdiag : float
        Largest off-diagonal autoMAC value.
    automac_worst_pair : tuple of int
        Mode indices (0-based within the target set) of that value.
    mode_independence : ndarray, shape (n_modes,)
        ``1 / (Q_rr (Q^-1)_rr)`` for the column-normalized FIM Q: sin^2 of the
        angle between mode r and the span of the other modes at the sensors
        (1 = orthogonal to all others, 0 = indistinguishable).
    mode_rms : ndarray, shape (n_modes,)
        RMS amplitude of each mode over the channels (shape units).
    mode_peak_fraction : ndarray, shape (n_modes,)
        Largest channel amplitude of each mode divided by its largest amplitude
        over ``phi_all`` (when given, else over the channels): 1 means a sensor
        sits on that mode's antinode.
    """

    n_channels: int
    n_modes: int
    fim_log10_det: float
    fim_condition: float
    automac: np.ndarray
    automac_max_offdiag: float
    automac_worst_pair: tuple[int, int]
    mode_independence: np.ndarray
    mode_rms: np.ndarray
    mode_peak_fraction: np.ndarray

    def as_dict(self) -> dict:
        """JSON-ready summary (lists and floats; infinities as None)."""

        def num(x):
            x = float(x)
            return x if np.isfinite(x) else None

        return {
            "n_channels": self.n_channels,
            "n_modes": self.n_modes,
            "fim_log10_det": num(self.fim_log10_det),
            "fim_condition": num(self.fim_condition),
            "automac_max_offdiag": num(self.automac_max_offdiag),
            "automac_worst_pair": list(self.automac_worst_pair),
            "mode_independence": [num(v) for v in self.mode_independence],
            "mode_rms": [num(v) for v in self.mode_rms],
            "mode_peak_fraction": [num(v) for v in self.mode_peak_fraction],
        }


def layout_metrics(phi_sensors: np.ndarray, phi_all: np.ndarray | None = None) -> LayoutMetrics:
    """Metrics of a layout from the target modes at its channels.

    Works for any layout (chosen by EfI or by hand), so layouts can be compared.

    Parameters
    ----------
    phi_sensors : array_like, shape (n_channels, n_modes)
        Target mode shapes at the layout's channels (projected on each
        channel's direction).
    phi_all : array_like, shape (n_candidates, n_modes), optional
        The same modes at all candidates, for ``mode_peak_fraction``.

    Returns
    -------
    LayoutMetrics
    """
    p = np.asarray(phi_sensors, dtype=float)
    if p.ndim != 2 or p.shape[0] == 0 or p.shape[1] == 0:
        raise PretestError(f"layout mode shapes must be (n_channels, n_modes), got shape {p.shape}")
    n_ch, n_m = p.shape
    q = p.T @ p
    sign, logdet = np.linalg.slogdet(q)
    log10_det = logdet / np.log(10.0) if sign > 0 else -np.inf
    norms = np.sqrt(np.diag(q))
    if np.any(norms == 0):
        cond = np.inf
        independence = np.where(norms == 0, 0.0, np.nan)
    else:
        qn = q / np.outer(norms, norms)
        s = np.linalg.svd(qn, compute_uv=False)
        cond = float(s[0] / s[-1]) if s[-1] > s[0] * 1e-15 else np.inf
        if np.isfinite(cond):
            independence = 1.0 / np.diag(np.linalg.inv(qn))
        else:
            independence = np.zeros(n_m)
    am = automac(p)
    off = am - np.diag(np.diag(am))
    if n_m > 1:
        i, j = np.unravel_index(int(np.argmax(off)), off.shape)
        worst = (int(min(i, j)), int(max(i, j)))
        max_off = float(off[i, j])
    else:
        worst, max_off = (0, 0), 0.0
    ref = np.abs(np.asarray(phi_all, dtype=float)) if phi_all is not None else np.abs(p)
    peak_ref = ref.max(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        peak = np.where(peak_ref > 0, np.abs(p).max(axis=0) / np.where(peak_ref > 0, peak_ref, 1.0), 0.0)
    return LayoutMetrics(
        n_channels=n_ch,
        n_modes=n_m,
        fim_log10_det=float(log10_det),
        fim_condition=float(cond),
        automac=am,
        automac_max_offdiag=max_off,
        automac_worst_pair=worst,
        mode_independence=np.asarray(independence, dtype=float),
        mode_rms=np.sqrt(np.diag(q) / n_ch),
        mode_peak_fraction=peak,
    )
