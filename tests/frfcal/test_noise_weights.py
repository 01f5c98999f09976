"""Raw-line noise weights (frfcal.campaign.noise_weights / fit_data): 1 / the variance of each log ratio."""

from types import SimpleNamespace

import numpy as np

from frfcal.campaign import fit_data, noise_weights
from frfcal.campaign._stages import REL_ERROR_FLOOR


def _article(H, std_error=None, noise_estimate=None):
    f = np.linspace(10.0, 40.0, H.shape[0])
    return SimpleNamespace(name="A1", freq_hz=f, frf=H, channels=("a", "b"), drives=("F",), std_error=std_error,
                           noise_estimate=noise_estimate, pairs=None)


def test_weights_are_the_inverse_relative_variance_with_a_floor():
    H = np.array([[1.0, 10.0], [0.01, 2.0], [3.0, 0.5]], complex)[:, :, None]
    se = np.full(H.shape, 0.01)
    w = noise_weights(_article(H, se), ["a", "b"])
    rel = 0.01 / np.abs(H)
    np.testing.assert_allclose(w, 1.0 / (rel**2 + REL_ERROR_FLOOR**2))
    # an anti-resonance value (|H| = 0.01, SNR 1) weighs 1e4 x less than a line at |H| = 1
    assert w[1, 0, 0] / w[0, 0, 0] < 2e-4
    # a value 1000x above its noise is not trusted beyond the 0.1 % floor
    assert w[0, 1, 0] <= 1.0 / REL_ERROR_FLOOR**2


def test_unmeasured_values_take_their_pairs_median_and_estimates_stand_in():
    H = np.ones((4, 2, 1), complex)
    se = np.array([[0.01, 0.0], [0.0, 0.0], [0.03, 0.0], [0.01, 0.0]])[:, :, None]
    w = noise_weights(_article(H, se), ["a", "b"])
    assert np.isclose(w[1, 0, 0], 1.0 / (0.01**2 + REL_ERROR_FLOOR**2))  # pair a's median, not 1 / floor^2
    assert np.allclose(w[:, 1, 0], 1.0 / (0.01**2 + REL_ERROR_FLOOR**2))  # pair b: nothing measured: all values'
    # without standard errors the estimate from the lines is used; without either, every value alike
    est = np.full(H.shape, 0.02)
    assert np.allclose(noise_weights(_article(H, None, est), ["b"]), 1.0 / (0.02**2 + REL_ERROR_FLOOR**2))
    assert noise_weights(_article(H), ["a"]) is None


def test_fit_data_carries_the_weights_unless_uniform():
    H = (1.0 + np.arange(6.0)).reshape(3, 2, 1).astype(complex)
    art = _article(H, np.full(H.shape, 0.05))
    d = fit_data(art, ["b", "a"])
    assert d.outputs == ("b", "a") and d.weights.shape == (3, 2, 1)
    np.testing.assert_allclose(d.weights[:, 0], noise_weights(art, ["b"])[:, 0])
    assert fit_data(art, ["a"], "uniform").weights is None
