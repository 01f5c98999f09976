"""``frfcal calibrate CAMPAIGN.toml``: calibrate, validate and cross-validate a campaign."""

from __future__ import annotations

import argparse

HELP = "calibrate an FE model against run files (campaign TOML): calibration, hold-out validation, cross-validation"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("campaign", help="campaign TOML file (see docs/campaign.md)")
    parser.add_argument("--json", action="store_true", help="print one JSON object with the results")
    parser.add_argument("--out", help="output directory (overrides [output] dir)")
    parser.add_argument("--starts", type=int, help="Latin-hypercube starts, at most (overrides [calibration] starts; "
                        "the multi-start stops earlier by the Bayesian rule unless adaptive_starts = false)")
    parser.add_argument("--realizations", type=int, help="cross-validation realizations (overrides the campaign)")
    parser.add_argument("--workers", type=int, help="local worker processes")
    parser.add_argument("--scheduler", help="Dask scheduler address (tcp://host:8786)")
    parser.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    parser.add_argument("--quiet", action="store_true", help="no progress messages")
    from frfcal.commands.run import add_campaign_options

    add_campaign_options(parser)


def _override(camp, args):
    from pathlib import Path

    changes = {}
    if args.out:
        changes["output"] = camp.output.model_copy(update={"dir": Path(args.out).resolve()})
    if args.no_figures:
        changes["output"] = changes.get("output", camp.output).model_copy(update={"figures": False})
    if args.starts is not None:
        changes["calibration"] = camp.calibration.model_copy(update={"starts": max(0, args.starts)})
    if args.realizations is not None:
        changes["crossvalidation"] = camp.crossvalidation.model_copy(update={"realizations": max(0, args.realizations)})
    if args.workers is not None or args.scheduler:
        ex = camp.execution.model_copy(update={k: v for k, v in (("workers", args.workers),
                                                               ("scheduler", args.scheduler)) if v is not None})
        changes["execution"] = ex
    return camp.model_copy(update=changes) if changes else camp


def run(args) -> int:
    import json

    from frfcal.campaign import json_default
    from frfcal.commands.run import run_stage

    # every stage through cross-validation (what `frfcal calibrate` always did), stored stages reused;
    # progress goes to stdout, or to stderr with --json (stdout holds only the JSON object)
    camp, res = run_stage(args, "crossvalidate")
    if args.json:
        print(json.dumps(res, default=json_default))
        return 0
    print_result(camp, res)
    return 0


def _source(d) -> str:
    """" (estimated from adjacent lines)" when the floor was estimated from the lines, else ""."""
    s = d.get("floor_source") or ""
    return f" ({s})" if "estimated" in s else ""


def _extended_deck(res, member: str) -> tuple:
    """(the diagnosis's extended deck, its deck parameters {name: p}) of ``member`` when the diagnosis accepted
    effects there, else (None, None)."""
    for d in ((res.get("diagnosis") or {}).get("members") or ()):
        if d.get("member") == member and d.get("accepted") and d.get("bdf"):
            return str(d["bdf"]), ((d.get("sd") or {}).get("after") or {}).get("p_refined")
    return None, None


def print_result(camp, res) -> None:
    """The calibration result as a table per member (parameters, SDs, identifiability)."""
    from calibration import floor_range_note

    for m in res["members"]:
        print(f"\n== {m['member']} ({', '.join(m['articles'])})")
        print(f"calibration SD (equalized test model, zeta0={100 * camp.calibration.zeta0:g} %)  "
              f"{m['sd_calibration_nominal']:.4g} -> {m['sd_calibration']:.4g}")
        v = m["validation"]
        if v:
            rng = v.get("floor_range")
            floor = (f", floor ~{v['sd_floor']:.2g}{_source(v)} ({v['floor_ratio']:.1f}x"
                     + (f"; {floor_range_note(*rng)}" if rng else "")
                     + ")") if v.get("sd_floor") else ""
            print(f"hold-out SD (raw lines, identified damping)  {v['sd_nominal']:.4g} -> {v['sd_calibrated']:.4g}"
                  f"{floor}  ({v['verdict']})")
            if v.get("scatter") is not None and v.get("floor_with_scatter_ratio") is not None:
                print(f"  one parameter set for {len(m['articles'])} articles: floor ~{v['sd_floor']:.2g} noise + "
                      f"{v['scatter']:.2g} test-to-test scatter ({v['floor_with_scatter_ratio']:.1f}x)")
        if m.get("sd_raw_calibration") is not None:
            fl = m.get("sd_raw_floor")
            print(f"raw calibration lines SD (identified damping)  {m['sd_raw_calibration_start']:.4g} -> "
                  f"{m['sd_raw_calibration']:.4g}"
                  + ("" if not fl else f", noise floor ~{fl:.2g}{_source({'floor_source': m.get('sd_raw_floor_source')})}"
                     f" ({m['sd_raw_calibration'] / fl:.1f}x"
                     + ("; the articles' scatter adds to it" if len(m["articles"]) > 1 else "") + ")"))
        cv = m["crossvalidation"]
        if cv:
            print(f"cross-validation RSE {cv['rse']:.4g} over {cv['realizations']} realizations")
        print(f"{'parameter':<22}{'nominal':>12}{'calibrated':>12}{'change%':>9}{'CV%':>8}  identifiable")
        notes = []
        for r in m["parameters"]:
            cvp = ""
            if "cv_percent" in r:
                cvp = f"{'n/a':>8}" if r["cv_percent"] is None else f"{r['cv_percent']:8.3f}"
                if r.get("cv_not_meaningful"):
                    notes.append(f"  CV of {r['name']}: {r['cv_not_meaningful']}")
            ident = "yes" if r["identifiable"] else f"NO: {r['identifiability']}"
            print(f"{r['name']:<22}{r['nominal_si']:12.4g}{r['calibrated_si']:12.4g}{100 * r['p']:+9.2f}{cvp:>8}  {ident}")
        for n in notes:
            print(n)
        weak = m["identifiability"]["weak_combinations"]
        for w in weak:
            print(f"weak combination (relative singular value {w['relative_singular_value']:.2e}): {w['combination']}")
        print(f"{m['identifiability']['n_identifiable']} of {len(m['parameters'])} parameters identifiable "
              "from these channels and band")
        if "bdf" in m:
            ext, p_ext = _extended_deck(res, m["member"])
            print(f"calibrated deck: {m['bdf']}" + (f" (without the effect(s) the diagnosis accepted; with them, "
                                                     f"parameters re-fitted: {ext})" if ext else ""))
            if p_ext:
                print("  parameters re-fitted with the effect(s) (change %): "
                      + ", ".join(f"{k} {100 * v:+.2f}" for k, v in p_ext.items()))
    total = res.get("time_s")
    print(f"\nresult: {res['result_file']}  ({res['timings']['total_s']:.1f} s"
          + (f"; {total:.1f} s with the stages after it" if total and total > res["timings"]["total_s"] + 0.05
             else "") + ")")
