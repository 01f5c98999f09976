"""Shared plants, channels and plans of the acquisition tests."""

from __future__ import annotations

import numpy as np

from acquisition import ChannelSpec, ModalPlant, plan_from_dict

MODES_HZ = (120.0, 185.0, 262.0)
ZETA = 0.001


def plant3(freqs=MODES_HZ) -> ModalPlant:
    """Three modes at zeta = 0.1 %, three sensors (one collocated) and one drive point."""
    shapes_out = np.array([[0.5, 0.4, 0.3], [0.35, -0.45, 0.5], [0.42, 0.25, -0.33]])
    shapes_in = np.array([[0.5, 0.4, 0.3]])
    return ModalPlant(freqs, ZETA, shapes_out, shapes_in)


SENSORS = tuple(
    ChannelSpec(f"acc{k}", "response", "acceleration", "m/s^2", sensitivity=0.0102, physical=f"sim/{k}",
                range_v=10.0, grid=10 + k, direction=(0.0, 0.0, 1.0))
    for k in range(3)
)
DRIVE = ChannelSpec("force", "force", "force", "N", sensitivity=0.0225, physical="sim/force", range_v=10.0,
                    grid=10, direction=(0.0, 0.0, 1.0))


def plan(lines: dict | None = None, **sections):
    data = {
        "name": "t",
        "sample_rate_hz": 4096.0,
        "channels": [{"name": c.name} for c in SENSORS] + [{"name": "force", "role": "force", "quantity": "force"}],
        "lines": lines or {
            "kind": "bandwidth", "start_hz": 100.0, "stop_hz": 300.0, "background_step": 0.04,
            "lines_per_bandwidth": 3, "span_bandwidths": 2,
            "poles": [{"frequency_hz": f, "damping": ZETA} for f in MODES_HZ],
        },
    }
    data.update(sections)
    return plan_from_dict(data)
