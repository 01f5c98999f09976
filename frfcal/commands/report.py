"""``frfcal report CAMPAIGN.toml``: the campaign's HTML report from its stored stage results (docs/report.md).

Reads ``<output dir>/stages`` as ``run_campaign`` stored it, keeps each
stage whose fingerprint still matches the campaign, the run files and the
model (a stale or missing stage is left out of the page with a note, it is
not recomputed), and writes ``<output dir>/report.html``.
"""

from __future__ import annotations

import argparse

HELP = "write the campaign's self-contained HTML report (report.html) from its stored stage results"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("campaign", help="campaign TOML file (see docs/campaign.md)")
    parser.add_argument("--out", help="output directory of the campaign (overrides [output] dir)")
    parser.add_argument("--quiet", action="store_true", help="no progress messages")


def stored_results(camp, *, campaign_file=None, log=print):
    """The campaign's stored stage results as :class:`frfcal.campaign._html.ReportResults`.

    Parameters
    ----------
    camp : Campaign
    campaign_file : path-like, optional
        The campaign TOML (shown verbatim in the report).

    Returns
    -------
    ReportResults
        Stages whose stored fingerprint differs from the current one (changed
        settings, run files or model) are None.

    Raises
    ------
    CalibrationError
        No stored load stage for the current run files (the campaign has not run).
    """
    from pathlib import Path

    from calibration import CalibrationError
    from frfcal.campaign import STAGES, StageStore, build_model, load_key, stage_keys
    from frfcal.campaign._html import ReportResults
    from frfcal.campaign._run import stored_front

    outdir = camp.resolve(camp.output.dir)
    store = StageStore(outdir / "stages")
    camp = stored_front(camp, store)  # UFF58 or acquired runs: the run files the stored front stages wrote
    lk = load_key(camp)
    load = store.load("load", lk)
    if load is None:
        raise CalibrationError(f"{store.directory}: no stored load stage for the campaign's current run files: "
                               "run 'frfcal calibrate' on the campaign first")
    pm, model = build_model(camp, load, log)
    keys = stage_keys(camp, model, lk)
    got, records = {}, {"load": {"status": "stored", "fingerprint": lk, "time_s": store.time_s("load")}}
    for name in STAGES[1:]:
        got[name] = store.load(name, keys[name])
        if got[name] is None:
            log(f"stage {name}: no stored result matching the campaign: left out of the report")
        else:
            records[name] = {"status": "stored", "fingerprint": keys[name], "time_s": store.time_s(name)}
    return ReportResults(load=load, identify=got.get("identify"), group=got.get("group"),
                         calibrate=got.get("calibrate"), validate=got.get("validate"),
                         crossvalidate=got.get("crossvalidate"), model=pm, stages=records,
                         campaign_file=None if campaign_file is None else Path(campaign_file))


def run(args) -> int:
    from pathlib import Path

    from frfcal.campaign import load_campaign
    from frfcal.campaign._html import report_stage

    camp = load_campaign(args.campaign)
    if args.out:
        camp = camp.model_copy(update={"output": camp.output.model_copy(update={"dir": Path(args.out).resolve()})})

    def log(msg):
        if not args.quiet:
            print(msg, flush=True)

    path = report_stage(camp, stored_results(camp, campaign_file=args.campaign, log=log), log=log)
    print(f"report: {path}")
    return 0
