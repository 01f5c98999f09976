"""UFF58 (universal file, function at nodal DOF) import and export of FRFs.

Mapping: a sensor or drive is an FE grid id plus a unit direction vector. In
UFF58 that is a node and a direction code (+-1..3 = +-X, +-Y, +-Z). Directions
along an axis map to the code; other directions get code 0 and the exact vector
travels in the ID lines (``id4`` response, ``id5`` reference), which this
reader also understands. Channel names travel in ``id2`` as ``"<out> / <in>"``
(and, cut to 10 characters, in the entity names).

Import identifies responses and references by the records' own fields (node
and direction), never by free text, so a MIMO file (n_out x n_in records)
becomes an (n_freq, n_out, n_in) run. ``id2`` names are used only in files
frfcal wrote (``id1`` starting ``frfcal FRF``).

Direction codes are along the axes of the node's displacement coordinate
system when the file has the test geometry (nodes 2411/15 with systems
2420/18): a skewed sensor's code is rotated into the global vector.

Export writes **binary UFF58b** by default: the abscissa and ordinate are raw
IEEE doubles, so a run file -> UFF -> run file round trip is bit-exact. (The
ASCII UFF58 format stores frequencies as E13.5, i.e. 6 significant digits; use
``binary=False`` only for tools that cannot read 58b.) pyuff 2.5 writes a wrong
byte count in 58b headers for complex uneven data, so the 58b records are
written here; reading goes through pyuff.

Units: ordinates in SI (m/s^2/N, m/s/N, m/N). On import, ``g``, ``mm/s^2``,
``mm/s``, ``mm`` and ``kN`` labels are converted to SI; other labels are refused.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from acquisition._driver import ChannelSpec
from acquisition.runfile import LineQuality, Run, RunFileError, create_run, read_run
from labdata import CHANNEL_UNITS, RESPONSE_QUANTITY

_SPEC = {"accelerance": 12, "mobility": 11, "receptance": 8}
_SPEC_INV = {v: k for k, v in _SPEC.items()}
_QTY = {q: (r, CHANNEL_UNITS[r]) for q, r in RESPONSE_QUANTITY.items()}
_IN, _FT, _LBF = 0.0254, 0.3048, 4.4482216152605
_SCALE_NUM = {"m/s^2": 1.0, "m/s2": 1.0, "g": 9.80665, "mm/s^2": 1e-3, "mm/s2": 1e-3, "m/s": 1.0, "mm/s": 1e-3,
              "m": 1.0, "mm": 1e-3, "in/s^2": _IN, "in/s2": _IN, "ft/s^2": _FT, "ft/s2": _FT, "in/s": _IN,
              "ft/s": _FT, "in": _IN, "none": 1.0, "": 1.0}
#: FRF quantity each ordinate unit implies (blank/NONE: none, the ordinate type decides)
_KIND_NUM = {**{u: "accelerance" for u in ("m/s^2", "m/s2", "g", "mm/s^2", "mm/s2", "in/s^2", "in/s2", "ft/s^2",
                                            "ft/s2")},
             **{u: "mobility" for u in ("m/s", "mm/s", "in/s", "ft/s")},
             **{u: "receptance" for u in ("m", "mm", "in")}}
_SCALE_DEN = {"n": 1.0, "kn": 1e3, "lbf": _LBF, "lb": _LBF, "none": 1.0, "": 1.0}


def _unit_labels(num, den) -> tuple[str, str]:
    """Normalized (ordinate, denominator) unit labels: lower case, no blanks or parentheses, ``²``/``**2`` as
    ``^2``; a force in the ordinate label (``g/N``, ``(m/s^2)/lbf``) moves to the denominator when that is blank."""
    def norm(t):
        t = str(t or "").strip().lower().replace(" ", "").replace("(", "").replace(")", "")
        return t.replace("²", "^2").replace("**2", "^2")
    num, den = norm(num), norm(den)
    for force in ("kn", "lbf", "lb", "n"):
        if num.endswith("/" + force):
            if den in ("", "none"):
                den = force
            if den != force:
                raise ValueError(f"the ordinate unit names the force {force!r} but the denominator unit is {den!r}")
            num = num[: -len(force) - 1]
            break
    return num, den


def _label_unit(label, known) -> str:
    """The unit in an axis label's last (...) or [...] when it is one of ``known`` (``Acceleration (g)`` ->
    ``g``); "" otherwise (a label without a unit, or with another remark in parentheses)."""
    import re

    found = re.findall(r"[\(\[]([^()\[\]]+)[\)\]]", str(label or ""))
    if not found:
        return ""
    unit = found[-1].strip()
    try:
        num, den = _unit_labels(unit, "")
    except ValueError:
        return ""
    return unit if (num in known and num not in ("", "none")) or den not in ("", "none") else ""


class UffError(ValueError):
    """A UFF file cannot be mapped to a run (names the file and the record)."""


def _dir_code(d) -> int:
    d = np.asarray(d, dtype=float)
    k = int(np.argmax(np.abs(d)))
    if abs(abs(d[k]) - 1) < 1e-12 and np.sum(np.abs(d)) - abs(d[k]) < 1e-12:
        return int(np.sign(d[k])) * (k + 1)
    return 0


def _code_dir(code: int) -> tuple[float, float, float]:
    d = [0.0, 0.0, 0.0]
    if 1 <= abs(code) <= 3:
        d[abs(code) - 1] = float(np.sign(code))
    return tuple(d)


#: UFF58 function type codes (the record's ``func_type``) and their names.
FUNCTION_TYPES = {0: "general", 1: "time response", 2: "auto spectrum", 3: "cross spectrum",
                  4: "frequency response function", 5: "transmissibility", 6: "coherence",
                  7: "auto correlation", 8: "cross correlation", 9: "power spectral density",
                  10: "energy spectral density", 11: "probability density function", 12: "spectrum",
                  13: "cumulative frequency distribution", 14: "peaks valley", 15: "stress/cycles",
                  16: "strain/cycles", 17: "orbit", 18: "mode indicator function", 19: "force pattern",
                  20: "partial power", 21: "partial coherence", 22: "eigenvalue", 23: "eigenvector",
                  24: "shock response spectrum", 25: "finite impulse response filter", 26: "multiple coherence",
                  27: "order function"}


def _header_lines(rec: dict) -> list[str]:
    return [
        "%-80s" % rec["id1"][:80],
        "%-80s" % rec["id2"][:80],
        "%-80s" % rec["id3"][:80],
        "%-80s" % rec["id4"][:80],
        "%-80s" % rec["id5"][:80],
        "%5i%10i%5i%10i %10s%10i%4i %10s%10i%4i"
        % (4, 0, 0, 0, rec["rsp_ent_name"][:10], rec["rsp_node"], rec["rsp_dir"], rec["ref_ent_name"][:10],
           rec["ref_node"], rec["ref_dir"]),
        "%10i%10i%10i%13.5e%13.5e%13.5e" % (6, rec["n"], 0, 0.0, 0.0, 0.0),
        "%10i%5i%5i%5i %-20s %-20s" % (18, 0, 0, 0, "Frequency", "Hz"),
        "%10i%5i%5i%5i %-20s %-20s" % (rec["spec"], 0, 0, 0, "Response", rec["unit"]),
        "%10i%5i%5i%5i %-20s %-20s" % (13, 0, 0, 0, "Force", "N"),
        "%10i%5i%5i%5i %-20s %-20s" % (0, 0, 0, 0, "NONE", "NONE"),
    ]


def export_uff(run_or_path, path, *, binary: bool = True) -> int:
    """Write every FRF of a run as UFF58 records; returns the number of records.

    Parameters
    ----------
    run_or_path : Run or path of a run file
    path : str or Path
        Output ``.uff`` file (overwritten).
    binary : bool
        UFF58b (exact, default) or ASCII UFF58 (frequencies to 6 digits).
    """
    run = run_or_path if isinstance(run_or_path, Run) else read_run(run_or_path)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)  # as import-uff and the other writers do
    if run.n_lines < 2:
        raise UffError(f"{run.path}: a UFF58 function needs at least 2 lines, the run has {run.n_lines}")
    order = np.argsort(run.frequency_hz, kind="stable")
    f = run.frequency_hz[order]
    frf = run.frf[order]
    unit = _QTY[run.quantity][1] + "/N"
    recs = []
    for j, dv in enumerate(run.drives):
        for i, s in enumerate(run.sensors):
            recs.append(dict(
                id1=f"frfcal FRF {run.quantity} article={run.article}",
                id2=f"{s.name} / {dv.name}",
                id3=run.created_utc,
                id4="rspdir " + " ".join(repr(float(x)) for x in s.direction),
                id5="refdir " + " ".join(repr(float(x)) for x in dv.direction),
                rsp_ent_name=s.name, rsp_node=int(s.grid), rsp_dir=_dir_code(s.direction),
                ref_ent_name=dv.name, ref_node=int(dv.grid), ref_dir=_dir_code(dv.direction),
                n=f.size, spec=_SPEC[run.quantity], unit=unit, data=frf[:, i, j],
            ))
    if binary:
        with open(path, "wb") as fh:
            for rec in recs:
                data = np.empty(3 * f.size, dtype="<f8")
                data[0::3] = f
                data[1::3] = rec["data"].real
                data[2::3] = rec["data"].imag
                head = "%6i\n%6ib%6i%6i%12i%12i%6i%6i%12i%12i\n" % (-1, 58, 1, 2, 11, data.nbytes, 0, 0, 0, 0)
                fh.write(head.encode("ascii"))
                fh.write(("\n".join(_header_lines(rec)) + "\n").encode("ascii"))
                fh.write(data.tobytes())
                fh.write(("%6i\n" % -1).encode("ascii"))
    else:
        import pyuff

        sets = []
        for rec in recs:
            ds = pyuff.prepare_58(
                binary=0, func_type=4, rsp_node=rec["rsp_node"], rsp_dir=rec["rsp_dir"], ref_node=rec["ref_node"],
                ref_dir=rec["ref_dir"], rsp_ent_name=rec["rsp_ent_name"][:10], ref_ent_name=rec["ref_ent_name"][:10],
                id1=rec["id1"], id2=rec["id2"], id3=rec["id3"], id4=rec["id4"], id5=rec["id5"], ord_data_type=6,
                abscissa_spacing=0, data=rec["data"], x=f, abscissa_spec_data_type=18,
                ordinate_spec_data_type=rec["spec"], orddenom_spec_data_type=13, abscissa_axis_units_lab="Hz",
                ordinate_axis_units_lab=_QTY[run.quantity][1], orddenom_axis_units_lab="N")
            ds["type"] = 58
            sets.append(ds)
        path.unlink(missing_ok=True)
        pyuff.UFF(str(path)).write_sets(sets, mode="overwrite")
    return len(recs)


def _parse_dir(text: str, key: str):
    parts = str(text).split()
    if len(parts) == 4 and parts[0] == key:
        try:
            return tuple(float(x) for x in parts[1:])
        except ValueError:
            return None
    return None


def _entity(name) -> str:
    """A UFF entity name, '' when blank or pyuff's 'NONE' placeholder."""
    name = str(name or "").strip()
    return "" if name.upper() == "NONE" else name


def _point_label(node: int, code: int, direction) -> str:
    """``101+Z`` for an axis code, ``103(0,0.6,0.8)`` for a general direction."""
    if 1 <= abs(code) <= 3:
        return f"{node}{'+-'[code < 0]}{'XYZ'[abs(code) - 1]}"
    return f"{node}(" + ",".join(f"{x:.6g}" for x in direction) + ")"


def _read_records(path: Path, types_wanted=(58,)) -> list[tuple[int, dict]]:
    """(1-based dataset number in the file, dataset) of every record of the wanted dataset types (UFF58)."""
    import pyuff

    try:
        uff = pyuff.UFF(str(path))
        types = list(uff.get_set_types())
        return [(k + 1, uff.read_sets(k)) for k, t in enumerate(types) if int(t) in types_wanted]
    except Exception as exc:  # pyuff raises bare Exceptions on malformed files
        raise UffError(f"{path}: cannot parse as a universal file: {exc}") from None


def _dataset_tags(data: bytes) -> list[int]:
    """Byte offsets of the ``    -1`` lines that open and close the datasets of a universal file, by pyuff's
    own rule (the tag followed by a line end, the end of the file or blanks to column 80)."""
    tags, at = [], -1
    while True:
        at = data.find(b"    -1", at + 1)
        if at == -1:
            return tags
        end = at + 6
        if end == len(data) or data[end] in (10, 13) or (end + 74 < len(data) and data[end:end + 74] == b" " * 74):
            tags.append(at)


def _check_complete(path: Path) -> None:
    """Refuse a universal file that ends inside a dataset (a truncated copy or download).

    pyuff pairs the ``    -1`` delimiters and silently drops an unpaired last one, so a file cut inside a
    record would import as the records before the cut: a smaller run that looks complete (outside trial,
    stop 33: an 11 x 1 run from a 16 x 2 file)."""
    data = path.read_bytes()
    tags = _dataset_tags(data)
    if len(tags) % 2:
        start = tags[-1]
        line = data.count(b"\n", 0, start) + 1
        head = data[start + 6:start + 200].lstrip(b" \r\n").split(b"\n", 1)[0][:6].strip().decode("ascii", "replace")
        raise UffError(f"{path}: the file ends inside dataset {len(tags) // 2 + 1} (type {head or '?'}, opened at "
                       f"line {line}, byte {start}): no closing -1 delimiter line: the file "
                       f"({len(data)} bytes) is truncated or damaged; nothing imported")


def _dataset_listing(path: Path) -> str:
    """What a universal file holds, for an error: "it holds datasets 151 x1, 164 x1" or "it holds no dataset
    pyuff can delimit (N bytes)" (a damaged or empty file, e.g. a binary one written record by record in
    overwrite mode)."""
    import pyuff

    try:
        types = [int(t) for t in pyuff.UFF(str(path)).get_set_types()]
    except Exception:  # pyuff raises bare Exceptions on malformed files
        types = []
    if not types:
        return f"it holds no dataset pyuff can delimit ({path.stat().st_size} bytes)"
    counts = {t: types.count(t) for t in dict.fromkeys(types)}
    return "it holds datasets " + ", ".join(f"{t} x{n}" for t, n in counts.items())


def _file_units_scale(path: Path, units) -> float | None:
    """FRF factor to SI (force factor / length factor) of the file's units dataset 164, None without one.

    Dataset 164 gives the factors that convert the file's units to SI ("divide by the
    factor"): an FRF (length over force) in file units times force / length is SI.
    """
    if not units:
        return None
    got = {(float(u.get("length", 1.0)), float(u.get("force", 1.0))) for _, u in units}
    if len(got) > 1:
        raise UffError(f"{path}: units datasets (164) {_listing(n for n, _ in units)} disagree: "
                       f"(length, force) factors {sorted(got)}")
    ((length, force),) = got
    if not (np.isfinite(length) and np.isfinite(force) and length > 0 and force > 0):
        raise UffError(f"{path}: units dataset (164) {units[0][0]}: length/force factors must be positive, "
                       f"got {length}, {force}")
    return force / length


def _cs_axes_18(path: Path, rec: list[tuple[int, dict]]) -> dict[int, tuple[int, np.ndarray, int]]:
    """Dataset 18 systems: label -> (type, axes in the reference system as columns, reference label)."""
    out = {}
    for n, d in rec:
        for k, lab in enumerate(np.atleast_1d(d.get("cs_num", []))):
            # pyuff: one row per system
            o, xp, xz = (np.atleast_2d(np.asarray(d[key], float))[k] for key in ("ref_o", "x_point", "xz_point"))
            ex = xp - o
            ex = ex / (np.linalg.norm(ex) or 1.0)
            ez = (xz - o) - ((xz - o) @ ex) * ex      # the xz point's part normal to x: the +z side
            if np.linalg.norm(ex) == 0 or np.linalg.norm(ez) < 1e-9 * max(np.linalg.norm(xz - o), 1e-300):
                raise UffError(f"{path}: coordinate system {int(lab)} (dataset {n}, type 18): its origin, x point "
                               "and xz point do not define a system")
            ez = ez / np.linalg.norm(ez)
            out[int(lab)] = (int(np.atleast_1d(d["cs_type"])[k]), np.column_stack([ex, np.cross(ez, ex), ez]),
                             int(np.atleast_1d(d["ref_cs_num"])[k]))
    return out


def _cs_axes_2420(path: Path, rec: list[tuple[int, dict]]) -> dict[int, tuple[int, np.ndarray, int]]:
    """Dataset 2420 systems: label -> (type, axes in global as columns, 0).

    The first three rows of the 2420 transformation matrix are the direction cosines of the local x, y, z
    axes in the global system (row 4 the origin), so the axes as columns are its transpose.
    """
    out = {}
    for n, d in rec:
        for lab, typ, T in zip(d.get("CS_sys_labels", []), d.get("CS_types", []), d.get("CS_matrices", [])):
            R = np.asarray(T, float)[:3, :3].T
            if not np.allclose(R.T @ R, np.eye(3), atol=1e-5):
                raise UffError(f"{path}: coordinate system {int(lab)} (dataset {n}, type 2420): the rotation rows "
                               "of its transformation matrix are not orthonormal")
            out[int(lab)] = (int(typ), R, 0)
    return out


def _displacement_axes(path: Path) -> dict[int, np.ndarray]:
    """Node -> axes (columns, global) of its displacement coordinate system, for nodes whose system is not global.

    The test geometry (node datasets 2411 or 15, coordinate systems 2420 or 18) says in which system each
    node's direction codes are: a skewed accelerometer is a node with a local displacement system, and
    its record's +Y means that system's y axis. Cartesian systems only (a cylindrical or spherical
    displacement system depends on the node's position: refused, naming the node).
    """
    nodes = _read_records(path, (2411, 15))
    if not nodes:
        return {}
    systems = {**_cs_axes_18(path, _read_records(path, (18,))), **_cs_axes_2420(path, _read_records(path, (2420,)))}

    def to_global(lab: int, node: int, seen=()) -> np.ndarray:
        if lab == 0:
            return np.eye(3)
        if lab not in systems:
            raise UffError(f"{path}: node {node} gives displacement coordinate system {lab}, which the file "
                           "does not define (datasets 2420/18): its direction codes cannot be placed")
        typ, R, ref = systems[lab]
        if typ != 0:
            raise UffError(f"{path}: node {node}: displacement coordinate system {lab} is "
                           f"{ {1: 'cylindrical', 2: 'spherical'}.get(typ, f'of type {typ}') }; only cartesian "
                           "systems are supported for direction codes")
        if lab in seen:
            raise UffError(f"{path}: coordinate system {lab} refers to itself (through {list(seen)})")
        return to_global(ref, node, seen + (lab,)) @ R

    out: dict[int, np.ndarray] = {}
    given: dict[int, int] = {}
    for n, d in nodes:
        for node, cs in zip(np.atleast_1d(d.get("node_nums", [])), np.atleast_1d(d.get("disp_cs", []))):
            node, cs = int(node), int(cs)
            if given.setdefault(node, cs) != cs:
                raise UffError(f"{path}: node {node} is given displacement coordinate systems {given[node]} and "
                               f"{cs} (dataset {n})")
            if cs != 0:
                out[node] = to_global(cs, node)
    return out


def _is_binary(path: Path) -> bool:
    """Whether the file's first dataset-58 header says binary (58b)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096).decode("latin-1")
    except OSError:
        return False
    return any(ln.strip().startswith("58b") for ln in head.splitlines())


#: Significant digits of an ASCII UFF58 abscissa (E13.5 in record 12 of uneven data).
ASCII_ABSCISSA_DIGITS = 6


def _spread_printed_lines(f: np.ndarray) -> tuple[np.ndarray, dict]:
    """Distinct lines from an abscissa that printed some of them the same.

    An ASCII UFF58 writes an uneven abscissa as E13.5: 6 significant digits.
    A stepped-sine grid denser than that (a few lines per half-power bandwidth
    of a lightly damped mode) prints neighbouring lines the same; each was a
    measurement at its own frequency, somewhere within half a unit of the last
    printed digit. ``f`` is sorted (stably, so in file order within a group).
    The k lines of a group are spread evenly inside that interval, narrowed to
    half the gap to each distinct neighbour, so the order holds: a shift of at
    most half a unit of the last digit (5e-6 relative), the rounding every
    other line of the file carries too.

    Returns the new abscissa and a summary {"groups", "lines", "max_shift_hz"}.
    """
    f0 = np.asarray(f, dtype=float)
    f = f0.copy()
    same = np.flatnonzero(np.diff(f0) == 0)
    starts = same[np.r_[True, np.diff(same) > 1]] if same.size else same
    groups = lines = 0
    max_shift = 0.0
    for a in starts.tolist():
        b = a + 1
        while b + 1 < f0.size and f0[b + 1] == f0[a]:
            b += 1
        x = f0[a]
        half = 0.5 * 10.0 ** (np.floor(np.log10(x)) - (ASCII_ABSCISSA_DIGITS - 1))
        lo = min(half, 0.5 * (x - f0[a - 1])) if a > 0 else min(half, 0.5 * x)
        hi = min(half, 0.5 * (f0[b + 1] - x)) if b + 1 < f0.size else half
        k = b - a + 1
        f[a:b + 1] = x - lo + (lo + hi) * np.arange(1, k + 1) / (k + 1)
        max_shift = max(max_shift, float(np.max(np.abs(f[a:b + 1] - x))))
        groups += 1
        lines += k
    return f, {"groups": groups, "lines": lines, "max_shift_hz": max_shift}


def _listing(items, limit: int = 6) -> str:
    items = list(items)
    more = f" and {len(items) - limit} more" if len(items) > limit else ""
    return ", ".join(str(x) for x in items[:limit]) + more


def import_uff(path, out, *, article: str | None = None, overwrite: bool = False) -> Run:
    """Convert the FRF records (UFF58, function type 4) of a universal file into a run file.

    Every record is one FRF H[response, reference]. Responses are identified by
    the record's response node and direction (``rsp_node``, ``rsp_dir``; or the
    exact vector in ``id4`` as written by :func:`export_uff`), references by
    ``ref_node``, ``ref_dir`` (``id5``). The run has one output per distinct
    response and one input per distinct reference, in order of first
    appearance, and the records must fill that matrix exactly once.

    Parameters
    ----------
    path : str or Path
        Universal file (ASCII UFF58 or binary 58b); records of other dataset
        types (nodes, trace lines, headers) are ignored.
    out : str or Path
        Run file to write (``.h5``).
    article : str, optional
        Test article; default from frfcal's ID line 1 or the file stem.
    overwrite : bool
        Replace an existing run file.

    Returns
    -------
    Run
        The run file read back: ``frf`` is (n_freq, n_out, n_in) in SI.

    Records of another function type (coherence, spectra, ...) beside the
    FRFs are left out and listed in the run's ``plan["skipped_records"]``
    (function type name and code -> record numbers).

    An ASCII file's abscissa keeps 6 significant digits: lines of a grid
    denser than that print the same and are spread within their last digit
    (:func:`_spread_printed_lines`; summary in ``plan["abscissa_spread"]``).
    In a binary (58b) file the same frequency twice is refused.

    Raises
    ------
    UffError
        Naming the file and the records at fault: no FRF records, records of
        another quantity, unknown or mixed units, a record on
        another abscissa, a direction that is not a translation (+-1..3, or an
        exact vector), a (response, reference) pair given twice or missing, one
        response or reference named differently in two records, a frequency
        repeated in a binary file.

    Notes
    -----
    Channel names: frfcal's own files carry the full names in ID line 2
    (``"<sensor> / <drive>"``) and they are kept. Otherwise a channel is named
    from the record's entity name and its point, ``"acc12 (101+Z)"``, or from
    the point alone when the entity name is blank: ``"n101+Z"`` for responses,
    ``"ref_n1+Z"`` for references. Grid = node; direction code +-1..3 is the
    unit vector +-X, +-Y, +-Z.
    """
    path = Path(path)
    if not path.exists():
        raise UffError(f"{path}: file not found")
    _check_complete(path)
    records = _read_records(path)
    plan = {"source": "uff58", "file": str(path)}
    if not records:
        raise UffError(f"{path}: no UFF58 records; {_dataset_listing(path)}")
    # records without unit labels are in the file's unit system (dataset 164), when it has one
    file_scale = _file_units_scale(path, _read_records(path, (164,)))
    # direction codes of nodes with a local displacement system (the test geometry's 2411/15 + 2420/18)
    node_axes = _displacement_axes(path)

    def rec(n: int, s: dict) -> str:
        return (f"record {n} (response {int(s.get('rsp_node', 0))}/{int(s.get('rsp_dir', 0))}, "
                f"reference {int(s.get('ref_node', 0))}/{int(s.get('ref_dir', 0))})")

    ftypes = {}
    for n, s in records:
        ftypes.setdefault(int(s.get("func_type", 0)), []).append(n)
    if 4 not in ftypes:
        raise UffError(f"{path}: no UFF58 frequency response function records (function type 4); "
                       f"function types found: {sorted(ftypes)}")
    if len(ftypes) > 1:
        # an analyzer's export often holds the coherences, auto- and cross-spectra beside the FRFs: the FRFs
        # are imported, the others are listed in the plan (and by the command) as left out
        plan["skipped_records"] = {f"{FUNCTION_TYPES.get(t, 'function type ' + str(t))} ({t})": ns
                                   for t, ns in sorted(ftypes.items()) if t != 4}
        records = [(n, s) for n, s in records if int(s.get("func_type", 0)) == 4]

    n0, s0 = records[0]
    f = np.asarray(s0["x"], dtype=float)
    own = all(str(s.get("id1", "")).startswith("frfcal FRF") for _, s in records)
    quantity, scale_of = None, {}
    outs: dict[tuple, dict] = {}
    ins: dict[tuple, dict] = {}
    cells: dict[tuple, tuple[int, np.ndarray]] = {}
    for n, s in records:
        x = np.asarray(s["x"], dtype=float)
        if x.shape != f.shape or np.any(x != f):
            raise UffError(f"{path}: {rec(n, s)} has a different frequency axis ({x.size} points, "
                           f"{x.min():.6g}-{x.max():.6g}) from {rec(n0, s0)} ({f.size} points, "
                           f"{f.min():.6g}-{f.max():.6g})")
        if int(s.get("abscissa_spec_data_type", 18)) not in (0, 18):
            raise UffError(f"{path}: {rec(n, s)}: abscissa type {s.get('abscissa_spec_data_type')} is not "
                           "frequency (18)")
        q = _SPEC_INV.get(int(s.get("ordinate_spec_data_type", 12)))
        if q is None:
            raise UffError(f"{path}: {rec(n, s)}: ordinate type {s.get('ordinate_spec_data_type')} is not an "
                           "FRF quantity (12 acceleration, 11 velocity, 8 displacement)")
        if int(s.get("orddenom_spec_data_type", 13)) not in (0, 13):
            raise UffError(f"{path}: {rec(n, s)}: ordinate denominator type {s.get('orddenom_spec_data_type')} "
                           "is not force (13)")
        if quantity not in (None, q):
            raise UffError(f"{path}: {rec(n, s)} is {q}, {rec(n0, s0)} is {quantity}")
        quantity = q
        data = np.asarray(s["data"])
        if not np.iscomplexobj(data):
            raise UffError(f"{path}: {rec(n, s)}: real ordinate data (type {s.get('ord_data_type')}); an FRF "
                           "needs complex data (type 5 or 6)")
        # a blank units label: some writers put the unit in the axis label instead ("Acceleration (g)")
        num_lab, den_lab = (str(s.get(k, "") or "").strip() for k in ("ordinate_axis_units_lab",
                                                                        "orddenom_axis_units_lab"))
        if num_lab.lower() in ("", "none"):
            num_lab = _label_unit(s.get("ordinate_axis_lab"), _SCALE_NUM) or num_lab
        if den_lab.lower() in ("", "none"):
            den_lab = _label_unit(s.get("orddenom_axis_lab"), _SCALE_DEN) or den_lab
        try:
            unit_num, unit_den = _unit_labels(num_lab, den_lab)
        except ValueError as exc:
            raise UffError(f"{path}: {rec(n, s)}: {exc}") from None
        if unit_num not in _SCALE_NUM:
            raise UffError(f"{path}: {rec(n, s)}: unknown ordinate unit {s.get('ordinate_axis_units_lab')!r} "
                           f"(known: {', '.join(u for u in _SCALE_NUM if u not in ('', 'none'))})")
        if unit_den not in _SCALE_DEN:
            raise UffError(f"{path}: {rec(n, s)}: unknown denominator unit {s.get('orddenom_axis_units_lab')!r} "
                           f"(known: N, kN, lbf)")
        if _KIND_NUM.get(unit_num, q) != q:
            raise UffError(f"{path}: {rec(n, s)}: ordinate unit {s.get('ordinate_axis_units_lab')!r} is a "
                           f"unit of {_KIND_NUM[unit_num]} but the ordinate type {s.get('ordinate_spec_data_type')} "
                           f"says {q}")
        scale = _SCALE_NUM[unit_num] / _SCALE_DEN[unit_den]
        label = f"{s.get('ordinate_axis_units_lab')}/{s.get('orddenom_axis_units_lab')}"
        if file_scale is not None and unit_num in ("", "none") and unit_den in ("", "none"):
            scale, label = file_scale, "the units of dataset 164"
        scale_of.setdefault(scale, []).append((n, label))

        keys = []
        for side, table, vec_line, tag in (("rsp", outs, "id4", "rspdir"), ("ref", ins, "id5", "refdir")):
            node, code = int(s[f"{side}_node"]), int(s[f"{side}_dir"])
            vec = _parse_dir(s.get(vec_line, ""), tag)
            if vec is None and not 1 <= abs(code) <= 3:
                raise UffError(f"{path}: {rec(n, s)}: {'response' if side == 'rsp' else 'reference'} direction "
                               f"code {code} is not a translation (+-1..3 = +-X, +-Y, +-Z)")
            if vec is None:
                vec = _code_dir(code)
                if node in node_axes:   # the code is along an axis of the node's own system
                    vec = tuple(float(x) for x in np.round(node_axes[node] @ np.asarray(vec), 12) + 0.0)
            key = (node, vec)
            ent = _entity(s.get(f"{side}_ent_name", ""))
            given = ""
            if own:
                parts = [t.strip() for t in str(s.get("id2", "")).split(" / ")]
                given = parts[0 if side == "rsp" else 1] if len(parts) == 2 else ""
            ch = table.setdefault(key, dict(node=node, code=code, vec=vec, ent=ent, given=given, first=n))
            if ch["ent"] != ent or ch["given"] != given:
                what = "response" if side == "rsp" else "reference"
                raise UffError(f"{path}: {what} {_point_label(node, code, vec)} is named "
                               f"{ch['given'] or ch['ent']!r} in record {ch['first']} and {given or ent!r} in "
                               f"{rec(n, s)}")
            keys.append(key)
        cell = tuple(keys)
        if cell in cells:
            raise UffError(f"{path}: {rec(n, s)} repeats the (response, reference) pair of record "
                           f"{cells[cell][0]}")
        cells[cell] = (n, data.astype(complex) * scale)
    if len(scale_of) > 1:
        raise UffError(f"{path}: mixed units: " + "; ".join(
            f"{v[0][1]} in records {_listing(m for m, _ in v)}" for v in scale_of.values()))

    missing = [(o, i) for o in outs for i in ins if (o, i) not in cells]
    if missing:
        lab = [f"{_point_label(outs[o]['node'], outs[o]['code'], o[1])} / "
               f"{_point_label(ins[i]['node'], ins[i]['code'], i[1])}" for o, i in missing]
        raise UffError(f"{path}: {len(outs)} responses x {len(ins)} references need {len(outs) * len(ins)} FRF "
                       f"records, {len(cells)} given; missing (response / reference): {_listing(lab)}")

    def name_of(ch: dict, prefix: str) -> str:
        point = _point_label(ch["node"], ch["code"], ch["vec"])
        if ch["given"]:
            return ch["given"]
        return f"{ch['ent']} ({point})" if ch["ent"] else f"{prefix}{point}"

    out_names = [name_of(c, "n") for c in outs.values()]
    in_names = [name_of(c, "ref_n") for c in ins.values()]
    seen: dict[str, int] = {}
    unique = []
    for nm in out_names + in_names:  # channel names are unique in a run
        seen[nm] = seen.get(nm, 0) + 1
        unique.append(nm if seen[nm] == 1 else f"{nm} #{seen[nm]}")
    out_names, in_names = unique[:len(outs)], unique[len(outs):]

    qname, unit = _QTY[quantity]
    sensors = [ChannelSpec(name=nm, role="response", quantity=qname, unit=unit, grid=c["node"], direction=c["vec"])
               for nm, c in zip(out_names, outs.values())]
    drives = [ChannelSpec(name=nm, role="force", quantity="force", unit="N", grid=c["node"], direction=c["vec"])
              for nm, c in zip(in_names, ins.values())]
    oi = {k: i for i, k in enumerate(outs)}
    ii = {k: j for j, k in enumerate(ins)}
    frf = np.empty((f.size, len(sensors), len(drives)), dtype=complex)
    for (ko, ki), (_, data) in cells.items():
        frf[:, oi[ko], ii[ki]] = data
    if article is None:
        id1 = str(s0.get("id1", ""))
        article = id1.split("article=", 1)[1].strip() if "article=" in id1 else path.stem
    bad = ~np.isfinite(f) | (f < 0)
    if bad.any():
        raise UffError(f"{path}: the abscissa has {int(bad.sum())} negative or non-finite frequencies "
                       f"(first: {f[bad][0]!r} Hz)")
    dc = f == 0
    if dc.any():
        # an FFT analyzer's records start at the DC line (0 Hz, often an exact 0): no FRF line, a run holds
        # positive frequencies only; the plan records what was left out
        plan["dropped_hz"] = f[dc].tolist()
        f, frf = f[~dc], frf[~dc]
        if f.size == 0:
            raise UffError(f"{path}: no line above 0 Hz")
    if np.any(np.diff(f) < 0):  # distinct lines out of order: a run holds them ascending
        order = np.argsort(f, kind="stable")
        f, frf = f[order], frf[order]
    step = np.diff(f)
    if np.any(step == 0):
        if _is_binary(path):  # doubles: the same frequency twice is a repeated line, not a rounding
            k = int(np.flatnonzero(step == 0)[0])
            raise UffError(f"{path}: line {f[k]!r} Hz appears {int(np.sum(f == f[k]))} times in the abscissa "
                           f"({int(np.sum(step == 0))} repeated in all)")
        f, spread = _spread_printed_lines(f)
        plan["abscissa_spread"] = spread
    w = create_run(out, article=article, sensors=sensors, drives=drives, quantity=quantity,
                   plan=plan, hardware={"source": "imported"}, overwrite=overwrite)
    nan_q = LineQuality(force_n=np.full(len(drives), np.nan), std_error=np.full((len(sensors), len(drives)), np.nan),
                        thd=np.full(len(sensors) + len(drives), np.nan))
    try:
        w.append_lines(f, frf, nan_q)
    except RunFileError:
        w.close("aborted")
        raise
    w.close("completed")
    return read_run(out)


__all__ = ["UffError", "export_uff", "import_uff"]
