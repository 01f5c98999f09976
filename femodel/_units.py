"""Unit systems a Nastran deck may be written in, and their factors to SI.

A deck declares one consistent unit system; every quantity is converted to SI
(m, kg, s, N, Pa) once, when the deck is read.  Force is derived from
length, mass and time (F = M L / T^2), so every system here is consistent.
"""

from __future__ import annotations

from dataclasses import dataclass

from femodel._model import ModelError


@dataclass(frozen=True)
class UnitSystem:
    """Factors that take one deck unit to SI.

    Parameters
    ----------
    name : str
        "si", "mm-t-s", "in-lbf-s" or "consistent".
    length_m : float
        Metres per deck length unit.
    mass_kg : float
        Kilograms per deck mass unit.
    time_s : float
        Seconds per deck time unit.
    """

    name: str
    length_m: float
    mass_kg: float
    time_s: float = 1.0

    @property
    def force_n(self) -> float:
        """Newtons per deck force unit (F = M L / T^2)."""
        return self.mass_kg * self.length_m / self.time_s**2

    @property
    def stress_pa(self) -> float:
        """Pascals per deck stress unit."""
        return self.force_n / self.length_m**2

    @property
    def density_kg_m3(self) -> float:
        """kg/m^3 per deck density unit."""
        return self.mass_kg / self.length_m**3

    def length(self, n: int) -> float:
        """Factor for length**n (n may be negative)."""
        return self.length_m**n


_INCH_M = 0.0254
_LBF_N = 4.4482216152605

UNIT_SYSTEMS: dict[str, UnitSystem] = {
    "si": UnitSystem("si", 1.0, 1.0),
    "consistent": UnitSystem("consistent", 1.0, 1.0),
    "mm-t-s": UnitSystem("mm-t-s", 1e-3, 1e3),
    # mass unit lbf s^2/in (slinch): F/(L/T^2)
    "in-lbf-s": UnitSystem("in-lbf-s", _INCH_M, _LBF_N / _INCH_M),
}


def unit_system(name: str) -> UnitSystem:
    """The :class:`UnitSystem` called ``name`` (case-insensitive).

    Raises
    ------
    ModelError
        For an unknown name; the message lists the known ones.
    """
    key = str(name).strip().lower()
    if key not in UNIT_SYSTEMS:
        raise ModelError(f"unknown unit system {name!r}; choose one of {sorted(UNIT_SYSTEMS)}")
    return UNIT_SYSTEMS[key]
