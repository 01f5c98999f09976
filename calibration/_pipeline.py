"""A campaign end to end: model + runs -> identification -> calibration -> validation -> CV -> outputs.

Plain orchestration of the kernels in this package; every step is timed and
reported through ``log`` (progress on long steps).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from calibration._campaign import Campaign
from calibration._crossval import cross_validate
from calibration._ensemble import grouping, pairwise_sd
from calibration._errors import CalibrationError
from calibration._fit import FitData, Objective, calibrate_cycles
from calibration._identifiability import identifiability
from calibration._sampling import half_bandwidth_frequencies
from calibration._signal import signal_pairs
from calibration._surrogate import FRFModel, build_surrogate
from calibration._validation import IdentifiedModes, noise_floor_sd, validate


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
    std_error: np.ndarray | None = None  # like frf: standard error of each value; None if the run has none
    pairs: np.ndarray | None = None  # (n_channels, n_in) bool: pairs with a signal above noise (None: all)


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
        se = np.asarray(run.std_error, float)[sel][:, rows][:, :, cols]
        se = se if np.any(se > 0) and np.all(np.isfinite(se)) else None  # all zero: not measured
        bad = ~np.all(np.isfinite(H[sel]), axis=(1, 2))
        if bad.any():
            raise CalibrationError(
                f"{path}: {bad.sum()} valid line(s) hold NaN/inf (first at {f[sel][bad][0]:.3f} Hz): flag them invalid"
            )
        drives = tuple(run.drives[c].name for c in cols)
        sig = signal_pairs(f[sel], H[sel], se)
        for line in sig.describe(names, drives):
            log(f"{path.name}: {line}: left out of calibration and validation")
        if not sig.usable.any():
            raise CalibrationError(f"{path}: no channel/drive pair carries a signal above the noise in the band")
        out.append(Article(
            name=entry.article or run.article,
            path=path,
            freq_hz=f[sel],
            frf=H[sel],
            channels=tuple(names),
            drives=drives,
            identification=None,
            ident_channels=tuple(names),
            quantity=run.quantity,
            std_error=se,
            pairs=None if sig.usable.all() else sig.usable,
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


def identified_modes(article: Article) -> IdentifiedModes:
    m = article.identification.modal
    return IdentifiedModes(m.frequency_hz, m.damping, m.shapes, article.ident_channels)


def _equalized_data(article: Article, zeta, f, outputs):
    from identification import equalized

    ss = equalized(article.identification, zeta)
    H = ss.frf(f)
    rows = [article.ident_channels.index(n) for n in outputs]
    return FitData(f, H[:, rows], tuple(outputs), inputs=article.drives, article=article.name,
                   mask=_pair_mask(article, outputs, f.size))


def _pair_mask(article: Article, channels, n_f: int):
    """FitData mask leaving out the pairs without signal (None when every pair has one)."""
    if article.pairs is None:
        return None
    use = article.pairs[[article.channels.index(n) for n in channels]]
    return None if use.all() else np.broadcast_to(use, (n_f, *use.shape)).copy()


def _noise_floor(article: Article, channels) -> float | None:
    """Noise floor of the SD of the article's raw lines on ``channels`` (None without standard errors)."""
    if article.std_error is None:
        return None
    rows = [article.channels.index(n) for n in channels]
    d = _raw_data(article, channels)
    return noise_floor_sd(d, article.std_error[:, rows])


def _members(camp: Campaign, articles, f, log):
    mode = camp.calibration.ensemble
    if mode == "all" or len(articles) == 1:
        return [("all", list(range(len(articles))))], None, None
    if mode == "article":
        return [(a.name, [i]) for i, a in enumerate(articles)], None, None
    eq = [_equalized_data(a, camp.calibration.zeta0, f, camp.channels.calibrate).frf for a in articles]
    D = pairwise_sd(eq)
    floors = [_noise_floor(a, camp.channels.calibrate) for a in articles]
    grp = grouping(D, camp.calibration.n_groups, None if any(x is None for x in floors) else floors)
    labels = grp.labels
    groups = [[i for i in range(len(articles)) if labels[i] == g] for g in range(labels.max() + 1)]
    log("groups: " + "; ".join(", ".join(articles[i].name for i in g) for g in groups))
    log("grouping: " + grp.describe([a.name for a in articles]))
    return [(f"group{g + 1}", idx) for g, idx in enumerate(groups)], D, grp


def _raw_data(article: Article, channels) -> FitData:
    """The article's measured in-band lines on ``channels``."""
    rows = [article.channels.index(n) for n in channels]
    return FitData(article.freq_hz, article.frf[:, rows], tuple(channels), article.drives, article=article.name,
                   mask=_pair_mask(article, channels, article.freq_hz.size))


def _refined(camp: Campaign, model, arts, cyc, band, lower, upper, log, label):
    """Refine the equalized optimum on the raw lines, then re-basis the raw-line stage until p settles.

    Returns (Refinement of the last cycle with every stage of all cycles, p, surrogate).
    """
    from calibration._refine import refine

    c = camp.calibration
    raw = [_raw_data(a, camp.channels.calibrate) for a in arts]
    idents = [(a.identification, a.ident_channels) for a in arts]
    modes = [identified_modes(a) for a in arts]
    opts = dict(quantity=arts[0].quantity, mac_min=camp.validation.mac_min, band_hz=band,
                max_nfev=c.max_evaluations)
    t0 = time.perf_counter()
    ref = refine(cyc.surrogate, cyc.p, raw, idents, modes, lower, upper, c.zeta0, floors=c.refine_floors, **opts)
    stages = list(ref.stages)
    log(f"[{label}] raw-line SD (identified damping) {ref.sd_raw_start:.4g} -> {ref.sd_raw:.4g} "
        f"after {len(ref.stages)} refinement stage(s), max |dp| {np.max(np.abs(ref.p - cyc.p)):.3g} "
        f"({time.perf_counter() - t0:.1f} s)")
    sur, basis = cyc.surrogate, cyc.basis
    for k in range(c.refine_cycles):
        t0 = time.perf_counter()
        sur, basis = build_surrogate(model, ref.p, band, c.basis_factor, enrich=c.enrich, previous_basis=basis)
        nxt = refine(sur, ref.p, raw, idents, modes, lower, upper, c.zeta0, floors=(0.0,), **opts)
        dp = float(np.max(np.abs(nxt.p - ref.p)))
        stages.extend(nxt.stages)
        ref = nxt
        log(f"[{label}] raw-line re-basis {k + 1}: SD {ref.sd_raw:.4g}, max |dp| {dp:.2e} "
            f"({time.perf_counter() - t0:.1f} s)")
        if dp < c.cycle_tol:
            break
    return replace(ref, stages=tuple(stages)), ref.p, sur


def _identifiability(camp: Campaign, cyc, data, ref, p, sur, arts, lower, upper, pm):
    """Identifiability at the reported point, from the objective that produced it.

    After the refinement that is the raw-line objective (identified damping as
    estimated, each article's lines); else the equalized one. The residual is
    stacked frequency-major per data set, so adjacent lines are n_out x n_in
    values apart (the stride of the correlated-residual inflation).
    """
    if ref is None:
        obj = Objective(cyc.surrogate, data, camp.calibration.zeta0, arts[0].quantity)
        stride = data[0].frf.shape[1] * data[0].frf.shape[2]
    else:
        from calibration._refine import ModalDampingObjective

        raw = [_raw_data(a, camp.channels.calibrate) for a in arts]
        obj = ModalDampingObjective(sur, raw, ref.zeta, ref.p_zeta, 0.0, arts[0].quantity)
        stride = raw[0].frf.shape[1] * raw[0].frf.shape[2]
    return identifiability(obj.jacobian(p), obj.residual(p), p, lower, upper, pm.parameters.names, stride=stride)


def _per_article(camp: Campaign, sur0, sur, arts, p, band, lower, upper, log, label) -> tuple:
    """Each article's own raw-line estimate, started from the ensemble's, and its hold-out SD.

    One parameter set cannot fit several articles to their noise floor: the
    articles differ (test-to-test scatter), and at 0.1 % damping a 0.3 %
    stiffness difference already moves a resonance by most of a half-power
    bandwidth. The ensemble estimate stays the member's result; these per-article
    estimates show the scatter (their spread) and whether each article's data
    are explained to their floor.
    """
    from calibration._refine import refine

    c = camp.calibration
    out = []
    for a in arts:
        modes = identified_modes(a)
        r = refine(sur, p, [_raw_data(a, camp.channels.calibrate)], [(a.identification, a.ident_channels)], [modes],
                   lower, upper, c.zeta0, floors=(0.0,), quantity=a.quantity, mac_min=camp.validation.mac_min,
                   band_hz=band, max_nfev=c.max_evaluations)
        row = {"article": a.name, "p": r.p.tolist(), "sd_raw_calibration": r.sd_raw, "sd_holdout": None}
        if camp.channels.holdout:
            v = validate(sur0, sur, r.p, [_raw_data(a, camp.channels.holdout)], modes, c.zeta0, None,
                         camp.validation.mac_min, a.quantity, band)
            row["sd_holdout"] = v.sd_calibrated
        out.append(row)
        log(f"[{label}] article {a.name}: own estimate, raw-line SD {r.sd_raw:.4g}"
            + ("" if row["sd_holdout"] is None else f", hold-out SD {row['sd_holdout']:.4g}"))
    P = np.array([r["p"] for r in out])
    spread = (1 + P).std(axis=0, ddof=1) / (1 + P).mean(axis=0)
    log(f"[{label}] article-to-article spread of the estimates: median {100 * np.median(spread):.3g} %, "
        f"largest {100 * spread.max():.3g} %")
    return tuple(out)


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
    members, D, grp = _members(camp, articles, f, log)
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
            log(f"[{label}] calibration SD (equalized test model, zeta0={100 * c.zeta0:g} %) "
                f"{cyc.calibration.sd_nominal:.4g} -> {cyc.sd:.4g} ({time.perf_counter() - t:.1f} s)")
            ref, p_final, sur_final = None, cyc.p, cyc.surrogate
            if c.refine:
                ref, p_final, sur_final = _refined(camp, model, arts, cyc, band, lower, upper, log, label)
            t_cal = time.perf_counter() - t
            idf = _identifiability(camp, cyc, data, ref, p_final, sur_final, arts, lower, upper, pm)
            log(f"[{label}] identifiability at the calibrated point:\n{idf.table()}")
            val = None
            t = time.perf_counter()
            if camp.channels.holdout:
                raw = [_raw_data(a, camp.channels.holdout) for a in arts]
                errs = [None if a.std_error is None else
                        a.std_error[:, [a.channels.index(n) for n in camp.channels.holdout]] for a in arts]
                val = validate(sur0, sur_final, p_final, raw, [identified_modes(a) for a in arts], c.zeta0,
                               camp.validation.target_sd, camp.validation.mac_min, arts[0].quantity, band,
                               std_error=None if any(e is None for e in errs) else errs,
                               damping=None if ref is None else (ref.zeta, ref.p_zeta))
                log(f"[{label}] {val.summary()}")
            if ref is not None and len(arts) > 1:
                ref = replace(ref, articles=_per_article(camp, sur0, sur_final, arts, p_final, band, lower, upper,
                                                         log, label))
            t_val = time.perf_counter() - t
            cv = None
            t = time.perf_counter()
            if camp.crossvalidation.realizations:
                if ref is None:
                    cv = cross_validate(cyc.surrogate, data, cyc.p, lower, upper, c.zeta0,
                                        camp.crossvalidation.realizations, camp.crossvalidation.seed, executor,
                                        arts[0].quantity, camp.crossvalidation.max_evaluations)
                else:  # recalibrate what was calibrated last: the raw lines with the identified damping
                    cv = cross_validate(sur_final, [_raw_data(a, camp.channels.calibrate) for a in arts], p_final,
                                        lower, upper, c.zeta0, camp.crossvalidation.realizations,
                                        camp.crossvalidation.seed, executor, arts[0].quantity,
                                        camp.crossvalidation.max_evaluations, damping=(ref.zeta, ref.p_zeta))
                log(f"[{label}] cross-validation RSE {cv.rse:.4g} ({cv.p.shape[0]} realizations)")
                for j in np.flatnonzero(cv.n_at_bound):
                    log(f"[{label}] CV of {pm.parameters.names[j]}: not meaningful, {cv.cv_reason[j]}")
            t_cv = time.perf_counter() - t
            if ref is not None:  # what follows (outputs, figures) reports the refined model
                cyc = replace(cyc, p=p_final, surrogate=sur_final, refinement=ref)
            results.append((label, arts, data, cyc, val, cv, {"calibration_s": t_cal, "validation_s": t_val,
                                                             "crossvalidation_s": t_cv}, idf))
    finally:
        close = getattr(executor, "close", None)
        if close:
            close()
    timings["total_s"] = time.perf_counter() - t_all
    out = _write_outputs(camp, pm, model, sur0, articles, results, D, timings, outdir, log, grp)
    return out


def _write_outputs(camp, pm, model, sur0, articles, results, D, timings, outdir, log, grp=None):
    members = []
    for label, arts, data, cyc, val, cv, tm, idf in results:
        params = []
        phys = pm.physical(cyc.p)
        nominal = pm.physical(np.zeros(pm.n_params))
        for j, name in enumerate(pm.parameters.names):
            row = {"name": name, "nominal_si": nominal[name], "calibrated_si": phys[name], "p": float(cyc.p[j]),
                   "identifiable": bool(idf.identifiable[j]), "identifiability": idf.reasons[j] or None}
            if cv is not None:
                row["cv_mean_si"] = float(pm.nominal[j] * (1 + cv.mean_p[j]))
                row["cv_percent"] = cv.cv(j)
                row["cv_not_meaningful"] = cv.cv_reason[j] or None
            params.append(row)
        entry = {
            "member": label,
            "articles": [a.name for a in arts],
            "parameters": params,
            "sd_calibration_nominal": cyc.calibration.sd_nominal,
            "sd_calibration": cyc.sd,
            "sd_calibration_definition": "equalized identified test model at zeta0 on the half-bandwidth grid",
            "sd_raw_calibration": None if cyc.refinement is None else cyc.refinement.sd_raw,
            "sd_raw_calibration_start": None if cyc.refinement is None else cyc.refinement.sd_raw_start,
            "sd_raw_definition": "raw calibration lines, model with identified damping mapped by MAC",
            "identifiability": idf.to_dict(),
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
                outdir, label, pm, model, sur0, arts, cyc, val, cv, camp, identifiability=idf)]
        members.append(entry)
    result = {
        "campaign": {k: v for k, v in json.loads(camp.model_dump_json()).items()},
        "articles": [a.name for a in articles],
        "pairwise_sd": None if D is None else D.tolist(),
        "grouping": None if grp is None else grp.to_dict(),
        "surrogate": {"size": sur0.size, "modes": len(sur0.basis_frequencies_hz), "static": sur0.n_static,
                      "enrichment": sur0.n_enrich, "timings_s": sur0.timings_s},
        "members": members,
        "timings": timings,
    }
    path = outdir / "calibration.json"
    path.write_text(json.dumps(result, indent=1, default=json_default))
    result["result_file"] = str(path)
    log(f"wrote {path}")
    return result


def json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    if isinstance(o, float) and not np.isfinite(o):
        return None
    raise TypeError(f"not JSON serializable: {type(o).__name__}")
