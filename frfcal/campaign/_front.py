"""The campaign's front stages: pretest (layout), acquire (stepped-sine runs), import (UFF58 files).

They produce the files the load stage reads: a layout file, run files. Each
is a function of the campaign and returns a small frozen dataclass naming the
files it wrote; :func:`frfcal.campaign.run_campaign` stores it with a
fingerprint like every other stage. Files go into the output directory.
"""

from __future__ import annotations

import json
import os
import tomllib
from dataclasses import dataclass
from pathlib import Path

from calibration import CalibrationError
from frfcal.campaign._schema import Campaign, RunEntry
from frfcal.campaign._store import file_hash

#: marker in the acquisition directory: the fingerprint of the acquire stage its run files belong to
ACQUIRE_MARKER = ".campaign-acquire.json"


@dataclass(frozen=True)
class LayoutResult:
    """The pretest stage: the layout file written, its channel and drive names, its figures."""

    path: Path
    channels: tuple
    drives: tuple
    figures: tuple = ()


@dataclass(frozen=True)
class RunFiles:
    """Run files a stage wrote (acquire, import): one per entry, with the article label (or None)."""

    paths: tuple
    articles: tuple

    def missing(self) -> list:
        """The listed run files that are no longer on disk (the stage then runs again)."""
        return [p for p in self.paths if not Path(p).exists()]


def deck(camp: Campaign) -> tuple[Path, str]:
    """The campaign's Nastran deck and units: ``[model] bdf/units``, else the parameter file's ``[model]``."""
    from femodel import read_parameters

    bdf, units = camp.resolve(camp.model.bdf), camp.model.units
    if bdf is None or units is None:
        params = read_parameters(camp.resolve(camp.model.parameters))
        bdf = bdf or params.bdf
        units = units or params.units
    if bdf is None:
        raise CalibrationError(f"{camp.resolve(camp.model.parameters)}: no deck: give [model] bdf in the campaign "
                               "or in the parameter file")
    return Path(bdf), units or "si"


# ----------------------------------------------------------------------------- pretest


def pretest_stage(camp: Campaign, outdir: Path, log=print) -> LayoutResult:
    """Plan sensors and drive points on the deck (``frfcal pretest``); write ``<outdir>/layout.json``."""
    import femodel
    import pretest

    s = camp.pretest
    cfg = s.config()
    bdf, units = deck(camp)
    model = femodel.read_bdf(bdf, units=units)
    res = pretest.plan_pretest(model, cfg)
    outdir.mkdir(parents=True, exist_ok=True)
    out = outdir / "layout.json"
    pretest.write_layout(out, res, model_path=bdf, units=units)
    figures = ()
    if s.figures:
        figures = (pretest.plot_layout(model, res, outdir / "layout_layout.png"),
                   pretest.plot_automac(res, outdir / "layout_automac.png"))
    log(f"pretest: {len(res.channel_names)} channels, drives {', '.join(res.drive_names)} on {bdf.name}; wrote {out}")
    return LayoutResult(out, tuple(res.channel_names), tuple(res.drive_names), tuple(Path(f) for f in figures))


# ----------------------------------------------------------------------------- acquire


def campaign_plan(camp: Campaign, layout: Path | None):
    """The acquisition plan (``acquisition.Plan``) of the campaign, with the campaign's layout filled in.

    The plan is ``[acquisition] plan`` (a TOML file, relative paths in it
    resolved against that file) or the inline ``[acquisition.plan]`` table
    (relative to the campaign file). A plan naming neither ``layout`` nor
    ``[[channels]]`` uses ``layout`` (the pretest stage's or ``[layout] file``);
    a plan that names its own while the campaign has one is refused.
    """
    from acquisition._plan import PlanError, plan_from_dict

    spec = camp.acquisition.plan
    if isinstance(spec, dict):
        data, base, source = dict(spec), camp.base_dir, f"{camp.base_dir}: [acquisition.plan]"
    else:
        path = camp.resolve(spec)
        try:
            data = tomllib.loads(path.read_text())
        except FileNotFoundError:
            raise CalibrationError(f"[acquisition] plan: {path} not found") from None
        except tomllib.TOMLDecodeError as exc:
            raise CalibrationError(f"{path}: not valid TOML: {exc}") from None
        base, source = path.resolve().parent, str(path)
    if "base_dir" in data:
        raise CalibrationError(f"{source}: base_dir: unknown field")
    own = "layout" in data or "channels" in data
    if layout is not None and own:
        raise CalibrationError(f"{source}: the plan names its own layout/channels and the campaign has "
                               "[pretest] or [layout]: keep one")
    if layout is None and not own:
        raise CalibrationError(f"{source}: no channels: give [pretest] or [layout] file in the campaign, "
                               "or layout/[[channels]] in the plan")
    if layout is not None:
        data["layout"] = str(Path(layout).resolve())
    data["base_dir"] = str(base)
    try:
        return plan_from_dict(data, source=source)
    except PlanError as exc:
        raise CalibrationError(str(exc)) from None


def plan_inputs(camp: Campaign, plan) -> dict:
    """What the acquire stage's fingerprint covers besides the plan itself: driver, hardware and plant files."""
    out = {"driver": camp.acquisition.driver, "plan": json.loads(plan.model_dump_json())}
    if camp.acquisition.hardware is not None:
        out["hardware_sha256"] = file_hash(camp.resolve(camp.acquisition.hardware))
    if plan.layout is not None:
        out["layout_sha256"] = file_hash(plan.resolve(plan.layout))
    if plan.sim is not None and plan.sim.model is not None:
        out["sim_model_sha256"] = file_hash(plan.resolve(plan.sim.model))
    if camp.simulation is not None and camp.acquisition.driver == "sim":
        # the simulated articles are the deck at their parameters: the deck and parameter file are inputs
        bdf, units = deck(camp)
        out["simulation"] = camp.simulation.model_dump(mode="json")
        out["truth_deck"] = {"bdf_sha256": file_hash(bdf), "units": units,
                             "parameters_sha256": file_hash(camp.resolve(camp.model.parameters))}
    return out


def driver_factory(camp: Campaign, plan):
    """``(make_driver, driver_channels)`` for :func:`acquisition.run_plan`, as ``frfcal acquire`` makes them.

    ``driver = "sim"`` simulates the plan's ``[sim]`` plant; "visa"/"ni" use
    ``[acquisition] hardware``. (Simulated articles with their own truth
    plants plug in here.)
    """
    from frfcal.commands.acquire import _hardware_factory, _sim_factory

    a = camp.acquisition
    if a.driver == "sim":
        if plan.sim is None:
            raise CalibrationError("[acquisition] driver = \"sim\" needs a [sim] plant in the plan (docs/acquisition.md)")
        return _sim_factory(plan)
    return _hardware_factory(plan, a.driver, str(camp.resolve(a.hardware)))


def _set_aside(directory: Path, why: str, log) -> None:
    """Move a run directory that belongs to other settings aside (never delete a measured line)."""
    k = 1
    while (target := directory.with_name(f"{directory.name}.superseded-{k}")).exists():
        k += 1
    os.replace(directory, target)
    log(f"acquire: {directory} {why}: moved to {target}")


def _run_safely(plan, make, runs: Path, channels):
    """:func:`acquisition.run_plan` with SIGTERM taking the Ctrl-C path (drive ramped down, run file closed);
    an abort becomes one error line saying that the completed lines are kept."""
    import signal
    import threading

    from acquisition import AcquisitionAbort, DriverError, run_plan

    def _term(signum, frame):
        raise KeyboardInterrupt

    main = threading.current_thread() is threading.main_thread()
    old = signal.signal(signal.SIGTERM, _term) if main else None
    try:
        return run_plan(plan, make, runs, progress=False, driver_channels=channels)
    except (AcquisitionAbort, DriverError) as exc:
        raise CalibrationError(f"acquire: aborted ({type(exc).__name__}: {exc}); drive ramped to zero, every "
                               f"completed line is kept in {runs}: run the same command again to resume") from None
    finally:
        if main:
            signal.signal(signal.SIGTERM, old)


def acquire_stage(camp: Campaign, plan, key: str, outdir: Path, log=print) -> RunFiles:
    """Run the plan into ``<outdir>/<[acquisition] dir>``; resume an interrupted acquisition of the same settings.

    The directory carries a marker with the stage fingerprint ``key``. Run
    files there with the same fingerprint are kept: completed ones are
    skipped, interrupted ones resumed line by line
    (:func:`acquisition.run_plan`). A directory from other settings (another
    fingerprint, or run files without a marker) is moved aside to
    ``<dir>.superseded-N`` and the acquisition starts afresh.
    """
    runs = outdir / camp.acquisition.dir
    marker = runs / ACQUIRE_MARKER
    if runs.exists():
        try:
            old = json.loads(marker.read_text()).get("fingerprint")
        except (OSError, ValueError, AttributeError):
            old = None
        if old != key and any(runs.iterdir()):
            _set_aside(runs, "holds runs of other acquisition settings" if old else "holds files of unknown origin", log)
        elif old == key:
            log(f"acquire: resuming in {runs} (completed runs are kept, interrupted ones continue)")
    runs.mkdir(parents=True, exist_ok=True)
    marker.write_text(json.dumps({"fingerprint": key}))
    if camp.simulation is not None and camp.acquisition.driver == "sim":
        return _simulated_acquisition(camp, plan, runs, log)
    make, channels = driver_factory(camp, plan)
    results = _run_safely(plan, make, runs, channels)
    bad = [r for r in results if r.status != "completed"]
    if bad:
        raise CalibrationError(f"acquire: {bad[0].path}: {bad[0].status}: run the stage again to resume")
    for r in results:
        log(f"acquire: {r.path}: {r.n_lines} lines ({r.n_new_lines} new)")
    return RunFiles(tuple(Path(r.path) for r in results), tuple(None for _ in results))


def _simulated_acquisition(camp: Campaign, plan, runs: Path, log) -> RunFiles:
    """The acquire stage on the simulated articles of ``[simulation]`` (``frfcal.campaign._acquire``)."""
    import femodel

    from frfcal.campaign._acquire import SimulationError, acquire_simulated

    bdf, units = deck(camp)
    pm = femodel.parametric_model(camp.resolve(camp.model.parameters), bdf, units=units)
    try:
        _, done = acquire_simulated(camp.simulation, plan, pm, runs, log=lambda m: log(f"acquire: {m}"))
    except SimulationError as exc:
        raise CalibrationError(str(exc)) from None
    return RunFiles(tuple(r.path for r in done), tuple(r.article for r in done))


# ----------------------------------------------------------------------------- import


def uff_entries(camp: Campaign) -> list:
    """(index, entry) of the ``[[run]]`` entries that name a UFF58 file."""
    return [(i, e) for i, e in enumerate(camp.run) if e.uff is not None]


def import_target(outdir: Path, entry: RunEntry) -> Path:
    """Run file an imported UFF58 entry becomes: ``<outdir>/runs/<article or file stem>.h5``."""
    return outdir / "runs" / f"{entry.article or Path(entry.uff).stem}.h5"


def import_stage(camp: Campaign, outdir: Path, log=print) -> RunFiles:
    """Import every ``uff = ...`` entry into a run file (the code of ``frfcal import-uff``)."""
    from frfcal.commands.import_uff import spread_note, uff_to_run

    paths, arts = [], []
    seen: dict = {}
    for i, e in uff_entries(camp):
        out = import_target(outdir, e)
        if out in seen:
            raise CalibrationError(f"[[run]] {seen[out] + 1} and {i + 1} would both import into {out}: "
                                   "give them different article labels")
        seen[out] = i
        info = uff_to_run(camp.resolve(e.uff), out, article=e.article, overwrite=True)
        log(f"import: {e.uff} -> {out}: {info['n_lines']} lines, {len(info['sensors'])} x {len(info['drives'])}, "
            f"article {info['article']!r}"
            + (f" (left out {len(info['dropped_hz'])} line(s) at 0 Hz)" if info["dropped_hz"] else "")
            + "".join(f" (left out {len(ns)} {what} record(s))" for what, ns in info["skipped_records"].items())
            + (f"; {spread_note(info['abscissa_spread'])}" if info["abscissa_spread"] else ""))
        paths.append(out)
        arts.append(e.article)
    return RunFiles(tuple(paths), tuple(arts))


def resolved_runs(camp: Campaign, imported: RunFiles | None, acquired: RunFiles | None) -> Campaign:
    """The campaign with every ``[[run]]`` a run file: imported entries replaced, or the acquired runs."""
    if acquired is not None:
        # several force levels per article: the lowest is the calibration data (docs/campaign.md, levels);
        # all levels stay in the acquire result for the nonlinearity check
        from frfcal.campaign._acquire import runs_by_level

        label = {str(Path(p)): a for p, a in zip(acquired.paths, acquired.articles)}
        lowest = [entries[0][1] for entries in runs_by_level(acquired.paths).values()]
        runs = [RunEntry(path=Path(p).resolve(), article=label.get(str(Path(p)))) for p in lowest]
    else:
        it = iter(imported.paths if imported is not None else ())
        runs = [RunEntry(path=Path(next(it)).resolve(), article=e.article) if e.uff is not None else e
                for e in camp.run]
    return camp.model_copy(update={"run": runs})
