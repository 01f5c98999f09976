"""Identified damping mapped onto FE modes by MAC pairing (paper Sec. 2.3.5).

The FE modes of a surrogate at p are paired with the identified modes by MAC
at the measured channels (one-to-one, greedy on the largest MAC, pairs below
``mac_min`` or further apart than ``MAX_FREQ_RATIO`` in frequency dropped); a
paired FE mode takes the identified modal damping.
Used by the hold-out validation and by the raw-line refinement.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration._errors import CalibrationError
from calibration._surrogate import Surrogate, reduced_modes
from labdata import mac


#: Largest frequency ratio of a mode pair (either way): with a few sensors a MAC of 0.7-0.8 between a 21.6 Hz
#: test mode and a 148 Hz model mode happens (outside case 2, 9 channels; at 1.3 a 117 Hz test mode still
#: paired with the 148 Hz one at MAC 0.71); such a pair is no pair. A calibrated model's modes are within a few
#: percent; the parameters' usual bounds (+-30 %) move a frequency by at most ~15 %.
MAX_FREQ_RATIO = 1.2


def pair_modes(mac_matrix: np.ndarray, mac_min: float = 0.6, freq_a=None, freq_b=None,
               max_ratio: float = MAX_FREQ_RATIO) -> list[tuple[int, int, float]]:
    """One-to-one pairs (i_a, i_b, mac) picked greedily by the largest MAC above ``mac_min``.

    With the frequencies of both sets (``freq_a`` (n_a,), ``freq_b`` (n_b,), Hz), only modes within a
    factor ``max_ratio`` of each other may pair.
    """
    M = np.array(mac_matrix, dtype=float, copy=True)
    if freq_a is not None and freq_b is not None:
        fa = np.asarray(freq_a, float)[:, None]
        fb = np.asarray(freq_b, float)[None, :]
        with np.errstate(divide="ignore", invalid="ignore"):
            far = ~(np.abs(np.log(fa / fb)) <= np.log(max_ratio))
        M[far] = -1.0
    pairs = []
    while M.size and np.nanmax(M) >= mac_min:
        i, j = np.unravel_index(np.nanargmax(M), M.shape)
        pairs.append((int(i), int(j), float(M[i, j])))
        M[i, :] = -1.0
        M[:, j] = -1.0
    return sorted(pairs)


@dataclass(frozen=True)
class IdentifiedModes:
    """Modal parameters from identification, at named output channels.

    frequency_hz : (m,) ; damping : (m,) ratios ; shapes : (n_ch, m) complex ; channels : tuple of str
    """

    frequency_hz: np.ndarray
    damping: np.ndarray
    shapes: np.ndarray
    channels: tuple

    def __post_init__(self) -> None:
        f = np.asarray(self.frequency_hz, float)
        z = np.asarray(self.damping, float)
        s = np.asarray(self.shapes)
        if s.ndim != 2 or s.shape != (len(self.channels), f.size) or z.shape != f.shape:
            raise CalibrationError(
                f"identified modes: shapes {s.shape} must be ({len(self.channels)} channels, {f.size} modes)"
            )
        object.__setattr__(self, "frequency_hz", f)
        object.__setattr__(self, "damping", z)
        object.__setattr__(self, "shapes", s)
        object.__setattr__(self, "channels", tuple(self.channels))


def median_damping(modes: IdentifiedModes, default: float) -> float:
    """The damping an FE mode without an identified partner takes: the median identified damping
    (``default`` when nothing was identified)."""
    return float(np.median(modes.damping)) if len(modes.damping) else float(default)


def mapped_damping(
    sur: Surrogate, p, modes: IdentifiedModes, zeta0: float = 0.01, mac_min: float = 0.6, band_hz=None
):
    """Per-reduced-mode damping at p: identified damping on MAC-paired modes, zeta0 elsewhere.

    Returns
    -------
    zeta : (r,) damping ratio per reduced mode (ascending frequency)
    pairs : list of dict (fe_hz, test_hz, mac, zeta)
    mac_matrix : (m_fe, m_test) MAC of the FE modes in the band (or all elastic) vs identified modes
    fe_hz : (m_fe,) frequencies of those FE modes
    """
    lam, X = reduced_modes(sur, p)
    fe_hz = np.sqrt(np.clip(lam, 0, None)) / (2 * np.pi)
    elastic = fe_hz > sur.rigid_hz
    if band_hz is not None:
        lo, hi = band_hz
        elastic &= (fe_hz >= 0.7 * lo) & (fe_hz <= 1.3 * hi)
    idx = np.flatnonzero(elastic)
    rows = sur.output_index(modes.channels)
    phi_fe = sur.outputs[rows] @ X[:, idx]
    M = mac(phi_fe, modes.shapes)
    zeta = np.full(lam.size, float(zeta0))
    pairs = []
    for i, j, v in pair_modes(M, mac_min, fe_hz[idx], modes.frequency_hz):
        zeta[idx[i]] = modes.damping[j]
        pairs.append({"fe_hz": float(fe_hz[idx[i]]), "test_hz": float(modes.frequency_hz[j]), "mac": v,
                      "zeta": float(modes.damping[j])})
    return zeta, pairs, M, fe_hz[idx]
