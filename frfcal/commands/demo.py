"""``frfcal demo``: the whole job of the toolkit on the bundled example, as one campaign.

1. ``frfcal example subframe --gap-mm 2``: the subframe FE model with its 17
   parameters and a doubler sheet facing the rail web across a 2 mm air gap
   (nothing joins them in the model);
2. ``frfcal pretest``: 20 accelerometers and a shaker by Effective Independence;
3. the campaign file ``campaign.toml`` (written here, docs/campaign.md): five
   simulated articles (``[simulation]``: the deck at the paper's Table 2.1
   changes plus scatter, free-free, damping per mode); on SF1-SF3 the gap is
   closed (a contact spring across the gap pairs), on SF4-SF5 open; SF5 has a
   loose part that rattles at the higher force level; the simulated lab sweeps
   each at 0.25 N and 1 N (at 1 N the sharpest resonance reaches about 270 m/s^2 of the 500 m/s^2 accelerometer range); calibration of the 17 parameters on 11 channels,
   hold-out validation on 9, cross-validation, one calibration per article group;
4. ``frfcal run campaign.toml``: every stage, stored under ``DIR/campaign``, through
   the diagnose stage (its nonlinearity gate compares each article's 1 N run with its
   0.25 N run) and the report ``DIR/campaign/report.html``;
5. the closing summary (:func:`closing_summary`, also ``DIR/demo_summary.json``): the
   report's path, the grouping, SD before/after calibration and diagnosis beside the
   floor per group, the effect found (or what ranked first), the nonlinear article(s).
"""

from __future__ import annotations

import argparse

from frfcal.campaign._acquire import PAPER_TABLE_2_1, paper_offsets  # noqa: F401  (the demo's truth)

HELP = "run the example campaign: model with an air gap, pretest, 5 simulated articles at 2 levels, calibration"

ARTICLES = ("SF1", "SF2", "SF3", "SF4", "SF5")
GAP_CLOSED = ("SF1", "SF2", "SF3")
LOOSE = "SF5"
LEVELS_N = (0.25, 1.0)
#: relative FRF error the settle detector leaves per line (the level check allows it between runs)
SETTLE_TOLERANCE = 3e-3


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="demo-output", help="output directory (default demo-output)")
    parser.add_argument("--dof", type=int, default=5000, help="approximate model size in DOF (default 5000)")
    parser.add_argument("--band", type=float, nargs=2, default=(100.0, 400.0), metavar=("LO_HZ", "HI_HZ"),
                        help="calibration band, Hz (default 100 400, as in the paper)")
    parser.add_argument("--starts", type=int, default=2, help="Latin-hypercube starts besides the nominal one (default 2)")
    parser.add_argument("--realizations", type=int, default=5,
                        help="cross-validation realizations (default 5: the fewest whose agreement can clear a "
                             "parameter of a weak combination as identifiable)")
    parser.add_argument("--workers", type=int, default=None, help="local worker processes (default: all cores)")


def _step(title: str) -> None:
    print(f"\n=== {title}", flush=True)


def _call(argv: list[str]) -> None:
    """Run one frfcal command as a user would type it (printed with a ``$``)."""
    from frfcal.cli import main

    print("$ frfcal " + " ".join(argv), flush=True)
    status = main(argv)
    if status != 0:
        raise RuntimeError(f"demo: 'frfcal {' '.join(argv)}' failed with status {status}")


def contact_rate(pm, layout_path, gap_pairs, band_hz) -> tuple[float, int]:
    """Rate (N/m) and component of the demo's contact spring: ``frfcal.effects`` sizing of a closed gap."""
    from frfcal.effects import standard_effects
    from frfcal.synth import SynthChannel
    from labdata import read_layout_file

    lay = read_layout_file(layout_path)
    sens = [SynthChannel(n, g, d) for n, g, d in zip(lay.names("channels"), lay.grids("channels"),
                                                     lay.directions("channels"))]
    drv = [SynthChannel(n, g, d) for n, g, d in zip(lay.names("drives"), lay.grids("drives"), lay.directions("drives"))]
    (eff,) = standard_effects(pm, sens, drv, gap=gap_pairs, band_hz=band_hz)["contact_spring"]
    comp = eff.term.dofs[0][1]
    return float(eff.term.scale), int(comp)


def write_campaign(path, *, params, layout, channels, band, gap_pairs, rate, component, starts, realizations,
                   workers=None) -> None:
    """The demo's campaign file (docs/campaign.md): simulated acquisition, calibration per article group."""
    import json

    lo, hi = band
    calibrate, holdout = channels[::2] + channels[1:2], [n for n in channels[1::2] if n != channels[1]]
    pairs = ", ".join(f"[{a}, {b}]" for a, b in gap_pairs)
    execution = "" if workers is None else f"\n[execution]\nworkers = {workers}\n"
    text = f"""# The frfcal demo campaign (written by 'frfcal demo'; run it with 'frfcal run campaign.toml')
[model]
parameters = "{params}"

[layout]
file = "{layout}"

[acquisition]
driver = "sim"
dir = "runs"

[acquisition.plan]          # the stepped-sine plan (docs/acquisition.md); channels from the layout
name = "demo"
sample_rate_hz = 1280.0
[acquisition.plan.lines]    # no predicted poles: the controller finds the articles' peaks on a 1 % background
kind = "bandwidth"
start_hz = {0.8 * lo:g}
stop_hz = {1.1 * hi:g}
background_step = 0.01
[acquisition.plan.force]
levels_n = {json.dumps(list(LEVELS_N))}
[acquisition.plan.settle]
tolerance = {SETTLE_TOLERANCE:g}
assumed_damping = 0.002
[acquisition.plan.measure]
blocks = 3
n_harmonics = 1
[acquisition.plan.limits]   # a local doubler-sheet mode near the shaker peaks at thousands of m/s^2 per N:
acceleration_m_s2_max = 1e4 # its few lines clip the accelerometers (flagged, left out), the sweep goes on
on_overload = "flag"
drive_v_max = 20.0          # and the shaker's force drops there (back-EMF): more voltage for the force level
[acquisition.plan.refine]
enabled = true
lines_per_bandwidth = 3
span_bandwidths = 2
peak_ratio = 1.02           # the noise is low: any local maximum of three background lines is a peak to refine
[acquisition.plan.ensemble]
articles = {json.dumps(list(ARTICLES))}

[simulation]                # what the articles are (the model does not know the gap or the loose part)
offsets = "paper"
scatter = 0.003
seed = 7
zeta_range = [1e-3, 3e-3]
mode_factor = 1.5
noise_rms = 2e-5

[[simulation.effect]]       # the air gap is closed on SF1-SF3: contact springs across the facing grids
name = "gap_contact"
kind = "spring"
articles = {json.dumps(list(GAP_CLOSED))}
pairs = [{pairs}]
components = [{component}]
rate_n_per_m = {rate:.6g}

[simulation.loose_part]     # SF5 rattles at the high level
article = "{LOOSE}"
mode = 3                    # the third elastic mode (~298 Hz); by default the part would sit on the largest
                            # drive-point resonance, the doubler sheet's, whose lines clip at 1 N (left out)
shift = 0.003
from_level_n = {LEVELS_N[-1]:g}

[channels]
calibrate = {json.dumps(calibrate)}
holdout = {json.dumps(holdout)}

[band]
low_hz = {lo:g}
high_hz = {hi:g}

[calibration]
starts = {starts}
max_cycles = 2
refine_cycles = 1
ensemble = "group"
n_groups = 2

[crossvalidation]
realizations = {realizations}

[diagnosis]                 # docs/diagnosis.md; sized for the demo's 5-minute budget on 2 cores
top_n = 2                   # candidates re-fitted nonlinearly after the linear screening, then recalibrated
max_effects = 1             # one effect per article group at most
max_evaluations = 15        # residual evaluations per screening fit stage
candidates = {{ spread_grids = 15 }}  # ground springs and lumped masses at 15 spread grids (default: every grid when <= 500 candidates, else 40)
{execution}
[output]
dir = "campaign"
"""
    from pathlib import Path

    Path(path).write_text(text)


def run(args) -> int:
    import json
    import os
    import time
    from pathlib import Path

    import femodel
    from frfcal.campaign import load_campaign, run_campaign
    from labdata import read_layout_file

    t_start = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    lo, hi = args.band
    model_dir = out / "model"

    _step("[1/4] FE model: the subframe with 17 parameters and a doubler sheet 2 mm off the rail web")
    print(f"$ frfcal example subframe --dof {args.dof} --units mm-t-s --gap-mm 2 --out {model_dir}", flush=True)
    ex = femodel.example_subframe(model_dir, target_dof=args.dof, units="mm-t-s", gap_mm=2.0)
    print(f"wrote {ex.bdf} ({ex.n_dof} DOF, {ex.mass_kg:.2f} kg) and {ex.params}; air gap 2 mm: "
          f"{len(ex.gap_pairs)} facing grid pairs that no element joins")

    _step("[2/4] pretest: 20 accelerometers and a shaker for the first 20 elastic modes")
    layout = out / "layout.json"
    _call(["pretest", str(ex.bdf), "--units", "mm-t-s", "--sensors", "20", "--modes", "20", "--out", str(layout)])

    _step("[3/4] the campaign file: 5 simulated articles, gap closed on SF1-SF3, SF5 loose at the high level")
    pm = femodel.parametric_model(ex.params)
    rate, comp = contact_rate(pm, layout, ex.gap_pairs, (lo, hi))
    print(f"closed gap: {len(ex.gap_pairs)} contact springs of {rate:.4g} N/m along component {comp} "
          "(frfcal.effects sizing of a closed gap)")
    names = list(read_layout_file(layout).names("channels"))
    campaign = out / "campaign.toml"
    write_campaign(campaign, params=Path(os.path.relpath(ex.params, out)).as_posix(), layout=layout.name, channels=names, band=(lo, hi),
                   gap_pairs=ex.gap_pairs, rate=rate, component=comp, starts=args.starts,
                   realizations=args.realizations, workers=args.workers)
    print(f"wrote {campaign}")

    _step("[4/4] $ frfcal run campaign.toml")
    camp = load_campaign(campaign)
    res = run_campaign(camp, log=lambda m: print(m, flush=True))

    wall = time.perf_counter() - t_start
    t = os.times()
    cpu = t.user + t.system + t.children_user + t.children_system
    _step(f"summary ({wall:.0f} s wall, {cpu:.0f} s CPU including worker processes)")
    lines, headline = closing_summary(res, checks=None if res.get("diagnosis") else _level_checks(res, out))
    for line in lines:
        print(line)
    print(f"campaign file {campaign}; every result under {out / 'campaign'} (calibration.json, diagnosis.json, "
          "figures, stages/)")
    headline.update(time_s=wall, cpu_s=cpu)
    (out / "demo_summary.json").write_text(json.dumps(headline, indent=1, default=str))
    return 0


def _level_checks(res, out) -> dict:
    """Level check of every article from the acquired run files (when the diagnose stage did not run):
    article -> flagged (bool) or the reason it could not be made."""
    from pathlib import Path

    from frfcal.campaign._acquire import level_checks, runs_by_level

    runs = runs_by_level(sorted((Path(out) / "campaign" / "runs").glob("*.h5")))
    return {a: ld if isinstance(ld, str) else bool(ld.flagged)
            for a, ld in level_checks(runs, settle_tolerance=SETTLE_TOLERANCE).items()}


def _g(x, fmt: str = ".3g") -> str:
    return "-" if x is None else format(float(x), fmt)


def _nonlinear(diag: dict) -> dict:
    """Flagged articles of the diagnosis' nonlinearity gate: article -> evidence in words."""
    import math
    out = {}
    for gate in diag.get("gates", []):
        nl = gate.get("nonlinearity") or {}
        if not nl.get("flagged"):
            continue
        why = []
        for m in nl.get("modes", []):
            if m.get("levels") and m.get("values"):
                why.append(f"mode at {m['frequency_hz']:.4g} Hz: {m['quantity']} {m['values'][0]:.4g} -> "
                           f"{m['values'][-1]:.4g} from {min(m['levels']):g} to {max(m['levels']):g} N "
                           f"({m['z']:.3g} sigma)")
        level = nl.get("level") or {}
        fm = [f for f in level.get("modes_hz", []) if f is not None]
        for p in level.get("pairs", []):
            if p.get("flagged") and p.get("peak_hz") is not None and math.isfinite(p["peak_hz"]):
                near = min(fm, key=lambda f: abs(f - p["peak_hz"])) if fm else None
                why.append(f"FRFs at {p['level_high']:g} and {p['level_low']:g} N differ by {p['z']:.3g} sigma, "
                           f"most at {p['peak_hz']:.4g} Hz" + (f" (nearest mode {near:.4g} Hz)" if near else ""))
        out[gate["article"]] = "; ".join(why[:2]) or nl.get("verdict") or "flagged"
    return out


def closing_summary(res: dict, checks: dict | None = None) -> tuple[list, dict]:
    """The demo's closing lines and its headline numbers (``demo_summary.json``) from ``run_campaign``'s result.

    Parameters
    ----------
    res : dict
        ``run_campaign``'s result: ``members`` (calibration.json), ``grouping``,
        ``articles``, ``stages``, and when the late stages ran ``diagnosis``
        (``write_diagnosis``) and ``report`` (path of report.html).
    checks : dict, optional
        article -> level check flagged (bool) or why there is none; used when
        the result has no diagnosis (else its nonlinearity gate is used).

    Returns
    -------
    (lines, headline) : list of str, dict
        SD values are the toolkit's relative log-magnitude deviation (docs/calibration.md), dimensionless.
    """
    from frfcal.campaign._diagnose import size_words

    lines, head = [], {}
    report = res.get("report")
    lines.append(f"report: {report}  (one self-contained HTML page: open it in a browser)" if report else
                 "report: not written (the report stage did not run)")
    head["report"] = report
    lines.append("stages: " + ", ".join(f"{k} {v['status']} ({v.get('time_s') or 0:.0f} s)"
                                        for k, v in res.get("stages", {}).items()))
    arts = res.get("articles") or []
    labels = (res.get("grouping") or {}).get("labels")
    groups = []
    if labels is not None and len(labels) == len(arts):
        for g in sorted(set(labels), key=list(labels).index):
            groups.append([a for a, lab in zip(arts, labels) if lab == g])
        lines.append(f"grouping: {len(groups)} article group(s): " + " | ".join(", ".join(g) for g in groups))
    head["groups"] = groups
    diag = res.get("diagnosis") or {}
    dmembers = {d["member"]: d for d in diag.get("members", [])}
    lines.append("SD (relative log-magnitude deviation; raw = measured lines, equalized = identified model at zeta0)")
    lines.append(f"  {'':34s} {'nominal':>9s} {'calibrated':>11s} {'diagnosed':>10s} {'floor':>9s}")
    head["members"] = []
    for m in res.get("members", []):
        v = m.get("validation") or {}
        d = dmembers.get(m.get("member"), {})
        sd = d.get("sd") or {}
        after = sd.get("after") or {}
        floor_cal = None if not sd else sd.get("floor", 0.0) + sd.get("scatter", 0.0)
        rows = [
            ("calibration, equalized", m.get("sd_calibration_nominal"), m.get("sd_calibration"),
             after.get("calibration_equalized"), None),
            ("calibration, raw lines", m.get("sd_raw_calibration_start"), m.get("sd_raw_calibration"),
             after.get("calibration_raw"), floor_cal),
            ("hold-out, raw lines", v.get("sd_nominal"), v.get("sd_calibrated"),
             after.get("holdout_refined", after.get("holdout")), v.get("sd_floor")),
        ]
        lines.append(f"member {m.get('member')} ({', '.join(m.get('articles', []))}):")
        for name, a, b, c, f in rows:
            lines.append(f"  {name:34s} {_g(a):>9s} {_g(b):>11s} {_g(c):>10s} {_g(f):>9s}")
        if sd:
            lines.append(f"  (raw calibration: 'nominal' is the refinement's start, the equalized optimum; its floor "
                         f"is noise {_g(sd.get('floor'))} + test-to-test scatter {_g(sd.get('scatter'))}; the "
                         "hold-out floor is the noise alone)")
        entry = {"member": m.get("member"), "articles": m.get("articles"),
                 "sd": {k: {"nominal": a, "calibrated": b, "diagnosed": c, "floor": f} for k, a, b, c, f in rows}}
        if d:
            lines.append(f"  diagnosis: {d['verdict']}")
            acc = d.get("accepted") or []
            for a in acc:
                lines.append(f"    accepted: {a['family']} {a['name']}: {a['size']}{size_words(a)} ({a['description']})")
            if d["verdict"] not in ("nothing to explain", "nonlinear"):
                for r in (d.get("ranked") or [])[:3]:
                    lines.append(f"    ranked {r['rank']}: {r['family']} {r['name']} ({r['size']}), explains "
                                 f"{100 * r['explained']:.1f} % of the residual")
                if d.get("candidates"):
                    lines.append("    candidates screened: " + ", ".join(f"{k} {n}" for k, n in
                                                                       d["candidates"].items()))
            if d["verdict"] in ("nonlinear", "no effect accepted", "nothing to explain"):
                lines.append(f"    {d['reason']}")
            entry.update(verdict=d["verdict"], accepted=[{k: a.get(k) for k in ("family", "name", "size", "c")}
                                                         for a in acc],
                         ranked_first=(d.get("ranked") or [{}])[0].get("name"))
        head["members"].append(entry)
    if diag:
        found = [f"{e['member']}: {a['family']} {a['name']} ({a['size']})" for e in head["members"]
                 for a in e.get("accepted", [])]
        lines.append("effect found: " + ("; ".join(found) if found else "none accepted"))
        sep = diag.get("separating_effects") or []
        if found:
            lines.append("effect that separates the groups: " + (", ".join(sep) if sep else
                                                                 "none established (no per-article separation fit)"))
        nl = _nonlinear(diag)
        head["nonlinear"] = sorted(nl)
        lines.append("nonlinear article(s): " + ("; ".join(f"{a} ({w})" for a, w in nl.items()) if nl else "none"))
    else:
        lines.append("effect found: the diagnose stage did not run")
        nl = sorted(a for a, f in (checks or {}).items() if f is True)
        head["nonlinear"] = nl
        lines.append("nonlinear article(s) (level check of the acquired runs): " + (", ".join(nl) or "none"))
    lines.append(f"the truth: gap closed on {', '.join(GAP_CLOSED)} (contact springs), open on "
                 f"{', '.join(a for a in ARTICLES if a not in GAP_CLOSED)}; {LOOSE} has a loose part from "
                 f"{LEVELS_N[-1]:g} N")
    return lines, head
