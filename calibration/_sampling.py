"""Frequency sampling with a fixed number of samples per half-power bandwidth (paper Eq. 2.5-2.6).

A resonance at f_i with modal damping zeta0 has the half-power bandwidth
2 zeta0 f_i. Steps that grow linearly with frequency, f_{k+1} = f_k (1 + 2 zeta0 / n),
put ``n`` samples into every half-bandwidth, so every mode contributes about
equally to the square deviation.
"""

from __future__ import annotations

import numpy as np

from calibration._errors import CalibrationError


def half_bandwidth_frequencies(
    low_hz: float, high_hz: float, zeta0: float = 0.01, samples_per_half_bandwidth: float = 3.0
) -> np.ndarray:
    """Geometric frequency grid with ``samples_per_half_bandwidth`` samples per 2*zeta0*f.

    Parameters
    ----------
    low_hz, high_hz : float
        Band edges in Hz, ``0 < low_hz < high_hz``. Both edges are included.
    zeta0 : float
        Equalized modal damping ratio (fraction, 0.01 = 1 %).
    samples_per_half_bandwidth : float
        Number of samples inside each half-power bandwidth.

    Returns
    -------
    (n_f,) ndarray
        Frequencies in Hz, increasing, ``f[k+1]/f[k]`` constant.
    """
    if not (np.isfinite(low_hz) and np.isfinite(high_hz)) or low_hz <= 0 or high_hz <= low_hz:
        raise CalibrationError(f"band_hz: need 0 < low < high, got [{low_hz}, {high_hz}]")
    if not 0 < zeta0 < 1:
        raise CalibrationError(f"zeta0: damping ratio must be in (0, 1), got {zeta0}")
    if samples_per_half_bandwidth <= 0:
        raise CalibrationError(
            f"samples_per_half_bandwidth: must be positive, got {samples_per_half_bandwidth}"
        )
    ratio = 1.0 + 2.0 * zeta0 / samples_per_half_bandwidth
    n = int(np.ceil(np.log(high_hz / low_hz) / np.log(ratio))) + 1
    return np.geomspace(low_hz, high_hz, max(n, 2))
