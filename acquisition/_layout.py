"""Read the pretest layout JSON (``"format": "frfcal-layout"``) into channel specs."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from acquisition._driver import ChannelSpec


class LayoutError(ValueError):
    """The layout file is malformed; the message names the file and the entry at fault."""


@dataclass(frozen=True)
class Layout:
    """Sensors and drives of a test set-up, as planned by pretest.

    ``sensors`` are response channels, ``drives`` force channels (one per
    drive point), both with grid id and unit direction vector (basic system).
    """

    path: str
    sensors: tuple[ChannelSpec, ...]
    drives: tuple[ChannelSpec, ...]
    model: dict
    target_modes_hz: tuple[float, ...]
    metrics: dict
    xyz_m: dict


#: Nominal sensitivities (V per SI unit) used when the layout gives none: 100 mV/g
#: accelerometers and 22.5 mV/N force sensors; the hardware configuration replaces them.
NOMINAL_SENSITIVITY = {"acceleration": 0.100 / 9.80665, "force": 0.0225}

_UNITS = {"acceleration": "m/s^2", "velocity": "m/s", "displacement": "m", "force": "N", "voltage": "V"}


def _channel(path: str, entry: dict, where: str, default_role: str) -> tuple[ChannelSpec, tuple]:
    if not isinstance(entry, dict):
        raise LayoutError(f"{path}: {where} must be an object, got {type(entry).__name__}")
    name = entry.get("name")
    if not isinstance(name, str) or not name:
        raise LayoutError(f"{path}: {where} has no 'name'")
    quantity = entry.get("quantity", "force" if default_role == "force" else "acceleration")
    if quantity not in _UNITS:
        raise LayoutError(f"{path}: {where} ({name}): unknown quantity {quantity!r}, expected one of {list(_UNITS)}")
    unit = entry.get("unit", _UNITS[quantity])
    if unit != _UNITS[quantity]:
        raise LayoutError(f"{path}: {where} ({name}): unit {unit!r} is not the SI unit {_UNITS[quantity]!r} of {quantity}")
    d = np.asarray(entry.get("direction", (0, 0, 0)), dtype=float)
    if d.shape != (3,):
        raise LayoutError(f"{path}: {where} ({name}): 'direction' must have 3 components, got {d.tolist()}")
    norm = np.linalg.norm(d)
    if norm == 0:
        raise LayoutError(f"{path}: {where} ({name}): 'direction' is the zero vector")
    d = d / norm
    try:
        grid = int(entry.get("grid", 0))
        sensitivity = float(entry.get("sensitivity_v_per_unit", NOMINAL_SENSITIVITY.get(quantity, 1.0)))
        range_v = float(entry.get("range_v", 10.0))
    except (TypeError, ValueError) as exc:
        raise LayoutError(f"{path}: {where} ({name}): bad numeric field: {exc}") from None
    iepe = entry.get("iepe_current_a")
    spec = ChannelSpec(
        name=name,
        role=entry.get("role", default_role),
        quantity=quantity,
        unit=unit,
        sensitivity=sensitivity,
        physical=str(entry.get("physical", "")),
        range_v=range_v,
        grid=grid,
        direction=tuple(float(x) for x in d),
        serial=str(entry.get("serial", "")),
        iepe_current_a=None if iepe is None else float(iepe),
    )
    xyz = tuple(float(x) for x in entry.get("xyz_m", (np.nan, np.nan, np.nan)))
    return spec, xyz


def read_layout(path) -> Layout:
    """Read a pretest layout JSON file.

    Parameters
    ----------
    path : str or Path
        File with ``{"format": "frfcal-layout", "version": 1, "channels": [...], "drives": [...]}``;
        each entry has name, role, quantity, unit, grid, direction and optionally
        ``sensitivity_v_per_unit`` (default: nominal 100 mV/g or 22.5 mV/N), ``range_v``,
        ``serial``, ``physical``, ``iepe_current_a``.

    Returns
    -------
    Layout
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise LayoutError(f"{path}: layout file not found") from None
    except json.JSONDecodeError as exc:
        raise LayoutError(f"{path}: not valid JSON: {exc}") from None
    if not isinstance(data, dict) or data.get("format") != "frfcal-layout":
        raise LayoutError(f"{path}: 'format' must be 'frfcal-layout'")
    if data.get("version") != 1:
        raise LayoutError(f"{path}: 'version' is {data.get('version')!r}, this reader knows 1")
    sensors, drives, xyz = [], [], {}
    for key, role, out in (("channels", "response", sensors), ("drives", "force", drives)):
        entries = data.get(key)
        if not isinstance(entries, list) or not entries:
            raise LayoutError(f"{path}: '{key}' must be a non-empty list")
        for k, entry in enumerate(entries):
            spec, p = _channel(str(path), entry, f"{key}[{k}]", role)
            out.append(spec)
            xyz[spec.name] = p
    names = [c.name for c in sensors + drives]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise LayoutError(f"{path}: duplicate channel names {dup}")
    return Layout(
        path=str(path),
        sensors=tuple(sensors),
        drives=tuple(drives),
        model=dict(data.get("model", {})),
        target_modes_hz=tuple(float(f) for f in data.get("target_modes_hz", ())),
        metrics=dict(data.get("metrics", {})),
        xyz_m=xyz,
    )
