"""Where the identified model leaves far more than the noise (``frfcal identify``, the campaign's identify
stage, ``settings["unexplained"]``): a weakly excited mode the identification missed is pointed at, and a
model that explains the data is quiet."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "identification"))
from synthetic import ring  # noqa: E402

from frfcal.campaign._identify import identify_lines, unexplained_line  # noqa: E402

BAND = (100.0, 550.0)
F_WEAK = 300.0


def _with_weak_mode(seed, amplitude):
    """The ring's FRFs (8 modes in the band) plus one mode at 300 Hz (zeta 0.1 %) seen by one output only, its
    peak ``amplitude`` x that output's RMS: as a lightly excited local mode of a real structure."""
    t = ring(n_mass=8, inputs=(0,), seed=seed)
    w, wn = 2 * np.pi * t.freq_hz, 2 * np.pi * F_WEAK
    g = -w**2 / (wn**2 - w**2 + 2j * 1e-3 * wn * w)
    H = t.H.copy()
    H[:, 3, 0] += amplitude * np.sqrt(np.mean(np.abs(t.H_clean[:, 3, 0]) ** 2)) * g / np.abs(g).max()
    return t, identify_lines(t.freq_hz, H, np.ones(t.freq_hz.size, bool), t.sigma, "accelerance", BAND)


@pytest.mark.parametrize("seed", [0, 2])
def test_a_weak_mode_the_identification_missed_is_pointed_at(seed):
    t, r = _with_weak_mode(seed, 0.02)
    assert np.min(np.abs(r.modal.frequency_hz - F_WEAK)) > 1.0, r.modal.frequency_hz  # missed (the finding)
    assert r.modal.n_modes == 8  # the ring's own modes all found
    (u,) = r.settings["unexplained"]  # one window, at the missed mode, nothing elsewhere
    assert u["window_hz"][0] <= F_WEAK <= u["window_hz"][1] and abs(u["frequency_hz"] - F_WEAK) < 1.0
    assert u["residual_sigma"] > 10 and u["lines"] >= 2
    assert "300.0 Hz" in unexplained_line(r) or "299.9 Hz" in unexplained_line(r)


def test_a_model_that_explains_the_data_is_quiet():
    t, r = _with_weak_mode(0, 0.1)  # strong enough to be identified
    assert np.min(np.abs(r.modal.frequency_hz - F_WEAK)) < 0.5
    assert r.settings["unexplained"] == [] and unexplained_line(r) is None


def test_no_reading_in_sigma_without_noise_weights():
    t = ring(n_mass=8, inputs=(0,), seed=0)
    r = identify_lines(t.freq_hz, t.H, np.ones(t.freq_hz.size, bool), None, "accelerance", BAND, weights=None)
    assert "unexplained" not in r.settings and unexplained_line(r) is None
