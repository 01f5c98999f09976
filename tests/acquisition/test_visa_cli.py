"""``frfcal acquire --driver visa`` end to end: a loopback lab in another process, the wall clock, pyvisa.

The server process is started by ``python -m acquisition._scpi_server`` from
the plan's ``[sim]`` plant and writes the hardware file; ``frfcal acquire``
then runs the plan exactly as it would against instruments in the lab.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest

pytest.importorskip("pyvisa")
pytest.importorskip("pyvisa_py")

from acquisition import ModalPlant, read_hardware_config, read_run  # noqa: E402
from frfcal.cli import main  # noqa: E402

pytestmark = pytest.mark.timeout(120)

PLAN = """
name = "demo"
sample_rate_hz = 4096.0

[[channels]]
name = "acc0"
sensitivity_v_per_unit = 0.0102
[[channels]]
name = "acc1"
sensitivity_v_per_unit = 0.0102
[[channels]]
name = "force"
role = "force"
quantity = "force"
sensitivity_v_per_unit = 0.0225

[lines]
kind = "linear"
start_hz = 100.0
stop_hz = 120.0
step_hz = 10.0

[force]
levels_n = [0.5]

[settle]
assumed_damping = 0.05
block_min_s = 0.05
min_blocks = 2

[measure]
blocks = 2

[sim.modes]
frequencies_hz = [115.0, 240.0]
damping = 0.01
shapes_out = [[0.5, 0.4], [0.35, -0.45]]
shapes_in = [[0.5, 0.4]]
"""


@pytest.fixture
def server(tmp_path):
    plan = tmp_path / "plan.toml"
    plan.write_text(PLAN)
    hw = tmp_path / "hw.toml"
    proc = subprocess.Popen([sys.executable, "-m", "acquisition._scpi_server", str(plan), "--hardware-out", str(hw),
                             "--lifetime-s", "100"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 30
        while not hw.exists():
            assert proc.poll() is None, proc.stdout.read()
            assert time.monotonic() < deadline, "loopback server did not start"
            time.sleep(0.1)
        yield plan, hw
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def test_acquire_driver_visa_runs_the_plan_through_the_instrument_stack(server, tmp_path, capsys):
    plan, hw = server
    cfg = read_hardware_config(hw)
    assert cfg.driver == "visa" and set(cfg.channels) == {"acc0", "acc1", "force", "gen_loopback"}
    out = tmp_path / "runs"
    assert main(["acquire", str(plan), "--driver", "visa", "--hardware", str(hw), "--out", str(out), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    (entry,) = result["runs"]
    assert entry["status"] == "completed" and entry["n_lines"] == 3
    run = read_run(entry["path"])
    assert run.status == "completed" and run.hardware["driver"] == "visa"
    assert run.hardware["details"]["generator"] == cfg.visa["generator"]
    plant = ModalPlant([115.0, 240.0], 0.01, np.array([[0.5, 0.4], [0.35, -0.45]]), np.array([[0.5, 0.4]]))
    ratio = run.frf / plant.frf(run.frequency_hz)
    assert np.max(np.abs(np.abs(ratio) - 1)) < 0.005
    assert np.max(np.abs(np.degrees(np.angle(ratio)))) < 0.5
    assert np.all(np.abs(run.force_n[:, 0] / 0.5 - 1) < 0.02)


def test_acquire_driver_visa_without_hardware_file_is_a_clear_error(tmp_path, capsys):
    plan = tmp_path / "plan.toml"
    plan.write_text(PLAN)
    assert main(["acquire", str(plan), "--driver", "visa", "--out", str(tmp_path)]) == 2
    assert "--driver visa needs --hardware" in capsys.readouterr().err
