"""The pretest layout JSON (``"format": "frfcal-layout"``) as acquisition's channel map.

The format and its one reader live in :mod:`labdata` (``docs/layout.md``);
this module maps the layout's channels to :class:`ChannelSpec` and adds the
one rule of its own: a sweep needs at least one drive.
"""

from __future__ import annotations

from dataclasses import dataclass

from acquisition._driver import ChannelSpec
from labdata import LayoutChannel, LayoutError, read_layout_file

__all__ = ["Layout", "LayoutError", "NOMINAL_SENSITIVITY", "read_layout"]


@dataclass(frozen=True)
class Layout:
    """Sensors and drives of a test set-up, as planned by pretest.

    ``sensors`` are response (and monitor) channels, ``drives`` force channels
    (one per drive point), both with grid id and unit direction vector (basic
    system).

    Attributes
    ----------
    path : str
    sensors, drives : tuple of ChannelSpec
    model : dict
        ``{"path": deck resolved against the layout's folder or None, "units": str or None}``.
    target_modes_hz : tuple of float
    metrics : dict
    xyz_m : dict
        Channel name -> grid position (m, basic system; NaN when not given).
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


def _spec(c: LayoutChannel) -> ChannelSpec:
    sensitivity = c.sensitivity_v_per_unit
    if sensitivity is None:
        sensitivity = NOMINAL_SENSITIVITY.get(c.quantity, 1.0)
    return ChannelSpec(
        name=c.name,
        role=c.role,
        quantity=c.quantity,
        unit=c.unit,
        sensitivity=sensitivity,
        physical=c.physical,
        range_v=10.0 if c.range_v is None else c.range_v,
        grid=c.grid,
        direction=c.direction,
        serial=c.serial,
        iepe_current_a=c.iepe_current_a,
    )


def read_layout(path) -> Layout:
    """Read a pretest layout JSON file as acquisition channels.

    Parameters
    ----------
    path : str or Path
        A layout file (``docs/layout.md``); each entry may carry the hardware
        hints ``sensitivity_v_per_unit`` (default: nominal 100 mV/g or
        22.5 mV/N), ``range_v`` (default 10 V), ``serial``, ``physical``,
        ``iepe_current_a``.

    Returns
    -------
    Layout

    Raises
    ------
    LayoutError
        (:class:`labdata.LayoutError`) naming the file and the entry at fault,
        or when the layout has no drive.
    """
    lay = read_layout_file(path)
    if not lay.drives:
        raise LayoutError(f"{lay.path}: 'drives' must be a non-empty list (a sweep needs a drive point)")
    channels = lay.channels + lay.drives
    return Layout(
        path=lay.path,
        sensors=tuple(_spec(c) for c in lay.channels),
        drives=tuple(_spec(c) for c in lay.drives),
        model={"path": lay.model_path, "units": lay.model_units},
        target_modes_hz=tuple(float(f) for f in lay.target_modes_hz),
        metrics=dict(lay.metrics),
        xyz_m={c.name: c.xyz_m for c in channels},
    )
