"""run_campaign: the stages in order, each result stored under ``<output dir>/stages`` with a fingerprint.

Stages: [pretest] -> [acquire | import] -> load -> identify -> equalize ->
group -> calibrate -> validate -> crossvalidate -> (outputs) -> the stages
registered in :data:`LATE_STAGES` (diagnosis, report, ...). The bracketed
ones run when the campaign has ``[pretest]``, ``[acquisition]`` or
``[[run]] uff = ...`` entries.

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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import scipy.sparse as sp

from calibration import analyze_ahead, make_executor
from frfcal.campaign._diagnose import DiagnosisResult, diagnose_stage, write_diagnosis
from frfcal.campaign._report import write_outputs
from calibration import CalibrationError
from frfcal.campaign._front import (
    acquire_stage,
    campaign_plan,
    import_stage,
    plan_inputs,
    pretest_stage,
    resolved_runs,
    uff_entries,
)
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
FRONT_STAGES = ("pretest", "acquire", "import")
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
    for i, e in enumerate(camp.run):
        if e.path is None:
            raise CalibrationError(f"[[run]] {i + 1}: uff = {str(e.uff)!r} is not imported yet (the import stage)")
    runs = [{"path": str(camp.resolve(e.path).resolve()), "article": e.article,
             "sha256": file_hash(camp.resolve(e.path))} for e in camp.run]
    return fingerprint(VERSION, "load", runs, _section(camp, "channels"), _section(camp, "band"),
                       _section(camp, "identification", "use_stored"))


def front_keys(camp: Campaign) -> dict:
    """Fingerprints of the front stages the campaign has (pretest, import; acquire needs the layout first)."""
    from frfcal.campaign._front import deck

    k = {}
    if camp.pretest is not None:
        bdf, units = deck(camp)
        k["pretest"] = fingerprint(VERSION, "pretest", _section(camp, "pretest"), str(bdf.resolve()), file_hash(bdf),
                                   units)
    ups = uff_entries(camp)
    if ups:
        k["import"] = fingerprint(VERSION, "import", [{"uff": str(camp.resolve(e.uff).resolve()), "article": e.article,
                                                       "sha256": file_hash(camp.resolve(e.uff))} for _, e in ups])
    return k


def stored_front(camp: Campaign, store: StageStore) -> Campaign:
    """The campaign with its ``[[run]]`` entries resolved from the *stored* front stages (nothing is run).

    The UFF58 entries become the run files the stored import stage wrote, an
    ``[acquisition]`` campaign gets the stored acquire stage's runs (the layout
    from the stored pretest stage or ``[layout] file``). For readers of a
    campaign that has run (``frfcal report``); a front stage that is missing
    or stale (changed UFF files, plan, layout) is a :class:`CalibrationError`
    naming it.
    """
    fk = front_keys(camp)
    if "import" not in fk and camp.acquisition is None:
        return camp

    def got(name, key):
        res = store.load(name, key)
        if res is None:
            raise CalibrationError(f"{store.directory}: no stored {name} stage matching the campaign (its inputs "
                                   "changed, or it has not run): run 'frfcal run' on the campaign first")
        return res

    imported = got("import", fk["import"]) if "import" in fk else None
    acquired = None
    if camp.acquisition is not None:
        layout = camp.resolve(camp.layout.file) if camp.layout is not None else None
        if camp.pretest is not None:
            layout = got("pretest", fk["pretest"]).path
        plan = campaign_plan(camp, layout)
        acquired = got("acquire", fingerprint(VERSION, "acquire", plan_inputs(camp, plan)))
    return resolved_runs(camp, imported, acquired)


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
    return k


class _Executor:
    """The campaign's executor, made and started on first use (a rerun that reuses every stage starts none)."""

    def __init__(self, camp: Campaign):
        self.camp = camp
        self._ex = None

    def get(self):
        if self._ex is None:
            ex = self.camp.execution
            self._ex = make_executor(ex.scheduler, ex.workers, progress=None, host=ex.host)
            self._ex.start()
        return self._ex

    def close(self):
        close = getattr(self._ex, "close", None)
        if close:
            close()


@dataclass
class StageContext:
    """What the stages of a campaign run have computed so far (``results[name]``), for later stages.

    ``camp`` has every ``[[run]]`` as a run file (after import/acquire);
    ``pm``, ``model`` the parametric and FRF model; ``articles`` the
    identified articles; ``outputs`` the dict :func:`write_outputs` returned
    (for stages registered with ``after_outputs``); ``executor()`` the
    campaign's executor (started on first call).
    """

    camp: Campaign
    outdir: Path
    log: Callable
    executor: Callable
    results: dict = field(default_factory=dict)
    pm: Any = None
    model: Any = None
    articles: tuple = ()
    outputs: dict | None = None
    names: list = field(default_factory=list)
    last: int = 0
    records: dict = field(default_factory=dict)


@dataclass(frozen=True)
class StageSpec:
    """A stage after cross-validation, plugged into :func:`run_campaign` by appending it to :data:`LATE_STAGES`.

    Attributes
    ----------
    name : str
        Stage name (``frfcal <name> CAMPAIGN.toml`` runs up to it when a command of that name exists).
    reads : tuple of str
        Stages whose results it reads; their fingerprints enter its own.
    settings : callable (Campaign) -> JSON-able
        The campaign settings its result depends on (e.g. ``lambda c: section(c, "diagnosis")``).
    compute : callable (StageContext) -> result
        The stage; its result (frozen dataclasses, arrays, numbers, strings)
        is stored like every other stage's and put into ``ctx.results[name]``.
    applies : callable (Campaign) -> bool
        Whether the campaign has this stage (default: always).
    after_outputs : bool
        Run after ``calibration.json`` and the figures are written (a report).
    """

    name: str
    reads: tuple
    settings: Callable
    compute: Callable
    applies: Callable = lambda camp: True
    after_outputs: bool = False


#: Stages after cross-validation, in order. A stage plugs in with one line, e.g.
#: ``LATE_STAGES.append(StageSpec("diagnose", ("calibrate", "validate"), lambda c: section(c, "diagnosis"), fn))``.
LATE_STAGES: list = []


def section(camp: Campaign, name: str, *keys):
    """A campaign section as a JSON-able dict (``keys``: only these), for a stage's fingerprint."""
    return _section(camp, name, *keys)


def campaign_stages(camp: Campaign) -> list:
    """The names of the stages this campaign has, in order."""
    names = [n for n, on in (("pretest", camp.pretest is not None), ("acquire", camp.acquisition is not None),
                             ("import", bool(uff_entries(camp)))) if on]
    names += list(STAGES)
    names += [s.name for s in LATE_STAGES if s.applies(camp)]
    return names


def _stale(result) -> bool:
    """A stored front-stage result whose files are gone (the stage then runs again)."""
    missing = getattr(result, "missing", None)
    if missing is not None:
        return bool(missing())
    path = getattr(result, "path", None)
    return isinstance(path, Path) and not path.exists()


def run_campaign(camp: Campaign, log=print, upto: str | None = None, force: str | None = None) -> dict:
    """Run the campaign's stages; write outputs into ``camp.output.dir``; return the result dict.

    Every stage result goes to ``<output dir>/stages/<stage>.json|.npz``;
    a stage whose inputs did not change since it was stored is read back
    instead of run (``result["stages"][name]["status"]`` is "ran" or
    "reused"). See docs/campaign.md.

    Parameters
    ----------
    camp : Campaign
    log : callable (str)
        Progress lines: ``[k/n] stage`` at each stage's start and its time at the end.
    upto : str, optional
        Stop after this stage (default: every stage). The outputs
        (calibration.json, deck, figures) are written when the run reaches
        cross-validation; before that the dict holds ``stages`` and ``upto``.
    force : str, optional
        Recompute this stage and every later one even when stored.
    """
    t_all = time.perf_counter()
    outdir = camp.resolve(camp.output.dir)
    store = StageStore(outdir / "stages")
    names = campaign_stages(camp)
    for what, n in (("upto", upto), ("force", force)):
        if n is not None and n not in names:
            raise CalibrationError(f"{what} {n!r}: this campaign's stages are {', '.join(names)}")
    last = names.index(upto) if upto else len(names) - 1
    forced = names.index(force) if force else len(names)
    total = last + 1
    records: dict = {}
    timings: dict = {}

    class _Done(Exception):
        pass

    def stage(name, key, compute):
        k = names.index(name)
        got = None if k >= forced else store.load(name, key)
        if got is not None and not _stale(got):
            records[name] = {"status": "reused", "fingerprint": key, "time_s": store.time_s(name)}
            log(f"[{k + 1}/{total}] {name}: inputs unchanged, stored result reused ({store.directory})")
        else:
            log(f"[{k + 1}/{total}] {name} ...")
            t0 = time.perf_counter()
            got = compute()
            dt = time.perf_counter() - t0
            store.save(name, key, got, dt)
            records[name] = {"status": "ran", "fingerprint": key, "time_s": dt}
            log(f"[{k + 1}/{total}] {name}: done in {dt:.1f} s")
        if k == last and k < names.index("crossvalidate"):
            raise _Done  # stop before the outputs: they need every stage through cross-validation
        return got

    def will_compute(name: str, key: str | None = None) -> bool:
        """Whether ``stage`` will run ``name`` rather than reuse a stored result (or stop before it). Before
        its key is known (``key`` None): whether no result of ``name`` is stored at all."""
        k = names.index(name)
        return k <= last and (k >= forced or not store.holds(name, key))

    executor = _Executor(camp)
    ctx = StageContext(camp, outdir, log, executor.get, names=names, last=last, records=records)
    try:
        try:
            return _stages(camp, ctx, stage, will_compute, records, timings, t_all)
        finally:
            executor.close()
    except _Done:
        return {"stages": records, "upto": names[last], "output_dir": str(outdir),
                "time_s": time.perf_counter() - t_all}


def _stages(camp, ctx, stage, will_compute, records, timings, t_all):
    """The stages in order (``stage(name, key, compute)`` runs or reuses one; ``will_compute(name, key)``
    says beforehand which it will do)."""
    outdir = ctx.outdir
    fk = front_keys(camp)
    layout = camp.resolve(camp.layout.file) if camp.layout is not None else None
    if camp.pretest is not None:
        layout = stage("pretest", fk["pretest"], lambda: pretest_stage(camp, outdir, ctx.log)).path
    imported = acquired = None
    if camp.acquisition is not None:
        plan = campaign_plan(camp, layout)
        key = fingerprint(VERSION, "acquire", plan_inputs(camp, plan))
        acquired = stage("acquire", key, lambda: acquire_stage(camp, plan, key, outdir, ctx.log))
    if "import" in fk:
        imported = stage("import", fk["import"], lambda: import_stage(camp, outdir, ctx.log))
    camp = ctx.camp = resolved_runs(camp, imported, acquired)
    ctx.results.update({"imported": imported, "acquired": acquired})

    t = time.perf_counter()
    load = stage("load", load_key(camp), lambda: load_stage(camp, ctx.log))
    timings["load_s"] = time.perf_counter() - t
    if will_compute("calibrate"):
        # the multi-start's worker processes start Python and their imports beside pyNastran's parse, which
        # leaves a core idle, rather than beside the first basis (docs/calibration.md, stop 43)
        ctx.executor()
    t = time.perf_counter()
    pm, model = build_model(camp, load, ctx.log)  # every time: the report needs it, its fingerprint guards calibrate
    ctx.pm, ctx.model = pm, model
    timings["model_s"] = time.perf_counter() - t
    keys = stage_keys(camp, model, records["load"]["fingerprint"])
    if will_compute("calibrate", keys["calibrate"]):
        # CHOLMOD's analysis of the first basis's K + sM (METIS, one core) beside the identification, which
        # runs on one BLAS thread below 10,000 lines (docs/calibration.md, "Toward 30 s: measured at stop 43")
        analyze_ahead(model, np.zeros(pm.n_params))
    t = time.perf_counter()
    ident = stage("identify", keys["identify"], lambda: identify_stage(camp, load.articles, ctx.log))
    articles = ident.attached(load.articles)
    ctx.articles = articles
    timings["identification_s"] = time.perf_counter() - t
    eq = stage("equalize", keys["equalize"], lambda: equalize_stage(camp, articles))
    groups = stage("group", keys["group"], lambda: group_stage(camp, articles, eq, ctx.log))
    outdir.mkdir(parents=True, exist_ok=True)
    bounds = (pm.lower, pm.upper)
    cal = stage("calibrate", keys["calibrate"],
                lambda: calibrate_stage(camp, model, articles, eq, groups, ctx.executor(), ctx.log))
    timings["basis_s"] = cal.basis_s
    val = stage("validate", keys["validate"], lambda: validate_stage(camp, articles, cal, bounds, ctx.log))
    ctx.results.update({"load": load, "identify": ident, "equalize": eq, "group": groups, "calibrate": cal,
                        "validate": val})
    xval = stage("crossvalidate", keys["crossvalidate"],
                 lambda: crossvalidate_stage(camp, articles, eq, cal, bounds, pm.parameters.names,
                                             ctx.executor(), ctx.log))
    ctx.results["crossvalidate"] = xval
    wanted = [s for s in LATE_STAGES if s.applies(camp) and ctx.names.index(s.name) <= ctx.last]

    def run_late(spec):
        key = fingerprint(VERSION, spec.name, [keys.get(r) or records.get(r, {}).get("fingerprint") for r in spec.reads],
                          spec.settings(camp))
        keys[spec.name] = key
        ctx.results[spec.name] = stage(spec.name, key, lambda: spec.compute(ctx))

    for spec in wanted:
        if not spec.after_outputs:
            run_late(spec)
    timings["total_s"] = time.perf_counter() - t_all
    out = write_outputs(camp, pm, articles, groups, cal, val, xval, timings, records, outdir, ctx.log)
    ctx.outputs = out
    diag = ctx.results.get("diagnose")
    if isinstance(diag, DiagnosisResult):
        out["diagnosis"] = write_diagnosis(diag, camp, pm, outdir, ctx.log)
    for spec in wanted:
        if spec.after_outputs:
            run_late(spec)
    if isinstance(ctx.results.get("report"), (str, Path)):
        out["report"] = str(ctx.results["report"])
    out["stages"] = records
    out["time_s"] = time.perf_counter() - t_all  # every stage, the outputs and the late stages after them
    return out


def _diagnose(ctx: StageContext):
    r = ctx.results
    return diagnose_stage(ctx.camp, r["load"], ctx.pm, ctx.model, ctx.articles, r["equalize"], r["calibrate"],
                          r["validate"], r["crossvalidate"], ctx.executor(), ctx.log, r["group"],
                          level_checks=_acquired_level_checks(r.get("acquired"), ctx.articles))


def _acquired_level_checks(acquired, articles=()) -> dict:
    """Level dependence of every acquired article swept at several force levels (the campaign calibrates on the
    lowest; docs/campaign.md): article -> (LevelDependence or reason, ((level N, path), ...)).

    The modes checked are those identified on the article's lowest-level run (``articles``, with their
    identification) when it was identified, else the peaks of its channel-averaged magnitude."""
    if acquired is None:
        return {}
    from acquisition.runfile import read_run

    from frfcal.campaign._acquire import level_checks, runs_by_level

    by_level = runs_by_level(acquired.paths)
    by_level = {a: e for a, e in by_level.items() if len(e) > 1}
    if not by_level:
        return {}
    first = next(iter(by_level.values()))[0][1]
    tol = ((read_run(first).plan or {}).get("settle") or {}).get("tolerance")
    ident = {Path(a.path).resolve(): a.identification for a in articles if a.identification is not None}
    modes = {}
    for art, entries in by_level.items():
        idn = ident.get(Path(entries[0][1]).resolve())
        if idn is not None and getattr(idn, "modal", None) is not None:
            modes[art] = sorted(float(f) for f in idn.modal.frequency_hz if f > 0)
    checks = level_checks(by_level, settle_tolerance=tol, modes_hz=modes)
    return {a: (checks[a], tuple(by_level[a])) for a in checks}


def _report(ctx: StageContext):
    from frfcal.campaign._html import ReportResults, report_stage

    r = ctx.results
    return report_stage(ctx.camp, ReportResults(
        load=r.get("load"), identify=r.get("identify"), group=r.get("group"), calibrate=r.get("calibrate"),
        validate=r.get("validate"), crossvalidate=r.get("crossvalidate"), model=ctx.pm,
        pretest=getattr(r.get("pretest"), "result", None), diagnosis=r.get("diagnose"), stages=dict(ctx.records),
        campaign_file=ctx.camp.source), log=ctx.log)


LATE_STAGES.append(StageSpec("diagnose", ("group", "calibrate", "validate", "crossvalidate"),
                             lambda c: [section(c, "diagnosis"), [e.level for e in c.run]], _diagnose,
                             applies=lambda c: c.diagnosis.enabled))
LATE_STAGES.append(StageSpec("report", ("load", "identify", "group", "calibrate", "validate", "crossvalidate",
                                        "diagnose"),
                             lambda c: [section(c, "output"), str(c.source)], _report, after_outputs=True))
