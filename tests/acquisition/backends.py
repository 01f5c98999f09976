"""Backends the controller suite runs against: factory ``plant -> Driver``.

Every factory returns a fresh driver for a :class:`acquisition.ModalPlant`;
channel addresses ``sim/<k>`` (plant output k) and ``sim/force`` (drive-point
force) are what the suite configures. Hardware emulators (VISA loopback) add
themselves here with one line.
"""

from __future__ import annotations

from acquisition import ShakerModel, SimulatedLab


def make_sim_driver(plant, **options):
    """The simulated lab as a sampling DAQ (raw blocks, demodulated by the controller)."""
    return SimulatedLab(plant, **({"shaker": ShakerModel(), "noise_rms": 1e-4, "seed": 1} | options))


def make_sim_lockin_driver(plant, **options):
    """The simulated lab as demodulating instruments (PhasorBlocks, like lock-in amplifiers)."""
    return SimulatedLab(plant, **({"shaker": ShakerModel(), "noise_rms": 1e-4, "seed": 2, "kind": "demodulating"} | options))


BACKENDS = {"sim": make_sim_driver, "sim-lockin": make_sim_lockin_driver}

from acquisition._scpi_server import make_visa_driver  # noqa: E402  (VISA driver + loopback SCPI server)
BACKENDS["visa"] = make_visa_driver
