"""The simulated lab and plants: exact transients, shaker force drop, sensor model, state-space input."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from acquisition import ChannelSpec, DriverError, ModalPlant, PlantError, ShakerModel, SimLabError, SimulatedLab, fit_harmonics
from tests.acquisition._common import plant3

CH = tuple(ChannelSpec(f"a{k}", "response", "acceleration", "m/s^2", sensitivity=0.01, physical=f"sim/{k}")
           for k in range(3)) + (ChannelSpec("F", "force", "force", "N", sensitivity=0.02, physical="sim/force"),)


def test_modal_frf_matches_the_textbook_sum_and_its_state_space():
    p = plant3()
    f = np.linspace(100, 300, 57)
    w = 2 * np.pi * f
    wr = 2 * np.pi * p.frequencies_hz
    rec = sum(np.einsum("o,i->oi", p.shapes_out[:, r], p.shapes_in[:, r])[None]
              / (wr[r] ** 2 - w[:, None, None] ** 2 + 2j * 0.001 * wr[r] * w[:, None, None]) for r in range(3))
    assert np.allclose(p.frf(f), -w[:, None, None] ** 2 * rec, rtol=1e-12)
    A, B, C, D = p.state_space()
    ss = ModalPlant.from_state_space(A, B, C, D)
    assert np.allclose(ss.frf(f), p.frf(f), rtol=1e-10)
    assert np.allclose(np.sort(ss.frequencies_hz), p.frequencies_hz) and np.allclose(ss.damping, 0.001)
    mob = ModalPlant(p.frequencies_hz, p.damping, p.shapes_out, p.shapes_in, quantity="mobility")
    assert np.allclose(mob.frf(f), p.frf(f) / (1j * w[:, None, None]))


def test_time_response_is_exact_against_scipy_lsim():
    """Ideal force source: the closed-form response (transient included, across a phase-continuous
    frequency step) agrees with scipy's lsim, whose first-order-hold error falls as h^2."""
    p = plant3()
    A, B, C, D = p.state_space()
    errs = []
    for rate in (16384.0, 65536.0):
        lab = SimulatedLab(p, shaker=None, gain_n_per_v=2.0, noise_rms=0.0, adc_bits=32)
        lab.configure(CH, rate)
        lab.set_drive(118.0, 0.5)
        b1 = lab.read_block(20)
        lab.set_drive(121.0, 0.8)
        b2 = lab.read_block(20)
        y = np.hstack([b1.samples, b2.samples])
        u = 2.0 * np.concatenate([b1.drive, b2.drive])
        _, y_ref, _ = signal.lsim((A, B, C, D), u, np.arange(u.size) / rate, interp=True)
        errs.append(np.abs(y[:3].T - y_ref).max() / np.abs(y_ref).max())
        assert np.allclose(y[3], u, atol=1e-6 * np.abs(u).max())  # force channel = ideal source
        d = np.concatenate([b1.drive, b2.drive])
        assert np.max(np.abs(np.diff(d))) < 2 * np.pi * 121 * 0.8 / rate * 1.01  # no phase jump
    assert errs[1] < 1e-4 and errs[0] / errs[1] > 10  # second-order convergence onto our result


def test_shaker_force_drops_at_resonance_and_steady_state_is_the_plant_frf():
    p = plant3()
    lab = SimulatedLab(p, shaker=ShakerModel(), noise_rms=0.0)
    lab.configure(CH, 4096.0)
    out = {}
    for f in (110.0, 120.0):
        lab.set_drive(f, 0.2)
        for _ in range(40):
            blk = lab.read_block(60)  # ~20 s: transients gone
        X = fit_harmonics(blk.samples, blk.rate_hz, f, 1)[:, 0]
        out[f] = X
        assert np.allclose(X[:3] / X[3], p.frf(f)[0, :, 0], rtol=1e-4)
    assert abs(out[120.0][3]) < 0.2 * abs(out[110.0][3])  # force dropout at the 120 Hz mode


def test_noise_quantization_overload_and_lockin_mode():
    p = plant3()
    lab = SimulatedLab(p, noise_rms=1.0, adc_bits=12, seed=3)
    lab.configure(CH, 4096.0)
    lab.set_drive(150.0, 0.0)
    blk = lab.read_block(300)
    lsb = 2 * 10.0 / 2**12 / 0.01  # 0.49 m/s^2
    assert abs(np.std(blk.samples[0]) - np.sqrt(1 + lsb**2 / 12)) < 0.05
    lsb = 2 * 10.0 / 2**12 / 0.01
    assert np.allclose(blk.samples[0] / lsb, np.round(blk.samples[0] / lsb), atol=1e-6)
    from dataclasses import replace

    lab = SimulatedLab(p, noise_rms=0.0)
    lab.configure(tuple(replace(c, range_v=0.5) for c in CH), 4096.0)
    lab.set_drive(120.0, 1.0)
    blk = lab.read_block(100)
    assert blk.overload[[0, 2]].all() and np.max(np.abs(blk.samples[:3])) <= 0.5 / 0.01 + 1e-9  # clipped at the range
    lock = SimulatedLab(p, noise_rms=0.0, kind="demodulating")
    lock.configure(CH, 4096.0)
    lock.set_drive(150.0, 0.3)
    for _ in range(30):
        pb = lock.read_block(100)
    assert pb.harmonics.shape == (4, 5) and np.allclose(pb.harmonics[:3, 0] / pb.harmonics[3, 0], p.frf(150.0)[0, :, 0], rtol=1e-4)


def test_ramp_down_and_errors():
    p = plant3()
    lab = SimulatedLab(p)
    with pytest.raises(DriverError, match="before configure"):
        lab.read_block(1)
    lab.configure(CH, 4096.0)
    lab.ramp_down()  # safe before anything moved
    lab.set_drive(130.0, 1.0)
    lab.read_block(10)
    t = lab.time_s()
    lab.ramp_down(0.5)
    assert lab.drive_amplitude_v == 0.0 and abs(lab.time_s() - t - 0.5) < 1e-3
    lab.ramp_down()
    lab.close()
    with pytest.raises(DriverError, match="closed"):
        lab.set_drive(100.0, 0.1)
    with pytest.raises(SimLabError, match="sim/9"):
        SimulatedLab(p).configure((ChannelSpec("x", "response", "acceleration", "m/s^2", physical="sim/9"),), 1000.0)
    with pytest.raises(PlantError, match="damping"):
        ModalPlant([100.0], [1.5], [[1.0]], [[1.0]])
    with pytest.raises(PlantError, match="shapes_out"):
        ModalPlant([100.0, 200.0], 0.01, [[1.0]], [[1.0, 1.0]])
    with pytest.raises(PlantError, match="stable"):
        ModalPlant.from_state_space([[0.0, 1.0], [-1.0, 0.1]], [[0.0], [1.0]], [[1.0, 0.0]])


def test_state_space_plant_with_drive_point_couples_the_shaker_like_the_modal_plant():
    p = plant3()
    A, B, C, D = p.state_space()
    ss = ModalPlant.from_state_space(A, B, C, D, C_drive=np.hstack([p.shapes_in, np.zeros_like(p.shapes_in)]))
    out = []
    for plant in (p, ss):
        lab = SimulatedLab(plant, noise_rms=0.0, adc_bits=32)
        lab.configure(CH, 4096.0)
        lab.set_drive(121.0, 0.3)
        blk = lab.read_block(300)
        out.append(blk.samples)
    assert np.allclose(out[0], out[1], atol=1e-9 * np.abs(out[0]).max())


def test_cubic_spring_shifts_the_resonance_with_level_and_the_linearity_check_flags_it(tmp_path):
    from acquisition import CubicSpring, read_run, run_sweep
    from acquisition.runfile import FLAG_NONLINEAR
    from tests.acquisition._common import DRIVE, SENSORS, plan

    p = plant3()
    nl = CubicSpring(mode=0, beta_per_m2kg=5e4)
    lines = {"kind": "linear", "start_hz": 119.8, "stop_hz": 120.6, "step_hz": 0.2}
    run_sweep(SimulatedLab(p, nonlinearity=nl, noise_rms=1e-4), plan(lines, linearity={"enabled": True, "peaks_only": False}),
              tmp_path / "nl.h5", sensors=SENSORS, drive=DRIVE, level_n=1.0)
    run = read_run(tmp_path / "nl.h5")
    assert np.any(run.flags & FLAG_NONLINEAR) and np.nanmax(run.linearity) > 0.05
    # the hardened mode's peak moved up: the measured FRF differs from the linear plant near 120 Hz
    assert np.max(np.abs(run.frf / p.frf(run.frequency_hz) - 1)) > 0.05
