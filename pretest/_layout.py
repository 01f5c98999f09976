"""The layout file, as pretest writes it: the planner's channel map and metrics.

The format, the reader and the writer are defined once, in :mod:`labdata`
(``docs/layout.md``); this module fills the file from a :class:`PretestResult`
(:func:`layout_dict`, :func:`write_layout`) and re-exports the reader with
pretest's error type (:func:`read_layout`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from labdata import (
    LAYOUT_FORMAT as FORMAT,
    LAYOUT_VERSION as VERSION,
    LayoutChannel,
    LayoutError,
    LayoutFile,
    layout_document,
    read_layout_file,
    write_layout_file,
)
from pretest._errors import PretestError

__all__ = ["LayoutChannel", "LayoutFile", "LayoutFileError", "layout_dict", "write_layout", "read_layout"]


class LayoutFileError(PretestError, LayoutError):
    """A malformed layout file, read through pretest: both a PretestError and a labdata.LayoutError."""


def _num(x):
    x = float(x)
    return x if np.isfinite(x) else None


def layout_dict(result, *, model_path=None, units=None, relative_to=None) -> dict:
    """The layout file content for a :class:`PretestResult`.

    Parameters
    ----------
    result : PretestResult
    model_path : str or Path, optional
        The model deck, stored relative to ``relative_to`` when possible.
    units : str, optional
        The deck's unit system.
    relative_to : str or Path, optional
        Folder of the layout file.
    """
    s, d = result.sensors, result.drives
    channels = [
        LayoutChannel(n, "response", "acceleration", "m/s^2", int(g), tuple(map(float, v)), tuple(map(float, x)))
        for n, g, v, x in zip(result.channel_names, s.grids, s.directions, s.xyz_m)
    ]
    drives = [
        LayoutChannel(n, "force", "force", "N", int(g), tuple(map(float, v)), tuple(map(float, x)))
        for n, g, v, x in zip(result.drive_names, d.grids, d.directions, d.xyz_m)
    ]
    m = result.metrics.as_dict()
    rk = result.drive_ranking
    dc = result.drive_candidates
    top = rk.order[: result.config.n_shaker_candidates]
    ml = result.mass_loading
    metrics = dict(m)
    metrics.update(
        {
            "method": "effective independence (Kammer 1991), backward deletion"
            + (", triaxial bundles" if result.config.triax else ""),
            "target_mode_numbers": [int(i) + 1 for i in result.target.indices],
            "n_rigid_modes": int(result.target.n_rigid),
            "n_candidates": int(np.unique(result.candidates.group).size),
            "n_sensors": int(np.unique(s.group).size),
            "min_distance_m": float(result.config.min_distance_m),
            "efi_swaps_for_distance": int(result.efi.n_swaps),
            "automac": [[round(float(v), 6) for v in row] for row in result.metrics.automac],
            "drive_candidates": [
                {
                    "grid": int(dc.grids[i]),
                    "direction": [float(v) for v in dc.directions[i]],
                    "weakest_participation": _num(rk.weakest[i]),
                    "weakest_mode_number": int(result.target.indices[rk.weakest_mode[i]]) + 1,
                    "adpr_s_per_kg": _num(rk.adpr[i]),
                    "adpr_normalized": _num(rk.adpr_normalized[i]),
                }
                for i in top.tolist()
            ],
            "drive_criterion": result.config.drive_criterion,
            **result.extra,
            "mass_loading": {
                "sensor_mass_kg": float(result.config.sensor_mass_kg),
                "drive_mass_kg": float(result.config.drive_mass_kg),
                "shift_hz": [_num(v) for v in ml.shift_hz],
                "relative_shift": [_num(v) for v in ml.relative_shift],
                "loaded_frequencies_hz": [_num(v) for v in ml.loaded_frequencies_hz],
            },
        }
    )
    return layout_document(
        channels,
        drives,
        model_path=model_path,
        units=units,
        target_modes_hz=result.target.frequencies_hz,
        metrics=metrics,
        relative_to=relative_to,
    )


def write_layout(path, result, *, model_path=None, units=None) -> Path:
    """Write the layout JSON for a :class:`PretestResult`; returns the path.

    The document is checked by the reader's rules before it is written.
    """
    path = Path(path)
    data = layout_dict(result, model_path=model_path, units=units, relative_to=path.parent)
    try:
        return write_layout_file(path, data)
    except LayoutError as exc:
        raise LayoutFileError(str(exc)) from None


def read_layout(path) -> LayoutFile:
    """Read a layout JSON file (see ``docs/layout.md``): :func:`labdata.read_layout_file`.

    Raises
    ------
    LayoutFileError
        A :class:`PretestError` (and a :class:`labdata.LayoutError`) naming the
        file and the entry and field at fault; also for a missing file.
    OSError
        If an existing file cannot be read.
    """
    try:
        return read_layout_file(path)
    except LayoutError as exc:
        raise LayoutFileError(str(exc)) from None
