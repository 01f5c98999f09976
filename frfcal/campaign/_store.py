"""Stage results on disk: one JSON file (structure) and one ``.npz`` (arrays) per stage, with a fingerprint.

A stage result is a tree of frozen dataclasses, tuples, dicts, numbers,
strings and arrays. :func:`encode` turns it into JSON plus named arrays;
:func:`decode` rebuilds it. Only dataclasses of this project's packages
(an allow-list of module prefixes) are rebuilt, arrays are read with
``allow_pickle=False``, and nothing is unpickled: a result directory a user
hands in can at worst fail to load, never run code.

The n x r reduction basis (fields named ``basis``, e.g.
``CycleResult.basis``) and fields with ``init=False`` (caches) are not
written; they come back as their default (None / empty).
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import json
import os
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from calibration import CalibrationError

FORMAT = "frfcal.stage/1"
_NOT_STORED = {"basis"}  # full-order (n, r): recomputed when a later run needs it
_ALLOWED = ("calibration.", "identification.", "femodel.", "frfcal.campaign.")


def encode(obj, arrays: dict):
    """JSON-able tree of ``obj``; its arrays are added to ``arrays`` under generated keys."""
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, (int, float)) and not isinstance(obj, bool):
        return obj
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return {"__path__": str(obj)}
    if isinstance(obj, np.ndarray):
        if obj.dtype == object:
            raise CalibrationError(f"stage store: object arrays are not stored (shape {obj.shape})")
        key = f"a{len(arrays)}"
        arrays[key] = obj
        return {"__nd__": key}
    if sp.issparse(obj):
        m = obj.tocsr()
        return {"__csr__": [encode(m.data, arrays), encode(m.indices, arrays), encode(m.indptr, arrays),
                            list(m.shape)]}
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        cls = type(obj)
        fields = {}
        for f in dataclasses.fields(obj):
            if not f.init or f.name in _NOT_STORED:
                continue
            fields[f.name] = encode(getattr(obj, f.name), arrays)
        return {"__dc__": f"{cls.__module__}:{cls.__qualname__}", "fields": fields}
    if isinstance(obj, tuple):
        return {"__tuple__": [encode(v, arrays) for v in obj]}
    if isinstance(obj, list):
        return [encode(v, arrays) for v in obj]
    if isinstance(obj, dict):
        if all(isinstance(k, str) for k in obj) and not any(k.startswith("__") for k in obj):
            return {k: encode(v, arrays) for k, v in obj.items()}
        return {"__items__": [[encode(k, arrays), encode(v, arrays)] for k, v in obj.items()]}
    raise CalibrationError(f"stage store: cannot store a {type(obj).__name__}")


def _class(name: str):
    module, _, qual = name.partition(":")
    if not module.startswith(_ALLOWED):
        raise CalibrationError(f"stage store: type {name!r} is not one of frfcal's result types")
    cls = importlib.import_module(module)
    for part in qual.split("."):
        cls = getattr(cls, part)
    if not dataclasses.is_dataclass(cls):
        raise CalibrationError(f"stage store: {name!r} is not a result type")
    return cls


def decode(tree, arrays):
    """Inverse of :func:`encode`; ``arrays`` maps the keys to arrays (an opened npz)."""
    if isinstance(tree, list):
        return [decode(v, arrays) for v in tree]
    if not isinstance(tree, dict):
        return tree
    if "__nd__" in tree:
        return np.asarray(arrays[tree["__nd__"]])
    if "__path__" in tree:
        return Path(tree["__path__"])
    if "__csr__" in tree:
        data, indices, indptr, shape = tree["__csr__"]
        return sp.csr_matrix((decode(data, arrays), decode(indices, arrays), decode(indptr, arrays)),
                             shape=tuple(shape))
    if "__tuple__" in tree:
        return tuple(decode(v, arrays) for v in tree["__tuple__"])
    if "__items__" in tree:
        return {decode(k, arrays): decode(v, arrays) for k, v in tree["__items__"]}
    if "__dc__" in tree:
        cls = _class(tree["__dc__"])
        return cls(**{k: decode(v, arrays) for k, v in tree["fields"].items()})
    return {k: decode(v, arrays) for k, v in tree.items()}


def fingerprint(*parts) -> str:
    """SHA-256 of the JSON of ``parts`` (campaign sections, upstream fingerprints, file hashes)."""
    text = json.dumps(parts, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def file_hash(path) -> str:
    """SHA-256 of a file's content (an input file of a stage)."""
    h = hashlib.sha256()
    try:
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    except OSError as exc:
        raise CalibrationError(f"{path}: cannot read: {exc.strerror or exc}") from None
    return h.hexdigest()


class StageStore:
    """The stage results of one campaign: ``<dir>/<stage>.json`` + ``<dir>/<stage>.npz``.

    Parameters
    ----------
    directory : Path
        Usually ``<output dir>/stages``.
    """

    def __init__(self, directory):
        self.directory = Path(directory)

    def _paths(self, stage: str):
        return self.directory / f"{stage}.json", self.directory / f"{stage}.npz"

    def load(self, stage: str, key: str):
        """The stored result of ``stage`` when its fingerprint is ``key``; None otherwise (or unreadable)."""
        jpath, npath = self._paths(stage)
        if not (jpath.exists() and npath.exists()):
            return None
        try:
            head = json.loads(jpath.read_text())
            if head.get("format") != FORMAT or head.get("fingerprint") != key:
                return None
            with np.load(npath, allow_pickle=False) as npz:
                return decode(head["result"], npz)
        except (OSError, ValueError, KeyError, TypeError, CalibrationError):
            return None  # damaged or foreign: the stage runs again

    def holds(self, stage: str, key: str | None) -> bool:
        """Whether a result of ``stage`` with fingerprint ``key`` (any, when None) is stored (its head read,
        not its arrays)."""
        jpath, npath = self._paths(stage)
        try:
            head = json.loads(jpath.read_text())
        except (OSError, ValueError):
            return False
        return (npath.exists() and head.get("format") == FORMAT
                and (key is None or head.get("fingerprint") == key))

    def save(self, stage: str, key: str, result, time_s: float) -> None:
        """Write ``result`` atomically (the JSON, which names the fingerprint, last)."""
        self.directory.mkdir(parents=True, exist_ok=True)
        arrays: dict = {}
        tree = encode(result, arrays)
        jpath, npath = self._paths(stage)
        jpath.unlink(missing_ok=True)  # no stale head may point at the new arrays
        tmp = npath.with_suffix(".tmp.npz")
        np.savez(tmp, **arrays)
        os.replace(tmp, npath)
        tmpj = jpath.with_suffix(".tmp")
        tmpj.write_text(json.dumps({"format": FORMAT, "stage": stage, "fingerprint": key, "time_s": time_s,
                                    "result": tree}))
        os.replace(tmpj, jpath)

    def time_s(self, stage: str) -> float | None:
        """Wall time the stored result took when it was computed."""
        jpath, _ = self._paths(stage)
        try:
            return float(json.loads(jpath.read_text()).get("time_s"))
        except (OSError, ValueError, TypeError):
            return None
