"""The hardware configuration file: physical channels, mapped once per lab.

The pretest layout says *what* is measured (sensor names, grids, directions,
quantities); this TOML file says *with what*: per channel its physical
address, sensitivity, serial, IEPE current and range, plus the driver set-up
(NI-DAQmx device or VISA instruments). See ``docs/hardware.md``::

    driver = "ni"                      # or "visa"

    [ni]
    ao_channel = "cDAQ1Mod4/ao0"
    ao_max_v = 2.0

    [visa]
    generator = "TCPIP::192.168.0.20::5025::SOCKET"

    [channels.acc01]
    physical = "cDAQ1Mod1/ai0"         # or the lock-in's VISA resource
    serial = "LW123456"
    sensitivity_mv_per_g = 100.2       # or sensitivity_mv_per_unit (mV per m/s^2, N, ...)
    iepe_current_ma = 4.0              # 0 or absent: voltage input
    range_v = 5.0                      # input range, peak volts

Unknown fields are rejected with an error naming the file and the field.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence

from acquisition._driver import ChannelSpec

#: Standard gravity, m/s^2 per g.
G0 = 9.80665
DRIVERS = ("ni", "visa")

_NI_FIELDS = {
    "ao_channel": str, "ao_max_v": float, "sample_clock": str, "start_trigger": str, "lead_s": float,
    "chunk_s": float, "buffer_s": float, "amplitude_ramp_s": float, "timeout_s": float, "terminal": str,
}
_VISA_FIELDS = {
    "generator": str, "backend": str, "timeout_ms": int, "tc_fraction": float, "filter_slope_db": int,
    "max_drive_v": float, "ramp_step_s": float,
}
_CHANNEL_FIELDS = {
    "physical": str, "serial": str, "sensitivity_mv_per_unit": float, "sensitivity_mv_per_g": float,
    "iepe_current_ma": float, "range_v": float,
}


class HardwareConfigError(ValueError):
    """The hardware configuration is malformed or does not cover the layout; names file and field."""


@dataclass(frozen=True)
class ChannelHardware:
    """The physical side of one channel.

    ``sensitivity_v_per_unit`` is volts per SI unit of the channel's quantity
    (from ``sensitivity_mv_per_unit``); ``sensitivity_v_per_g`` is set
    instead when the file gives mV/g (converted once the quantity is known).
    """

    name: str
    physical: str
    serial: str = ""
    sensitivity_v_per_unit: float | None = None
    sensitivity_v_per_g: float | None = None
    iepe_current_a: float | None = None
    range_v: float | None = None


@dataclass(frozen=True)
class HardwareConfig:
    """A parsed hardware configuration file.

    Attributes
    ----------
    path : str
    driver : {"ni", "visa"} or None
        Default driver of the lab (``frfcal acquire --driver`` overrides it).
    ni, visa : dict
        Keyword arguments of :class:`~acquisition.drivers.ni.NiDaqDriver` and
        :class:`~acquisition.drivers.visa.VisaDriver`.
    channels : dict[str, ChannelHardware]
    """

    path: str
    driver: str | None
    ni: dict = field(default_factory=dict)
    visa: dict = field(default_factory=dict)
    channels: dict = field(default_factory=dict)

    def mapped(self, specs: Sequence[ChannelSpec]) -> tuple[ChannelSpec, ...]:
        """The layout's channel specs with their physical side filled in from this file.

        Name, role, quantity, unit, grid and direction come from ``specs``
        (the pretest layout); physical address, sensitivity, serial, IEPE
        current and range from the file. Every channel of ``specs`` must be in
        the file.
        """
        out = []
        for spec in specs:
            hw = self.channels.get(spec.name)
            if hw is None:
                raise HardwareConfigError(
                    f"{self.path}: channel {spec.name!r} of the layout has no [channels.{spec.name}] entry "
                    f"(mapped: {', '.join(sorted(self.channels)) or 'none'})"
                )
            sensitivity = spec.sensitivity
            if hw.sensitivity_v_per_unit is not None:
                sensitivity = hw.sensitivity_v_per_unit
            elif hw.sensitivity_v_per_g is not None:
                if spec.quantity != "acceleration":
                    raise HardwareConfigError(
                        f"{self.path}: channels.{spec.name}.sensitivity_mv_per_g is for accelerometers, "
                        f"but {spec.name!r} measures {spec.quantity}"
                    )
                sensitivity = hw.sensitivity_v_per_g / G0
            out.append(replace(
                spec,
                physical=hw.physical,
                sensitivity=sensitivity,
                serial=hw.serial or spec.serial,
                iepe_current_a=hw.iepe_current_a,
                range_v=hw.range_v if hw.range_v is not None else spec.range_v,
            ))
        return tuple(out)

    def make_driver(self, driver: str | None = None, **overrides):
        """A driver built from the ``[ni]`` or ``[visa]`` section (``driver`` defaults to the file's)."""
        kind = driver or self.driver
        if kind not in DRIVERS:
            raise HardwareConfigError(f"{self.path}: no driver chosen: set driver = \"ni\" or \"visa\" (or pass --driver)")
        if kind == "ni":
            from acquisition.drivers.ni import NiDaqDriver

            if "ao_channel" not in self.ni:
                raise HardwareConfigError(f"{self.path}: [ni] needs ao_channel (the AO feeding the amplifier)")
            return NiDaqDriver(**(self.ni | overrides))
        from acquisition.drivers.visa import VisaDriver

        if "generator" not in self.visa:
            raise HardwareConfigError(f"{self.path}: [visa] needs generator (the generator's VISA resource)")
        return VisaDriver(**(self.visa | overrides))


def _typed(path: str, where: str, table: dict, fields: dict) -> dict:
    if not isinstance(table, dict):
        raise HardwareConfigError(f"{path}: [{where}] must be a table")
    out = {}
    for key, value in table.items():
        if key not in fields:
            raise HardwareConfigError(f"{path}: unknown field {where}.{key} (known: {', '.join(sorted(fields))})")
        kind = fields[key]
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, kind) or isinstance(value, bool):
            raise HardwareConfigError(f"{path}: {where}.{key} must be a {kind.__name__}, got {value!r}")
        if kind is float and not math.isfinite(value):
            raise HardwareConfigError(f"{path}: {where}.{key} must be finite, got {value!r}")
        out[key] = value
    return out


def _channel(path: str, name: str, table: dict) -> ChannelHardware:
    t = _typed(path, f"channels.{name}", table, _CHANNEL_FIELDS)
    where = f"{path}: channels.{name}"
    if not t.get("physical"):
        raise HardwareConfigError(f"{where}.physical is missing (the DAQ channel or the lock-in's VISA resource)")
    if "sensitivity_mv_per_unit" in t and "sensitivity_mv_per_g" in t:
        raise HardwareConfigError(f"{where}: give sensitivity_mv_per_unit or sensitivity_mv_per_g, not both")
    if "sensitivity_mv_per_unit" not in t and "sensitivity_mv_per_g" not in t:
        raise HardwareConfigError(f"{where}: sensitivity missing (sensitivity_mv_per_unit or sensitivity_mv_per_g)")
    for key in ("sensitivity_mv_per_unit", "sensitivity_mv_per_g", "range_v"):
        if key in t and t[key] <= 0:
            raise HardwareConfigError(f"{where}.{key} must be positive, got {t[key]}")
    iepe = t.get("iepe_current_ma", 0.0)
    if not 0 <= iepe <= 20:
        raise HardwareConfigError(f"{where}.iepe_current_ma must lie in [0, 20] mA, got {iepe}")
    return ChannelHardware(
        name=name,
        physical=t["physical"],
        serial=t.get("serial", ""),
        sensitivity_v_per_unit=t["sensitivity_mv_per_unit"] / 1000 if "sensitivity_mv_per_unit" in t else None,
        sensitivity_v_per_g=t["sensitivity_mv_per_g"] / 1000 if "sensitivity_mv_per_g" in t else None,
        iepe_current_a=iepe / 1000 if iepe > 0 else None,
        range_v=t.get("range_v"),
    )


def hardware_config_from_dict(data: dict, source: str = "hardware config") -> HardwareConfig:
    """Validate a hardware configuration given as a dict (the TOML structure)."""
    known = {"driver", "ni", "visa", "channels"}
    for key in data:
        if key not in known:
            raise HardwareConfigError(f"{source}: unknown top-level field {key!r} (known: {', '.join(sorted(known))})")
    driver = data.get("driver")
    if driver is not None and driver not in DRIVERS:
        raise HardwareConfigError(f"{source}: driver must be one of {DRIVERS}, got {driver!r}")
    ni = _typed(source, "ni", data.get("ni", {}), _NI_FIELDS)
    visa = _typed(source, "visa", data.get("visa", {}), _VISA_FIELDS)
    raw = data.get("channels", {})
    if not isinstance(raw, dict) or not raw:
        raise HardwareConfigError(f"{source}: [channels.<name>] tables are missing")
    channels = {name: _channel(source, name, table) for name, table in raw.items()}
    seen: dict[str, str] = {}
    for ch in channels.values():
        if ch.physical in seen:
            raise HardwareConfigError(
                f"{source}: channels {seen[ch.physical]!r} and {ch.name!r} both use {ch.physical!r}"
            )
        seen[ch.physical] = ch.name
    return HardwareConfig(path=source, driver=driver, ni=ni, visa=visa, channels=channels)


def read_hardware_config(path) -> HardwareConfig:
    """Read and validate a hardware configuration TOML file; errors name the file and the field."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise HardwareConfigError(f"{path}: hardware configuration file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise HardwareConfigError(f"{path}: not valid TOML: {exc}") from None
    return hardware_config_from_dict(data, source=str(path))


def hardware_template(specs: Sequence[ChannelSpec], driver: str = "ni") -> str:
    """A hardware TOML skeleton with one ``[channels.<name>]`` table per layout channel.

    ``physical`` is left empty (the file is rejected until every channel is
    mapped); sensitivities, serials, ranges and IEPE currents already in the
    specs are carried over.
    """
    if driver not in DRIVERS:
        raise HardwareConfigError(f"driver must be one of {DRIVERS}, got {driver!r}")
    lines = [f'driver = "{driver}"', ""]
    if driver == "ni":
        lines += ["[ni]", 'ao_channel = ""            # e.g. "cDAQ1Mod4/ao0": the AO feeding the amplifier',
                  "ao_max_v = 2.0", ""]
    else:
        lines += ["[visa]", 'generator = ""             # e.g. "TCPIP::192.168.0.20::5025::SOCKET"', ""]
    for spec in specs:
        lines += [f"[channels.{spec.name}]           # {spec.role} {spec.quantity}, grid {spec.grid}",
                  'physical = ""', f'serial = "{spec.serial}"',
                  f"sensitivity_mv_per_unit = {spec.sensitivity * 1000:.6g}   # mV per {spec.unit}",
                  f"iepe_current_ma = {(spec.iepe_current_a or 0.004) * 1000:g}",
                  f"range_v = {spec.range_v:g}", ""]
    return "\n".join(lines)
