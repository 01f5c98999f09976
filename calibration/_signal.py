"""Which response/drive pairs carry a signal above the noise.

A MIMO test of a nearly symmetric structure has pairs that the structure does
not couple: a vertical accelerometer under a lateral drive of a planar frame
measures noise only. In the log-ratio metric (Eq. 2.5) such a pair is a
disaster: the model's tiny cross response against pure noise gives |eps| of
order 1-5 per line, and a handful of such pairs outweigh every other pair by
10^4 and decide the optimum. They carry no information on the parameters, so
the campaign leaves them out of identification weights, calibration and
validation, and says so.

Two estimates, used in this order:

* **Per-line standard errors** (acquisition records them for every line): the
  pair's median signal-to-noise ratio |H|/sigma over the band.
* **Roughness** when the data carry no standard errors (UFF58 has none): the
  median over adjacent lines of |log10(H[k+1]/H[k])|^2. A measured FRF is
  smooth on its line grid (a stepped sine is dense where it changes fast), so
  its median is small (< 0.01 even at 1 % noise); two independent complex
  Gaussian noise samples give |log10 ratio|^2 of about 0.4 in the median.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration._errors import CalibrationError

#: smallest median |H|/sigma over the band of a pair that carries a signal
MIN_SNR = 3.0
#: largest median adjacent-line |log10 ratio|^2 of a pair that carries a signal (no standard errors)
MAX_ROUGHNESS = 0.05


@dataclass(frozen=True)
class SignalPairs:
    """Outcome of :func:`signal_pairs`.

    Attributes
    ----------
    usable : (n_out, n_in) bool
        Pairs that carry a signal.
    statistic : (n_out, n_in) float
        The median SNR (``method == "snr"``) or the median roughness (``"roughness"``).
    method : str
    """

    usable: np.ndarray
    statistic: np.ndarray
    method: str

    def describe(self, outputs, inputs) -> list[str]:
        """One line per pair left out, e.g. ``"s3 / F1: no signal above noise (median SNR 0.8)"``."""
        lines = []
        for o, i in zip(*np.nonzero(~self.usable)):
            what = (f"median SNR {self.statistic[o, i]:.2g}" if self.method == "snr"
                    else f"median adjacent-line |log10 ratio|^2 {self.statistic[o, i]:.2g}, as noise")
            lines.append(f"{outputs[o]} / {inputs[i]}: no signal above noise ({what})")
        return lines


def signal_pairs(freq_hz, H, std_error=None, *, min_snr: float = MIN_SNR,
                 max_roughness: float = MAX_ROUGHNESS) -> SignalPairs:
    """Response/drive pairs of an FRF matrix that carry a signal.

    Parameters
    ----------
    freq_hz : (n_f,) Hz, the lines (any order)
    H : (n_f, n_out, n_in) complex FRF
    std_error : (n_f, n_out, n_in) float, optional
        Per-line standard error of H; used when present and positive somewhere.
    min_snr, max_roughness : float
        Thresholds (see the module docstring).

    Returns
    -------
    SignalPairs
    """
    f = np.asarray(freq_hz, float)
    H = np.asarray(H, complex)
    if H.ndim != 3 or H.shape[0] != f.size:
        raise CalibrationError(f"signal_pairs: H shape {H.shape} does not match {f.size} lines")
    if f.size < 3:
        return SignalPairs(np.ones(H.shape[1:], bool), np.full(H.shape[1:], np.nan), "none")
    if std_error is not None:
        s = np.asarray(std_error, float)
        if s.shape == H.shape and np.all(np.isfinite(s)) and np.any(s > 0):
            with np.errstate(divide="ignore", invalid="ignore"):
                snr = np.where(s > 0, np.abs(H) / s, np.inf)
            med = np.median(snr, axis=0)
            return SignalPairs(med >= min_snr, med, "snr")
    order = np.argsort(f)
    Hs = H[order]
    with np.errstate(divide="ignore", invalid="ignore"):
        step = np.log10(Hs[1:] / Hs[:-1])
    rough = np.abs(step) ** 2
    rough[~np.isfinite(rough)] = np.inf
    med = np.median(rough, axis=0)
    return SignalPairs(med <= max_roughness, med, "roughness")
