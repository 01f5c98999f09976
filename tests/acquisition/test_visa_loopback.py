"""VISA driver through the real pyvisa + pyvisa-py stack against the loopback SCPI server.

Every exchange crosses a TCP socket on 127.0.0.1; the server's transcript is
what actually went over the wire.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pyvisa")
pytest.importorskip("pyvisa_py")

from acquisition import ChannelSpec, DriverError, ModalPlant, PhasorBlock, ShakerModel  # noqa: E402
from acquisition._scpi import SR830_TIME_CONSTANTS_S  # noqa: E402
from acquisition._scpi_server import LoopbackLab, VirtualClock, loopback_visa_driver  # noqa: E402
from acquisition.drivers.visa import VisaDriver  # noqa: E402

pytestmark = pytest.mark.timeout(60)


def plant() -> ModalPlant:
    shapes_out = np.array([[1.0, 0.6], [0.4, -0.9]])
    shapes_in = np.array([[0.8, 0.5]])
    return ModalPlant([120.0, 310.0], 0.001, shapes_out, shapes_in)


CHANNELS = (
    ChannelSpec("force", "force", "force", "N", sensitivity=0.0225, physical="sim/force", range_v=1.0),
    ChannelSpec("acc1", "response", "acceleration", "m/s^2", sensitivity=0.0102, physical="sim/0", range_v=1.0),
    ChannelSpec("acc2", "response", "acceleration", "m/s^2", sensitivity=0.0051, physical="sim/1", range_v=1.0),
)


@pytest.fixture
def driver():
    d = loopback_visa_driver(plant(), lab_options={"shaker": ShakerModel(), "lifetime_s": 60})
    yield d
    d.close()


def settled(d, n_cycles=20, n_blocks=4) -> PhasorBlock:
    for _ in range(n_blocks):
        block = d.read_block(n_cycles)
    return block


def test_frf_and_force_match_plant_physics(driver):
    """Steady-state ratios of lock-in phasors equal the plant's exact FRF; force = shaker gain x V."""
    p = plant()
    driver.configure(CHANNELS, None)
    for f in (80.0, 119.7, 120.0, 200.0, 310.0, 450.0):
        driver.set_drive(f, 0.2)
        block = settled(driver)
        assert isinstance(block, PhasorBlock)
        assert block.frequency_hz == f
        assert block.harmonics.shape == (3, 1)
        assert not block.overload.any()
        force = block.harmonics[0, 0]
        h = block.harmonics[1:, 0] / force
        exact = p.frf([f])[0][:, 0]
        np.testing.assert_allclose(h, exact, rtol=2e-3)
        expected_force = 0.2 * driver.lab.shaker_gain(f)
        assert abs(force - expected_force) <= 2e-3 * abs(expected_force)
    # the force drops at the resonance (the shaker is loaded by the structure)
    assert abs(driver.lab.shaker_gain(120.0)) < 0.2 * abs(driver.lab.shaker_gain(80.0))


def test_lockin_filter_settles_after_a_step():
    """After a frequency step the blocks follow the lock-in's 4-stage RC cascade (24 dB/octave)."""
    d = loopback_visa_driver(plant(), lab_options={"lifetime_s": 60, "noise_v_per_rthz": 0.0}, tc_fraction=1.0)
    try:
        d.configure(CHANNELS, None)
        d.set_drive(200.0, 0.2)
        before = settled(d, n_blocks=40).harmonics[1, 0]  # tau = 0.1 s at 200 Hz: 40 blocks = 40 tau
        d.set_drive(210.0, 0.2)
        values = np.array([d.read_block(20).harmonics[1, 0] for _ in range(10)])
        after = values[-1]
        # time constant: largest SR830 value <= 1.0 x block length (20 cycles at 210 Hz)
        tau = [t for t in SR830_TIME_CONSTANTS_S if t <= 20 / 210.0][-1]
        assert d.lab.lockins["lockin_resp0"].oflt == SR830_TIME_CONSTANTS_S.index(tau)
        x = np.arange(1, 11) * (20 / 210.0) / tau
        remaining = np.exp(-x) * (1 + x + x**2 / 2 + x**3 / 6)
        expected = after + (before - after) * remaining
        np.testing.assert_allclose(values, expected, rtol=1e-6)  # SNAP? carries 7 digits
        assert abs(values[0] - after) > 0.1 * abs(before - after)
    finally:
        d.close()


def test_virtual_time_advances_by_whole_blocks(driver):
    driver.configure(CHANNELS, None)
    driver.set_drive(250.0, 0.1)
    t0 = driver.time_s()
    b1 = driver.read_block(25)
    b2 = driver.read_block(50)
    assert b1.t0_s == pytest.approx(t0)
    assert b1.duration_s == pytest.approx(0.1)
    assert b2.t0_s == pytest.approx(t0 + 0.1)
    assert driver.time_s() == pytest.approx(t0 + 0.3)


def test_output_overload_is_flagged(driver):
    """A channel whose range is far below its signal trips the lock-in's output overload bit."""
    small = list(CHANNELS)
    small[1] = ChannelSpec("acc1", "response", "acceleration", "m/s^2", sensitivity=0.0102, physical="sim/0",
                           range_v=1e-5)
    driver.configure(small, None)
    driver.set_drive(119.9, 0.5)
    block = settled(driver)
    assert block.overload.tolist() == [False, True, False]


def test_ramp_down_is_idempotent_and_safe_before_configure():
    d = loopback_visa_driver(plant(), lab_options={"lifetime_s": 30})
    try:
        d.ramp_down()  # nothing opened yet: nothing to do
        assert d.lab.transcript == []
        d.configure(CHANNELS, None)
        d.set_drive(150.0, 1.0)
        assert d.lab.drive_v_peak == pytest.approx(1.0)
        d.ramp_down(0.2)
        d.ramp_down(0.2)
        assert d.lab.drive_v_peak == 0.0
        assert not d.lab.generator.output
    finally:
        d.close()


def test_bad_configuration_is_rejected_with_channel_names():
    d = loopback_visa_driver(plant(), lab_options={"lifetime_s": 30})
    try:
        with pytest.raises(ValueError, match="acc2.*sim/7|sim/7"):
            d.configure([CHANNELS[0], ChannelSpec("acc2", "response", "acceleration", "m/s^2", physical="sim/7")], None)
        with pytest.raises(ValueError, match="'a'.*'b'.*share"):
            d.configure([ChannelSpec("a", "response", "acceleration", "m/s^2", physical="sim/0"),
                         ChannelSpec("b", "response", "acceleration", "m/s^2", physical="sim/0")], None)
        d.configure(CHANNELS, None)
        with pytest.raises(ValueError, match="amplitude"):
            d.set_drive(100.0, 50.0)
    finally:
        d.close()


def test_unreachable_instrument_is_a_driver_error():
    clock = VirtualClock()
    with LoopbackLab(plant(), clock=clock, lifetime_s=30) as lab:
        port = lab.port("generator")
    d = VisaDriver(f"TCPIP::127.0.0.1::{port}::SOCKET", clock=clock, timeout_ms=300)
    try:
        with pytest.raises(DriverError, match=r"generator \(TCPIP::127.0.0.1::\d+::SOCKET\): (cannot connect|connection lost).*(refused|\*IDN)"):
            d.configure(CHANNELS, None)
    finally:
        d.close()


def test_blocks_during_reference_relock_are_discarded_and_remeasured():
    d = loopback_visa_driver(plant(), lab_options={"lifetime_s": 60, "relock_cycles": 30.0})
    try:
        d.configure(CHANNELS, None)
        d.set_drive(200.0, 0.2)
        n = len(d.lab.transcript)
        block = d.read_block(20)  # 30 cycles to re-lock: blocks 1 and 2 (20 cycles each) are discarded
        snaps = [c for i, c, _ in d.lab.transcript[n:] if i == "lockin_resp0" and c.startswith("SNAP?")]
        assert len(snaps) == 3
        assert block.t0_s == pytest.approx(2 * 20 / 200.0)
        assert not block.overload.any()
        d.set_drive(200.0, 0.3)  # amplitude only: no re-lock, one block
        n = len(d.lab.transcript)
        d.read_block(20)
        assert sum(c.startswith("SNAP?") for i, c, _ in d.lab.transcript[n:] if i == "lockin_resp0") == 1
    finally:
        d.close()


def test_reference_that_never_locks_is_a_driver_error():
    d = loopback_visa_driver(plant(), lab_options={"lifetime_s": 60, "relock_cycles": 1e6}, max_unlocked_blocks=2)
    try:
        d.configure(CHANNELS, None)
        d.set_drive(200.0, 0.2)
        with pytest.raises(DriverError, match=r"\['force', 'acc1', 'acc2'\]: reference unlocked for 3 blocks at 200 Hz"):
            d.read_block(20)
    finally:
        d.close()


def test_unknown_visa_backend_is_driver_unavailable():
    from acquisition.drivers import DriverUnavailable

    d = VisaDriver("TCPIP::127.0.0.1::1::SOCKET", backend="@nonexistent")
    with pytest.raises(DriverUnavailable, match="VISA backend '@nonexistent' unavailable"):
        d.configure(CHANNELS, None)
