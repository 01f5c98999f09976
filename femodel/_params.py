"""Calibration parameters: the TOML parameter file, its validation, deck values.

A parameter names one field of one or more bulk-data cards of a deck and
scales it: P = P0 (1 + p), P0 the deck's (nominal) value and p the normalized
parameter that calibration moves within ``[lower, upper]``. The file format
is documented in ``docs/parameters.md``::

    [model]
    bdf = "subframe.bdf"      # relative to the parameter file
    units = "mm-t-s"          # si | mm-t-s | in-lbf-s | consistent

    [[parameter]]
    name = "t_top_skin"
    card = "PSHELL"
    id = 1                    # or ids = [1, 2, 3] for a group
    field = "T"
    lower = -0.3              # bounds on p; or lower_value/upper_value (absolute)
    upper = 0.3
    nominal = 2.5             # optional: P0 as the lab's table gives it, checked against the deck
    unit = "mm"               # optional: unit of nominal/lower_value/upper_value (default: deck units)
    description = "thickness of the top skin"   # optional

The same schema as JSON (``.json``): ``{"model": {...}, "parameter": [{...}, ...]}``.

Physical values are SI inside: the deck's unit system (and PARAM,WTMASS for
mass-like fields) is applied when values are read from or written to a deck.
"""

from __future__ import annotations

import json
import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from femodel._model import ModelError
from femodel._units import _INCH_M, _LBF_N
from femodel._units import UNIT_SYSTEMS as _CORE_UNITS


class ParameterError(ModelError):
    """A parameter file or parameter definition is invalid (names file and parameter)."""


#: unit system -> (metres per length unit, kilograms per mass unit); time is seconds.
#: The same systems as :mod:`femodel._units`, which the reader uses.
UNIT_SYSTEMS: dict[str, tuple[float, float]] = {
    name: (us.length_m, us.mass_kg) for name, us in _CORE_UNITS.items()
}

#: (card, field) -> physical kind. The kind fixes the SI conversion factor.
SUPPORTED_FIELDS: dict[tuple[str, str], str] = {
    ("MAT1", "E"): "stress",
    ("MAT1", "RHO"): "density",
    ("PSHELL", "T"): "length",
    ("CONM2", "M"): "mass",
    ("PBUSH", "K1"): "trans_spring",
    ("PBUSH", "K2"): "trans_spring",
    ("PBUSH", "K3"): "trans_spring",
    ("PBUSH", "K4"): "rot_spring",
    ("PBUSH", "K5"): "rot_spring",
    ("PBUSH", "K6"): "rot_spring",
    ("PELAS", "K"): "spring",
    ("CELAS2", "K"): "spring",
    ("PMASS", "M"): "scalar_mass",
    ("CMASS2", "M"): "scalar_mass",
    ("PBAR", "A"): "area",
    ("PBAR", "I1"): "area_moment",
    ("PBAR", "I2"): "area_moment",
    ("PBAR", "J"): "area_moment",
    ("PROD", "A"): "area",
    ("PROD", "J"): "area_moment",
}

#: Nastran's own names of fields the table spells shorter: PELAS K1 (its first spring's rate; a PELAS
#: card's second spring, K2, is not a parameter) and PMASS M1 are read as K and M.
FIELD_ALIASES: dict[tuple[str, str], str] = {("PELAS", "K1"): "K", ("PMASS", "M1"): "M"}

#: Kinds whose unit follows the components the scalar element joins (translational, rotational).
COMPONENT_KINDS: dict[str, tuple[str, str]] = {"spring": ("trans_spring", "rot_spring"),
                                               "scalar_mass": ("mass", "rot_mass")}

#: Relative tolerance between a declared value (``nominal``; an absolute bound against its normalized
#: twin) and the deck: about 4 significant digits. Unit mistakes (factors of 10^3) and wrong deck
#: versions fail; a table rounded to 4 or more digits passes.
NOMINAL_RTOL = 1e-4

_PSI = _LBF_N / _INCH_M**2
_SLINCH = _LBF_N / _INCH_M
#: the pound as a mass (lbm): a lab's table of CONM2 masses or densities in lb means it, whatever WTMASS the
#: deck carries (declared values are compared with the deck's SI value, WTMASS applied)
_LBM = 0.45359237
_SLUG = _LBF_N / 0.3048
#: physical kind -> {unit label: SI value of one unit}. Labels are case-sensitive; ``N/mm2``,
#: ``N mm/rad``, ``N.mm/rad``, ``N·mm/rad`` are read as ``N/mm^2``, ``N*mm/rad``.
UNITS: dict[str, dict[str, float]] = {
    "stress": {"Pa": 1.0, "kPa": 1e3, "MPa": 1e6, "GPa": 1e9, "N/m^2": 1.0, "N/mm^2": 1e6,
               "psi": _PSI, "ksi": 1e3 * _PSI, "lbf/in^2": _PSI},
    "density": {"kg/m^3": 1.0, "g/cm^3": 1e3, "t/m^3": 1e3, "kg/mm^3": 1e9, "t/mm^3": 1e12,
                "lbf*s^2/in^4": _SLINCH / _INCH_M**3, "lb/in^3": _LBM / _INCH_M**3, "lbm/in^3": _LBM / _INCH_M**3,
                "lb/ft^3": _LBM / 0.3048**3, "lbm/ft^3": _LBM / 0.3048**3},
    "length": {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "in": _INCH_M},
    "area": {"m^2": 1.0, "cm^2": 1e-4, "mm^2": 1e-6, "in^2": _INCH_M**2},
    "area_moment": {"m^4": 1.0, "cm^4": 1e-8, "mm^4": 1e-12, "in^4": _INCH_M**4},
    "mass": {"kg": 1.0, "g": 1e-3, "t": 1e3, "lbf*s^2/in": _SLINCH, "slinch": _SLINCH, "lb": _LBM, "lbm": _LBM,
             "slug": _SLUG},
    "trans_spring": {"N/m": 1.0, "N/mm": 1e3, "kN/m": 1e3, "kN/mm": 1e6, "lbf/in": _LBF_N / _INCH_M},
    "rot_spring": {"N*m/rad": 1.0, "N*mm/rad": 1e-3, "kN*m/rad": 1e3, "lbf*in/rad": _LBF_N * _INCH_M},
    "rot_mass": {"kg*m^2": 1.0, "kg*mm^2": 1e-6, "t*mm^2": 1e-3, "lbf*s^2*in": _SLINCH * _INCH_M**2,
                 "lb*in^2": _LBM * _INCH_M**2, "lbm*in^2": _LBM * _INCH_M**2},
}

_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")
_MODEL_KEYS = {"bdf", "units"}
_PARAM_KEYS = {"name", "card", "id", "ids", "field", "lower", "upper", "lower_value", "upper_value", "nominal",
               "unit", "description"}
_DECLARED = ("nominal", "lower_value", "upper_value")


def _unit_label(text: str) -> str:
    """Spelling variants of a unit label in one form (``N mm/rad`` -> ``N*mm/rad``, ``mm2`` -> ``mm^2``)."""
    t = text.strip().replace("\u00b2", "^2").replace("\u00b3", "^3").replace("\u2074", "^4").replace("**", "^")
    t = re.sub(r"\s*[\u00b7.]\s*|\s+", "*", t)
    return re.sub(r"([A-Za-z])(\d)", r"\1^\2", t)


def unit_factor(kind: str, unit: str) -> float | None:
    """SI value of one ``unit`` of a physical ``kind`` (``"spring"``, ``"scalar_mass"``: either of its
    :data:`COMPONENT_KINDS`), or None."""
    label = _unit_label(unit)
    kinds = COMPONENT_KINDS.get(kind, (kind,))
    for k in kinds:
        if label in UNITS[k]:
            return UNITS[k][label]
    return None


def _unit_kind(kind: str, unit: str) -> str:
    """The spring (scalar mass) kind a spring (scalar mass) unit names (``kind`` itself otherwise)."""
    if kind not in COMPONENT_KINDS:
        return kind
    trans, rot = COMPONENT_KINDS[kind]
    return trans if _unit_label(unit) in UNITS[trans] else rot


@dataclass(frozen=True)
class Parameter:
    """One calibration parameter.

    Attributes
    ----------
    name : str
        Unique name.
    card, field : str
        Bulk-data card type and field, e.g. ``("PSHELL", "T")``.
    ids : tuple of int
        The card ids it scales (one, or a group scaled together).
    lower, upper : float
        Bounds on the normalized parameter p (dimensionless, P = P0 (1 + p)).
    unit : str
        Unit of ``nominal``, ``lower_value`` and ``upper_value`` (a key of
        :data:`UNITS` for the field's kind); ``""`` = the deck's own units,
        i.e. the number as written on the card.
    description : str
        Free text.
    nominal : float or None
        P0 as declared by the file, in ``unit``; checked against the deck to
        :data:`NOMINAL_RTOL`. When absolute bounds were converted with the
        deck's value, that value (in ``unit``).
    lower_value, upper_value : float or None
        Absolute bounds on P as declared by the file, in ``unit``; ``lower``
        and ``upper`` hold them converted to p.
    """

    name: str
    card: str
    ids: tuple[int, ...]
    field: str
    lower: float
    upper: float
    unit: str = ""
    description: str = ""
    nominal: float | None = None
    lower_value: float | None = None
    upper_value: float | None = None

    @property
    def keys(self) -> tuple[tuple[str, int, str], ...]:
        """The ``(card, id, field)`` keys this parameter scales."""
        return tuple((self.card, i, self.field) for i in self.ids)


@dataclass(frozen=True)
class ParameterSet:
    """An ordered set of parameters, optionally tied to a deck.

    Attributes
    ----------
    parameters : tuple of Parameter
    bdf : Path or None
        The deck named in the ``[model]`` table (resolved against the file).
    units : str or None
        Its unit system (a key of :data:`UNIT_SYSTEMS`).
    source : Path or None
        The parameter file, for error messages.
    """

    parameters: tuple[Parameter, ...]
    bdf: Path | None = None
    units: str | None = None
    source: Path | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        where = f"{self.source}: " if self.source else ""
        seen: dict[str, int] = {}
        owner: dict[tuple, str] = {}
        for prm in self.parameters:
            if prm.name in seen:
                raise ParameterError(f"{where}duplicate parameter name {prm.name!r}")
            seen[prm.name] = len(seen)
            for key in prm.keys:
                if key in owner:
                    raise ParameterError(
                        f"{where}parameters {owner[key]!r} and {prm.name!r} both scale "
                        f"{key[0]} {key[1]} field {key[2]}"
                    )
                owner[key] = prm.name
        if self.units is not None and self.units not in UNIT_SYSTEMS:
            raise ParameterError(f"{where}[model] units must be one of {sorted(UNIT_SYSTEMS)}, got {self.units!r}")

    def __len__(self) -> int:
        return len(self.parameters)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parameters)

    @property
    def lower(self) -> np.ndarray:
        """Lower bounds on p, shape (n_params,)."""
        return np.array([p.lower for p in self.parameters])

    @property
    def upper(self) -> np.ndarray:
        """Upper bounds on p, shape (n_params,)."""
        return np.array([p.upper for p in self.parameters])

    def index(self, name: str) -> int:
        for j, p in enumerate(self.parameters):
            if p.name == name:
                return j
        raise ParameterError(f"no parameter named {name!r} (have {', '.join(self.names)})")

    def key_to_index(self) -> dict[tuple[str, int, str], int]:
        """Map every ``(card, id, field)`` key to the index of its parameter."""
        return {key: j for j, p in enumerate(self.parameters) for key in p.keys}


def _fail(source, message: str):
    where = f"{source}: " if source else ""
    raise ParameterError(where + message)


def _number(tab: dict, key: str, label: str, source) -> float | None:
    v = tab.get(key)
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        _fail(source, f"{label}: {key} must be a finite number, got {v!r}")
    return float(v)


def _parameter_from_table(tab: dict, k: int, source, deck=None) -> Parameter:
    """One validated parameter; ``deck`` = (pyNastran model, unit system) checks declared values."""
    label = f"[[parameter]] #{k + 1}"
    if not isinstance(tab, dict):
        _fail(source, f"{label} must be a table")
    name = tab.get("name")
    if isinstance(name, str):
        label = f"parameter {name!r}"
    unknown = sorted(set(tab) - _PARAM_KEYS)
    if unknown:
        _fail(source, f"{label}: unknown key(s) {unknown}; allowed: {sorted(_PARAM_KEYS)}")
    tab = {key: v for key, v in tab.items() if v is not None}  # JSON null = key left out
    for req in ("name", "card", "field"):
        if req not in tab:
            _fail(source, f"{label}: missing required key {req!r}")
    for b in ("lower", "upper"):
        if b not in tab and f"{b}_value" not in tab:
            _fail(source, f"{label}: missing required key {b!r} (or {b + '_value'!r}, in physical units)")
    if not isinstance(name, str) or not _NAME_RE.match(name):
        _fail(source, f"{label}: name must be an identifier-like string, got {name!r}")
    card, fld = tab["card"], tab["field"]
    if not isinstance(card, str) or not isinstance(fld, str):
        _fail(source, f"{label}: card and field must be strings")
    card, fld = card.strip().upper(), fld.strip().upper()
    fld = FIELD_ALIASES.get((card, fld), fld)
    if (card, fld) not in SUPPORTED_FIELDS:
        supported = ", ".join(f"{c}.{f}" for c, f in SUPPORTED_FIELDS)
        _fail(source, f"{label}: card {card} field {fld} cannot be parameterized (supported: {supported})")
    if ("id" in tab) == ("ids" in tab):
        _fail(source, f"{label}: give exactly one of 'id' or 'ids'")
    ids = [tab["id"]] if "id" in tab else tab["ids"]
    if not isinstance(ids, list) or not ids or not all(isinstance(i, int) and not isinstance(i, bool) and i > 0 for i in ids):
        _fail(source, f"{label}: id/ids must be positive integers, got {ids!r}")
    if len(set(ids)) != len(ids):
        _fail(source, f"{label}: ids repeat a card id: {ids!r}")
    for opt in ("unit", "description"):
        if opt in tab and not isinstance(tab[opt], str):
            _fail(source, f"{label}: {opt} must be a string")
    unit = tab.get("unit", "").strip()
    kind = SUPPORTED_FIELDS[(card, fld)]
    if unit and unit_factor(kind, unit) is None:
        kinds = COMPONENT_KINDS.get(kind, (kind,))
        known = sorted(u for k in kinds for u in UNITS[k])
        _fail(source, f"{label}: unit {unit!r} is not a unit of {card} {fld} (known: {', '.join(known)})")
    nominal = _number(tab, "nominal", label, source)
    if nominal is not None and not nominal > 0.0:
        _fail(source, f"{label}: nominal must be positive (P = P0 (1 + p)), got {nominal!r}")
    given = {b: _number(tab, b, label, source) for b in ("lower", "upper")}
    absolute = {b: _number(tab, f"{b}_value", label, source) for b in ("lower", "upper")}
    in_unit = unit or "(deck units)"

    keys = tuple((card, int(i), fld) for i in ids)
    if deck is not None and (nominal is not None or any(v is not None for v in absolute.values())):
        model, units = deck
        values = [_deck_value(label, unit, key, model, units, source) for key in keys]
        if nominal is not None:
            for key, (raw, v) in zip(keys, values):
                _check_nominal(label, nominal, unit, key, raw, v, units, source)
        elif any(v is not None for v in absolute.values()):
            v0 = values[0][1]
            for key, (raw, v) in zip(keys[1:], values[1:]):
                if abs(v - v0) > NOMINAL_RTOL * abs(v0):
                    _fail(source, f"{label}: lower_value/upper_value on a group need equal deck values, but "
                                  f"{card} {ids[0]} {fld} = {values[0][0]!r} and {card} {key[1]} {fld} = {raw!r}; "
                                  "give normalized lower/upper instead")
            nominal = v0  # the deck's P0, in `unit`
    ref = nominal
    if ref is None and any(v is not None for v in absolute.values()):
        _fail(source, f"{label}: lower_value/upper_value need 'nominal' or a deck ([model] bdf) to be converted "
                      "to normalized bounds")
    bounds = []
    for b in ("lower", "upper"):
        p, v = given[b], absolute[b]
        if v is not None:
            if not v > 0.0:
                _fail(source, f"{label}: {b}_value must be positive (P = P0 (1 + p) > 0), got {v!r}")
            if p is not None and abs(v - ref * (1.0 + p)) > NOMINAL_RTOL * abs(v):
                _fail(source, f"{label}: {b} = {p!r} and {b}_value = {v!r} {in_unit} disagree: with the nominal "
                              f"{ref:.8g} {in_unit} {b} = {p!r} is {ref * (1.0 + p):.8g} (relative tolerance "
                              f"{NOMINAL_RTOL:g})")
            if p is None:
                p = v / ref - 1.0
        bounds.append(p)
    lo, hi = bounds
    lv, uv = absolute["lower"], absolute["upper"]
    if lv is not None and uv is not None and not lv < uv:
        _fail(source, f"{label}: lower_value ({lv!r}) must be less than upper_value ({uv!r})")
    for b, v in absolute.items():
        if v is None:
            continue
        if v > ref * (1 + NOMINAL_RTOL) if b == "lower" else v < ref * (1 - NOMINAL_RTOL):
            _fail(source, f"{label}: the nominal value {ref:.8g} {in_unit} must lie within the bounds, "
                          f"{b}_value is {v!r}")
    if lv is not None and given["lower"] is None:
        lo = min(lo, 0.0)  # a lower_value at P0 within the tolerance is p = 0
    if uv is not None and given["upper"] is None:
        hi = max(hi, 0.0)
    if not lo < hi:
        _fail(source, f"{label}: lower ({lo}) must be less than upper ({hi})")
    if lo <= -1.0:
        _fail(
            source,
            f"{label}: lower bound {lo} makes the physical value {card} {fld} = P0*(1{lo:+g}) "
            "non-positive; lower must be > -1",
        )
    if not lo <= 0.0 <= hi:
        _fail(source, f"{label}: the nominal point p = 0 must lie within [lower, upper] = [{lo}, {hi}]")
    return Parameter(
        name=name,
        card=card,
        ids=tuple(int(i) for i in ids),
        field=fld,
        lower=lo,
        upper=hi,
        unit=unit,
        description=tab.get("description", ""),
        nominal=nominal,
        lower_value=lv,
        upper_value=uv,
    )


def parameters_from_dict(data: dict, source=None, base_dir=None) -> ParameterSet:
    """Validate a parsed parameter file (a dict as from ``tomllib`` or ``json``).

    When a parameter declares ``nominal`` or absolute bounds and ``[model] bdf``
    names a deck, the deck is read (pyNastran) to check the nominal values and
    to convert absolute bounds that come without a ``nominal``.

    Raises
    ------
    ParameterError
        On unknown keys, missing keys, bad bounds, duplicate names or keys, an
        unknown unit, a declared nominal value that disagrees with the deck.
    """
    if not isinstance(data, dict):
        _fail(source, "parameter file must be a table (TOML) or an object (JSON)")
    unknown = sorted(set(data) - {"model", "parameter"})
    if unknown:
        _fail(source, f"unknown top-level key(s) {unknown}; allowed: ['model', 'parameter']")
    bdf = units = None
    if "model" in data:
        model = data["model"]
        if not isinstance(model, dict):
            _fail(source, "[model] must be a table")
        bad = sorted(set(model) - _MODEL_KEYS)
        if bad:
            _fail(source, f"[model]: unknown key(s) {bad}; allowed: {sorted(_MODEL_KEYS)}")
        if "bdf" in model:
            if not isinstance(model["bdf"], str) or not model["bdf"]:
                _fail(source, "[model] bdf must be a non-empty string path")
            bdf = Path(model["bdf"])
            if not bdf.is_absolute() and base_dir is not None:
                bdf = Path(base_dir) / bdf
        if "units" in model:
            units = model["units"]
            if units not in UNIT_SYSTEMS:
                _fail(source, f"[model] units must be one of {sorted(UNIT_SYSTEMS)}, got {units!r}")
    tables = data.get("parameter", [])
    if not isinstance(tables, list) or not tables:
        _fail(source, "no [[parameter]] tables")
    deck = None
    if bdf is not None and any(isinstance(t, dict) and any(t.get(d) is not None for d in _DECLARED) for t in tables):
        from femodel._writeback import _read_deck

        try:
            deck = (_read_deck(bdf), units or "si")
        except FileNotFoundError as exc:
            _fail(source, f"[model] bdf: {exc} (needed to check the declared nominal values and bounds)")
    params = tuple(_parameter_from_table(t, k, source, deck) for k, t in enumerate(tables))
    return ParameterSet(params, bdf=bdf, units=units, source=Path(source) if source else None)


def _json_object(pairs, path):
    out = {}
    for key, value in pairs:
        if key in out:
            raise ParameterError(f"{path}: not valid JSON for a parameter file: key {key!r} appears twice in one "
                                 "object")
        out[key] = value
    return out


def read_parameters(path) -> ParameterSet:
    """Read and validate a parameter file: TOML (``.toml``) or JSON (``.json``), see ``docs/parameters.md``.

    The deck named in ``[model] bdf`` is resolved relative to the file. It is
    read only when a parameter declares ``nominal``, ``lower_value`` or
    ``upper_value`` (to check or convert them); see :func:`nominal_values` for
    the other checks against a deck.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".toml", ".json"):
        raise ParameterError(f"{path}: a parameter file must be .toml or .json, not {path.suffix or 'no extension'!r}")
    try:
        text = path.read_text()
    except OSError as exc:
        raise ParameterError(f"{path}: cannot read parameter file ({exc.strerror or exc})") from None
    if suffix == ".json":
        try:
            data = json.loads(text, object_pairs_hook=lambda pairs: _json_object(pairs, path))
        except json.JSONDecodeError as exc:
            where = f"line {exc.lineno}, column {exc.colno}"
            raise ParameterError(f"{path}: not valid JSON: {exc.msg} at {where}") from None
    else:
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ParameterError(f"{path}: not valid TOML: {exc}") from None
    return parameters_from_dict(data, source=path, base_dir=path.parent)


# ----------------------------------------------------------------------------
# Values in a pyNastran deck
# ----------------------------------------------------------------------------
def _container(model, card: str) -> dict:
    if card == "MAT1":
        return model.materials
    if card in ("PSHELL", "PBUSH", "PELAS", "PBAR", "PROD"):
        return model.properties
    if card == "PMASS":
        return model.properties_mass
    if card in ("CONM2", "CMASS2"):
        return model.masses
    if card == "CELAS2":
        return model.elements
    raise KeyError(card)  # pragma: no cover - guarded by SUPPORTED_FIELDS


def deck_card(model, key, source=None, label: str | None = None):
    """The pyNastran card object for ``(card, id, field)``, or a ParameterError (prefixed with ``label``,
    e.g. "parameter 'M_mass'", the parameter whose card it is)."""
    card, cid, fld = key
    obj = _container(model, card).get(cid)
    if obj is None or obj.type != card:
        have = "" if obj is None else f" (id {cid} is a {obj.type})"
        _fail(source, f"{label + ': ' if label else ''}card {card} {cid} (field {fld}) is not in the deck{have}")
    return obj


def get_deck_value(obj, fld: str) -> float | None:
    """The raw deck value of ``fld`` on a pyNastran card (deck units)."""
    t = obj.type
    if t == "MAT1":
        return obj.e if fld == "E" else obj.rho
    if t == "PSHELL":
        return obj.t
    if t in ("CONM2", "CMASS2", "PMASS"):
        return obj.mass
    if t in ("PBAR", "PROD"):
        return {"A": obj.A, "I1": getattr(obj, "i1", None), "I2": getattr(obj, "i2", None), "J": obj.j}[fld]
    if t == "PBUSH":
        i = int(fld[1]) - 1
        return obj.Ki[i] if len(obj.Ki) > i else None
    if t in ("PELAS", "CELAS2"):
        return obj.k
    raise KeyError(t)  # pragma: no cover


def set_deck_value(obj, fld: str, value: float) -> None:
    """Set ``fld`` on a pyNastran card (deck units); MAT1 G follows E when E moves."""
    t = obj.type
    if t == "MAT1":
        if fld == "E":
            if obj.g is not None and obj.e:
                obj.g = obj.g * (value / obj.e)
            obj.e = value
        else:
            obj.rho = value
    elif t == "PSHELL":
        # the fibre distances Z1, Z2 default to -T/2, T/2 (pyNastran fills them in when the deck leaves them
        # blank): they follow T, so the card is written with them blank again, not at the old T's values
        old = obj.t
        if old is not None and getattr(obj, "z1", None) is not None and obj.z1 == -old / 2.0:
            obj.z1 = -value / 2.0
        if old is not None and getattr(obj, "z2", None) is not None and obj.z2 == old / 2.0:
            obj.z2 = value / 2.0
        obj.t = value
    elif t in ("CONM2", "CMASS2", "PMASS"):
        obj.mass = value
    elif t in ("PBAR", "PROD"):
        setattr(obj, {"A": "A", "I1": "i1", "I2": "i2", "J": "j"}[fld], value)
    elif t == "PBUSH":
        obj.Ki[int(fld[1]) - 1] = value
    elif t in ("PELAS", "CELAS2"):
        obj.k = value
    else:  # pragma: no cover
        raise KeyError(t)


def _spring_kind(model, key, source) -> str:
    """Translational or rotational, from the components a PELAS/CELAS2 spring (PMASS/CMASS2 scalar mass)
    connects: ``trans_spring``/``rot_spring`` (``mass``/``rot_mass``)."""
    card, cid, fld = key
    if card == "CELAS2":
        elems = [model.elements[cid]]
    elif card == "CMASS2":
        elems = [model.masses[cid]]
    elif card == "PMASS":
        elems = [e for e in model.masses.values() if e.type == "CMASS1" and e.pid == cid]
    else:
        elems = [e for e in model.elements.values() if e.type == "CELAS1" and e.pid == cid]
    trans, rot = COMPONENT_KINDS[SUPPORTED_FIELDS[(card, fld)]]
    comps = set()
    for e in elems:
        for c in (e.c1, e.c2):
            if c not in (None, 0):
                comps.add(int(c))
    if not comps:
        return trans
    if comps <= {1, 2, 3}:
        return trans
    if comps <= {4, 5, 6}:
        return rot
    what = "springs connect" if trans == "trans_spring" else "scalar masses join"
    _fail(source, f"{card} {cid} {fld}: {what} both translational and rotational components {sorted(comps)}; "
          "its unit is ambiguous")
    return ""  # pragma: no cover


def si_factor(model, key, units: str, source=None) -> float:
    """Multiply a deck value of ``key`` by this to get SI (applies PARAM,WTMASS to masses)."""
    if units not in UNIT_SYSTEMS:
        _fail(source, f"units must be one of {sorted(UNIT_SYSTEMS)}, got {units!r}")
    L, Mu = UNIT_SYSTEMS[units]
    kind = SUPPORTED_FIELDS[(key[0], key[2])]
    if kind in COMPONENT_KINDS:
        kind = _spring_kind(model, key, source)
    wtmass = 1.0
    if "WTMASS" in model.params:
        wtmass = float(model.params["WTMASS"].values[0])
    return {
        "stress": Mu / L,
        "density": Mu / L**3 * wtmass,
        "length": L,
        "area": L**2,
        "area_moment": L**4,
        "mass": Mu * wtmass,
        "rot_mass": Mu * L**2 * wtmass,
        "trans_spring": Mu,
        "rot_spring": Mu * L**2,
    }[kind]


def _deck_value(label: str, unit: str, key, model, units: str, source) -> tuple[float, float]:
    """(number on the card, value in ``unit`` or, without a unit, that same number) of one key."""
    obj = deck_card(model, key, source, label)
    raw = get_deck_value(obj, key[2])
    if raw is None:
        _fail(source, f"{label}: {key[0]} {key[1]} has no field {key[2]}")
    raw = float(raw)
    if not unit:
        return raw, raw
    kind = SUPPORTED_FIELDS[(key[0], key[2])]
    actual = _spring_kind(model, key, source) if kind in COMPONENT_KINDS else kind
    if _unit_kind(kind, unit) != actual:
        _fail(source, f"{label}: unit {unit!r} is a {_unit_kind(kind, unit).replace('_', ' ')} unit, but "
                      f"{key[0]} {key[1]} {key[2]} is a {actual.replace('_', ' ')}")
    return raw, raw * si_factor(model, key, units, source) / unit_factor(kind, unit)


def _check_nominal(label: str, nominal: float, unit: str, key, raw: float, value: float, units: str, source) -> None:
    rel = abs(value - nominal) / abs(value) if value else math.inf
    if not rel <= NOMINAL_RTOL:
        in_unit = f" = {value:.8g} {unit}" if unit else ""
        _fail(source, f"{label}: nominal = {nominal!r} {unit or '(deck units)'} disagrees with the deck: "
                      f"{key[0]} {key[1]} field {key[2]} = {raw!r} ({units}){in_unit}; relative difference "
                      f"{rel:.3g} > {NOMINAL_RTOL:g}")


def nominal_values(params: ParameterSet, model, units: str | None = None, source=None) -> list[np.ndarray]:
    """SI nominal values of every parameter's cards, checked against a pyNastran deck.

    Parameters
    ----------
    params : ParameterSet
    model : pyNastran.bdf.bdf.BDF
        The deck, read (not necessarily cross-referenced).
    units : str, optional
        Unit system of the deck; defaults to ``params.units`` or ``"si"``.

    Returns
    -------
    list of (n_ids,) float arrays
        P0 per card id of each parameter (SI).

    Raises
    ------
    ParameterError
        When a card or field is missing, a nominal value is not positive
        (P = P0 (1 + p) then cannot represent a physical value), or a
        parameter's declared ``nominal`` disagrees with the deck (beyond
        :data:`NOMINAL_RTOL`; names parameter, card and field).
    """
    units = units or params.units or "si"
    source = source or params.source
    out = []
    for prm in params.parameters:
        vals = []
        for key in prm.keys:
            obj = deck_card(model, key, source, f"parameter {prm.name!r}")
            raw = get_deck_value(obj, prm.field)
            if raw is None:
                _fail(source, f"parameter {prm.name!r}: {key[0]} {key[1]} has no field {key[2]}")
            v = float(raw) * si_factor(model, key, units, source)
            if not v > 0.0:
                _fail(
                    source,
                    f"parameter {prm.name!r}: {key[0]} {key[1]} field {key[2]} is {raw!r}; a scaled "
                    "parameter needs a positive nominal value",
                )
            if prm.nominal is not None:
                _, declared = _deck_value(f"parameter {prm.name!r}", prm.unit, key, model, units, source)
                _check_nominal(f"parameter {prm.name!r}", prm.nominal, prm.unit, key, float(raw), declared, units,
                               source)
            vals.append(v)
        out.append(np.array(vals))
    return out
