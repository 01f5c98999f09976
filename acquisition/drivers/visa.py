"""VISA driver: a function generator driving the shaker amplifier, one lock-in per channel.

Hardware picture: a Keysight 33500B-style generator feeds the power amplifier;
its sync output is the external reference of one SR830-style lock-in per
measured channel (force sensor and accelerometers, each through its IEPE
signal conditioner). Each lock-in returns the complex amplitude of its
channel relative to the drive, so :meth:`VisaDriver.read_block` returns a
:class:`~acquisition.PhasorBlock`.

Transport (:class:`VisaInstrument`, a pyvisa resource with error mapping and
reconnection) is separate from the command vocabulary
(:mod:`acquisition._scpi`). pyvisa is imported only when a driver opens its
instruments, with an error naming the ``visa`` extra if it is missing.

Timing: after a frequency or amplitude change the lock-ins' output filters
settle; a block of ``n_cycles`` drive cycles is one wait of
``n_cycles / f`` on the driver's clock followed by one ``SNAP? 1,2`` per
lock-in. The lock-in time constant is the largest one not above
``tc_fraction`` times the block length, so successive blocks are nearly
independent and the controller's settle detector sees the filter settle.
Every setting is followed by a ``SYST:ERR?`` query: it reads the generator's
error queue and synchronizes the instrument with the driver's clock.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from acquisition._driver import ChannelSpec, DriverError, DriverInfo, PhasorBlock
from acquisition.drivers import DriverUnavailable
from acquisition._scpi import (
    LIAS_FILTER_OVERLOAD,
    LIAS_INPUT_OVERLOAD,
    LIAS_OUTPUT_OVERLOAD,
    LIAS_UNLOCK,
    GeneratorVocabulary,
    LockinVocabulary,
    ScpiReplyError,
    parse_idn,
    parse_int,
    rms_to_peak,
)

#: Status bits flagged as overload in the block.
LIAS_OVERLOADS = LIAS_INPUT_OVERLOAD | LIAS_FILTER_OVERLOAD | LIAS_OUTPUT_OVERLOAD


def _pyvisa():
    try:
        import pyvisa
    except ImportError as exc:  # pragma: no cover - exercised only without the extra
        raise DriverUnavailable(
            "the VISA driver needs pyvisa (and pyvisa-py for the '@py' backend): "
            "pip install 'frfcal[visa]'"
        ) from exc
    return pyvisa


class WallClock:
    """Real time: ``now()`` is ``time.monotonic()``, ``sleep()`` blocks."""

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, duration_s: float) -> None:
        if duration_s > 0:
            time.sleep(duration_s)


class VisaInstrument:
    """One instrument over VISA: write/query with faults mapped to :class:`DriverError`.

    Every fault (timeout, lost connection, undecodable reply) closes the
    resource, so the next call reconnects on a clean stream; the error message
    names the instrument, its resource and the command.

    Parameters
    ----------
    resource_manager : pyvisa.ResourceManager
    resource : str
        VISA resource string, e.g. ``"TCPIP::192.168.1.20::5025::SOCKET"``.
    name : str
        Human name used in messages (``"generator"``, ``"lock-in acc03"``).
    timeout_ms : int
        VISA I/O timeout.
    log : list, optional
        Receives ``(name, command, reply)`` for every exchange (reply None for writes).
    """

    def __init__(self, resource_manager, resource: str, name: str, timeout_ms: int = 3000, log: list | None = None):
        self._rm = resource_manager
        self.resource = resource
        self.name = name
        self.timeout_ms = int(timeout_ms)
        self.log = log
        self._res = None

    def _open(self):
        if self._res is None:
            pyvisa = _pyvisa()
            try:
                res = self._rm.open_resource(self.resource, open_timeout=self.timeout_ms)
            except (pyvisa.errors.VisaIOError, OSError, ValueError) as exc:
                raise DriverError(f"{self.name} ({self.resource}): cannot connect: {exc}") from exc
            res.timeout = self.timeout_ms
            res.read_termination = "\n"
            res.write_termination = "\n"
            self._res = res
        return self._res

    def close(self) -> None:
        res, self._res = self._res, None
        if res is not None:
            try:
                res.close()
            except Exception:  # noqa: BLE001 - a dead connection may fail to close; it is gone either way
                pass

    def _fault(self, command: str, exc: BaseException) -> DriverError:
        pyvisa = _pyvisa()
        self.close()
        if isinstance(exc, pyvisa.errors.VisaIOError) and exc.error_code == pyvisa.constants.StatusCode.error_timeout:
            return DriverError(
                f"{self.name} ({self.resource}): no reply to {command!r} within {self.timeout_ms} ms "
                "(timeout: the instrument is busy, hung, or the connection dropped)"
            )
        if isinstance(exc, UnicodeDecodeError):
            return DriverError(f"{self.name} ({self.resource}): garbled reply to {command!r} (not ASCII)")
        return DriverError(f"{self.name} ({self.resource}): connection lost during {command!r}: {exc}")

    def write(self, command: str) -> None:
        pyvisa = _pyvisa()
        res = self._open()
        try:
            res.write(command)
        except (pyvisa.errors.VisaIOError, OSError) as exc:
            raise self._fault(command, exc) from exc
        if self.log is not None:
            self.log.append((self.name, command, None))

    def query(self, command: str, parse=None):
        """Send ``command`` and return its reply, parsed by ``parse`` if given.

        A reply that ``parse`` rejects is a garbled reply: :class:`DriverError`
        naming the instrument and the command.
        """
        pyvisa = _pyvisa()
        res = self._open()
        try:
            reply = res.query(command)
        except (pyvisa.errors.VisaIOError, OSError, UnicodeDecodeError) as exc:
            raise self._fault(command, exc) from exc
        if self.log is not None:
            self.log.append((self.name, command, reply))
        if parse is None:
            return reply
        try:
            return parse(reply)
        except ScpiReplyError as exc:
            self.close()
            raise DriverError(f"{self.name} ({self.resource}): garbled reply to {command!r}: {exc}") from exc


@dataclass
class _Channel:
    spec: ChannelSpec
    inst: VisaInstrument
    oflt: int = -1


class VisaDriver:
    """Signal generator + lock-in amplifiers over VISA, as a :class:`~acquisition.Driver`.

    Parameters
    ----------
    generator : str
        VISA resource of the function generator.
    backend : str
        pyvisa backend, ``"@py"`` (pyvisa-py) by default, ``""`` for NI-VISA/Keysight VISA.
    timeout_ms : int
        I/O timeout for every instrument.
    clock : object with ``now()`` and ``sleep(s)``, optional
        Time base; :class:`WallClock` by default (the loopback server shares a virtual clock).
    tc_fraction : float
        Lock-in time constant as a fraction of the block length (upper bound).
    filter_slope_db : {6, 12, 18, 24}
        Lock-in output filter slope, dB/octave.
    max_drive_v : float
        Largest drive amplitude accepted by :meth:`set_drive`, peak volts.
    ramp_step_s : float
        Interval between amplitude steps while ramping down, s.
    max_unlocked_blocks : int
        Blocks in a row a lock-in may report reference unlock (``LIAS?`` bit 3)
        before :class:`DriverError`; unlocked blocks are discarded and re-measured.
    resource_manager : pyvisa.ResourceManager, optional
        Shared manager; one is opened (and closed again) otherwise.
    """

    def __init__(
        self,
        generator: str,
        *,
        backend: str = "@py",
        timeout_ms: int = 3000,
        clock=None,
        tc_fraction: float = 0.1,
        filter_slope_db: int = 24,
        max_drive_v: float = 10.0,
        ramp_step_s: float = 0.05,
        max_unlocked_blocks: int = 5,
        resource_manager=None,
    ):
        if not generator:
            raise ValueError("VisaDriver: the generator's VISA resource is empty")
        if not 0 < tc_fraction <= 1:
            raise ValueError(f"VisaDriver: tc_fraction must lie in (0, 1], got {tc_fraction}")
        self.generator_resource = generator
        self.backend = backend
        self.timeout_ms = int(timeout_ms)
        self.clock = clock if clock is not None else WallClock()
        self.tc_fraction = float(tc_fraction)
        self.filter_slope_db = int(filter_slope_db)
        self.max_drive_v = float(max_drive_v)
        self.ramp_step_s = float(ramp_step_s)
        self.max_unlocked_blocks = int(max_unlocked_blocks)
        self.gen_vocab = GeneratorVocabulary()
        self.lockin_vocab = LockinVocabulary()
        LockinVocabulary().slope(self.filter_slope_db)  # validates the slope early
        self.log: list[tuple[str, str, str | None]] = []
        self._rm = resource_manager
        self._own_rm = resource_manager is None
        self._gen: VisaInstrument | None = None
        self._channels: list[_Channel] = []
        self._frequency_hz: float | None = None
        self._amplitude_v = 0.0
        self._output_on = False

    # ------------------------------------------------------------------ set-up
    def _manager(self):
        if self._rm is None:
            pyvisa = _pyvisa()
            try:
                self._rm = pyvisa.ResourceManager(self.backend)
            except (OSError, ValueError) as exc:
                raise DriverUnavailable(f"VISA backend {self.backend!r} unavailable: {exc}") from exc
        return self._rm

    def _check_errors(self) -> None:
        """Drain the generator's error queue; any entry is a :class:`DriverError`."""
        code, message = self._gen.query(self.gen_vocab.error_query, self.gen_vocab.parse_error)
        if code != 0:
            errors = [f"{code},{message!r}"]
            for _ in range(20):
                code, message = self._gen.query(self.gen_vocab.error_query, self.gen_vocab.parse_error)
                if code == 0:
                    break
                errors.append(f"{code},{message!r}")
            raise DriverError(f"generator ({self.generator_resource}): instrument error queue: {'; '.join(errors)}")

    def configure(self, channels: Sequence[ChannelSpec], sample_rate_hz: float | None = None) -> DriverInfo:
        """Reset the generator (output off) and set up one lock-in per channel.

        Each channel's ``physical`` is its lock-in's VISA resource; the
        sensitivity is the largest full scale that keeps ``range_v`` (peak)
        on scale. ``sample_rate_hz`` is ignored (the instruments demodulate).
        """
        channels = list(channels)
        if not channels:
            raise ValueError("VisaDriver.configure: no channels")
        seen: dict[str, str] = {}
        for ch in channels:
            if not ch.physical:
                raise ValueError(f"channel {ch.name!r}: no lock-in VISA resource ('physical' is empty)")
            if ch.physical in seen:
                raise ValueError(
                    f"channels {seen[ch.physical]!r} and {ch.name!r} share the lock-in {ch.physical}; one lock-in measures one channel"
                )
            seen[ch.physical] = ch.name
            if ch.sensitivity <= 0:
                raise ValueError(f"channel {ch.name!r}: sensitivity must be positive V/unit, got {ch.sensitivity}")
        rm = self._manager()
        self.close_instruments()
        self._gen = VisaInstrument(rm, self.generator_resource, "generator", self.timeout_ms, self.log)
        devices = [self._gen.query(self.gen_vocab.idn_query, parse_idn)]
        for command in self.gen_vocab.setup():
            self._gen.write(command)
        self._output_on = False
        self._amplitude_v = 0.0
        self._frequency_hz = None
        self._check_errors()
        self._channels = []
        for ch in channels:
            inst = VisaInstrument(rm, ch.physical, f"lock-in {ch.name}", self.timeout_ms, self.log)
            devices.append(inst.query(self.lockin_vocab.idn_query, parse_idn))
            sens = self.lockin_vocab.sensitivity_index(ch.range_v / math.sqrt(2.0))
            for command in (*self.lockin_vocab.setup(), self.lockin_vocab.sensitivity(sens),
                            self.lockin_vocab.slope(self.filter_slope_db)):
                inst.write(command)
            inst.query(self.lockin_vocab.status_query, self.lockin_vocab.parse_status)  # clears latched bits
            self._channels.append(_Channel(ch, inst))
        return DriverInfo(
            name="visa",
            kind="demodulating",
            sample_rate_hz=None,
            devices=tuple(devices),
            details={
                "generator": self.generator_resource,
                "lockins": {c.spec.name: c.spec.physical for c in self._channels},
                "filter_slope_db": self.filter_slope_db,
                "tc_fraction": self.tc_fraction,
                "backend": self.backend,
            },
        )

    # ------------------------------------------------------------------ drive
    def set_drive(self, frequency_hz: float, amplitude_v: float) -> None:
        """Set frequency and amplitude (peak V); the 33500B keeps the phase continuous."""
        if self._gen is None:
            raise DriverError("VisaDriver.set_drive before configure")
        if not (math.isfinite(frequency_hz) and frequency_hz > 0):
            raise ValueError(f"drive frequency must be positive and finite, got {frequency_hz} Hz")
        if not (math.isfinite(amplitude_v) and 0 <= amplitude_v <= self.max_drive_v):
            raise ValueError(f"drive amplitude must lie in [0, {self.max_drive_v}] V peak, got {amplitude_v}")
        if frequency_hz != self._frequency_hz:
            self._gen.write(self.gen_vocab.frequency(frequency_hz))
            self._frequency_hz = float(frequency_hz)
        if amplitude_v == 0:
            if self._output_on:
                self._gen.write(self.gen_vocab.output(False))
                self._output_on = False
        else:
            if amplitude_v != self._amplitude_v or not self._output_on:
                self._gen.write(self.gen_vocab.amplitude(amplitude_v))
            if not self._output_on:
                self._gen.write(self.gen_vocab.output(True))
                self._output_on = True
        self._amplitude_v = float(amplitude_v)
        self._check_errors()

    def read_block(self, n_cycles: int) -> PhasorBlock:
        """Wait ``n_cycles`` drive cycles, then read X, Y and status of every lock-in."""
        if self._gen is None or self._frequency_hz is None:
            raise DriverError("VisaDriver.read_block before configure and set_drive")
        if n_cycles < 1:
            raise ValueError(f"n_cycles must be >= 1, got {n_cycles}")
        duration = n_cycles / self._frequency_hz
        oflt = self.lockin_vocab.time_constant_index(self.tc_fraction * duration)
        for ch in self._channels:
            if ch.oflt != oflt:
                ch.inst.write(self.lockin_vocab.time_constant(oflt))
                # read back: verifies the setting and orders it before the wait
                got = ch.inst.query(self.lockin_vocab.time_constant_query, parse_int)
                if got != oflt:
                    raise DriverError(f"{ch.inst.name} ({ch.inst.resource}): time constant index {got} after 'OFLT {oflt}'")
                ch.oflt = oflt
        for _ in range(self.max_unlocked_blocks + 1):
            t0 = self.clock.now()
            self.clock.sleep(duration)
            values = np.empty((len(self._channels), 1), complex)
            status = np.zeros(len(self._channels), int)
            for k, ch in enumerate(self._channels):
                xy = ch.inst.query(self.lockin_vocab.snap_query, self.lockin_vocab.parse_snap)
                status[k] = ch.inst.query(self.lockin_vocab.status_query, self.lockin_vocab.parse_status)
                values[k, 0] = rms_to_peak(xy) / ch.spec.sensitivity
            # a lock-in whose reference PLL lost lock during the block (e.g. re-locking after a
            # frequency step) read garbage: the block is discarded and measured again
            if not np.any(status & LIAS_UNLOCK):
                return PhasorBlock(t0_s=t0, frequency_hz=self._frequency_hz, duration_s=duration,
                                   harmonics=values, overload=(status & LIAS_OVERLOADS) != 0)
        names = [ch.spec.name for ch, st in zip(self._channels, status) if st & LIAS_UNLOCK]
        raise DriverError(
            f"lock-in(s) {names}: reference unlocked for {self.max_unlocked_blocks + 1} blocks at "
            f"{self._frequency_hz:g} Hz: check the generator's sync output and the reference cables"
        )

    def time_s(self) -> float:
        return self.clock.now()

    @property
    def drive_amplitude_v(self) -> float:
        """The drive amplitude last commanded (peak V; 0 with the output off)."""
        return self._amplitude_v if self._output_on else 0.0

    # ------------------------------------------------------------------ safety
    def ramp_down(self, duration_s: float = 0.5) -> None:
        """Step the amplitude to the minimum over ``duration_s``, then switch the output off.

        Safe in any state and idempotent: before :meth:`configure` there is
        nothing to switch off; after a transport fault the generator is
        reconnected (once) and switched off directly. Raises
        :class:`DriverError` only if the output could not be confirmed off.
        """
        if self._gen is None:
            return
        try:
            if self._output_on and self._amplitude_v > 0:
                n = max(1, int(round(duration_s / self.ramp_step_s)))
                for k in range(n - 1, 0, -1):
                    self._gen.write(self.gen_vocab.amplitude(self._amplitude_v * k / n))
                    self.clock.sleep(duration_s / n)
                self._gen.write(self.gen_vocab.amplitude(0.0))
            self._gen.write(self.gen_vocab.output(False))
            self._gen.query(self.gen_vocab.error_query, self.gen_vocab.parse_error)
        except DriverError as first:
            try:
                self._gen.write(self.gen_vocab.output(False))
                self._gen.query(self.gen_vocab.error_query, self.gen_vocab.parse_error)
            except DriverError as second:
                raise DriverError(
                    f"ramp_down could not confirm the generator output off ({first}; then {second}): "
                    "switch the amplifier off by hand"
                ) from second
        self._output_on = False
        self._amplitude_v = 0.0

    def close_instruments(self) -> None:
        for ch in self._channels:
            ch.inst.close()
        if self._gen is not None:
            self._gen.close()

    def close(self) -> None:
        """Ramp down (if still driving) and release every instrument."""
        try:
            if self._output_on:
                self.ramp_down()
        finally:
            self.close_instruments()
            self._channels = []
            self._gen = None
            if self._own_rm and self._rm is not None:
                self._rm.close()
                self._rm = None
