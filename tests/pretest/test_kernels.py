"""Metrics, drive-point ranking and mass loading on manufactured systems with known answers."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla

from pretest import (
    PretestError,
    automac,
    layout_metrics,
    mac,
    mass_loading_shifts,
    rank_drive_points,
)
from tests.pretest._problems import chain_system, plate_modes


def test_mac_known_values():
    a = np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]])
    b = np.array([[1.0, 1.0], [1.0, 0.0], [0.0, 0.0]])
    np.testing.assert_allclose(mac(a, b), [[0.5, 1.0], [0.5, 0.0]])
    # invariant to scaling, complex shapes allowed
    np.testing.assert_allclose(mac(3j * a, -2 * b), mac(a, b))
    am = automac(b)
    np.testing.assert_allclose(np.diag(am), 1.0)
    assert am[0, 1] == pytest.approx(0.5)


def test_layout_metrics_orthogonal_and_angle():
    eye = np.eye(4)
    m = layout_metrics(2.0 * eye)
    assert m.fim_condition == pytest.approx(1.0)
    assert m.automac_max_offdiag == pytest.approx(0.0)
    np.testing.assert_allclose(m.mode_independence, 1.0)
    assert m.fim_log10_det == pytest.approx(4 * np.log10(4.0))
    # two modes at angle theta: independence = sin^2(theta), MAC = cos^2(theta)
    theta = 0.3
    p = np.array([[1.0, np.cos(theta)], [0.0, np.sin(theta)], [0.0, 0.0]])
    m = layout_metrics(p)
    np.testing.assert_allclose(m.mode_independence, np.sin(theta) ** 2, rtol=1e-12)
    assert m.automac_max_offdiag == pytest.approx(np.cos(theta) ** 2)
    assert m.automac_worst_pair == (0, 1)
    # condition of the normalized FIM [[1, c], [c, 1]] is (1 + c) / (1 - c)
    c = np.cos(theta)
    assert m.fim_condition == pytest.approx((1 + c) / (1 - c))


def test_layout_metrics_singular_layout_reported_not_raised():
    p = np.array([[1.0, 2.0], [2.0, 4.0]])
    m = layout_metrics(p)
    assert m.fim_log10_det == -np.inf and m.fim_condition == np.inf
    assert m.automac_max_offdiag == pytest.approx(1.0)
    d = m.as_dict()
    assert d["fim_condition"] is None


def test_drive_at_nodal_line_ranks_last_and_adpr_formula():
    phi, xyz, pairs = plate_modes(nx=11, ny=9, n_modes=6)
    f = np.array([(m / 1.0) ** 2 + (n / 0.7) ** 2 for m, n in pairs]) * 10.0
    rk = rank_drive_points(phi, f)
    expect = (phi**2 / (2 * np.pi * f)).sum(axis=1)
    np.testing.assert_allclose(rk.adpr, expect)
    # the plate's centre line x = a/2 is nodal for every m = 2 mode: weakest participation 0 there
    centre = np.flatnonzero(np.isclose(xyz[:, 0], 0.5))
    assert centre.size and np.all(rk.weakest[centre] < 1e-12)
    rank_of = np.empty(rk.order.size, dtype=int)
    rank_of[rk.order] = np.arange(rk.order.size)
    assert rank_of[centre].min() >= np.count_nonzero(rk.weakest > 1e-12)
    assert rk.weakest[rk.order[0]] > 0.1
    assert np.all(np.diff(rk.weakest[rk.order]) <= 1e-15)
    # participation is relative to each mode's best drive point
    np.testing.assert_allclose(rk.participation.max(axis=0), 1.0)


def test_drive_ranking_rejects_rigid_modes_and_unknown_criterion():
    phi, _, _ = plate_modes(n_modes=3)
    with pytest.raises(PretestError, match="elastic"):
        rank_drive_points(phi, [0.0, 10.0, 20.0])
    with pytest.raises(PretestError, match="criterion"):
        rank_drive_points(phi, [5.0, 10.0, 20.0], criterion="best")


def test_mass_loading_first_order_matches_exact_eigenvalues():
    K, M = chain_system(n=8)
    w2, phi = sla.eigh(K, M)
    f = np.sqrt(w2) / (2 * np.pi)
    j, dm = 5, 0.002  # 2 g on a ~0.6 kg mass
    u = np.zeros((1, 3, 8))
    u[0, 0] = phi[j]
    ml = mass_loading_shifts(f, u, [dm])
    M2 = M.copy()
    M2[j, j] += dm
    f_exact = np.sqrt(sla.eigh(K, M2, eigvals_only=True)) / (2 * np.pi)
    exact_shift = f_exact - f
    # first-order: error is second order in the mass ratio (~(dm/m)^2 ~ 1e-5 relative)
    np.testing.assert_allclose(ml.shift_hz, exact_shift, rtol=0.02, atol=1e-6 * f.max())
    assert np.all(ml.shift_hz <= 0)
    # a mode with a node at the loaded DOF is not shifted; mass along y/z loads too
    u2 = np.zeros((1, 3, 8))
    u2[0, 1] = phi[j]
    np.testing.assert_allclose(mass_loading_shifts(f, u2, dm).shift_hz, ml.shift_hz)


def test_mass_loading_bad_input():
    with pytest.raises(PretestError, match="translations"):
        mass_loading_shifts([1.0, 2.0], np.zeros((2, 3, 3)), 0.001)
    with pytest.raises(PretestError, match=">= 0"):
        mass_loading_shifts([1.0], np.zeros((1, 3, 1)), -1.0)
