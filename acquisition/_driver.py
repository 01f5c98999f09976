"""The driver protocol: everything the stepped-sine controller knows about hardware.

One small protocol fits both kinds of lab set-up:

* a **sampling DAQ** (NI-DAQmx, the simulated lab): the driver streams the drive
  waveform and returns raw samples of every input channel on one shared sample
  clock (:class:`SampleBlock`); the controller demodulates them over whole
  cycles of the drive frequency;
* **demodulating instruments** (a signal generator with lock-in amplifiers or a
  dynamic signal analyzer over VISA): the driver returns complex amplitudes of
  the fundamental and, where the instrument gives them, harmonics
  (:class:`PhasorBlock`).

The controller never asks which driver it talks to; it calls
:func:`acquisition.phasors` (or equivalent) on whatever block comes back.

Units: drive amplitude in volts (peak) at the generator/AO output; channel data
in engineering units (N, m/s^2, V) after sensitivity scaling; frequencies in Hz;
times in seconds of the driver's clock (virtual for the simulated lab).

Safety contract: :meth:`Driver.ramp_down` must be callable in any state, any
number of times, and must leave the drive at zero; the controller calls it on
every exit path (normal end, Ctrl-C, exception, limit breach, driver fault).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, Sequence, runtime_checkable

import numpy as np


class DriverError(RuntimeError):
    """A hardware or transport fault (timeout, garbled reply, instrument error, underflow)."""


@dataclass(frozen=True)
class ChannelSpec:
    """One measured channel, as mapped once by the user.

    Parameters
    ----------
    name : str
        Channel name (unique in a run), e.g. ``"acc17"`` or ``"force"``.
    role : {"response", "force", "monitor"}
        What the controller uses the channel for; ``"force"`` channels are the
        FRF inputs (one per drive point).
    quantity : {"acceleration", "velocity", "displacement", "force", "voltage"}
    unit : str
        SI engineering unit of the scaled data, e.g. ``"m/s^2"``, ``"N"``.
    sensitivity : float
        Volts per engineering unit (e.g. 0.01 V/(m/s^2) for 100 mV/g is 0.0102).
    physical : str
        The hardware address of the channel (``"cDAQ1Mod1/ai0"``, ``"GPIB0::8::INSTR"``,
        ``"sim/3"``).
    range_v : float
        Input range (peak volts) the channel is configured for; overload is
        judged against it.
    grid, direction : int, (3,) float
        FE grid id and unit direction vector (basic coordinates) the sensor is
        attached to; ``grid=0`` for channels not tied to the model.
    serial : str
    iepe_current_a : float or None
        IEPE excitation current, or None for a voltage input.
    """

    name: str
    role: str
    quantity: str
    unit: str
    sensitivity: float = 1.0
    physical: str = ""
    range_v: float = 10.0
    grid: int = 0
    direction: tuple[float, float, float] = (0.0, 0.0, 0.0)
    serial: str = ""
    iepe_current_a: float | None = None


@dataclass(frozen=True)
class DriverInfo:
    """What :meth:`Driver.configure` reports back about the hardware."""

    name: str
    kind: str  # "sampling" or "demodulating"
    sample_rate_hz: float | None
    devices: tuple[str, ...] = ()
    details: dict = field(default_factory=dict)


@dataclass(frozen=True)
class SampleBlock:
    """Raw samples of every channel on the shared sample clock.

    ``samples`` is ``(n_channels, n_samples)`` in engineering units; sample k
    was taken at ``t0_s + k / rate_hz``. ``drive`` is the drive waveform
    actually output over the same samples (volts), or None if unknown.
    ``overload`` flags channels whose input range was exceeded in the block.
    """

    t0_s: float
    rate_hz: float
    samples: np.ndarray
    overload: np.ndarray
    drive: np.ndarray | None = None


@dataclass(frozen=True)
class PhasorBlock:
    """Demodulated complex peak amplitudes from instruments.

    ``harmonics`` is ``(n_channels, n_harmonics)`` complex, column 0 being the
    fundamental at ``frequency_hz``; phases are relative to the drive.
    ``duration_s`` is the integration time the instrument used.
    """

    t0_s: float
    frequency_hz: float
    duration_s: float
    harmonics: np.ndarray
    overload: np.ndarray


@runtime_checkable
class Driver(Protocol):
    """The four things a controller asks of the hardware, plus set-up and close."""

    def configure(self, channels: Sequence[ChannelSpec], sample_rate_hz: float | None) -> DriverInfo:
        """Set up channels (sensitivities, ranges, IEPE) and the shared clock."""
        ...

    def set_drive(self, frequency_hz: float, amplitude_v: float) -> None:
        """Change drive frequency and amplitude phase-continuously (no restart, no jump)."""
        ...

    def read_block(self, n_cycles: int) -> SampleBlock | PhasorBlock:
        """Wait for and return the next block covering ``n_cycles`` whole drive cycles."""
        ...

    def time_s(self) -> float:
        """The driver's clock (virtual for the simulated lab)."""
        ...

    def ramp_down(self, duration_s: float = 0.5) -> None:
        """Bring the drive smoothly to zero. Safe in any state, idempotent."""
        ...

    def close(self) -> None:
        """Release the hardware (after :meth:`ramp_down`)."""
        ...
