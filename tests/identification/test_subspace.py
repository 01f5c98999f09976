"""Manufactured truth: subspace identification, labels, equalization, storage."""

from __future__ import annotations

import numpy as np
import pytest

from identification import (
    Identification,
    IdentificationError,
    StateSpace,
    equalized,
    identify,
    mac,
    square_deviation,
    to_continuous,
    to_discrete,
)
from tests.identification.synthetic import ring


def _random_stable(n_modes=4, p=3, m=2, seed=1, real_pole=True):
    rng = np.random.default_rng(seed)
    f = np.sort(rng.uniform(150, 500, n_modes))
    z = rng.uniform(0.002, 0.02, n_modes)
    blocks = []
    for fi, zi in zip(f, z):
        w = 2 * np.pi * fi
        s, wd = -zi * w, w * np.sqrt(1 - zi**2)
        blocks.append(np.array([[s, wd], [-wd, s]]))
    if real_pole:
        blocks.append(np.array([[-2 * np.pi * 300.0]]))
    from scipy.linalg import block_diag

    A = block_diag(*blocks)
    n = A.shape[0]
    T = rng.standard_normal((n, n))  # hide the modal form
    A = T @ A @ np.linalg.inv(T)
    return StateSpace(A, rng.standard_normal((n, m)) * 1e3, rng.standard_normal((p, n)), rng.standard_normal((p, m)))


def test_bilinear_map_is_exact_both_ways():
    sys = _random_stable()
    alpha = 2 * np.pi * 300.0
    Ad, Bd, Cd, Dd = to_discrete(sys.A, sys.B, sys.C, sys.D, alpha)
    A, B, C, D = to_continuous(Ad, Bd, Cd, Dd, alpha)
    for x, y in ((A, sys.A), (B, sys.B), (C, sys.C), (D, sys.D)):
        np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-9 * np.abs(y).max())
    # same FRF: H_c(i w) == H_d(z), z = (alpha + i w)/(alpha - i w)
    w = 2 * np.pi * np.array([120.0, 333.0, 710.0])
    z = (alpha + 1j * w) / (alpha - 1j * w)
    Hd = np.array([Cd @ np.linalg.solve(zk * np.eye(Ad.shape[0]) - Ad, Bd) + Dd for zk in z])
    np.testing.assert_allclose(Hd, sys.frf(w / (2 * np.pi)), rtol=1e-9)


def test_noise_free_model_is_recovered_exactly_on_a_random_grid():
    sys = _random_stable()
    rng = np.random.default_rng(5)
    f = np.sort(rng.uniform(100, 600, 400))  # non-uniform grid
    H = sys.frf(f)
    r = identify(f, H, sys.n_states, quantity="receptance", zeta_max=1.1)
    true = sys.poles()
    got = r.model.poles()
    np.testing.assert_allclose(np.sort_complex(got), np.sort_complex(true), rtol=1e-8)
    np.testing.assert_allclose(r.model.frf(f), H, rtol=1e-7, atol=1e-9 * np.abs(H).max())
    # D is estimated, and evaluation at frequencies never measured matches the truth
    np.testing.assert_allclose(r.model.D, sys.D, rtol=1e-6, atol=1e-8)
    f_new = np.array([50.0, 777.0, 2000.0])
    np.testing.assert_allclose(r.frf(f_new), sys.frf(f_new), rtol=1e-6)
    assert r.model.quantity == "receptance"
    assert r.poles.count("real") == 1


def test_dual_orientation_gives_the_same_model():
    sys = _random_stable(p=1, m=6, real_pole=False)
    f = np.linspace(100, 600, 500)
    H = sys.frf(f)
    r = identify(f, H, sys.n_states)
    assert r.settings["dual"] is True
    assert r.model.n_out == 1 and r.model.n_in == 6
    np.testing.assert_allclose(np.sort_complex(r.model.poles()), np.sort_complex(sys.poles()), rtol=1e-8)
    np.testing.assert_allclose(r.model.frf(f), H, rtol=1e-7)


@pytest.fixture(scope="module")
def truth():
    return ring()


@pytest.fixture(scope="module")
def ident40(truth):
    return identify(truth.freq_hz, truth.H, 40, band_hz=(100, 550))


def _check_against_truth(r, truth, f_tol=1e-4, z_tol=0.05, min_mac=0.99):
    fm = r.modal.frequency_hz
    assert fm.size == truth.f_n.size, (fm, truth.f_n)
    assert np.max(np.abs(fm - truth.f_n) / truth.f_n) < f_tol
    assert np.max(np.abs(r.modal.damping - truth.zeta) / truth.zeta) < z_tol
    assert np.min(np.diag(mac(r.modal.shapes, truth.shapes))) > min_mac


def test_ring_truth_recovered(truth, ident40):
    # 20 modes 120-520 Hz, pairs 0.13-0.7 % apart (about 1-3 half-power bandwidths), zeta 0.1 %,
    # 20 outputs x 2 inputs, accelerance, 0.5 % noise
    spacing = np.diff(truth.f_n) / truth.f_n[:-1]
    assert spacing.min() < 3 * 2 * truth.zeta[0]  # the test really has close modes
    _check_against_truth(ident40, truth)
    assert np.all(ident40.poles.physical)
    # the model fits the noisy data to the noise level: 0.5 % noise -> SD ~ (0.005/ln10)^2
    assert ident40.fit_deviation_total < 3 * (0.005 / np.log(10)) ** 2 * 10
    assert ident40.fit_deviation.shape == (20, 2)


@pytest.mark.parametrize("order", [80, 120])
def test_overmodelling_adds_no_physical_pole(truth, order):
    r = identify(truth.freq_hz, truth.H, order, band_hz=(100, 550))
    _check_against_truth(r, truth)
    assert r.poles.count("physical") == 20
    assert len(r.poles) > 20  # the extra poles are kept in the model, labelled
    assert r.poles.physical.sum() + sum(1 for s in r.poles.labels if s != "physical") == len(r.poles)


def test_per_line_standard_errors_as_weights(truth):
    r = identify(truth.freq_hz, truth.H, 40, band_hz=(100, 550), weights=truth.sigma)
    _check_against_truth(r, truth)


def test_per_output_noise_levels_as_weights(truth):
    noise = np.sqrt(np.mean(truth.sigma**2, axis=(0, 2)))
    r = identify(truth.freq_hz, truth.H, 40, band_hz=(100, 550), weights=noise)
    _check_against_truth(r, truth)


def test_equalized_has_exactly_zeta0_on_physical_poles(truth, ident40):
    zeta0 = 0.01
    eq = equalized(ident40, zeta0)
    lam = eq.poles()
    lam = lam[lam.imag > 0]
    np.testing.assert_allclose(-lam.real / np.abs(lam), zeta0, rtol=1e-12)
    # the oscillation frequency Im(lambda) is kept
    np.testing.assert_allclose(np.sort(lam.imag), np.sort(ident40.modal.eigenvalues.imag), rtol=1e-12)
    # paper Eq. 2.10-2.11 literally
    eqp = equalized(ident40, zeta0, definition="paper")
    lp = eqp.poles()
    lp = lp[lp.imag > 0]
    np.testing.assert_allclose(-lp.real / lp.imag, zeta0, rtol=1e-12)
    # evaluation anywhere; at zeta0 = 1 % the peaks drop by about zeta/zeta0 = 10x
    f = np.linspace(100, 550, 5000)
    He = eq.frf(f)
    Hi = ident40.frf(f)
    assert He.shape == (5000, 20, 2)
    assert np.max(np.abs(He)) < 0.3 * np.max(np.abs(Hi))
    # equalizing back to each pole's own damping reproduces the model
    same = equalized(ident40.model, float(ident40.modal.damping[0]), physical=ident40.modal.eigenvalues[:1])
    np.testing.assert_allclose(same.frf(f), Hi, rtol=1e-8, atol=1e-10 * np.abs(Hi).max())


def test_equalized_leaves_real_and_residual_poles_alone():
    sys = _random_stable(real_pole=True)
    f = np.linspace(100, 600, 500)
    # the top mode lies above the 100-420 Hz band: a residual ("out-of-band") pole
    r = identify(f, sys.frf(f), sys.n_states, band_hz=(100, 420), zeta_max=1.1)
    r2 = r
    assert r.poles.count("out-of-band") >= 1 and r.poles.count("real") == 1
    eq = equalized(r2, 0.05)
    before = np.sort_complex(r.model.poles())
    after = np.sort_complex(eq.poles())
    real_before = before[before.imag == 0]
    real_after = after[after.imag == 0]
    np.testing.assert_allclose(real_after, real_before, rtol=1e-10)
    # only the poles labelled physical moved
    phys = r2.poles.eigenvalues[r2.poles.physical]
    others = r2.poles.eigenvalues[~r2.poles.physical & (r2.poles.eigenvalues.imag > 0)]
    for lam in others:
        assert np.min(np.abs(after - lam)) < 1e-8 * abs(lam)
    for lam in phys:
        assert np.min(np.abs(after - lam)) > 1e-6 * abs(lam)
    with pytest.raises(IdentificationError, match="real"):
        equalized(r.model, 0.05, physical=real_before)


def test_square_deviation_values():
    rng = np.random.default_rng(0)
    H = rng.standard_normal((50, 3, 2)) + 1j * rng.standard_normal((50, 3, 2))
    assert square_deviation(H, H) == pytest.approx(0.0, abs=1e-30)
    assert square_deviation(10 * H, H) == pytest.approx(1.0)
    phi = 0.3
    assert square_deviation(H * np.exp(1j * phi), H) == pytest.approx((phi / np.log(10)) ** 2)
    with pytest.raises(IdentificationError, match="shape"):
        square_deviation(H, H[:-1])


def test_to_arrays_round_trip(ident40):
    arrays, attrs = ident40.to_arrays()
    assert all(isinstance(v, np.ndarray) for v in arrays.values())
    back = Identification.from_arrays(arrays, attrs)
    np.testing.assert_array_equal(back.model.A, ident40.model.A)
    assert back.poles.labels == ident40.poles.labels
    assert back.band_hz == ident40.band_hz and back.order == 40
    np.testing.assert_array_equal(back.modal.shapes, ident40.modal.shapes)
    np.testing.assert_allclose(equalized(back, 0.02).A, equalized(ident40, 0.02).A)
    with pytest.raises(IdentificationError, match="lacks field 'A'"):
        Identification.from_arrays({k: v for k, v in arrays.items() if k != "A"}, attrs)


def test_bad_input_names_the_argument(truth):
    f, H = truth.freq_hz, truth.H
    with pytest.raises(IdentificationError, match="H has 1999 lines but freq_hz has 2000"):
        identify(f, H[:-1], 10)
    with pytest.raises(IdentificationError, match=r"H must be \(n_freq, n_out, n_in\)"):
        identify(f, H[:, :, 0], 10)
    with pytest.raises(IdentificationError, match="order must be a positive integer"):
        identify(f, H, 0)
    with pytest.raises(IdentificationError, match="band_hz"):
        identify(f, H, 10, band_hz=(600, 100))
    with pytest.raises(IdentificationError, match="weights"):
        identify(f, H, 10, weights=np.ones(3))
    Hn = H.copy()
    Hn[10, 0, 0] = np.nan
    with pytest.raises(IdentificationError, match="NaN/Inf at line 10"):
        identify(f, Hn, 10)
    valid = np.ones(f.size, bool)
    valid[10] = False
    identify(f, Hn, 10, valid=valid)  # invalid lines are skipped
    with pytest.raises(IdentificationError, match="too few lines"):
        identify(f[:5], H[:5], 30)
    with pytest.raises(IdentificationError, match="zeta0"):
        equalized(StateSpace(np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)), np.zeros((1, 1))), 1.5)


def test_unstable_pole_is_reflected_and_labelled():
    sys = _random_stable(real_pole=False, seed=3)
    Am, Bm, Cm = sys.A, sys.B, sys.C
    lam, X = np.linalg.eig(Am)
    k = int(np.argmax(lam.imag))  # make the top mode unstable (negative damping)
    lam_u = lam.copy()
    for i in range(lam.size):
        if np.isclose(lam[i], lam[k]) or np.isclose(lam[i], np.conj(lam[k])):
            lam_u[i] = complex(-lam[i].real, lam[i].imag)
    Au = (X @ np.diag(lam_u) @ np.linalg.inv(X)).real
    bad = StateSpace(Au, Bm, Cm, sys.D)
    f = np.linspace(100, 600, 400)
    H = bad.frf(f)
    free = identify(f, H, bad.n_states, enforce_stability=False)
    assert free.poles.count("unstable") == 1
    assert np.max(free.model.poles().real) > 0
    np.testing.assert_allclose(free.model.frf(f), H, rtol=1e-6)
    forced = identify(f, H, bad.n_states)
    assert forced.poles.count("unstable") == 1 and forced.settings["n_reflected"] == 1
    assert np.max(forced.model.poles().real) < 0
    i = forced.poles.labels.index("unstable")
    # reflection keeps the oscillation frequency and flips the sign of the real part
    assert abs(forced.poles.eigenvalues[i] - lam[k]) < 1e-6 * abs(lam[k])
    assert forced.modal.n_modes == bad.n_states // 2 - 1  # the unstable pole is not a mode
