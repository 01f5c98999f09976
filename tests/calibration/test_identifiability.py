"""Identifiability: manufactured least-squares problems with known covariance, and a pinned beam parameter."""

import numpy as np
import pytest

from calibration import (
    CalibrationError,
    FitData,
    Objective,
    build_surrogate,
    calibrate,
    cross_validate,
    full_order_frf,
    half_bandwidth_frequencies,
    identifiability,
    with_spread,
)
from tests.calibration._models import beam_model

NAMES = ("a", "b", "c", "d")
LO, HI = -0.3 * np.ones(4), 0.3 * np.ones(4)


def _linear(sigma=1e-3, m=400, seed=0):
    rng = np.random.default_rng(seed)
    J = rng.standard_normal((m, 4)) * np.array([1.0, 0.5, 2.0, 0.1])
    r = sigma * rng.standard_normal(m)
    return J, r


def test_std_and_correlation_match_linear_least_squares():
    J, r = _linear()
    idf = identifiability(J, r, np.zeros(4), LO, HI, NAMES)
    s2 = r @ r / (J.shape[0] - 4)
    C = s2 * np.linalg.inv(J.T @ J)
    assert idf.residual_variance == pytest.approx(s2)
    assert np.allclose(idf.std, np.sqrt(np.diag(C)), rtol=1e-10)
    assert np.allclose(idf.correlation, C / np.outer(np.sqrt(np.diag(C)), np.sqrt(np.diag(C))), atol=1e-12)
    assert idf.identifiable.all() and idf.n_identifiable == 4
    # unit-column singular values: a random orthogonal-ish design, none weak
    assert idf.singular_values[-1] / idf.singular_values[0] > 0.5 and not idf.weak()


def test_std_grows_with_noise_until_not_identifiable():
    J, r = _linear(sigma=0.2)
    idf = identifiability(J, r, np.zeros(4), LO, HI, NAMES)
    # std of d ~ 0.2 / (0.1 sqrt(400)) = 0.1 > 5 % of its range 0.6; a, b, c: 0.01, 0.02, 0.005
    assert idf.std == pytest.approx([0.01, 0.02, 0.005, 0.1], rel=0.15)
    assert not idf.identifiable[3] and "exceeds 5 % of its range" in idf.reasons[3]
    assert idf.identifiable[:3].all()


def test_half_data_refits_spread_like_the_formal_std_of_a_linear_problem():
    # The rule behind with_spread: for a linear least-squares problem the spread of estimates on random
    # halves of the residuals about their mean is the full-data std (Var(p_half - p_full) = 2 s^2 - s^2).
    rng = np.random.default_rng(3)
    m, theta = 400, np.array([0.05, -0.1, 0.02, 0.1])
    J = rng.standard_normal((m, 4)) * np.array([1.0, 0.5, 2.0, 0.1])
    y = J @ theta + 0.05 * rng.standard_normal(m)
    full = np.linalg.lstsq(J, y, rcond=None)[0]
    idf = identifiability(J, y - J @ full, full, LO, HI, NAMES)
    halves = []
    for _ in range(400):
        keep = rng.permutation(m)[: m // 2]
        halves.append(np.linalg.lstsq(J[keep], y[keep], rcond=None)[0])
    spread = np.std(halves, axis=0, ddof=1)
    assert spread == pytest.approx(idf.std, rel=0.2)  # measured 0.88-1.10 over seeds 0-3
    out = with_spread(idf, np.array(halves))
    # consistent: nothing changes but the recorded spread; d (std 0.025 < 0.03) stays identifiable
    assert out.identifiable.tolist() == idf.identifiable.tolist() == [True] * 4
    assert out.reasons == idf.reasons and np.allclose(out.spread, spread)
    # the reported std is the larger of the two; the formal one is kept
    assert np.allclose(out.std, np.maximum(idf.std, spread)) and np.array_equal(out.std_formal, idf.std)


def test_refits_that_scatter_or_pin_overrule_an_optimistic_formal_std():
    J, r = _linear()
    idf = identifiability(J, r, np.zeros(4), LO, HI, NAMES)
    assert idf.identifiable.all() and np.all(idf.std < 1e-3)
    rng = np.random.default_rng(1)
    P = 1e-4 * rng.standard_normal((10, 4))
    P[:, 1] = 0.06 * np.linspace(-1, 1, 10)  # s.d. 3.6 % with the lines: beyond 5 % of the 0.6 range
    P[3, 2] = HI[2]  # pinned in one refit
    out = with_spread(idf, P)
    assert out.identifiable.tolist() == [True, False, False, True] and out.n_identifiable == 2
    assert "cross-validation spread" in out.reasons[1] and "formal std" in out.reasons[1]
    assert "at a bound in 1 of 10 cross-validation refits" in out.reasons[2]
    assert np.isnan(out.spread[2]) and out.spread[1] == pytest.approx(P[:, 1].std(ddof=1))
    assert out.std[1] == out.spread[1] and out.std[2] == idf.std[2]  # a pinned refit has no spread to use
    assert out.to_dict()["parameters"][1]["std_formal_p"] == pytest.approx(idf.std[1])
    assert out.to_dict()["parameters"][2]["spread_p"] is None
    assert "CV s.d.%" in out.table() and "pinned" in out.table()
    # already not identifiable: the reason is kept, not replaced
    J2, r2 = _linear(sigma=0.2)
    weak = identifiability(J2, r2, np.zeros(4), LO, HI, NAMES)
    P2 = np.zeros((5, 4))
    P2[:, 3] = np.linspace(-0.2, 0.2, 5)
    assert with_spread(weak, P2).reasons[3] == weak.reasons[3]
    with pytest.raises(CalibrationError, match="refits have 3 parameters"):
        with_spread(idf, np.zeros((5, 3)))


def test_refits_that_agree_readmit_a_parameter_of_a_weak_combination():
    """Flagged only for taking part in a flat combination (formal std tiny): >= 5 refits agreeing within 1 % of
    the range readmit it; a wider spread, too few refits or a pinned refit do not."""
    J, r = _linear(sigma=1e-6)
    J[:, 1] = -2.0 * J[:, 0] + 2e-3 * np.random.default_rng(5).standard_normal(J.shape[0])
    idf = identifiability(J, r, np.zeros(4), LO, HI, NAMES)
    assert idf.identifiable.tolist() == [False, False, True, True]
    assert idf.reasons[0].startswith("in weak combination") and np.all(idf.std < 0.03)
    # the verdict says the formal std is small where it is (<= 1 % of the range) and who decides then
    small = idf.std <= 0.01 * (HI - LO)
    assert all(("the cross-validation refits decide" in why) == bool(s) for why, s in zip(idf.reasons[:2], small[:2]))
    P = 1e-4 * np.random.default_rng(2).standard_normal((10, 4))
    out = with_spread(idf, P)
    assert out.identifiable.all() and out.reasons[:2] == ("", "")
    P[:, 1] = np.linspace(-0.01, 0.01, 10)  # s.d. 0.64 %: above 1 % of the 0.6 range
    assert with_spread(idf, P).identifiable.tolist() == [True, False, True, True]
    few = with_spread(idf, P[:4])
    assert few.identifiable.tolist() == [False, False, True, True]  # too few refits: and the verdict says so
    assert all(why.endswith("; 4 cross-validation refits cannot decide: at least 5 are needed ([crossvalidation] "
                            "realizations)") for why in few.reasons[:2]) and few.reasons[2:] == ("", "")
    assert with_spread(idf, P[:1]).reasons[0].endswith("1 cross-validation refit cannot decide: at least 5 are "
                                                        "needed ([crossvalidation] realizations)")
    P[0, 0] = LO[0]
    assert not with_spread(idf, P).identifiable[0]
    # at a bound (not only a weak combination) is never readmitted
    pinned = identifiability(J, r, np.array([LO[0], 0, 0, 0]), LO, HI, NAMES)
    assert not with_spread(pinned, 1e-4 * np.ones((10, 4)) * np.arange(10)[:, None]).identifiable[0]


def test_collinear_pair_is_named_as_a_combination():
    J, r = _linear()
    # b moves the residual like -2 a (plus a trace of its own): a change of a by x with b by x/2 is invisible
    J[:, 1] = -2.0 * J[:, 0] + 1e-4 * np.random.default_rng(5).standard_normal(J.shape[0])
    idf = identifiability(J, r, np.zeros(4), LO, HI, NAMES)
    assert not idf.identifiable[0] and not idf.identifiable[1]
    assert idf.identifiable[2] and idf.identifiable[3]
    c, other = idf.max_correlation(0)
    assert other == "b" and c > 0.99  # J_b = -2 J_a: the estimates move together
    (rel, words), = idf.weak()
    assert rel < 1e-3
    assert words.startswith("+0.89 a +0.45 b")
    assert "weak combination +0.89 a +0.45 b" in idf.reasons[0]
    assert "weak combinations" in idf.table()


def test_exactly_dependent_and_dead_parameters_get_infinite_std():
    J, r = _linear()
    J[:, 1] = J[:, 0]
    J[:, 3] = 0.0
    idf = identifiability(J, r, np.zeros(4), LO, HI, NAMES)
    assert np.isinf(idf.std[[0, 1, 3]]).all() and np.isfinite(idf.std[2])
    assert "no influence" in idf.reasons[3]
    assert "null combination" in idf.reasons[0]
    assert idf.correlation[0, 1] == -1.0  # equal columns: a up and b down by the same is invisible
    assert "+0.71 a -0.71 b" in idf.reasons[1]
    d = idf.to_dict()
    assert d["parameters"][3]["std_p"] is None and d["parameters"][3]["identifiable"] is False
    assert d["n_identifiable"] == 1


def test_residuals_correlated_along_frequency_inflate_the_std():
    rng = np.random.default_rng(2)
    m, k, rho = 4000, 4, 0.9  # 4 channels, AR(1) along frequency with coefficient 0.9
    J = rng.standard_normal((m, 4))
    e = rng.standard_normal((m // k, k))
    for i in range(1, e.shape[0]):
        e[i] = rho * e[i - 1] + np.sqrt(1 - rho**2) * e[i]
    r = 1e-3 * e.ravel()
    plain = identifiability(J, r, np.zeros(4), LO, HI, NAMES)
    inflated = identifiability(J, r, np.zeros(4), LO, HI, NAMES, stride=k)
    assert plain.inflation == 1.0
    assert inflated.inflation == pytest.approx((1 + rho) / (1 - rho), rel=0.15)
    assert np.allclose(inflated.std / plain.std, np.sqrt(inflated.inflation))
    assert "for residuals correlated along frequency" in inflated.table()
    white = identifiability(J, 1e-3 * rng.standard_normal(m), np.zeros(4), LO, HI, NAMES, stride=k)
    assert white.inflation < 1.1
    with pytest.raises(CalibrationError, match="stride"):
        identifiability(J, r, np.zeros(4), LO, HI, NAMES, stride=0)


def test_bad_shapes_raise():
    J, r = _linear()
    with pytest.raises(CalibrationError, match="Jacobian"):
        identifiability(J[:, :3], r, np.zeros(4), LO, HI, NAMES)
    with pytest.raises(CalibrationError, match="names"):
        identifiability(J, r, np.zeros(4), LO, HI, NAMES[:3])


@pytest.fixture(scope="module")
def pinned_beam():
    """Beam calibrated against a truth with k_bush at +40 % (bounds +-30 %), 0.5 % noise."""
    model, _ = beam_model()
    band = (20.0, 400.0)
    sur, _ = build_surrogate(model, np.zeros(7), band)
    p_true = np.array([0.0047, 0.1802, -0.1423, 0.1795, -0.0753, -0.0307, 0.40])
    f = half_bandwidth_frequencies(*band, 0.01, 3)
    rng = np.random.default_rng(1)
    H = full_order_frf(model, p_true, f, 0.01)
    H = H * (1 + 0.005 * (rng.standard_normal(H.shape) + 1j * rng.standard_normal(H.shape)) / np.sqrt(2))
    data = [FitData(f, H, model.output_names)]
    lo, hi = -0.3 * np.ones(7), 0.3 * np.ones(7)
    cal = calibrate(sur, data, lo, hi, 0.01, n_starts=0)
    return model, sur, data, cal, p_true, lo, hi


def test_beam_parameter_beyond_its_bound_is_reported_pinned_the_others_identified(pinned_beam):
    model, sur, data, cal, p_true, lo, hi = pinned_beam
    obj = Objective(sur, data, 0.01)
    idf = identifiability(obj.jacobian(cal.p), obj.residual(cal.p), cal.p, lo, hi, model.parameter_names)
    assert idf.at_bound.tolist() == [0, 0, 0, 0, 0, 0, 1]
    assert idf.identifiable.tolist() == [True] * 6 + [False]
    assert "upper bound (+30.0 %)" in idf.reasons[6]
    # the free estimates are near the truth on the scale of their std (0.01-0.2 % of p)
    err = np.abs(cal.p[:6] - p_true[:6])
    assert np.all(idf.std[:6] < 0.005) and np.all(err < 6 * idf.std[:6] + 1e-4)
    assert "6 of 7 parameters identifiable" in idf.table()


def test_crossvalidation_does_not_report_a_pinned_parameter_as_certain(pinned_beam):
    model, sur, data, cal, p_true, lo, hi = pinned_beam
    cv = cross_validate(sur, data, cal.p, lo, hi, 0.01, n_realizations=4, seed=0)
    assert cv.n_at_bound.tolist() == [0, 0, 0, 0, 0, 0, 4]
    # the pinned spread is exactly zero: that is what used to be printed as "CV 0.000 %"
    assert cv.cv_percent[6] < 1e-6
    assert cv.cv(6) is None and "at a bound in 4 of 4 realizations" in cv.cv_reason[6]
    d = cv.to_dict()
    assert d["cv_percent"][6] is None and d["cv_not_meaningful"][6].startswith("at a bound")
    assert all(0 < d["cv_percent"][j] < 1 for j in range(6)) and d["cv_not_meaningful"][:6] == [None] * 6
