"""The stepped-sine controller and run file, driving the VISA driver through pyvisa-py.

A whole sweep and fault injection (timeout, garbled reply, error-queue entry,
connection drop) cross real sockets to the loopback SCPI server, which answers
from the plant's exact steady-state response.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pyvisa")
pytest.importorskip("pyvisa_py")

from acquisition import (  # noqa: E402
    ChannelSpec,
    DriverError,
    ModalPlant,
    ShakerModel,
    plan_from_dict,
    read_run,
    run_sweep,
)
from acquisition._scpi_server import loopback_visa_driver  # noqa: E402

pytestmark = pytest.mark.timeout(120)

MODES_HZ = (150.0, 260.0, 410.0)


def plant() -> ModalPlant:
    return ModalPlant(MODES_HZ, 0.001, np.array([[1.0, 0.7, 0.5], [0.4, -0.9, 0.8]]), np.array([[0.8, 0.5, -0.6]]))


SENSORS = (
    ChannelSpec("a1", "response", "acceleration", "m/s^2", sensitivity=0.0102, physical="sim/0", range_v=5.0),
    ChannelSpec("a2", "response", "acceleration", "m/s^2", sensitivity=0.0102, physical="sim/1", range_v=5.0),
)
DRIVE = ChannelSpec("force", "force", "force", "N", sensitivity=0.0225, physical="sim/force", range_v=5.0)


def make_plan(lines: dict):
    return plan_from_dict({
        "lines": lines,
        "limits": {"drive_v_max": 10.0},
        "channels": [{"name": "a1"}, {"name": "a2"}, {"name": "force", "role": "force", "quantity": "force"}],
    })


def driver(**lab):
    return loopback_visa_driver(plant(), lab_options={"shaker": ShakerModel(), "lifetime_s": 120} | lab, timeout_ms=300)


def test_sweep_through_visa_matches_plant_within_sim_lab_tolerances(tmp_path):
    """0.5 % magnitude and 0.5 deg phase at every line, resonance peaks included; force within 2 %."""
    plan = make_plan({"kind": "bandwidth", "start_hz": 120.0, "stop_hz": 450.0, "background_step": 0.05,
                      "lines_per_bandwidth": 2, "span_bandwidths": 2,
                      "poles": [{"frequency_hz": f, "damping": 0.001} for f in MODES_HZ]})
    d = driver()
    try:
        result = run_sweep(d, plan, tmp_path / "run.h5", sensors=SENSORS, drive=DRIVE, level_n=0.3)
    finally:
        d.close()
    assert result.status == "completed"
    run = read_run(tmp_path / "run.h5")
    assert run.status == "completed" and run.hardware["driver"] == "visa"
    exact = plant().frf(run.frequency_hz)
    ratio = run.frf / exact
    assert np.max(np.abs(np.abs(ratio) - 1)) < 0.005
    assert np.max(np.abs(np.degrees(np.angle(ratio)))) < 0.5
    for f0 in MODES_HZ:  # the peaks were measured (lines within a half-power bandwidth)
        assert np.min(np.abs(run.frequency_hz - f0)) <= 0.001 * f0
    assert np.all(np.abs(run.force_n[:, 0] / 0.3 - 1) < 0.02)
    assert not run.flags.any()
    assert d.lab.drive_v_peak == 0.0


FAULTS = [
    # (instrument, kind, command, skip, expected message)
    ("lockin_resp1", "timeout", "SNAP?", 60, r"lock-in a2 \(TCPIP::127.0.0.1::\d+::SOCKET\): no reply to 'SNAP\? 1,2' within 300 ms"),
    ("lockin_force0", "garble", "SNAP?", 60, r"lock-in force .*: garbled reply to 'SNAP\? 1,2'"),
    ("generator", "error", "FREQ", 4, r"generator .*: instrument error queue: -222,'Data out of range'"),
    # pyvisa-py sees a raw socket closed by the peer as a reply that never comes
    ("generator", "drop", "VOLT", 8, r"generator .*: (connection lost during 'VOLT|no reply to 'SYST:ERR\?')"),
    ("lockin_resp0", "drop", "LIAS?", 60, r"lock-in a1 .*(connection lost|no reply) .*'LIAS\?'"),
]


@pytest.mark.parametrize("instrument, kind, command, skip, message", FAULTS,
                         ids=[f"{f[1]}-{f[0]}" for f in FAULTS])
def test_fault_aborts_ramps_down_and_keeps_completed_lines(tmp_path, instrument, kind, command, skip, message):
    plan = make_plan({"kind": "linear", "start_hz": 170.0, "stop_hz": 240.0, "step_hz": 5.0})
    d = driver()
    d.lab.inject(instrument, kind, command, skip=skip)
    done = []
    path = tmp_path / "run.h5"
    try:
        with pytest.raises(DriverError, match=message):
            run_sweep(d, plan, path, sensors=SENSORS, drive=DRIVE, level_n=0.3,
                      on_line=lambda f, frf, q: done.append((f, frf.copy())))
        # drive ramped to zero and the output switched off, on the instrument itself
        assert d.lab.drive_v_peak == 0.0 and not d.lab.generator.output
        tail = [c for i, c, _ in d.lab.transcript if i == "generator"][-2:]
        assert tail == ["OUTP OFF", "SYST:ERR?"]
    finally:
        d.close()
    run = read_run(path)
    assert run.status == "aborted"
    assert 0 < len(done) < 15  # the fault struck mid-sweep
    # nothing completed is lost: every line reported complete is in the file, unchanged
    np.testing.assert_array_equal(run.frequency_hz, [f for f, _ in done])
    np.testing.assert_array_equal(run.frf, np.array([h for _, h in done]))
    ratio = run.frf / plant().frf(run.frequency_hz)
    assert np.max(np.abs(ratio - 1)) < 0.005

    # ... and the run resumes on a fresh connection and completes
    d2 = driver(seed=1)
    try:
        result = run_sweep(d2, plan, path, sensors=SENSORS, drive=DRIVE, level_n=0.3, resume=True)
    finally:
        d2.close()
    assert result.status == "completed" and result.n_new_lines == 15 - len(done)
    run = read_run(path)
    assert run.status == "completed"
    np.testing.assert_allclose(np.sort(run.frequency_hz), np.arange(170.0, 240.1, 5.0))
