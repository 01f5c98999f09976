"""``frfcal acquire`` ends an aborted run with one clear line and a resumable file."""

from __future__ import annotations

from acquisition import read_run
from frfcal.cli import main
from tests.acquisition.test_plan_cli import PLAN, _write


def test_limit_breach_is_reported_in_one_line_and_the_run_is_marked_aborted(tmp_path, capsys):
    # a drive-voltage limit far below what 0.5 N needs: the controller must refuse to set it
    plan = _write(tmp_path, PLAN.replace("[force]\nlevels_n = [0.5]", "[force]\nlevels_n = [0.5]\n\n[limits]\ndrive_v_max = 0.001"))
    status = main(["acquire", str(plan), "--driver", "sim", "--out", str(tmp_path / "runs"), "--no-progress"])
    err = capsys.readouterr().err
    assert status == 3
    assert "LimitBreach" in err and "drive ramped to zero" in err and "resume" in err
    assert "Traceback" not in err
    runs = sorted((tmp_path / "runs").glob("*.h5"))
    assert runs, "the run file must exist even when the first line aborts"
    assert read_run(runs[0]).status == "aborted"
