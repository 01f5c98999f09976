"""``frfcal run CAMPAIGN.toml``: every stage of a campaign in order, each result kept on disk.

Also the campaign form of the stage commands: ``frfcal pretest|acquire|identify|calibrate CAMPAIGN.toml``
run the campaign up to that stage (:func:`run_stage`), reusing what is stored.
"""

from __future__ import annotations

import argparse

HELP = "run a whole campaign (campaign TOML): pretest/acquire/import, identify, calibrate, validate, ..."

_CAMPAIGN_TABLES = ("run", "channels", "band", "acquisition", "pretest", "layout", "calibration")


def is_campaign_file(path) -> bool:
    """Whether ``path`` is a campaign file: a TOML file with a [model] table and campaign sections.

    Raises
    ------
    ValueError
        When the file looks like both a campaign and a sweep plan (a plan has
        ``[lines]``), naming what to change.
    """
    import tomllib
    from pathlib import Path

    p = Path(path)
    if p.suffix.lower() != ".toml" or not p.is_file():
        return False
    try:
        data = tomllib.loads(p.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError, OSError):
        return False  # the command's own reader reports what is wrong
    campaign = isinstance(data.get("model"), dict) and any(k in data for k in _CAMPAIGN_TABLES)
    if campaign and "lines" in data:
        raise ValueError(f"{p}: both a campaign ([model], {', '.join(k for k in _CAMPAIGN_TABLES if k in data)}) "
                         "and a sweep plan ([lines]): move the plan into [acquisition.plan] or its own file")
    return campaign


def add_campaign_options(parser: argparse.ArgumentParser) -> None:
    """Options of the campaign form (shared by run and the stage commands)."""
    parser.add_argument("--force", "--redo", dest="force_stage", metavar="STAGE",
                        help="recompute from this stage on even when stored (e.g. identify, calibrate)")


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("campaign", help="campaign TOML file (see docs/campaign.md)")
    add_campaign_options(parser)
    parser.add_argument("--upto", metavar="STAGE", help="stop after this stage")
    parser.add_argument("--out", help="output directory (overrides [output] dir)")
    parser.add_argument("--workers", type=int, help="local worker processes")
    parser.add_argument("--scheduler", help="Dask scheduler address (tcp://host:8786), or 'local'")
    parser.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    parser.add_argument("--json", action="store_true", help="print one JSON object with the results")
    parser.add_argument("--quiet", action="store_true", help="no progress messages")


def run_stage(args, upto: str | None):
    """Load the campaign ``args.campaign`` (with the command's overrides) and run it up to ``upto``.

    Returns (campaign, result dict). Progress goes to stdout, or to stderr
    with ``--json``.
    """
    import sys

    from frfcal.campaign import load_campaign, run_campaign
    from frfcal.commands.calibrate import _override

    for name in ("out", "starts", "realizations", "workers", "scheduler", "no_figures"):
        if not hasattr(args, name):
            setattr(args, name, None)
    camp = _override(load_campaign(args.campaign), args)
    upto = _data_stage(camp, upto, args.campaign)
    stream = sys.stderr if getattr(args, "json", False) else sys.stdout
    quiet = getattr(args, "quiet", False)

    def log(msg):
        if not quiet:
            print(msg, file=stream, flush=True)

    return camp, run_campaign(camp, log=log, upto=upto, force=getattr(args, "force_stage", None))


def _data_stage(camp, upto, source):
    """``acquire`` on a campaign that imports UFF58 files means its import stage; a missing stage is an error."""
    from frfcal.campaign._front import uff_entries

    if upto == "pretest" and camp.pretest is None:
        raise ValueError(f"{source}: no [pretest] section: add one to plan the layout"
                         + (" (the campaign uses [layout] file)" if camp.layout is not None else ""))
    if upto == "acquire" and camp.acquisition is None:
        if uff_entries(camp):
            return "import"
        raise ValueError(f"{source}: nothing to acquire: add an [acquisition] section, or [[run]] uff = files "
                         "to import (its [[run]] path = files are read as they are)")
    return upto


def campaign_command(args, upto: str) -> int:
    """The campaign form of a stage command: run up to ``upto``; print the stages (or one JSON object)."""
    import json

    from frfcal.campaign import json_default

    # the command's own options (--out of a layout or run directory, ...) do not apply to a campaign
    args = argparse.Namespace(campaign=args._campaign_path, force_stage=getattr(args, "force_stage", None),
                              json=getattr(args, "json", False), quiet=getattr(args, "quiet", False))
    camp, res = run_stage(args, upto)
    if getattr(args, "json", False):
        print(json.dumps(res, default=json_default))
        return 0
    print(f"{args.campaign}: up to {res.get('upto', upto)} in {res.get('time_s', 0.0):.1f} s; "
          f"stage results in {res.get('output_dir')}/stages")
    print_stages(res)
    return 0


def print_stages(res) -> None:
    """One line per stage: ran or reused, and its time."""
    for name, r in res["stages"].items():
        t = r.get("time_s")
        print(f"  {name:<14}{r['status']:<8}" + ("" if t is None else f"{t:8.1f} s"))


def run(args) -> int:
    import json

    from frfcal.campaign import json_default
    from frfcal.commands.calibrate import print_result

    camp, res = run_stage(args, args.upto)
    if args.json:
        print(json.dumps(res, default=json_default))
        return 0
    if "members" in res:
        print_result(camp, res)
    else:
        print(f"\nstopped after {res['upto']} ({res['time_s']:.1f} s); stored in {res['output_dir']}/stages")
    print("stages:")
    print_stages(res)
    return 0
