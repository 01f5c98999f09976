"""The diagnose stage: is there anything to explain, is it nonlinear, which effect does the model lack?

Flow per ensemble member (docs/diagnosis.md):

1. **significance** (:func:`member_residual`): the calibrated model's residual on
   the raw calibration and hold-out lines against the noise floor (per-line
   standard errors, else the identification's fit residual) and the
   test-to-test scatter of the member's articles
   (:func:`calibration.residual_check`). Inside the floor: stop, "nothing to
   explain".
2. **nonlinearity gate** (:func:`nonlinearity_gate`): run files of the same
   article at several force levels (level dependence), THD of the run files,
   up/down sweeps at one level. Flagged: stop, "nonlinear"; no linear effect
   is accepted.
3. candidates and screening (when the kernels are present).

The stage writes nothing; :func:`write_diagnosis` writes ``diagnosis.json``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibration import (
    CalibrationError,
    FitData,
    ModalDampingObjective,
    ResidualItem,
    antiresonances,
    expected_from_std_error,
    log_deviation,
    mode_residuals,
    residual_check,
    scatter_sd,
)
from calibration._damping import mapped_damping
from frfcal.campaign._schema import Campaign
from frfcal.campaign._stages import Article, floor_std_error, floors_of, ident_frf, identified_modes, pair_mask

VERDICTS = ("nothing to explain", "nonlinear", "effect(s) found", "no effect accepted")


# ----------------------------------------------------------------------------- residual


def _channels(camp: Campaign) -> list:
    return list(camp.channels.calibrate) + list(camp.channels.holdout)


def model_frf(sur, p, article: Article, channels, damping, k: int, zeta0: float, mac_min: float, band):
    """The calibrated model's FRF on the article's raw lines and ``channels`` (all values, no mask).

    ``damping`` is the refinement's (zeta per article, p_ref) or None: then
    the identified damping mapped by MAC at ``p``.
    """
    rows = [article.channels.index(n) for n in channels]
    H = article.frf[:, rows]
    d = FitData(article.freq_hz, H, tuple(channels), article.drives, article=article.name)
    if damping is not None:
        zeta, p_ref = damping[0][k], damping[1]
    else:
        modes = identified_modes(article)
        fallback = float(np.median(modes.damping)) if len(modes.damping) else zeta0
        zeta, p_ref = mapped_damping(sur, p, modes, fallback, mac_min, band)[0], p
    eps = ModalDampingObjective(sur, [d], [zeta], p_ref, 0.0, article.quantity).deviation(p)[0]
    return H * 10 ** eps.reshape(H.shape)


def difference_noise(eps, window: int = 15) -> np.ndarray:
    """Noise ``E|eps|^2`` per value from the differences of adjacent lines (difference-based estimate).

    Measurement noise is independent from line to line; a model error is
    correlated over neighbouring lines. The half squared difference of
    adjacent residuals, ``|eps_k - eps_k+1|^2 / 2``, keeps the noise and
    cancels most of a smooth model error; its running median over ``window``
    lines of the pair, over ln 2 (exponential distribution), is the local
    noise (robust to the few lines where a sharp misfit does not cancel).

    Parameters
    ----------
    eps : (n_f, n_out, n_in) complex residual on ascending lines

    Returns
    -------
    (n_f, n_out, n_in) float
    """
    from scipy.ndimage import uniform_filter1d

    e = np.asarray(eps)
    if e.shape[0] < 3:
        return np.abs(e) ** 2
    d = np.abs(np.diff(e, axis=0)) ** 2 / 2
    d = np.concatenate([d, d[-1:]], axis=0)
    return uniform_filter1d(d, size=min(window, d.shape[0]), axis=0, mode="nearest")


def _expected(article: Article, channels, H, eps):
    """(E|eps|^2 per value, source): the per-line standard errors, else the estimate from the test lines.

    Without standard errors (e.g. run files imported from UFF58), the
    standard errors estimated from the test lines themselves
    (:func:`calibration.estimate_std_error`, the same floor the hold-out
    prints): it needs neither the identification (whose own misfit would pass
    for noise) nor the model (a model error must not raise its own floor).
    Articles built without that estimate fall back to
    :func:`difference_noise` of the residual.
    """
    se, src = floor_std_error(article, channels)
    if se is not None:
        return expected_from_std_error(H, se), src
    return difference_noise(eps), "adjacent-line differences of the residual (no standard errors)"


def _frequency_scatter(modes_per) -> list:
    """Per article, per identified mode: standard deviation (Hz) of its frequency over the articles
    (nearest mode within 5 % in each other article); zeros with one article."""
    out = []
    for a, ma in enumerate(modes_per):
        s = np.zeros(len(ma.frequency_hz))
        if len(modes_per) > 1:
            for k, f in enumerate(ma.frequency_hz):
                fs = [f]
                for b, mb in enumerate(modes_per):
                    if b != a and len(mb.frequency_hz):
                        j = np.argmin(np.abs(mb.frequency_hz - f))
                        if abs(mb.frequency_hz[j] / f - 1) < 0.05:
                            fs.append(mb.frequency_hz[j])
                s[k] = np.std(fs, ddof=1) if len(fs) > 1 else 0.0
        out.append(s)
    return out


def member_residual(camp: Campaign, load, articles, member, cfg=None, model=None):
    """Is there anything to explain for one calibrated member? (:func:`calibration.residual_check`).

    Parameters
    ----------
    camp : Campaign ; load : LoadResult (channel/drive geometry for the drive points)
    articles : identified articles ; member : MemberCalibration
    cfg : DiagnosisSection (default: the campaign's)
    model : (Surrogate, x, damping), optional
        Another model of the member (e.g. extended by accepted effects);
        ``damping`` is (zeta per article, p_ref) or None (identified damping
        mapped by MAC); default the member's calibrated surrogate and p with
        the refinement's damping.

    Returns
    -------
    (ResidualCheck, list of per-article model FRFs on the raw lines and channels)
    """
    cfg = cfg or camp.diagnosis
    chans = _channels(camp)
    band = (camp.band.low_hz, camp.band.high_hz)
    arts = [articles[i] for i in member.articles]
    ref = member.refinement
    damping = None if ref is None else (ref.zeta, ref.p_zeta)
    sur, x = member.surrogate, member.p
    if model is not None:
        sur, x, damping = model
    items, models, sources, model_frfs, tests = [], [], set(), [], []
    geo_c = {t.name: t for t in load.channels}
    geo_d = {t.name: t for t in load.drives}
    modes_per = [identified_modes(a) for a in arts]
    scatter_hz = _frequency_scatter(modes_per)
    mode_rows, anti = [], []
    for k, a in enumerate(arts):
        rows = [a.channels.index(n) for n in chans]
        Ht = a.frf[:, rows]
        Hm = model_frf(sur, x, a, chans, damping, k, camp.calibration.zeta0,
                       camp.validation.mac_min, band)
        model_frfs.append(Hm)
        eps = log_deviation(Hm, Ht)
        q, src = _expected(a, chans, Ht, eps)
        sources.add(src)
        mask = pair_mask(a, chans, a.freq_hz.size)
        tests.append(Ht)
        items.append(ResidualItem(a.name, a.freq_hz, eps, q, mask))
        models.append(ident_frf(a, chans))
        mode_rows.extend(mode_residuals(sur, x, modes_per[k], a.name,
                                        mac_min=camp.validation.mac_min, band_hz=band,
                                        shift_threshold=cfg.shift_threshold, scatter_hz=scatter_hz[k]))
        pairs = [(c, d) for c, n in enumerate(chans) for d, dn in enumerate(a.drives)
                 if n in geo_c and dn in geo_d and geo_c[n].grid == geo_d[dn].grid
                 and abs(float(np.dot(geo_c[n].direction, geo_d[dn].direction))) > 0.99]
        anti.extend(antiresonances(a.name, a.freq_hz, Hm, Ht, pairs, chans, a.drives, mask=mask))
    sc = scatter_sd([a.freq_hz for a in arts], tests, models, [it.expected for it in items],
                    [it.mask for it in items])
    check = residual_check(items, chans, arts[0].drives, scatter=sc, band_hz=band, modes=tuple(mode_rows),
                           antiresonances=tuple(anti), ratio_threshold=cfg.ratio_threshold,
                           z_threshold=cfg.z_threshold, floor_source=" / ".join(sorted(sources)))
    return check, model_frfs


# ----------------------------------------------------------------------------- screening target


@dataclass(frozen=True)
class ScreeningTarget:
    """What the screening and the acceptance's fits compare the model with, per article, at zeta0 and at each
    continuation damping (the interface of :class:`frfcal.campaign._stages.EqualizeResult`).

    kind : "debiased" or "equalized" (``[diagnosis] target``)
    data : tuple of FitData, one per article, at zeta0
    continuation : tuple of (zeta, tuple of FitData per article)
    """

    kind: str
    data: tuple
    continuation: tuple = ()

    def member(self, idx):
        """(data, continuation) of the articles ``idx``, as :func:`calibration.screen` takes them."""
        return ([self.data[i] for i in idx],
                [(z, [d[i] for i in idx]) for z, d in self.continuation])


def debiased_data(article: Article, channels, zeta: float, grid_hz=None) -> FitData:
    """The article's raw lines on ``channels`` with its identified poles' damping raised to ``zeta``
    (:func:`calibration.debiased_target`), weighted per line by its share of log f.

    ``T = H_raw + H_id(max(zeta_id, zeta)) - H_id(zeta_id)``: the identified
    model enters only through the damping change of its own physical poles,
    so its misfit to the lines (the mass line below the first mode, a mode
    labelled negligible) cancels. The raw lines are uneven (dense at the
    resonances); :func:`calibration.log_frequency_weights` makes the sum over
    them a quadrature in log f, the measure of the equalized target's
    half-bandwidth grid. ``grid_hz``: thinned to the raw line nearest each of these frequencies
    (:func:`calibration.thinned_lines`).
    """
    from dataclasses import replace

    from calibration import debiased_target, log_frequency_weights, thinned_lines
    from frfcal.campaign._stages import raw_data

    raw = raw_data(article, channels)
    ident = article.identification
    if ident.model.n_in != len(article.drives):
        raise CalibrationError(f"article {article.name!r} ({article.path.name}): its identified model has "
                               f"{ident.model.n_in} inputs, the run file {len(article.drives)} drives "
                               f"{list(article.drives)}: [diagnosis] target = \"debiased\" needs one per drive "
                               "(use target = \"equalized\")")
    t = debiased_target(raw, ident, article.ident_channels, zeta)
    t = replace(t, weights=log_frequency_weights(t.freq_hz))
    return t if grid_hz is None else thinned_lines(t, grid_hz)


def screening_target(camp: Campaign, articles, eq) -> ScreeningTarget:
    """The screening's target of every article (``[diagnosis] target``): the equalize stage's data
    (``"equalized"``) or the debiased raw lines at zeta0 and at the continuation dampings (``"debiased"``)."""
    if camp.diagnosis.target == "equalized":
        return ScreeningTarget("equalized", tuple(eq.data), tuple(eq.continuation))
    from calibration import half_bandwidth_frequencies

    chans = camp.channels.calibrate
    c = camp.calibration
    data = tuple(debiased_data(a, chans, c.zeta0) for a in articles)
    thin = camp.diagnosis.continuation_lines == "half-bandwidth"

    def grid(z):  # [diagnosis] continuation_lines: a wider stage on its own half-bandwidth grid's nearest lines
        return half_bandwidth_frequencies(camp.band.low_hz, camp.band.high_hz, z, c.samples_per_half_bandwidth) \
            if thin and z > c.zeta0 else None

    cont = tuple((z, tuple(debiased_data(a, chans, z, grid(z)) for a in articles)) for z in c.continuation_zeta)
    return ScreeningTarget("debiased", data, cont)


# ----------------------------------------------------------------------------- nonlinearity


def _sweep_order(time_s) -> str:
    t = np.asarray(time_s, float)
    if t.size > 1 and np.all(np.isfinite(t)):
        dt = np.diff(t)
        return "up" if np.all(dt > 0) else "down" if np.all(dt < 0) else "unknown"
    return "unknown"


@dataclass(frozen=True)
class LevelRun:
    """One run file of an article as the nonlinearity gate sees it.

    article : str ; path : Path ; level : force level (N), None when unknown ; level_source : "campaign"
    (``[[run]] level``), "run file" (median achieved force over the valid lines, mean over drives) or
    "unknown" (the run file holds no force) ; sweep : "up"/"down"/"unknown"
    """

    article: str
    path: Path
    level: float | None
    level_source: str
    sweep: str


def _frf_level(a: Article, lr: LevelRun, band):
    from calibration import FRFLevel

    ln = a.lines
    f = np.asarray(ln.frequency_hz, float)
    use = np.asarray(ln.valid, bool) & (f >= band[0]) & (f <= band[1])
    se = None if ln.std_error is None else np.asarray(ln.std_error, float)[use]
    if se is not None and not (np.all(np.isfinite(se)) and np.all(se > 0)):
        se = None
    return FRFLevel(f[use], np.asarray(ln.frf)[use], lr.level, se, "N", a.quantity, a.path.name, lr.sweep)


def nonlinearity_gate(camp: Campaign, articles, log=print) -> dict:
    """The nonlinearity checks per article name, from the campaign's run files.

    Run files with the same article name are the same article: at two or more
    distinct force levels (``[[run]] level``, N, else the run's median achieved
    force; levels within 2 % are one level) they feed
    :func:`calibration.level_dependence` on the identified modes in the band;
    an up and a down sweep at one level feed :func:`calibration.sweep_direction`;
    every run's THD (when the run file has it) feeds :func:`calibration.distortion`
    (the run with the largest THD is reported).

    Returns
    -------
    dict article name -> (Nonlinearity or None, tuple of LevelRun, tuple of str notes)
    """
    from acquisition.runfile import read_run

    from calibration import distortion, level_dependence, nonlinearity, sweep_direction

    cfg = camp.diagnosis
    lo = camp.identification.low_hz or 0.8 * camp.band.low_hz
    hi = camp.identification.high_hz or 1.25 * camp.band.high_hz
    by_name: dict = {}
    for i, a in enumerate(articles):
        by_name.setdefault(a.name, []).append(i)
    out = {}
    for name, idx in by_name.items():
        runs, dist, notes = [], [], []
        for i in idx:
            a, entry = articles[i], camp.run[i]
            run = read_run(a.path)
            ok = np.asarray(run.valid, bool)
            if entry.level is not None:
                lvl, src = float(entry.level), "campaign"
            else:
                fn = np.asarray(run.force_n, float)[ok]
                lvl = float(np.median(np.mean(np.abs(fn), axis=1))) if fn.size else float("nan")
                lvl, src = (lvl, "run file") if np.isfinite(lvl) and lvl > 0 else (None, "unknown")
            runs.append(LevelRun(name, a.path, lvl, src, _sweep_order(np.asarray(run.time_s, float)[ok])))
            thd = np.asarray(run.thd, float)
            if thd.size and np.any(np.isfinite(thd) & (thd > 0)):
                modal = a.identification.modal
                dist.append(distortion(run.frequency_hz, thd, channels=[s.name for s in run.sensors]
                                       + [d.name for d in run.drives], threshold=cfg.thd_threshold,
                                       modes_hz=modal.frequency_hz, damping=modal.damping, label=a.path.name))
        level = sweep = None
        good = [k for k, r in enumerate(runs) if r.level is not None]
        distinct = []
        for k in sorted(good, key=lambda k: runs[k].level):
            if not distinct or runs[k].level > 1.02 * runs[distinct[-1]].level:
                distinct.append(k)
        if len(distinct) >= 2:
            a0 = articles[idx[distinct[0]]]
            modal = a0.identification.modal
            fm = [f for f in modal.frequency_hz if camp.band.low_hz <= f <= camp.band.high_hz]
            try:
                level = level_dependence([_frf_level(articles[idx[k]], runs[k], (lo, hi)) for k in distinct],
                                         fm or None, z_threshold=cfg.nonlinearity_z)
            except CalibrationError as exc:
                notes.append(f"{name}: level dependence not evaluated: {exc}")
        elif len(idx) == 1:
            notes.append(f"{name}: one run file: no level-dependence check")
        else:
            notes.append(f"{name}: {len(idx)} run files at {len(distinct)} distinct known force level(s): "
                         "no level-dependence check")
        ups = [k for k in good if runs[k].sweep == "up"]
        downs = [k for k in good if runs[k].sweep == "down"]
        pair = next(((u, d) for u in ups for d in downs if abs(runs[u].level / runs[d].level - 1) < 0.02), None)
        if pair is not None:
            try:
                sweep = sweep_direction(*(_frf_level(articles[idx[k]], runs[k], (lo, hi)) for k in pair),
                                        z_threshold=cfg.nonlinearity_z)
            except CalibrationError as exc:
                notes.append(f"{name}: sweep direction not evaluated: {exc}")
        worst = max(dist, key=lambda d: (d.flagged, np.nanmax(d.max_thd))) if dist else None
        verdict = None
        if level is not None or worst is not None or sweep is not None:
            verdict = nonlinearity(level, worst, sweep)
        for n in notes:
            log(n)
        out[name] = (verdict, tuple(runs), tuple(notes))
    return out


# ----------------------------------------------------------------------------- the stage


@dataclass(frozen=True)
class ArticleGate:
    """The nonlinearity gate of one article (all its run files).

    nonlinearity : calibration.Nonlinearity or None (no check possible: one level,
    no THD, no up/down pair) ; runs : tuple of LevelRun ; notes : why a check was not run
    """

    article: str
    nonlinearity: object | None
    runs: tuple
    notes: tuple = ()

    def to_dict(self) -> dict:
        return {"article": self.article,
                "nonlinearity": None if self.nonlinearity is None else self.nonlinearity.to_dict(),
                "runs": [{"path": str(r.path), "level_n": r.level, "level_source": r.level_source,
                          "sweep": r.sweep} for r in self.runs],
                "notes": list(self.notes)}


@dataclass(frozen=True)
class MemberDiagnosis:
    """One ensemble member's diagnosis.

    Attributes
    ----------
    label : str ; articles : tuple of article names
    verdict : one of VERDICTS ; reason : the verdict in one sentence
    residual : calibration.ResidualCheck of the calibrated model
    nonlinear_modes : tuple of dict (article, mode, frequency_hz, quantity, levels, values, ratio, z)
    sd : dict, SD of the calibrated model (key "before") on calibration (raw lines), hold-out and
        cross-validation, beside the floor; key "after" with an accepted effect
    channels : tuple of str, the most affected channels (largest residual ratio first)
    n_candidates : dict family -> number of candidates screened (None: not screened)
    ranked : tuple of dict, the top of the screening (:func:`ranked_table`)
    screening : calibration.Screening or None
    accepted : tuple of dict, the accepted effects (rows of :func:`ranked_table` re-fitted, with the decision)
    trials : tuple of dict, every recalibration tried (names, c, hold-out before/after, decision)
    extended : tuple of femodel.Candidate or None, the accepted candidates (their terms extend the deck)
    x_extended : ([p, c]) of the extended model or None
    overlay : dict or None, FRFs of the first article at the most affected channels (:func:`overlay_figure`):
        article, freq_hz (n_f,), channels, drives, test, before, after ((n_f, k, n_in) complex; after None
        without an accepted effect)
    """

    label: str
    articles: tuple
    verdict: str
    reason: str
    residual: object
    nonlinear_modes: tuple = ()
    sd: dict | None = None
    channels: tuple = ()
    n_candidates: dict | None = None
    ranked: tuple = ()
    screening: object | None = None
    accepted: tuple = ()
    trials: tuple = ()
    extended: tuple | None = None
    x_extended: np.ndarray | None = None
    overlay: dict | None = None

    def to_dict(self) -> dict:
        return {"member": self.label, "articles": list(self.articles), "verdict": self.verdict,
                "reason": self.reason, "residual": self.residual.to_dict(),
                "nonlinear_modes": [dict(m) for m in self.nonlinear_modes], "sd": self.sd,
                "most_affected_channels": list(self.channels), "candidates": self.n_candidates,
                "ranked": [dict(r) for r in self.ranked],
                "screening": None if self.screening is None else {
                    k: v for k, v in self.screening.to_dict().items() if k != "candidates"},
                "accepted": [dict(a) for a in self.accepted], "trials": [dict(t) for t in self.trials]}


@dataclass(frozen=True)
class DiagnosisResult:
    """The diagnose stage: the nonlinearity gate per article and the diagnosis per ensemble member."""

    gates: tuple  # of ArticleGate
    members: tuple  # of MemberDiagnosis
    separations: tuple = ()  # of dict: accepted effects fitted per article against the article groups

    def to_dict(self) -> dict:
        return {"gates": [g.to_dict() for g in self.gates], "members": [m.to_dict() for m in self.members],
                "separations": [dict(x) for x in self.separations],
                "separating_effects": [x["name"] for x in self.separations if x["separates"]]}


def _sd_table(member, val, xval, check, arts=()) -> dict:
    """SD of the calibrated model on calibration (raw lines), hold-out, cross-validation, beside the floor."""
    ref = member.refinement
    v = val.validation if val is not None else None
    cv = xval.crossvalidation if xval is not None else None
    return {
        "calibration_raw": None if ref is None else float(ref.sd_raw),
        "calibration_equalized": float(member.cycle.sd),
        "holdout": None if v is None else float(v.sd_calibrated),
        "holdout_floor": None if v is None or v.sd_floor is None else float(v.sd_floor),
        "crossvalidation_rse": None if cv is None else float(cv.rse),
        "residual_all_channels": float(check.sd),
        "floor": float(check.floor),
        "floor_source": check.floor_source,
        "scatter": float(check.scatter),
        "identification_fit": float(np.mean([a.identification.fit_deviation_total for a in arts])) if arts else None,
    }


def _nonlinear_modes(gate: ArticleGate) -> list:
    nl = gate.nonlinearity
    if nl is None:
        return []
    rows = [{"article": gate.article, "check": "level dependence", "mode": c.mode, "frequency_hz": c.frequency_hz,
             "quantity": c.quantity, "levels_n": list(c.levels), "values": list(c.values), "ratio": c.ratio,
             "z": c.z} for c in nl.modes]
    if nl.level is not None:  # the model-free FRF difference between levels, where it is largest
        fm = np.asarray(nl.level.modes_hz, float)
        rows += [{"article": gate.article, "check": "FRF level difference", "frequency_hz": p.peak_hz,
                  "nearest_mode_hz": float(fm[np.argmin(np.abs(fm - p.peak_hz))]) if fm.size else None,
                  "levels_n": [p.level_low, p.level_high], "z": p.z} for p in nl.level.pairs
                 if p.flagged and np.isfinite(p.peak_hz)]
    if nl.distortion is not None:
        for x in nl.distortion.lines:
            rows.append({"article": gate.article, "check": "harmonic distortion", "mode": x.mode,
                         "frequency_hz": x.frequency_hz, "channel": x.channel, "thd": x.thd, "relation": x.relation})
    if nl.sweep is not None:
        for b in nl.sweep.bands:
            rows.append({"article": gate.article, "check": "sweep direction", "frequency_hz": b.peak_up_hz,
                         "band_hz": [b.f_low_hz, b.f_high_hz], "z": b.max_z})
    return rows


def _screen_member(camp: Campaign, pm, model, load, eq, m, quantity, log, executor=None):
    """Candidates of the deck and set-up, screened on the member's equalized data (with continuation)."""
    from calibration import build_surrogate, screen
    from femodel import candidate_regions

    c, cfg = camp.calibration, camp.diagnosis
    lo, hi = camp.band.low_hz, camp.band.high_hz
    t0 = time.perf_counter()
    cands, terms, cctx = member_candidates(camp, pm, load, m.p, log)
    zoom = point_zoom(cctx, pm, m.p, cands, terms)
    sur, T = m.surrogate, m.basis
    if T is None:  # not stored: rebuilt at the calibrated point
        sur, T = build_surrogate(model, m.p, (lo, hi), c.basis_factor, enrich=c.enrich)
    data, cont = eq.member(m.articles)
    scr = screen(sur, T, m.p, data, c.zeta0, terms, pm.lower, pm.upper, quantity=quantity, model=model, n_check=cfg.top_n,
                 shift_hz=max(lo / 4.0, hi / 50.0), continuation=cont, max_nfev=cfg.max_evaluations,
                 executor=executor, groups=[cd.family for cd in cands], zoom=zoom,
                 zoom_rounds=cctx.options.zoom_rounds, regions=candidate_regions(cands))
    counts: dict = {}
    for cd in cands:
        counts[cd.family] = counts.get(cd.family, 0) + 1
    rows = ranked_table(cands, scr)
    ctx = dict(cands=cands, terms=terms, sur=sur, T=T, data=data, cont=cont, screening=scr, zoom=zoom,
               zoom_rounds=cctx.options.zoom_rounds, cctx=cctx, screening_now=scr)
    log(f"[{m.label}] screened {len(cands)} candidates ({len(scr.zoomed)} of them zoomed) in "
        f"{time.perf_counter() - t0:.1f} s; first: "
        + "; ".join(f"{r['family']} {r['name']} ({r['size']}, explained {100 * r['explained']:.1f} %)"
                    for r in rows[:3]))
    return counts, rows, scr, ctx


def _overlay(camp, article: Article, channels, before, after) -> dict:
    """Test and model FRFs of one article at ``channels`` (before: calibrated model; after: extended)."""
    allc = _channels(camp)
    idx = [allc.index(c) for c in channels]
    rows = [article.channels.index(c) for c in channels]
    return {"article": article.name, "quantity": article.quantity, "freq_hz": article.freq_hz,
            "channels": list(channels), "drives": list(article.drives), "test": article.frf[:, rows],
            "before": before[:, idx], "after": None if after is None else after[:, idx]}


def overlay_figure(overlay: dict, title: str = ""):
    """FRF overlays before/after at the most affected channels: |H| of test, calibrated and extended model.

    Returns
    -------
    matplotlib.figure.Figure (one row per channel, the first drive of each; log |H| over Hz)
    """
    from matplotlib.figure import Figure

    ch = overlay["channels"]
    f = np.asarray(overlay["freq_hz"])
    fig = Figure(figsize=(8, 2.2 * len(ch) + 0.6))
    axes = fig.subplots(len(ch), 1, sharex=True, squeeze=False)[:, 0]
    for k, (ax, name) in enumerate(zip(axes, ch)):
        d = 0
        ax.semilogy(f, np.abs(overlay["test"][:, k, d]), ".", ms=2, color="0.3", label="test (raw lines)")
        ax.semilogy(f, np.abs(overlay["before"][:, k, d]), "-", lw=0.9, color="C3", label="calibrated model")
        if overlay.get("after") is not None:
            ax.semilogy(f, np.abs(overlay["after"][:, k, d]), "-", lw=0.9, color="C0",
                        label="with the accepted effect(s)")
        ax.set_ylabel(f"|H| {name}/{overlay['drives'][d]}")
        ax.grid(True, which="both", lw=0.3)
    axes[0].legend(loc="best", fontsize=7)
    axes[-1].set_xlabel("frequency [Hz]")
    fig.suptitle(title or f"{overlay['article']}: most affected channels ({overlay['quantity']})")
    return fig


def _lines_per_bandwidth(article: Article) -> float:
    """Median number of raw lines within one half-power bandwidth of the identified modes in band (>= 1)."""
    m = article.identification.modal
    f = article.freq_hz
    n = [np.sum((f >= fr * (1 - z)) & (f <= fr * (1 + z))) for fr, z in zip(m.frequency_hz, m.damping)
         if f.min() <= fr <= f.max()]
    return float(max(np.median(n), 1.0)) if n else 1.0


def _holdout(camp, articles, m, sur, x, quantity):
    """Hold-out SD of (sur, x) on the raw hold-out lines (calibration lines without hold-out channels), with
    the identified damping mapped by MAC (the same footing before and after an effect), and its value count."""
    from calibration import validate

    from frfcal.campaign._stages import raw_data

    chans = list(camp.channels.holdout) or list(camp.channels.calibrate)
    arts = [articles[i] for i in m.articles]
    v = validate(sur, sur, x, [raw_data(a, chans) for a in arts], [identified_modes(a) for a in arts],
                 camp.calibration.zeta0, None, camp.validation.mac_min, quantity,
                 (camp.band.low_hz, camp.band.high_hz))
    return float(v.sd_calibrated), int(v.n_values)


def _cv(camp, sur, data, x, lower, upper, quantity, executor):
    from calibration import cross_validate

    xv = camp.crossvalidation
    n = max(xv.realizations, 3)
    return cross_validate(sur, data, x, lower, upper, camp.calibration.zeta0, n, xv.seed, executor, quantity,
                          xv.max_evaluations)


def _holdout_floor(camp, check) -> float:
    hold_chans = list(camp.channels.holdout) or list(camp.channels.calibrate)
    rows = [x for x in check.channels if x.label in hold_chans]
    n = sum(x.n_values for x in rows)
    return float(sum(x.expected * x.n_values for x in rows) / n) if n else float(check.floor)


def _overlap(ctx, name_a: str, name_b: str) -> bool:
    """Whether two candidates are element-subset factors sharing an element (a model cannot hold both)."""
    cands = {cd.name: cd.term for cd in ctx["cands"]}
    a, b = cands.get(name_a), cands.get(name_b)
    ea, eb = getattr(a, "elements", None), getattr(b, "elements", None)
    return ea is not None and eb is not None and bool(set(ea) & set(eb))


def _accept_member(camp, load, pm, model, articles, m, check, rows, ctx, quantity, executor, log):
    """Recalibrate with the top candidates (singly, then greedily combined), accept by hold-out and
    cross-validation beyond their scatter with a per-parameter penalty, stop at the floor.

    Returns (accepted rows, trials (dicts), sd after (dict or None), fit of the accepted set or None)."""
    from calibration import accept, fit_with

    cfg, c = camp.diagnosis, camp.calibration
    lo, hi = camp.band.low_hz, camp.band.high_hz
    shift = max(lo / 4.0, hi / 50.0)
    sur, T, data, cont = ctx["sur"], ctx["T"], ctx["data"], ctx["cont"]
    by_name = {t.name: t for t in ctx["terms"]}
    arts = [articles[i] for i in m.articles]
    # the floor of the hold-out comparison: the residual check's expected |eps|^2 on the hold-out channels
    # (re-estimated with every accepted effect: the adjacent-line estimate shrinks with the model error)
    floor = _holdout_floor(camp, check)
    check_after = None
    hb, n_vals = _holdout(camp, articles, m, m.surrogate, m.p, quantity)
    n_res = max(int(n_vals / np.mean([_lines_per_bandwidth(a) for a in arts])), 2)
    cv_b = _cv(camp, sur, data, m.p, pm.lower, pm.upper, quantity, executor)
    base = {"holdout": hb, "cv": cv_b, "x": m.p}
    accepted, trials, fit_acc, refined = [], [], None, None
    order = _tried(ctx["cands"], ctx["screening"])
    order += _compounds(ctx, ctx["screening"], order)
    starts: dict = {}  # candidate -> (p, c of the accepted effects and its own) from the re-screening's check
    screened_after = None
    n_effects = 0  # a compound effect (several terms) counts once against max_effects
    for _ in range(cfg.max_effects):
        by_name = {t.name: t for t in ctx["terms"]}  # the re-screening's zoom may have added candidates
        best = None
        for r in order:
            new = list(r.get("members", [r["name"]]))
            if any(n == a["name"] or _overlap(ctx, n, a["name"]) for n in new for a in accepted):
                continue  # the same effect, or an element subset sharing elements with an accepted one
            names = [a["name"] for a in accepted] + new
            p0, c0 = starts.get(r["name"], (m.p, [a["c"] for a in accepted] + list(r.get("member_c", [r["c"]]))))
            # a single candidate the screening re-fitted (same data, stages and extension) goes on from its
            # converged check: only the final stage runs, to fit_with's tolerance
            warm = ctx["screening"].check(r["name"]) if not accepted and "members" not in r else None
            fit = fit_with(sur, T, model, [by_name[n] for n in names], data, c.zeta0, pm.lower, pm.upper,
                           p0=p0, c0=c0, continuation=cont, quantity=quantity, shift_hz=shift,
                           max_nfev=cfg.max_evaluations, warm=warm, with_basis=False)
            ha, _ = _holdout(camp, articles, m, fit.surrogate, fit.x, quantity)
            trial = {"names": names, "c": fit.c.tolist(), "sd_equalized": fit.sd, "holdout_before": base["holdout"],
                     "holdout_after": ha}
            if "members" in r:
                trial["effect"] = r["name"]
            if screened_after is not None:
                trial["screened_after"] = screened_after
            if best is None or ha < best[1]:
                best = (r, ha, fit, trial)
            trials.append(trial)
        if best is None:
            break
        best = _tied_places(camp, articles, m, model, pm, ctx, accepted, best, trials, quantity, log)
        best = _contact_shape(camp, articles, m, model, pm, ctx, accepted, best, trials, quantity, log)
        r, ha, fit, trial = best
        new = list(r.get("members", [r["name"]]))
        check_try = member_residual(camp, load, articles, m, model=(fit.surrogate, fit.x, None))[0]
        floor = min(floor, _holdout_floor(camp, check_try))
        cv_a = _cv(camp, fit.surrogate, data, fit.x, fit.lower, fit.upper, quantity, executor)
        dec = accept(base["holdout"], ha, base["cv"].sd_test, cv_a.sd_test, floor, len(new), n_res)
        trial.update(decision=dec.to_dict(), cv_before=float(base["cv"].rse), cv_after=float(cv_a.rse))
        log(f"[{m.label}] {' + '.join(trial['names'])}: hold-out SD {base['holdout']:.4g} -> {ha:.4g}, "
            f"cross-validation {base['cv'].rse:.4g} -> {cv_a.rse:.4g}: "
            f"{'ACCEPTED' if dec.accepted else 'not accepted'} ({dec.reason})")
        if not dec.accepted:
            break
        accepted = [dict(a) for a in accepted] + [dict(x) for x in (r["member_rows"] if "members" in r else [r])]
        for a, cj in zip(accepted, fit.c):  # the earlier effects re-fitted together with the new one(s)
            cd = ctx["cands"][[cd.name for cd in ctx["cands"]].index(a["name"])]
            a["c"] = float(cj)
            a["value"], a["unit"], a["size"] = _physical(cd.term, float(cj))
        for a in accepted[len(accepted) - len(new):]:
            a["decision"] = dec.to_dict()
            if "members" in r:
                a["effect"] = r["name"]
        n_effects += 1
        base, fit_acc, check_after = {"holdout": ha, "cv": cv_a, "x": fit.x}, fit, check_try
        if dec.stop or n_effects >= cfg.max_effects:
            break
        # the floor on its own footing: the accepted set refined on the raw lines (estimated damping, as the
        # "after"); a residual inside the floor there has nothing left to explain (the equalized hold-out of
        # the comparison above carries the identification's error and never reaches the floor)
        refined = (tuple(a["name"] for a in accepted),
                   _refined(camp, pm, model, articles, m, fit, _terms_of(ctx, accepted), quantity, log))
        ref = refined[1][0]
        damping = None if ref is None else (ref.zeta, ref.p_zeta)
        check_ref = member_residual(camp, load, articles, m, model=(refined[1][3], refined[1][2], damping))[0]
        trial["residual_refined"] = {"significant": bool(check_ref.significant), "ratio": float(check_ref.ratio)}
        if not check_ref.significant:
            log(f"[{m.label}] refined with {' + '.join(refined[0])}: the residual is inside the floor "
                f"(ratio {check_ref.ratio:.3g}): no further effect is looked for")
            break
        # re-screen the other candidates on the model extended by the accepted effects: an effect that only
        # stands out once the first is in (a weaker second term the first absorbed) enters the combination
        order, starts = _rescreen(camp, model, m, ctx, fit, [a["name"] for a in accepted], quantity, executor, log)
        screened_after = [a["name"] for a in accepted]
    after = None
    if fit_acc is not None:
        if refined is not None and refined[0] == tuple(a["name"] for a in accepted):
            ref, h_ref, x_ref, sur_ref = refined[1]  # the last accepted set was refined for the floor check
        else:
            ref, h_ref, x_ref, sur_ref = _refined(camp, pm, model, articles, m, fit_acc, _terms_of(ctx, accepted),
                                                  quantity, log)
        damping = None if ref is None else (ref.zeta, ref.p_zeta)
        check_after, frfs_after = member_residual(camp, load, articles, m, model=(sur_ref, x_ref, damping))
        floor = min(floor, _holdout_floor(camp, check_after))
        after = {"holdout_refined": h_ref, "calibration_raw": None if ref is None else float(ref.sd_raw),
                 "holdout": base["holdout"], "crossvalidation_rse": float(base["cv"].rse),
                 "calibration_equalized": float(fit_acc.sd), "holdout_before_same_footing": hb,
                 "crossvalidation_rse_before": float(cv_b.rse), "floor_holdout": floor,
                 "holdout_floor_ratio": (h_ref if h_ref is not None else base["holdout"]) / floor
                 if floor > 0 else None,
                 "n_independent_residuals": n_res, "residual": check_after.to_dict(),
                 "p_refined": dict(zip(pm.names, np.asarray(x_ref[:pm.n_params], float).tolist()))}
        n_p = pm.n_params
        idf = None
        t_idf = time.perf_counter()
        if ref is not None:  # what the raw lines tell of the refined sizes (the calibrate stage's identifiability)
            idf = effect_identifiability(camp, arts, sur_ref, x_ref, ref, fit_acc.lower, fit_acc.upper,
                                         list(pm.names) + [a["name"] for a in accepted], quantity, pm.n_params)
        for j, a in enumerate(accepted):  # the refined magnitudes (raw lines, estimated damping) are reported
            cd = ctx["cands"][[cd.name for cd in ctx["cands"]].index(a["name"])]
            a["c_equalized"], a["c"] = a["c"], float(x_ref[n_p + j])
            a["value"], a["unit"], a["size"] = _physical(cd.term, a["c"])
            if idf is not None:
                a.update(_size_uncertainty(idf, n_p + j, a["c"]))
                log(f"[{m.label}] {a['name']}: refined size {a['size']}, "
                    + (f"standard deviation from the noise {a['size_std_percent']:.3g} % (model error not "
                       "included)" if a["size_std_percent"] is not None else "standard deviation not resolved")
                    + ("" if a["size_identifiable"] else f": {a['size_identifiability']}")
                    + f" ({time.perf_counter() - t_idf:.1f} s)")
        # an effect accepted on the screening's target may be refined on the raw lines to a size the data do not
        # see (a spring at 1e-37 N/m): dropped, and reported as such
        sizes = refined_sizes(camp, arts, sur_ref, x_ref, damping, n_p, accepted, n_res, quantity,
                              sur_without=fit_acc.surrogate)
        n_fitted = len(accepted)
        accepted, dropped, x_kept = drop_negligible(accepted, sizes, x_ref, n_p)
        if dropped:
            after["negligible"] = dropped
            for a in dropped:
                z = a["refined_effect"]
                log(f"[{m.label}] {a['name']} refined to {a['size']}: negligible (without it the hold-out SD is "
                    f"x{1 / z['ratio']:.4f}, less than the penalty x{1 / z['penalty_ratio']:.4f} of one "
                    f"parameter; largest mode shift {z['max_mode_shift']:.2e}): dropped")
        fit_acc = (fit_acc, x_kept, frfs_after, n_fitted)
    return tuple(accepted), tuple(trials), after, fit_acc


def _tied_places(camp, articles, m, model, pm, ctx, accepted, best, trials, quantity, log):
    """The place of a point effect where the screening cannot tell: the candidates of the best trial's point
    family and kind (``femodel.POINT_FAMILIES``: a ground spring's component, a lumped mass) whose linear
    screening score lies within the linear score's own error of the best's, measured at the best by its
    nonlinear check (|explained re-fitted - explained linear|), are recalibrated too (``fit_with`` as the
    acceptance's trials: from the member's point through the continuation stages; at most ``zoom_grids``, best
    linear score first), and the lowest hold-out SD wins (the acceptance's footing).

    Why: a zoom chain takes one nonlinear check (its best linear score), and the acceptance tries only checked
    candidates; where the scores tie (springs to ground near a free edge: 14.4-14.7 % linear, 17.3-17.6 %
    re-fitted, a 3 % linearization error) the check goes to any of them. On the shell the true spring's grid
    was never tried and one 2.5 element sizes away was accepted (+40 %); tried, the truth's grid has the lower
    hold-out SD.

    Returns ``best`` (row, hold-out, fit, trial), replaced when a tied place has a lower hold-out SD; the row
    then carries ``located_from`` (the screened candidate it replaced) and ``tied`` (the places tried, with
    their hold-out SD). Every place tried is appended to ``trials`` (``tied_with``)."""
    from calibration import fit_with
    from femodel import POINT_FAMILIES

    r, ha, fit, trial = best
    cctx, scr = ctx.get("cctx"), ctx.get("screening_now")
    if "members" in r or cctx is None or scr is None or r["family"] not in POINT_FAMILIES:
        return best
    chk = scr.check(r["name"])
    if chk is None:
        return best
    cands = {cd.name: cd for cd in ctx["cands"]}
    me = cands[r["name"]]
    pf = POINT_FAMILIES[me.family]
    kind = pf.key(me)
    k_me = scr.names.index(r["name"])
    band = abs(float(chk.explained) - float(chk.explained_linear))
    lin = scr.explained
    done = {n for t in trials for n in t["names"][len(accepted):] if len(t["names"]) == len(accepted) + 1}
    tied = [k for k in np.argsort(-lin, kind="stable")
            if lin[k] > 0 and lin[k] >= lin[k_me] - band and scr.names[k] not in done and scr.names[k] in cands
            and cands[scr.names[k]].family == me.family and len(cands[scr.names[k]].grids) == 1
            and pf.key(cands[scr.names[k]]) == kind][:cctx.options.zoom_grids]
    if not tied:
        return best
    cfg, c = camp.diagnosis, camp.calibration
    shift = max(camp.band.low_hz / 4.0, camp.band.high_hz / 50.0)
    by_name = {t.name: t for t in ctx["terms"]}
    acc_names = [a["name"] for a in accepted]
    rows = {x["name"]: x for x in ranked_table(ctx["cands"], scr, n=len(scr.names))}
    t0 = time.perf_counter()
    out = [(r["name"], ha)]
    for k in tied:
        name = scr.names[k]
        # as the acceptance's own trials: from the member's point through the continuation stages (a start at
        # the best's fitted point, where the parameters absorbed part of the effect at its place, favours it)
        f2 = fit_with(ctx["sur"], ctx["T"], model, [by_name[n] for n in acc_names + [name]], ctx["data"], c.zeta0,
                      pm.lower, pm.upper, p0=m.p, c0=[a["c"] for a in accepted] + [float(scr.c_linear[k])],
                      continuation=ctx["cont"], quantity=quantity, shift_hz=shift, max_nfev=cfg.max_evaluations,
                      with_basis=False)
        h2, _ = _holdout(camp, articles, m, f2.surrogate, f2.x, quantity)
        t2 = {"names": acc_names + [name], "c": f2.c.tolist(), "sd_equalized": f2.sd,
              "holdout_before": trial["holdout_before"], "holdout_after": h2, "tied_with": r["name"]}
        if "screened_after" in trial:
            t2["screened_after"] = trial["screened_after"]
        trials.append(t2)
        out.append((name, h2))
        if h2 < best[1]:
            best = (dict(rows[name], located_from=r["name"]), h2, f2, t2)
    log(f"[{m.label}] {r['name']}: {len(tied)} place(s) tied with it in the screening (linear score within "
        f"{100 * band:.2g} % of its {100 * lin[k_me]:.3g} %) recalibrated in {time.perf_counter() - t0:.1f} s; "
        f"lowest hold-out SD: {best[0]['name']} ({best[1]:.4g}; {r['name']} {ha:.4g})")
    best[0]["tied"] = [{"name": n, "grids": list(cands[n].grids), "holdout_after": h} for n, h in out]
    return best


def _contact_shape(camp, articles, m, model, pm, ctx, accepted, best, trials, quantity, log,
                   keep_fraction: float = 0.2, gain: float = 0.9):
    """Which pairs of the best trial's contact candidate touch: a rate per pair, fitted together, and the
    pairs that carry one as one candidate, kept when its hold-out SD is lower.

    The contact family offers cells, windows and unions of a patch size (several element sizes); a gap that
    closes on fewer pairs (a line of a few) is then best matched by a window that also holds pairs that do
    not touch, and the fit stays above the floor. A shape zoom by the linear score cannot tell the shapes
    apart (docs/diagnosis.md: the score at c = 0 of an effect that moves modes by many bandwidths), so the
    shape is fitted: each pair of the best candidate (3 to 2 ``zoom_grids`` pairs) becomes its own spring
    term (scale from its own stiffness), all fitted with the existing parameters and the accepted effects
    (``fit_with`` from the best trial's point, rates >= 0: a non-negative fit, which leaves the pairs that
    do not touch at zero; pairs an accepted contact holds are left out); the pairs whose rate exceeds
    ``keep_fraction`` of the largest make one candidate (one common rate, ``<name>_shape``), recalibrated
    as the acceptance's trials (from the member's point through the continuation stages). It replaces the
    best when its hold-out SD is below ``gain`` times the best's (a subset of a contact that closes
    everywhere must not win on the noise); the row then carries ``shaped_from`` and the per-pair rates
    (``pair_rates``). Every fit is appended to ``trials``.
    """
    from calibration import fit_with
    from femodel import candidate_pairs, contact_on_pairs

    r, ha, fit, trial = best
    cctx = ctx.get("cctx")
    if "members" in r or cctx is None or r["family"] != "contact_spring":
        return best
    cands = {cd.name: cd for cd in ctx["cands"]}
    me = cands[r["name"]]
    # the pairs an accepted contact holds already are not fitted again (two terms on one pair: one rate)
    held = {pr for a in accepted if cands[a["name"]].family == "contact_spring"
            for pr in candidate_pairs(cands[a["name"]])}
    pairs = [pr for pr in candidate_pairs(me) if pr not in held]
    if not 3 <= len(pairs) <= 2 * cctx.options.zoom_grids:
        return best
    taken = set(cctx.used_names) | set(cands)
    singles = [(pr, cd) for k, pr in enumerate(pairs) if f"{me.name}_pair{k + 1}" not in taken
               for cd in [contact_on_pairs(cctx, me, [pr], f"{me.name}_pair{k + 1}")] if cd is not None]
    fitted = [pr for pr, _ in singles]  # the pairs with a term of their own
    singles = [cd for _, cd in singles]
    name = next(f"{me.name}_shape{'' if k == 0 else k + 1}" for k in range(len(taken) + 1)
                if f"{me.name}_shape{'' if k == 0 else k + 1}" not in taken)
    if len(singles) < 3:
        return best
    cfg, c = camp.diagnosis, camp.calibration
    shift = max(camp.band.low_hz / 4.0, camp.band.high_hz / 50.0)
    by_name = {t.name: t for t in ctx["terms"]}
    acc_names = [a["name"] for a in accepted]
    acc_terms = [by_name[n] for n in acc_names]
    t0 = time.perf_counter()
    rate = float(fit.c[-1]) * float(me.term.scale)  # the best's rate per pair (N/m)
    f_all = fit_with(ctx["sur"], ctx["T"], model, acc_terms + [candidate_term(pm, cd, m.p) for cd in singles],
                     ctx["data"], c.zeta0, pm.lower, pm.upper, p0=fit.p,
                     c0=[a["c"] for a in accepted] + [rate / float(cd.term.scale) for cd in singles],
                     quantity=quantity, shift_hz=shift, max_nfev=cfg.max_evaluations, with_basis=False)
    rates = np.asarray(f_all.c[len(accepted):], float) * np.array([float(cd.term.scale) for cd in singles])
    pair_rates = [{"pair": list(pr), "rate_N_per_m": float(k)} for pr, k in zip(fitted, rates)]
    h_all, _ = _holdout(camp, articles, m, f_all.surrogate, f_all.x, quantity)
    trials.append({"names": acc_names + [cd.name for cd in singles], "c": f_all.c.tolist(), "sd_equalized": f_all.sd,
                   "holdout_before": trial["holdout_before"], "holdout_after": h_all, "shape_of": r["name"],
                   "pair_rates": pair_rates})
    keep = rates > keep_fraction * rates.max() if rates.max() > 0 else np.zeros(rates.size, bool)
    if keep.all() or not keep.any():
        log(f"[{m.label}] {r['name']}: per-pair rates fitted over its {len(singles)} pairs "
            f"({time.perf_counter() - t0:.1f} s): {'every pair carries' if keep.all() else 'no pair carries'} "
            "the contact; kept as it is")
        return best
    new = contact_on_pairs(cctx, me, [pr for pr, k in zip(fitted, keep) if k], name)
    if new is None:
        return best
    t_new = candidate_term(pm, new, m.p)
    f2 = fit_with(ctx["sur"], ctx["T"], model, acc_terms + [t_new], ctx["data"], c.zeta0, pm.lower, pm.upper,
                  p0=m.p, c0=[a["c"] for a in accepted] + [float(rates[keep].mean()) / float(new.term.scale)],
                  continuation=ctx["cont"], quantity=quantity, shift_hz=shift, max_nfev=cfg.max_evaluations,
                  with_basis=False)
    h2, _ = _holdout(camp, articles, m, f2.surrogate, f2.x, quantity)
    t2 = {"names": acc_names + [new.name], "c": f2.c.tolist(), "sd_equalized": f2.sd,
          "holdout_before": trial["holdout_before"], "holdout_after": h2, "shape_of": r["name"]}
    if "screened_after" in trial:
        t2["screened_after"] = trial["screened_after"]
    trials.append(t2)
    kept = ", ".join(f"{a}-{b}" for (a, b), k in zip(fitted, keep) if k)
    log(f"[{m.label}] {r['name']}: per-pair rates fitted over its {len(singles)} pairs, {int(keep.sum())} carry "
        f"the contact ({kept}); as one candidate hold-out SD {h2:.4g} against {ha:.4g} "
        f"({time.perf_counter() - t0:.1f} s)" + (": it replaces it" if h2 < gain * ha else ": kept as it is"))
    if not h2 < gain * ha:
        return best
    ctx["cands"].append(new)
    ctx["terms"].append(t_new)
    cval = float(f2.c[-1])
    value, unit, words = _physical(new.term, cval)
    row = dict(r, name=new.name, grids=list(new.grids), center=[float(x) for x in new.center],
               element_size=float(new.size), description=new.description, c=cval, value=value, unit=unit,
               size=words, shaped_from=r["name"], pair_rates=pair_rates)
    return row, h2, f2, t2


def _compounds(ctx, scr, tried) -> list:
    """Compound effects (``femodel.COMPOUND_EFFECTS``: several terms that are one physical effect, e.g. a
    shaker attachment's mass and stinger spring at the drive grid) with a member among the ``tried`` rows:
    one row each, recalibrated and judged together (``members``, ``member_c`` the start: each member's
    checked or linear magnitude)."""
    from femodel import COMPOUND_EFFECTS, compound_candidates

    names = {r["name"] for r in tried}
    comps = [(n, ms) for n, ms in compound_candidates(ctx["cands"]) if any(x.name in names for x in ms)]
    if not comps:
        return []
    rows = {r["name"]: r for r in ranked_table(ctx["cands"], scr, n=len(scr.names))}
    out = []
    for name, members in comps:
        mr = [rows[x.name] for x in members if x.name in rows]
        if len(mr) != len(members):
            continue
        first = mr[0]
        family = next((k for k in COMPOUND_EFFECTS if name.startswith(k + "_g")), name)
        out.append(dict(first, name=name, family=family, members=[x["name"] for x in mr],
                        member_c=[x["c"] for x in mr], member_rows=mr,
                        description=" + ".join(x["description"] for x in mr)))
    return out


def _terms_of(ctx, rows) -> list:
    """The femodel terms of candidate rows."""
    by = {cd.name: cd.term for cd in ctx["cands"]}
    return [by[r["name"]] for r in rows]


def _tried(cands, scr) -> list:
    """The candidates the acceptance recalibrates: every nonlinearly checked one (``top_n`` and the best of
    every family) that explains part of the residual, best score first (rows of :func:`ranked_table`)."""
    return [r for r in ranked_table(cands, scr, n=max(len(scr.checks), 1)) if r["checked"] and r["explained"] > 0]


def holdout_ranking(cands, scr, trials, n: int = 10) -> tuple:
    """The ranked table after the acceptance: the candidates recalibrated singly in its first round ranked by
    the fraction of the hold-out SD (raw lines, one footing) they remove, ``explained_holdout`` = 1 - after /
    before, then the others in the screening's order. The equalized screening fraction is a proxy (on
    identified, equalized data its residual holds the identification's own error, which no effect
    explains); the hold-out fraction is measured on data the fit did not see, and is what the acceptance
    judges. Every row keeps its screening numbers and ``screening_rank``."""
    single = {t["names"][0]: t for t in trials if len(t["names"]) == 1}
    # every singly recalibrated candidate, wherever the screening ranked it (a place tied with a point effect,
    # _tied_places, may lie far down the screening's order)
    full = ranked_table(cands, scr, n=len(scr.names) if single else max(n, len(scr.checks)))
    tried = sorted((r for r in full if r["name"] in single), key=lambda r: single[r["name"]]["holdout_after"])
    rest = [r for r in full if r["name"] not in single][:max(n, len(scr.checks))]
    out = []
    for k, r in enumerate((tried + rest)[:n]):
        t = single.get(r["name"])
        frac = None if t is None or not t["holdout_before"] > 0 else 1.0 - t["holdout_after"] / t["holdout_before"]
        out.append(dict(r, rank=k + 1, screening_rank=r["rank"], explained_holdout=frac))
    return tuple(out)


def _rescreen(camp, model, m, ctx, fit, accepted, quantity, executor, log):
    """The screening again on the model extended by the accepted effects (their fit ``fit``): every other
    candidate (none sharing elements with an accepted one), linear stage through the continuation, the
    ``top_n`` best re-fitted nonlinearly with the accepted magnitudes free.

    Returns (checked rows of the new ranking (:func:`ranked_table`), {name: (p, c) start of its
    recalibration together with the accepted effects: the check's point}).
    """
    from calibration import extend_with_candidates, extended_model, screen, shifted_solver
    from femodel import candidate_regions

    cfg, c = camp.diagnosis, camp.calibration
    shift = max(camp.band.low_hz / 4.0, camp.band.high_hz / 50.0)
    by_name = {t.name: t for t in ctx["terms"]}
    family = {cd.name: cd.family for cd in ctx["cands"]}
    cand = {cd.name: cd for cd in ctx["cands"]}
    done = set(accepted)
    rest = [t for t in ctx["terms"]
            if t.name not in done and not any(_overlap(ctx, t.name, a) for a in accepted)]
    if not rest:
        return [], {}
    t0 = time.perf_counter()
    sur_f, T_f = fit.surrogate, fit.basis
    if T_f is None:  # fitted without its basis (the acceptance's trials): the same extension, with it
        sur_f, T_f = extend_with_candidates(ctx["sur"], ctx["T"], model, [by_name[a] for a in accepted],
                                            shift_hz=shift)
    scr = screen(sur_f, T_f, fit.x, ctx["data"], c.zeta0, rest, fit.lower, fit.upper,
                 quantity=quantity, model=extended_model(model, [by_name[a] for a in accepted]), n_check=cfg.top_n,
                 solve=shifted_solver(model, ctx["sur"].p_basis, shift),  # the accepted magnitudes are 0 there
                 shift_hz=shift, continuation=ctx["cont"], max_nfev=cfg.max_evaluations, executor=executor,
                 groups=[family[t.name] for t in rest], zoom=ctx["zoom"], zoom_rounds=ctx["zoom_rounds"],
                 regions=candidate_regions([cand[t.name] for t in rest]))
    ctx["screening_now"] = scr  # the ties of a point effect in the next round are this screening's (_tied_places)
    rows = ranked_table(ctx["cands"], scr)
    n_p = fit.surrogate.n_params - len(accepted)
    starts = {}
    for r in rows:
        chk = scr.check(r["name"])
        if chk is not None:
            starts[r["name"]] = (chk.p[:n_p], list(chk.p[n_p:]) + [chk.c])
    log(f"[{m.label}] re-screened {len(rest) + len(scr.zoomed)} candidates ({len(scr.zoomed)} zoomed) with {' + '.join(accepted)} in "
        f"{time.perf_counter() - t0:.1f} s; first: "
        + "; ".join(f"{r['family']} {r['name']} ({r['size']}, explained {100 * r['explained']:.1f} %)"
                    for r in rows[:3]))
    tried = _tried(ctx["cands"], scr)
    return tried + _compounds(ctx, scr, tried), starts


def _refined(camp, pm, model, articles, m, fit, extended_terms, quantity, log):
    """The raw-line refinement of the extended model, as the calibrate stage refines: damping continuation on
    the extended surrogate, then ``refine_cycles`` re-basis cycles on the full extended model
    (``pm.with_terms``); and its hold-out SD with the damping it estimated: the "after" on the footing of the
    calibrated model's "before".

    Returns (Refinement or None, hold-out SD or None, x, surrogate)."""
    from calibration import FRFModel, build_surrogate, refine

    from frfcal.campaign._stages import fit_data, raw_basis_check, raw_rebasis_tol

    c = camp.calibration
    if not c.refine:
        return None, None, fit.x, fit.surrogate
    t0 = time.perf_counter()
    band = (camp.band.low_hz, camp.band.high_hz)
    arts = [articles[i] for i in m.articles]
    raw = [fit_data(a, camp.channels.calibrate, c.refine_weights) for a in arts]
    modes = [identified_modes(a) for a in arts]
    idents = [(a.identification, a.ident_channels) for a in arts]
    opts = dict(quantity=quantity, mac_min=camp.validation.mac_min, band_hz=band, max_nfev=c.max_evaluations)
    ref = refine(fit.surrogate, fit.x, raw, idents, modes, fit.lower, fit.upper, c.zeta0, floors=c.refine_floors,
                 **opts)
    sur = fit.surrogate
    if c.refine_cycles:
        ext = pm.with_terms(list(extended_terms))
        mext = FRFModel(K=ext.K, M=ext.M, inputs=model.inputs, outputs=model.outputs,
                        input_names=model.input_names, output_names=model.output_names,
                        parameter_names=tuple(ext.names), parametric=ext)
        basis = None
        for k in range(c.refine_cycles):
            tol = raw_rebasis_tol(c, k)
            if k and tol:  # as the calibrate stage (the first build has no full basis to check)
                chk, _ = raw_basis_check(mext, sur, basis, ref, band, tol)
                log(f"[{m.label}] extended model, re-basis {k + 1}: {chk.describe()}"
                    + (": kept" if chk.adequate else ""))
                if chk.adequate:
                    break
            sur, basis = build_surrogate(mext, ref.p, band, c.basis_factor, enrich=c.enrich, previous_basis=basis)
            nxt = refine(sur, ref.p, raw, idents, modes, fit.lower, fit.upper, c.zeta0, floors=(0.0,), **opts)
            dp = float(np.max(np.abs(nxt.p - ref.p)))
            ref = nxt
            if dp < c.cycle_tol:
                break
    h = None
    if camp.channels.holdout:
        h = _holdout_at(camp, arts, sur, ref.p, quantity, (ref.zeta, ref.p_zeta), camp.channels.holdout)
    log(f"[{m.label}] extended model refined on the raw lines: SD {ref.sd_raw:.4g}"
        + ("" if h is None else f", hold-out SD {h:.4g} (estimated damping)")
        + f" ({time.perf_counter() - t0:.1f} s)")
    return ref, h, ref.p, sur


#: An effect size inside its bounds is judged as a parameter of range +-EFFECT_RANGE of its value (its own
#: bounds span decades, [0, 100 x scale]: range-relative thresholds would pass anything).
EFFECT_RANGE = 0.5


def effect_identifiability(camp, arts, sur, x, ref, lower, upper, names, quantity, n_p: int):
    """:func:`calibration.identifiability` of the extended model at its refined point ``x``, from the raw-line
    objective the refinement ``ref`` ended on (its estimated damping, each article's lines), as the calibrate
    stage reports the parameters'.

    The effect magnitudes (``x[n_p:]``) enter relative to their refined value, q = c / c* - 1 (so
    ``std`` is a fraction of the size), with bounds +-:data:`EFFECT_RANGE`; an effect at its own bound (c at 0
    or at its upper bound to 1e-9 of the range) keeps that bound and is reported at it."""
    from calibration import ModalDampingObjective, identifiability

    from frfcal.campaign._stages import fit_data

    raw = [fit_data(a, camp.channels.calibrate, camp.calibration.refine_weights) for a in arts]
    obj = ModalDampingObjective(sur, raw, ref.zeta, ref.p_zeta, 0.0, quantity)
    stride = raw[0].frf.shape[1] * raw[0].frf.shape[2]
    x = np.asarray(x, float)
    J, v, lo, hi = relative_effects(obj.jacobian(x), x, lower, upper, n_p)
    return identifiability(J, obj.residual(x), v, lo, hi, names, stride=stride)


def relative_effects(jacobian, x, lower, upper, n_p: int) -> tuple:
    """(J, x, lower, upper) with every effect magnitude ``x[n_p:]`` inside its bounds replaced by
    q = c / c* - 1 at q = 0 (its Jacobian column times c*, bounds +-:data:`EFFECT_RANGE`); the parameters and
    an effect at its bound (within 1e-9 of the range, or c* = 0) as given."""
    J = np.array(jacobian, float)
    x = np.asarray(x, float)
    v, lo, hi = x.copy(), np.array(lower, float), np.array(upper, float)
    for k in range(n_p, x.size):
        span = hi[k] - lo[k]
        if x[k] - lo[k] > 1e-9 * span and hi[k] - x[k] > 1e-9 * span and x[k] != 0:
            J[:, k] *= x[k]
            v[k], lo[k], hi[k] = 0.0, -EFFECT_RANGE, EFFECT_RANGE
    return J, v, lo, hi


def _size_uncertainty(idf, k: int, c: float) -> dict:
    """An accepted effect's size as the data resolve it (``idf`` from :func:`effect_identifiability`): its
    standard deviation relative to the size (%, None when unresolved or at a bound), identifiable or not and
    why, its largest correlation and with what."""
    std = float(idf.std[k])
    corr = np.asarray(idf.correlation[k], float).copy()
    corr[k] = np.nan
    j = int(np.nanargmax(np.abs(corr))) if np.any(np.isfinite(corr)) else None
    relative = idf.at_bound[k] == 0
    return {"size_std_percent": 100.0 * std if np.isfinite(std) and relative and c else None,
            "size_identifiable": bool(idf.identifiable[k]),
            "size_identifiability": idf.reasons[k] or "identifiable",
            "size_max_correlation": None if j is None else {"with": idf.names[j], "value": float(corr[j])}}


def size_words(a: dict) -> str:
    """" (+-12 %)" or " (size not identifiable: ...)" after an accepted effect's size, "" without an estimate."""
    if "size_identifiable" not in a:
        return ""
    if not a["size_identifiable"]:
        return f" (size not identifiable from these channels: {a['size_identifiability']})"
    return f" (+-{a['size_std_percent']:.2g} % from the noise, 1 s.d.)" if a["size_std_percent"] is not None else ""


def _holdout_at(camp, arts, sur, x, quantity, damping, channels) -> float:
    """SD of (sur, x) on the raw lines of ``channels`` with ``damping`` ((zeta per article, p_ref) as the
    refinement estimated it, or None: the identified damping mapped by MAC); the floor's standard errors as
    :func:`floors_of` gives them (measured, else estimated from adjacent lines)."""
    from calibration import validate

    from frfcal.campaign._stages import raw_data

    errs, src = floors_of(arts, channels)
    v = validate(sur, sur, x, [raw_data(a, channels) for a in arts], [identified_modes(a) for a in arts],
                 camp.calibration.zeta0, None, camp.validation.mac_min, quantity,
                 (camp.band.low_hz, camp.band.high_hz), std_error=errs, damping=damping, floor_source=src,
                 with_floor_range=False)
    return float(v.sd_calibrated)


def _mode_shift(sur, x, x0, band, sur0=None) -> float:
    """Largest relative frequency change of the model's elastic modes in ``band`` between x0 (on ``sur0``,
    default ``sur``) and x (sorted eigenvalues of the reduced models: a small change keeps their order)."""
    from calibration import reduced_modes

    sur0 = sur if sur0 is None else sur0
    f = [np.sqrt(np.clip(reduced_modes(s, np.asarray(v, float))[0], 0, None)) / (2 * np.pi)
         for s, v in ((sur, x), (sur0, x0))]
    n = min(f[0].size, f[1].size)
    f = [v[:n] for v in f]
    use = (f[1] > sur0.rigid_hz) & (f[1] >= band[0]) & (f[1] <= band[1])
    return float(np.max(np.abs(f[0][use] / f[1][use] - 1.0))) if use.any() else 0.0


def refined_sizes(camp, arts, sur, x, damping, n_p: int, accepted, n_res: int, quantity, sur_without=None) -> list:
    """Per accepted effect, its final (refined) size seen by the data: the hold-out SD (raw lines of the
    hold-out channels, or of the calibration channels without any; the damping the refinement estimated) of
    the final model ``(sur, x)`` and of the same model with the effect's magnitude ``x[n_p + j]`` set to 0,
    beside the acceptance's penalty for its parameter (:func:`calibration.negligible_effect`), and the largest
    relative shift of a mode in band it makes. ``negligible``: the model is as good without it (an effect
    refined to ~0 after it was accepted on the screening's target).

    ``sur_without``: the surrogate the magnitudes are set to 0 on (same parameters as ``sur``), default
    ``sur``. The refined surrogate's basis is built at the refined point: for a stiff effect (a contact
    refined to its upper bound, a near-rigid tie) every basis vector moves the tied DOF together, so on that
    basis the effect's term projects to ~0 and setting its magnitude to 0 changes nothing: the effect would
    look negligible while it explains the data. The diagnose stage passes the acceptance fit's surrogate,
    the calibrated basis extended by the effects' static corrections, which holds the model without them
    exactly (c = 0 is its own basis point)."""
    from calibration import negligible_effect

    chans = list(camp.channels.holdout) or list(camp.channels.calibrate)
    band = (camp.band.low_hz, camp.band.high_hz)
    x = np.asarray(x, float)
    s0 = sur if sur_without is None else sur_without
    h = _holdout_at(camp, arts, sur, x, quantity, damping, chans)
    damping0 = damping if s0 is sur else _damping_on(sur, s0, damping)
    out = []
    for j, _ in enumerate(accepted):
        x0 = x.copy()
        x0[n_p + j] = 0.0
        h0 = _holdout_at(camp, arts, s0, x0, quantity, damping0, chans)
        neg, ratio, allowed = negligible_effect(h, h0, max(int(n_res), 2))
        out.append({"holdout_with": h, "holdout_without": h0, "ratio": ratio, "penalty_ratio": allowed,
                    "max_mode_shift": _mode_shift(sur, x, x0, band, s0), "negligible": neg})
    return out


def _damping_on(sur, sur0, damping):
    """The refinement's estimated damping ((zeta per article over the reduced modes of ``sur`` at p_ref, p_ref))
    carried to the reduced modes of ``sur0`` (same parameters, another basis): each mode of ``sur0`` at p_ref
    takes the damping of the mode of ``sur`` nearest in frequency there. None stays None."""
    from calibration import reduced_modes

    if damping is None:
        return None
    zeta, p_ref = damping
    f = np.sqrt(np.clip(reduced_modes(sur, np.asarray(p_ref, float))[0], 0, None))
    f0 = np.sqrt(np.clip(reduced_modes(sur0, np.asarray(p_ref, float))[0], 0, None))
    near = np.argmin(np.abs(f0[:, None] - f[None, :]), axis=1)
    return [np.asarray(z, float)[near] for z in zeta], p_ref


def drop_negligible(accepted, sizes, x, n_p: int) -> tuple:
    """Split the accepted rows by their refined size (:func:`refined_sizes`): (kept rows, negligible rows,
    x of the model with the kept effects only: ``[p, c of the kept]``). Every row gets ``refined_effect``
    (its size record) and ``term_index`` (its position among the terms of the fitted model)."""
    x = np.asarray(x, float)
    kept, dropped = [], []
    for j, (a, z) in enumerate(zip(accepted, sizes)):
        a = dict(a, refined_effect=dict(z), term_index=j)
        (dropped if z["negligible"] else kept).append(a)
    x_kept = np.concatenate([x[:n_p], [x[n_p + a["term_index"]] for a in kept]])
    return kept, dropped, x_kept


def diagnose_stage(camp: Campaign, load, pm, model, articles, eq, cal, val, xval, executor=None,
                   log=print, groups=None, level_checks=None) -> DiagnosisResult:
    """The diagnosis of every calibrated member: significance, the nonlinearity gate, the screening of
    candidate effects (module docstring).

    ``articles`` carry their identification; ``eq``, ``cal``, ``val``, ``xval``
    are the equalize, calibrate, validate and cross-validate results; ``pm``
    and ``model`` the campaign's parametric and FRF model; ``executor`` runs
    the cross-validation of the acceptance (None: serial); ``groups`` the
    group stage's result: with article groups, every accepted effect is
    fitted per article to find the one that separates them. ``level_checks``
    (article -> (calibration.LevelDependence or the reason it could not be
    made, ((level N, run path), ...))) replaces the gate's level check of
    those articles: an acquiring campaign calibrates on each article's lowest
    level and checks all its levels here.
    """
    gate = nonlinearity_gate(camp, articles, log)
    for name, (check, entries) in (level_checks or {}).items():
        from calibration import nonlinearity

        runs = tuple(LevelRun(name, Path(path), float(level), "run file", "unknown") for level, path in entries)
        if isinstance(check, str):
            nl, notes = gate.get(name, (None,))[0], (f"{name}: level dependence {check}",)
        else:
            nl, notes = nonlinearity(check, None, None), ()
        gate[name] = (nl, runs, notes)
    gates = tuple(ArticleGate(name, nl, runs, notes) for name, (nl, runs, notes) in gate.items())
    by_name = {g.article: g for g in gates}
    target = None  # built once, when a member is screened
    out, fits = [], []
    for m, v, x in zip(cal.members, val.members, xval.members):
        names = tuple(dict.fromkeys(articles[i].name for i in m.articles))
        t_res = time.perf_counter()
        check, frfs_before = member_residual(camp, load, articles, m)
        frfs_after = None
        for k, line in enumerate(check.describe()):
            log(f"[{m.label}] {line}" + (f" ({time.perf_counter() - t_res:.1f} s)" if k == 0 else ""))
        chans = tuple(c.label for c in sorted(check.channels, key=lambda c: -c.ratio))
        sd = _sd_table(m, v, x, check, [articles[i] for i in m.articles])
        flagged = [by_name[n] for n in names if by_name[n].nonlinearity is not None
                   and by_name[n].nonlinearity.flagged]
        nl_modes = tuple(r for g in flagged for r in _nonlinear_modes(g))
        counts, rows, scr, acc, trials, extended = None, (), None, (), (), None
        if not check.significant:
            verdict = "nothing to explain"
            reason = (f"the residual is inside the floor (SD {check.ratio:.3g} x the expected "
                      f"{check.expected:.3g}, threshold {check.ratio_threshold:g}): no effect is looked for")
            if flagged:
                reason += "; the nonlinearity gate flags " + ", ".join(g.article for g in flagged) + " (reported)"
        elif flagged:
            verdict = "nonlinear"
            what = "; ".join(
                f"{r['article']}: {r['check']}" + (f" of mode {r['mode']} at {r['frequency_hz']:.5g} Hz"
                                                   if r.get("mode") else f" at {r['frequency_hz']:.5g} Hz")
                + (f" ({r['quantity']} {r['values'][0]:.4g} -> {r['values'][-1]:.4g} from {min(r['levels_n']):.3g}"
                   f" to {max(r['levels_n']):.3g} N, {r['z']:.3g} sigma)" if r["check"] == "level dependence" else "")
                for r in nl_modes) or "; ".join(g.article for g in flagged)
            reason = (f"the residual is significant ({check.ratio:.3g} x the floor) and the test article behaves "
                      f"nonlinearly: {what}; no linear effect is accepted in its place")
        else:
            quantity = articles[m.articles[0]].quantity
            if target is None:
                target = screening_target(camp, articles, eq)
            counts, rows, scr, ctx = _screen_member(camp, pm, model, load, target, m, quantity, log, executor)
            acc, trials, after, fit = _accept_member(camp, load, pm, model, articles, m, check, rows, ctx,
                                                     quantity, executor, log)
            rows = holdout_ranking(ctx["cands"], scr, trials)
            counts = {}  # screened per family, the zoomed candidates (first screening and re-screenings) included
            for cd in ctx["cands"]:
                counts[cd.family] = counts.get(cd.family, 0) + 1
            if after is not None:
                sd["after"] = after
            dropped = (after or {}).get("negligible", ())
            negl = ("; " + "; ".join(f"{a['name']} was accepted but refined to {a['size']}, negligible "
                                     f"(the model is as good without it): dropped" for a in dropped)
                    if dropped else "")
            if acc:
                verdict = "effect(s) found"
                extended = (tuple(ctx["cands"][[cd.name for cd in ctx["cands"]].index(a["name"])] for a in acc),
                            fit[1])
                frfs_after = fit[2]
                fits.append((m, acc, fit[0], extended[0], fit[3]))
                reason = "accepted: " + "; ".join(f"{a['description']}: {a['size']}{size_words(a)}"
                                                  for a in acc) + negl
                still = ((after or {}).get("residual") or {})
                if still.get("significant"):  # said here too, not only in the "after" line
                    sampled = _sampled_points(ctx["cctx"], ctx["cands"]) if ctx.get("cctx") else ""
                    reason += (f"; the residual with them is still significant ({still['ratio']:.3g} x the "
                               "expected): the model still lacks something, or an accepted effect stands in for "
                               "another" + (f"; the point families were sampled ({sampled}): a denser sample "
                                            "([diagnosis] candidates = { spread_grids = N }) may find it"
                                            if sampled else ""))
            elif dropped:
                verdict = "no effect accepted"
                reason = (f"the residual is significant ({check.ratio:.3g} x the floor) and no nonlinearity is "
                          f"flagged; " + negl[2:])
            else:
                verdict = "no effect accepted"
                top = rows[0] if rows else None
                why = trials[0]["decision"]["reason"] if trials and "decision" in trials[0] else "no candidate fitted"
                reason = (f"the residual is significant ({check.ratio:.3g} x the floor) and no nonlinearity is "
                          "flagged; " + (f"the screening ranks {top['family']} {top['name']} first ({top['size']}, "
                                         f"explains {100 * top['explained']:.1f} % of the residual)" if top else
                                         "no candidate") + f"; not accepted: {why}")
        split = _one_set_over_groups(m, groups, articles)
        if split and check.significant and verdict != "nonlinear":
            reason += (f"; the articles fall into groups ({split}) and ensemble = \"all\" fits one parameter set to "
                       "them: an effect on some articles only is diluted over all; [calibration] ensemble = "
                       "\"group\" diagnoses each group and names the effect that separates them")
        log(f"[{m.label}] diagnosis: {verdict}: {reason}")
        overlay = None
        if check.significant:
            overlay = _overlay(camp, articles[m.articles[0]], chans[:camp.diagnosis.figures_channels],
                               frfs_before[0], None if frfs_after is None else frfs_after[0])
        out.append(MemberDiagnosis(m.label, names, verdict, reason, check, nl_modes, sd, chans, counts, rows, scr,
                                   acc, trials, None if extended is None else extended[0],
                                   None if extended is None else np.asarray(extended[1], float), overlay))
    return DiagnosisResult(gates, tuple(out), _separations(camp, articles, target or eq, groups, fits, log))


def _one_set_over_groups(m, groups, articles) -> str:
    """"A1, A2; A3, A4" when member ``m`` holds articles the group stage found in more than one group (ensemble
    "all"), else ""."""
    from frfcal.campaign._stages import split_words

    grp = None if groups is None else groups.grouping
    if grp is None or len(groups.members) != 1:
        return ""
    labels = np.asarray(grp.labels)
    sets = [tuple(i for i in m.articles if labels[i] == g) for g in np.unique(labels[list(m.articles)])]
    return split_words(articles, sets) if len(sets) > 1 else ""


def _separations(camp: Campaign, articles, eq, groups, fits, log) -> tuple:
    """Every accepted effect fitted per article (all parameters re-fitted, from the member's common point,
    through the damping continuation) against the group stage's article groups (``separating_effect``).

    Returns a tuple of dicts: ``member``, ``name``, ``family``, ``separates``, ``separation``
    (``Separation.to_dict()``, c normalized), ``value`` (per-article physical magnitude) and ``unit``.
    """
    from calibration import separating_effect

    if groups is None or len(groups.members) < 2 or not fits:
        return ()
    label = np.full(len(articles), -1)
    for g, (_, idx) in enumerate(groups.members):
        label[list(idx)] = g
    use = [i for i in range(len(articles)) if label[i] >= 0]
    data = [[eq.data[i]] for i in use]
    cont = [(z, [[d[i]] for i in use]) for z, d in eq.continuation]
    out = []
    for m, acc, fit, cands, n_fitted in fits:
        n_p = fit.surrogate.n_params - n_fitted  # the fit holds every accepted term, negligible ones included
        for a, cd in zip(acc, cands):
            t0 = time.perf_counter()
            sep = separating_effect(fit.surrogate, fit.x, data, camp.calibration.zeta0, label[use], fit.lower,
                                    fit.upper, index=n_p + a.get("term_index", 0), refit_p=True, continuation=cont,
                                    max_nfev=camp.diagnosis.max_evaluations)
            per = [float(_physical(cd.term, float(c))[0]) for c in sep.magnitude]
            # the sizes of the screening's footing (damping zeta0, the continuation): they separate the articles;
            # the accepted size is the one refined on the raw lines, and may differ from these
            log(f"[{m.label}] {a['name']} per article (fitted at the screening's damping {camp.calibration.zeta0:g}, "
                f"not refined on the raw lines): "
                + ", ".join(f"{n} {v:.4g}" for n, v in zip(sep.articles, per)) + (f" {a['unit']}" if a["unit"] else "")
                + f": {'SEPARATES' if sep.separates else 'does not separate'} the groups ({sep.reason}; "
                + f"{time.perf_counter() - t0:.1f} s)")
            out.append({"member": m.label, "name": a["name"], "family": a["family"], "separates": bool(sep.separates),
                        "separation": sep.to_dict(), "value": per, "unit": a["unit"]})
    return tuple(out)


def new_cards(pm, extended, x, path: Path) -> list:
    """Write the deck extended by the accepted effects' terms at ``x = [p, c]``; return the new cards' lines.

    The new cards are the lines of the extended deck that the deck written at
    the same ``p`` without the effects does not have (CELAS2, CONM2, copied
    property and material cards, re-pointed elements; fixed format).
    """
    import tempfile

    ext = pm.with_terms([c.term for c in extended])
    ext.write_bdf(path, x)
    with tempfile.TemporaryDirectory() as tmp:
        base = pm.write_bdf(Path(tmp) / "base.bdf", np.asarray(x, float)[:pm.n_params])
        old = set(Path(base).read_text().splitlines())
    return [ln for ln in Path(path).read_text().splitlines() if ln not in old and not ln.startswith("$")]


def write_diagnosis(diag: DiagnosisResult, camp: Campaign, pm, outdir: Path, log=print) -> dict:
    """Write ``diagnosis.json``, per member with an accepted effect ``extended_<member>.bdf``, and the FRF
    overlays ``diagnosis_<member>.png`` (``[output] figures``) into ``outdir``; return the JSON content plus
    ``result_file``."""
    from frfcal.campaign._report import json_default

    outdir = Path(outdir)
    d = diag.to_dict()
    for m, md in zip(diag.members, d["members"]):
        if m.extended and camp.output.write_bdf:
            path = outdir / f"extended_{m.label}.bdf"
            md["new_cards"] = new_cards(pm, m.extended, m.x_extended, path)
            md["bdf"] = str(path)
            log(f"wrote {path} ({len(md['new_cards'])} new card line(s))")
        if m.overlay is not None and camp.output.figures:
            path = outdir / f"diagnosis_{m.label}.png"
            overlay_figure(m.overlay, f"[{m.label}] {m.verdict}: {m.overlay['article']}, most affected channels"
                           ).savefig(path, dpi=90)
            md["figures"] = [str(path)]
    path = outdir / "diagnosis.json"
    path.write_text(json.dumps(d, indent=1, default=json_default))
    d["result_file"] = str(path)
    log(f"wrote {path}")
    return d


# ----------------------------------------------------------------------------- candidates and screening


def _physical(term, c: float) -> tuple:
    """(value, unit, words) of a term at normalized magnitude c."""
    from femodel import ElementFactor

    v = float(term.value(c))
    if isinstance(term, ElementFactor):
        return v, "x", f"{'stiffness' if term.kind == 'K' else 'mass'} factor {v:.3g}"
    return v, term.unit, f"{v:.3g} {term.unit}"


def member_candidates(camp: Campaign, pm, load, p, log=print) -> tuple:
    """Candidate effects of the deck and the test set-up (femodel.generate_candidates) and their
    CandidateTerm (dK, dM at ``p``) for the screening.

    Sensors are the grids of the calibration and hold-out channels, drives the
    drive channels' grids and directions.

    Returns (list of Candidate, list of CandidateTerm, femodel.CandidateContext: for the zoom,
    :func:`point_zoom`).
    """
    from femodel import CandidateOptions, ParameterError, candidate_context, generate_candidates

    cfg = camp.diagnosis
    try:
        opts = CandidateOptions(**{k: tuple(v) if isinstance(v, list) else v for k, v in cfg.candidates.items()})
    except TypeError as exc:
        raise CalibrationError(f"[diagnosis] candidates: {exc}") from None
    except ParameterError as exc:
        raise CalibrationError(f"[diagnosis] candidates: {exc}") from None
    sensors = tuple(dict.fromkeys(t.grid for t in load.channels))
    drives = tuple((t.grid, tuple(t.direction)) for t in load.drives)
    t0 = time.perf_counter()
    cctx = candidate_context(pm, sensors=sensors, drives=drives, options=opts)
    cands = list(generate_candidates(pm, families=cfg.families, context=cctx))
    terms = candidate_terms(pm, cands, p)
    counts = {}
    for c in cands:
        counts[c.family] = counts.get(c.family, 0) + 1
    log("candidates: " + ", ".join(f"{k} {v}" for k, v in counts.items())
        + f" ({time.perf_counter() - t0:.1f} s with their derivatives)")
    sampled = _sampled_points(cctx, cands)
    if sampled:
        log(f"  {sampled} (a spread sample, refined by the zoom around the best; every grid: [diagnosis] "
            f"candidates = {{ spread_grids = N }})")
    return cands, terms, cctx


def _sampled_points(cctx, cands) -> str:
    """"lumped_mass at 40 of 1200 grids, ..." for the point families sampled at fewer grids than eligible, or ""."""
    from femodel import point_coverage

    cov = {}
    for (fam, _), (n, n_all) in point_coverage(cctx, cands).items():
        a, b = cov.get(fam, (0, 0))
        cov[fam] = (max(a, n), max(b, n_all))
    return ", ".join(f"{fam} at {n} of {n_all} grids" for fam, (n, n_all) in cov.items() if n < n_all)


def candidate_term(pm, cand, p):
    """The screening's CandidateTerm of a femodel Candidate: its dK, dM at ``p``."""
    return candidate_terms(pm, [cand], p)[0]


def candidate_terms(pm, cands, p) -> list:
    """:func:`candidate_term` of many candidates: their derivatives in one
    :meth:`femodel.ParametricModel.term_derivatives` call (the element clusters assembled in one pass)."""
    from calibration import CandidateTerm

    ds = pm.term_derivatives([c.term for c in cands], p)
    return [CandidateTerm(c.name, d["K"], d["M"], c.term.lower, c.term.upper) for c, d in zip(cands, ds)]


def point_zoom(cctx, pm, p, cands: list, terms: list):
    """The screening's zoom of the point families (``calibration.screen(zoom=...)``), or None.

    Each call (a round) takes the ``zoom_top`` best candidates (linear explained > 0) of every point family
    (``femodel.POINT_FAMILIES``: lumped masses, ground springs) and offers the same family's candidates at
    the untested grids of their neighbourhoods (``femodel.zoom_candidates``, at most ``zoom_grids`` each);
    the new candidates and their terms (dK, dM at ``p``) are appended to ``cands`` and ``terms`` (the
    campaign's lists: ranking, acceptance and re-screening see them as any other candidate). None when
    ``zoom_rounds`` is 0 or no candidate is of a point family.
    """
    from femodel import POINT_FAMILIES, zoom_candidates

    o = cctx.options
    fams = [f for f in POINT_FAMILIES if any(c.family == f for c in cands)]
    if not o.zoom_rounds or not fams:
        return None

    def zoom(names, explained):
        score = dict(zip(names, np.asarray(explained, float).tolist()))
        new: list = []
        parents: list = []
        for fam in fams:
            best = sorted((c for c in cands if c.family == fam and score.get(c.name, 0.0) > 0.0),
                          key=lambda c: -score[c.name])[:o.zoom_top]
            for b in best:
                got = zoom_candidates(cctx, cands + new, b)
                new.extend(got)
                parents += [b.name] * len(got)
        out = [(t, c.family, par) for t, c, par in zip(candidate_terms(pm, new, p), new, parents)]
        cands.extend(new)
        terms.extend(t for t, _, _ in out)
        return out

    return zoom


def ranked_table(cands, scr, n: int = 10) -> tuple:
    """The screening's ranking as rows: family, location, physical size with unit, explained fraction."""
    idx = {c.name: i for i, c in enumerate(cands)}
    rows = []
    for rank, k in enumerate(scr.order[:n]):
        name = scr.names[int(k)]
        c = cands[idx[name]]
        chk = scr.check(name)
        cval = float(chk.c) if chk is not None else float(scr.c_linear[k])
        value, unit, words = _physical(c.term, cval)
        rows.append({
            "rank": rank + 1, "name": name, "family": c.family, "grids": list(c.grids), "parts": list(c.parts),
            "center": [float(x) for x in c.center], "element_size": float(c.size), "description": c.description,
            "c": cval, "value": value, "unit": unit, "size": words,
            "explained": float(chk.explained) if chk is not None else float(scr.explained[k]),
            "explained_linear": float(scr.explained[k]), "checked": chk is not None,
            "converged": None if chk is None else bool(chk.converged),
            "significant": bool(scr.significant[k]),
        })
    return tuple(rows)
