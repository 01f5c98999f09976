"""An accepted effect whose final size the data do not see (calibration.negligible_effect,
frfcal.campaign._diagnose.drop_negligible)."""

from __future__ import annotations

import numpy as np
import pytest

from calibration import CalibrationError, accept, negligible_effect


def test_an_effect_refined_to_zero_is_negligible_a_real_one_is_not():
    n = 120
    # a spring refined to 1e-37 N/m: the model with and without it is the same model
    neg, ratio, allowed = negligible_effect(0.0125, 0.0125, n)
    assert neg and ratio == 1.0
    assert allowed == pytest.approx(np.exp(-np.log(n) / n))
    # the same threshold as the acceptance's penalty: an effect whose removal raises the hold-out by just less
    # than the penalty is negligible, by just more is not
    h0 = 0.0125
    assert negligible_effect(h0 * allowed * 1.0001, h0, n)[0]
    assert not negligible_effect(h0 * allowed * 0.9999, h0, n)[0]
    # ... and an effect accept() takes on those numbers is the one negligible_effect keeps
    cv_b, cv_a = [0.05, 0.051, 0.049], [0.02, 0.021, 0.019]
    for ha in (h0 * allowed * 1.0001, h0 * allowed * 0.9999):
        assert accept(h0, ha, cv_b, cv_a, 1e-4, 1, n).accepted == (not negligible_effect(ha, h0, n)[0])
    # a real effect: the model without it is 20 x worse
    assert not negligible_effect(0.0125, 0.25, n)[0]
    # two parameters (a compound) have twice the penalty
    assert negligible_effect(0.0125, 0.0125, n, 2)[2] == pytest.approx(allowed ** 2)


def test_negligible_effect_refuses_bad_input():
    with pytest.raises(CalibrationError, match="finite"):
        negligible_effect(0.01, 0.0, 100)
    with pytest.raises(CalibrationError, match="n_residuals"):
        negligible_effect(0.01, 0.02, 1)


def test_drop_negligible_keeps_the_seen_effects_and_their_magnitudes():
    from frfcal.campaign._diagnose import drop_negligible

    acc = [{"name": "mass_g44", "c": 2.3}, {"name": "stinger_g18", "c": 1e-37}, {"name": "ground_g15_z", "c": 0.7}]
    sizes = [{"negligible": False, "ratio": 0.1}, {"negligible": True, "ratio": 1.0},
             {"negligible": False, "ratio": 0.5}]
    x = np.array([0.1, -0.2, 2.3, 1e-37, 0.7])  # 2 parameters, then the 3 effects' c
    kept, dropped, x_kept = drop_negligible(acc, sizes, x, 2)
    assert [a["name"] for a in kept] == ["mass_g44", "ground_g15_z"]
    assert [a["name"] for a in dropped] == ["stinger_g18"] and dropped[0]["refined_effect"]["negligible"]
    assert [a["term_index"] for a in kept] == [0, 2]
    np.testing.assert_array_equal(x_kept, [0.1, -0.2, 2.3, 0.7])
    assert acc[1] == {"name": "stinger_g18", "c": 1e-37}  # the caller's rows are not modified
