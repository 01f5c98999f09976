"""Hardware configuration file: parsing, validation, mapping onto the pretest layout."""

from __future__ import annotations

import json

import pytest

from acquisition import ChannelSpec, read_layout
from acquisition._hardware_config import (
    G0,
    HardwareConfigError,
    hardware_config_from_dict,
    read_hardware_config,
)

HW_TOML = """
driver = "ni"

[ni]
ao_channel = "cDAQ1Mod4/ao0"
ao_max_v = 2
lead_s = 0.25

[visa]
generator = "TCPIP::192.168.0.20::5025::SOCKET"
timeout_ms = 5000

[channels.acc01]
physical = "cDAQ1Mod1/ai0"
serial = "LW100001"
sensitivity_mv_per_g = 100.0
iepe_current_ma = 4.0
range_v = 5.0

[channels.acc02]
physical = "cDAQ1Mod1/ai1"
sensitivity_mv_per_unit = 10.2
iepe_current_ma = 2

[channels.drive1]
physical = "cDAQ1Mod1/ai2"
serial = "F2001"
sensitivity_mv_per_unit = 22.5
iepe_current_ma = 4.0

[channels.spare]
physical = "cDAQ1Mod2/ai0"
sensitivity_mv_per_unit = 1000
"""

LAYOUT = {
    "format": "frfcal-layout", "version": 1, "model": {"path": "plate.bdf", "units": "mm-t-s"},
    "channels": [
        {"name": "acc01", "role": "response", "quantity": "acceleration", "unit": "m/s^2", "grid": 101,
         "direction": [0, 0, 1], "xyz_m": [0.1, 0.2, 0.0]},
        {"name": "acc02", "role": "response", "quantity": "acceleration", "unit": "m/s^2", "grid": 102,
         "direction": [0, 1, 0], "xyz_m": [0.3, 0.2, 0.0]},
    ],
    "drives": [{"name": "drive1", "role": "force", "quantity": "force", "unit": "N", "grid": 201,
                "direction": [0, 0, -1], "xyz_m": [0.2, 0.1, 0.0]}],
}


@pytest.fixture
def files(tmp_path):
    hw = tmp_path / "hardware.toml"
    hw.write_text(HW_TOML)
    lay = tmp_path / "layout.json"
    lay.write_text(json.dumps(LAYOUT))
    return hw, lay


def test_layout_channels_get_their_physical_side(files):
    hw_path, lay_path = files
    hw = read_hardware_config(hw_path)
    layout = read_layout(lay_path)
    specs = hw.mapped(layout.sensors + layout.drives)
    by = {s.name: s for s in specs}
    a1, a2, f = by["acc01"], by["acc02"], by["drive1"]
    # the layout's geometry is kept
    assert (a1.grid, a1.direction) == (101, (0.0, 0.0, 1.0))
    assert (f.grid, f.direction, f.role) == (201, (0.0, 0.0, -1.0), "force")
    # the file's physical side is applied, in SI: 100 mV/g = 0.1/9.80665 V/(m/s^2)
    assert a1.physical == "cDAQ1Mod1/ai0" and a1.serial == "LW100001"
    assert a1.sensitivity == pytest.approx(0.1 / G0, rel=1e-12)
    assert a1.iepe_current_a == pytest.approx(0.004) and a1.range_v == 5.0
    assert a2.sensitivity == pytest.approx(0.0102) and a2.iepe_current_a == pytest.approx(0.002)
    assert a2.range_v == layout.sensors[1].range_v  # not in the file: the layout's value
    assert f.sensitivity == pytest.approx(0.0225) and f.serial == "F2001"


def test_drivers_are_built_from_their_sections(files):
    pytest.importorskip("nidaqmx")
    from acquisition.drivers.ni import NiDaqDriver
    from acquisition.drivers.visa import VisaDriver

    hw = read_hardware_config(files[0])
    ni = hw.make_driver()
    assert isinstance(ni, NiDaqDriver)
    assert (ni.ao_channel, ni.ao_max_v, ni.lead_s) == ("cDAQ1Mod4/ao0", 2.0, 0.25)
    visa = hw.make_driver("visa")
    assert isinstance(visa, VisaDriver)
    assert (visa.generator_resource, visa.timeout_ms) == ("TCPIP::192.168.0.20::5025::SOCKET", 5000)


def test_ni_driver_configured_from_layout_and_file_uses_the_file_sensitivities(files):
    """End to end: layout + hardware file -> NI task configuration (autospecced nidaqmx)."""
    pytest.importorskip("nidaqmx")
    from unittest import mock

    import nidaqmx
    from nidaqmx.task.collections import AIChannelCollection

    hw = read_hardware_config(files[0])
    layout = read_layout(files[1])
    tasks = {}

    def task(name):
        t = mock.create_autospec(nidaqmx.Task, instance=True)
        t.ai_channels = mock.create_autospec(AIChannelCollection, instance=True)
        tasks[name] = t
        return t

    drv = hw.make_driver(task_factory=task, reader_factory=mock.Mock(), writer_factory=mock.Mock())
    drv.configure(hw.mapped(layout.sensors + layout.drives), 25600.0)
    ai = tasks["frfcal_ai"].ai_channels
    accel = ai.add_ai_accel_chan.call_args_list
    assert [c.args[0] for c in accel] == ["cDAQ1Mod1/ai0", "cDAQ1Mod1/ai1"]
    assert accel[0].kwargs["sensitivity"] == pytest.approx(100.0)  # mV/g back again
    assert accel[1].kwargs["sensitivity"] == pytest.approx(10.2 * G0)
    assert accel[1].kwargs["current_excit_val"] == pytest.approx(0.002)
    force = ai.add_ai_force_iepe_chan.call_args
    assert force.args[0] == "cDAQ1Mod1/ai2" and force.kwargs["sensitivity"] == pytest.approx(22.5)


@pytest.mark.parametrize(
    "patch, message",
    [
        ({"colour": "red"}, r"unknown top-level field 'colour'"),
        ({"driver": "gpib"}, r"driver must be one of"),
        ({"ni": {"ao_chan": "x"}}, r"unknown field ni.ao_chan"),
        ({"visa": {"timeout_ms": "fast"}}, r"visa.timeout_ms must be a int"),
        ({"channels": {"a": {"physical": "x", "sensitivity_mv_per_unit": 1, "gain": 2}}}, r"unknown field channels.a.gain"),
        ({"channels": {"a": {"sensitivity_mv_per_unit": 1}}}, r"channels.a.physical is missing"),
        ({"channels": {"a": {"physical": "x"}}}, r"channels.a: sensitivity missing"),
        ({"channels": {"a": {"physical": "x", "sensitivity_mv_per_unit": 1, "sensitivity_mv_per_g": 1}}}, r"not both"),
        ({"channels": {"a": {"physical": "x", "sensitivity_mv_per_unit": -1}}}, r"sensitivity_mv_per_unit must be positive"),
        ({"channels": {"a": {"physical": "x", "sensitivity_mv_per_unit": 1, "iepe_current_ma": 40}}}, r"iepe_current_ma"),
        ({"channels": {"a": {"physical": "x", "sensitivity_mv_per_unit": 1},
                       "b": {"physical": "x", "sensitivity_mv_per_unit": 1}}}, r"'a' and 'b' both use 'x'"),
        ({"channels": {}}, r"\[channels.<name>\] tables are missing"),
    ],
)
def test_bad_files_are_rejected_naming_the_field(patch, message):
    base = {"channels": {"a": {"physical": "Dev1/ai0", "sensitivity_mv_per_unit": 10.0}}}
    with pytest.raises(HardwareConfigError, match=r"^hw.toml: .*" + message):
        hardware_config_from_dict(base | patch, source="hw.toml")


def test_mapping_errors_name_the_channel(files):
    hw = read_hardware_config(files[0])
    with pytest.raises(HardwareConfigError, match=r"channel 'acc99' of the layout has no \[channels.acc99\]"):
        hw.mapped([ChannelSpec("acc99", "response", "acceleration", "m/s^2")])
    with pytest.raises(HardwareConfigError, match=r"sensitivity_mv_per_g is for accelerometers.*'acc01' measures force"):
        hw.mapped([ChannelSpec("acc01", "force", "force", "N")])
    with pytest.raises(HardwareConfigError, match="no driver chosen"):
        hardware_config_from_dict({"channels": {"a": {"physical": "x", "sensitivity_mv_per_unit": 1}}}, "h").make_driver()
    with pytest.raises(HardwareConfigError, match=r"\[ni\] needs ao_channel"):
        hardware_config_from_dict({"driver": "ni", "channels": {"a": {"physical": "x", "sensitivity_mv_per_unit": 1}}},
                                  "h").make_driver()


def test_missing_and_invalid_files(tmp_path):
    with pytest.raises(HardwareConfigError, match="not found"):
        read_hardware_config(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("driver = \n")
    with pytest.raises(HardwareConfigError, match="bad.toml: not valid TOML"):
        read_hardware_config(bad)


def test_the_documented_example_is_valid():
    """docs/hardware.md's example file parses and maps as the text says."""
    import re
    import tomllib
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[2] / "docs" / "hardware.md").read_text()
    block = re.search(r"```toml\n(.*?)```", doc, re.S).group(1)
    hw = hardware_config_from_dict(tomllib.loads(block), "docs/hardware.md")
    assert hw.driver == "ni" and hw.ni["ao_channel"] == "cDAQ1Mod4/ao0"
    (acc, force) = hw.mapped([ChannelSpec("acc01", "response", "acceleration", "m/s^2"),
                              ChannelSpec("drive1", "force", "force", "N")])
    assert acc.sensitivity == pytest.approx(0.1002 / G0) and acc.iepe_current_a == pytest.approx(0.004)
    assert force.sensitivity == pytest.approx(0.0225) and force.physical == "cDAQ1Mod1/ai3"
