"""Pairs without signal (an uncoupled response/drive pair of a MIMO test) are found, with or without std errors."""

import numpy as np

from calibration._signal import signal_pairs


def _mimo(rng, n_f=600, noise=0.01):
    """Two decoupled 2-mode systems: outputs 0-1 respond to drive 0 only, outputs 2-3 to drive 1 only."""
    f = np.sort(np.concatenate([np.geomspace(20, 400, n_f), 101 + np.linspace(-1, 1, 40)]))
    w = 2 * np.pi * f
    H = np.zeros((f.size, 4, 2), complex)
    for (o, i), (fn, z) in {(0, 0): (101, 0.001), (1, 0): (101, 0.001), (2, 1): (233, 0.002),
                            (3, 1): (233, 0.002)}.items():
        wn = 2 * np.pi * fn
        H[:, o, i] = -w**2 / (wn**2 - w**2 + 2j * z * wn * w) * (1 + 0.3 * o)
    level = np.median(np.abs(H), axis=0).max()
    sigma = noise * np.abs(H) + 1e-3 * level
    Hn = H + sigma * (rng.standard_normal(H.shape) + 1j * rng.standard_normal(H.shape)) / np.sqrt(2)
    return f, Hn, sigma


def test_uncoupled_pairs_found_from_standard_errors_and_from_roughness():
    expected = np.array([[1, 0], [1, 0], [0, 1], [0, 1]], bool)
    for seed in range(5):
        f, H, sigma = _mimo(np.random.default_rng(seed))
        with_se = signal_pairs(f, H, sigma)
        assert with_se.method == "snr"
        np.testing.assert_array_equal(with_se.usable, expected)
        rough = signal_pairs(f[::-1], H[::-1])  # line order does not matter
        assert rough.method == "roughness"
        np.testing.assert_array_equal(rough.usable, expected)
        assert rough.statistic[expected].max() < 0.01 < 0.3 < rough.statistic[~expected].min()
        text = rough.describe(["a", "b", "c", "d"], ["F1", "F2"])
        assert len(text) == 4 and text[0].startswith("a / F2: no signal above noise")


def test_noisy_but_coupled_pairs_are_kept():
    f, H, sigma = _mimo(np.random.default_rng(9), noise=0.05)  # 5 % noise: still a signal
    assert signal_pairs(f, H).usable[[0, 1, 2, 3], [0, 0, 1, 1]].all()
