"""``frfcal info``: drivers, VISA resources and NI devices, each probed safely."""

from __future__ import annotations

import json

import numpy as np
import pytest

from acquisition import ModalPlant
from acquisition._scpi_server import LoopbackLab
from frfcal.cli import main
from frfcal.commands import info

pytestmark = pytest.mark.timeout(60)


def run_json(capsys, *argv) -> dict:
    assert main(["info", "--no-scan", "--json", *argv]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.fixture
def lab():
    p = ModalPlant([100.0], 0.01, np.array([[1.0]]), np.array([[1.0]]))
    with LoopbackLab(p, lifetime_s=30) as lab:
        yield lab


def test_drivers_and_packages_are_reported(capsys):
    report = run_json(capsys)
    assert report["drivers"]["sim"]["available"] is True
    assert report["packages"]["numpy"] == np.__version__
    visa = report["drivers"]["visa"]
    pyvisa = pytest.importorskip("pyvisa")
    assert visa["available"] is True and f"pyvisa {pyvisa.__version__}" in visa["detail"]
    ni = report["drivers"]["ni"]
    assert ni["detail"].startswith(f"nidaqmx {report['packages']['nidaqmx']}")
    # the NI probe agrees with itself: the runtime is either found (and devices listed) or named as missing
    assert ni["available"] == report["ni"]["ok"]
    if not ni["available"]:
        assert "not installed" in ni["detail"] or "unusable" in ni["detail"]


def test_missing_extras_name_the_extra(capsys, monkeypatch):
    real = info._version
    monkeypatch.setattr(info, "_version", lambda d: None if d in ("pyvisa", "nidaqmx") else real(d))
    report = run_json(capsys)
    assert report["drivers"]["visa"] == {"available": False, "detail": "not installed: pip install 'frfcal[visa]'"}
    assert report["drivers"]["ni"] == {"available": False, "detail": "not installed: pip install 'frfcal[ni]'"}
    assert report["ni"]["detail"] == "nidaqmx not installed"
    assert main(["info", "--no-scan"]) == 0
    text = capsys.readouterr().out
    assert "visa  unavailable not installed: pip install 'frfcal[visa]'" in text


def test_probe_asks_idn_over_visa(capsys, lab):
    pytest.importorskip("pyvisa_py")
    dead = f"TCPIP::127.0.0.1::{lab.port('generator')}::SOCKET"
    good = lab.generator_resource
    lab.inject("lockin_resp0", "garble", "*IDN?")
    garbled = lab.resource("lockin_resp0")
    report = run_json(capsys, "--probe", good, "--probe", garbled, "--timeout-ms", "500")
    ok, bad = report["probes"]
    assert ok == {"resource": good, "ok": True, "reply": "Agilent Technologies,33522B,MY00000001,4.00-loopback"}
    assert bad["ok"] is False and "garbled reply to '*IDN?'" in bad["reply"]
    lab.stop()
    report = run_json(capsys, "--probe", dead, "--timeout-ms", "300")
    assert report["probes"][0]["ok"] is False


def test_hardware_file_check_probes_its_instruments(capsys, lab, tmp_path):
    pytest.importorskip("pyvisa_py")
    hw = tmp_path / "hw.toml"
    hw.write_text(
        'driver = "visa"\n[visa]\n'
        f'generator = "{lab.generator_resource}"\n'
        f'[channels.force]\nphysical = "{lab.resource("lockin_force0")}"\nsensitivity_mv_per_unit = 22.5\n'
        f'[channels.acc1]\nphysical = "{lab.resource("lockin_resp0")}"\nsensitivity_mv_per_g = 100\n'
        '[channels.acc2]\nphysical = "TCPIP::127.0.0.1::1::SOCKET"\nsensitivity_mv_per_g = 100\n'
    )
    report = run_json(capsys, "--hardware", str(hw), "--timeout-ms", "500")
    h = report["hardware"]
    assert [p["ok"] for p in h["probes"]] == [True, True, True, False]
    assert len(h["problems"]) == 1 and h["problems"][0].startswith("TCPIP::127.0.0.1::1::SOCKET")
    assert main(["info", "--no-scan", "--hardware", str(hw), "--timeout-ms", "500"]) == 0
    assert "problem: TCPIP::127.0.0.1::1::SOCKET" in capsys.readouterr().out


def test_ni_hardware_file_lists_the_devices_it_needs(capsys, tmp_path):
    hw = tmp_path / "hw.toml"
    hw.write_text('driver = "ni"\n[ni]\nao_channel = "cDAQ1Mod4/ao0"\n'
                  '[channels.acc1]\nphysical = "cDAQ1Mod1/ai0"\nsensitivity_mv_per_g = 100\niepe_current_ma = 4\n')
    report = run_json(capsys, "--hardware", str(hw))
    h = report["hardware"]
    assert h["ni_devices_needed"] == ["cDAQ1Mod1", "cDAQ1Mod4"]
    present = {d["name"] for d in report["ni"]["devices"]}
    assert h["problems"] == [f"NI device {d!r} not present" for d in h["ni_devices_needed"] if d not in present]


def test_bad_hardware_file_is_one_line_error(capsys, tmp_path):
    hw = tmp_path / "hw.toml"
    hw.write_text('driver = "ni"\n[ni]\nao_chanel = "x"\n')
    assert main(["info", "--no-scan", "--hardware", str(hw)]) == 2
    assert "unknown field ni.ao_chanel" in capsys.readouterr().err


def test_hardware_template_from_layout_maps_once_filled_in(capsys, tmp_path):
    import tomllib

    from acquisition import read_layout
    from acquisition._hardware_config import HardwareConfigError, hardware_config_from_dict

    lay = tmp_path / "layout.json"
    lay.write_text(json.dumps({
        "format": "frfcal-layout", "version": 1,
        "channels": [{"name": f"acc{k}", "quantity": "acceleration", "unit": "m/s^2", "grid": 10 + k,
                      "direction": [0, 0, 1]} for k in range(3)],
        "drives": [{"name": "drive1", "quantity": "force", "unit": "N", "grid": 7, "direction": [1, 0, 0]}],
    }))
    assert main(["info", "--hardware-template", str(lay)]) == 0
    data = tomllib.loads(capsys.readouterr().out)
    assert list(data["channels"]) == ["acc0", "acc1", "acc2", "drive1"]
    with pytest.raises(HardwareConfigError, match="physical is missing"):
        hardware_config_from_dict(data, "template")  # nothing is guessed: the user maps every channel
    for k, name in enumerate(data["channels"]):
        data["channels"][name]["physical"] = f"cDAQ1Mod1/ai{k}"
    data["ni"]["ao_channel"] = "cDAQ1Mod2/ao0"
    hw = hardware_config_from_dict(data, "filled")
    layout = read_layout(lay)
    specs = hw.mapped(layout.sensors + layout.drives)
    assert [s.physical for s in specs] == ["cDAQ1Mod1/ai0", "cDAQ1Mod1/ai1", "cDAQ1Mod1/ai2", "cDAQ1Mod1/ai3"]
    assert all(s.iepe_current_a == pytest.approx(0.004) for s in specs)
    assert specs[3].grid == 7 and specs[3].direction == (1.0, 0.0, 0.0)
