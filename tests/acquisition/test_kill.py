"""SIGKILL the acquiring process at random moments: every completed line survives and the run resumes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from acquisition import plan_lines, read_run
from tests.acquisition._common import plan, plant3

REPO = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.timeout(300)


def _start(path):
    proc = subprocess.Popen([sys.executable, "-m", "tests.acquisition._kill_worker", str(path)], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    out: list[str] = []
    ready = threading.Event()

    def pump():
        for line in proc.stdout:
            out.append(line.strip())
            if line.startswith("READY"):
                ready.set()

    t = threading.Thread(target=pump, daemon=True)
    t.start()
    return proc, out, ready, t


def test_sigkill_at_random_moments_loses_no_completed_line(tmp_path):
    path = tmp_path / "run.h5"
    rng = np.random.default_rng(20261123)
    committed: list[float] = []
    kills = 0
    kills_mid_run = 0
    for attempt in range(6):
        proc, out, ready, t = _start(path)
        assert ready.wait(60), "worker did not start"
        time.sleep(float(rng.uniform(0.0, 1.2)))
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
            kills += 1
        proc.wait(30)
        t.join(5)
        new = [float(x.split()[1]) for x in out if x.startswith("LINE")]
        kills_mid_run += bool(new) and "DONE" not in out
        committed += new
        if path.exists():
            run = read_run(path)  # readable after every kill
            assert run.status in ("running", "aborted", "completed")
            have = set(run.frequency_hz.tolist())
            missing = [f for f in committed if f not in have]
            assert not missing, f"completed lines lost after kill {attempt}: {missing}"
            assert run.n_lines == len(have)  # no duplicates from resuming
        else:
            assert not committed
        if "DONE" in out:
            break
    assert kills >= 3 and kills_mid_run >= 2
    # finish the run and check it against the plant
    proc, out, ready, t = _start(path)
    proc.wait(120)
    t.join(5)
    assert "DONE" in out
    run = read_run(path)
    assert run.status == "completed"
    expected = plan_lines(plan())
    assert run.n_lines == expected.size
    assert np.allclose(np.sort(run.frequency_hz), expected)
    assert set(committed) <= set(run.frequency_hz.tolist())
    p = plant3()
    assert np.max(np.abs(run.frf / p.frf(run.frequency_hz) - 1)) < 0.01
