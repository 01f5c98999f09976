"""Hold-out validation: per-article damping, noise floor, wording that does not claim a pass."""

import numpy as np
import pytest

from calibration import (
    CalibrationError,
    FitData,
    IdentifiedModes,
    build_surrogate,
    floor_range,
    full_order_frf,
    noise_floor_sd,
    range_text,
    reduced_modes,
    validate,
)
from tests.calibration._models import beam_model

BAND = (20.0, 400.0)
P_TRUE = np.array([0.0047, 0.1802, -0.1423, 0.1795, -0.0753, -0.0307, 0.1311])
HOLD = [1, 3, 5, 7, 9]


@pytest.fixture(scope="module")
def beam():
    model, _ = beam_model()
    sur0, _ = build_surrogate(model, np.zeros(7), BAND)
    sur1, _ = build_surrogate(model, P_TRUE, BAND)
    lam, X = reduced_modes(sur1, P_TRUE)
    fe_hz = np.sqrt(np.clip(lam, 0, None)) / (2 * np.pi)
    sel = (fe_hz > 15) & (fe_hz < 450)
    return model, sur0, sur1, fe_hz[sel], (sur1.outputs @ X)[:, sel] + 0j


def _article(model, zeta, name, noise=0.0, seed=0):
    f = np.arange(20.0, 400.0, 0.25)
    H = full_order_frf(model, P_TRUE, f, zeta)[:, HOLD]
    sig = noise * np.abs(H)
    if noise:
        rng = np.random.default_rng(seed)
        H = H + sig * (rng.standard_normal(H.shape) + 1j * rng.standard_normal(H.shape)) / np.sqrt(2)
    return FitData(f, H, tuple(model.output_names[i] for i in HOLD), article=name), sig


def test_each_article_takes_its_own_identified_damping(beam):
    model, sur0, sur1, fe_hz, shapes = beam
    (d1, _), (d2, _) = _article(model, 0.003, "A1"), _article(model, 0.008, "A2")
    m1 = IdentifiedModes(fe_hz, np.full(fe_hz.size, 0.003), shapes, model.output_names)
    m2 = IdentifiedModes(fe_hz, np.full(fe_hz.size, 0.008), shapes, model.output_names)
    per = validate(sur0, sur1, P_TRUE, [d1, d2], [m1, m2])
    first = validate(sur0, sur1, P_TRUE, [d1, d2], m1)  # the old behaviour: article 1's damping for both
    a1, a2 = per.items
    assert a1["article"] == "A1" and a2["article"] == "A2"
    # what is left is the out-of-band modes at zeta0 = 1 % instead of the article's damping
    assert a1["sd_calibrated"] < 5e-5 and a2["sd_calibrated"] < 5e-5
    assert first.items[1]["sd_calibrated"] > 10 * per.items[1]["sd_calibrated"]
    assert first.items[0]["sd_calibrated"] == pytest.approx(a1["sd_calibrated"])
    assert [p["zeta"] for p in per.pairs_calibrated[1]] == [0.008] * fe_hz.size
    with pytest.raises(CalibrationError, match="2 sets of identified modes for 1 data items"):
        validate(sur0, sur1, P_TRUE, [d1], [m1, m2])


@pytest.mark.parametrize("noise", [0.01, 0.03])
def test_noise_floor_predicts_the_sd_of_the_truth(beam, noise):
    model, sur0, sur1, fe_hz, shapes = beam
    d, sig = _article(model, 0.003, "A1", noise=noise, seed=3)
    m = IdentifiedModes(fe_hz, np.full(fe_hz.size, 0.003), shapes, model.output_names)
    # zeta0 = the article's damping also on unpaired (out-of-band) modes: only the noise is left
    v = validate(sur0, sur1, P_TRUE, [d], [m], zeta0=0.003, std_error=[sig])
    assert v.sd_floor == pytest.approx(noise**2 / np.log(10) ** 2, rel=0.01)  # sigma/|H| with the noisy |H|
    assert noise_floor_sd(d, sig) == v.sd_floor
    # the true parameters with the true damping leave only the noise: ratio ~1
    assert 0.9 < v.floor_ratio < 1.15
    assert v.improved and v.below_target is None and v.verdict == "improved"
    s = v.summary()
    assert s.startswith("hold-out SD (raw lines, identified damping) ") and f"({v.floor_ratio:.1f}x;" in s
    # the truth's SD is one draw of the noise: inside the 90 % range of a model at its floor
    lo, hi = v.floor_range
    assert lo < v.sd_floor < hi and lo <= v.sd_calibrated <= hi, (v.floor_range, v.sd_calibrated)
    assert f"at its floor a model scores {range_text(lo, hi)} in 90 % of noise draws)" in s
    assert "pass" not in s.lower()
    d_json = v.to_dict()
    assert "passed" not in d_json and d_json["verdict"] == "improved" and d_json["sd_floor"] == v.sd_floor


def test_wording_with_target_and_when_worse(beam):
    model, sur0, sur1, fe_hz, shapes = beam
    d, _ = _article(model, 0.003, "A1")
    m = IdentifiedModes(fe_hz, np.full(fe_hz.size, 0.003), shapes, model.output_names)
    # noise-free lines: the calibrated SD is round-off (6e-16 with the loads' first moments in the basis)
    v = validate(sur0, sur1, P_TRUE, d, m, target_sd=1e-20)
    assert v.verdict == "improved, above target 1e-20" and v.sd_floor is None and v.floor_ratio is None
    v = validate(sur0, sur1, P_TRUE, d, m, target_sd=1e-9)
    assert v.verdict == "improved, below target 1e-09"
    # "calibrated" point worse than nominal: the nominal surrogate evaluated far from the truth
    w = validate(sur1, sur0, -P_TRUE, d, m)
    assert not w.improved and w.verdict == "worse"
    with pytest.raises(CalibrationError, match="shape"):
        validate(sur0, sur1, P_TRUE, [d], [m], std_error=[np.ones(3)])


def _circular(rng, shape):
    return (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)) / np.sqrt(2)


@pytest.mark.parametrize("q", [1e-4, 0.05, 0.5, 2.0, 30.0, 1e3, 1e7])
def test_log_noise_variance_is_the_mean_square_log_error(q):
    """E|ln(1 + z)|^2 for circular complex Gaussian z, E|z|^2 = q, against Monte Carlo (4e5 samples):
    q for small noise, only (ln q)^2 / 4 + ... where the noise swamps the value."""
    from calibration._metric import log_noise_variance

    z = np.sqrt(q) * _circular(np.random.default_rng(3), 400_000)
    mc = np.mean(np.abs(np.log1p(z)) ** 2)
    assert log_noise_variance(q) == pytest.approx(mc, rel=0.015)
    assert log_noise_variance(np.array([[q]])).shape == (1, 1)
    if q < 1e-3:
        assert log_noise_variance(q) == pytest.approx(q, rel=1e-3)


def test_the_floor_of_an_anti_resonance_is_the_error_its_noise_leaves():
    """A drive-point-like FRF with deep anti-resonances and an absolute noise floor (an outside trial's
    UFF data, stop 33): the floor from the true |H| is the mean square log error the noise leaves,
    where the first-order (sigma/|H|)^2 over-counts the values the noise swamps; from the noisy |H|
    it stays near it (a little low), not at the 200x a line of tiny measured |H| gave before."""
    f = np.linspace(20.0, 400.0, 1500)
    w = 2 * np.pi * f
    fn, zeta = np.array([60.0, 140.0, 250.0, 330.0]), 0.002
    wn = 2 * np.pi * fn
    H = np.sum(-w[:, None] ** 2 / (wn**2 - w[:, None] ** 2 + 2j * zeta * wn * w[:, None]), axis=1)
    H = H[:, None, None] * np.array([1.0, -0.7])[None, :, None]  # two channels, anti-resonances between modes
    sig = np.sqrt((0.007 * np.abs(H)) ** 2 + (0.03 * np.median(np.abs(H))) ** 2)  # noise > |H| on 44 values
    d_true = FitData(f, H, ("a", "b"), article="T")
    floor = noise_floor_sd(d_true, sig)
    first_order = np.mean((sig / np.abs(H)) ** 2) / np.log(10) ** 2
    rng = np.random.default_rng(7)
    realized, from_noisy, first_noisy = [], [], []
    for k in range(400):  # the mean of 400 realizations' SDs scatters by 0.5 %
        Hn = H + sig * _circular(rng, H.shape)
        realized.append(np.mean(np.abs(np.log10(Hn / H)) ** 2))
        if k < 200:
            from_noisy.append(noise_floor_sd(FitData(f, Hn, ("a", "b"), article="T"), sig))
            first_noisy.append(np.mean((sig / np.abs(Hn)) ** 2) / np.log(10) ** 2)
    assert floor == pytest.approx(np.mean(realized), rel=0.02)
    assert first_order > 2 * floor  # measured 2.45x
    assert 0.6 < np.median(from_noisy) / floor < 1.2 and np.max(from_noisy) < 1.5 * floor  # 0.83x, 1.0x
    assert np.max(first_noisy) > 20 * floor  # 204x


def test_floor_range_covers_a_correct_models_sd_where_a_few_values_hold_the_floor():
    """1000 values at 1 % noise and three below their noise (|H| = 0.25-0.5 sigma, an anti-resonance): the
    three hold most of the realized floor, which scatters by several times its expectation. The 5-95 % range
    about the model's values holds a correct model's SD in about 90 % of independent noise draws."""
    rng = np.random.default_rng(4)
    H = np.exp(1j * rng.uniform(0, 2 * np.pi, 1003)) * np.r_[np.ones(1000), 0.25, 0.35, 0.5]
    s = np.r_[np.full(1000, 0.01), np.ones(3)]
    lo, hi = floor_range(H, s)
    realized = []
    for _ in range(300):
        n = s / np.sqrt(2) * (rng.standard_normal(H.size) + 1j * rng.standard_normal(H.size))
        realized.append(np.mean(np.abs(np.log10(H / (H + n))) ** 2))
    realized = np.array(realized)
    inside = np.mean((realized >= lo) & (realized <= hi))
    assert 0.84 < inside < 0.96, inside
    assert hi > 3 * lo  # the three values make the range wide
    with pytest.raises(CalibrationError, match="3 model values but 2 standard errors"):
        floor_range(H[:3], s[:2])
