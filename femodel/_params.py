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
    lower = -0.3
    upper = 0.3
    unit = "m"                # optional, informative (values are SI inside)
    description = "thickness of the top skin"   # optional

Physical values are SI inside: the deck's unit system (and PARAM,WTMASS for
mass-like fields) is applied when values are read from or written to a deck.
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from femodel._model import ModelError
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
}

_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")
_MODEL_KEYS = {"bdf", "units"}
_PARAM_KEYS = {"name", "card", "id", "ids", "field", "lower", "upper", "unit", "description"}


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
        Informative SI unit of the physical value (``"Pa"``, ``"m"``, ...).
    description : str
        Free text.
    """

    name: str
    card: str
    ids: tuple[int, ...]
    field: str
    lower: float
    upper: float
    unit: str = ""
    description: str = ""

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


def _parameter_from_table(tab: dict, k: int, source) -> Parameter:
    label = f"[[parameter]] #{k + 1}"
    if not isinstance(tab, dict):
        _fail(source, f"{label} must be a table")
    name = tab.get("name")
    if isinstance(name, str):
        label = f"parameter {name!r}"
    unknown = sorted(set(tab) - _PARAM_KEYS)
    if unknown:
        _fail(source, f"{label}: unknown key(s) {unknown}; allowed: {sorted(_PARAM_KEYS)}")
    for req in ("name", "card", "field", "lower", "upper"):
        if req not in tab:
            _fail(source, f"{label}: missing required key {req!r}")
    if not isinstance(name, str) or not _NAME_RE.match(name):
        _fail(source, f"{label}: name must be an identifier-like string, got {name!r}")
    card, fld = tab["card"], tab["field"]
    if not isinstance(card, str) or not isinstance(fld, str):
        _fail(source, f"{label}: card and field must be strings")
    card, fld = card.strip().upper(), fld.strip().upper()
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
    bounds = []
    for b in ("lower", "upper"):
        v = tab[b]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            _fail(source, f"{label}: {b} must be a finite number, got {v!r}")
        bounds.append(float(v))
    lo, hi = bounds
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
    for opt in ("unit", "description"):
        if opt in tab and not isinstance(tab[opt], str):
            _fail(source, f"{label}: {opt} must be a string")
    return Parameter(
        name=name,
        card=card,
        ids=tuple(int(i) for i in ids),
        field=fld,
        lower=lo,
        upper=hi,
        unit=tab.get("unit", ""),
        description=tab.get("description", ""),
    )


def parameters_from_dict(data: dict, source=None, base_dir=None) -> ParameterSet:
    """Validate a parsed parameter file (a dict as from ``tomllib``).

    Raises
    ------
    ParameterError
        On unknown keys, missing keys, bad bounds, duplicate names or keys.
    """
    if not isinstance(data, dict):
        _fail(source, "parameter file must be a TOML table")
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
    params = tuple(_parameter_from_table(t, k, source) for k, t in enumerate(tables))
    return ParameterSet(params, bdf=bdf, units=units, source=Path(source) if source else None)


def read_parameters(path) -> ParameterSet:
    """Read and validate a parameter file (TOML, see ``docs/parameters.md``).

    The deck named in ``[model] bdf`` is resolved relative to the file; it is
    not read here (see :func:`nominal_values` for checks against a deck).
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ParameterError(f"{path}: cannot read parameter file ({exc.strerror or exc})") from None
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
    if card in ("PSHELL", "PBUSH", "PELAS"):
        return model.properties
    if card == "CONM2":
        return model.masses
    if card == "CELAS2":
        return model.elements
    raise KeyError(card)  # pragma: no cover - guarded by SUPPORTED_FIELDS


def deck_card(model, key, source=None):
    """The pyNastran card object for ``(card, id, field)``, or a ParameterError."""
    card, cid, fld = key
    obj = _container(model, card).get(cid)
    if obj is None or obj.type != card:
        have = "" if obj is None else f" (id {cid} is a {obj.type})"
        _fail(source, f"card {card} {cid} (field {fld}) is not in the deck{have}")
    return obj


def get_deck_value(obj, fld: str) -> float | None:
    """The raw deck value of ``fld`` on a pyNastran card (deck units)."""
    t = obj.type
    if t == "MAT1":
        return obj.e if fld == "E" else obj.rho
    if t == "PSHELL":
        return obj.t
    if t == "CONM2":
        return obj.mass
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
        obj.t = value
    elif t == "CONM2":
        obj.mass = value
    elif t == "PBUSH":
        obj.Ki[int(fld[1]) - 1] = value
    elif t in ("PELAS", "CELAS2"):
        obj.k = value
    else:  # pragma: no cover
        raise KeyError(t)


def _spring_kind(model, key, source) -> str:
    """Translational or rotational, from the components a PELAS/CELAS2 spring connects."""
    card, cid, _ = key
    if card == "CELAS2":
        elems = [model.elements[cid]]
    else:
        elems = [e for e in model.elements.values() if e.type == "CELAS1" and e.pid == cid]
    comps = set()
    for e in elems:
        for c in (e.c1, e.c2):
            if c not in (None, 0):
                comps.add(int(c))
    if not comps:
        return "trans_spring"
    if comps <= {1, 2, 3}:
        return "trans_spring"
    if comps <= {4, 5, 6}:
        return "rot_spring"
    _fail(source, f"{card} {cid} K: springs connect both translational and rotational components {sorted(comps)}; "
          "its unit is ambiguous")
    return ""  # pragma: no cover


def si_factor(model, key, units: str, source=None) -> float:
    """Multiply a deck value of ``key`` by this to get SI (applies PARAM,WTMASS to masses)."""
    if units not in UNIT_SYSTEMS:
        _fail(source, f"units must be one of {sorted(UNIT_SYSTEMS)}, got {units!r}")
    L, Mu = UNIT_SYSTEMS[units]
    kind = SUPPORTED_FIELDS[(key[0], key[2])]
    if kind == "spring":
        kind = _spring_kind(model, key, source)
    wtmass = 1.0
    if "WTMASS" in model.params:
        wtmass = float(model.params["WTMASS"].values[0])
    return {
        "stress": Mu / L,
        "density": Mu / L**3 * wtmass,
        "length": L,
        "mass": Mu * wtmass,
        "trans_spring": Mu,
        "rot_spring": Mu * L**2,
    }[kind]


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
        When a card or field is missing, or a nominal value is not positive
        (P = P0 (1 + p) then cannot represent a physical value).
    """
    units = units or params.units or "si"
    source = source or params.source
    out = []
    for prm in params.parameters:
        vals = []
        for key in prm.keys:
            obj = deck_card(model, key, source)
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
            vals.append(v)
        out.append(np.array(vals))
    return out
