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
            first = deck_card(model, prm.keys[0], source)
            p0 = float(get_deck_value(first, prm.field)) * si_factor(model, prm.keys[0], units, source)
            for k in prm.keys:
                obj = deck_card(model, k, source)
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
              units: str | None = None, added_cards=(), keep_includes: bool = True) -> Path:
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

    extra = []
    for (card, cid), obj in sorted(modified.items()):
        container = {"MAT1": bdf.materials, "CONM2": bdf.masses, "CELAS2": bdf.elements}.get(card, bdf.properties)
        del container[cid]
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
