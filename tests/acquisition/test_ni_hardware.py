"""Real NI-DAQmx hardware: run only with ``pytest --hardware`` in the lab (see docs/hardware.md).

Needs ``FRFCAL_HARDWARE_CONFIG`` naming a hardware TOML file with ``driver =
"ni"``, an ``[ni]`` section, and a channel ``ao_loopback``: an AI voltage
input wired to the AO output (``sensitivity_mv_per_unit = 1000``, no IEPE).
All other channels of the file are configured too (IEPE excitation on), so a
wiring or sensitivity mistake shows up here before a test article is mounted.
"""

from __future__ import annotations

import numpy as np
import pytest

from acquisition import ChannelSpec, fit_harmonics
from tests.conftest import lab_hardware

pytestmark = [pytest.mark.hardware, pytest.mark.timeout(120)]


@pytest.fixture
def rig():
    hw = lab_hardware("ao_loopback", "an AI wired to the AO output")
    specs = [ChannelSpec("ao_loopback", "monitor", "voltage", "V", range_v=10.0)]
    for name, ch in hw.channels.items():
        if name == "ao_loopback":
            continue
        if ch.sensitivity_v_per_g is not None:
            specs.append(ChannelSpec(name, "response", "acceleration", "m/s^2"))
        else:
            specs.append(ChannelSpec(name, "response", "voltage", "V"))
    driver = hw.make_driver("ni")
    yield driver, hw.mapped(specs)
    driver.close()


def test_ao_loopback_amplitude_phase_and_continuity(rig):
    driver, specs = rig
    info = driver.configure(specs, 25600.0)
    assert info.sample_rate_hz == pytest.approx(25600.0)
    phases = []
    for f in (80.0, 160.0, 320.0):
        driver.set_drive(f, 0.5)
        driver.read_block(10)
        block = driver.read_block(40)
        x = fit_harmonics(block.samples[:1], block.rate_hz, f, 3)[0]
        drive = fit_harmonics(block.drive[None, :], block.rate_hz, f, 1)[0, 0]
        assert abs(x[0]) == pytest.approx(0.5, rel=0.01)  # AO and AI gain within 1 %
        assert abs(x[1]) < 1e-3 and abs(x[2]) < 1e-3  # clean sine
        phases.append(np.angle(x[0] / drive))
        assert not block.overload[0]
    # the AO->AI delay of the shared clock is a pure delay: phase proportional to frequency
    delay = -np.array(phases) / (2 * np.pi * np.array([80.0, 160.0, 320.0]))
    assert np.ptp(delay) < 2 / 25600.0
    driver.ramp_down(0.2)


def test_ramp_down_leaves_zero_volts(rig):
    driver, specs = rig
    driver.configure(specs, 25600.0)
    driver.set_drive(100.0, 1.0)
    driver.read_block(10)
    driver.ramp_down(0.2)
    driver.ramp_down(0.2)  # idempotent
    driver.set_drive(100.0, 0.0)  # restart streaming at zero amplitude to look at the output
    block = driver.read_block(20)
    assert np.max(np.abs(block.samples[0])) < 5e-3
