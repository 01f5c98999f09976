"""A campaign end to end: model + runs -> identification -> calibration -> validation -> CV -> outputs.

Plain orchestration of the kernels in this package; every step is timed and
reported through ``log`` (progress on long steps).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibration._campaign import Campaign
from calibration._crossval import cross_validate
from calibration._ensemble import group_articles, pairwise_sd
from calibration._errors import CalibrationError
from calibration._fit import FitData, calibrate_cycles
from calibration._sampling import half_bandwidth_frequencies
from calibration._surrogate import FRFModel, build_surrogate
from calibration._validation import IdentifiedModes, validate


@dataclass(frozen=True)
class Article:
    """One test article's data as the calibration uses it."""

    name: str
    path: Path
    freq_hz: np.ndarray  # raw lines in band, valid only
    frf: np.ndarray  # (n_f, n_sensors_sel, n_in) raw, channels = Article.channels
    channels: tuple
    drives: tuple
    identification: object  # identification.Identification
    ident_channels: tuple  # output rows of the identified model
    quantity: str


def _sensor_rows(run, names, path):
    lookup = {s.name: i for i, s in enumerate(run.sensors)}
    missing = [n for n in names if n not in lookup]
    if missing:
        raise CalibrationError(f"{path}: channels {missing} are not sensors of the run (has {sorted(lookup)})")
    return [lookup[n] for n in names]


def _drive_cols(run, names, path):
    lookup = {d.name: i for i, d in enumerate(run.drives)}
    if not names:
        return list(range(len(run.drives)))
    missing = [n for n in names if n not in lookup]
    if missing:
        raise CalibrationError(f"{path}: drives {missing} are not drives of the run (has {sorted(lookup)})")
    return [lookup[n] for n in names]


def load_articles(camp: Campaign, log=print, identify_data: bool = True) -> list[Article]:
    """Read every run, select channels and band, identify (or load the stored identification).

    With ``identify_data=False`` only the run files are read and checked
    (identification left None; see :func:`identified_articles`).
    """
    from acquisition.runfile import read_run

    ch = camp.channels
    names = list(ch.calibrate) + list(ch.holdout)
    lo, hi = camp.band.low_hz, camp.band.high_hz
    out = []
    for entry in camp.run:
        path = camp.resolve(entry.path)
        run = read_run(path)
        rows = _sensor_rows(run, names, path)
        cols = _drive_cols(run, ch.drives, path)
        f = np.asarray(run.frequency_hz, float)
        valid = np.asarray(run.valid, bool)
        inband = (f >= lo) & (f <= hi)
        if not np.any(inband & valid):
            raise CalibrationError(
                f"{path}: band [{lo}, {hi}] Hz has no valid lines (run covers "
                f"{f.min() if f.size else float('nan'):.1f}-{f.max() if f.size else float('nan'):.1f} Hz)"
            )
        H = np.asarray(run.frf)[:, rows][:, :, cols]
        sel = inband & valid
        bad = ~np.all(np.isfinite(H[sel]), axis=(1, 2))
        if bad.any():
            raise CalibrationError(
                f"{path}: {bad.sum()} valid line(s) hold NaN/inf (first at {f[sel][bad][0]:.3f} Hz): flag them invalid"
            )
        out.append(Article(
            name=entry.article or run.article,
            path=path,
            freq_hz=f[sel],
            frf=H[sel],
            channels=tuple(names),
            drives=tuple(run.drives[c].name for c in cols),
            identification=None,
            ident_channels=tuple(names),
            quantity=run.quantity,
        ))
    quantities = {a.quantity for a in out}
    if len(quantities) > 1:
        raise CalibrationError(f"runs mix FRF quantities {sorted(quantities)}")
    return identified_articles(camp, out, log) if identify_data else out


def identified_articles(camp: Campaign, articles, log=print) -> list[Article]:
    """Attach an identification to every article: the stored one when usable, else identify now."""
    from dataclasses import replace

    from acquisition.runfile import read_analysis, read_run
    from calibration._identify_run import identify_run
    from identification import Identification

    lo, hi = camp.band.low_hz, camp.band.high_hz
    ilo = camp.identification.low_hz or 0.8 * lo
    ihi = camp.identification.high_hz or 1.25 * hi
    out = []
    for a in articles:
        run = read_run(a.path)
        ident = None
        ident_channels = a.channels
        if camp.identification.use_stored and "identification" in (run.analyses or ()):
            arrays, attrs = read_analysis(a.path, "identification")
            cand = Identification.from_arrays(arrays, attrs)
            if cand.model.n_out == len(run.sensors) and cand.model.n_in == len(run.drives):
                ident = cand
                ident_channels = tuple(s.name for s in run.sensors)
                log(f"{a.path.name}: using stored identification (order {cand.order})")
        if ident is None:
            t0 = time.perf_counter()
            ident = identify_run(run, (ilo, ihi), order=camp.identification.order, channels=a.channels,
                                 drives=a.drives)
            blo, bhi = ident.band_hz
            how = "set" if ident.order_selection is None else f"automatic: {ident.order_selection.reason}"
            log(f"{a.path.name}: identified order {ident.order} ({how}), {ident.modal.n_modes} modes in "
                f"{blo:.0f}-{bhi:.0f} Hz, weights {ident.settings['weights']} ({time.perf_counter() - t0:.1f} s)")
        out.append(replace(a, identification=ident, ident_channels=ident_channels))
    return out


def build_model(camp: Campaign, articles, log=print):
    """ParametricModel + FRFModel with the campaign's channels as outputs and drives as inputs."""
    import femodel
    from acquisition.runfile import read_run

    t0 = time.perf_counter()
    params = camp.resolve(camp.model.parameters)
    pm = femodel.parametric_model(params, camp.resolve(camp.model.bdf), units=camp.model.units)
    run = read_run(articles[0].path)
    spec = {s.name: s for s in run.sensors}
    dspec = {d.name: d for d in run.drives}
    C_rows = []
    for name in articles[0].channels:
        s = spec[name]
        try:
            C_rows.append(femodel.sensor_matrix(pm.assembly, [s.grid], [s.direction]))
        except ValueError as exc:
            raise CalibrationError(f"channel {name!r} (grid {s.grid}, direction {tuple(s.direction)}): {exc}") from None
    B_cols = []
    for name in articles[0].drives:
        d = dspec[name]
        try:
            B_cols.append(femodel.sensor_matrix(pm.assembly, [d.grid], [d.direction]).T)
        except ValueError as exc:
            raise CalibrationError(f"drive {name!r} (grid {d.grid}, direction {tuple(d.direction)}): {exc}") from None
    import scipy.sparse as sp

    model = FRFModel(
        K=pm.K, M=pm.M,
        inputs=sp.hstack(B_cols).tocsc(),
        outputs=sp.vstack(C_rows).tocsr(),
        input_names=articles[0].drives,
        output_names=articles[0].channels,
        parameter_names=tuple(pm.parameters.names),
        parametric=pm,
    )
    log(f"model: {pm.K.shape[0]} DOF, {pm.n_params} parameters ({time.perf_counter() - t0:.1f} s)")
    return pm, model


def _identified_modes(article: Article) -> IdentifiedModes:
    m = article.identification.modal
    return IdentifiedModes(m.frequency_hz, m.damping, m.shapes, article.ident_channels)


def _equalized_data(article: Article, zeta, f, outputs):
    from identification import equalized

    ss = equalized(article.identification, zeta)
    H = ss.frf(f)
    rows = [article.ident_channels.index(n) for n in outputs]
    return FitData(f, H[:, rows], tuple(outputs), inputs=article.drives, article=article.name)


def _members(camp: Campaign, articles, f, log):
    mode = camp.calibration.ensemble
    if mode == "all" or len(articles) == 1:
        return [("all", list(range(len(articles))))], None
    if mode == "article":
        return [(a.name, [i]) for i, a in enumerate(articles)], None
    eq = [_equalized_data(a, camp.calibration.zeta0, f, camp.channels.calibrate).frf for a in articles]
    D = pairwise_sd(eq)
    labels = group_articles(D, camp.calibration.n_groups)
    groups = [[i for i in range(len(articles)) if labels[i] == g] for g in range(labels.max() + 1)]
    log("groups: " + "; ".join(", ".join(articles[i].name for i in g) for g in groups))
    return [(f"group{g + 1}", idx) for g, idx in enumerate(groups)], D


def run_campaign(camp: Campaign, log=print) -> dict:
    """Run the campaign; write outputs into ``camp.output.dir``; return the result dict."""
    from calibration._executor import make_executor

    timings = {}
    t_all = time.perf_counter()
    t = time.perf_counter()
    articles = load_articles(camp, log, identify_data=False)
    timings["load_s"] = time.perf_counter() - t
    t = time.perf_counter()
    pm, model = build_model(camp, articles, log)
    timings["model_s"] = time.perf_counter() - t
    t = time.perf_counter()
    articles = identified_articles(camp, articles, log)
    timings["identification_s"] = time.perf_counter() - t
    c = camp.calibration
    band = (camp.band.low_hz, camp.band.high_hz)
    f = half_bandwidth_frequencies(*band, c.zeta0, c.samples_per_half_bandwidth)
    f_stage = {z: half_bandwidth_frequencies(*band, z, c.samples_per_half_bandwidth) for z in c.continuation_zeta}
    members, D = _members(camp, articles, f, log)
    outdir = camp.resolve(camp.output.dir)
    outdir.mkdir(parents=True, exist_ok=True)
    lower, upper = pm.lower, pm.upper
    executor = make_executor(camp.execution.scheduler, camp.execution.workers,
                             progress=None)
    results = []
    try:
        executor.start()  # local workers start and import while the basis is built
        t = time.perf_counter()
        sur0, T0 = build_surrogate(model, np.zeros(pm.n_params), band, c.basis_factor, enrich=c.enrich)
        timings["basis_s"] = time.perf_counter() - t
        log(f"surrogate: {sur0.size} ({len(sur0.basis_frequencies_hz)} modes, {sur0.n_static} static, "
            f"{sur0.n_enrich} enrichment) in {timings['basis_s']:.1f} s")
        for label, idx in members:
            arts = [articles[i] for i in idx]
            data = [_equalized_data(a, c.zeta0, f, camp.channels.calibrate) for a in arts]
            cont = [(z, [_equalized_data(a, z, f_stage[z], camp.channels.calibrate) for a in arts])
                    for z in c.continuation_zeta]
            t = time.perf_counter()
            log(f"[{label}] calibrating on {len(arts)} article(s), {len(f)} frequencies x "
                f"{len(camp.channels.calibrate)} channels, {c.starts + 1} starts")
            cyc = calibrate_cycles(model, data, band, lower, upper, c.zeta0, c.starts, c.seed, executor,
                                   arts[0].quantity, c.max_cycles, c.cycle_tol, c.basis_factor, surrogate=sur0,
                                   log=log, continuation=cont, enrich=c.enrich, max_nfev=c.max_evaluations,
                                   basis=T0)
            t_cal = time.perf_counter() - t
            log(f"[{label}] SD {cyc.calibration.sd_nominal:.4g} -> {cyc.sd:.4g} ({t_cal:.1f} s)")
            val = None
            t = time.perf_counter()
            if camp.channels.holdout:
                raw = []
                for a in arts:
                    rows = [a.channels.index(n) for n in camp.channels.holdout]
                    raw.append(FitData(a.freq_hz, a.frf[:, rows], tuple(camp.channels.holdout), a.drives,
                                       article=a.name))
                val = validate(sur0, cyc.surrogate, cyc.p, raw, _identified_modes(arts[0]), c.zeta0,
                               camp.validation.target_sd, camp.validation.mac_min, arts[0].quantity, band)
                log(f"[{label}] hold-out SD {val.sd_nominal:.4g} -> {val.sd_calibrated:.4g} "
                    f"({'passed' if val.passed else 'FAILED'})")
            t_val = time.perf_counter() - t
            cv = None
            t = time.perf_counter()
            if camp.crossvalidation.realizations:
                cv = cross_validate(cyc.surrogate, data, cyc.p, lower, upper, c.zeta0,
                                    camp.crossvalidation.realizations, camp.crossvalidation.seed, executor,
                                    arts[0].quantity, camp.crossvalidation.max_evaluations)
                log(f"[{label}] cross-validation RSE {cv.rse:.4g} ({cv.p.shape[0]} realizations)")
            t_cv = time.perf_counter() - t
            results.append((label, arts, data, cyc, val, cv, {"calibration_s": t_cal, "validation_s": t_val,
                                                             "crossvalidation_s": t_cv}))
    finally:
        close = getattr(executor, "close", None)
        if close:
            close()
    timings["total_s"] = time.perf_counter() - t_all
    out = _write_outputs(camp, pm, model, sur0, articles, results, D, timings, outdir, log)
    return out


def _write_outputs(camp, pm, model, sur0, articles, results, D, timings, outdir, log):
    members = []
    for label, arts, data, cyc, val, cv, tm in results:
        params = []
        phys = pm.physical(cyc.p)
        nominal = pm.physical(np.zeros(pm.n_params))
        for j, name in enumerate(pm.parameters.names):
            row = {"name": name, "nominal_si": nominal[name], "calibrated_si": phys[name], "p": float(cyc.p[j])}
            if cv is not None:
                row["cv_mean_si"] = float(pm.nominal[j] * (1 + cv.mean_p[j]))
                row["cv_percent"] = float(cv.cv_percent[j])
            params.append(row)
        entry = {
            "member": label,
            "articles": [a.name for a in arts],
            "parameters": params,
            "sd_calibration_nominal": cyc.calibration.sd_nominal,
            "sd_calibration": cyc.sd,
            "calibration": cyc.to_dict(),
            "validation": None if val is None else val.to_dict(),
            "crossvalidation": None if cv is None else cv.to_dict(),
            "timings": tm,
        }
        if camp.output.write_bdf:
            bdf_out = outdir / f"calibrated_{label}.bdf"
            pm.write_bdf(bdf_out, cyc.p)
            entry["bdf"] = str(bdf_out)
        if camp.output.figures:
            from calibration._figures import member_figures

            entry["figures"] = [str(p) for p in member_figures(
                outdir, label, pm, model, sur0, arts, cyc, val, cv, camp)]
        members.append(entry)
    result = {
        "campaign": {k: v for k, v in json.loads(camp.model_dump_json()).items()},
        "articles": [a.name for a in articles],
        "pairwise_sd": None if D is None else D.tolist(),
        "surrogate": {"size": sur0.size, "modes": len(sur0.basis_frequencies_hz), "static": sur0.n_static,
                      "enrichment": sur0.n_enrich, "timings_s": sur0.timings_s},
        "members": members,
        "timings": timings,
    }
    path = outdir / "calibration.json"
    path.write_text(json.dumps(result, indent=1, default=_json_default))
    result["result_file"] = str(path)
    log(f"wrote {path}")
    return result


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    if isinstance(o, float) and not np.isfinite(o):
        return None
    raise TypeError(f"not JSON serializable: {type(o).__name__}")
