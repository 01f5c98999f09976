"""The same calibration in mm-t-s and in SI gives the same result (the example subframe)."""

import numpy as np
import pytest

import femodel
from calibration import FitData, FRFModel, build_surrogate, calibrate, half_bandwidth_frequencies, surrogate_frf
from tests.calibration._synthetic import DRIVE, layout, truth_frf

BAND = (100.0, 400.0)


def _setup(tmp, units):
    ex = femodel.example_subframe(tmp / units, target_dof=1500, units=units)
    pm = femodel.parametric_model(ex.params)
    grids, dirs = layout(pm)
    C = femodel.sensor_matrix(pm.assembly, grids, dirs)
    model = FRFModel(pm.K, pm.M, C[[DRIVE]].T.toarray(), C, parametric=pm,
                     parameter_names=tuple(pm.parameters.names))
    return pm, model, grids, dirs


@pytest.fixture(scope="module")
def both(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("units")
    return {u: _setup(tmp, u) for u in ("mm-t-s", "si")}


def test_same_physics_in_both_unit_systems(both):
    (pm_a, model_a, *_), (pm_b, model_b, *_) = both["mm-t-s"], both["si"]
    np.testing.assert_allclose(pm_a.nominal, pm_b.nominal, rtol=1e-9)
    f = half_bandwidth_frequencies(*BAND, 0.01, 3)
    p = np.linspace(-0.1, 0.1, pm_a.n_params)
    Ha = surrogate_frf(build_surrogate(model_a, np.zeros(pm_a.n_params), BAND)[0], p, f)
    Hb = surrogate_frf(build_surrogate(model_b, np.zeros(pm_b.n_params), BAND)[0], p, f)
    np.testing.assert_allclose(Ha, Hb, rtol=1e-6)


def test_same_calibration_in_both_unit_systems(both):
    rng = np.random.default_rng(4)
    p_true = rng.uniform(-0.1, 0.1, 17)
    results = {}
    for units, (pm, model, grids, dirs) in both.items():
        def data(z):
            f = half_bandwidth_frequencies(*BAND, z, 3)
            return [FitData(f, truth_frf(pm, grids, dirs, p_true, f, z), model.output_names)]

        sur, _ = build_surrogate(model, np.zeros(pm.n_params), BAND)
        cal = calibrate(sur, data(0.01), pm.lower, pm.upper, 0.01, n_starts=0,
                        continuation=[(0.08, data(0.08)), (0.03, data(0.03))])
        results[units] = cal
    a, b = results["mm-t-s"], results["si"]
    np.testing.assert_allclose(a.p, b.p, atol=1e-4)  # 0.01 % of P0; optimizer tolerance level
    assert abs(a.sd - b.sd) < 1e-9 + 1e-6 * a.sd
    assert a.sd < 1e-3 * a.sd_nominal
