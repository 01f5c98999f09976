"""A basis refreshed without a new factorization (corrected_basis) against a cold one and the full order."""

import numpy as np
import pytest
import scipy.linalg as sla

import calibration._surrogate as surrogate_module
from calibration import build_surrogate, full_order_frf, half_bandwidth_frequencies, reduced_modes, surrogate_frf
from tests.calibration._models import beam_model

BAND = (20.0, 400.0)
# far from the nominal point in every parameter, as a re-basis cycle after a calibration is
P_NEW = np.array([0.15, -0.12, 0.2, -0.18, 0.1, 0.25, -0.2])


def _in_band_frequencies(model, p, top_hz):
    K, M = model.stiffness(p), model.mass(p)
    lam = sla.eigh(K.toarray(), M.toarray(), eigvals_only=True)
    f = np.sqrt(np.clip(lam, 0, None)) / (2 * np.pi)
    return f[(f > 1.0) & (f <= top_hz)]


@pytest.fixture(scope="module", params=[40, 800], ids=["dense-450", "sparse-1600"])
def refreshed(request):
    """Nominal basis, then the corrected refresh at P_NEW (nominal factorization kept) and a cold build there."""
    n_el = request.param
    sensors = [int(round(x)) for x in np.linspace(0, n_el, 10)]
    model, _ = beam_model(n_el=n_el, sensors=sensors)
    sur0, T0 = build_surrogate(model, np.zeros(7), BAND)
    p_factor = model.factor_cache["refresh_factor"]["p"].copy()
    sur1, T1 = build_surrogate(model, P_NEW, BAND, previous_basis=T0, previous_surrogate=sur0)
    kept_p = model.factor_cache["refresh_factor"]["p"].copy()
    cold, _ = build_surrogate(model, P_NEW, BAND)
    return model, sur0, sur1, T1, cold, p_factor, kept_p


def test_corrected_refresh_makes_no_factorization(refreshed):
    model, sur0, sur1, T1, _, p_factor, kept_p = refreshed
    np.testing.assert_array_equal(kept_p, p_factor)  # still the nominal factorization
    assert "correction steps (no factorization)" in sur1.timings_s
    assert sur1.size > sur0.size  # the old basis plus its corrections
    np.testing.assert_allclose(sur1.p_basis, P_NEW)
    M1 = model.mass(P_NEW)
    np.testing.assert_allclose(T1.T @ (M1 @ T1), np.eye(T1.shape[1]), atol=1e-8)


def test_corrected_refresh_gets_the_modes_at_the_new_point(refreshed):
    """In-band frequencies at P_NEW: the nominal basis is off by 1e-6..1e-5, the corrected one agrees with a
    basis built from scratch there (Lanczos modes at P_NEW) to 1e-7 (step_tol 1e-4 squared is 1e-8)."""
    model, sur0, sur1, _, cold, _, _ = refreshed

    def freqs(sur):
        lam, _ = reduced_modes(sur, P_NEW)
        f = np.sqrt(np.clip(lam, 0, None)) / (2 * np.pi)
        return f[(f > 1.0) & (f <= 1.25 * BAND[1])]

    ref = freqs(cold)
    assert ref.size == 5
    if model.K.shape[0] <= 1500:  # the dense path's modes are exact: so is the cold surrogate's
        np.testing.assert_allclose(ref, _in_band_frequencies(model, P_NEW, 1.25 * BAND[1]), rtol=1e-9)
    e0 = np.max(np.abs(freqs(sur0)[: ref.size] / ref - 1))
    e1 = np.max(np.abs(freqs(sur1)[: ref.size] / ref - 1))
    assert e0 > 1e-6  # the refresh has something to do
    assert e1 < 1e-7 and e1 < 1e-2 * e0


def test_corrected_refresh_frf_matches_full_order_and_cold_build(refreshed):
    model, sur0, sur1, _, cold, _, _ = refreshed
    f = half_bandwidth_frequencies(*BAND, 0.01, 3)
    Hf = full_order_frf(model, P_NEW, f, 0.01)

    def rel(sur):
        return np.max(np.abs(surrogate_frf(sur, P_NEW, f, 0.01) - Hf) / np.abs(Hf))

    e0, e1, ec = rel(sur0), rel(sur1), rel(cold)
    assert e1 < 2e-3
    assert e1 < 0.2 * e0
    assert e1 < 2 * ec + 1e-4  # as good as a basis built from scratch at the new point


def test_a_point_far_from_the_factorization_is_refactorized():
    """30 % in every parameter: the kept nominal factorization would converge too slowly, so the refresh
    factorizes at the new point (and keeps that factorization); the basis is then as good as a cold one."""
    p_far = np.array([0.3, -0.3, 0.3, -0.3, 0.3, 0.3, -0.3])
    model, _ = beam_model(n_el=800, sensors=list(range(0, 801, 80)))
    sur0, T0 = build_surrogate(model, np.zeros(7), BAND)
    sur1, _ = build_surrogate(model, p_far, BAND, previous_basis=T0, previous_surrogate=sur0)
    assert "correction steps (refactorized)" in sur1.timings_s
    np.testing.assert_allclose(model.factor_cache["refresh_factor"]["p"], p_far)
    cold, _ = build_surrogate(model, p_far, BAND)
    f = half_bandwidth_frequencies(*BAND, 0.01, 3)
    Hf = full_order_frf(model, p_far, f, 0.01)

    def rel(sur):
        return np.max(np.abs(surrogate_frf(sur, p_far, f, 0.01) - Hf) / np.abs(Hf))

    assert rel(sur1) < 2 * rel(cold) + 1e-4
    assert rel(sur1) < 0.2 * rel(sur0)


def test_corrected_basis_steps_shrink_and_a_refactorization_is_reported():
    """Each correction step leaves a much smaller one; forcing the refactorization calls it once."""
    model, _ = beam_model(n_el=800, sensors=list(range(0, 801, 80)))
    sur0, T0 = build_surrogate(model, np.zeros(7), BAND)
    kept = model.factor_cache["refresh_factor"]
    B = np.asarray(model.inputs, float)
    C = model.outputs.toarray()
    args = (model.stiffness(P_NEW), model.mass(P_NEW), T0, sur0.K.at(P_NEW), sur0.M.at(P_NEW), kept["solve"],
            kept["static"], np.hstack([B, C.T]), 1.25 * BAND[1], kept["shift_hz"])
    T, n_modes, n_static, steps, refactored = surrogate_module.corrected_basis(*args, step_tol=1e-6, max_steps=3)
    assert not refactored
    assert len(steps) >= 2
    assert steps[0] > 1e-3  # the nominal basis is visibly off at P_NEW
    assert all(b < 0.3 * a for a, b in zip(steps, steps[1:]))
    assert n_modes > 0
    assert T.shape[1] == T0.shape[1] + n_modes + n_static
    calls = []

    def refactor():
        calls.append(1)
        return kept["solve"], kept["static"]

    *_, refactored = surrogate_module.corrected_basis(*args, refactor=refactor, refactor_step=0.0)
    assert refactored and len(calls) == 1
