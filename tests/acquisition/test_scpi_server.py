"""The loopback SCPI server on its own: raw sockets, no pyvisa (protocol, faults, bounds)."""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from acquisition import ModalPlant
from acquisition._scpi_server import LoopbackLab, VirtualClock

pytestmark = pytest.mark.timeout(30)


def plant():
    return ModalPlant([100.0], 0.01, np.array([[1.0]]), np.array([[1.0]]))


def ask(sock, line: str) -> str:
    sock.sendall((line + "\n").encode())
    data = b""
    while not data.endswith(b"\n"):
        chunk = sock.recv(4096)
        if not chunk:
            raise ConnectionError("closed")
        data += chunk
    return data.decode("latin-1").rstrip("\n")


@pytest.fixture
def lab():
    with LoopbackLab(plant(), lifetime_s=20) as lab:
        yield lab


def connect(lab, instrument):
    s = socket.create_connection(("127.0.0.1", lab.port(instrument)), timeout=2)
    return s


def test_binds_only_loopback_on_free_ports(lab):
    ports = {lab.port(name) for name in ["generator", *lab.lockins]}
    assert len(ports) == 2 + lab.n_out + lab.n_in  # generator, drive monitor, one per input and output
    for server in lab._servers.values():
        assert server.server_address[0] == "127.0.0.1"


def test_generator_state_error_queue_and_compound_lines(lab):
    with connect(lab, "generator") as s:
        assert ask(s, "FREQ 123.5;VOLT 0.4;OUTP ON;FREQ?").startswith("+1.23500000000000E+02")
        assert lab.drive_v_peak == pytest.approx(0.2)
        s.sendall(b"VOLT 99\n")  # out of range: refused, queued
        s.sendall(b"BOGUS 1\n")
        assert ask(s, "SYST:ERR?") == '-222,"Data out of range"'
        assert ask(s, "SYST:ERR?") == '-113,"Undefined header; BOGUS"'
        assert ask(s, "SYST:ERR?") == '+0,"No error"'
        assert lab.generator.vpp == 0.4


def test_lockin_reads_the_plant_in_volts_rms(lab):
    lab.set_sensitivity("lockin_resp0", 0.01)
    lab.noise_v_per_rthz = 0.0
    with connect(lab, "generator") as g, connect(lab, "lockin_resp0") as li:
        ask(g, "FREQ 90;VOLT 1;OUTP ON;*OPC?")
        lab.clock.sleep(100.0)  # far beyond the default 1 s time constant
        x, y = (float(v) for v in ask(li, "SNAP? 1,2").split(","))
        expected = 0.01 * plant().frf([90.0])[0, 0, 0] * lab.force_phasor()[0] / np.sqrt(2)
        assert complex(x, y) == pytest.approx(expected, rel=1e-6)
        r, theta = (float(v) for v in ask(li, "SNAP? 3,4").split(","))
        assert r == pytest.approx(abs(expected), rel=1e-6)
        assert theta == pytest.approx(np.degrees(np.angle(expected)), abs=1e-4)


@pytest.mark.parametrize("kind", ["timeout", "garble", "drop"])
def test_faults_on_raw_sockets(lab, kind):
    lab.inject("lockin_resp0", kind, "*IDN?")
    with connect(lab, "lockin_resp0") as s:
        s.settimeout(0.3)
        if kind == "timeout":
            with pytest.raises(socket.timeout):
                ask(s, "*IDN?")
        elif kind == "garble":
            reply = ask(s, "*IDN?")
            assert "SR830" not in reply and not reply.isprintable()
        else:
            with pytest.raises((ConnectionError, OSError)):
                ask(s, "*IDN?")
    with connect(lab, "lockin_resp0") as s:  # one-shot: the next connection is healthy
        assert "SR830" in ask(s, "*IDN?")


def test_fault_arguments_are_checked(lab):
    with pytest.raises(ValueError, match="fault kind"):
        lab.inject("generator", "explode")
    with pytest.raises(ValueError, match="no instrument 'scope'"):
        lab.inject("scope", "drop")
    with pytest.raises(ValueError, match="only the generator has an error queue"):
        lab.inject("lockin_resp0", "error")


def test_server_stops_by_itself():
    lab = LoopbackLab(plant(), clock=VirtualClock(), lifetime_s=0.5).start()
    port = lab.port("generator")
    t0 = time.monotonic()
    assert lab.stopped.wait(10)
    assert time.monotonic() - t0 < 5
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
