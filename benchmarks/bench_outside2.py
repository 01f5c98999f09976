"""The whole chain on the second outside case, stage by stage (issues 12, 14).

The case is ``tests/frfcal/outside2_case.py`` (what ``test_outside_data2.py`` builds): a 1014-DOF mm-t-s
shell deck (floor panel + U-rail, free-free), a lab's parameter table (6 parameters), five UFF58 files
(16 responses x 3 references, about 2600 lines, damping 0.05-0.3 % varying by mode, 0.7 % noise), a
contact effect on A4-A5. It is built once under ``--dir`` (kept; ``--rebuild`` to write it again).

Each stage is run as a lab runs it, through the CLI in its own process:
``python -m frfcal run campaign.toml --upto STAGE --force STAGE`` (every earlier stage is read back from
``out/stages``), in order import, load, identify, equalize, group, calibrate, validate, crossvalidate,
diagnose. Per stage: the wall time of the process, its CPU time (the process and its worker processes,
``RUSAGE_CHILDREN``), the stage's own time as the campaign records it, and the 1-minute load average
before and after (the machine may be shared: compare CPU times across runs, not wall times alone).
The stage results that the figures rest on are summarized (parameters, SDs, accepted effects) so two
runs can be compared.

    python benchmarks/bench_outside2.py [--dir /tmp/frfcal-outside2] [--out /tmp/frfcal-outside2/bench.json]
                                        [--stages calibrate,diagnose] [--rebuild]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("import", "load", "identify", "equalize", "group", "calibrate", "validate", "crossvalidate", "diagnose")


def build_case(out: Path) -> Path:
    sys.path.insert(0, str(ROOT))
    from tests.frfcal import outside2_case as oc

    oc.build(out)
    names = {e: f"{e} ({n}{'+-'[c < 0]}{'XYZ'[abs(c) - 1]})" for e, n, c in oc.RESPONSES}
    return oc.campaign(out, names)


def run_stage(camp: Path, stage: str, log_dir: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cmd = [sys.executable, "-m", "frfcal", "run", str(camp), "--upto", stage, "--force", stage, "--json"]
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    with open(log_dir / f"{stage}.log", "w") as err:
        proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=err, text=True, cwd=camp.parent, env=env)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    row = {"stage": stage, "wall_s": wall, "cpu_s": (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime),
           "load_before": load0, "load_after": os.getloadavg()[0], "returncode": proc.returncode,
           "command": " ".join(cmd)}
    if proc.returncode:
        row["error"] = (log_dir / f"{stage}.log").read_text()[-2000:]
        return row
    res = json.loads(proc.stdout)
    row["stage_s"] = (res.get("stages", {}).get(stage) or {}).get("time_s")
    return row


def summary(out_dir: Path) -> dict:
    """The figures the stages end on: per member the parameters, SDs and, after diagnosis, the accepted effects."""
    s: dict = {}
    cal = out_dir / "calibration.json"
    if cal.exists():
        res = json.loads(cal.read_text())
        s["members"] = [{"articles": m["articles"], "p": {r["name"]: r["p"] for r in m["parameters"]},
                         "sd_raw_calibration": m.get("sd_raw_calibration"),
                         "sd_holdout": (m.get("validation") or {}).get("sd_calibrated"),
                         "cv_rse": (m.get("crossvalidation") or {}).get("rse")} for m in res["members"]]
    diag = out_dir / "diagnosis.json"
    if diag.exists():
        d = json.loads(diag.read_text())
        s["diagnosis"] = [{"articles": g["articles"], "verdict": g["verdict"],
                           "accepted": [(a["name"], a["value"]) for a in g["accepted"]],
                           "holdout_refined": ((g.get("sd") or {}).get("after") or {}).get("holdout_refined")}
                          for g in d["members"]]
    return s


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dir", default=str(Path(tempfile.gettempdir()) / "frfcal-outside2"))
    ap.add_argument("--out", help="result JSON (default DIR/bench.json)")
    ap.add_argument("--stages", default=",".join(STAGES), help="comma-separated stages to time (in order)")
    ap.add_argument("--rebuild", action="store_true", help="write the case again")
    args = ap.parse_args(argv)
    d = Path(args.dir)
    camp = d / "campaign.toml"
    if args.rebuild or not camp.exists():
        t = time.perf_counter()
        build_case(d)
        print(f"case built in {d} ({time.perf_counter() - t:.1f} s)")
    log_dir = d / "bench-logs"
    log_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    print(f"{'stage':<14}{'wall s':>9}{'CPU s':>9}{'stage s':>9}{'load':>12}")
    for stage in [s for s in args.stages.split(",") if s]:
        if stage not in STAGES:
            ap.error(f"--stages: unknown stage {stage!r} (one of {', '.join(STAGES)})")
        row = run_stage(camp, stage, log_dir)
        rows.append(row)
        st = row.get("stage_s")
        print(f"{stage:<14}{row['wall_s']:9.1f}{row['cpu_s']:9.1f}{'' if st is None else f'{st:9.1f}':>9}"
              f"{row['load_before']:6.1f}-{row['load_after']:<5.1f}")
        if row["returncode"]:
            print(row["error"], file=sys.stderr)
            break
    result = {"case": str(d), "cpu_count": os.cpu_count(), "stages": rows, "results": summary(d / "out")}
    out = Path(args.out) if args.out else d / "bench.json"
    out.write_text(json.dumps(result, indent=1))
    print(f"wrote {out}")
    return 1 if any(r["returncode"] for r in rows) else 0


if __name__ == "__main__":
    raise SystemExit(main())
