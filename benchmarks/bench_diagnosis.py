"""Diagnosis benchmark: screening and acceptance on the example subframe with several hundred candidates (issue 14).

The truth is the shell subframe with a doubler sheet facing a rail web at a
2 mm gap (``femodel.example_subframe(..., gap_mm=2)``) plus ONE undeclared
effect of ``frfcal.effects.standard_effects`` (default the contact spring
across the gap, closed), synthesized by ``frfcal.synth.synthesize`` with
parameter offsets, damping varying from mode to mode and 0.5-1 % noise, as
``bench_calibration.py`` does. The calibration model (the deck) lacks it.

Untimed preparation: the campaign's own stages (load -> identify ->
equalize -> calibrate with few starts (``--starts``) -> raw-line refinement),
called one by one so that the calibrated surrogate and its basis stay in
memory (``run_campaign`` returns only the written results). Its time is
reported separately.

Timed, the diagnosis stages (wall and process CPU time each):

1. candidate generation (``femodel.generate_candidates``, every family, cap
   ``--candidates-per-family``);
2. term derivatives at the calibrated p (``ParametricModel.term_derivatives``
   per family, as the diagnose stage forms them);
3. screening (``calibration.screen`` called as the diagnose stage calls it:
   linear scores on every continuation stage, the zoom of the point families
   around their best candidates (``frfcal.campaign._diagnose.point_zoom``,
   its own time and CPU in the table; ``--no-zoom`` without), nonlinear
   re-fits of the ``[diagnosis] top_n`` best places (``--n-check``), of each
   family's best and of each checked region's alternatives, with
   ``[diagnosis] max_evaluations``; until stop 30 the bench checked the 10
   best without families or regions, a lighter screening than the stage's);
4. acceptance: ``calibration.fit_with`` of the ``--top`` best singly (from
   their converged nonlinear checks, ``fit_with(warm=...)``, on the check's own extension; ``--no-warm``:
   from the baseline through the continuation stages) and the best of them together with the best-ranked
   candidate that acts on other DOF (two on common DOF, a gap and a window of it, are one effect twice),
   hold-out SD (the target's hold-out channels) of each and, as the diagnose stage decides, for the single one
   with the lowest hold-out SD and for the combination ``calibration.cross_validate`` (same splits) before
   and after and ``calibration.accept``.

The target (``--target``, default the campaign default ``[diagnosis] target = "debiased"``): what the
screening, the fits and the hold-out compare the model with, as the diagnose stage builds it
(``frfcal.campaign._diagnose.screening_target``): ``debiased`` the raw lines with the identified poles'
damping raised to each stage's, ``equalized`` the identified model on the half-bandwidth grids. Built
before the timed stages (its time is in the untimed table).

Then, untimed in the table, the campaign's diagnose stage itself
(``frfcal.campaign._diagnose.diagnose_stage``, after the validate and
cross-validate stages) on the same calibrated member: everything it does
(residual check, screening, acceptance with its combinations, tied places
and re-screening, raw-line refinement), its wall and CPU time, its verdict
and its timestamped log (``--no-stage`` without). The table above times the
kernels of a simpler acceptance; the stage is what a user waits for.

Then (untimed) the hold-out SD with the truth damping of the calibrated deck
and of the deck extended by the accepted candidate at its fitted magnitude
(``SynthCampaign.model_sd``, full-order modes) beside the floor
(``SynthCampaign.floor_sd``); and, as the diagnose stage ends (``--no-refine``
without), the chosen effect refined on the raw lines with estimated damping
and re-basis cycles on the extended deck: its size and the deck's hold-out
SD with truth damping at the refined point, the campaign's final answer.

    python benchmarks/bench_diagnosis.py [--dof 200000] [--effect contact_spring] [--candidates-per-family 500]
                                         [--seed 11] [--target debiased|equalized]
                                         [--continuation-lines raw|half-bandwidth]
                                         [--out benchmarks/results/diagnosis.json]

Prints a table and writes benchmarks/results/diagnosis.json. A quick check:
``--dof 20000 --out /tmp/diag.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: the candidate families that describe each effect family of ``standard_effects``
MATCHING = {
    "contact_spring": ("contact_spring",),
    "sensor_mass": ("sensor_mass", "sensor_masses"),
    "shaker_attachment": ("shaker_attachment_mass", "stinger_spring"),
    "ground_spring": ("ground_spring",),
    "element_cluster": ("element_cluster",),
    "lumped_mass": ("lumped_mass",),
}
#: a candidate matches the true effect when it acts within this many of its element sizes of the effect
MATCH_SIZES = 2.0
BAND = (100.0, 400.0)


def peak_memory_gb() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return max(own, kids) / 1e6  # ru_maxrss is KiB on Linux


def cpu_s() -> float:
    """CPU time of this process and its live worker processes (user + system, BLAS threads included)."""
    import psutil

    me = psutil.Process()
    t = me.cpu_times()
    total = t.user + t.system + t.children_user + t.children_system
    for ch in me.children(recursive=True):
        try:
            c = ch.cpu_times()
            total += c.user + c.system
        except psutil.NoSuchProcess:  # a worker that ended meanwhile is in children_* once reaped
            pass
    return total


class Clock:
    """Wall and CPU time (this process and its pool workers) of named stages."""

    def __init__(self):
        self.rows: dict = {}

    def start(self):
        return time.perf_counter(), cpu_s()

    def stop(self, name, t0):
        w, c = time.perf_counter() - t0[0], cpu_s() - t0[1]
        self.rows[name] = {"wall_s": w, "cpu_s": c}
        return w


def _effect_where(fe, effect):
    """(grid ids, element ids) where a true effect acts."""
    from femodel import AddedMass, AddedSpring

    t = effect.term
    if isinstance(t, AddedSpring):
        return {int(g) for d in t.dofs for g in (d[0], d[2]) if g}, set()
    if isinstance(t, AddedMass):
        return {int(g) for g in t.grids}, set()
    els = {int(e) for e in t.elements}
    grids = set()
    for card, tab in fe.elements.items():
        if len(tab) and "nodes" in tab.fields:
            sel = np.isin(tab.ids, list(els))
            grids.update(int(g) for g in np.asarray(tab.fields["nodes"])[sel].ravel() if g > 0)
    return grids, els


def matches(fe, length_m, effects, family, cands) -> np.ndarray:
    """Bool per candidate: of a family describing the effect and acting where the effect acts.

    Acting where: shares a grid (an element for element clusters) with one of
    the effect's terms, or its centre lies within MATCH_SIZES of its element
    sizes of one of the effect's grids (spread-grid families do not sit on the
    exact grid).
    """
    from femodel import ElementFactor

    fams = MATCHING[family]
    where = [_effect_where(fe, e) for e in effects]
    grids = sorted(set().union(*(g for g, _ in where)))
    els = set().union(*(e for _, e in where))
    xyz = fe.xyz[fe.grid_index(grids)]
    out = np.zeros(len(cands), bool)
    for i, c in enumerate(cands):
        if c.family not in fams:
            continue
        if isinstance(c.term, ElementFactor):
            out[i] = bool(els.intersection(int(e) for e in c.term.elements))
            continue
        if set(int(g) for g in c.grids).intersection(grids):
            out[i] = True
            continue
        d = np.linalg.norm(xyz - np.asarray(c.center) * length_m, axis=1).min()
        out[i] = d <= MATCH_SIZES * max(float(c.size), 1e-12) * length_m
    return out


def _diagnosis_default(field: str) -> str:
    """The campaign's default of a ``[diagnosis]`` field (``target``, ``continuation_lines``)."""
    from frfcal.campaign._schema import DiagnosisSection

    return getattr(DiagnosisSection(), field)


def physical(term, c):
    """Physical value of a term at normalized magnitude c (spring rate, mass, or the factor 1 + c)."""
    from femodel import ElementFactor

    return 1.0 + float(c) if isinstance(term, ElementFactor) else float(term.value(c))


def main(argv=None) -> int:
    from frfcal.effects import standard_effects

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dof", type=int, default=200_000)
    ap.add_argument("--effect", default="contact_spring", choices=sorted(MATCHING),
                    help="the undeclared effect of the truth (a family of frfcal.effects.standard_effects)")
    ap.add_argument("--candidates-per-family", type=int, default=500, help="CandidateOptions.max_per_family")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--starts", type=int, default=4, help="calibration multi-start (untimed preparation)")
    ap.add_argument("--n-check", type=int, default=None,
                    help="nonlinear checks of the screening (default: the campaign's [diagnosis] top_n); each "
                         "family's best is checked too and each checked region's alternatives, as the stage does")
    ap.add_argument("--top", type=int, default=3, help="candidates fitted singly in the acceptance")
    ap.add_argument("--cv-realizations", type=int, default=5, help="cross-validation splits of the acceptance")
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--target", choices=("debiased", "equalized"), default=None,
                    help="the screening's and the acceptance's target ([diagnosis] target; default: the campaign "
                         "default, " + repr(_diagnosis_default("target")) + "); the hold-out SD of the trials is on "
                         "the same target's hold-out channels")
    ap.add_argument("--continuation-lines", choices=("raw", "half-bandwidth"), default=None,
                    help="[diagnosis] continuation_lines of the debiased target: every raw line at the continuation "
                         "stages, or the raw line nearest each point of the stage's half-bandwidth grid (default: "
                         "the campaign default, " + repr(_diagnosis_default("continuation_lines")) + ")")
    ap.add_argument("--no-zoom", dest="zoom", action="store_false",
                    help="no zoom of the point families (CandidateOptions.zoom_rounds = 0)")
    ap.add_argument("--no-stage", dest="stage", action="store_false",
                    help="skip the run of the campaign's diagnose stage itself (untimed in the table above; its "
                         "wall time, verdict and log are reported after it)")
    ap.add_argument("--no-model-sd", action="store_true", help="skip the full-order hold-out SD with truth damping")
    ap.add_argument("--no-refine", dest="refine", action="store_false",
                    help="skip the raw-line refinement of the chosen effect (untimed; needs the model SD)")
    ap.add_argument("--no-warm", dest="warm", action="store_false",
                    help="fit_with of a single candidate from (p_baseline, c) through the continuation stages, "
                         "not from its converged nonlinear check (fit_with's warm)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "diagnosis.json"))
    args = ap.parse_args(argv)
    args.target = args.target or _diagnosis_default("target")
    args.continuation_lines = args.continuation_lines or _diagnosis_default("continuation_lines")
    from frfcal._malloc import keep_large_allocations

    malloc_tuned = keep_large_allocations()  # as the frfcal command does

    import femodel
    from calibration import make_executor
    from frfcal.campaign import load_campaign
    from frfcal.campaign._stages import build_model, calibrate_stage, equalize_stage, group_stage, identify_stage, load_stage
    from frfcal.synth import SynthChannel, synthesize

    load0 = os.getloadavg()
    tmp = Path(tempfile.mkdtemp(prefix="bench_diag_"))
    prep = {}
    t = time.perf_counter()
    ex = femodel.example_subframe(tmp / "model", target_dof=args.dof, gap_mm=2.0)
    pm0 = femodel.parametric_model(ex.params)
    prep["example + parametric model"] = time.perf_counter() - t
    print(f"example: {ex.n_dof} DOF, {len(ex.gap_pairs)} gap pairs ({prep['example + parametric model']:.1f} s)",
          flush=True)
    g = np.asarray(pm0.assembly.model.grid_ids)
    grids = g[np.linspace(3, len(g) - 10, 20).astype(int)]
    dirs = np.tile([0.0, 0.0, 1.0], (20, 1))
    dirs[1::4] = [1.0, 0.0, 0.0]
    dirs[2::4] = [0.0, 1.0, 0.0]
    names = [f"acc{i + 1}" for i in range(20)]
    sensors = [SynthChannel(n, int(gid), tuple(d)) for n, gid, d in zip(names, grids, dirs)]
    drives = [SynthChannel("force17", int(grids[16]), tuple(dirs[16]))]  # collocated with acc17
    cal_ch = [names[i] for i in (0, 4, 6, 9, 11, 12, 13, 14, 17, 18, 19)]
    hold_ch = [n for n in names if n not in cal_ch]

    t = time.perf_counter()
    std = standard_effects(pm0, sensors, drives, gap=ex.gap_pairs, band_hz=BAND)
    effects = std[args.effect]
    sc = synthesize(ex.bdf, ex.params, tmp / "data", sensors=sensors, drives=drives, band_hz=BAND, n_articles=1,
                    seed=args.seed, parametric=pm0, write_uff=False, effects=effects)
    prep["effect + truth data"] = time.perf_counter() - t
    for e in effects:
        print(f"truth effect: {e.term.description} (p = 1 at {e.value:.4g} {e.unit})", flush=True)
    del pm0
    camp = load_campaign(sc.write_campaign(
        tmp / "campaign.toml", calibrate=cal_ch, holdout=hold_ch, band_hz=BAND,
        calibration={"starts": args.starts}, crossvalidation={"realizations": 0}, diagnosis={"target": args.target, "continuation_lines": args.continuation_lines},
        output={"dir": str(tmp / "out"), "figures": False}))

    def log(m):
        print("  " + m, flush=True)

    t = time.perf_counter()
    load = load_stage(camp, log)
    _, model = build_model(camp, load, log)
    articles = identify_stage(camp, load.articles, log).attached(load.articles)
    eq = equalize_stage(camp, articles)
    groups = group_stage(camp, articles, eq, log)
    pool = make_executor(camp.execution.scheduler, args.workers or camp.execution.workers, progress=None)
    pool.start()  # also runs the screening's nonlinear checks and the cross-validation below
    try:
        cal = calibrate_stage(camp, model, articles, eq, groups, pool, log)
        prep["campaign calibration (load, identify, equalize, calibrate, refine)"] = time.perf_counter() - t
        return _diagnose(args, ex, sc, effects, camp, model, articles, eq, cal, pool, sensors, drives, hold_ch,
                         prep, load0, malloc_tuned, load, groups)
    finally:
        pool.close()


def _diagnose(args, ex, sc, effects, camp, model, articles, eq, cal, pool, sensors, drives, hold_ch, prep, load0,
              malloc_tuned, load=None, groups=None) -> int:
    import femodel
    from calibration import accept, cross_validate, fit_with, holdout_sd, screen, shifted_solver
    from femodel import CandidateOptions, candidate_context, candidate_regions, generate_candidates
    from frfcal.campaign._diagnose import candidate_terms
    from frfcal.campaign._diagnose import point_zoom
    from frfcal.campaign._diagnose import debiased_data, screening_target
    from frfcal.campaign._stages import equalized_data

    pm = model.parametric
    (m,) = cal.members
    p_cal, sur, basis = m.p, m.surrogate, m.basis
    zeta = camp.calibration.zeta0
    quantity = articles[0].quantity
    t0 = time.perf_counter()
    target = screening_target(camp, articles, eq)  # [diagnosis] target (--target), as the diagnose stage builds it
    data, cont = target.member(m.articles)
    if target.kind == "debiased":
        hold = [debiased_data(articles[i], hold_ch, zeta) for i in m.articles]
    else:
        hold = [equalized_data(articles[i], zeta, eq.freq_hz, hold_ch) for i in m.articles]
    prep["screening target (" + target.kind + ")"] = time.perf_counter() - t0
    shift_hz = max(BAND[0] / 4.0, BAND[1] / 50.0)  # build_surrogate's default
    print(f"calibrated: surrogate {sur.size}, p {np.array2string(p_cal, precision=3)}; "
          f"preparation {sum(prep.values()):.0f} s (not timed)", flush=True)

    # ------------------------------------------------------------------ timed diagnosis
    clock = Clock()
    c_all = clock.start()
    t0 = clock.start()
    cctx = candidate_context(pm, sensors=[int(s.grid) for s in sensors],
                             drives=[(int(d.grid), d.direction) for d in drives],
                             options=CandidateOptions(max_per_family=args.candidates_per_family,
                                                      zoom_rounds=3 if args.zoom else 0))
    cands = list(generate_candidates(pm, context=cctx))
    clock.stop("candidate generation", t0)
    families = list(dict.fromkeys(c.family for c in cands))
    per_family = {f: sum(c.family == f for c in cands) for f in families}

    t0 = clock.start()
    by_term, deriv_s = {}, {}
    for f in families:  # as the diagnose stage: one term_derivatives call (a family's clusters in one pass)
        t1 = time.process_time()
        mine = [c for c in cands if c.family == f]
        by_term.update(zip((c.name for c in mine), candidate_terms(pm, mine, p_cal)))
        deriv_s[f] = time.process_time() - t1
    terms = [by_term[c.name] for c in cands]
    clock.stop("term derivatives", t0)

    t0 = clock.start()
    solve = shifted_solver(model, sur.p_basis, shift_hz)  # one factorization, shared by every extension below
    clock.stop("shared factorization K + s M", t0)

    t0 = clock.start()
    dcfg = camp.diagnosis  # the diagnose stage's screening: its check count, evaluations, families, regions
    s = screen(sur, basis, p_cal, data, zeta, terms, pm.lower, pm.upper, quantity=quantity, model=model,
               n_check=args.n_check or dcfg.top_n, max_nfev=dcfg.max_evaluations, solve=solve,
               continuation=cont, executor=pool, groups=[c.family for c in cands],
               zoom=point_zoom(cctx, pm, p_cal, cands, terms), zoom_rounds=cctx.options.zoom_rounds,
               regions=candidate_regions(cands))
    clock.stop("screening (linear + zoom + nonlinear checks)", t0)
    clock.rows["  of which the zoom (derivatives + linear scores)"] = {"wall_s": s.timings_s["zoom"],
                                                                       "cpu_s": s.timings_s["cpu: zoom"]}
    per_family = {f: sum(c.family == f for c in cands) for f in families}  # the zoomed candidates included

    t0 = clock.start()
    cvo = dict(n_realizations=args.cv_realizations, seed=args.seed, quantity=quantity, max_nfev=20, executor=pool)
    p_b = s.p_baseline
    h_before = float(np.mean([holdout_sd(sur, p_b, h, zeta, quantity) for h in hold]))
    cv_before = cross_validate(sur, data, p_b, pm.lower, pm.upper, zeta, **cvo).sd_test
    floor = sc.floor_sd(hold_ch, BAND)
    n_ind = 2 * sum(h.n_values for h in hold) // camp.calibration.samples_per_half_bandwidth
    by_name = {c.name: k for k, c in enumerate(terms)}

    def start_c(name):
        chk = s.check(name)
        return chk.c if chk is not None else s.c_linear[by_name[name]]

    def trial(names_):
        fit = fit_with(sur, basis, model, [terms[by_name[n]] for n in names_], data, zeta, pm.lower, pm.upper,
                       p0=p_b, c0=[start_c(n) for n in names_], continuation=cont, quantity=quantity,
                       solve=solve, max_nfev=dcfg.max_evaluations,
                       warm=s.check(names_[0]) if len(names_) == 1 and args.warm else None,
                       with_basis=False)
        fits[tuple(names_)] = fit
        h = float(np.mean([holdout_sd(fit.surrogate, fit.x, d, zeta, quantity) for d in hold]))
        return {"candidates": list(names_), "c": fit.c.tolist(), "sd_fit": fit.sd, "holdout_sd": h,
                "cv_test_mean": None, "accepted": False, "stop": False, "time_s": fit.time_s,
                "reason": "not cross-validated: the acceptance decides on the lowest hold-out SD"}

    def decide(r, before_h, before_cv, n_added):
        """Cross-validation and ``accept`` of one trial, as the diagnose stage decides on its best trial."""
        fit = fits[tuple(r["candidates"])]
        cv = cross_validate(fit.surrogate, data, fit.x, fit.lower, fit.upper, zeta, **cvo).sd_test
        a = accept(before_h, r["holdout_sd"], before_cv, cv, floor, n_added, n_ind)
        r.update(cv_test_mean=float(np.mean(cv)), accepted=bool(a.accepted), stop=bool(a.stop), reason=a.reason)
        return cv

    top = [s.names[i] for i in s.order[:args.top]]
    trials, fits = [], {}
    for n in top:  # singly: each recalibrated, the lowest hold-out SD decided on
        trials.append(trial([n]))
    best1 = min(trials, key=lambda r: r["holdout_sd"])
    cv_best = decide(best1, h_before, cv_before, 1)
    # two candidates on common DOF (a gap and a window of it) are one effect twice: the partner acts elsewhere
    on_best = terms[by_name[best1["candidates"][0]]].rows
    n_partner = max(args.top, 10)
    other = next((s.names[i] for i in s.order[:n_partner] if not np.intersect1d(on_best, terms[i].rows).size), None)
    if other is not None:  # the best single one with the best-ranked candidate acting elsewhere, against it
        r = trial(best1["candidates"] + [other])
        decide(r, best1["holdout_sd"], cv_best, 1)
        r["against"] = best1["candidates"]
        trials.append(r)
    clock.stop("acceptance (fit_with, hold-out, cross-validation, accept)", t0)
    total = clock.stop("diagnosis total", c_all)
    mem = peak_memory_gb()

    # ------------------------------------------------------------------ the truth (untimed)
    fe = pm.assembly.model
    length_m = float(femodel.unit_system(fe.units).length_m)
    hit = matches(fe, length_m, effects, args.effect, cands)
    rank_of = {s.names[i]: r + 1 for r, i in enumerate(s.order)}
    true_names = [c.name for c, h in zip(cands, hit) if h]
    true_rank = min((rank_of[n] for n in true_names), default=None)
    true_best = min(true_names, key=rank_of.get) if true_names else None
    accepted = [r for r in trials if r["accepted"] and len(r["candidates"]) == 1]
    chosen = min(accepted, key=lambda r: r["holdout_sd"]) if accepted else None
    mag = None
    if true_best is not None:
        cand = cands[by_name[true_best]]
        fitted = next((r for r in trials if r["candidates"] == [true_best]), None)
        c_est = fitted["c"][0] if fitted else float(start_c(true_best))
        truth_total = sum(physical(e.term, e.term.normalized(e.value)) *
                          (len(e.term.dofs) if hasattr(e.term, "dofs") else 1) for e in effects)
        n_where = len(cand.term.dofs) if hasattr(cand.term, "dofs") else 1
        mag = {"candidate": true_best, "c": c_est, "value_each": physical(cand.term, c_est), "n_where": n_where,
               "value_total": physical(cand.term, c_est) * (n_where if not hasattr(cand.term, "elements") else 1),
               "truth_value_each": [e.value for e in effects], "truth_total": truth_total,
               "unit": cand.term.unit or "factor"}
    sd_model, refined = {}, None
    if not args.no_model_sd:
        t = time.perf_counter()
        sd_model["calibrated deck (raw-line refined p)"] = sc.model_sd(p_cal, 0, hold_ch, BAND)
        sd_model["deck at the screening baseline p (before)"] = sc.model_sd(p_b, 0, hold_ch, BAND)
        if chosen is not None:
            n = chosen["candidates"][0]
            term = cands[by_name[n]].term
            fit = fits[(n,)]
            sd_model[f"deck + {n}"] = sc.model_sd(fit.p, 0, hold_ch, BAND, terms=[term],
                                                  values=[physical(term, fit.c[0])])
            if args.refine:
                # the diagnose stage's final answer: the accepted set refined on the raw lines (damping
                # estimated, re-basis cycles on the extended deck), the "after" the campaign reports
                from frfcal.campaign._diagnose import _refined

                t1 = time.perf_counter()
                ref, h_ref, x_ref, sur_ref = _refined(camp, pm, model, articles, m, fit, [term], quantity,
                                                      lambda msg: print("  " + msg, flush=True))
                prep["raw-line refinement of the chosen effect (as the diagnose stage)"] = time.perf_counter() - t1
                c_ref = float(x_ref[pm.n_params])
                refined = {"candidate": n, "c": c_ref, "value_each": physical(term, c_ref),
                           "holdout_sd_estimated_damping": h_ref,
                           "sd_raw": None if ref is None else float(ref.sd_raw)}
                if ref is not None:  # what the raw lines resolve of the refined size (as the stage reports it)
                    from frfcal.campaign._diagnose import _size_uncertainty, effect_identifiability

                    idf = effect_identifiability(camp, [articles[i] for i in m.articles], sur_ref, x_ref, ref,
                                                 fit.lower, fit.upper, list(pm.names) + [n], quantity, pm.n_params)
                    refined.update(_size_uncertainty(idf, pm.n_params, c_ref))
                sd_model[f"deck + {n}, refined on the raw lines (the campaign's answer)"] = sc.model_sd(
                    x_ref[:pm.n_params], 0, hold_ch, BAND, terms=[term], values=[physical(term, c_ref)])
        sd_model["truth (deck + true effect at p_true)"] = sc.model_sd(
            sc.p_true[0], 0, hold_ch, BAND, terms=[e.term for e in effects], values=[e.value for e in effects])
        prep["full-order hold-out SD with truth damping"] = time.perf_counter() - t

    # ------------------------------------------------------------------ the diagnose stage itself
    stage = None
    if args.stage:  # the campaign's stage end to end on the same calibrated member: all of what it does
        from frfcal.campaign._diagnose import diagnose_stage
        from frfcal.campaign._stages import crossvalidate_stage, validate_stage

        print("the campaign's diagnose stage (validate, cross-validate untimed):", flush=True)
        t_st = time.perf_counter()
        lines = []

        def slog(msg):
            lines.append([round(time.perf_counter() - t_st, 1), msg])
            print(f"  {lines[-1][0]:7.1f} s  {msg}", flush=True)

        bounds = (pm.lower, pm.upper)
        val = validate_stage(camp, articles, cal, bounds, slog)
        xval = crossvalidate_stage(camp, articles, eq, cal, bounds, pm.parameters.names, pool, slog)
        t_d, c_d = time.perf_counter(), cpu_s()
        diag = diagnose_stage(camp, load, pm, model, articles, eq, cal, val, xval, pool, slog, groups)
        (dm,) = diag.members
        stage = {"wall_s": time.perf_counter() - t_d, "cpu_s": cpu_s() - c_d, "verdict": dm.verdict,
                 "reason": dm.reason, "accepted": [{k: a.get(k) for k in ("name", "family", "size", "value", "unit")}
                                                   for a in dm.accepted], "log": lines}

    # ------------------------------------------------------------------ report
    print()
    print(f"target {target.kind}: {sum(d.frf.shape[0] for d in data)} lines at zeta0, "
          + ", ".join(f"{sum(d.frf.shape[0] for d in ds)} at {z:g}" for z, ds in cont))
    print(f"{ex.n_dof} DOF, {len(cands)} candidates ({len(s.zoomed)} of them zoomed), surrogate {sur.size}, "
          f"{data[0].frf.shape[0]} lines x {data[0].frf.shape[1]} outputs x {data[0].frf.shape[2]} drives; "
          f"{os.cpu_count()} cores, load average {load0[0]:.1f} at start, {os.getloadavg()[0]:.1f} now")
    print(f"{'family':<26}{'candidates':>12}{'derivative CPU':>16}")
    for f in families:
        print(f"{f:<26}{per_family[f]:>12d}{deriv_s[f]:>15.2f}s")
    print()
    print(f"{'diagnosis stage':<60}{'wall':>9}{'CPU':>9}  (CPU: this process + pool workers)")
    for k, v in clock.rows.items():
        print(f"{k:<60}{v['wall_s']:>8.1f}s{v['cpu_s']:>8.1f}s")
    print(f"peak memory {mem:.2f} GB (ru_maxrss, whole run); target total < 60 s: "
          f"{'met' if total < 60 else 'NOT met'} ({total:.1f} s wall)")
    print()
    print(f"{'not timed':<60}{'wall':>9}")
    for k, v in prep.items():
        print(f"{k:<60}{v:>8.1f}s")
    print()
    print(f"screening: baseline SD {s.sd_baseline:.4g}; top {min(5, len(s.order))}: " + ", ".join(
        f"{s.names[i]} ({cands[i].family}, {100 * (s.check(s.names[i]).explained if s.check(s.names[i]) else s.explained[i]):.1f} %)"
        for i in s.order[:5]))
    print(f"true effect ({args.effect}): rank {true_rank} of {len(cands)} ({len(true_names)} matching candidates; "
          f"best {true_best})")
    if mag:
        print(f"magnitude: estimated {mag['value_total']:.4g} {mag['unit']} ({mag['n_where']} place(s) x "
              f"{mag['value_each']:.4g}), true {mag['truth_total']:.4g}")
    if refined:
        print(f"refined on the raw lines (the campaign's answer): {refined['candidate']} at {refined['value_each']:.4g}"
              f" per place, raw-line SD {refined['sd_raw']}, hold-out SD {refined['holdout_sd_estimated_damping']}"
              " (estimated damping)")
        if "size_identifiable" in refined:
            sd = refined["size_std_percent"]
            print("  its size as the raw lines resolve it: "
                  + (f"s.d. from the noise {sd:.3g} %" if sd is not None else "s.d. not resolved")
                  + f", {refined['size_identifiability']}; largest correlation {refined['size_max_correlation']}")
    print()
    print(f"{'acceptance trial':<52}{'c':>18}{'hold-out SD':>13}{'/floor':>8}{'CV test':>11}  verdict")
    print(f"{'before (existing parameters re-fitted)':<52}{'':>18}{h_before:>13.4g}{h_before / floor:>8.2f}"
          f"{np.mean(cv_before):>11.4g}")
    for r in trials:
        lab = " + ".join(r["candidates"]) + (f" (vs {r['against'][0]})" if "against" in r else "")
        cs = ", ".join(f"{c:.3g}" for c in r["c"])
        cvm = "-" if r["cv_test_mean"] is None else f"{r['cv_test_mean']:.4g}"
        verdict = "-" if r["cv_test_mean"] is None else "ACCEPT" if r["accepted"] else "reject"
        print(f"{lab[:51]:<52}{cs:>18}{r['holdout_sd']:>13.4g}{r['holdout_sd'] / floor:>8.2f}"
              f"{cvm:>11}  {verdict}{' stop' if r['stop'] else ''}: {r['reason']}")
    if not any("against" in r for r in trials):
        print(f"(no combination trial: none of the {n_partner} best candidates acts off the best single one's DOF)")
    print(f"floor (hold-out raw lines, truth vs its noise): {floor:.4g}")
    for k, v in sd_model.items():
        print(f"hold-out SD with truth damping, {k}: {v:.4g} ({v / floor:.2f} x floor)")
    if stage is not None:
        print(f"the campaign's diagnose stage end to end (residual check, screening, acceptance with its "
              f"combinations and re-screening, raw-line refinement): {stage['wall_s']:.1f} s wall, "
              f"{stage['cpu_s']:.1f} s CPU; verdict {stage['verdict']}: {stage['reason']}")

    out = {
        "dof": int(ex.n_dof), "effect": args.effect, "target": target.kind,
        "continuation_lines": args.continuation_lines,
        "target_lines": {"zeta0": [int(d.frf.shape[0]) for d in data],
                         **{f"{z:g}": [int(d.frf.shape[0]) for d in ds] for z, ds in cont}}, "truth_effects": [e.record(sc.articles) for e in effects],
        "n_candidates": len(cands), "n_zoomed": len(s.zoomed), "zoom": bool(args.zoom),
        "candidates_per_family": per_family, "cap_per_family": args.candidates_per_family,
        "derivative_cpu_s_per_family": deriv_s, "cores": os.cpu_count(), "load_avg_start": load0,
        "load_avg_end": os.getloadavg(), "malloc_kept_large_blocks": malloc_tuned,
        "timings": clock.rows, "diagnosis_total_wall_s": total, "target_s": 60.0, "peak_memory_gb": mem,
        "untimed_s": prep, "surrogate_size": int(sur.size), "basis_rows": int(basis.shape[0]),
        "data_shape": list(data[0].frf.shape), "continuation_zeta": [z for z, _ in cont], "zeta0": zeta,
        "starts": args.starts + 1, "warm_start_from_checks": bool(args.warm), "screening": {k: v for k, v in s.to_dict().items() if k != "candidates"},
        "top_linear": [{"name": s.names[i], "family": cands[i].family, "explained": float(s.explained[i]),
                        "c_linear": float(s.c_linear[i])} for i in s.order[:20]],
        "true_rank": true_rank, "true_matching": true_names, "true_best": true_best, "magnitude": mag,
        "holdout_sd_before": h_before, "cv_test_before": list(map(float, cv_before)), "floor_holdout": floor,
        "n_independent": int(n_ind), "trials": trials, "holdout_sd_truth_damping": sd_model, "refined": refined,
        "diagnose_stage": stage,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1, default=float))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
