"""``frfcal diagnose CAMPAIGN.toml``: what does the calibrated model lack? (docs/diagnosis.md)."""

from __future__ import annotations

import argparse

HELP = ("diagnose a calibrated campaign: is the residual above the noise floor, is the article nonlinear, "
        "which effect explains it")


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("campaign", help="campaign TOML file (see docs/campaign.md, [diagnosis])")
    parser.add_argument("--json", action="store_true", help="print one JSON object (docs/diagnosis.md)")
    parser.add_argument("--out", help="output directory (overrides [output] dir)")
    parser.add_argument("--workers", type=int, help="local worker processes")
    parser.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    parser.add_argument("--quiet", action="store_true", help="no progress messages")


def _fmt(x, spec=".4g"):
    return "n/a" if x is None else format(x, spec)


def ranked_lines(rows) -> list:
    """The ranked candidates as table lines (header first): every column as wide as its longest entry (at
    least its heading), so a long family name (``shaker_attachment_mass``), a location with four grids and
    two parts or a long size never shifts the columns after it."""
    cells = []
    for r in rows:
        loc = ("grids " + " ".join(map(str, r["grids"][:4])) + ("..." if len(r["grids"]) > 4 else "")
               + f" ({', '.join(r['parts'][:2])}) at ({', '.join(f'{x:.3g}' for x in r['center'])})")
        h = r.get("explained_holdout")
        cells.append((str(r["rank"]), r["family"], loc, r["size"], f"{100 * r['explained']:.1f}%",
                      "-" if h is None else f"{100 * h:.1f}%", "" if r["checked"] else "(linear)"))
    head = ("#", "family", "location", "size", "explained", "hold-out", "")
    w = [max([len(head[k])] + [len(c[k]) for c in cells]) for k in range(len(head))]
    left = (False, True, True, False, False, False, True)  # text columns left-aligned, numbers right-aligned

    def line(c):
        return " ".join(x.ljust(n) if lf else x.rjust(n) for x, n, lf in zip(c, w, left)).rstrip()

    return [line(head)] + [line(c) for c in cells]


def print_diagnosis(d: dict, out) -> None:
    """The human-readable diagnosis (``d`` = the ``diagnosis`` entry of the result)."""
    from frfcal.campaign._diagnose import size_words

    for g in d["gates"]:
        nl = g["nonlinearity"]
        levels = ", ".join(f"{_fmt(r['level_n'], '.3g')} N ({r['sweep']})" for r in g["runs"])
        state = "not checked" if nl is None else nl["verdict"]
        print(f"article {g['article']}: {len(g['runs'])} run(s) at {levels}; nonlinearity gate: {state}", file=out)
        for n in g["notes"]:
            print(f"  {n}", file=out)
    for m in d["members"]:
        r = m["residual"]
        print(f"\n== {m['member']} ({', '.join(m['articles'])})", file=out)
        print(f"verdict: {m['verdict'].upper()}", file=out)
        print(f"  {m['reason']}", file=out)
        print(f"is there anything to explain: {r['test']}", file=out)
        print(f"{'place':<28}{'SD':>11}{'expected':>11}{'ratio':>8}{'sigma':>10}", file=out)
        for p in r["ranked"][:10]:
            if p["kind"] == "mode":
                print(f"mode {p['mode']} {p['test_hz']:.5g} Hz ({p['article']}): model {p['model_hz']:.5g} Hz, "
                      f"{p['shift_bandwidths']:+.2f} half-power bandwidths, MAC {p['mac']:.3f}", file=out)
            else:
                print(f"{p['kind'] + ' ' + p['label']:<28}{p['sd']:11.3g}{p['expected']:11.3g}{p['ratio']:8.3g}"
                      f"{p['z']:10.3g}", file=out)
        for x in m["nonlinear_modes"]:
            what = f"mode {x['mode']} " if x.get("mode") else ""
            extra = ""
            if x["check"] == "level dependence":
                extra = (f": {x['quantity']} {x['values'][0]:.4g} -> {x['values'][-1]:.4g} (x{x['ratio']:.3g}) "
                         f"from {min(x['levels_n']):.3g} to {max(x['levels_n']):.3g} N, {x['z']:.3g} sigma")
            print(f"nonlinear ({x['article']}): {x['check']} at {what}{x['frequency_hz']:.5g} Hz{extra}", file=out)
        if m["ranked"]:
            print("candidates screened: " + ", ".join(f"{k} {v}" for k, v in m["candidates"].items()), file=out)
            for line in ranked_lines(m["ranked"][:10]):
                print(line, file=out)
        for a in m["accepted"]:
            print(f"ACCEPTED: {a['description']}: {a['size']}{size_words(a)} (grids {', '.join(map(str, a['grids']))}; "
                  f"{', '.join(a['parts'])}): {a['decision']['reason']}", file=out)
            if len(a.get("tied", ())) > 1:
                print(f"  place: the lowest hold-out SD of {len(a['tied'])} places the screening could not tell "
                      "apart: " + ", ".join(f"grid {'/'.join(map(str, x['grids']))} {x['holdout_after']:.4g}"
                                            for x in sorted(a["tied"], key=lambda x: x["holdout_after"])), file=out)
            if a.get("shaped_from"):
                rates = sorted(a.get("pair_rates", ()), key=lambda x: -x["rate_N_per_m"])
                print(f"  shape: {len(a['grids']) // 2} of the {len(rates)} pairs of {a['shaped_from']} carry "
                      "the contact in a rate fitted per pair (largest: "
                      + ", ".join(f"{x['pair'][0]}-{x['pair'][1]} {x['rate_N_per_m']:.3g} N/m" for x in rates[:4])
                      + ")", file=out)
        for a in (m["sd"].get("after") or {}).get("negligible", []):
            z = a["refined_effect"]
            print(f"NEGLIGIBLE, dropped: {a['description']}: accepted, then refined to {a['size']}: without it the "
                  f"hold-out SD is x{z['holdout_without'] / z['holdout_with'] if z['holdout_with'] else float('inf'):.4f}"
                  f" (the penalty of one parameter: x{1 / z['penalty_ratio']:.4f}), largest mode shift "
                  f"{100 * z['max_mode_shift']:.2g} %", file=out)
        if not m["accepted"] and m["trials"]:
            t = m["trials"][0]
            if "decision" in t:
                print(f"not accepted: {' + '.join(t['names'])}: {t['decision']['reason']}", file=out)
        sd = m["sd"]
        print(f"SD of the calibrated model: calibration (raw lines) {_fmt(sd['calibration_raw'])}, hold-out "
              f"{_fmt(sd['holdout'])}, cross-validation RSE {_fmt(sd['crossvalidation_rse'])}; residual on all "
              f"channels {_fmt(sd['residual_all_channels'])} beside the floor {_fmt(sd['floor'])} "
              f"({sd['floor_source']})" + (f" + scatter {sd['scatter']:.3g}" if sd["scatter"] else ""), file=out)
        a = sd.get("after")
        if a:
            print(f"SD with the accepted effect(s): calibration (raw lines) {_fmt(a['calibration_raw'])}, hold-out "
                  f"{_fmt(a['holdout_refined'])} = {_fmt(a['holdout_floor_ratio'], '.3g')} x its floor "
                  f"{_fmt(a['floor_holdout'])}; on one footing (identified damping): hold-out "
                  f"{_fmt(a['holdout_before_same_footing'])} -> {_fmt(a['holdout'])}, cross-validation RSE "
                  f"{_fmt(a['crossvalidation_rse_before'])} -> {_fmt(a['crossvalidation_rse'])}", file=out)
            print(f"after: {a['residual']['test']}", file=out)
            if a.get("p_refined"):  # the deck parameters fitted with the effects: the calibrated ones lacked them
                print("deck parameters with the accepted effect(s), refined on the raw lines (p, relative change): "
                      + ", ".join(f"{k} {100 * v:+.2f} %" for k, v in a["p_refined"].items()), file=out)
        if m.get("bdf"):
            print(f"extended deck: {m['bdf']}; new cards:", file=out)
            for ln in m["new_cards"][:20]:
                print(f"  {ln}", file=out)
        for fpath in m.get("figures", []):
            print(f"figure: {fpath}", file=out)
    for x in d.get("separations", []):
        sep = x["separation"]
        per = ", ".join(f"{a} {v:.4g}" for a, v in zip(sep["articles"], x.get("value") or sep["magnitude"]))
        print(f"\nseparating effect: {x['name']} ({x['family']}, accepted in {x['member']}): "
              f"{'SEPARATES' if x['separates'] else 'does not separate'} the article groups {sep['groups']}; "
              f"size per article at the screening's damping: {per}{' ' + x['unit'] if x.get('unit') else ''} "
              f"({sep['reason']})", file=out)
    print(f"\ndiagnosis: {d['result_file']}", file=out)


def run(args) -> int:
    import json
    import sys

    from calibration import CalibrationError
    from frfcal.campaign import json_default, load_campaign, run_campaign
    from frfcal.commands.calibrate import _override

    args.starts = args.realizations = args.scheduler = None
    camp = _override(load_campaign(args.campaign), args)
    if not camp.diagnosis.enabled:
        raise CalibrationError(f"{args.campaign}: [diagnosis] enabled = false: nothing to run")
    stream = sys.stderr if args.json else sys.stdout

    def log(msg):
        if not args.quiet:
            print(msg, file=stream, flush=True)

    res = run_campaign(camp, log=log, upto="diagnose")
    d = res["diagnosis"]
    if args.json:
        out = dict(d)
        out["calibration_file"] = res["result_file"]
        out["stages"] = res["stages"]
        print(json.dumps(out, default=json_default))
        return 0
    print_diagnosis(d, sys.stdout)
    return 0
