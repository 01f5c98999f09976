"""Hardware drivers: can the software keep up with the hardware?

* NI-DAQmx streaming loop: host CPU time the driver spends per second of
  signal for 22 channels (21 IEPE inputs + force) at 51.2 kS/s, with the
  DAQmx reader and writer replaced by minimal in-memory stand-ins (so only
  the driver's own work is timed: waveform generation, top-up, scaling,
  bookkeeping). Real time needs a ratio well below 1.
* VISA loopback: SCPI exchanges per second through pyvisa + pyvisa-py to the
  loopback server, and wall time per frequency line of a controller sweep
  (3 modes at zeta = 0.1 %, 2 sensors + force) on the virtual clock.

Prints a table and writes ``benchmarks/results/hardware.json``.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from acquisition import ChannelSpec, ModalPlant, plan_from_dict, read_run, run_sweep
from acquisition.drivers.ni import NiDaqDriver

RESULTS = Path(__file__).resolve().parent / "results" / "hardware.json"


class _Task:
    """Just enough of nidaqmx.Task for the driver: records nothing, costs nothing."""

    def __init__(self, name):
        self.name = name
        self.ai_channels = self.ao_channels = self
        self.timing = self.triggers = self
        self.start_trigger = self
        self.in_stream = SimpleNamespace(overloaded_chans_exist=False)
        self.out_stream = SimpleNamespace()

    def __getattr__(self, name):  # add_ai_*_chan, cfg_samp_clk_timing, start, stop, write, close, ...
        return lambda *a, **k: None


class _Reader:
    def __init__(self, stream):
        self.noise = np.random.default_rng(0).normal(0, 1e-3, (22, 1 << 16))

    def read_many_sample(self, data, number_of_samples_per_channel, timeout):
        k = number_of_samples_per_channel
        data[:] = self.noise[:, :k]
        return k


class _Writer:
    """Takes every block at once (the driver's writer factory is called with the stream)."""

    def __init__(self, stream, auto_start=False):
        self.stream = stream

    def write_many_sample(self, data, timeout):
        return data.size


def bench_ni(rate=51200.0, seconds=20.0) -> dict:
    chans = [ChannelSpec(f"acc{k:02d}", "response", "acceleration", "m/s^2", sensitivity=0.0102,
                         physical=f"cDAQ1Mod{1 + k // 4}/ai{k % 4}", iepe_current_a=0.004) for k in range(21)]
    chans.append(ChannelSpec("force", "force", "force", "N", sensitivity=0.0225, physical="cDAQ1Mod7/ai0",
                             iepe_current_a=0.004))
    drv = NiDaqDriver("cDAQ1Mod8/ao0", task_factory=_Task, reader_factory=_Reader, writer_factory=_Writer)
    drv.configure(chans, rate)
    drv.set_drive(123.4, 0.5)
    blocks = 0
    t0 = time.process_time()
    while drv.time_s() < seconds:
        drv.read_block(50)  # ~0.4 s blocks
        blocks += 1
        if blocks % 10 == 0:
            drv.set_drive(123.4 + blocks / 10, 0.5)  # a new line now and then
    cpu = time.process_time() - t0
    signal = drv.time_s()
    drv.close()
    return {"channels": 22, "rate_hz": rate, "signal_s": signal, "cpu_s": cpu, "cpu_per_signal_s": cpu / signal}


def bench_visa() -> dict:
    from acquisition._scpi_server import make_visa_driver

    p = ModalPlant([150.0, 260.0, 410.0], 0.001, np.array([[1.0, 0.7, 0.5], [0.4, -0.9, 0.8]]),
                   np.array([[0.8, 0.5, -0.6]]))
    plan = plan_from_dict({
        "lines": {"kind": "bandwidth", "start_hz": 120.0, "stop_hz": 450.0, "background_step": 0.05,
                  "lines_per_bandwidth": 2, "span_bandwidths": 2,
                  "poles": [{"frequency_hz": f, "damping": 0.001} for f in (150.0, 260.0, 410.0)]},
        "limits": {"drive_v_max": 10.0},
        "channels": [{"name": "a1"}, {"name": "a2"}, {"name": "force", "role": "force", "quantity": "force"}],
    })
    sensors = tuple(ChannelSpec(f"a{k + 1}", "response", "acceleration", "m/s^2", sensitivity=0.0102,
                                physical=f"sim/{k}", range_v=5.0) for k in range(2))
    drive = ChannelSpec("force", "force", "force", "N", sensitivity=0.0225, physical="sim/force", range_v=5.0)
    d = make_visa_driver(p)
    path = Path(tempfile.mkdtemp()) / "run.h5"
    t0 = time.perf_counter()
    try:
        run_sweep(d, plan, path, sensors=sensors, drive=drive, level_n=0.3)
    finally:
        d.close()
    wall = time.perf_counter() - t0
    run = read_run(path)
    ratio = run.frf / p.frf(run.frequency_hz)
    n_ex = len(d.lab.transcript)
    return {"lines": int(run.n_lines), "exchanges": n_ex, "wall_s": wall, "exchanges_per_s": n_ex / wall,
            "wall_s_per_line": wall / run.n_lines, "virtual_s": float(run.time_s[-1]),
            "max_mag_error": float(np.max(np.abs(np.abs(ratio) - 1))),
            "max_phase_error_deg": float(np.max(np.abs(np.degrees(np.angle(ratio)))))}


def main() -> None:
    ni = bench_ni()
    visa = bench_visa()
    print("NI-DAQmx streaming loop (driver only, 22 ch @ 51.2 kS/s)")
    print(f"  {'signal (s)':>12} {'CPU (s)':>10} {'CPU / signal':>14}")
    print(f"  {ni['signal_s']:12.1f} {ni['cpu_s']:10.3f} {ni['cpu_per_signal_s']:14.4f}")
    print("VISA loopback sweep (pyvisa-py, 3 modes, zeta 0.1 %)")
    print(f"  {'lines':>6} {'exchanges':>10} {'exch/s':>8} {'wall/line (s)':>14} {'max |dH|/H':>11} {'max dphi (deg)':>15}")
    print(f"  {visa['lines']:6d} {visa['exchanges']:10d} {visa['exchanges_per_s']:8.0f} {visa['wall_s_per_line']:14.3f}"
          f" {visa['max_mag_error']:11.2e} {visa['max_phase_error_deg']:15.3f}")
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps({"ni_streaming": ni, "visa_loopback": visa}, indent=2))
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
