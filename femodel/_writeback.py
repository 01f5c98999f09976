"""Write a modified model back to Nastran bulk data.

The deck is read with pyNastran, the parameterized fields are set to new
physical values (SI in, converted to the deck's unit system), and the deck is
written again. INCLUDE files are written beside the new main file at the same
relative paths (or, when that would overwrite the source files or when asked,
merged into one flattened file). The modified cards and any added cards are
written at the end of the main file in free-field format with the shortest
decimal that reads back to the same double, so values round-trip exactly; all
other cards are written by pyNastran in large-field format.
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path

import numpy as np

from femodel._params import (
    ParameterError,
    ParameterSet,
    _container,
    SUPPORTED_FIELDS,
    deck_card,
    get_deck_value,
    set_deck_value,
    si_factor,
)


def _read_deck(path: Path, save_file_structure: bool = False):
    from pyNastran.bdf.bdf import BDF
    from pyNastran.bdf.errors import MissingDeckSections

    log = logging.getLogger("femodel.pynastran")
    log.setLevel(logging.ERROR)
    if not path.is_file():
        raise FileNotFoundError(f"Nastran deck not found: {path}")
    from femodel._reader import _deck_kind, read_bulk_with_begin

    if _deck_kind(path) == "bulk-with-begin":  # as read_bdf reads it (its INCLUDEs flattened on write)
        bdf = BDF(debug=None, log=log)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                read_bulk_with_begin(bdf, path)
        except (SyntaxError, RuntimeError, ValueError, KeyError, IndexError, TypeError, AssertionError) as exc:
            raise ParameterError(f"{path}: pyNastran could not parse the deck: {exc}") from None
        return bdf
    last = None
    for punch in (False, True):
        bdf = BDF(debug=None, log=log)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                bdf.read_bdf(str(path), xref=False, validate=False, punch=punch,
                             save_file_structure=save_file_structure)
            return bdf
        except MissingDeckSections as exc:
            last = exc
            continue
        except (SyntaxError, RuntimeError, ValueError, KeyError, IndexError, TypeError, AssertionError) as exc:
            raise ParameterError(f"{path}: pyNastran could not parse the deck: {exc}") from None
    raise ParameterError(f"{path}: pyNastran could not parse the deck: {last}")


def _fmt_field(value) -> str:
    if value is None:
        return ""
    if isinstance(value, (bool, np.bool_)):
        raise ParameterError(f"card field {value!r}: booleans are not bulk-data values")
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        v = float(value)
        if not np.isfinite(v):
            raise ParameterError(f"card field {value!r} is not finite")
        return np.format_float_scientific(v, unique=True, trim="0")
    s = str(value).strip()
    if "," in s or "\n" in s:
        raise ParameterError(f"card field {value!r} may not contain commas or newlines")
    return s


def free_field_card(fields) -> str:
    """A bulk-data card in free-field format with exact (round-trip) reals.

    Parameters
    ----------
    fields : sequence
        Card name followed by its fields (int, float, str or None for blank),
        in the order of the small-field layout (continuation markers omitted).

    Returns
    -------
    str
        The card, 8 data fields per line, newline-terminated.
    """
    fields = list(fields)
    if not fields or not isinstance(fields[0], str) or not fields[0].strip():
        raise ParameterError(f"added card {fields!r}: the first field must be the card name")
    name = fields[0].strip().upper()
    data = [_fmt_field(v) for v in fields[1:]]
    while data and data[-1] == "":
        data.pop()
    chunks = [data[i:i + 8] for i in range(0, max(len(data), 1), 8)]
    lines = []
    for k, chunk in enumerate(chunks):
        if k < len(chunks) - 1:
            chunk = chunk + [""] * (8 - len(chunk))
        lines.append((name if k == 0 else "") + "," + ",".join(chunk))
    return "\n".join(lines) + "\n"


def _decimal_strings(x: float):
    """Exact decimal spellings of the double ``x`` (with a decimal point): compact exponent and positional."""
    m, e = np.format_float_scientific(x, unique=True, trim=".").split("e")
    e = int(e)
    if "." not in m:
        m += "."
    sci = m if e == 0 else f"{m}{e:+d}"  # Nastran's implicit exponent: 1.5+5 = 1.5E+5
    pos = np.format_float_positional(x, unique=True, trim=".")
    return sci, pos


def small_field_value(value: float) -> float:
    """The value nearest ``value`` (fewest significant digits dropped) whose spelling fits a small 8-character
    field: an added card of a fitted magnitude is then written in small field, exactly as it will be read."""
    v = float(value)
    if not np.isfinite(v):
        raise ParameterError(f"card field {value!r} is not finite")
    for digits in range(17, 0, -1):
        x = float(f"{v:.{digits - 1}e}")
        if any(len(c) <= 8 for c in _decimal_strings(x)):
            return x
    raise ParameterError(f"card field {value!r} does not fit in 8 characters")  # pragma: no cover


def _real_field(value: float, width: int) -> tuple[str, bool]:
    """The most precise spelling of a real in ``width`` characters and whether it is exact.

    Tries the shortest exact decimal first, then ever fewer significant digits.
    """
    v = float(value)
    if not np.isfinite(v):
        raise ParameterError(f"card field {value!r} is not finite")
    if v == 0.0:
        return "0.", True
    for digits in range(17, 0, -1):
        x = float(f"{v:.{digits - 1}e}")
        fits = [c for c in _decimal_strings(x) if len(c) <= width]
        if fits:
            return min(fits, key=len), x == v
    raise ParameterError(f"card field {value!r} does not fit in {width} characters")  # pragma: no cover


def fixed_field_card(fields) -> str:
    """A bulk-data card in fixed format: small field when every real fits exactly, else large field.

    Small field (8-character fields) is used when every real value has an
    exact spelling of at most 8 characters; otherwise the card is written in
    large field (``NAME*``, 16-character fields), whose reals carry 13 to 15
    significant digits (relative error below 1e-13), so values read back
    essentially exactly by Nastran and by pyNastran alike. Unlike free field,
    Nastran does not round large-field reals to 8 characters.

    Parameters
    ----------
    fields : sequence
        Card name followed by its fields (int, float, str or None for blank),
        in small-field order (continuation markers omitted).

    Returns
    -------
    str
        The card, newline-terminated.
    """
    fields = list(fields)
    if not fields or not isinstance(fields[0], str) or not fields[0].strip():
        raise ParameterError(f"added card {fields!r}: the first field must be the card name")
    name = fields[0].strip().upper()
    data = list(fields[1:])
    while data and data[-1] is None:
        data.pop()

    def spell(v, width):
        if v is None:
            return "", True
        if isinstance(v, (bool, np.bool_)):
            raise ParameterError(f"card {name} field {v!r}: booleans are not bulk-data values")
        if isinstance(v, (int, np.integer)):
            s = str(int(v))
        elif isinstance(v, (float, np.floating)):
            return _real_field(v, width)
        else:
            s = str(v).strip()
        if len(s) > width or "," in s:
            raise ParameterError(f"card {name} field {v!r} does not fit a {width}-character field")
        return s, True

    small = [spell(v, 8) for v in data]
    if all(ok for _, ok in small):
        lines, head = [], name.ljust(8)
        for i in range(0, max(len(small), 1), 8):
            chunk = "".join(s.rjust(8) for s, _ in small[i:i + 8])
            lines.append((head if i == 0 else " " * 8) + chunk)
        return "\n".join(ln.rstrip() for ln in lines) + "\n"
    large = [spell(v, 16)[0] for v in data]
    lines = []
    for i in range(0, max(len(large), 1), 4):
        head = (name + "*").ljust(8) if i == 0 else "*".ljust(8)
        lines.append(head + "".join(s.rjust(16) for s in large[i:i + 4]))
    return "\n".join(ln.rstrip() for ln in lines) + "\n"


def _resolve_values(values, parameters: ParameterSet | None, model, units, source):
    """Map every value to ((card, id, field) -> SI value)."""
    out: dict[tuple[str, int, str], float] = {}
    for key, value in values.items():
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise ParameterError(f"write_bdf: value for {key!r} must be a number, got {value!r}") from None
        if not np.isfinite(v) or v <= 0.0:
            raise ParameterError(f"write_bdf: value for {key!r} must be positive and finite, got {value!r}")
        if isinstance(key, str):
            if parameters is None:
                raise ParameterError(f"write_bdf: value keyed by name {key!r} needs parameters=ParameterSet")
            prm = parameters.parameters[parameters.index(key)]
            # a group moves together: every card is scaled by the factor of the first
            first = deck_card(model, prm.keys[0], source, f"parameter {prm.name!r}")
            p0 = float(get_deck_value(first, prm.field)) * si_factor(model, prm.keys[0], units, source)
            for k in prm.keys:
                obj = deck_card(model, k, source, f"parameter {prm.name!r}")
                pk = float(get_deck_value(obj, prm.field)) * si_factor(model, k, units, source)
                out[k] = v if k == prm.keys[0] else pk * (v / p0)
        else:
            if not (isinstance(key, tuple) and len(key) == 3):
                raise ParameterError(f"write_bdf: key {key!r} must be a parameter name or (card, id, field)")
            card, cid, fld = str(key[0]).upper(), int(key[1]), str(key[2]).upper()
            if (card, fld) not in SUPPORTED_FIELDS:
                raise ParameterError(f"write_bdf: card {card} field {fld} cannot be written back")
            out[(card, cid, fld)] = v
    return out


#: Property cards whose element subsets can be written back with scaled copies.
_COPYABLE_PROPERTIES = ("PSHELL", "PBAR", "PBARL", "PBEAM", "PBEAML", "PROD", "PSOLID")
_MID_FIELDS = ("mid", "mid1", "mid2", "mid3", "mid4")


class DeckEditor:
    """Adds cards to a deck being written: fresh ids, unit conversion, scaled property copies.

    Handed to each added term family's ``write_cards`` by :func:`write_bdf`
    after the parameter values are set, so copies carry the written values.
    Ids are taken above the largest id in use in each Nastran id space
    (elements, including masses and rigid elements; properties; materials).

    Attributes
    ----------
    units : UnitSystem
        The deck's unit system.
    wtmass : float
        PARAM,WTMASS of the deck.
    cards : list of str
        The cards added so far (fixed format, :func:`fixed_field_card`).
    """

    def __init__(self, bdf, units: str, source):
        from femodel._units import unit_system

        self._bdf = bdf
        self.source = source
        self.units = unit_system(units)
        self.wtmass = float(bdf.params["WTMASS"].values[0]) if "WTMASS" in bdf.params else 1.0
        self.cards: list[str] = []
        self._repointed: dict[int, int] = {}

        def top(*containers):
            return max((int(k) for c in containers for k in c), default=0)

        self._next = {
            "element": top(bdf.elements, bdf.masses, bdf.rigid_elements, bdf.plotels) + 1,
            "property": top(bdf.properties, bdf.properties_mass) + 1,
            "material": top(bdf.materials, bdf.thermal_materials) + 1,
        }

    def new_id(self, space: str) -> int:
        """A fresh id in ``space`` ("element", "property" or "material")."""
        i = self._next[space]
        self._next[space] = i + 1
        return i

    def add(self, fields) -> None:
        """Append a card given as a field list (written by :func:`fixed_field_card`)."""
        self.cards.append(fixed_field_card(fields))

    def deck_value(self, si_value: float, kind: str) -> float:
        """An SI value in the deck's units; ``kind`` is "trans_spring", "rot_spring" or "mass"."""
        L, Mu = self.units.length_m, self.units.mass_kg
        factor = {"trans_spring": Mu, "rot_spring": Mu * L**2, "mass": Mu * self.wtmass}[kind]
        return float(si_value) / factor

    def scaled_copies(self, elements, kind: str, factor: float, name: str) -> None:
        """Re-point ``elements`` to copies of their properties with stiffness or mass times ``factor``.

        ``kind`` "K" scales E and G of every MAT1 the property names (G left
        blank where it follows E); "M" scales RHO and the property's NSM. The
        elements' cards are rewritten with the new property id.
        """
        import copy

        bdf, where = self._bdf, f"{self.source}: added term {name!r}"
        new_pid: dict[int, int] = {}
        new_mid: dict[int, int] = {}
        for eid in elements:
            elem = bdf.elements.get(int(eid))
            if elem is None:
                raise ParameterError(f"{where}: element {eid} is not in the deck")
            if int(eid) in self._repointed:
                raise ParameterError(f"{where}: element {eid} is already in another element-subset term")
            if getattr(elem, "pid", None) is None:
                raise ParameterError(f"{where}: element {eid} ({elem.type}) has no property to copy")
            pid = int(elem.pid)
            prop = bdf.properties.get(pid)
            if prop is None or prop.type not in _COPYABLE_PROPERTIES:
                have = "missing" if prop is None else prop.type
                raise ParameterError(f"{where}: element {eid} has property {pid} ({have}); element-subset "
                                     f"factors are written back for {', '.join(_COPYABLE_PROPERTIES)} only")
            if pid not in new_pid:
                new = copy.deepcopy(prop)
                new.pid = self.new_id("property")
                new.comment = ""
                for fld in _MID_FIELDS:
                    mid = getattr(new, fld, None)
                    if mid is None or int(mid) <= 0:
                        continue
                    mid = int(mid)
                    if mid not in new_mid:
                        new_mid[mid] = self._material_copy(mid, kind, factor, where)
                    setattr(new, fld, new_mid[mid])
                nsm = getattr(new, "nsm", None)
                if kind == "M" and nsm is not None:  # PBEAM/PBEAML: one NSM per station
                    new.nsm = np.asarray(nsm, float) * factor if np.ndim(nsm) else float(nsm) * factor
                new_pid[pid] = new.pid
                self.add(new.repr_fields())
            elem.pid = new_pid[pid]
            self._repointed[int(eid)] = new_pid[pid]

    def _material_copy(self, mid: int, kind: str, factor: float, where: str) -> int:
        import copy

        mat = self._bdf.materials.get(mid)
        if mat is None or mat.type != "MAT1":
            raise ParameterError(f"{where}: material {mid} is not a MAT1 ({'missing' if mat is None else mat.type})")
        new = copy.deepcopy(mat)
        new.mid = self.new_id("material")
        follows = (mat.e and mat.nu is not None and mat.g is not None
                   and abs(mat.g - mat.e / (2.0 * (1.0 + mat.nu))) <= 1e-12 * abs(mat.g))
        if kind == "K":
            new.e = None if mat.e is None else mat.e * factor
            new.g = None if mat.g is None else mat.g * factor
        else:
            new.rho = mat.rho * factor
        fields = list(new.repr_fields())
        if follows:
            fields[3] = None
        self.add(fields)
        return new.mid


def _include_targets(bdf, model_path: Path, out_path: Path):
    """{source file: output file} for a deck with INCLUDEs, or None to flatten."""
    files = [Path(f) for f in getattr(bdf, "active_filenames", [])]
    if len(files) < 2:
        return None
    main_dir = model_path.resolve().parent
    targets = {str(files[0]): str(out_path)}
    for f in files[1:]:
        fr = f.resolve()
        try:
            rel = fr.relative_to(main_dir)
        except ValueError:
            rel = Path(f.name)
        target = out_path.parent / rel
        if target.resolve() in {x.resolve() for x in files}:
            return None  # would overwrite a source file: flatten instead
        targets[str(f)] = str(target)
    if len(set(targets.values())) != len(targets):
        return None
    return targets


def write_bdf(model_path, out_path, values, *, parameters: ParameterSet | None = None,
              units: str | None = None, added_cards=(), added_terms=(), keep_includes: bool = True) -> Path:
    """Write ``model_path`` to ``out_path`` with new physical values and added cards.

    Parameters
    ----------
    model_path, out_path : path-like
        The source deck and the deck to write (one flattened file).
    values : mapping
        New physical values in SI units, keyed by parameter name (needs
        ``parameters``; for a group the value is that of the first card id
        and the other ids are scaled by the same factor) or by
        ``(card, id, field)``, e.g. ``{("PSHELL", 4, "T"): 2.6e-3}``.
    parameters : ParameterSet, optional
        Resolves names; its ``units`` is the default unit system.
    units : str, optional
        The deck's unit system ("si", "mm-t-s", "in-lbf-s", "consistent").
    added_cards : sequence
        Extra cards, each a string (written verbatim) or a field list
        ``["CONM2", 99, 17, 0, 0.05]`` (written in exact free field).
    added_terms : sequence of (term family, value)
        Added term families (:mod:`femodel._terms`) and their physical values
        (SI magnitude, or the factor of an element subset). Their cards get
        fresh ids and are written in fixed format (:func:`fixed_field_card`);
        elements of a subset factor are re-pointed to scaled property copies.
    keep_includes : bool
        Write INCLUDE files beside ``out_path`` at their relative paths
        (default). The deck is flattened into one file instead when this is
        False or when an include would overwrite its own source.

    Returns
    -------
    Path
        ``out_path``.

    Raises
    ------
    ParameterError
        A key that names a missing card, field or parameter; a non-positive
        value; a malformed added card.
    """
    model_path, out_path = Path(model_path), Path(out_path)
    units = units or (parameters.units if parameters is not None else None) or "si"
    source = model_path
    bdf = _read_deck(model_path, save_file_structure=keep_includes)
    si_values = _resolve_values(values, parameters, bdf, units, source)

    modified = {}
    g_default = set()  # MAT1 ids whose G follows E (blank or equal to E / 2(1 + nu))
    for mid, m in bdf.materials.items():
        if m.type == "MAT1" and m.e and m.nu is not None and m.g is not None:
            if abs(m.g - m.e / (2.0 * (1.0 + m.nu))) <= 1e-12 * abs(m.g):
                g_default.add(mid)
    for key, v_si in si_values.items():
        obj = deck_card(bdf, key, source)
        if get_deck_value(obj, key[2]) is None:
            raise ParameterError(f"{source}: {key[0]} {key[1]} has no field {key[2]} to write")
        set_deck_value(obj, key[2], v_si / si_factor(bdf, key, units, source))
        modified[(key[0], key[1])] = obj

    editor = DeckEditor(bdf, units, source)
    for family, value in added_terms:
        family.write_cards(float(value), editor)

    extra = []
    for (card, cid), obj in sorted(modified.items()):
        del _container(bdf, card)[cid]
        comment = obj.comment or ""
        fields = list(obj.repr_fields())
        if card == "MAT1" and cid in g_default:
            fields[3] = None  # keep G blank so that it follows the new E
        extra.append(comment + free_field_card(fields))
    for card in added_cards:
        if isinstance(card, str):
            extra.append(card if card.endswith("\n") else card + "\n")
        else:
            extra.append(free_field_card(card))
    extra.extend(editor.cards)

    out_path.parent.mkdir(parents=True, exist_ok=True)
    targets = _include_targets(bdf, model_path, out_path) if keep_includes else None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if targets:
            for target in targets.values():
                Path(target).parent.mkdir(parents=True, exist_ok=True)
            bdf.write_bdfs(targets, relative_dirname=str(out_path.parent), size=16, is_double=False, enddata=False)
        else:
            bdf.write_bdf(str(out_path), size=16, is_double=False, enddata=False)
    with open(out_path, "a") as fh:
        if extra:
            fh.write("$ cards written by frfcal (free field, exact values)\n")
            fh.write("".join(extra))
        fh.write("ENDDATA\n")
    return out_path
