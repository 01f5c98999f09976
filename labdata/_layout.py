"""The layout file (``"format": "frfcal-layout"``, version 1): schema, the one reader and the one writer.

``docs/layout.md`` is the format. pretest writes it (:func:`layout_document`,
:func:`write_layout_file`), acquisition and the application read it
(:func:`read_layout_file`); each layer keeps its own view of the result
(``pretest.LayoutFile`` is :class:`LayoutFile`, ``acquisition.Layout`` maps
the channels to ``ChannelSpec``).

Rules (the same for every reader)::

    {"format": "frfcal-layout", "version": 1,                  required
     "model": {"path": str | null, "units": str | null},        optional object
     "channels": [entry, ...],                                   required, non-empty
     "drives": [entry, ...],                                     optional (may be empty)
     "target_modes_hz": [float, ...], "metrics": {...}}          optional; unknown keys ignored

    entry: name      non-empty str, unique over channels and drives   required
           grid      Nastran GRID id, integer >= 1                    required
           direction 3 finite numbers, not all zero (normalized)      required
           role      channels: "response" (default) or "monitor"; drives: "force" (default)
           quantity  response: acceleration (default) | velocity | displacement;
                     monitor: any channel quantity; drive: force (default)
           unit      the SI unit of the quantity (default), nothing else
           xyz_m     3 finite numbers, metres, basic system (default: unknown, NaN)
           sensitivity_v_per_unit, range_v   optional, finite > 0
           iepe_current_a                    optional, finite >= 0
           serial, physical                  optional strings
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from numbers import Integral, Real
from pathlib import Path

import numpy as np

from labdata._errors import LayoutError
from labdata._quantities import CHANNEL_UNITS, RESPONSE_QUANTITY

__all__ = [
    "LAYOUT_FORMAT",
    "LAYOUT_VERSION",
    "LayoutChannel",
    "LayoutFile",
    "layout_from_dict",
    "read_layout_file",
    "layout_document",
    "write_layout_file",
]

LAYOUT_FORMAT = "frfcal-layout"
LAYOUT_VERSION = 1

_NAN3 = (math.nan, math.nan, math.nan)
#: Allowed roles and the default one, per list of the file.
_ROLES = {"channels": ("response", "monitor"), "drives": ("force",)}
_MOTION = tuple(RESPONSE_QUANTITY.values())
#: Allowed quantities per role; the first one is the default.
_QUANTITIES = {
    "response": _MOTION,
    "monitor": ("acceleration",) + tuple(q for q in CHANNEL_UNITS if q != "acceleration"),
    "force": ("force",),
}


@dataclass(frozen=True)
class LayoutChannel:
    """One single-axis channel of a layout: a grid and a unit direction (basic system).

    Attributes
    ----------
    name : str
        Unique over the channels and drives of the file.
    role : {"response", "monitor", "force"}
    quantity : str
        ``acceleration``, ``velocity``, ``displacement`` (responses), ``force``
        (drives), or ``voltage`` (monitors).
    unit : str
        The SI unit of ``quantity`` (``m/s^2``, ``m/s``, ``m``, ``N``, ``V``).
    grid : int
        Nastran GRID id the channel sits on.
    direction : tuple of 3 float
        Unit vector of the measuring (or driving) direction, basic system.
    xyz_m : tuple of 3 float
        The grid's position, basic system, metres (NaN when not given).
    sensitivity_v_per_unit, range_v, iepe_current_a : float or None
        Optional hardware hints (V per SI unit, V peak, A); normally they live
        in the hardware file.
    serial, physical : str
        Optional hardware hints (sensor serial, DAQ address).
    """

    name: str
    role: str
    quantity: str
    unit: str
    grid: int
    direction: tuple[float, float, float]
    xyz_m: tuple[float, float, float] = _NAN3
    sensitivity_v_per_unit: float | None = None
    range_v: float | None = None
    iepe_current_a: float | None = None
    serial: str = ""
    physical: str = ""

    def as_dict(self) -> dict:
        """The JSON entry of this channel (optional fields only when set)."""
        out = {
            "name": self.name,
            "role": self.role,
            "quantity": self.quantity,
            "unit": self.unit,
            "grid": int(self.grid),
            "direction": [float(v) for v in self.direction],
        }
        if all(math.isfinite(float(v)) for v in self.xyz_m):
            out["xyz_m"] = [float(v) for v in self.xyz_m]
        for key in ("sensitivity_v_per_unit", "range_v", "iepe_current_a"):
            if getattr(self, key) is not None:
                out[key] = float(getattr(self, key))
        for key in ("serial", "physical"):
            if getattr(self, key):
                out[key] = getattr(self, key)
        return out


@dataclass(frozen=True)
class LayoutFile:
    """A layout as read from disk (or validated from a dictionary).

    Attributes
    ----------
    path : str
        The file (``"<layout>"`` for a dictionary without a file).
    model_path : str or None
        Model deck, resolved against the layout file's folder.
    model_units : str or None
        The deck's unit system as given to ``femodel.read_bdf``.
    channels, drives : tuple of LayoutChannel
    target_modes_hz : ndarray, shape (n_target,)
        Hz.
    metrics : dict
        As written by the planner; unknown keys are kept, never interpreted.
    """

    path: str
    model_path: str | None
    model_units: str | None
    channels: tuple[LayoutChannel, ...]
    drives: tuple[LayoutChannel, ...]
    target_modes_hz: np.ndarray
    metrics: dict

    def grids(self, which: str = "channels") -> np.ndarray:
        """Grid ids of ``which`` (``"channels"`` or ``"drives"``), int64 (n,)."""
        return np.array([c.grid for c in getattr(self, which)], dtype=np.int64)

    def directions(self, which: str = "channels") -> np.ndarray:
        """Unit directions of ``which``, (n, 3), basic system."""
        return np.array([c.direction for c in getattr(self, which)], dtype=float).reshape(-1, 3)

    def names(self, which: str = "channels") -> tuple[str, ...]:
        """Channel names of ``which``, in file order."""
        return tuple(c.name for c in getattr(self, which))


def _is_number(x) -> bool:
    return isinstance(x, Real) and not isinstance(x, bool)


def _vector(path, where, name, key, value) -> tuple[float, float, float]:
    if (not isinstance(value, (list, tuple)) or len(value) != 3
            or not all(_is_number(v) and math.isfinite(float(v)) for v in value)):
        raise LayoutError(f"{path}: {where} ({name}): '{key}' must be 3 finite numbers, got {value!r}")
    return tuple(float(v) for v in value)


def _optional_float(path, where, name, entry, key, minimum, strict) -> float | None:
    value = entry.get(key)
    if value is None:
        return None
    bad = not _is_number(value) or not math.isfinite(float(value))
    if not bad:
        bad = float(value) <= minimum if strict else float(value) < minimum
    if bad:
        rel = ">" if strict else ">="
        raise LayoutError(f"{path}: {where} ({name}): '{key}' must be a finite number {rel} {minimum:g}, got {value!r}")
    return float(value)


def _grid(path, where, name, value) -> int:
    grid = None
    if isinstance(value, Integral) and not isinstance(value, bool):
        grid = int(value)
    elif _is_number(value) and math.isfinite(float(value)) and float(value).is_integer():
        grid = int(value)
    elif isinstance(value, str) and value.strip().lstrip("+").isdigit():
        grid = int(value)
    if grid is None or grid < 1:
        raise LayoutError(f"{path}: {where} ({name}): 'grid' must be a Nastran grid id (integer >= 1), got {value!r}")
    return grid


def _channel(path, entry, key: str, k: int) -> LayoutChannel:
    where = f"{key}[{k}]"
    if not isinstance(entry, dict):
        raise LayoutError(f"{path}: {where} must be an object, got {type(entry).__name__}")
    name = entry.get("name")
    if not isinstance(name, str) or not name:
        raise LayoutError(f"{path}: {where} has no 'name'")
    roles = _ROLES[key]
    role = entry.get("role", roles[0])
    if role not in roles:
        raise LayoutError(f"{path}: {where} ({name}): 'role' must be one of {list(roles)} in '{key}', got {role!r}")
    allowed = _QUANTITIES[role]
    quantity = entry.get("quantity", allowed[0])
    if quantity not in allowed:
        raise LayoutError(
            f"{path}: {where} ({name}): unknown quantity {quantity!r} for role {role!r}, expected one of {list(allowed)}"
        )
    si = CHANNEL_UNITS[quantity]
    unit = entry.get("unit", si)
    if unit != si:
        raise LayoutError(f"{path}: {where} ({name}): unit {unit!r} is not the SI unit {si!r} of {quantity}")
    if "grid" not in entry:
        raise LayoutError(f"{path}: {where} ({name}): 'grid' is missing (the Nastran grid id the channel sits on)")
    grid = _grid(path, where, name, entry["grid"])
    if "direction" not in entry:
        raise LayoutError(f"{path}: {where} ({name}): 'direction' is missing (a unit vector, basic system)")
    d = np.array(_vector(path, where, name, "direction", entry["direction"]))
    norm = float(np.linalg.norm(d))
    if norm == 0.0:
        raise LayoutError(f"{path}: {where} ({name}): 'direction' is the zero vector")
    xyz = entry.get("xyz_m")
    xyz = _NAN3 if xyz is None else _vector(path, where, name, "xyz_m", xyz)
    text = {}
    for field in ("serial", "physical"):
        value = entry.get(field, "")
        if not isinstance(value, str):
            raise LayoutError(f"{path}: {where} ({name}): '{field}' must be a string, got {value!r}")
        text[field] = value
    return LayoutChannel(
        name=name,
        role=role,
        quantity=quantity,
        unit=unit,
        grid=grid,
        direction=tuple(float(v) for v in d / norm),
        xyz_m=xyz,
        sensitivity_v_per_unit=_optional_float(path, where, name, entry, "sensitivity_v_per_unit", 0.0, True),
        range_v=_optional_float(path, where, name, entry, "range_v", 0.0, True),
        iepe_current_a=_optional_float(path, where, name, entry, "iepe_current_a", 0.0, False),
        **text,
    )


def layout_from_dict(data, path=None) -> LayoutFile:
    """Validate a layout document (the parsed JSON) and return it as a :class:`LayoutFile`.

    Parameters
    ----------
    data : dict
        The document (see the module docstring and ``docs/layout.md``).
    path : str or Path, optional
        The file it came from: named in errors, and the folder a relative
        ``model.path`` is resolved against. Without it the model path is kept
        as written.

    Raises
    ------
    LayoutError
        Naming the file and the entry and field at fault.
    """
    label = "<layout>" if path is None else str(path)
    if not isinstance(data, dict) or data.get("format") != LAYOUT_FORMAT:
        raise LayoutError(f"{label}: 'format' must be {LAYOUT_FORMAT!r}")
    if data.get("version") != LAYOUT_VERSION or isinstance(data.get("version"), bool):
        raise LayoutError(f"{label}: 'version' is {data.get('version')!r}, this reader knows {LAYOUT_VERSION}")
    chans = data.get("channels")
    if not isinstance(chans, list) or not chans:
        raise LayoutError(f"{label}: 'channels' must be a non-empty list")
    drives = data.get("drives", [])
    if drives is None:
        drives = []
    if not isinstance(drives, list):
        raise LayoutError(f"{label}: 'drives' must be a list")
    ch = tuple(_channel(label, e, "channels", k) for k, e in enumerate(chans))
    dr = tuple(_channel(label, e, "drives", k) for k, e in enumerate(drives))
    names = [c.name for c in ch + dr]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise LayoutError(f"{label}: duplicate channel names {dup}")
    model = data.get("model")
    if model is None:
        model = {}
    if not isinstance(model, dict):
        raise LayoutError(f"{label}: 'model' must be an object with 'path' and 'units'")
    mpath, units = model.get("path"), model.get("units")
    for key, value in (("path", mpath), ("units", units)):
        if value is not None and (not isinstance(value, str) or not value):
            raise LayoutError(f"{label}: 'model.{key}' must be a non-empty string or null, got {value!r}")
    if mpath is not None and path is not None and not os.path.isabs(mpath):
        mpath = str((Path(path).parent / mpath).resolve())
    target = data.get("target_modes_hz")
    if target is None:
        target = []
    if not isinstance(target, list) or not all(_is_number(f) and math.isfinite(float(f)) for f in target):
        raise LayoutError(f"{label}: 'target_modes_hz' must be a list of finite numbers (Hz)")
    metrics = data.get("metrics")
    if metrics is None:
        metrics = {}
    if not isinstance(metrics, dict):
        raise LayoutError(f"{label}: 'metrics' must be an object, got {type(metrics).__name__}")
    return LayoutFile(
        path=label,
        model_path=mpath,
        model_units=units,
        channels=ch,
        drives=dr,
        target_modes_hz=np.asarray(target, dtype=float).reshape(-1),
        metrics=dict(metrics),
    )


def read_layout_file(path) -> LayoutFile:
    """Read and validate a layout JSON file (``docs/layout.md``).

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    LayoutFile
        With ``model_path`` resolved against the file's folder and every
        direction normalized.

    Raises
    ------
    LayoutError
        Missing file, invalid JSON, or any rule broken; the message names the
        file and the entry and field at fault.
    OSError
        If an existing file cannot be read.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise LayoutError(f"{path}: layout file not found") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise LayoutError(f"{path}: not valid JSON: {exc}") from None
    return layout_from_dict(data, path)


def layout_document(
    channels,
    drives=(),
    *,
    model_path=None,
    units: str | None = None,
    target_modes_hz=(),
    metrics: dict | None = None,
    relative_to=None,
) -> dict:
    """The layout file content (a JSON-ready dict) for channels and drives.

    Parameters
    ----------
    channels, drives : sequence of LayoutChannel
    model_path : str or Path, optional
        The model deck, stored relative to ``relative_to`` when possible
        (absolute when on another drive).
    units : str, optional
        The deck's unit system.
    target_modes_hz : array_like, optional
        Hz.
    metrics : dict, optional
        Anything JSON can hold.
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
    return {
        "format": LAYOUT_FORMAT,
        "version": LAYOUT_VERSION,
        "model": {"path": path, "units": units},
        "channels": [c.as_dict() for c in channels],
        "drives": [d.as_dict() for d in drives],
        "target_modes_hz": [float(f) for f in np.asarray(target_modes_hz, dtype=float).reshape(-1)],
        "metrics": dict(metrics or {}),
    }


def write_layout_file(path, document: dict) -> Path:
    """Validate ``document`` by the reader's rules and write it as JSON; returns the path.

    Nothing is written when the document breaks a rule, so every file written
    here reads back.

    Raises
    ------
    LayoutError
        As :func:`layout_from_dict`, naming ``path``.
    """
    path = Path(path)
    layout_from_dict(document, path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(document, indent=1) + "\n", encoding="utf-8")
    return path
