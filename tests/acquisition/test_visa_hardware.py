"""Real VISA instruments: run only with ``pytest --hardware`` in the lab (see docs/hardware.md).

Needs ``FRFCAL_HARDWARE_CONFIG`` naming a hardware TOML file with a ``[visa]``
section (the generator) and a channel ``gen_loopback``: a lock-in whose input
is wired to the generator output through a known attenuator
(``sensitivity_mv_per_unit`` = 1000 x the attenuation, so the channel reads
the generator volts).
"""

from __future__ import annotations

import pytest

from acquisition import ChannelSpec
from tests.conftest import lab_hardware

pytestmark = [pytest.mark.hardware, pytest.mark.timeout(300)]


@pytest.fixture
def rig():
    hw = lab_hardware("gen_loopback", "a lock-in reading the generator output")
    driver = hw.make_driver("visa")
    spec = hw.mapped([ChannelSpec("gen_loopback", "monitor", "voltage", "V", range_v=1.0)])
    yield driver, spec
    driver.close()


def test_instruments_answer_and_error_queue_is_empty(rig):
    driver, specs = rig
    info = driver.configure(specs)
    assert len(info.devices) == 2 and all(d.count(",") >= 3 for d in info.devices)


def test_generator_amplitude_through_lockin(rig):
    driver, specs = rig
    driver.configure(specs)
    for f in (100.0, 400.0):
        driver.set_drive(f, 0.2)
        for _ in range(10):
            block = driver.read_block(50)
        assert abs(block.harmonics[0, 0]) == pytest.approx(0.2, rel=0.02)
        assert not block.overload[0]
    driver.ramp_down(0.5)
