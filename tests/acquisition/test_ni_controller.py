"""The stepped-sine controller through the NI-DAQmx driver's streaming loop (autospecced nidaqmx).

Behind the fakes the "device" is a structure: the AO samples drive an ideal
shaker (force = 4 N/V), and each accelerometer channel is the plant's exact
response to that force, piecewise linear between samples (first-order hold,
exact per complex pole). So the controller sees real transients after every
step, through the same task, reader and writer calls as on hardware.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("nidaqmx")

from scipy.signal import lfilter  # noqa: E402

from acquisition import ChannelSpec, DriverError, ModalPlant, plan_from_dict, read_run, run_sweep  # noqa: E402
from acquisition.drivers.ni import NiDaqDriver  # noqa: E402
from tests.acquisition.test_ni_fake import FakeDevice  # noqa: E402

pytestmark = pytest.mark.timeout(120)

RATE = 4096.0
SHAKER_N_PER_V = 4.0
MODES_HZ = (120.0, 185.0)
ZETA = 0.01


def plant() -> ModalPlant:
    return ModalPlant(MODES_HZ, ZETA, np.array([[0.5, 0.4], [0.35, -0.45]]), np.array([[0.5, 0.4]]))


class StructureResponse:
    """Exact first-order-hold response of a ModalPlant to the force the AO drives.

    The structure feels the force interpolated linearly between samples; the
    fundamental of that interpolant is the sampled sine times sinc^2(f/fs), so
    the FRF this device has is ``(H(f) - D) sinc^2(f/fs) + D`` (the feedthrough
    D of accelerance acts on the sample itself): :meth:`frf`.
    """

    @staticmethod
    def frf(p: ModalPlant, f, rate: float) -> np.ndarray:
        d = p.diagonal_form()[3].real
        return (p.frf(f) - d) * np.sinc(np.asarray(f) / rate)[:, None, None] ** 2 + d

    def __init__(self, p: ModalPlant, rate: float):
        poles, bz, cz, d = p.diagonal_form()
        T = 1.0 / rate
        a = np.exp(poles * T)
        g0 = (a - 1) / poles
        g1 = (a - 1 - poles * T) / (poles**2 * T)
        self.a, self.b = a, bz[:, 0]
        self.num = np.stack([g1, g0 - g1], axis=1)  # z[n] = a z[n-1] + b (g1 u[n] + (g0 - g1) u[n-1])
        self.cz, self.d = cz, d[:, 0]
        self.state = np.zeros(poles.size, complex)
        self.u_last = 0.0
        self.n = 0

    def __call__(self, generated, n0, k):
        assert n0 == self.n  # the device is clocked once, in order
        u = SHAKER_N_PER_V * generated[n0:n0 + k]
        z = np.empty((self.a.size, k), complex)
        for j in range(self.a.size):
            b = self.b[j] * self.num[j]
            # transposed direct form: the carried state is b1 u[-1] + a z[-1]
            zi = [b[1] * self.u_last + self.a[j] * self.state[j]]
            z[j], _ = lfilter(b, [1.0, -self.a[j]], u, zi=zi)
            self.state[j] = z[j, -1]
        self.u_last, self.n = u[-1], self.n + k
        acc = (self.cz @ z).real + np.outer(self.d.real, u)
        return np.vstack([acc, u])


SENSORS = tuple(ChannelSpec(f"acc{k}", "response", "acceleration", "m/s^2", sensitivity=0.0102,
                            physical=f"cDAQ1Mod1/ai{k}", range_v=5.0, iepe_current_a=0.004) for k in range(2))
DRIVE = ChannelSpec("force", "force", "force", "N", sensitivity=0.0225, physical="cDAQ1Mod1/ai3", range_v=5.0,
                    iepe_current_a=0.004)


def make_plan(**sections):
    return plan_from_dict({
        "sample_rate_hz": RATE,
        "channels": [{"name": "acc0"}, {"name": "acc1"}, {"name": "force", "role": "force", "quantity": "force"}],
        "lines": {"kind": "bandwidth", "start_hz": 100.0, "stop_hz": 200.0, "background_step": 0.1,
                  "lines_per_bandwidth": 2, "span_bandwidths": 1,
                  "poles": [{"frequency_hz": f, "damping": ZETA} for f in MODES_HZ]},
        "settle": {"assumed_damping": ZETA},
    } | sections)


def rig(p: ModalPlant):
    dev = FakeDevice(respond=StructureResponse(p, RATE))
    drv = NiDaqDriver("cDAQ1Mod4/ao0", ao_max_v=2.0, task_factory=dev.task,
                      reader_factory=dev.reader_factory(), writer_factory=dev.writer_factory())
    return dev, drv


def test_sweep_through_ni_streaming_matches_plant(tmp_path):
    p = plant()
    dev, drv = rig(p)
    try:
        res = run_sweep(drv, make_plan(), tmp_path / "r.h5", sensors=SENSORS, drive=DRIVE, level_n=0.5)
    finally:
        drv.close()
    assert res.status == "completed"
    run = read_run(tmp_path / "r.h5")
    assert run.hardware["driver"] == "ni" and run.hardware["sample_rate_hz"] == RATE
    ratio = run.frf / StructureResponse.frf(p, run.frequency_hz, RATE)
    assert np.max(np.abs(np.abs(ratio) - 1)) < 0.005
    assert np.max(np.abs(np.degrees(np.angle(ratio)))) < 0.5
    assert np.all(np.abs(run.force_n[:, 0] / 0.5 - 1) < 0.02)
    # one continuous stream for the whole sweep: started once, never restarted until the ramp-down
    starts = [e for e in dev.events if e.startswith("start")]
    assert starts == ["start frfcal_ao", "start frfcal_ai"]
    assert dev.events[-2:] == ["write frfcal_ao 0.0", "stop frfcal_ao"]


def test_ao_underflow_mid_sweep_aborts_safely_keeping_lines(tmp_path):
    p = plant()
    dev, drv = rig(p)
    done = []

    def on_line(f, frf, q):
        done.append(f)
        if len(done) == 3:
            dev.pause(int(RATE))  # the host stalls for 1 s: the AO FIFO runs dry

    try:
        with pytest.raises(DriverError, match="AO underflow"):
            run_sweep(drv, make_plan(), tmp_path / "r.h5", sensors=SENSORS, drive=DRIVE, level_n=0.5,
                      on_line=on_line)
        assert drv.drive_amplitude_v == 0.0
        assert dev.events[-2:] == ["write frfcal_ao 0.0", "stop frfcal_ao"]
    finally:
        drv.close()
    run = read_run(tmp_path / "r.h5")
    assert run.status == "aborted" and list(run.frequency_hz) == done
