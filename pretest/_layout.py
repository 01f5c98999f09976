"""The layout file: the pretest's channel map, read by acquisition and calibration.

Format (JSON, documented in ``docs/layout.md``)::

    {"format": "frfcal-layout", "version": 1,
     "model": {"path": "subframe.bdf", "units": "mm-t-s"},
     "channels": [{"name": "acc01", "role": "response", "quantity": "acceleration",
                   "unit": "m/s^2", "grid": 1234, "direction": [0, 0, 1],
                   "xyz_m": [0.1, 0.2, 0.0]}, ...],
     "drives": [{"name": "drive1", "role": "force", "quantity": "force", "unit": "N",
                 "grid": 4321, "direction": [0, 0, 1], "xyz_m": [...]}, ...],
     "target_modes_hz": [...], "metrics": {...}}
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pretest._errors import PretestError

__all__ = ["LayoutChannel", "LayoutFile", "layout_dict", "write_layout", "read_layout"]

FORMAT = "frfcal-layout"
VERSION = 1


@dataclass(frozen=True)
class LayoutChannel:
    """One channel of a layout: a grid and a unit direction (basic system)."""

    name: str
    role: str
    quantity: str
    unit: str
    grid: int
    direction: tuple[float, float, float]
    xyz_m: tuple[float, float, float]


@dataclass(frozen=True)
class LayoutFile:
    """A layout as read from disk.

    Attributes
    ----------
    path : str
    model_path : str or None
        Model deck, resolved against the layout file's folder.
    model_units : str or None
    channels, drives : tuple of LayoutChannel
    target_modes_hz : ndarray
    metrics : dict
    """

    path: str
    model_path: str | None
    model_units: str | None
    channels: tuple[LayoutChannel, ...]
    drives: tuple[LayoutChannel, ...]
    target_modes_hz: np.ndarray
    metrics: dict

    def grids(self, which: str = "channels") -> np.ndarray:
        return np.array([c.grid for c in getattr(self, which)], dtype=np.int64)

    def directions(self, which: str = "channels") -> np.ndarray:
        return np.array([c.direction for c in getattr(self, which)], dtype=float).reshape(-1, 3)


def _num(x):
    x = float(x)
    return x if np.isfinite(x) else None


def _entry(name, role, quantity, unit, grid, direction, xyz):
    return {
        "name": name,
        "role": role,
        "quantity": quantity,
        "unit": unit,
        "grid": int(grid),
        "direction": [float(v) for v in direction],
        "xyz_m": [float(v) for v in xyz],
    }


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
    path = None
    if model_path is not None:
        path = str(model_path)
        if relative_to is not None:
            try:
                path = os.path.relpath(os.path.abspath(model_path), os.path.abspath(relative_to))
            except ValueError:
                path = os.path.abspath(model_path)
    s, d = result.sensors, result.drives
    channels = [
        _entry(n, "response", "acceleration", "m/s^2", g, v, x)
        for n, g, v, x in zip(result.channel_names, s.grids, s.directions, s.xyz_m)
    ]
    drives = [
        _entry(n, "force", "force", "N", g, v, x)
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
    return {
        "format": FORMAT,
        "version": VERSION,
        "model": {"path": path, "units": units},
        "channels": channels,
        "drives": drives,
        "target_modes_hz": [float(f) for f in result.target.frequencies_hz],
        "metrics": metrics,
    }


def write_layout(path, result, *, model_path=None, units=None) -> Path:
    """Write the layout JSON for a :class:`PretestResult`; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = layout_dict(result, model_path=model_path, units=units, relative_to=path.parent)
    path.write_text(json.dumps(data, indent=1) + "\n")
    return path


def _channel(path, entry, where, role_default, quantity_default, unit_default) -> LayoutChannel:
    if not isinstance(entry, dict):
        raise PretestError(f"{path}: {where} must be an object")
    name = entry.get("name")
    if not isinstance(name, str) or not name:
        raise PretestError(f"{path}: {where} has no 'name'")
    try:
        grid = int(entry["grid"])
    except (KeyError, TypeError, ValueError):
        raise PretestError(f"{path}: {where} ({name}): 'grid' must be an integer grid id") from None
    d = np.asarray(entry.get("direction", ()), dtype=float)
    if d.shape != (3,) or not np.all(np.isfinite(d)) or np.linalg.norm(d) == 0:
        raise PretestError(f"{path}: {where} ({name}): 'direction' must be a non-zero 3-vector")
    d = d / np.linalg.norm(d)
    xyz = np.asarray(entry.get("xyz_m", (np.nan,) * 3), dtype=float)
    if xyz.shape != (3,):
        raise PretestError(f"{path}: {where} ({name}): 'xyz_m' must have 3 components")
    return LayoutChannel(
        name=name,
        role=str(entry.get("role", role_default)),
        quantity=str(entry.get("quantity", quantity_default)),
        unit=str(entry.get("unit", unit_default)),
        grid=grid,
        direction=tuple(float(v) for v in d),
        xyz_m=tuple(float(v) for v in xyz),
    )


def read_layout(path) -> LayoutFile:
    """Read a layout JSON file (see ``docs/layout.md``).

    Raises
    ------
    PretestError
        Naming the file and the entry at fault.
    OSError
        If the file cannot be read.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise PretestError(f"{path}: not valid JSON: {exc}") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise PretestError(f"{path}: 'format' must be {FORMAT!r}")
    if data.get("version") != VERSION:
        raise PretestError(f"{path}: 'version' is {data.get('version')!r}; this reader knows {VERSION}")
    chans = data.get("channels")
    if not isinstance(chans, list) or not chans:
        raise PretestError(f"{path}: 'channels' must be a non-empty list")
    drives = data.get("drives", [])
    if not isinstance(drives, list):
        raise PretestError(f"{path}: 'drives' must be a list")
    ch = tuple(_channel(path, e, f"channels[{i}]", "response", "acceleration", "m/s^2") for i, e in enumerate(chans))
    dr = tuple(_channel(path, e, f"drives[{i}]", "force", "force", "N") for i, e in enumerate(drives))
    names = [c.name for c in ch + dr]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise PretestError(f"{path}: duplicate channel names {dup}")
    model = data.get("model") or {}
    mpath = model.get("path")
    if mpath is not None and not os.path.isabs(mpath):
        mpath = str((path.parent / mpath).resolve())
    return LayoutFile(
        path=str(path),
        model_path=mpath,
        model_units=model.get("units"),
        channels=ch,
        drives=dr,
        target_modes_hz=np.asarray(data.get("target_modes_hz", []), dtype=float),
        metrics=dict(data.get("metrics", {})),
    )
