"""Loopback SCPI instrument server: a function generator and lock-ins answering from a plant.

Each emulated instrument listens on its own TCP port on 127.0.0.1 (a free port
chosen by the OS), like a LAN instrument's raw socket, so the VISA driver
reaches it through the real pyvisa + pyvisa-py stack as
``TCPIP::127.0.0.1::PORT::SOCKET``. Lines end with ``\\n``; ``;`` separates
commands on one line.

Physics: the generator drives a shaker (:meth:`LoopbackLab.shaker_gain`: an
:class:`acquisition.ShakerModel` loaded by the drive-point receptance, so the
force drops at resonances, or a plain gain with a roll-off); the lock-in on a force
channel sees that force, the lock-in on a response channel sees the plant's
exact steady-state response ``plant.frf(f) @ force`` (any object with
``frf(freq_hz) -> (n_f, n_out, n_in)``, e.g. :class:`acquisition.ModalPlant`),
both times the channel's sensitivity (V per SI unit). The lock-in output
follows a change of frequency or amplitude through its cascade of RC stages
(time constant ``OFLT``, slope ``OFSL``) in exact closed form, and carries
Gaussian noise of the input noise density over the filter's equivalent noise
bandwidth. Structural transients are not modelled here (the simulated lab
does that); this server tests the instrument stack, not the settle detector.

Time is a :class:`VirtualClock` shared with the driver in the same process:
it moves only when the driver sleeps, so a loopback run is deterministic and
much faster than real time. Because the driver synchronizes with a query
(``SYST:ERR?``) after every setting, each setting is time-stamped before the
driver's next sleep.

Faults are injected with :meth:`LoopbackLab.inject`: ``"timeout"`` (the
query is never answered), ``"garble"`` (the reply is noise), ``"error"`` (an
entry is pushed on the generator's error queue), ``"drop"`` (the connection
is closed). Servers are bounded: they stop by themselves after
``lifetime_s`` and bind 127.0.0.1 unless another ``host`` is named.
"""

from __future__ import annotations

import math
import socket
import socketserver
import threading
from dataclasses import dataclass, field, replace

import numpy as np

from acquisition._scpi import (
    LIAS_INPUT_OVERLOAD,
    LIAS_OUTPUT_OVERLOAD,
    LIAS_UNLOCK,
    SR830_SENSITIVITIES_V,
    SR830_SLOPES_DB,
    SR830_TIME_CONSTANTS_S,
    enbw_hz,
)

FAULT_KINDS = ("timeout", "garble", "error", "drop")
#: Input overload of the emulated lock-in, peak volts.
LOCKIN_INPUT_LIMIT_V = 1.4


class VirtualClock:
    """A clock that advances only when somebody sleeps on it (thread-safe)."""

    def __init__(self, start_s: float = 0.0):
        self._t = float(start_s)
        self._lock = threading.Lock()

    def now(self) -> float:
        with self._lock:
            return self._t

    def sleep(self, duration_s: float) -> None:
        with self._lock:
            self._t += max(0.0, float(duration_s))


@dataclass
class _Fault:
    instrument: str
    kind: str
    match: str
    skip: int
    count: int
    message: str


@dataclass
class _Generator:
    frequency_hz: float = 1000.0
    vpp: float = 0.1
    output: bool = False
    load: str = "50"
    function: str = "SIN"
    unit: str = "VPP"
    sync: bool = False
    errors: list = field(default_factory=list)


@dataclass
class _Lockin:
    name: str
    role: str  # "force" or "response"
    index: int
    sensitivity_v_per_unit: float = 1.0
    conditioner_gain: float = 1.0
    sens: int = 26
    oflt: int = 10
    ofsl: int = 1
    status: int = 0
    fmod: int = 1
    stages: np.ndarray = field(default_factory=lambda: np.zeros(4, complex))
    target: complex = 0j
    t_s: float = 0.0
    unlocked_until: float = -math.inf


def _advance_stages(stages: np.ndarray, target: complex, x: float) -> np.ndarray:
    """Cascade of RC stages with constant input ``target`` advanced by ``x`` time constants.

    With deviations e_k = s_k - u the cascade e_1' = -e_1, e_k' = e_{k-1} - e_k
    (in units of tau) has the closed form e_k(x) = e^{-x} sum_{j<=k} e_j(0) x^{k-j}/(k-j)!.
    """
    e0 = stages - target
    out = np.empty_like(e0)
    decay = math.exp(-x) if x < 700 else 0.0
    for k in range(e0.size):
        acc = 0j
        for j in range(k + 1):
            acc += e0[j] * x ** (k - j) / math.factorial(k - j)
        out[k] = decay * acc
    return out + target


class LoopbackLab:
    """A generator and one lock-in per plant input and output, served on 127.0.0.1.

    Parameters
    ----------
    plant : object with ``frf(freq_hz) -> (n_f, n_out, n_in)``
        The structure (SI: force in N, response in the plant's quantity).
    clock : VirtualClock, optional
        Shared with the driver; a new one by default.
    shaker_n_per_v, shaker_corner_hz : float
        Shaker + amplifier without a ``shaker`` model: force per generator
        volt (N/V, peak) at low frequency and a first-order roll-off corner (Hz).
    shaker : acquisition.ShakerModel, optional
        Electrodynamic shaker loading the drive point (see :meth:`shaker_gain`).
    noise_v_per_rthz : float
        Noise density of each channel referred to the sensor output (V/sqrt(Hz)).
    drive_input : int
        The plant input the shaker drives.
    relock_cycles : float
        After a frequency change every lock-in reports reference unlock
        (``LIAS?`` bit 3, latched) until this many cycles of the new frequency
        have passed; 0 (default) re-locks instantly.
    seed : int
    lifetime_s : float
        Wall-clock seconds after which the servers stop by themselves.
    host : str
        Interface the instruments listen on: loopback (127.0.0.1) unless
        another address is named (a lab reachable from other machines).
    """

    def __init__(
        self,
        plant,
        *,
        clock: VirtualClock | None = None,
        shaker_n_per_v: float = 5.0,
        shaker_corner_hz: float = 2000.0,
        shaker=None,
        noise_v_per_rthz: float = 20e-9,
        drive_input: int = 0,
        relock_cycles: float = 0.0,
        seed: int = 0,
        lifetime_s: float = 600.0,
        host: str = "127.0.0.1",
    ):
        self.plant = plant
        self.host = str(host)
        self.clock = clock if clock is not None else VirtualClock()
        self.shaker_n_per_v = float(shaker_n_per_v)
        self.shaker_corner_hz = float(shaker_corner_hz)
        self.shaker = shaker
        self.noise_v_per_rthz = float(noise_v_per_rthz)
        self.drive_input = int(drive_input)
        self.relock_cycles = float(relock_cycles)
        self.lifetime_s = float(lifetime_s)
        self._rng = np.random.default_rng(seed)
        self._lock = threading.RLock()
        h = np.asarray(plant.frf(np.array([100.0])))
        if h.ndim != 3:
            raise ValueError(f"plant.frf must return (n_f, n_out, n_in), got shape {h.shape}")
        self.n_out, self.n_in = h.shape[1], h.shape[2]
        if not 0 <= self.drive_input < self.n_in:
            raise ValueError(f"drive_input {drive_input} is not an input of a plant with {self.n_in} inputs")
        self.generator = _Generator()
        self.lockins: dict[str, _Lockin] = {}
        for i in range(self.n_in):
            self.lockins[f"lockin_force{i}"] = _Lockin(f"lockin_force{i}", "force", i)
        for o in range(self.n_out):
            self.lockins[f"lockin_resp{o}"] = _Lockin(f"lockin_resp{o}", "response", o)
        self.lockins["lockin_drive"] = _Lockin("lockin_drive", "drive", 0)
        self.transcript: list[tuple[str, str, str | None]] = []
        self._faults: list[_Fault] = []
        self._servers: dict[str, socketserver.ThreadingTCPServer] = {}
        self._threads: list[threading.Thread] = []
        self._timer: threading.Timer | None = None
        self._frf_cache: dict[float, np.ndarray] = {}
        #: Set once every server is shut down and its sockets are closed.
        self.stopped = threading.Event()

    # ------------------------------------------------------------ lifecycle
    def start(self) -> "LoopbackLab":
        """Bind every instrument to a free port on ``host`` (127.0.0.1) and serve in daemon threads."""
        for name in ["generator", *self.lockins]:
            server = _InstrumentServer((self.host, 0), _Handler)
            server.lab = self
            server.instrument = name
            self._servers[name] = server
            t = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
            t.start()
            self._threads.append(t)
        self._timer = threading.Timer(self.lifetime_s, self.stop)
        self._timer.daemon = True
        self._timer.start()
        return self

    def stop(self) -> None:
        """Stop serving and close every connection (idempotent)."""
        servers, self._servers = self._servers, {}
        stoppers = [threading.Thread(target=server.shutdown) for server in servers.values()]
        for t in stoppers:  # in parallel: each waits up to one poll interval
            t.start()
        for t in stoppers:
            t.join()
        for server in servers.values():
            server.server_close()
            server.close_connections()
        if self._timer is not None:
            self._timer.cancel()
        if servers:
            self.stopped.set()

    def __enter__(self) -> "LoopbackLab":
        return self.start() if not self._servers else self

    def __exit__(self, *exc) -> None:
        self.stop()

    def port(self, instrument: str) -> int:
        return self._servers[instrument].server_address[1]

    def addresses(self) -> dict:
        """``{instrument: (address, port)}`` every server is bound to."""
        return {name: tuple(srv.server_address[:2]) for name, srv in self._servers.items()}

    def resource(self, instrument: str) -> str:
        """VISA resource string of an instrument, ``TCPIP::<host>::PORT::SOCKET`` (host 127.0.0.1 by default)."""
        return f"TCPIP::{self.host}::{self.port(instrument)}::SOCKET"

    @property
    def generator_resource(self) -> str:
        return self.resource("generator")

    def lockin_for(self, channel) -> str:
        """The lock-in that measures a channel, addressed as on the simulated lab.

        ``physical="sim/<k>"`` is plant output k, ``"sim/force"`` (or role
        ``"force"`` without an address) the drive-point force, ``"sim/drive"``
        (or role ``"monitor"``) the drive voltage; response channels without an
        address take plant outputs in the order they are asked for.
        """
        phys = channel.physical
        if phys == "sim/force" or (not phys and channel.role == "force"):
            return f"lockin_force{self.drive_input}"
        if phys == "sim/drive" or (not phys and channel.role == "monitor"):
            return "lockin_drive"
        if phys.startswith("sim/"):
            try:
                k = int(phys[4:])
            except ValueError:
                raise ValueError(f"channel {channel.name!r}: bad simulated address {phys!r}") from None
            if not 0 <= k < self.n_out:
                raise ValueError(f"channel {channel.name!r}: the plant has outputs 0..{self.n_out - 1}, got {phys!r}")
            return f"lockin_resp{k}"
        raise ValueError(f"channel {channel.name!r}: the loopback lab cannot measure {phys!r}")

    def set_sensitivity(self, instrument: str, sensitivity_v_per_unit: float, conditioner_gain: float = 1.0) -> None:
        """The sensor behind a lock-in: volts per SI unit at the lock-in input (sensor x conditioner).

        ``conditioner_gain`` is the part of it due to the signal conditioner;
        the noise density is referred to the sensor, so it scales with it.
        """
        with self._lock:
            self.lockins[instrument].sensitivity_v_per_unit = float(sensitivity_v_per_unit)
            self.lockins[instrument].conditioner_gain = float(conditioner_gain)

    # ------------------------------------------------------------ faults
    def inject(self, instrument: str, kind: str, match: str = "", *, skip: int = 0, count: int = 1,
               message: str = '-222,"Data out of range"') -> None:
        """Arm a fault on the next command(s) of ``instrument`` starting with ``match``.

        ``skip`` matching commands pass first; the fault then fires ``count``
        times. ``"timeout"`` and ``"garble"`` act on queries (a command without
        a reply is unaffected), ``"error"`` pushes ``message`` on the
        generator's error queue after the command, ``"drop"`` closes the
        connection instead of executing the command.
        """
        if kind not in FAULT_KINDS:
            raise ValueError(f"fault kind must be one of {FAULT_KINDS}, got {kind!r}")
        if instrument != "generator" and instrument not in self.lockins:
            raise ValueError(f"no instrument {instrument!r}; have generator, {', '.join(self.lockins)}")
        if kind == "error" and instrument != "generator":
            raise ValueError("only the generator has an error queue (SYST:ERR?); inject 'error' there")
        with self._lock:
            self._faults.append(_Fault(instrument, kind, match.upper(), skip, count, message))

    def _take_fault(self, instrument: str, command: str) -> _Fault | None:
        with self._lock:
            for f in self._faults:
                if f.instrument == instrument and command.upper().startswith(f.match) and f.count > 0:
                    if f.skip > 0:
                        f.skip -= 1
                        return None
                    f.count -= 1
                    return f
        return None

    # ------------------------------------------------------------ physics
    @property
    def drive_v_peak(self) -> float:
        """Generator output, peak volts (0 with the output off)."""
        g = self.generator
        return g.vpp / 2.0 if g.output else 0.0

    def _frf(self, f: float) -> np.ndarray:
        h = self._frf_cache.get(f)
        if h is None:
            h = np.asarray(self.plant.frf(np.array([f])))[0]
            self._frf_cache[f] = h
        return h

    def shaker_gain(self, frequency_hz: float) -> complex:
        """Force per generator volt at the drive point, N/V (complex).

        With a ``shaker`` (:class:`acquisition.ShakerModel`) and a plant that
        knows its drive-point receptance X, the back-EMF, armature mass and
        suspension load the drive point, ``F = G V / (1 + Z_s X)`` with
        ``Z_s = s m_a + c_e + k_s / s``, so the force drops at resonances;
        otherwise ``shaker_n_per_v / (1 + i f / shaker_corner_hz)``.
        """
        cd = getattr(self.plant, "drive_point_form", lambda: None)()
        if self.shaker is not None and cd is not None:
            sh = self.shaker
            s = 2j * np.pi * frequency_hz
            poles, bz, _, _ = self.plant.diagonal_form()
            x_dp = (cd[self.drive_input] / (s - poles)) @ bz[:, self.drive_input]
            z_s = s * sh.armature_mass_kg + sh.electrical_damping_ns_per_m + sh.suspension_stiffness_n_per_m / s
            return complex(sh.gain_n_per_v / (1 + z_s * s * x_dp))
        if self.shaker is not None:
            return complex(self.shaker.gain_n_per_v)
        return complex(self.shaker_n_per_v / (1 + 1j * frequency_hz / self.shaker_corner_hz))

    def force_phasor(self) -> np.ndarray:
        """Force at each plant input, complex peak N (only the driven input is non-zero)."""
        f = np.zeros(self.n_in, complex)
        f[self.drive_input] = self.drive_v_peak * self.shaker_gain(self.generator.frequency_hz)
        return f

    def _targets(self) -> dict[str, complex]:
        force = self.force_phasor()
        resp = self._frf(self.generator.frequency_hz) @ force if self.drive_v_peak > 0 else np.zeros(self.n_out, complex)
        out = {}
        for name, li in self.lockins.items():
            if li.role == "force":
                q = force[li.index]
            elif li.role == "response":
                q = resp[li.index]
            else:
                q = self.drive_v_peak  # the drive itself: phase 0 against the reference
            out[name] = complex(q) * li.sensitivity_v_per_unit
        return out

    def _advance(self) -> None:
        """Bring every lock-in filter to now under the current (constant) inputs."""
        now = self.clock.now()
        for li in self.lockins.values():
            dt = now - li.t_s
            if dt > 0:
                tau = SR830_TIME_CONSTANTS_S[li.oflt]
                li.stages = _advance_stages(li.stages, li.target, dt / tau)
            li.t_s = now

    def _retarget(self) -> None:
        targets = self._targets()
        for name, li in self.lockins.items():
            li.target = targets[name]
            if abs(li.target) > LOCKIN_INPUT_LIMIT_V:
                li.status |= LIAS_INPUT_OVERLOAD

    def _reading(self, li: _Lockin) -> complex:
        """X + iY in V rms at the filter output, with noise over the filter ENBW."""
        n_stages = SR830_SLOPES_DB[li.ofsl] // 6
        value = li.stages[n_stages - 1] / math.sqrt(2.0)
        sigma = self.noise_v_per_rthz * li.conditioner_gain * math.sqrt(enbw_hz(SR830_TIME_CONSTANTS_S[li.oflt], SR830_SLOPES_DB[li.ofsl]))
        value += complex(*self._rng.normal(0.0, sigma, 2))
        if abs(value) > SR830_SENSITIVITIES_V[li.sens]:
            li.status |= LIAS_OUTPUT_OVERLOAD
        return value

    # ------------------------------------------------------------ commands
    def handle(self, instrument: str, command: str) -> tuple[str | None, str | None]:
        """Process one command; returns (reply or None, fault kind or None)."""
        fault = self._take_fault(instrument, command)
        if fault is not None and fault.kind == "drop":
            self.transcript.append((instrument, command, None))
            return None, "drop"
        with self._lock:
            self._advance()
            if instrument == "generator":
                reply = self._generator_command(command)
            else:
                reply = self._lockin_command(self.lockins[instrument], command)
            self._retarget()
            if fault is not None and fault.kind == "error" and instrument == "generator":
                self.generator.errors.append(fault.message)
        if fault is not None and fault.kind == "garble" and reply is not None:
            reply = "\x7f#?%" + "".join(reversed(reply))[:5] + "\x1a"
        if fault is not None and fault.kind == "timeout":
            reply = None
        self.transcript.append((instrument, command, reply))
        return reply, (fault.kind if fault is not None else None)

    def _generator_command(self, command: str) -> str | None:
        g = self.generator
        head, _, arg = command.strip().partition(" ")
        head = head.upper()
        arg = arg.strip()

        def number(lo: float, hi: float) -> float | None:
            try:
                v = float(arg)
            except ValueError:
                g.errors.append('-104,"Data type error"')
                return None
            if not lo <= v <= hi:
                g.errors.append('-222,"Data out of range"')
                return None
            return v

        if head == "*IDN?":
            return "Agilent Technologies,33522B,MY00000001,4.00-loopback"
        if head == "*RST":
            self.generator = _Generator(errors=g.errors)
            return None
        if head == "*CLS":
            g.errors.clear()
            return None
        if head == "*OPC?":
            return "1"
        if head == "SYST:ERR?":
            return g.errors.pop(0) if g.errors else '+0,"No error"'
        if head in ("OUTP", "OUTPUT"):
            if arg.upper() in ("ON", "1"):
                g.output = True
            elif arg.upper() in ("OFF", "0"):
                g.output = False
            else:
                g.errors.append('-224,"Illegal parameter value"')
            return None
        if head == "OUTP?":
            return "1" if g.output else "0"
        if head == "OUTP:LOAD":
            g.load = arg.upper()
            return None
        if head == "OUTP:SYNC":
            g.sync = arg.upper() in ("ON", "1")
            return None
        if head == "FUNC":
            g.function = arg.upper()
            return None
        if head == "VOLT:UNIT":
            g.unit = arg.upper()
            return None
        if head == "VOLT:OFFS":
            number(-10.0, 10.0)
            return None
        if head == "FREQ":
            v = number(1e-6, 30e6)
            if v is not None:
                if v != g.frequency_hz and self.relock_cycles > 0:
                    # the lock-ins' reference PLLs re-lock onto the new sync frequency
                    until = self.clock.now() + self.relock_cycles / v
                    for li in self.lockins.values():
                        li.unlocked_until = until
                        li.status |= LIAS_UNLOCK
                g.frequency_hz = v  # phase-continuous on a 33500B: no transient to model
            return None
        if head == "FREQ?":
            return f"{g.frequency_hz:+.14E}"
        if head == "VOLT":
            v = number(0.001, 20.0)
            if v is not None:
                g.vpp = v
            return None
        if head == "VOLT?":
            return f"{g.vpp:+.14E}"
        g.errors.append(f'-113,"Undefined header; {head}"')
        return None

    def _lockin_command(self, li: _Lockin, command: str) -> str | None:
        head, _, arg = command.strip().partition(" ")
        head = head.upper()
        arg = arg.strip()

        def index(n: int) -> int | None:
            try:
                i = int(arg)
            except ValueError:
                return None
            return i if 0 <= i < n else None

        if head == "*IDN?":
            return f"Stanford_Research_Systems,SR830,s/n{li.name},ver1.07-loopback"
        if head in ("*RST", "*CLS"):
            if head == "*RST":
                li.sens, li.oflt, li.ofsl = 26, 10, 1
            li.status = 0
            return None
        if head in ("FMOD", "RSLP", "ISRC", "ICPL", "IGND", "HARM", "OUTX"):
            return None
        if head in ("SENS", "OFLT", "OFSL"):
            i = index({"SENS": 27, "OFLT": 20, "OFSL": 4}[head])
            if i is not None:
                setattr(li, head.lower(), i)
            return None
        if head in ("SENS?", "OFLT?", "OFSL?"):
            return str(getattr(li, head[:-1].lower()))
        if head == "FREQ?":
            return f"{self.generator.frequency_hz:.6f}"
        if head == "LIAS?":
            status, li.status = li.status, 0
            if self.clock.now() < li.unlocked_until:
                li.status |= LIAS_UNLOCK  # still re-locking: latched again
            return str(status)
        if head in ("SNAP?", "OUTP?"):
            z = self._reading(li)
            values = {1: z.real, 2: z.imag, 3: abs(z), 4: math.degrees(math.atan2(z.imag, z.real)),
                      9: self.generator.frequency_hz}
            try:
                which = [int(p) for p in arg.split(",")]
                return ",".join(f"{values[w]:.6e}" for w in which)
            except (ValueError, KeyError):
                return None
        return None  # an SR830 ignores what it does not know (and sets an ERRS bit)


class _InstrumentServer(socketserver.ThreadingMixIn, socketserver.TCPServer):
    daemon_threads = True
    allow_reuse_address = True
    lab: LoopbackLab
    instrument: str

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._connections: set[socket.socket] = set()
        self._conn_lock = threading.Lock()

    def track(self, sock: socket.socket, add: bool) -> None:
        with self._conn_lock:
            (self._connections.add if add else self._connections.discard)(sock)

    def close_connections(self) -> None:
        with self._conn_lock:
            for sock in list(self._connections):
                try:
                    sock.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                sock.close()
            self._connections.clear()


class _Handler(socketserver.StreamRequestHandler):
    def setup(self) -> None:
        super().setup()
        self.request.settimeout(self.server.lab.lifetime_s)
        self.server.track(self.request, True)

    def finish(self) -> None:
        self.server.track(self.request, False)
        try:
            super().finish()
        except OSError:
            pass

    def handle(self) -> None:
        lab: LoopbackLab = self.server.lab
        name = self.server.instrument
        while True:
            try:
                raw = self.rfile.readline()
            except OSError:
                return
            if not raw:
                return
            line = raw.decode("ascii", errors="replace").strip()
            if not line:
                continue
            replies = []
            for command in (c.strip() for c in line.split(";")):
                if not command:
                    continue
                reply, fault = lab.handle(name, command)
                if fault == "drop":
                    self.request.shutdown(socket.SHUT_RDWR)
                    return
                if reply is not None:
                    replies.append(reply)
            if replies:
                try:
                    self.wfile.write((";".join(replies) + "\n").encode("latin-1"))
                    self.wfile.flush()
                except OSError:
                    return


def loopback_visa_driver(plant, *, lab_options: dict | None = None, **driver_options):
    """A :class:`~acquisition.drivers.visa.VisaDriver` talking to its own :class:`LoopbackLab`.

    The lab is started on 127.0.0.1 with a :class:`VirtualClock` shared with
    the driver. At :meth:`configure` each channel is wired to a lock-in by its
    simulated-lab address (:meth:`LoopbackLab.lockin_for`), and the lock-in's
    sensor gets the channel's sensitivity (the mapping a user makes once in
    the hardware configuration file). As a lab would, a signal conditioner
    with gain ``min(1, 1 V / range_v)`` sits in front of each lock-in so that
    the channel's range fits the lock-in's 1 V rms full scale (the driver sees
    the combined sensitivity). Closing the driver stops the lab.
    ``driver.lab`` gives access to the lab (fault injection, transcript,
    generator state).
    """
    from acquisition.drivers.visa import VisaDriver

    class LoopbackVisaDriver(VisaDriver):
        def configure(self, channels, sample_rate_hz=None):
            mapped, next_out = [], 0
            for ch in channels:
                if not ch.physical and ch.role == "response":
                    ch = replace(ch, physical=f"sim/{next_out}")
                    next_out += 1
                name = self.lab.lockin_for(ch)
                gain = min(1.0, 1.0 / ch.range_v)  # the signal conditioner in front of the lock-in
                self.lab.set_sensitivity(name, ch.sensitivity * gain, gain)
                mapped.append(replace(ch, physical=self.lab.resource(name), sensitivity=ch.sensitivity * gain,
                                      range_v=ch.range_v * gain))
            return super().configure(mapped, sample_rate_hz)

        @property
        def drive_amplitude_v(self) -> float:
            """The generator's actual output (peak V, 0 when off), read from the instrument model."""
            return self.lab.drive_v_peak

        def close(self):
            try:
                super().close()
            finally:
                self.lab.stop()

    options = dict(lab_options or {})
    clock = options.pop("clock", None) or VirtualClock()
    lab = LoopbackLab(plant, clock=clock, **options).start()
    try:
        driver = LoopbackVisaDriver(lab.generator_resource, clock=clock, **driver_options)
    except Exception:
        lab.stop()
        raise
    driver.lab = lab
    return driver


def make_visa_driver(plant, **options):
    """Factory ``plant -> Driver`` for the controller suite and ``frfcal acquire --driver visa --loopback``.

    A :func:`loopback_visa_driver` with the simulated lab's electrodynamic
    shaker and lock-ins that take 3 cycles to re-lock after a frequency step
    (so the driver discards the first block of every line). ``options`` go to the lab (``noise_v_per_rthz``, ``seed``,
    ``shaker``, ``lifetime_s``...) except the driver's own keywords
    (``timeout_ms``, ``tc_fraction``, ``filter_slope_db``, ``max_drive_v``).
    """
    from acquisition._simlab import ShakerModel

    driver_keys = {"timeout_ms", "tc_fraction", "filter_slope_db", "max_drive_v", "ramp_step_s"}
    driver_options = {k: v for k, v in options.items() if k in driver_keys}
    lab_options = {"shaker": ShakerModel(), "relock_cycles": 3.0} | {
        k: v for k, v in options.items() if k not in driver_keys}
    return loopback_visa_driver(plant, lab_options=lab_options, **driver_options)


def _plan_plant(plan):
    """The plant of a plan's ``[sim]`` section, as ``--driver sim`` builds it."""
    from acquisition._plan import sim_plant_arrays
    from acquisition._plant import ModalPlant

    return ModalPlant(*sim_plant_arrays(plan))


def serve_plan(plan, *, drive: str | None = None, clock=None, noise_v_per_rthz: float = 20e-9,
               lifetime_s: float = 3600.0, host: str = "127.0.0.1") -> tuple[LoopbackLab, str]:
    """Start a loopback lab for a plan and return it with the text of a matching hardware TOML file.

    One lock-in per response channel of the plan, one on the force sensor of
    ``drive`` (the drive point the shaker is on; default the first) and one,
    mapped as ``gen_loopback``, on the generator output. Sensitivities and
    ranges are the plan's, with the loopback signal conditioner
    (``min(1, 1 V / range_v)``) folded in.
    """
    from acquisition._controller import plan_channels
    from acquisition._simlab import ShakerModel
    from acquisition.drivers.visa import WallClock

    sensors, drives = plan_channels(plan)
    names = [d.name for d in drives]
    drive = drive or names[0]
    if drive not in names:
        raise ValueError(f"--drive {drive!r} is not a drive of the plan (have {names})")
    plant = _plan_plant(plan)
    if len(sensors) != plant.n_out or len(drives) != plant.n_in:
        raise ValueError(f"the plan has {len(sensors)} sensors and {len(drives)} drives, the [sim] plant "
                         f"{plant.n_out} outputs and {plant.n_in} inputs")
    shaker = ShakerModel() if plan.sim.shaker == "electrodynamic" else None
    lab = LoopbackLab(plant, clock=clock or WallClock(), shaker=shaker, noise_v_per_rthz=noise_v_per_rthz,
                      drive_input=names.index(drive), lifetime_s=lifetime_s, seed=plan.sim.seed,
                      host=host).start()
    text = ['driver = "visa"', "", "[visa]", f'generator = "{lab.generator_resource}"', "timeout_ms = 3000", ""]
    wiring = [(s, f"lockin_resp{k}") for k, s in enumerate(sensors)]
    wiring.append((drives[names.index(drive)], f"lockin_force{names.index(drive)}"))
    for spec, inst in wiring:
        gain = min(1.0, 1.0 / spec.range_v)
        lab.set_sensitivity(inst, spec.sensitivity * gain, gain)
        text += [f"[channels.{spec.name}]", f'physical = "{lab.resource(inst)}"',
                 f"sensitivity_mv_per_unit = {spec.sensitivity * gain * 1000:.12g}",
                 f"range_v = {spec.range_v * gain:.12g}", ""]
    text += ["[channels.gen_loopback]", f'physical = "{lab.resource("lockin_drive")}"',
             "sensitivity_mv_per_unit = 1000", ""]
    return lab, "\n".join(text)


def main(argv=None) -> int:
    """``python -m acquisition._scpi_server PLAN.toml --hardware-out hw.toml``: a lab to dry-run against."""
    import argparse
    import os
    import time
    from pathlib import Path

    from acquisition._plan import load_plan

    ap = argparse.ArgumentParser(
        prog="python -m acquisition._scpi_server",
        description="Serve a loopback generator and lock-ins on 127.0.0.1 (or --host) answering from a plan's [sim] plant "
                    "(wall clock), and write a hardware TOML file pointing at them.")
    ap.add_argument("plan", help="sweep plan TOML with a [sim] section")
    ap.add_argument("--hardware-out", required=True, help="hardware TOML file to write")
    ap.add_argument("--drive", help="drive point the shaker is on (default: the plan's first)")
    ap.add_argument("--lifetime-s", type=float, default=3600.0, help="stop after this many seconds (default 3600)")
    ap.add_argument("--noise-v-per-rthz", type=float, default=20e-9, help="sensor noise density, V/sqrt(Hz)")
    ap.add_argument("--host", default="127.0.0.1",
                    help="interface to listen on (default 127.0.0.1: loopback only; name another to serve a network)")
    args = ap.parse_args(argv)
    lab, text = serve_plan(load_plan(args.plan), drive=args.drive, noise_v_per_rthz=args.noise_v_per_rthz,
                           lifetime_s=args.lifetime_s, host=args.host)
    out = Path(args.hardware_out)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, out)  # appears complete or not at all
    print(f"loopback lab: generator {lab.generator_resource}; hardware file {out}; "
          f"stops after {args.lifetime_s:g} s or Ctrl-C", flush=True)
    try:
        lab.stopped.wait()
    except KeyboardInterrupt:
        pass
    finally:
        lab.stop()
    return 0


if __name__ == "__main__":  # pragma: no cover - exercised through a subprocess in the tests
    raise SystemExit(main())
