"""A surrogate extended with added term families: accuracy against the full model, and calibrating the terms.

The truth is the extended model itself at known magnitudes (a contact spring
between two parts, a sensor mass, a spring to ground and a stiffness factor
on a few elements); its noise-free FRFs are fitted with the surrogate of the
original model extended by :func:`calibration.extended_surrogate`.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import femodel
from calibration import (
    CalibrationError,
    FitData,
    FRFModel,
    Objective,
    build_surrogate,
    calibrate,
    extended_surrogate,
    full_order_frf,
    half_bandwidth_frequencies,
    surrogate_frf,
)
from calibration._surrogate import _projected
from femodel import AddedMass, AddedSpring, ElementFactor, example_subframe, parametric_model
from tests.calibration._synthetic import DRIVE, layout
from tests.femodel.test_terms import FRAME_P, FRAME_PARAMS, FRAME_TERMS, frame_deck

ZETA = 0.01
SCHEDULE = (0.08, 0.03)


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    """Frame models before/after the terms, with oblique sensors and drives (every channel sees every mode)."""
    d = tmp_path_factory.mktemp("frame_ext")
    pm = parametric_model(FRAME_PARAMS, frame_deck(d / "frame.bdf"))
    ext = pm.with_terms(FRAME_TERMS)
    grids = [3, 5, 13, 15, 22, 24, 16, 6]
    dirs = _unit([[0.3, 0.4, 0.866], [0.5, -0.6, 0.62], [-0.4, 0.3, 0.866], [0.7, 0.5, 0.5],
                  [0.2, 0.6, 0.77], [0.6, 0.6, -0.5], [0.1, -0.5, 0.86], [-0.6, 0.2, 0.77]])
    C = femodel.sensor_matrix(pm.assembly, grids, dirs)
    B = femodel.sensor_matrix(pm.assembly, [3, 15], _unit([[0.48, 0.36, 0.8], [0.6, 0.64, 0.48]])).T
    band = (5.0, 400.0)
    m0 = FRFModel(pm.K, pm.M, B, C, parameter_names=pm.names, parametric=pm)
    m1 = FRFModel(ext.K, ext.M, B, C, parameter_names=ext.names, parametric=ext)
    sur, T = build_surrogate(m0, np.zeros(pm.n_params), band)
    sur1, T1 = extended_surrogate(sur, T, m1, shift_hz=max(band[0] / 4, band[1] / 50))
    return pm, ext, m1, band, sur, T, sur1, T1


def _data(ref, p, band, zeta):
    f = half_bandwidth_frequencies(*band, zeta, 3)
    return ref(p, f, zeta), f


def test_extended_basis_is_M_orthonormal_and_keeps_the_old_one(frame):
    pm, ext, m1, band, sur, T, sur1, T1 = frame
    M0 = ext.mass(np.zeros(ext.n_params))
    np.testing.assert_allclose(T1.T @ (M0 @ T1), np.eye(T1.shape[1]), atol=1e-10)
    assert sur1.size > sur.size and sur1.n_static > sur.n_static
    assert sur1.parameter_names == ext.names and sur1.p_basis.shape == (ext.n_params,)
    # the old vectors stay (up to the final congruence, identity here)
    np.testing.assert_allclose(T1[:, :sur.size], T, atol=1e-9 * np.abs(T).max())


def test_extended_surrogate_matches_full_order_frf(frame):
    pm, ext, m1, band, sur, T, sur1, T1 = frame
    f = np.linspace(band[0], band[1], 400)
    H = full_order_frf(m1, FRAME_P, f, ZETA)
    Hs = surrogate_frf(sur1, FRAME_P, f, ZETA)
    err = np.abs(Hs / H - 1)
    assert err.max() < 0.01, err.max()
    # the terms matter (the FRFs move by far more than the error) ...
    H0 = full_order_frf(m1, np.r_[FRAME_P[:3], 0, 0, 0, 0], f, ZETA)
    assert np.median(np.abs(H0 / H - 1)) > 30 * np.median(err)
    # ... and the static corrections are what carries them: the old basis alone is far worse
    sur_p = replace(sur, K=_projected(ext.K, T), M=_projected(ext.M, T), p_basis=np.zeros(ext.n_params),
                    parameter_names=ext.names)
    err_p = np.abs(surrogate_frf(sur_p, FRAME_P, f, ZETA) / H - 1)
    assert err_p.max() > 10 * err.max()


def test_extension_without_its_basis_is_the_same_reduced_model(frame):
    """``with_basis=False`` orthogonalizes the new columns once in full space and leaves the rest to the
    reduced congruence, without forming them: the same surrogate (FRF, reduced modes) as with the basis.
    Not to round-off: the rank cut (vector_rtol) keeps the directions of the new columns' Gram matrix above
    1e-10 of its largest eigenvalue, and a round-off change of that matrix turns the kept ones by up to
    round-off / 1e-10 (measured: FRF 1e-7 relative at most)."""
    pm, ext, m1, band, sur, T, sur1, T1 = frame
    sur2, T2 = extended_surrogate(sur, T, m1, shift_hz=max(band[0] / 4, band[1] / 50), with_basis=False)
    assert T2 is None and sur2.size == sur1.size
    f = np.linspace(band[0], band[1], 400)
    H1, H2 = surrogate_frf(sur1, FRAME_P, f, ZETA), surrogate_frf(sur2, FRAME_P, f, ZETA)
    np.testing.assert_allclose(H2, H1, rtol=1e-6, atol=1e-6 * np.abs(H1).max())
    from calibration._surrogate import reduced_modes

    lam1, _ = reduced_modes(sur1, FRAME_P)
    lam2, _ = reduced_modes(sur2, FRAME_P)
    np.testing.assert_allclose(lam2, lam1, rtol=1e-7, atol=1e-6)


def test_calibration_recovers_the_added_terms_on_the_frame(frame):
    pm, ext, m1, band, sur, T, sur1, T1 = frame

    def ref(p, f, z):
        return full_order_frf(m1, p, f, z)

    H, f = _data(ref, FRAME_P, band, ZETA)
    data = [FitData(f, H, m1.output_names)]
    cont = []
    for z in SCHEDULE:
        Hz, fz = _data(ref, FRAME_P, band, z)
        cont.append((z, [FitData(fz, Hz, m1.output_names)]))
    assert Objective(sur1, data, ZETA).sd(FRAME_P) < 1e-8
    # diagnosis hands candidates over at a screening magnitude; existing parameters start nominal
    start = np.r_[0, 0, 0, 0.5, 0.5, 0.5, 0]
    cal = calibrate(sur1, data, ext.lower, ext.upper, ZETA, n_starts=0, continuation=cont, p_start=start)
    phys, truth = ext.physical(cal.p), ext.physical(FRAME_P)
    for name in ext.names:
        assert phys[name] == pytest.approx(truth[name], rel=0.01), name
    assert cal.sd < 1e-8


@pytest.fixture(scope="module")
def subframe(tmp_path_factory):
    d = tmp_path_factory.mktemp("subframe_ext")
    ex = example_subframe(d, 3000)
    pm = parametric_model(ex.params)
    fe = pm.assembly.model
    quads = fe.elements["CQUAD4"]

    def grids_of(pid):
        return np.unique(quads["nodes"][quads["pid"] == pid])

    arm, bracket = grids_of(8), grids_of(4)  # arm RHS, bracket RHS
    ga, gb = int(arm[len(arm) // 2]), int(bracket[len(bracket) // 2])
    terms = (
        AddedSpring("k_contact", ((ga, 3, gb, 3), (ga, 2, gb, 2)), 1e5),
        AddedMass("m_sensor", (int(bracket[0]),), 0.05),
        AddedSpring("k_ground", ((int(fe.grid_ids[0]), 3, 0, 0),), 1e4),
        ElementFactor("f_web", tuple(int(e) for e in quads.ids[quads["pid"] == 3][:12])),
    )
    ext = pm.with_terms(terms)
    grids, dirs = layout(pm)
    C = femodel.sensor_matrix(pm.assembly, grids, dirs)
    B = C[[DRIVE]].T
    band = (20.0, 400.0)
    m0 = FRFModel(pm.K, pm.M, B, C, parameter_names=pm.names, parametric=pm)
    m1 = FRFModel(ext.K, ext.M, B, C, parameter_names=ext.names, parametric=ext)
    sur, T = build_surrogate(m0, np.zeros(pm.n_params), band)
    sur1, _ = extended_surrogate(sur, T, m1, shift_hz=max(band[0] / 4, band[1] / 50))

    def ref(p, f, z):
        """Reference FRFs of the extended full model: a fresh basis at p with modes to 4x the band top.

        (The shell model's lumped mass has no rotary inertia, so the dense
        ``full_order_frf`` does not apply.)"""
        s, _ = build_surrogate(m1, p, band, basis_factor=4.0, enrich=False)
        return surrogate_frf(s, p, f, z)

    return pm, ext, m1, band, sur1, ref


def test_subframe_extended_surrogate_and_calibration(subframe):
    pm, ext, m1, band, sur1, ref = subframe
    p_true = np.r_[np.zeros(pm.n_params), 0.8, 1.2, 0.6, -0.3]
    f = np.linspace(band[0], band[1], 300)
    H = ref(p_true, f, ZETA)
    err = np.abs(surrogate_frf(sur1, p_true, f, ZETA) / H - 1)
    assert err.max() < 0.01, err.max()
    Hc, fc = _data(ref, p_true, band, ZETA)
    data = [FitData(fc, Hc, m1.output_names)]
    cont = []
    for z in SCHEDULE:
        Hz, fz = _data(ref, p_true, band, z)
        cont.append((z, [FitData(fz, Hz, m1.output_names)]))
    start = np.r_[np.zeros(pm.n_params), 0.5, 0.5, 0.5, 0.0]
    cal = calibrate(sur1, data, ext.lower, ext.upper, ZETA, n_starts=0, continuation=cont, p_start=start)
    phys, truth = ext.physical(cal.p), ext.physical(p_true)
    for name in ext.names[pm.n_params:]:
        assert phys[name] == pytest.approx(truth[name], rel=0.01), name
    np.testing.assert_allclose(cal.p[:pm.n_params], 0.0, atol=0.01)


def test_extended_surrogate_rejects_a_mismatched_model(frame):
    pm, ext, m1, band, sur, T, sur1, T1 = frame
    with pytest.raises(CalibrationError, match="basis is"):
        extended_surrogate(sur, T[:, :-1], m1, shift_hz=1.0)
    with pytest.raises(CalibrationError, match="shift_hz"):
        extended_surrogate(sur, T, m1)
    other = pm.with_terms([AddedMass("m", (3,), 0.1)])
    bad = FRFModel(other.K, other.M, m1.inputs, m1.outputs, parameter_names=("E", "x", "m_tip", "m"))
    with pytest.raises(CalibrationError, match="first parameters"):
        extended_surrogate(sur, T, bad, shift_hz=1.0)
