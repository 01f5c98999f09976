"""Caches the calibration keeps: on its own FRFModel (factorization) and in AffineMatrix.cache (local terms)."""

import pickle

import numpy as np

from calibration import build_surrogate
from tests.calibration._models import beam_model


def test_factor_cache_is_an_explicit_slot_that_stays_in_process():
    model, _ = beam_model(n_el=12, sensors=[0, 3, 6, 9, 12])
    assert model.factor_cache == {}
    slot = model.factor_cache
    slot["kept"] = True  # what a cycle stores there (symbolic factorization, pattern union) stays for the next
    sur1, T1 = build_surrogate(model, np.zeros(7), (20.0, 400.0))
    assert model.factor_cache is slot and slot["kept"]
    assert not any(k.startswith("_") for k in vars(model))  # nothing written behind the dataclass's back
    # the local term tables are kept with the full-order matrices they come from
    assert "calibration.local_halves" in model.K.cache and "calibration.local_halves" in model.M.cache
    sur2, T2 = build_surrogate(model, np.zeros(7), (20.0, 400.0))
    np.testing.assert_allclose(sur2.K.at(np.zeros(7)), sur1.K.at(np.zeros(7)), rtol=1e-12, atol=1e-9)
    shipped = pickle.loads(pickle.dumps(model))
    assert shipped.factor_cache == {} and model.factor_cache  # not sent to worker processes
    assert shipped.input_names == model.input_names
