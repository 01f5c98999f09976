"""NI-DAQmx driver: streamed analog output drive, synchronized IEPE analog inputs.

Hardware picture: an NI-DAQmx device or CompactDAQ chassis with IEPE input
modules (accelerometers and the force sensor, each with its sensitivity and
IEPE excitation current) and an analog output feeding the shaker amplifier.

* **One clock, one start.** The AO task takes its sample clock from the AI
  task (``/<dev>/ai/SampleClock``) and arms on the AI start trigger
  (``/<dev>/ai/StartTrigger``); the AO task is started first (armed), then the
  AI task, so sample k of the drive and sample k of every input share one
  clock edge.
* **Non-regenerative streaming.** ``RegenerationMode.DONT_ALLOW_REGENERATION``:
  the driver writes the drive ahead of the hardware by ``lead_s`` and keeps
  topping it up while it reads, so frequency and amplitude change without
  stopping the tasks. The waveform generator keeps its phase across changes
  (phase-continuous) and ramps amplitude changes over ``amplitude_ramp_s``.
  If the driver is not called for longer than ``lead_s`` the AO buffer runs
  dry: DAQmx stops the generation (error -200290/-200621/-200016/-200018) and
  :class:`~acquisition.DriverError` ("AO underflow") is raised.
* A block read after :meth:`NiDaqDriver.set_drive` starts at the first sample
  generated with the new setting (earlier samples are read and dropped), so
  the controller never demodulates a mixture of two frequencies.
* Overload: a channel is flagged when DAQmx reports it in
  ``in_stream.overloaded_chans`` or a sample reaches its configured range.

``nidaqmx`` is imported only inside the driver, with an error naming the
``ni`` extra; task, reader and writer classes can be injected (the tests pass
autospecced fakes of the real nidaqmx classes).
"""

from __future__ import annotations

import math
import re
from typing import Callable, Sequence

import numpy as np

from acquisition._driver import ChannelSpec, DriverError, DriverInfo, SampleBlock
from acquisition.drivers import DriverUnavailable

#: Standard gravity, m/s^2 per g (sensitivities in mV/g on calibration sheets).
G0 = 9.80665
#: DAQmx error codes meaning the analog output ran out of samples.
AO_UNDERFLOW_CODES = (-200290, -200621, -200016, -200018)
#: DAQmx error codes meaning the analog input buffer was overwritten.
AI_OVERFLOW_CODES = (-200279, -200010)


def _nidaqmx():
    try:
        import nidaqmx
        import nidaqmx.constants
        import nidaqmx.errors
        import nidaqmx.stream_readers
        import nidaqmx.stream_writers
    except ImportError as exc:  # pragma: no cover - exercised only without the extra
        raise DriverUnavailable("the NI-DAQmx driver needs the nidaqmx package: pip install 'frfcal[ni]'") from exc
    return nidaqmx


def device_of(physical: str) -> str:
    """``"cDAQ1Mod1/ai0"`` -> ``"cDAQ1Mod1"``."""
    return physical.strip("/").split("/")[0]


def timing_root(device: str) -> str:
    """Device whose ``ai/SampleClock`` and ``ai/StartTrigger`` terminals the tasks share.

    A CompactDAQ module (``cDAQ1Mod1``) uses its chassis' timing engine
    (``cDAQ1``); a PCI/PXI/USB device (``Dev1``, ``PXI1Slot2``) its own.
    """
    m = re.fullmatch(r"(.+?)Mod\d+", device)
    return m.group(1) if m else device


class PhaseContinuousSine:
    """Sine generator whose frequency and amplitude change without phase jumps.

    ``generate(n)`` returns the next ``n`` samples; after :meth:`set` the
    frequency changes at the next sample (the phase accumulator keeps running)
    and the amplitude moves linearly to its new value over ``ramp_samples``.
    """

    def __init__(self, rate_hz: float, ramp_samples: int):
        self.rate_hz = float(rate_hz)
        self.ramp_samples = max(1, int(ramp_samples))
        self.phase_cycles = 0.0
        self.frequency_hz = 0.0
        self.amplitude = 0.0
        self._target = 0.0
        self._step = 0.0

    def set(self, frequency_hz: float, amplitude: float, ramp_samples: int | None = None) -> None:
        self.frequency_hz = float(frequency_hz)
        self._target = float(amplitude)
        n = self.ramp_samples if ramp_samples is None else max(1, int(ramp_samples))
        self._step = (self._target - self.amplitude) / n

    def generate(self, n: int) -> np.ndarray:
        k = np.arange(n)
        if self._step != 0.0:
            amp = self.amplitude + self._step * (k + 1)
            amp = np.minimum(amp, self._target) if self._step > 0 else np.maximum(amp, self._target)
            self.amplitude = float(amp[-1]) if n else self.amplitude
            if self.amplitude == self._target:
                self._step = 0.0
        else:
            amp = np.full(n, self.amplitude)
        inc = self.frequency_hz / self.rate_hz
        phase = self.phase_cycles + inc * k
        self.phase_cycles = math.fmod(self.phase_cycles + inc * n, 1.0)
        return amp * np.sin(2 * np.pi * phase)

    @property
    def settled(self) -> bool:
        return self._step == 0.0


class NiDaqDriver:
    """NI-DAQmx analog output drive + IEPE analog inputs on one shared clock, as a :class:`~acquisition.Driver`.

    Parameters
    ----------
    ao_channel : str
        Physical AO channel feeding the amplifier, e.g. ``"cDAQ1Mod4/ao0"``.
    ao_max_v : float
        AO range and the largest drive amplitude accepted, peak volts.
    sample_clock : str, optional
        Terminal the AO task takes its sample clock from; default
        ``/<timing root of the first AI channel>/ai/SampleClock``.
    start_trigger : str, optional
        Terminal the AO task arms on; default ``/<root>/ai/StartTrigger``.
    lead_s : float
        How far ahead of the hardware the drive is written, s (also the
        longest pause allowed between driver calls while driving).
    chunk_s : float
        Granularity of reads and writes in the streaming loop, s.
    buffer_s : float
        Size of the AI and AO buffers, s.
    amplitude_ramp_s : float
        Duration of the linear ramp on an amplitude change, s.
    timeout_s : float
        Timeout of every DAQmx read and write, s.
    terminal : str
        AI terminal configuration name (``"PSEUDO_DIFF"`` for IEPE modules).
    task_factory, reader_factory, writer_factory : callable, optional
        ``nidaqmx.Task``, ``AnalogMultiChannelReader`` and
        ``AnalogSingleChannelWriter`` by default.
    """

    def __init__(
        self,
        ao_channel: str,
        *,
        ao_max_v: float = 2.0,
        sample_clock: str | None = None,
        start_trigger: str | None = None,
        lead_s: float = 0.2,
        chunk_s: float = 0.05,
        buffer_s: float = 10.0,
        amplitude_ramp_s: float = 0.01,
        timeout_s: float = 10.0,
        terminal: str = "PSEUDO_DIFF",
        task_factory: Callable | None = None,
        reader_factory: Callable | None = None,
        writer_factory: Callable | None = None,
    ):
        if not ao_channel:
            raise ValueError("NiDaqDriver: the AO channel is empty")
        if not 0 < chunk_s <= lead_s:
            raise ValueError(f"NiDaqDriver: need 0 < chunk_s <= lead_s, got chunk_s={chunk_s}, lead_s={lead_s}")
        self.ao_channel = ao_channel
        self.ao_max_v = float(ao_max_v)
        self.sample_clock = sample_clock
        self.start_trigger = start_trigger
        self.lead_s = float(lead_s)
        self.chunk_s = float(chunk_s)
        self.buffer_s = float(buffer_s)
        self.amplitude_ramp_s = float(amplitude_ramp_s)
        self.timeout_s = float(timeout_s)
        self.terminal = terminal
        self._task_factory = task_factory
        self._reader_factory = reader_factory
        self._writer_factory = writer_factory
        self._ai = None
        self._ao = None
        self._channels: list[ChannelSpec] = []
        self._scale = np.ones(0)
        self._range = np.ones(0)
        self._rate = None
        self._running = False
        self._gen: PhaseContinuousSine | None = None

    # ------------------------------------------------------------------ set-up
    def _add_ai_channel(self, nidaqmx, ch: ChannelSpec) -> float:
        """Add one AI channel; returns the software scale (1 where DAQmx scales to SI)."""
        c = nidaqmx.constants
        terminal = getattr(c.TerminalConfiguration, self.terminal)
        limit = ch.range_v / ch.sensitivity
        iepe = ch.iepe_current_a is not None and ch.iepe_current_a > 0
        excitation = dict(
            current_excit_source=c.ExcitationSource.INTERNAL if iepe else c.ExcitationSource.NONE,
            current_excit_val=float(ch.iepe_current_a) if iepe else 0.0,
        )
        ai = self._ai.ai_channels
        if ch.quantity == "acceleration":
            ai.add_ai_accel_chan(
                ch.physical, name_to_assign_to_channel=ch.name, terminal_config=terminal,
                min_val=-limit, max_val=limit, units=c.AccelUnits.METERS_PER_SECOND_SQUARED,
                sensitivity=ch.sensitivity * G0 * 1000.0,
                sensitivity_units=c.AccelSensitivityUnits.MILLIVOLTS_PER_G, **excitation,
            )
            return 1.0
        if ch.quantity == "force" and iepe:
            ai.add_ai_force_iepe_chan(
                ch.physical, name_to_assign_to_channel=ch.name, terminal_config=terminal,
                min_val=-limit, max_val=limit, units=c.ForceUnits.NEWTONS,
                sensitivity=ch.sensitivity * 1000.0,
                sensitivity_units=c.ForceIEPESensorSensitivityUnits.MILLIVOLTS_PER_NEWTON, **excitation,
            )
            return 1.0
        chan = ai.add_ai_voltage_chan(ch.physical, name_to_assign_to_channel=ch.name, terminal_config=terminal,
                                      min_val=-ch.range_v, max_val=ch.range_v)
        if iepe:
            # an IEPE sensor of another quantity (velocity, a force sensor read as volts, ...):
            # a voltage channel with current excitation and AC coupling, scaled in software
            chan.ai_excit_voltage_or_current = c.ExcitationVoltageOrCurrent.USE_CURRENT
            chan.ai_excit_src = c.ExcitationSource.INTERNAL
            chan.ai_excit_val = float(ch.iepe_current_a)
            chan.ai_coupling = c.Coupling.AC
        return 1.0 / ch.sensitivity

    def configure(self, channels: Sequence[ChannelSpec], sample_rate_hz: float | None) -> DriverInfo:
        """Create the AI task (one channel per spec) and the AO task slaved to its clock and trigger."""
        nidaqmx = _nidaqmx()
        c = nidaqmx.constants
        channels = list(channels)
        if not channels:
            raise ValueError("NiDaqDriver.configure: no channels")
        if sample_rate_hz is None or not sample_rate_hz > 0:
            raise ValueError(f"NiDaqDriver.configure: a positive sample_rate_hz is required, got {sample_rate_hz}")
        for ch in channels:
            if not ch.physical:
                raise ValueError(f"channel {ch.name!r}: no physical AI channel ('physical' is empty)")
            if ch.sensitivity <= 0 or ch.range_v <= 0:
                raise ValueError(f"channel {ch.name!r}: sensitivity and range_v must be positive")
        self.close()
        task = self._task_factory or nidaqmx.Task
        rate = float(sample_rate_hz)
        buffer = int(round(self.buffer_s * rate))
        root = timing_root(device_of(channels[0].physical))
        clock = self.sample_clock or f"/{root}/ai/SampleClock"
        trigger = self.start_trigger or f"/{root}/ai/StartTrigger"
        try:
            self._ai = task("frfcal_ai")
            self._ao = task("frfcal_ao")
            self._scale = np.array([self._add_ai_channel(nidaqmx, ch) for ch in channels])
            self._ai.timing.cfg_samp_clk_timing(rate, sample_mode=c.AcquisitionType.CONTINUOUS, samps_per_chan=buffer)
            self._ao.ao_channels.add_ao_voltage_chan(self.ao_channel, name_to_assign_to_channel="drive",
                                                     min_val=-self.ao_max_v, max_val=self.ao_max_v)
            self._arm_ao(nidaqmx, rate, buffer, clock, trigger)
            reader = self._reader_factory or nidaqmx.stream_readers.AnalogMultiChannelReader
            writer = self._writer_factory or nidaqmx.stream_writers.AnalogSingleChannelWriter
            self._reader = reader(self._ai.in_stream)
            self._writer = writer(self._ao.out_stream, auto_start=False)
        except nidaqmx.errors.DaqNotFoundError as exc:
            self._ai = self._ao = None
            raise DriverUnavailable(
                "NI-DAQmx runtime not installed on this machine (the nidaqmx package needs NI's DAQmx "
                "driver; 'frfcal info' shows what is present)"
            ) from exc
        except nidaqmx.errors.DaqError as exc:
            self.close()
            raise DriverError(f"NI-DAQmx set-up failed (error {exc.error_code}): {exc}") from exc
        self._channels = channels
        self._range = np.array([ch.range_v / ch.sensitivity for ch in channels])
        self._rate = rate
        self._clock, self._trigger, self._buffer = clock, trigger, buffer
        self._running = False
        self._gen = PhaseContinuousSine(rate, round(self.amplitude_ramp_s * rate))
        self._read = 0
        self._written = 0
        self._history = np.zeros(0)
        self._history_start = 0
        self._change_index = 0
        return DriverInfo(
            name="ni",
            kind="sampling",
            sample_rate_hz=rate,
            devices=tuple(sorted({device_of(ch.physical) for ch in channels} | {device_of(self.ao_channel)})),
            details={"ao_channel": self.ao_channel, "sample_clock": clock, "start_trigger": trigger,
                     "regeneration": "DONT_ALLOW_REGENERATION", "lead_s": self.lead_s,
                     "channels": {ch.name: ch.physical for ch in channels}},
        )

    def _arm_ao(self, nidaqmx, rate, buffer, clock, trigger) -> None:
        c = nidaqmx.constants
        self._ao.timing.cfg_samp_clk_timing(rate, source=clock, sample_mode=c.AcquisitionType.CONTINUOUS,
                                            samps_per_chan=buffer)
        self._ao.out_stream.regen_mode = c.RegenerationMode.DONT_ALLOW_REGENERATION
        self._ao.triggers.start_trigger.cfg_dig_edge_start_trig(trigger)

    # ------------------------------------------------------------------ streaming
    def _daq_error(self, exc, where: str) -> DriverError:
        code = getattr(exc, "error_code", None)
        if code in AO_UNDERFLOW_CODES:
            self._running = False
            return DriverError(f"AO underflow on {self.ao_channel} during {where} (DAQmx error {code}): "
                               "the drive stopped because new samples came too late")
        if code in AI_OVERFLOW_CODES:
            return DriverError(f"AI buffer overflow during {where} (DAQmx error {code}): samples were lost")
        return DriverError(f"NI-DAQmx error {code} during {where}: {exc}")

    def _write(self, n: int) -> None:
        nidaqmx = _nidaqmx()
        data = self._gen.generate(n)
        try:
            self._writer.write_many_sample(np.ascontiguousarray(data), timeout=self.timeout_s)
        except nidaqmx.errors.DaqError as exc:
            raise self._daq_error(exc, "the AO write") from exc
        self._history = np.concatenate([self._history, data])  # trimmed by read_block
        self._written += n

    def _top_up(self) -> None:
        lead = int(round(self.lead_s * self._rate))
        chunk = max(1, int(round(self.chunk_s * self._rate)))
        while self._written - self._read < lead:
            self._write(chunk)

    def _read_samples(self, n: int) -> np.ndarray:
        """Read ``n`` samples of every channel, keeping the AO ``lead_s`` ahead."""
        nidaqmx = _nidaqmx()
        out = np.empty((len(self._channels), n))
        chunk = max(1, int(round(self.chunk_s * self._rate)))
        done = 0
        while done < n:
            self._top_up()
            k = min(chunk, n - done)
            buf = np.zeros((len(self._channels), k))
            try:
                self._reader.read_many_sample(buf, number_of_samples_per_channel=k, timeout=self.timeout_s)
            except nidaqmx.errors.DaqError as exc:
                raise self._daq_error(exc, "the AI read") from exc
            out[:, done:done + k] = buf
            done += k
            self._read += k
        return out * self._scale[:, None]

    def _start(self) -> None:
        nidaqmx = _nidaqmx()
        try:
            self._top_up()
            self._ao.start()  # armed: waits for the AI start trigger
            self._ai.start()
        except nidaqmx.errors.DaqError as exc:
            raise self._daq_error(exc, "the task start") from exc
        self._running = True

    def set_drive(self, frequency_hz: float, amplitude_v: float) -> None:
        """Change the streamed drive phase-continuously; takes effect at the next sample written."""
        if self._ai is None:
            raise DriverError("NiDaqDriver.set_drive before configure")
        if not (math.isfinite(frequency_hz) and 0 < frequency_hz < self._rate / 2):
            raise ValueError(f"drive frequency must lie in (0, {self._rate / 2}) Hz, got {frequency_hz}")
        if not (math.isfinite(amplitude_v) and 0 <= amplitude_v <= self.ao_max_v):
            raise ValueError(f"drive amplitude must lie in [0, {self.ao_max_v}] V peak, got {amplitude_v}")
        self._gen.set(frequency_hz, amplitude_v)
        self._change_index = self._written + self._gen.ramp_samples
        if not self._running:
            if self._ai is not None and self._read > 0:
                self._restart()
            self._start()

    def _restart(self) -> None:
        """Re-arm after a ramp-down: AO back on the shared clock, bookkeeping from zero."""
        nidaqmx = _nidaqmx()
        try:
            self._ai.stop()
            self._ao.stop()
            self._arm_ao(nidaqmx, self._rate, self._buffer, self._clock, self._trigger)
        except nidaqmx.errors.DaqError as exc:
            raise self._daq_error(exc, "the re-arm") from exc
        self._read = self._written = self._history_start = 0
        self._history = np.zeros(0)
        self._change_index = self._gen.ramp_samples

    def read_block(self, n_cycles: int) -> SampleBlock:
        """Samples of every channel over ``n_cycles`` whole drive cycles (rounded to whole samples)."""
        if not self._running:
            raise DriverError("NiDaqDriver.read_block while not streaming (call set_drive first)")
        if n_cycles < 1:
            raise ValueError(f"n_cycles must be >= 1, got {n_cycles}")
        if self._read < self._change_index:
            self._read_samples(self._change_index - self._read)  # drop samples of the previous setting
        n = int(round(n_cycles * self._rate / self._gen.frequency_hz))
        start = self._read
        data = self._read_samples(n)
        overload = np.abs(data) >= 0.999 * self._range[:, None]
        overload = overload.any(axis=1)
        try:
            if self._ai.in_stream.overloaded_chans_exist:
                names = set(self._ai.in_stream.overloaded_chans)
                overload |= np.array([ch.name in names for ch in self._channels])
        except _nidaqmx().errors.DaqError as exc:
            raise self._daq_error(exc, "the overload query") from exc
        drive = self._history[start - self._history_start:start - self._history_start + n].copy()
        # samples before the next block will never be asked for again
        self._history = self._history[self._read - self._history_start:]
        self._history_start = self._read
        return SampleBlock(t0_s=start / self._rate, rate_hz=self._rate, samples=data, overload=overload, drive=drive)

    def time_s(self) -> float:
        return 0.0 if not self._rate else self._read / self._rate

    @property
    def drive_amplitude_v(self) -> float:
        """Amplitude of the drive being streamed (peak V; 0 when not streaming)."""
        return self._gen.amplitude if (self._running and self._gen is not None) else 0.0

    # ------------------------------------------------------------------ safety
    def ramp_down(self, duration_s: float = 0.5) -> None:
        """Ramp the streamed drive to zero, stop both tasks and hold the AO at 0 V.

        Safe in any state and idempotent. If streaming already failed (AO
        underflow), the tasks are stopped and 0 V is written on demand.
        Raises :class:`DriverError` only if 0 V could not be confirmed.
        """
        if self._ao is None:
            return
        nidaqmx = _nidaqmx()
        first = None
        if self._running:
            try:
                n = max(1, int(round(duration_s * self._rate)))
                self._gen.set(self._gen.frequency_hz, 0.0, ramp_samples=n)
                end = self._written + n
                while self._read < end + int(self.chunk_s * self._rate):
                    self._read_samples(max(1, int(round(self.chunk_s * self._rate))))
            except DriverError as exc:
                first = exc
        self._running = False
        try:
            for t in (self._ai, self._ao):
                try:
                    t.stop()
                except nidaqmx.errors.DaqError:
                    pass  # a task stopped by an error may refuse; the on-demand write below decides
            self._ao.timing.samp_timing_type = nidaqmx.constants.SampleTimingType.ON_DEMAND
            self._ao.write(0.0, auto_start=True)
            self._ao.stop()
        except nidaqmx.errors.DaqError as exc:
            raise DriverError(
                f"ramp_down could not confirm 0 V on {self.ao_channel} (DAQmx error {exc.error_code})"
                + (f" after {first}" if first else "") + ": switch the amplifier off by hand"
            ) from exc
        if self._gen is not None:
            self._gen.set(self._gen.frequency_hz, 0.0, ramp_samples=1)
            self._gen.amplitude = 0.0

    def close(self) -> None:
        """Ramp down and release both tasks (idempotent)."""
        try:
            self.ramp_down()
        finally:
            for t in (self._ai, self._ao):
                if t is not None:
                    try:
                        t.close()
                    except Exception:  # noqa: BLE001 - closing a failed task; the handle is gone either way
                        pass
            self._ai = self._ao = None
