"""NI-DAQmx driver against autospecced fakes of the real nidaqmx classes.

``unittest.mock.create_autospec`` builds every task, channel collection,
timing, trigger, stream, reader and writer from the installed nidaqmx
package, so a wrong method or keyword fails here as it would on hardware.
Behind the fakes sits a tiny "device": the AO FIFO is consumed one sample per
AI sample-clock tick, and each AI channel is a known function of the drive
actually generated (force = 2 N/V x drive, acceleration = 3 (m/s^2)/V x the
drive delayed by 7 samples, a voltage monitor of the drive).
"""

from __future__ import annotations

from unittest import mock

import numpy as np
import pytest

nidaqmx = pytest.importorskip("nidaqmx")

import nidaqmx.constants as c  # noqa: E402
import nidaqmx.errors  # noqa: E402
from nidaqmx.stream_readers import AnalogMultiChannelReader  # noqa: E402
from nidaqmx.stream_writers import AnalogSingleChannelWriter  # noqa: E402
from nidaqmx.task import InStream, OutStream, Timing  # noqa: E402
from nidaqmx.task.collections import AIChannelCollection, AOChannelCollection  # noqa: E402
from nidaqmx.task.triggering import StartTrigger, Triggers  # noqa: E402

from acquisition import ChannelSpec, DriverError, SampleBlock  # noqa: E402
from acquisition.drivers.ni import G0, NiDaqDriver, timing_root  # noqa: E402

RATE = 10240.0
DELAY = 7

CHANNELS = (
    ChannelSpec("force", "force", "force", "N", sensitivity=0.0225, physical="cDAQ1Mod1/ai0", range_v=5.0,
                serial="F1234", iepe_current_a=0.004),
    ChannelSpec("acc1", "response", "acceleration", "m/s^2", sensitivity=0.0102, physical="cDAQ1Mod1/ai1",
                range_v=5.0, iepe_current_a=0.002),
    ChannelSpec("drive_mon", "monitor", "voltage", "V", sensitivity=0.5, physical="cDAQ1Mod2/ai0", range_v=10.0),
)


class FakeDevice:
    """Hardware behind the autospecced nidaqmx objects (one shared sample clock)."""

    def __init__(self, respond=None):
        #: ``respond(generated, n0, k) -> (n_channels, k)``: the inputs over samples n0..n0+k
        self.respond = respond or self._respond
        self.events: list[str] = []
        self._gen = np.zeros(1 << 16)  # every AO sample clocked out so far (grown by doubling)
        self._n = 0
        self.fifo = np.zeros(0)  # AO samples written but not yet generated
        self.underflow = False
        self.tasks = {}

    # -- factories handed to the driver ---------------------------------
    def task(self, name):
        t = mock.create_autospec(nidaqmx.Task, instance=True)
        t.name = name
        # autospeccing a channel collection is slow (hundreds of methods): only the one each task uses
        if "ai" in name:
            t.ai_channels = mock.create_autospec(AIChannelCollection, instance=True)
        else:
            t.ao_channels = mock.create_autospec(AOChannelCollection, instance=True)
        t.timing = mock.create_autospec(Timing, instance=True)
        t.triggers = mock.create_autospec(Triggers, instance=True)
        t.triggers.start_trigger = mock.create_autospec(StartTrigger, instance=True)
        t.in_stream = mock.create_autospec(InStream, instance=True)
        t.in_stream.overloaded_chans_exist = False
        t.in_stream.overloaded_chans = []
        t.out_stream = mock.create_autospec(OutStream, instance=True)
        t.start.side_effect = lambda: self.events.append(f"start {name}")
        t.stop.side_effect = lambda: self._stop(name)
        t.write.side_effect = lambda data, auto_start=False, timeout=10.0: self.events.append(f"write {name} {data}")
        self.tasks[name] = t
        return t

    def _stop(self, name):
        self.events.append(f"stop {name}")
        if name == "frfcal_ao":
            self.fifo = np.zeros(0)  # stopping a task discards what it had not generated

    def reader_factory(self):
        cls = mock.create_autospec(AnalogMultiChannelReader)
        cls.return_value.read_many_sample.side_effect = self._read
        return cls

    def writer_factory(self):
        cls = mock.create_autospec(AnalogSingleChannelWriter)
        cls.return_value.write_many_sample.side_effect = self._write
        return cls

    # -- physics -----------------------------------------------------------
    def _write(self, data, timeout=10.0):
        if self.underflow:
            raise nidaqmx.errors.DaqError("The generation has stopped to prevent the regeneration of old samples.",
                                          -200290)
        assert data.dtype == np.float64 and data.flags.c_contiguous
        self.events.append(f"ao write {data.size}")
        self.fifo = np.concatenate([self.fifo, data])
        return data.size

    @property
    def generated(self) -> np.ndarray:
        return self._gen[: self._n]

    def _clock(self, k: int) -> None:
        """k ticks of the shared sample clock: k AO samples leave the FIFO (zeros once it is dry)."""
        while self._n + k > self._gen.size:
            self._gen = np.concatenate([self._gen, np.zeros(self._gen.size)])
        m = min(k, self.fifo.size)
        self._gen[self._n:self._n + m] = self.fifo[:m]
        self._gen[self._n + m:self._n + k] = 0.0
        self._n += k
        self.fifo = self.fifo[m:]
        if m < k:
            self.underflow = True

    def pause(self, n_samples: int) -> None:
        """The host stalls while the hardware keeps clocking."""
        self._clock(n_samples)

    def _read(self, data, number_of_samples_per_channel=-1, timeout=10.0):
        k = number_of_samples_per_channel
        assert data.shape[1] == k and data.dtype == np.float64 and data.flags.c_contiguous
        self._clock(k)
        if self.underflow:
            raise nidaqmx.errors.DaqError("The generation has stopped to prevent the regeneration of old samples.",
                                          -200290)
        data[:] = self.respond(self.generated, self.generated.size - k, k)
        return k

    @staticmethod
    def _respond(g, n0, k):
        idx = np.arange(n0, n0 + k)
        delayed = np.where(idx - DELAY >= 0, g[np.maximum(idx - DELAY, 0)], 0.0)
        # force 2 N/V; acceleration 3 (m/s^2)/V delayed; raw volts (the driver divides by 0.5 V/V)
        return np.vstack([2.0 * g[n0:n0 + k], 3.0 * delayed, g[n0:n0 + k]])


@pytest.fixture
def rig():
    dev = FakeDevice()
    drv = NiDaqDriver("cDAQ1Mod4/ao0", ao_max_v=2.0, task_factory=dev.task,
                      reader_factory=dev.reader_factory(), writer_factory=dev.writer_factory())
    yield dev, drv
    drv.close()


def phasor(x: np.ndarray, f: float, rate: float) -> complex:
    t = np.arange(x.size) / rate
    return 2.0 / x.size * np.sum(x * np.exp(-2j * np.pi * f * t))


def test_timing_root_of_cdaq_modules_and_plain_devices():
    assert timing_root("cDAQ1Mod3") == "cDAQ1"
    assert timing_root("Dev1") == "Dev1"
    assert timing_root("PXI1Slot2") == "PXI1Slot2"


def test_task_and_channel_configuration(rig):
    dev, drv = rig
    info = drv.configure(CHANNELS, RATE)
    ai, ao = dev.tasks["frfcal_ai"], dev.tasks["frfcal_ao"]
    # IEPE force sensor: mV/N, internal excitation at its current, range in N
    ai.ai_channels.add_ai_force_iepe_chan.assert_called_once_with(
        "cDAQ1Mod1/ai0", name_to_assign_to_channel="force", terminal_config=c.TerminalConfiguration.PSEUDO_DIFF,
        min_val=pytest.approx(-5.0 / 0.0225), max_val=pytest.approx(5.0 / 0.0225), units=c.ForceUnits.NEWTONS,
        sensitivity=pytest.approx(22.5), sensitivity_units=c.ForceIEPESensorSensitivityUnits.MILLIVOLTS_PER_NEWTON,
        current_excit_source=c.ExcitationSource.INTERNAL, current_excit_val=0.004,
    )
    # IEPE accelerometer: 0.0102 V/(m/s^2) = 100.03 mV/g, data in m/s^2, 2 mA
    ai.ai_channels.add_ai_accel_chan.assert_called_once_with(
        "cDAQ1Mod1/ai1", name_to_assign_to_channel="acc1", terminal_config=c.TerminalConfiguration.PSEUDO_DIFF,
        min_val=pytest.approx(-5.0 / 0.0102), max_val=pytest.approx(5.0 / 0.0102),
        units=c.AccelUnits.METERS_PER_SECOND_SQUARED, sensitivity=pytest.approx(0.0102 * G0 * 1000),
        sensitivity_units=c.AccelSensitivityUnits.MILLIVOLTS_PER_G,
        current_excit_source=c.ExcitationSource.INTERNAL, current_excit_val=0.002,
    )
    ai.ai_channels.add_ai_voltage_chan.assert_called_once_with(
        "cDAQ1Mod2/ai0", name_to_assign_to_channel="drive_mon", terminal_config=c.TerminalConfiguration.PSEUDO_DIFF,
        min_val=-10.0, max_val=10.0)
    ai.timing.cfg_samp_clk_timing.assert_called_once_with(
        RATE, sample_mode=c.AcquisitionType.CONTINUOUS, samps_per_chan=int(10 * RATE))
    ao.ao_channels.add_ao_voltage_chan.assert_called_once_with(
        "cDAQ1Mod4/ao0", name_to_assign_to_channel="drive", min_val=-2.0, max_val=2.0)
    # AO on the AI sample clock and armed on the AI start trigger (the chassis' timing engine)
    ao.timing.cfg_samp_clk_timing.assert_called_once_with(
        RATE, source="/cDAQ1/ai/SampleClock", sample_mode=c.AcquisitionType.CONTINUOUS, samps_per_chan=int(10 * RATE))
    ao.triggers.start_trigger.cfg_dig_edge_start_trig.assert_called_once_with("/cDAQ1/ai/StartTrigger")
    assert ao.out_stream.regen_mode == c.RegenerationMode.DONT_ALLOW_REGENERATION
    assert info.kind == "sampling" and info.sample_rate_hz == RATE
    assert info.devices == ("cDAQ1Mod1", "cDAQ1Mod2", "cDAQ1Mod4")
    assert dev.events == []  # nothing starts before the first set_drive


def test_streaming_loop_starts_ao_armed_before_ai_and_recovers_the_frf(rig):
    dev, drv = rig
    drv.configure(CHANNELS, RATE)
    drv.set_drive(160.0, 0.8)  # 64 samples per cycle
    starts = [e for e in dev.events if e.startswith("start")]
    assert starts == ["start frfcal_ao", "start frfcal_ai"]
    first_start = dev.events.index("start frfcal_ao")
    assert dev.events[0].startswith("ao write") and first_start > 0  # the buffer is primed before arming
    block = drv.read_block(20)
    first = block
    block = drv.read_block(20)  # the delayed channel has left the start-up ramp behind
    assert isinstance(block, SampleBlock)
    assert block.samples.shape == (3, 20 * 64) and block.rate_hz == RATE
    # the block starts after the 10 ms amplitude ramp: pure steady drive of known phase
    assert first.t0_s == pytest.approx(round(0.01 * RATE) / RATE)
    assert block.t0_s == pytest.approx(first.t0_s + 20 / 160.0)
    np.testing.assert_allclose(block.drive, dev.generated[round(block.t0_s * RATE):][:block.drive.size])
    force = phasor(block.samples[0], 160.0, RATE)
    acc = phasor(block.samples[1], 160.0, RATE)
    assert abs(force) == pytest.approx(1.6, rel=1e-9)
    h = acc / force
    expected = 1.5 * np.exp(-2j * np.pi * 160.0 * DELAY / RATE)
    assert abs(h - expected) < 1e-9
    np.testing.assert_allclose(block.samples[2], block.drive / 0.5)  # software scaling of the voltage channel
    assert not block.overload.any()
    # the driver keeps the AO ahead by lead_s, never more than lead + one chunk
    assert round(0.15 * RATE) <= dev.fifo.size <= round(0.25 * RATE) + 1
    assert drv.time_s() == pytest.approx(dev.generated.size / RATE)


def test_frequency_and_amplitude_change_without_restart_or_phase_jump(rig):
    dev, drv = rig
    drv.configure(CHANNELS, RATE)
    drv.set_drive(160.0, 0.8)
    drv.read_block(10)
    change = int(round(drv.time_s() * RATE)) + dev.fifo.size  # the next sample the driver will write
    drv.set_drive(320.0, 0.4)
    block = drv.read_block(10)
    assert [e for e in dev.events if e.startswith(("start", "stop"))] == ["start frfcal_ao", "start frfcal_ai"]
    # the new block starts after the change (and its ramp) and holds only the new frequency
    assert round(block.t0_s * RATE) >= change + round(0.01 * RATE)
    assert abs(phasor(block.samples[0], 320.0, RATE)) == pytest.approx(0.8, rel=1e-9)
    g = dev.generated[: round(block.t0_s * RATE) + block.drive.size]
    # phase continuity: no sample-to-sample step larger than the steepest slope of either sine
    max_step = 2 * np.pi * 320.0 / RATE * 0.8 * 1.01
    assert np.max(np.abs(np.diff(g))) <= max_step
    around = g[change - 5: change + 5]
    assert np.max(np.abs(np.diff(around))) <= max_step


def test_ai_overload_is_flagged_from_daqmx_and_from_range(rig):
    dev, drv = rig
    drv.configure(CHANNELS, RATE)
    drv.set_drive(160.0, 0.5)
    ai = dev.tasks["frfcal_ai"]
    ai.in_stream.overloaded_chans_exist = True
    ai.in_stream.overloaded_chans = ["acc1"]
    assert drv.read_block(10).overload.tolist() == [False, True, False]
    ai.in_stream.overloaded_chans_exist = False
    assert drv.read_block(10).overload.tolist() == [False, False, False]
    # 1.5 m/s^2 peak on an accelerometer channel ranged to 0.01 V / 0.0102 V/(m/s^2) = 0.98 m/s^2
    tight = list(CHANNELS)
    tight[1] = ChannelSpec("acc1", "response", "acceleration", "m/s^2", sensitivity=0.0102,
                           physical="cDAQ1Mod1/ai1", range_v=0.01, iepe_current_a=0.002)
    drv.configure(tight, RATE)
    drv.set_drive(160.0, 0.5)
    block = drv.read_block(10)
    assert block.overload.tolist() == [False, True, False]


def test_ao_underflow_is_a_driver_error_and_ramp_down_still_zeroes_the_output(rig):
    dev, drv = rig
    drv.configure(CHANNELS, RATE)
    drv.set_drive(160.0, 0.8)
    drv.read_block(10)
    dev.pause(int(0.5 * RATE))  # the host stalls longer than lead_s: the FIFO runs dry
    with pytest.raises(DriverError, match=r"AO underflow on cDAQ1Mod4/ao0 .*-200290"):
        drv.read_block(10)
    dev.events.clear()
    drv.ramp_down()
    ao = dev.tasks["frfcal_ao"]
    assert ao.timing.samp_timing_type == c.SampleTimingType.ON_DEMAND
    assert dev.events == ["stop frfcal_ai", "stop frfcal_ao", "write frfcal_ao 0.0", "stop frfcal_ao"]
    drv.ramp_down()  # idempotent
    assert dev.events[-2:] == ["write frfcal_ao 0.0", "stop frfcal_ao"]


def test_ramp_down_streams_a_smooth_ramp_to_zero(rig):
    dev, drv = rig
    drv.configure(CHANNELS, RATE)
    drv.set_drive(160.0, 1.0)
    drv.read_block(10)
    n_before = dev.generated.size + dev.fifo.size
    drv.ramp_down(0.25)
    ramp = np.concatenate([dev.generated, dev.fifo])[n_before:]
    envelope = np.abs(ramp[: round(0.25 * RATE)])
    # linear envelope from 1 to 0 over 0.25 s, then silence
    assert envelope[:64].max() == pytest.approx(1.0, abs=0.01)
    assert envelope[-64:].max() < 0.02
    assert np.all(np.abs(ramp[round(0.25 * RATE):]) == 0.0)
    assert dev.events[-4:] == ["stop frfcal_ai", "stop frfcal_ao", "write frfcal_ao 0.0", "stop frfcal_ao"]


def test_restart_after_ramp_down_rearms_on_the_shared_clock(rig):
    dev, drv = rig
    drv.configure(CHANNELS, RATE)
    drv.set_drive(160.0, 0.5)
    drv.read_block(5)
    drv.ramp_down(0.05)
    drv.set_drive(320.0, 0.5)
    block = drv.read_block(10)
    ao = dev.tasks["frfcal_ao"]
    assert ao.timing.cfg_samp_clk_timing.call_count == 2
    assert ao.triggers.start_trigger.cfg_dig_edge_start_trig.call_count == 2
    assert block.t0_s == pytest.approx(round(0.01 * RATE) / RATE)  # bookkeeping restarted with the tasks


def test_iepe_sensor_of_another_quantity_is_an_excited_ac_coupled_voltage_channel(rig):
    dev, drv = rig
    drv.configure([ChannelSpec("vel", "response", "velocity", "m/s", sensitivity=0.1, physical="Dev1/ai0",
                               range_v=5.0, iepe_current_a=0.004)], RATE)
    ai = dev.tasks["frfcal_ai"].ai_channels
    ai.add_ai_voltage_chan.assert_called_once_with(
        "Dev1/ai0", name_to_assign_to_channel="vel", terminal_config=c.TerminalConfiguration.PSEUDO_DIFF,
        min_val=-5.0, max_val=5.0)
    chan = ai.add_ai_voltage_chan.return_value
    assert chan.ai_excit_voltage_or_current == c.ExcitationVoltageOrCurrent.USE_CURRENT
    assert chan.ai_excit_src == c.ExcitationSource.INTERNAL and chan.ai_excit_val == 0.004
    assert chan.ai_coupling == c.Coupling.AC
    assert dev.tasks["frfcal_ao"].timing.cfg_samp_clk_timing.call_args.kwargs["source"] == "/Dev1/ai/SampleClock"


def test_bad_channels_are_named(rig):
    _, drv = rig
    with pytest.raises(ValueError, match="'x'.*physical"):
        drv.configure([ChannelSpec("x", "response", "acceleration", "m/s^2")], RATE)
    with pytest.raises(ValueError, match="sample_rate_hz"):
        drv.configure(CHANNELS, None)


def test_missing_ni_runtime_is_driver_unavailable():
    """Without NI's DAQmx library, creating a task raises DaqNotFoundError: one clear line, no traceback."""
    from acquisition.drivers import DriverUnavailable

    def no_runtime(name):
        raise nidaqmx.errors.DaqNotFoundError("Could not find an installation of NI-DAQmx.")

    drv = NiDaqDriver("Dev1/ao0", task_factory=no_runtime)
    with pytest.raises(DriverUnavailable, match="NI-DAQmx runtime not installed") as err:
        drv.configure(CHANNELS, RATE)
    assert isinstance(err.value, DriverError) and isinstance(err.value, ValueError)
    drv.close()  # nothing was opened: closing is a no-op
