"""Thinning raw lines to a stage's half-bandwidth grid (calibration.thinned_lines)."""

from __future__ import annotations

import numpy as np
import pytest

from calibration import CalibrationError, FitData, half_bandwidth_frequencies, log_frequency_weights, thinned_lines


def _raw(n=2000, seed=0):
    """Uneven lines: a uniform grid plus a dense cluster at a resonance; one output, one input."""
    rng = np.random.default_rng(seed)
    f = np.sort(np.concatenate([np.linspace(100, 400, n // 2), 230 + rng.uniform(-3, 3, n // 2)]))
    H = (1.0 / (230.0**2 - f**2 + 2j * 0.005 * 230.0 * f))[:, None, None]
    mask = np.ones(H.shape, bool)
    mask[::7] = False
    return FitData(f, H, ("a",), ("F",), mask=mask, article="A1", weights=log_frequency_weights(f))


def test_thinned_to_a_wide_stage_grid_keeps_measured_lines_and_the_log_f_quadrature():
    d = _raw()
    g = half_bandwidth_frequencies(100, 400, 0.08, 3.0)
    t = thinned_lines(d, g)
    # about one line per grid point (never more), each a measured line with its own value and mask
    assert g.size - 2 <= t.freq_hz.size <= g.size < d.freq_hz.size / 20
    idx = np.searchsorted(d.freq_hz, t.freq_hz)
    np.testing.assert_array_equal(d.freq_hz[idx], t.freq_hz)
    np.testing.assert_array_equal(d.frf[idx], t.frf)
    np.testing.assert_array_equal(d.mask[idx], t.mask)
    # each kept line is the nearest in log f to its grid point: within half a grid step
    step = np.log(g[1] / g[0])
    near = np.abs(np.log(t.freq_hz)[:, None] - np.log(g)[None, :]).min(axis=1)
    assert near.max() <= 0.5 * step + 1e-12
    # the weights are the subset's log-f shares (mean 1): a weighted mean over the kept lines estimates the same
    # log-f average of a smooth function as over all lines
    assert t.weights.mean() == pytest.approx(1.0)
    smooth = np.log(d.freq_hz) ** 2
    full = np.sum(d.weights * smooth) / d.weights.sum()
    kept = np.sum(t.weights * np.log(t.freq_hz) ** 2) / t.weights.sum()
    assert kept == pytest.approx(full, rel=2e-3)
    # the dense cluster at the resonance no longer dominates the count
    assert np.sum(np.abs(t.freq_hz - 230) < 3) <= 3


def test_the_lines_own_grid_keeps_them_all_and_bad_grids_are_refused():
    d = _raw(200)
    assert thinned_lines(d, d.freq_hz) is d  # every line is the nearest to itself
    with pytest.raises(CalibrationError, match="grid_hz"):
        thinned_lines(d, [])
    with pytest.raises(CalibrationError, match="grid_hz"):
        thinned_lines(d, [100.0, -1.0])
