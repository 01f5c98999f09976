"""A stiff effect seen from a basis built with it: the "without it" model must come from a basis that holds it.

The diagnose stage refines an accepted effect on a surrogate of the extended deck built at the refined point.
A contact refined to its upper bound (a near-rigid tie) makes every vector of that basis move the tied DOF
together: on it, setting the magnitude to 0 hardly changes the model, and the effect looked negligible and
was dropped while it explained the data (200k-DOF example, stop 31). ``refined_sizes`` evaluates the model
without the effect on the acceptance fit's surrogate (the calibrated basis extended by the effect's static
corrections: exact at c = 0); here its mode shift is checked against full-order eigenvalues.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla

import femodel
from calibration import FRFModel, build_surrogate, extended_surrogate
from femodel import AddedSpring, parametric_model
from calibration import reduced_modes
from frfcal.campaign._diagnose import _damping_on, _mode_shift
from tests.femodel.test_terms import FRAME_PARAMS, frame_deck


def _full_shift(ext, x, x0, band) -> float:
    """_mode_shift's measure on the full-order eigenvalues."""
    f1, f0 = [np.sqrt(np.clip(sla.eigh(ext.stiffness(v).toarray(), ext.mass(v).toarray(), eigvals_only=True),
                              0, None)) / (2 * np.pi) for v in (x, x0)]
    use = (f0 > 1.0) & (f0 >= band[0]) & (f0 <= band[1])
    return float(np.max(np.abs(f1[use] / f0[use] - 1.0)))


def test_a_stiff_tie_is_not_seen_as_negligible_from_its_own_basis(tmp_path):
    pm = parametric_model(FRAME_PARAMS, frame_deck(tmp_path / "frame.bdf"))
    tie = AddedSpring("k_tie", ((24, 3, 5, 3), (24, 1, 5, 1), (24, 2, 5, 2)), 1e5, upper=1e4)
    ext = pm.with_terms([tie])
    C = femodel.sensor_matrix(pm.assembly, [3, 5, 13, 15, 22, 24, 16, 6], np.tile([0.3, 0.4, 0.866], (8, 1)))
    B = femodel.sensor_matrix(pm.assembly, [3], [[0.48, 0.36, 0.8]]).T
    band = (5.0, 400.0)
    m0 = FRFModel(pm.K, pm.M, B, C, parameter_names=pm.names, parametric=pm)
    m1 = FRFModel(ext.K, ext.M, B, C, parameter_names=ext.names, parametric=ext)
    sur, T = build_surrogate(m0, np.zeros(pm.n_params), band)
    fit_sur, _ = extended_surrogate(sur, T, m1, shift_hz=max(band[0] / 4, band[1] / 50))  # the acceptance fit's
    x = np.r_[np.zeros(pm.n_params), tie.upper]  # refined to its upper bound: 1e9 N/m, a rigid tie
    x0 = np.zeros(ext.n_params)
    refined, _ = build_surrogate(m1, x, band)  # the refinement's basis, built with the tie in place
    true = _full_shift(ext, x, x0, band)
    assert true > 0.5  # the tie moves the modes by far more than any tolerance
    assert _mode_shift(refined, x, x0, band, fit_sur) == pytest.approx(true, rel=1e-6)
    # from its own basis the tie looks half as large: the defect the stage no longer has
    assert abs(_mode_shift(refined, x, x0, band) / true - 1.0) > 0.3

    # the refinement's damping (per mode of the refined surrogate) carried to the other basis by frequency:
    # every mode of the fit's surrogate gets the damping of its counterpart
    f_ref = np.sqrt(np.clip(reduced_modes(refined, x)[0], 0, None))
    zeta = 1e-3 * (1.0 + np.arange(f_ref.size))  # distinct per mode
    (z0,), p_ref = _damping_on(refined, fit_sur, ([zeta], x))
    f_fit = np.sqrt(np.clip(reduced_modes(fit_sur, x)[0], 0, None))
    assert z0.shape == f_fit.shape and p_ref is x
    k = np.flatnonzero((f_ref / (2 * np.pi) > 1.0) & (f_ref / (2 * np.pi) < band[1]))
    assert k.size >= 4
    np.testing.assert_allclose(f_fit[k], f_ref[k], rtol=1e-3)  # both bases hold the in-band modes
    np.testing.assert_array_equal(z0[k], zeta[k])
    assert _damping_on(refined, fit_sur, None) is None
