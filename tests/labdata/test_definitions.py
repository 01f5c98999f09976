"""FRF quantities and their factor, MAC and its edge cases, the figure-saving default: each defined once."""

from __future__ import annotations

import struct
import warnings

import numpy as np
import pytest

from labdata import (
    CHANNEL_UNITS,
    FIGURE_DPI,
    FIGURE_FORMAT,
    FRF_QUANTITIES,
    RESPONSE_QUANTITY,
    LabDataError,
    check_frf_quantity,
    frf_quantity_of,
    mac,
    quantity_factor,
    quantity_power,
    save_figure,
)

# ---------------------------------------------------------------- quantities


def test_quantity_names_once_in_one_order():
    import acquisition._plant
    import acquisition.runfile
    import calibration._surrogate
    import identification._statespace

    assert FRF_QUANTITIES == ("accelerance", "mobility", "receptance")
    for module in (acquisition._plant, acquisition.runfile, identification._statespace):
        assert module.QUANTITIES is FRF_QUANTITIES
    assert calibration._surrogate._QUANTITIES is FRF_QUANTITIES
    assert [RESPONSE_QUANTITY[q] for q in FRF_QUANTITIES] == ["acceleration", "velocity", "displacement"]
    assert [frf_quantity_of(r) for r in ("acceleration", "velocity", "displacement")] == list(FRF_QUANTITIES)
    assert [CHANNEL_UNITS[RESPONSE_QUANTITY[q]] for q in FRF_QUANTITIES] == ["m/s^2", "m/s", "m"]
    assert CHANNEL_UNITS["force"] == "N"
    assert [quantity_power(q) for q in FRF_QUANTITIES] == [2, 1, 0]


def test_factor_is_the_time_derivative_for_e_plus_iwt():
    """x(t) = Re(X e^{+iwt}): velocity and acceleration by finite differences equal Re(q X e^{iwt})."""
    w, X = 2 * np.pi * 7.0, 0.3 - 0.8j
    t = np.linspace(0.0, 0.2, 20001)
    dt = t[1] - t[0]
    x = np.real(X * np.exp(1j * w * t))
    v = np.gradient(x, dt, edge_order=2)
    a = np.gradient(v, dt, edge_order=2)
    inner = slice(10, -10)
    for q, numeric in (("receptance", x), ("mobility", v), ("accelerance", a)):
        exact = np.real(quantity_factor(q, w) * X * np.exp(1j * w * t))
        scale = np.max(np.abs(exact))
        assert np.max(np.abs(numeric[inner] - exact[inner])) < 1e-4 * scale, q


def test_factor_values_exact_and_shaped():
    w = np.array([[0.0, 1.5], [2.0, 1e3]])
    acc = quantity_factor("accelerance", w)
    assert acc.shape == w.shape and acc.dtype == complex
    np.testing.assert_array_equal(acc.real, -(w**2))
    np.testing.assert_array_equal(acc.imag, 0.0)
    np.testing.assert_array_equal(quantity_factor("mobility", w), 1j * w)
    np.testing.assert_array_equal(quantity_factor("receptance", w), np.ones_like(w))


@pytest.mark.parametrize("call", [lambda: quantity_factor("inertance", 1.0), lambda: quantity_power("FRF"),
                                  lambda: check_frf_quantity("Accelerance", "run.quantity")])
def test_unknown_quantity_named(call):
    with pytest.raises(LabDataError, match=r"must be one of \('accelerance', 'mobility', 'receptance'\), got '\w+'"):
        call()


def test_response_quantity_of_force_is_refused():
    with pytest.raises(LabDataError, match=r"response quantity must be one of .* got 'force'"):
        frf_quantity_of("force")


# ---------------------------------------------------------------------- MAC


def test_mac_values_angle_and_scaling():
    theta = 0.4
    a = np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]])
    b = np.array([[np.cos(theta)], [np.sin(theta)], [0.0]])
    np.testing.assert_allclose(mac(a, b), [[np.cos(theta) ** 2], [np.sin(theta) ** 2]], rtol=1e-14)
    # complex shapes: any complex scale of a column leaves MAC unchanged
    rng = np.random.default_rng(3)
    A = rng.normal(size=(6, 3)) + 1j * rng.normal(size=(6, 3))
    B = rng.normal(size=(6, 2)) + 1j * rng.normal(size=(6, 2))
    np.testing.assert_allclose(mac(A * np.array([2j, -0.5, 1 + 1j]), B * np.array([1e-6, -3j])), mac(A, B), rtol=1e-12)
    M = mac(A, A)
    assert np.all(np.diag(M) <= 1.0) and np.allclose(np.diag(M), 1.0, rtol=0, atol=1e-14)
    assert np.all((M >= 0) & (M <= 1))
    # a real mode against its complex (monophase) version: 1
    assert mac(A[:, 0].real, np.exp(0.7j) * A[:, 0].real)[0, 0] == pytest.approx(1.0, abs=1e-14)


def test_mac_edge_cases():
    a = np.array([[1.0, 0.0], [1.0, 0.0], [0.0, 0.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        M = mac(a, a)  # a zero column: MAC 0, no NaN, no warning
    np.testing.assert_array_equal(M, [[1.0, 0.0], [0.0, 0.0]])
    nan = np.array([[1.0, np.nan], [1.0, 1.0], [0.0, 0.0]])
    np.testing.assert_array_equal(mac(nan, a), [[1.0, 0.0], [0.0, 0.0]])
    # 1-D shapes are one column; the result is always 2-D
    assert mac([1.0, 1.0, 0.0], a).shape == (1, 2) and mac(a, [0.0, 1.0, 0.0]).shape == (2, 1)
    assert mac([1.0, 2.0], [2.0, 4.0]).tolist() == [[1.0]]
    # no columns -> empty, right shape
    assert mac(np.zeros((3, 0)), a).shape == (0, 2)


def test_mac_shape_errors():
    with pytest.raises(LabDataError, match=r"phi_a has shape \(3, 2\), phi_b \(4, 1\) \(3 and 4 rows\)"):
        mac(np.ones((3, 2)), np.ones((4, 1)))
    with pytest.raises(LabDataError, match=r"phi_b must be \(n_dof,\) or \(n_dof, n_modes\), got shape \(3, 2, 2\)"):
        mac(np.ones((3, 2)), np.ones((3, 2, 2)))
    with pytest.raises(LabDataError, match=r"phi_a must be numeric"):
        mac(np.array(["a", "b"]), np.ones(2))


def test_layers_use_the_one_mac():
    import calibration._validation
    import identification
    import pretest

    assert identification.mac is mac and pretest.mac is mac and calibration._validation.mac is mac


# ------------------------------------------------------------------ figures


def _png_size(path):
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", head[16:24])


def test_save_figure_default_resolution_and_format(tmp_path):
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.figure import Figure

    assert FIGURE_FORMAT == "png"
    fig = plt.figure(figsize=(4.0, 2.5))
    fig.add_subplot().plot([0, 1], [1, 0])
    num = fig.number
    out = save_figure(fig, tmp_path / "deep" / "er" / "line")
    assert out == tmp_path / "deep" / "er" / "line.png"  # suffix added, folders created
    assert _png_size(out) == (round(4.0 * FIGURE_DPI), round(2.5 * FIGURE_DPI))
    assert not plt.fignum_exists(num)  # released from pyplot
    # a figure made without pyplot, another resolution and suffix
    fig = Figure(figsize=(2.0, 1.0))
    fig.add_subplot().plot([0, 1])
    out = save_figure(fig, tmp_path / "small.png", dpi=50, tight=False)
    assert _png_size(out) == (100, 50)
