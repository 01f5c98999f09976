"""Nonlinearity checks: level dependence, harmonic distortion, sweep direction.

Manufactured truth (a linear modal system at two levels, the same system with a
level-dependent damping or an equivalent-linear stiffening, a Duffing oscillator
swept up and down by harmonic balance) and the real bolted Brake-Reuss beam
(../shared/reference/measured/brb-stepped-sine, skipped when absent).
"""

from __future__ import annotations

import numpy as np
import pytest

from calibration import (
    CalibrationError,
    FRFLevel,
    distortion,
    level_dependence,
    nonlinearity,
    sweep_direction,
)
from tests.conftest import reference_path

F_HZ = np.array([50.0, 120.0, 210.0])
ZETA = np.array([0.001, 0.002, 0.003])
PHI = np.array([[1.0, 0.8], [0.7, -1.1], [-0.9, 0.5]])  # (mode, output): 2 outputs, drive on output 0


def _lines(f_hz=F_HZ, zeta=ZETA, n=41, span=12.0):
    """Stepped-sine lines: n per mode over f_r (1 +- span zeta)."""
    bands = [np.linspace(f * (1 - span * z), f * (1 + span * z), n) for f, z in zip(f_hz, zeta)]
    return np.unique(np.concatenate(bands))


def _accelerance(f, f_hz=F_HZ, zeta=ZETA):
    """(n_f, 2, 1) accelerance of a 3-mode system, unit modal masses."""
    w = 2 * np.pi * f
    H = np.zeros((f.size, 2, 1), complex)
    for r, (fr, z) in enumerate(zip(f_hz, zeta)):
        wr = 2 * np.pi * fr
        H[:, :, 0] += np.outer(1.0 / (wr**2 - w**2 + 2j * z * wr * w), PHI[r] * PHI[r, 0])
    return -(w**2)[:, None, None] * H


def _noisy(H, rel, rng):
    """Complex noise with E|e|^2 = (rel |H|)^2 and the matching standard errors."""
    s = rel * np.abs(H)
    e = s * (rng.standard_normal(H.shape) + 1j * rng.standard_normal(H.shape)) / np.sqrt(2)
    return H + e, s


def _level(f, H, level, rng, rel=0.01, label=""):
    Hn, s = _noisy(H, rel, rng)
    return FRFLevel(f, Hn, level, std_error=s, quantity="accelerance", label=label)


# ------------------------------------------------------------ linear: no alarm
def test_linear_two_levels_not_flagged_over_seeds():
    """Same FRF, independent 1 % noise, levels 1 and 4 N: no mode and no model-free pair flagged."""
    f = _lines()
    H = _accelerance(f)
    zs, n_flag = [], 0
    for seed in range(12):
        rng = np.random.default_rng(seed)
        r = level_dependence([_level(f, H, 1.0, rng), _level(f, H, 4.0, rng)])
        assert len(r.modes_hz) == 3  # found the three resonances
        np.testing.assert_allclose(r.modes_hz, F_HZ, rtol=1e-4)
        np.testing.assert_allclose([fit.damping for fit in r.fits[0]], ZETA, rtol=0.1)
        n_flag += r.flagged
        zs += [c.z for c in r.changes]
        assert all(np.isfinite(p.z) for p in r.pairs)
        v = nonlinearity(level=r)
        assert v.verdict == ("nonlinear" if r.flagged else "linear")
    assert n_flag == 0
    zs = np.asarray(zs)
    # the per-mode z are close to standard normal: the uncertainties are honest, not inflated
    assert np.max(np.abs(zs)) < 4.5
    assert 0.6 < np.std(zs) < 1.4, np.std(zs)


def test_linear_verdict_words_and_dict():
    rng = np.random.default_rng(1)
    f = _lines()
    H = _accelerance(f)
    r = level_dependence([_level(f, H, 4.0, rng, label="hi"), _level(f, H, 1.0, rng, label="lo")])
    assert r.levels == (1.0, 4.0) and r.labels == ("lo", "hi")  # sorted by level
    v = nonlinearity(level=r)
    assert not v.flagged and v.verdict == "linear" and v.linear_effects_admissible and v.modes == ()
    assert "no level dependence beyond noise" in r.evidence[0]
    d = v.to_dict()
    assert d["verdict"] == "linear" and len(d["level"]["changes"]) == 6
    assert len(d["level"]["fits"]) == 2 and d["level"]["fits"][0][1]["frequency_hz"] == pytest.approx(120, rel=1e-4)


# -------------------------------------------------------------- nonlinear: flag
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cubic_stiffening_flags_the_right_mode(seed):
    """Mode 2 stiffens by 0.5 % (equivalent linear) at the high level: mode 2 frequency, nothing else."""
    rng = np.random.default_rng(seed)
    f = _lines()
    lo = _level(f, _accelerance(f), 0.5, rng)
    hi = _level(f, _accelerance(f, F_HZ * [1, 1.005, 1]), 2.0, rng)
    r = level_dependence([lo, hi])
    assert r.flagged
    flagged = {(c.mode, c.quantity) for c in r.changes if c.flagged}
    assert flagged == {(2, "frequency")}, flagged
    c = next(c for c in r.changes if c.flagged)
    assert c.ratio == pytest.approx(1.005, abs=2e-4)
    assert c.z > 50
    v = nonlinearity(level=r)
    assert v.verdict == "nonlinear" and not v.linear_effects_admissible
    assert any("mode 2 at 120" in e and "frequency +0.5" in e for e in v.evidence), v.evidence
    # the model-free check sees it too
    assert r.pairs[0].flagged and r.pairs[0].sd > 10 * r.pairs[0].noise_sd


def test_the_model_free_difference_is_located_at_the_changed_mode():
    """The lines where the two levels differ most lie in the changed mode's half-power band."""
    rng = np.random.default_rng(11)
    f = _lines()
    lo = _level(f, _accelerance(f), 0.5, rng)
    hi = _level(f, _accelerance(f, F_HZ * [1, 1.002, 1]), 2.0, rng)
    p = level_dependence([lo, hi]).pairs[0]
    assert p.flagged
    assert abs(p.peak_hz - F_HZ[1]) < 3 * ZETA[1] * F_HZ[1], p.peak_hz
    assert p.to_dict()["peak_hz"] == p.peak_hz


def test_a_mode_that_cannot_be_fitted_is_left_out_and_the_others_checked():
    """A given mode with no resonance in its band (a spurious identified pole, or a band too crowded for six
    lines) is dropped with the reason; the other modes are still checked (it used to void the whole check)."""
    rng = np.random.default_rng(4)
    f = _lines()
    lo = _level(f, _accelerance(f), 0.5, rng)
    hi = _level(f, _accelerance(f, F_HZ * [1, 1.005, 1]), 2.0, rng)
    r = level_dependence([lo, hi], [50.0, 85.0, 120.0, 210.0])  # no mode and no line near 85 Hz
    np.testing.assert_allclose(r.modes_hz, F_HZ, rtol=1e-4)
    assert {(c.mode, c.quantity) for c in r.changes if c.flagged} == {(2, "frequency")}
    assert any(e.startswith("mode near 85 Hz left out") and "lines" in e for e in r.evidence), r.evidence
    with pytest.raises(CalibrationError, match="no resonance could be checked"):
        level_dependence([lo, hi], [85.0, 90.0])


def test_level_dependent_damping_three_levels():
    """Mode 1 damping 0.10 -> 0.13 -> 0.16 % over 0.2-2 N: flagged as damping of mode 1, trend positive."""
    rng = np.random.default_rng(5)
    f = _lines()
    levels = [
        _level(f, _accelerance(f, F_HZ, ZETA * [z, 1, 1]), lvl, rng)
        for z, lvl in ((1.0, 0.2), (1.3, 0.63), (1.6, 2.0))
    ]
    r = level_dependence(levels)
    flagged = {(c.mode, c.quantity) for c in r.changes if c.flagged}
    assert flagged == {(1, "damping")}
    c = next(c for c in r.changes if c.flagged)
    assert c.slope_per_decade > 0 and c.ratio == pytest.approx(1.6, rel=0.05)
    np.testing.assert_allclose(c.values, 0.001 * np.array([1.0, 1.3, 1.6]), rtol=0.05)
    assert "damping 0.1 % -> 0.16" in r.evidence[1]


def test_repeatability_floor_suppresses_a_small_change():
    """A 0.05 % frequency change is significant against 1 % noise but not against 0.1 % test-to-test scatter."""
    rng = np.random.default_rng(3)
    f = _lines()
    lo = _level(f, _accelerance(f), 1.0, rng)
    hi = _level(f, _accelerance(f, F_HZ * [1.0005, 1, 1]), 3.0, rng)
    assert level_dependence([lo, hi]).flagged
    r = level_dependence([lo, hi], frequency_repeatability=1e-3, scatter_delta=5e-3)
    assert not r.flagged, r.evidence
    assert "repeatability" in r.noise


def test_level_dependence_refuses_bad_input():
    f = _lines()
    H = _accelerance(f)
    a = FRFLevel(f, H, 1.0, label="a.h5")
    with pytest.raises(CalibrationError, match="two or more levels"):
        level_dependence([a])
    with pytest.raises(CalibrationError, match="same level"):
        level_dependence([a, FRFLevel(f, H, 1.0, label="b.h5")])
    with pytest.raises(CalibrationError, match="different units"):
        level_dependence([a, FRFLevel(f, H, 2.0, unit="m/s^2", label="b.h5")])
    with pytest.raises(CalibrationError, match="b.h5: std_error shape"):
        FRFLevel(f, H, 1.0, std_error=np.ones((f.size, 1, 1)), label="b.h5")
    with pytest.raises(CalibrationError, match="quantity"):
        FRFLevel(f, H, 1.0, quantity="inertance")
    with pytest.raises(CalibrationError, match="z_threshold must be"):
        level_dependence([a, FRFLevel(f, H, 2.0)], z_threshold=0)
    with pytest.raises(CalibrationError, match="frequency_repeatability must be"):
        level_dependence([a, FRFLevel(f, H, 2.0)], frequency_repeatability=-0.1)


# ---------------------------------------------------------- real bolted beam
def _brb(tag, by):
    d = np.load(reference_path("measured", "brb-stepped-sine", "frf.npz"))
    f = d[f"{tag}_freq_hz"]
    force, acc = d[f"{tag}_force_n"], d[f"{tag}_acc_ms2"]
    # README: fundamental amplitudes, phase of the response relative to the force running
    # 0 -> -pi through resonance; the authors plot acc/(2 pi f)^2: with that phase, a receptance
    H = acc / force / (2 * np.pi * f) ** 2 * np.exp(1j * d[f"{tag}_phase_rad"])
    level = float(np.mean(force)) if by == "N" else float(np.max(acc))
    return FRFLevel(f, H, level, unit=by, quantity="receptance", label=tag)


@pytest.mark.parametrize("family, by", [("fc", "N"), ("rc", "m/s^2")])
def test_bolted_beam_is_flagged_damping_rising(family, by):
    tags = [f"{family}{k}" for k in range(4 if family == "fc" else 8)]
    r = level_dependence([_brb(t, by) for t in tags])
    v = nonlinearity(level=r)
    assert v.flagged and v.verdict == "nonlinear" and not v.linear_effects_admissible
    damp = next(c for c in r.changes if c.quantity == "damping")
    assert damp.flagged and damp.z > 20 and damp.slope_per_decade > 0
    assert np.all(np.diff(damp.values) > 0)  # rises at every step
    assert damp.ratio > 3.5  # ~0.13-0.15 % -> 0.59-0.64 %
    assert 1.2e-3 < damp.values[0] < 1.7e-3 and 5.5e-3 < damp.values[-1] < 6.7e-3
    assert all(p.flagged for p in r.pairs)  # every level differs from the lowest beyond the fit residual
    assert any("mode 1 at 80." in e and "damping" in e and f"x{damp.ratio:.3g}" in e for e in v.evidence)
    if family == "rc":  # response control holds the level: the Levy reference fits (README) are reproduced
        levy = [1.53e-3, 1.98e-3, 2.37e-3, 3.04e-3, 3.85e-3, 4.68e-3, 5.59e-3, 6.45e-3]
        np.testing.assert_allclose(damp.values, levy, rtol=0.02)


# ----------------------------------------------------------------- distortion
def test_distortion_flags_resonance_and_superharmonic_lines():
    f = np.linspace(10, 200, 191)
    rng = np.random.default_rng(0)
    thd = 0.003 * (1 + 0.2 * rng.standard_normal((f.size, 3))) ** 2  # noise floor ~0.3 %
    k1 = np.argmin(np.abs(f - 120.0))
    k3 = np.argmin(np.abs(f - 40.0))
    thd[k1 - 1 : k1 + 2, 0] = [0.06, 0.12, 0.07]  # response channel at the resonance
    thd[k3, 1] = 0.08  # superharmonic 1/3 of the 120 Hz mode on the second sensor
    thd[50, 2] = 0.004  # above the floor but below the threshold: not flagged
    r = distortion(f, thd, channels=["acc1", "acc2", "force"], modes_hz=[120.0], damping=[0.002])
    assert r.flagged
    found = {(x.channel, x.mode, x.relation) for x in r.lines}
    assert found == {("acc1", 1, "resonance"), ("acc2", 1, "superharmonic 1/3")}
    assert len(r.lines) == 4 and r.max_thd[0] == pytest.approx(0.12)
    assert r.floor[0] == pytest.approx(0.003, rel=0.2)
    assert any("acc1" in e and "12 %" in e and "resonance of mode 1" in e for e in r.evidence)
    assert nonlinearity(distortion=r).verdict == "nonlinear"


def test_distortion_below_the_floor_is_not_flagged():
    """A THD above the threshold that is the channel's own noise floor (a quiet channel) is not flagged."""
    f = np.linspace(10, 200, 50)
    thd = np.full((f.size, 2), 0.002)
    thd[:, 1] = 0.08  # broad, flat: noise on a weak channel
    r = distortion(f, thd)
    assert not r.flagged and nonlinearity(distortion=r).verdict == "linear"
    # the same channel with an explicit, lower floor is flagged everywhere
    assert len(distortion(f, thd, floor=[0.002, 0.002]).lines) == f.size
    with pytest.raises(CalibrationError, match="thd must be"):
        distortion(f, thd[:-1])


# ------------------------------------------------------------ sweep direction
def _duffing_sweep(f, direction, zeta=0.002, fn=100.0, beta=0.0, force=1.0):
    """Harmonic-balance receptance of m q'' + c q' + k q (1 + beta q^2) = F cos wt, swept up or down.

    The amplitude a solves a^2 [(wn^2 (1 + 3/4 beta a^2) - w^2)^2 + (2 zeta wn w)^2] = F^2;
    where three branches coexist the sweep stays on the one nearest its last amplitude.
    """
    wn = 2 * np.pi * fn
    order = np.arange(f.size) if direction == "up" else np.arange(f.size)[::-1]
    H = np.zeros(f.size, complex)
    a_prev = 0.0
    for k in order:
        w = 2 * np.pi * f[k]
        c = 0.75 * beta * wn**2
        # cubic in x = a^2: c^2 x^3 + 2 c (wn^2 - w^2) x^2 + ((wn^2 - w^2)^2 + (2 zeta wn w)^2) x - F^2 = 0
        x = np.roots([c**2, 2 * c * (wn**2 - w**2), (wn**2 - w**2) ** 2 + (2 * zeta * wn * w) ** 2, -(force**2)])
        x = np.real(x[(np.abs(x.imag) < 1e-9 * np.abs(x)) & (x.real > 0)])
        # both sweeps start far from resonance, on the low-amplitude branch
        a = np.sqrt(x[np.argmin(np.abs(np.sqrt(x) - a_prev))]) if a_prev else np.sqrt(x.min())
        a_prev = a
        H[k] = 1.0 / (wn**2 * (1 + 0.75 * beta * a**2) - w**2 + 2j * zeta * wn * w)
    return H[:, None, None]


def test_sweep_direction_finds_the_jump_of_a_hardening_mode():
    f = np.linspace(97, 106, 181)
    beta = 2.5e5  # hardening: the upper branch reaches 103.45 Hz at 1 N, the jump down sits at 101 Hz
    rng = np.random.default_rng(2)
    Hu, su = _noisy(_duffing_sweep(f, "up", beta=beta), 0.01, rng)
    Hd, sd = _noisy(_duffing_sweep(f, "down", beta=beta), 0.01, rng)
    up = FRFLevel(f, Hu, 1.0, std_error=su, quantity="receptance", sweep="up", label="up.h5")
    down = FRFLevel(f, Hd, 1.0, std_error=sd, quantity="receptance", sweep="down", label="down.h5")
    r = sweep_direction(up, down)
    assert r.flagged and len(r.bands) == 1
    b = r.bands[0]
    # the two-branch region above the linear resonance (noise-free: 101.0-103.45 Hz differ by > 5 %)
    assert 100.5 < b.f_low_hz < 101.2 and 103.3 < b.f_high_hz < 103.6
    assert b.peak_up_hz == pytest.approx(103.45, abs=0.06) and b.peak_down_hz == pytest.approx(100.95, abs=0.06)
    assert b.peak_up_hz > b.peak_down_hz and b.max_relative_difference > 0.5
    assert "hardening" in r.evidence[0]
    assert nonlinearity(sweep=r).verdict == "nonlinear"
    with pytest.raises(CalibrationError, match="down.h5: given as the up sweep but its lines were measured down"):
        sweep_direction(down, up)


@pytest.mark.parametrize("with_std_error", [True, False])
def test_sweep_direction_linear_agrees_within_noise(with_std_error):
    f = np.linspace(97, 103, 121)
    rng = np.random.default_rng(4)
    H = _duffing_sweep(f, "up")  # beta = 0: linear, both directions identical
    Hu, su = _noisy(H, 0.01, rng)
    Hd, sd = _noisy(H, 0.01, rng)
    up = FRFLevel(f, Hu, 1.0, std_error=su if with_std_error else None, quantity="receptance")
    down = FRFLevel(f, Hd, 1.0, std_error=sd if with_std_error else None, quantity="receptance")
    r = sweep_direction(up, down)
    assert not r.flagged and abs(r.z_overall) < 4
    assert nonlinearity(sweep=r).verdict == "linear"


def test_nonlinearity_needs_a_check():
    with pytest.raises(CalibrationError, match="no nonlinearity check"):
        nonlinearity()


# ------------------------------------------------- no standard errors; run files
@pytest.mark.parametrize("noise", ["relative", "absolute"])
def test_linear_without_standard_errors_not_flagged(noise):
    """Noise floor from the local fit residual only (no std_error): still no false alarm over seeds."""
    f = _lines()
    H = _accelerance(f)
    for seed in range(8):
        rng = np.random.default_rng(100 + seed)
        levels = []
        for lvl in (1.0, 4.0):
            s = 0.01 * (np.abs(H) if noise == "relative" else np.abs(H).max(axis=0, keepdims=True))
            e = s * (rng.standard_normal(H.shape) + 1j * rng.standard_normal(H.shape)) / np.sqrt(2)
            levels.append(FRFLevel(f, H + e, lvl))
        r = level_dependence(levels)
        assert not r.flagged, (seed, r.evidence)
        assert "fit residual" in r.noise
        np.testing.assert_allclose(r.modes_hz, F_HZ, rtol=2e-4)  # a noise bump is never taken for a mode
    # and a real 0.5 % stiffening is still found without standard errors
    hi = FRFLevel(f, _accelerance(f, F_HZ * [1, 1.005, 1]), 4.0)
    r = level_dependence([levels[0], hi])
    assert {(c.mode, c.quantity) for c in r.changes if c.flagged} == {(2, "frequency")}


def test_run_files_sweep_order_and_distortion(tmp_path):
    """Up and down stepped-sine run files of a hardening mode: order from time_s, jump and THD flagged."""
    from acquisition.runfile import ChannelSpec, LineQuality, create_run, read_run

    from calibration import distortion_of_run, frf_level_from_run

    sens = (ChannelSpec("acc1", "response", "acceleration", "m/s^2", grid=1, direction=(0.0, 0.0, 1.0)),)
    drv = (ChannelSpec("F1", "force", "force", "N", grid=1, direction=(0.0, 0.0, 1.0)),)
    f = np.linspace(97, 106, 91)
    rng = np.random.default_rng(7)
    runs = {}
    for direction in ("up", "down"):
        H = -((2 * np.pi * f) ** 2)[:, None, None] * _duffing_sweep(f, direction, beta=2.5e5)
        Hn, s = _noisy(H, 0.01, rng)
        thd = np.full((f.size, 2), 0.002)
        thd[:, 0] += 0.05 * (np.abs(H[:, 0, 0]) / np.abs(H).max()) ** 2  # distortion grows with the response
        path = tmp_path / f"{direction}.h5"
        order = range(f.size) if direction == "up" else range(f.size - 1, -1, -1)
        with create_run(path, article="BRB-1", sensors=sens, drives=drv) as w:
            for t, k in enumerate(order):
                q = LineQuality(force_n=np.ones(1), std_error=s[k], thd=thd[k], time_s=float(t))
                w.append_line(f[k], Hn[k], q)
        runs[direction] = read_run(path)
    up, down = frf_level_from_run(runs["up"]), frf_level_from_run(runs["down"])
    assert (up.sweep, down.sweep) == ("up", "down") and up.level == pytest.approx(1.0)
    r = sweep_direction(up, down)
    assert r.flagged and r.bands[0].peak_up_hz > r.bands[0].peak_down_hz
    d = distortion_of_run(runs["up"], modes_hz=[100.0], damping=[0.002], threshold=0.02)
    assert d.flagged and {x.channel for x in d.lines} == {"acc1"}
    assert max(x.thd for x in d.lines) > 0.04
    v = nonlinearity(sweep=r, distortion=d)
    assert v.verdict == "nonlinear" and "sweep direction: FLAGGED" in v.evidence
    assert v.to_dict()["distortion"]["flagged"]
