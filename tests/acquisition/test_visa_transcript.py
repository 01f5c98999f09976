"""Transcript tests: every SCPI command and query the VISA driver sends, in order.

The transcript is recorded by the loopback server, i.e. it is what crossed
the socket through pyvisa + pyvisa-py, not what the driver meant to send.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pyvisa")
pytest.importorskip("pyvisa_py")

from acquisition import ChannelSpec, ModalPlant  # noqa: E402
from acquisition._scpi_server import loopback_visa_driver  # noqa: E402

pytestmark = pytest.mark.timeout(60)

CHANNELS = (
    ChannelSpec("force", "force", "force", "N", sensitivity=0.0225, physical="sim/force", range_v=1.0),
    ChannelSpec("acc1", "response", "acceleration", "m/s^2", sensitivity=0.0102, physical="sim/0", range_v=0.1),
)

GENERATOR_SETUP = [
    ("generator", "*IDN?", "Agilent Technologies,33522B,MY00000001,4.00-loopback"),
    ("generator", "*RST", None),
    ("generator", "*CLS", None),
    ("generator", "OUTP OFF", None),
    ("generator", "OUTP:LOAD INF", None),
    ("generator", "FUNC SIN", None),
    ("generator", "VOLT:UNIT VPP", None),
    ("generator", "VOLT:OFFS 0", None),
    ("generator", "VOLT 0.001", None),
    ("generator", "OUTP:SYNC ON", None),
    ("generator", "SYST:ERR?", '+0,"No error"'),
]


def lockin_setup(name: str, sens: int) -> list:
    return [
        (name, "*IDN?", f"Stanford_Research_Systems,SR830,s/n{name},ver1.07-loopback"),
        (name, "*RST", None),
        (name, "*CLS", None),
        (name, "FMOD 0", None),  # external reference (the generator's sync output)
        (name, "RSLP 1", None),  # TTL rising edge
        (name, "ISRC 0", None),  # input A
        (name, "ICPL 0", None),  # AC coupling
        (name, "IGND 0", None),
        (name, "HARM 1", None),
        (name, f"SENS {sens}", None),
        (name, "OFSL 3", None),  # 24 dB/octave
        (name, "LIAS?", "0"),
    ]


@pytest.fixture
def driver():
    p = ModalPlant([120.0, 310.0], 0.001, np.array([[1.0, 0.6]]), np.array([[0.8, 0.5]]))
    d = loopback_visa_driver(p, lab_options={"lifetime_s": 60})
    yield d
    d.close()


def commands(transcript):
    return [(inst, cmd) for inst, cmd, _ in transcript]


def test_setup_transcript(driver):
    driver.configure(CHANNELS, None)
    # range 1 V peak = 0.71 V rms -> SENS 26 (1 V); 0.1 V peak = 71 mV rms -> SENS 23 (100 mV)
    expected = GENERATOR_SETUP + lockin_setup("lockin_force0", 26) + lockin_setup("lockin_resp0", 23)
    assert driver.lab.transcript == expected
    # the driver's own log agrees with what the server received
    names = {"generator": "generator", "lock-in force": "lockin_force0", "lock-in acc1": "lockin_resp0"}
    assert [(names[i], c) for i, c in commands(driver.log)] == commands(expected)


def test_line_transcript(driver):
    driver.configure(CHANNELS, None)
    n = len(driver.lab.transcript)
    driver.set_drive(100.0, 0.25)
    driver.read_block(10)
    driver.read_block(10)
    driver.set_drive(100.0, 0.3)  # force-control correction: amplitude only
    driver.read_block(10)
    driver.set_drive(100.4, 0.3)  # next line: frequency only
    driver.read_block(10)
    # 10 cycles at 100 Hz = 0.1 s; largest time constant <= 10 ms is 10 ms (OFLT 6)
    snap = [("lockin_force0", "SNAP? 1,2"), ("lockin_force0", "LIAS?"),
            ("lockin_resp0", "SNAP? 1,2"), ("lockin_resp0", "LIAS?")]
    expected = [
        ("generator", "FREQ 100"), ("generator", "VOLT 0.5"), ("generator", "OUTP ON"), ("generator", "SYST:ERR?"),
        ("lockin_force0", "OFLT 6"), ("lockin_force0", "OFLT?"),
        ("lockin_resp0", "OFLT 6"), ("lockin_resp0", "OFLT?"),
        *snap,
        *snap,
        ("generator", "VOLT 0.6"), ("generator", "SYST:ERR?"),
        *snap,
        ("generator", "FREQ 100.4"), ("generator", "SYST:ERR?"),
        ("lockin_force0", "OFLT 5"), ("lockin_force0", "OFLT?"),  # 99.6 ms block: 3 ms
        ("lockin_resp0", "OFLT 5"), ("lockin_resp0", "OFLT?"),
        *snap,
    ]
    assert commands(driver.lab.transcript[n:]) == expected
    replies = [r for _, c, r in driver.lab.transcript[n:] if c == "SYST:ERR?"]
    assert replies == ['+0,"No error"'] * 3


def test_abort_transcript(driver):
    driver.configure(CHANNELS, None)
    driver.set_drive(150.0, 0.5)
    driver.read_block(10)
    n = len(driver.lab.transcript)
    driver.ramp_down(0.25)  # 5 steps of 50 ms
    driver.ramp_down(0.25)  # again: only confirms the output off
    expected = [
        ("generator", "VOLT 0.8"), ("generator", "VOLT 0.6"), ("generator", "VOLT 0.4"), ("generator", "VOLT 0.2"),
        ("generator", "VOLT 0.001"), ("generator", "OUTP OFF"), ("generator", "SYST:ERR?"),
        ("generator", "OUTP OFF"), ("generator", "SYST:ERR?"),
    ]
    assert commands(driver.lab.transcript[n:]) == expected
    assert driver.lab.drive_v_peak == 0.0
    m = len(driver.lab.transcript)
    driver.close()  # already off: close sends nothing more
    assert len(driver.lab.transcript) == m
