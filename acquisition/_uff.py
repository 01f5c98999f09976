"""UFF58 (universal file, function at nodal DOF) import and export of FRFs.

Mapping: a sensor or drive is an FE grid id plus a unit direction vector. In
UFF58 that is a node and a direction code (+-1..3 = +-X, +-Y, +-Z). Directions
along an axis map to the code; other directions get code 0 and the exact vector
travels in the ID lines (``id4`` response, ``id5`` reference), which this
reader also understands. Channel names travel in ``id2`` as ``"<out> / <in>"``.

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

_SPEC = {"accelerance": 12, "mobility": 11, "receptance": 8}
_SPEC_INV = {v: k for k, v in _SPEC.items()}
_QTY = {"accelerance": ("acceleration", "m/s^2"), "mobility": ("velocity", "m/s"), "receptance": ("displacement", "m")}
_SCALE_NUM = {"m/s^2": 1.0, "m/s2": 1.0, "g": 9.80665, "mm/s^2": 1e-3, "mm/s2": 1e-3, "m/s": 1.0, "mm/s": 1e-3,
              "m": 1.0, "mm": 1e-3, "none": 1.0, "": 1.0}
_SCALE_DEN = {"n": 1.0, "kn": 1e3, "none": 1.0, "": 1.0}


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


def import_uff(path, out, *, article: str | None = None, overwrite: bool = False) -> Run:
    """Convert the FRF records (UFF58, function type 4) of a universal file into a run file.

    All records must share one abscissa; the outputs and inputs are the distinct
    (node, direction) pairs (or channel names written by :func:`export_uff`).
    Returns the run read back.
    """
    import pyuff

    path = Path(path)
    if not path.exists():
        raise UffError(f"{path}: file not found")
    try:
        uff = pyuff.UFF(str(path))
        types = list(uff.get_set_types())
        sets = [uff.read_sets(k) for k, t in enumerate(types) if int(t) == 58]
    except Exception as exc:  # pyuff raises bare Exceptions on malformed files
        raise UffError(f"{path}: cannot parse as a universal file: {exc}") from None
    sets = [s for s in sets if int(s.get("func_type", 0)) == 4]
    if not sets:
        raise UffError(f"{path}: no UFF58 frequency response function records (function type 4)")
    f = np.asarray(sets[0]["x"], dtype=float)
    outs, ins, quantity = {}, {}, None
    entries = []
    for k, s in enumerate(sets):
        x = np.asarray(s["x"], dtype=float)
        if x.shape != f.shape or np.any(x != f):
            raise UffError(f"{path}: record {k} has a different frequency axis from record 0")
        q = _SPEC_INV.get(int(s.get("ordinate_spec_data_type", 12)))
        if q is None:
            raise UffError(f"{path}: record {k}: ordinate type {s.get('ordinate_spec_data_type')} is not an FRF quantity")
        if quantity not in (None, q):
            raise UffError(f"{path}: record {k} is {q}, earlier records are {quantity}")
        quantity = q
        unit_num = str(s.get("ordinate_axis_units_lab", "")).strip().lower().split("/n")[0]
        unit_den = str(s.get("orddenom_axis_units_lab", "")).strip().lower()
        if unit_num not in _SCALE_NUM:
            raise UffError(f"{path}: record {k}: unknown ordinate unit {s.get('ordinate_axis_units_lab')!r}")
        if unit_den not in _SCALE_DEN:
            raise UffError(f"{path}: record {k}: unknown denominator unit {s.get('orddenom_axis_units_lab')!r}")
        scale = _SCALE_NUM[unit_num] / _SCALE_DEN[unit_den]
        names = [t.strip() for t in str(s.get("id2", "")).split(" / ")]
        rd = _parse_dir(s.get("id4", ""), "rspdir")
        fd = _parse_dir(s.get("id5", ""), "refdir")
        if (rd is None and not 1 <= abs(int(s["rsp_dir"])) <= 3) or (fd is None and not 1 <= abs(int(s["ref_dir"])) <= 3):
            raise UffError(f"{path}: record {k}: direction code {s['rsp_dir']}/{s['ref_dir']} is not a translation")
        rd = rd if rd is not None else _code_dir(int(s["rsp_dir"]))
        fd = fd if fd is not None else _code_dir(int(s["ref_dir"]))
        axis = "XYZ"
        rname = names[0] if len(names) == 2 and names[0] else f"n{int(s['rsp_node'])}{'+-'[int(s['rsp_dir']) < 0]}{axis[abs(int(s['rsp_dir'])) - 1]}"
        fname = names[1] if len(names) == 2 and names[1] else f"ref_n{int(s['ref_node'])}{'+-'[int(s['ref_dir']) < 0]}{axis[abs(int(s['ref_dir'])) - 1]}"
        outs.setdefault(rname, (int(s["rsp_node"]), rd))
        ins.setdefault(fname, (int(s["ref_node"]), fd))
        entries.append((rname, fname, np.asarray(s["data"], dtype=complex) * scale))
    qname, unit = _QTY[quantity]
    sensors = [ChannelSpec(name=n, role="response", quantity=qname, unit=unit, grid=g, direction=d)
               for n, (g, d) in outs.items()]
    drives = [ChannelSpec(name=n, role="force", quantity="force", unit="N", grid=g, direction=d)
              for n, (g, d) in ins.items()]
    frf = np.full((f.size, len(sensors), len(drives)), np.nan + 0j)
    oi = {n: i for i, n in enumerate(outs)}
    ii = {n: j for j, n in enumerate(ins)}
    for rname, fname, data in entries:
        frf[:, oi[rname], ii[fname]] = data
    if np.isnan(frf).any():
        raise UffError(f"{path}: the records do not cover every (response, reference) pair")
    if article is None:
        id1 = str(sets[0].get("id1", ""))
        article = id1.split("article=", 1)[1].strip() if "article=" in id1 else path.stem
    w = create_run(out, article=article, sensors=sensors, drives=drives, quantity=quantity,
                   plan={"source": "uff58", "file": str(path)}, hardware={"source": "imported"}, overwrite=overwrite)
    nan_q = LineQuality(force_n=np.full(len(drives), np.nan), std_error=np.full((len(sensors), len(drives)), np.nan),
                        thd=np.full(len(sensors) + len(drives), np.nan))
    try:
        for k in range(f.size):
            w.append_line(f[k], frf[k], nan_q)
    except RunFileError:
        w.close("aborted")
        raise
    w.close("completed")
    return read_run(out)


__all__ = ["UffError", "export_uff", "import_uff"]
