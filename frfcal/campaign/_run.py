"""run_campaign: the stages in order, each result stored under ``<output dir>/stages`` with a fingerprint.

A stage whose fingerprint (its campaign settings, the fingerprints of the
stages it reads, and for the load stage the content of the run files; for
the calibrate stage the assembled model) matches the stored one is not run
again: its stored result is read instead. A rerun with unchanged inputs
therefore only rewrites the outputs, a changed ``[validation]`` setting
redoes validation onward, and an interrupted campaign resumes after the
last stage it completed.
"""

from __future__ import annotations

import hashlib
import json
import time

import numpy as np
import scipy.sparse as sp

from calibration import make_executor
from frfcal.campaign._diagnose import diagnose_stage, write_diagnosis
from frfcal.campaign._report import write_outputs
from frfcal.campaign._schema import Campaign
from frfcal.campaign._stages import (
    build_model,
    calibrate_stage,
    crossvalidate_stage,
    equalize_stage,
    group_stage,
    identify_stage,
    load_stage,
    validate_stage,
)
from frfcal.campaign._store import StageStore, file_hash, fingerprint

STAGES = ("load", "identify", "equalize", "group", "calibrate", "validate", "crossvalidate")
ALL_STAGES = STAGES + ("diagnose",)  # diagnose runs only with run_campaign(..., diagnose=True)
VERSION = 1  # bump when a stage computes differently: every stored result is then stale


def _section(camp: Campaign, name: str, *keys):
    d = json.loads(getattr(camp, name).model_dump_json())
    return {k: d[k] for k in keys} if keys else d


def model_fingerprint(model) -> str:
    """SHA-256 of the assembled model: every K and M term, exponents, inputs, outputs, nominal values, bounds."""
    h = hashlib.sha256()

    def add(a):
        if sp.issparse(a):
            a = a.tocsr()
            for part in (a.data, a.indices, a.indptr, np.asarray(a.shape)):
                h.update(np.ascontiguousarray(part).tobytes())
        else:
            h.update(np.ascontiguousarray(np.asarray(a)).tobytes())

    for aff in (model.K, model.M):
        for m in aff.matrices:
            add(m)
        add(np.asarray(aff.exponents, float))
    add(model.inputs)
    add(model.outputs)
    pm = model.parametric
    for a in (pm.nominal, pm.lower, pm.upper):
        add(np.asarray(a, float))
    h.update(json.dumps([list(pm.parameters.names), list(model.output_names), list(model.input_names)]).encode())
    return h.hexdigest()


def load_key(camp: Campaign) -> str:
    """Fingerprint of the load stage: run files (path, content), channels, band, use of stored identifications."""
    runs = [{"path": str(camp.resolve(e.path).resolve()), "article": e.article,
             "sha256": file_hash(camp.resolve(e.path))} for e in camp.run]
    return fingerprint(VERSION, "load", runs, _section(camp, "channels"), _section(camp, "band"),
                       _section(camp, "identification", "use_stored"))


def stage_keys(camp: Campaign, model, load: str) -> dict:
    """The fingerprint of every stage after load, from the campaign, the model and the load fingerprint."""
    k = {"load": load}
    k["identify"] = fingerprint(VERSION, "identify", k["load"], _section(camp, "identification"))
    k["equalize"] = fingerprint(VERSION, "equalize", k["identify"],
                                _section(camp, "calibration", "zeta0", "samples_per_half_bandwidth",
                                         "continuation_zeta"))
    k["group"] = fingerprint(VERSION, "group", k["equalize"], _section(camp, "calibration", "ensemble", "n_groups"))
    k["calibrate"] = fingerprint(VERSION, "calibrate", k["group"], model_fingerprint(model),
                                 _section(camp, "calibration"), _section(camp, "validation", "mac_min"))
    k["validate"] = fingerprint(VERSION, "validate", k["calibrate"], _section(camp, "validation"))
    k["crossvalidate"] = fingerprint(VERSION, "crossvalidate", k["calibrate"], _section(camp, "crossvalidation"))
    k["diagnose"] = fingerprint(VERSION, "diagnose", k["group"], k["calibrate"], k["validate"], k["crossvalidate"],
                                _section(camp, "diagnosis"), [e.level for e in camp.run])
    return k


class _Executor:
    """The campaign's executor, made and started on first use (a rerun that reuses every stage starts none)."""

    def __init__(self, camp: Campaign):
        self.camp = camp
        self._ex = None

    def get(self):
        if self._ex is None:
            self._ex = make_executor(self.camp.execution.scheduler, self.camp.execution.workers, progress=None)
            self._ex.start()
        return self._ex

    def close(self):
        close = getattr(self._ex, "close", None)
        if close:
            close()


def run_campaign(camp: Campaign, log=print, diagnose: bool = False) -> dict:
    """Run the campaign's stages; write outputs into ``camp.output.dir``; return the result dict.

    ``diagnose=True`` (``frfcal diagnose``, ``frfcal run``) adds the diagnose
    stage after cross-validation (skipped when ``[diagnosis] enabled = false``);
    its result is under ``result["diagnosis"]`` and in ``diagnosis.json``.

    Every stage result goes to ``<output dir>/stages/<stage>.json|.npz``;
    a stage whose inputs did not change since it was stored is read back
    instead of run (``result["stages"][name]["status"]`` is "ran" or
    "reused"). See docs/architecture.md.
    """
    t_all = time.perf_counter()
    outdir = camp.resolve(camp.output.dir)
    store = StageStore(outdir / "stages")
    records: dict = {}
    timings: dict = {}

    def stage(name, key, compute):
        got = store.load(name, key)
        if got is not None:
            records[name] = {"status": "reused", "fingerprint": key, "time_s": store.time_s(name)}
            log(f"stage {name}: inputs unchanged, result read from {store.directory}")
            return got
        t0 = time.perf_counter()
        res = compute()
        dt = time.perf_counter() - t0
        store.save(name, key, res, dt)
        records[name] = {"status": "ran", "fingerprint": key, "time_s": dt}
        return res

    t = time.perf_counter()
    load = stage("load", load_key(camp), lambda: load_stage(camp, log))
    timings["load_s"] = time.perf_counter() - t
    t = time.perf_counter()
    pm, model = build_model(camp, load, log)  # every time: the report needs it, its fingerprint guards calibrate
    timings["model_s"] = time.perf_counter() - t
    keys = stage_keys(camp, model, records["load"]["fingerprint"])
    t = time.perf_counter()
    ident = stage("identify", keys["identify"], lambda: identify_stage(camp, load.articles, log))
    articles = ident.attached(load.articles)
    timings["identification_s"] = time.perf_counter() - t
    eq = stage("equalize", keys["equalize"], lambda: equalize_stage(camp, articles))
    groups = stage("group", keys["group"], lambda: group_stage(camp, articles, eq, log))
    outdir.mkdir(parents=True, exist_ok=True)
    executor = _Executor(camp)
    bounds = (pm.lower, pm.upper)
    try:
        cal = stage("calibrate", keys["calibrate"],
                    lambda: calibrate_stage(camp, model, articles, eq, groups, executor.get(), log))
        timings["basis_s"] = cal.basis_s
        val = stage("validate", keys["validate"], lambda: validate_stage(camp, articles, cal, bounds, log))
        xval = stage("crossvalidate", keys["crossvalidate"],
                     lambda: crossvalidate_stage(camp, articles, eq, cal, bounds, pm.parameters.names,
                                                 executor.get(), log))
        diag = None
        if diagnose and camp.diagnosis.enabled:
            t = time.perf_counter()
            diag = stage("diagnose", keys["diagnose"],
                         lambda: diagnose_stage(camp, load, pm, model, articles, eq, cal, val, xval,
                                                   executor.get(), log, groups))
            timings["diagnosis_s"] = time.perf_counter() - t
    finally:
        executor.close()
    timings["total_s"] = time.perf_counter() - t_all
    result = write_outputs(camp, pm, articles, groups, cal, val, xval, timings, records, outdir, log)
    if diag is not None:
        result["diagnosis"] = write_diagnosis(diag, camp, pm, outdir, log)
    return result
