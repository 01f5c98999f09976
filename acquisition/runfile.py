"""HDF5 run files: one stepped-sine run, written line by line, never losing a completed line.

This is the public module other layers (calibration) import. Schema: see
``docs/runfile.md``. The writer creates the whole file structure up front under
a temporary name, switches HDF5 to SWMR mode and renames it into place, so the
file at ``path`` is always readable; every line is appended with a flush of each
dataset followed by a flush of the ``lines/count`` dataset, which is what a
reader trusts. A process killed at any moment therefore leaves every completed
line readable, and :func:`resume_run` continues the run.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Sequence

import h5py
import numpy as np

from acquisition._driver import ChannelSpec
from labdata import FRF_QUANTITIES

FORMAT = "frfcal-run"
VERSION = 1
QUANTITIES = FRF_QUANTITIES
STATUSES = ("running", "completed", "aborted")

#: Line flag bits (``Run.flags``); a line is *valid* when no bit is set.
FLAG_OVERLOAD = 1
FLAG_FORCE = 2  # force amplitude outside tolerance
FLAG_NOT_SETTLED = 4  # settle detector timed out
FLAG_NONLINEAR = 8  # linearity check failed
FLAG_THD = 16  # total harmonic distortion above limit
FLAG_NOISY = 32  # standard error above limit
FLAG_NAMES = {
    FLAG_OVERLOAD: "overload",
    FLAG_FORCE: "force",
    FLAG_NOT_SETTLED: "not_settled",
    FLAG_NONLINEAR: "nonlinear",
    FLAG_THD: "thd",
    FLAG_NOISY: "noisy",
}

_CHANNEL_STR = ("name", "role", "quantity", "unit", "physical", "serial")
_CHANNEL_FLOAT = ("sensitivity", "range_v", "iepe_current_a")


class RunFileError(ValueError):
    """A run file is missing, unreadable or inconsistent; the message names the file and item."""


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def _software_version() -> str:
    try:
        from importlib.metadata import version

        return f"frfcal {version('frfcal')}"
    except Exception:  # package metadata absent (source checkout)
        return "frfcal unknown"


@dataclass(frozen=True)
class LineQuality:
    """Quality figures of one measured line.

    Parameters
    ----------
    force_n : (n_in,) float
        Achieved force amplitude (peak N) at each drive point.
    std_error : (n_out, n_in) float
        Standard error of the FRF estimate (same unit as the FRF), from block scatter.
    thd : (n_channels,) float
        Total harmonic distortion of every channel, sensors then drives (fraction).
    settle_metric : float
        Estimated relative FRF error left by the transient when measuring started.
    overload : bool
        Any channel overloaded (clipped) during the line.
    flags : int
        Bitwise OR of the ``FLAG_*`` constants.
    drive_v : float
        Drive amplitude (peak V) at the end of the line.
    time_s : float
        Driver clock when the line was finished.
    settle_time_s : float
        Time spent settling (driver clock), s.
    n_blocks : int
        Blocks averaged for the estimate.
    linearity : float
        Relative FRF change between two force levels (NaN if not checked).
    """

    force_n: np.ndarray
    std_error: np.ndarray
    thd: np.ndarray
    settle_metric: float = 0.0
    overload: bool = False
    flags: int = 0
    drive_v: float = float("nan")
    time_s: float = float("nan")
    settle_time_s: float = float("nan")
    n_blocks: int = 0
    linearity: float = float("nan")


@dataclass(frozen=True)
class Run:
    """A run read back from a file (immutable).

    ``frf`` is ``(n_f, n_out, n_in)`` complex SI of ``quantity``; the quality arrays
    are per line; ``valid`` marks lines without flags. Lines are sorted by
    ascending frequency (``time_s`` gives the measurement order).
    """

    path: str
    article: str
    sensors: tuple[ChannelSpec, ...]
    drives: tuple[ChannelSpec, ...]
    quantity: str
    frequency_hz: np.ndarray
    frf: np.ndarray
    force_n: np.ndarray
    std_error: np.ndarray
    thd: np.ndarray
    settle_metric: np.ndarray
    overload: np.ndarray
    flags: np.ndarray
    drive_v: np.ndarray
    time_s: np.ndarray
    settle_time_s: np.ndarray
    n_blocks: np.ndarray
    linearity: np.ndarray
    status: str
    plan: dict
    hardware: dict
    software_version: str
    created_utc: str
    updated_utc: str
    analyses: tuple[str, ...] = ()

    @property
    def valid(self) -> np.ndarray:
        """``(n_f,)`` bool: lines with no quality flag set."""
        return self.flags == 0

    @property
    def n_lines(self) -> int:
        return int(self.frequency_hz.size)


# --------------------------------------------------------------------- layout
def _line_specs(n_out: int, n_in: int) -> dict[str, tuple[tuple[int, ...], str]]:
    n_ch = n_out + n_in
    return {
        "frequency_hz": ((), "f8"),
        "frf": ((n_out, n_in), "c16"),
        "std_error": ((n_out, n_in), "f8"),
        "force_n": ((n_in,), "f8"),
        "thd": ((n_ch,), "f8"),
        "settle_metric": ((), "f8"),
        "overload": ((), "u1"),
        "flags": ((), "u4"),
        "drive_v": ((), "f8"),
        "time_s": ((), "f8"),
        "settle_time_s": ((), "f8"),
        "n_blocks": ((), "i4"),
        "linearity": ((), "f8"),
    }


def _write_channels(group: h5py.Group, channels: Sequence[ChannelSpec]) -> None:
    str_dt = h5py.string_dtype("utf-8")
    for key in _CHANNEL_STR:
        group.create_dataset(key, data=np.array([getattr(c, key) for c in channels], dtype=object), dtype=str_dt)
    for key in _CHANNEL_FLOAT:
        vals = [np.nan if getattr(c, key) is None else float(getattr(c, key)) for c in channels]
        group.create_dataset(key, data=np.array(vals, dtype=float))
    group.create_dataset("grid", data=np.array([int(c.grid) for c in channels], dtype=np.int64))
    group.create_dataset(
        "direction", data=np.array([tuple(c.direction) for c in channels], dtype=float).reshape(len(channels), 3)
    )


def _read_channels(path: str, group: h5py.Group) -> tuple[ChannelSpec, ...]:
    data = {}
    for key in _CHANNEL_STR + _CHANNEL_FLOAT + ("grid", "direction"):
        if key not in group:
            raise RunFileError(f"{path}: dataset '{group.name}/{key}' is missing")
        data[key] = group[key][()]
    n = len(data["name"])
    for key, arr in data.items():
        if len(arr) != n:
            raise RunFileError(f"{path}: '{group.name}/{key}' has {len(arr)} entries, '{group.name}/name' has {n}")
    if data["direction"].shape != (n, 3):
        raise RunFileError(f"{path}: '{group.name}/direction' must be ({n}, 3), got {data['direction'].shape}")
    out = []
    for k in range(n):
        s = {key: (data[key][k].decode() if isinstance(data[key][k], bytes) else str(data[key][k])) for key in _CHANNEL_STR}
        iepe = float(data["iepe_current_a"][k])
        d = data["direction"][k]
        if np.any(d) and abs(np.linalg.norm(d) - 1) > 1e-6:
            raise RunFileError(f"{path}: '{group.name}/direction' of channel {s['name']!r} is not a unit vector: {d}")
        out.append(
            ChannelSpec(
                name=s["name"],
                role=s["role"],
                quantity=s["quantity"],
                unit=s["unit"],
                sensitivity=float(data["sensitivity"][k]),
                physical=s["physical"],
                range_v=float(data["range_v"][k]),
                grid=int(data["grid"][k]),
                direction=tuple(float(x) for x in d),
                serial=s["serial"],
                iepe_current_a=None if np.isnan(iepe) else iepe,
            )
        )
    return tuple(out)


def _check_channels(channels: Sequence[ChannelSpec], what: str) -> None:
    names = [c.name for c in channels]
    if len(set(names)) != len(names):
        raise RunFileError(f"{what}: channel names are not unique: {names}")
    for c in channels:
        if not isinstance(c, ChannelSpec):
            raise RunFileError(f"{what}: expected ChannelSpec, got {type(c).__name__}")


# --------------------------------------------------------------------- writer
class RunWriter:
    """Appends lines to a run file created by :func:`create_run` or reopened by :func:`resume_run`.

    Use as a context manager: leaving the block by an exception closes the run
    as ``"aborted"``; call :meth:`close` with ``"completed"`` at a normal end.
    """

    def __init__(self, path: Path, h5: h5py.File, n_out: int, n_in: int):
        self.path = Path(path)
        self._h5 = h5
        self.n_out = n_out
        self.n_in = n_in
        self._specs = _line_specs(n_out, n_in)
        self._count = int(h5["lines/count"][0])
        self.closed = False

    @property
    def n_lines(self) -> int:
        """Number of lines committed so far."""
        return self._count

    @property
    def frequency_hz_done(self) -> np.ndarray:
        """Frequencies (Hz) of the committed lines, in measurement order."""
        return np.array(self._h5["lines/frequency_hz"][: self._count])

    def append_line(self, frequency_hz: float, frf: np.ndarray, quality: LineQuality) -> None:
        """Append one line and flush it to disk (it survives a kill from this point on).

        Parameters
        ----------
        frequency_hz : float
            Actual line frequency, Hz.
        frf : (n_out, n_in) complex
            FRF of the run's quantity, SI.
        quality : LineQuality
        """
        frf = np.asarray(frf, dtype=complex)
        if frf.shape != (self.n_out, self.n_in):
            raise RunFileError(f"{self.path}: frf line must be {(self.n_out, self.n_in)}, got {frf.shape}")
        self.append_lines(np.array([frequency_hz], dtype=float), frf[None], [quality])

    def append_lines(self, frequency_hz, frf, quality) -> None:
        """Append a block of lines in one write and flush them (a kill leaves all or none of them).

        The bulk form of :meth:`append_line` for data that arrive whole (UFF58
        import, synthesized data): each dataset is resized and written once, then
        ``/lines/count`` covers the block. Writing 1,561 lines of an 18 x 2 run
        takes a fraction of a second instead of ~10 s line by line.

        Parameters
        ----------
        frequency_hz : (n,) float
            Actual line frequencies, Hz.
        frf : (n, n_out, n_in) complex
            FRF of the run's quantity, SI.
        quality : LineQuality or sequence of n LineQuality
            One quality shared by every line, or one per line.
        """
        if self.closed:
            raise RunFileError(f"{self.path}: run is closed; resume it to append lines")
        f = np.asarray(frequency_hz, dtype=float).reshape(-1)
        n = f.size
        frf = np.asarray(frf, dtype=complex)
        if frf.shape != (n, self.n_out, self.n_in):
            raise RunFileError(f"{self.path}: frf block must be {(n, self.n_out, self.n_in)}, got {frf.shape}")
        bad = ~np.isfinite(f) | (f <= 0)
        if bad.any():
            raise RunFileError(f"{self.path}: line frequency must be positive and finite, got {f[bad][0]}")
        if n == 0:
            return
        qs = [quality] * n if isinstance(quality, LineQuality) else list(quality)
        if len(qs) != n:
            raise RunFileError(f"{self.path}: {len(qs)} line qualities for {n} lines")
        per_line = {
            "std_error": lambda q: q.std_error, "force_n": lambda q: q.force_n, "thd": lambda q: q.thd,
            "settle_metric": lambda q: q.settle_metric, "overload": lambda q: bool(q.overload),
            "flags": lambda q: int(q.flags), "drive_v": lambda q: q.drive_v, "time_s": lambda q: q.time_s,
            "settle_time_s": lambda q: q.settle_time_s, "n_blocks": lambda q: int(q.n_blocks),
            "linearity": lambda q: q.linearity,
        }
        values = {"frequency_hz": f, "frf": frf}
        for name, get in per_line.items():
            shape = self._specs[name][0]
            col = []
            for q in qs:
                arr = np.asarray(get(q))
                if arr.shape != shape:
                    raise RunFileError(f"{self.path}: quality field '{name}' must have shape {shape}, got {arr.shape}")
                col.append(arr)
            values[name] = np.stack(col)
        k = self._count
        for name in self._specs:
            ds = self._h5["lines"][name]
            if ds.shape[0] < k + n:
                ds.resize(k + n, axis=0)
            ds[k:k + n] = values[name]
            ds.flush()
        self._set_updated()
        cnt = self._h5["lines/count"]
        cnt[0] = k + n
        cnt.flush()
        self._count = k + n

    def _set_updated(self) -> None:
        ds = self._h5["updated_utc"]
        ds[0] = _now().encode()
        ds.flush()

    def close(self, status: str = "completed") -> None:
        """Close the file with the final status (``"completed"`` or ``"aborted"``). Idempotent."""
        if status not in ("completed", "aborted"):
            raise RunFileError(f"{self.path}: final status must be 'completed' or 'aborted', got {status!r}")
        if self.closed:
            return
        ds = self._h5["status"]
        ds[0] = status.encode()
        ds.flush()
        self._set_updated()
        self._h5.close()
        self.closed = True
        # Reopen outside SWMR so that the root attribute agrees (convenience for other tools).
        with h5py.File(self.path, "r+") as h5:
            h5.attrs["status"] = status

    def __enter__(self) -> "RunWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close("aborted" if exc_type is not None else "completed")


def create_run(
    path,
    *,
    article: str,
    sensors: Sequence[ChannelSpec],
    drives: Sequence[ChannelSpec],
    quantity: str = "accelerance",
    plan: dict | None = None,
    hardware: dict | None = None,
    overwrite: bool = False,
) -> RunWriter:
    """Create a run file (status ``"running"``) and return a writer.

    Parameters
    ----------
    path : str or Path
        Target ``.h5`` file; refused if it exists unless ``overwrite``.
    article : str
        Test article name (e.g. serial number of the piece).
    sensors, drives : sequences of ChannelSpec
        FRF outputs (response sensors) and inputs (force sensors at the drive points).
    quantity : {"accelerance", "mobility", "receptance"}
    plan, hardware : dict
        JSON-serializable sweep plan and hardware configuration, stored verbatim.
    """
    path = Path(path)
    if quantity not in QUANTITIES:
        raise RunFileError(f"{path}: quantity must be one of {QUANTITIES}, got {quantity!r}")
    sensors, drives = tuple(sensors), tuple(drives)
    if not sensors or not drives:
        raise RunFileError(f"{path}: a run needs at least one sensor and one drive")
    _check_channels(sensors + drives, str(path))
    if path.exists() and not overwrite:
        raise RunFileError(f"{path}: file exists (resume it, or pass overwrite=True)")
    try:
        plan_json = json.dumps(plan or {})
        hw_json = json.dumps(hardware or {})
    except TypeError as exc:
        raise RunFileError(f"{path}: plan/hardware are not JSON-serializable: {exc}") from None
    tmp = path.with_name(path.name + ".creating")
    h5 = h5py.File(tmp, "w", libver="latest")
    try:
        h5.attrs["format"] = FORMAT
        h5.attrs["version"] = VERSION
        h5.attrs["article"] = article
        h5.attrs["quantity"] = quantity
        h5.attrs["software_version"] = _software_version()
        h5.attrs["created_utc"] = _now()
        h5.attrs["plan_json"] = plan_json
        h5.attrs["hardware_json"] = hw_json
        h5.attrs["status"] = "running"
        for name, value in (("status", "running"), ("updated_utc", _now())):
            ds = h5.create_dataset(name, shape=(1,), maxshape=(1,), chunks=(1,), dtype="S32")
            ds[0] = value.encode()
        _write_channels(h5.create_group("sensors"), sensors)
        _write_channels(h5.create_group("drives"), drives)
        lines = h5.create_group("lines")
        cnt = lines.create_dataset("count", shape=(1,), maxshape=(1,), chunks=(1,), dtype="i8")
        cnt[0] = 0
        for name, (shape, dt) in _line_specs(len(sensors), len(drives)).items():
            lines.create_dataset(name, shape=(0,) + shape, maxshape=(None,) + shape, chunks=(64,) + shape, dtype=dt)
        h5.create_group("analysis")
        h5.flush()
        h5.swmr_mode = True
    except BaseException:
        h5.close()
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, path)
    return RunWriter(path, h5, len(sensors), len(drives))


def resume_run(path) -> RunWriter:
    """Reopen an interrupted (or aborted) run for appending; status goes back to ``"running"``.

    The committed lines are copied into a fresh file that atomically replaces
    the old one (a killed SWMR writer leaves HDF5 consistency flags that forbid
    reopening it for writing); rows beyond ``lines/count`` are dropped.
    Stored analyses are kept. ``writer.frequency_hz_done`` lists the lines done.
    """
    path = Path(path)
    run = read_run(path)
    analyses = {name: read_analysis(path, name) for name in run.analyses}
    tmp = path.with_name(path.name + ".resuming")
    writer = create_run(
        tmp,
        article=run.article,
        sensors=run.sensors,
        drives=run.drives,
        quantity=run.quantity,
        plan=run.plan,
        hardware=run.hardware,
        overwrite=True,
    )
    h5 = writer._h5
    h5.attrs["created_utc"] = run.created_utc
    for k in range(run.n_lines):
        writer.append_line(
            run.frequency_hz[k],
            run.frf[k],
            LineQuality(
                force_n=run.force_n[k],
                std_error=run.std_error[k],
                thd=run.thd[k],
                settle_metric=run.settle_metric[k],
                overload=bool(run.overload[k]),
                flags=int(run.flags[k]),
                drive_v=run.drive_v[k],
                time_s=run.time_s[k],
                settle_time_s=run.settle_time_s[k],
                n_blocks=int(run.n_blocks[k]),
                linearity=run.linearity[k],
            ),
        )
    h5.close()
    if analyses:
        with h5py.File(tmp, "r+") as f:
            for name, (arrays, attrs) in analyses.items():
                _store_analysis(f, name, arrays, attrs)
    os.replace(tmp, path)
    h5 = h5py.File(path, "r+", libver="latest")
    h5.swmr_mode = True
    return RunWriter(path, h5, len(run.sensors), len(run.drives))


# --------------------------------------------------------------------- reader
def _open_read(path: Path) -> h5py.File:
    if not path.exists():
        raise RunFileError(f"{path}: run file not found")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        if "already open for write" in str(exc) or "consistency flags" in str(exc):
            try:
                return h5py.File(path, "r", swmr=True)
            except OSError as exc2:
                raise RunFileError(f"{path}: cannot open run file: {exc2}") from None
        raise RunFileError(f"{path}: not a readable HDF5 run file: {exc}") from None


def _attr(path: Path, h5: h5py.File, name: str) -> str:
    if name not in h5.attrs:
        raise RunFileError(f"{path}: root attribute '{name}' is missing")
    v = h5.attrs[name]
    return v.decode() if isinstance(v, bytes) else str(v)


def read_run(path) -> Run:
    """Read and validate a run file; only committed lines are returned.

    Raises
    ------
    RunFileError
        Naming the file and the dataset or attribute at fault.
    """
    path = Path(path)
    h5 = _open_read(path)
    try:
        fmt = _attr(path, h5, "format")
        if fmt != FORMAT:
            raise RunFileError(f"{path}: attribute 'format' is {fmt!r}, expected {FORMAT!r}")
        version = int(h5.attrs["version"]) if "version" in h5.attrs else None
        if version != VERSION:
            raise RunFileError(f"{path}: attribute 'version' is {version}, this reader knows {VERSION}")
        quantity = _attr(path, h5, "quantity")
        if quantity not in QUANTITIES:
            raise RunFileError(f"{path}: attribute 'quantity' is {quantity!r}, expected one of {QUANTITIES}")
        for group in ("sensors", "drives", "lines"):
            if group not in h5:
                raise RunFileError(f"{path}: group '/{group}' is missing")
        sensors = _read_channels(str(path), h5["sensors"])
        drives = _read_channels(str(path), h5["drives"])
        n_out, n_in = len(sensors), len(drives)
        if "status" not in h5:
            raise RunFileError(f"{path}: dataset '/status' is missing")
        status = h5["status"][0].decode()
        if status not in STATUSES:
            raise RunFileError(f"{path}: dataset '/status' holds {status!r}, expected one of {STATUSES}")
        if "count" not in h5["lines"]:
            raise RunFileError(f"{path}: dataset '/lines/count' is missing")
        n = int(h5["lines/count"][0])
        arrays = {}
        for name, (shape, _) in _line_specs(n_out, n_in).items():
            if name not in h5["lines"]:
                raise RunFileError(f"{path}: dataset '/lines/{name}' is missing")
            ds = h5["lines"][name]
            if ds.shape[1:] != shape:
                raise RunFileError(f"{path}: dataset '/lines/{name}' has shape {ds.shape}, expected (n,)+{shape}")
            if ds.shape[0] < n:
                raise RunFileError(f"{path}: dataset '/lines/{name}' holds {ds.shape[0]} lines, count says {n}")
            arrays[name] = np.array(ds[:n])
        f = arrays["frequency_hz"]
        if n and (not np.all(np.isfinite(f)) or np.any(f <= 0)):
            raise RunFileError(f"{path}: dataset '/lines/frequency_hz' holds non-positive or non-finite values")
        # lines are stored in measurement order (refinement steps back); readers get ascending frequency
        order = np.argsort(f, kind="stable")
        arrays = {k: v[order] for k, v in arrays.items()}
        f = arrays["frequency_hz"]
        try:
            plan = json.loads(_attr(path, h5, "plan_json"))
            hardware = json.loads(_attr(path, h5, "hardware_json"))
        except json.JSONDecodeError as exc:
            raise RunFileError(f"{path}: attribute 'plan_json'/'hardware_json' is not valid JSON: {exc}") from None
        analyses = tuple(sorted(h5["analysis"].keys())) if "analysis" in h5 else ()
        return Run(
            path=str(path),
            article=_attr(path, h5, "article"),
            sensors=sensors,
            drives=drives,
            quantity=quantity,
            frequency_hz=f,
            frf=arrays["frf"],
            force_n=arrays["force_n"],
            std_error=arrays["std_error"],
            thd=arrays["thd"],
            settle_metric=arrays["settle_metric"],
            overload=arrays["overload"].astype(bool),
            flags=arrays["flags"].astype(np.int64),
            drive_v=arrays["drive_v"],
            time_s=arrays["time_s"],
            settle_time_s=arrays["settle_time_s"],
            n_blocks=arrays["n_blocks"],
            linearity=arrays["linearity"],
            status=status,
            plan=plan,
            hardware=hardware,
            software_version=_attr(path, h5, "software_version"),
            created_utc=_attr(path, h5, "created_utc"),
            updated_utc=h5["updated_utc"][0].decode() if "updated_utc" in h5 else "",
            analyses=analyses,
        )
    finally:
        h5.close()


# ------------------------------------------------------------------- analyses
def _store_analysis(h5: h5py.File, name: str, arrays: dict, attrs: dict) -> None:
    group = h5.require_group("analysis")
    if name in group:
        del group[name]
    g = group.create_group(name)
    for key, value in arrays.items():
        g.create_dataset(key, data=np.asarray(value))
    for key, value in attrs.items():
        g.attrs[key] = value if isinstance(value, (int, float, str, np.ndarray, np.number)) else json.dumps(value)


def write_analysis(path, name: str, arrays: dict, attrs: dict | None = None) -> None:
    """Store derived results (e.g. identified modes) in ``/analysis/<name>`` of a closed run file.

    Parameters
    ----------
    arrays : dict[str, ndarray]
        Datasets to store (replacing an analysis of the same name).
    attrs : dict
        Scalars/strings stored as attributes; other values are stored as JSON strings.
    """
    path = Path(path)
    if not name or "/" in name:
        raise RunFileError(f"{path}: analysis name must be a non-empty string without '/', got {name!r}")
    read_run(path)  # validates
    try:
        h5 = h5py.File(path, "r+")
    except OSError as exc:
        raise RunFileError(
            f"{path}: cannot open for writing the analysis {name!r} (a killed writer may have left it open; "
            f"resume or close the run first): {exc}"
        ) from None
    with h5:
        _store_analysis(h5, name, arrays, attrs or {})


def read_analysis(path, name: str) -> tuple[dict[str, np.ndarray], dict]:
    """Read ``/analysis/<name>``: ``(arrays, attrs)``."""
    path = Path(path)
    h5 = _open_read(path)
    with h5:
        key = f"analysis/{name}"
        if key not in h5:
            raise RunFileError(f"{path}: analysis '{name}' not found (have: {sorted(h5.get('analysis', {}).keys())})")
        g = h5[key]
        arrays = {k: np.array(g[k][()]) for k in g.keys()}
        attrs = {}
        for k, v in g.attrs.items():
            attrs[k] = v.decode() if isinstance(v, bytes) else (v.item() if isinstance(v, np.generic) else v)
        return arrays, attrs


__all__ = [
    "FLAG_FORCE",
    "FLAG_NAMES",
    "FLAG_NOISY",
    "FLAG_NONLINEAR",
    "FLAG_NOT_SETTLED",
    "FLAG_OVERLOAD",
    "FLAG_THD",
    "LineQuality",
    "Run",
    "RunFileError",
    "RunWriter",
    "create_run",
    "read_analysis",
    "read_run",
    "resume_run",
    "write_analysis",
]
