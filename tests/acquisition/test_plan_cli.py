"""Plans as data (TOML, validation, lines, estimates) and ``frfcal acquire``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from acquisition import PlanError, estimate_duration_s, load_plan, plan_from_dict, plan_lines, read_run, summarize_plan
from frfcal.cli import main
from tests.acquisition._common import plant3

PLAN = """
name = "demo"
sample_rate_hz = 4096.0
layout = "layout.json"

[lines]
kind = "bandwidth"
start_hz = 110.0
stop_hz = 135.0
background_step = 0.04
lines_per_bandwidth = 2
span_bandwidths = 1.5
poles = [{ frequency_hz = 120.0, damping = 0.001 }]

[force]
levels_n = [0.5]

[ensemble]
articles = ["SF01", "SF02"]

[sim]
noise_rms = 1e-4
article_scatter = 0.0

[sim.modes]
frequencies_hz = [120.0, 185.0, 262.0]
damping = 0.001
shapes_out = [[0.5, 0.4, 0.3], [0.35, -0.45, 0.5], [0.42, 0.25, -0.33]]
shapes_in = [[0.5, 0.4, 0.3], [0.35, -0.45, 0.5]]
"""

LAYOUT = {
    "format": "frfcal-layout", "version": 1, "model": {"path": "m.bdf", "units": "mm-t-s"},
    "channels": [{"name": f"acc{k}", "role": "response", "quantity": "acceleration", "unit": "m/s^2",
                  "grid": 10 + k, "direction": [0, 0, 2], "xyz_m": [0.1 * k, 0, 0]} for k in range(3)],
    "drives": [{"name": "d1", "role": "force", "quantity": "force", "unit": "N", "grid": 10, "direction": [0, 0, 1],
                "xyz_m": [0, 0, 0]},
               {"name": "d2", "role": "force", "quantity": "force", "unit": "N", "grid": 11, "direction": [0, 1, 0],
                "xyz_m": [0.1, 0, 0]}],
    "target_modes_hz": [120.0], "metrics": {},
}


def _write(tmp_path, text=PLAN):
    (tmp_path / "layout.json").write_text(json.dumps(LAYOUT))
    (tmp_path / "plan.toml").write_text(text)
    return tmp_path / "plan.toml"


def test_lines_and_estimates():
    base = {"channels": [{"name": "a"}, {"name": "F", "role": "force", "quantity": "force"}]}
    lin = plan_from_dict(base | {"lines": {"kind": "linear", "start_hz": 100, "stop_hz": 550, "step_hz": 0.3}})
    f = plan_lines(lin)
    assert f.size == 1501 and f[0] == 100 and abs(f[-1] - 550) < 1e-9
    log = plan_from_dict(base | {"lines": {"kind": "log", "start_hz": 100, "stop_hz": 1000, "n_lines": 11}})
    assert np.allclose(plan_lines(log), np.logspace(2, 3, 11))
    bw = plan_from_dict(base | {"lines": {"kind": "bandwidth", "start_hz": 100, "stop_hz": 550, "background_step": 0.05,
                                          "lines_per_bandwidth": 4, "span_bandwidths": 3,
                                          "poles": [{"frequency_hz": 200, "damping": 0.001}]}})
    f = plan_lines(bw)
    near = f[np.abs(f - 200) <= 3 * 0.4]
    assert np.allclose(np.diff(near), 0.1) and near.size == 25  # 4 lines per 0.4 Hz bandwidth over +-3 bandwidths
    assert np.all(np.diff(f) > 0)
    est = estimate_duration_s(bw)
    assert est.shape == f.shape and est[np.argmin(np.abs(f - 200))] > est[-1]  # lines at the peak settle longest
    fixed = plan_from_dict(base | {"lines": {"kind": "linear", "start_hz": 100, "stop_hz": 101, "step_hz": 0.5},
                                   "settle": {"mode": "fixed", "fixed_dwell_s": 3.0}})
    assert np.all(estimate_duration_s(fixed) > 3.0)
    assert "estimated duration" in summarize_plan(bw)


def test_plan_errors_name_the_field(tmp_path):
    with pytest.raises(PlanError, match=r"lines\.step_hz|kind='linear' needs step_hz"):
        plan_from_dict({"channels": [{"name": "a"}], "lines": {"kind": "linear", "start_hz": 1, "stop_hz": 2}})
    with pytest.raises(PlanError, match=r"force\.level_n.*Extra inputs"):
        plan_from_dict({"channels": [{"name": "a"}], "lines": {"kind": "log", "start_hz": 1, "stop_hz": 2, "n_lines": 3},
                        "force": {"level_n": [1.0]}})
    with pytest.raises(PlanError, match="stop_hz"):
        plan_from_dict({"channels": [{"name": "a"}], "lines": {"kind": "log", "start_hz": 5, "stop_hz": 2, "n_lines": 3}})
    p = tmp_path / "bad.toml"
    p.write_text("name = [")
    with pytest.raises(PlanError, match="bad.toml: not valid TOML"):
        load_plan(p)


def test_acquire_dry_run_and_sim_ensemble(tmp_path, capsys):
    path = _write(tmp_path)
    assert main(["acquire", str(path), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "2 article(s) x 2 drive point(s) x 1 level(s) = 4 run file(s)" in out and "estimated duration" in out
    assert main(["acquire", str(path), "--dry-run", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["n_drives"] == 2 and info["n_lines"] == plan_lines(load_plan(path)).size
    assert main(["acquire", str(path), "--driver", "sim", "--out", str(tmp_path / "runs"), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)["runs"]
    assert [r["status"] for r in res] == ["completed"] * 4
    names = sorted(p.name for p in (tmp_path / "runs").glob("*.h5"))
    assert names == ["demo_SF01_d1_0.5N.h5", "demo_SF01_d2_0.5N.h5", "demo_SF02_d1_0.5N.h5", "demo_SF02_d2_0.5N.h5"]
    p = plant3()
    for k, d in enumerate(("d1", "d2")):
        run = read_run(tmp_path / "runs" / f"demo_SF01_{d}_0.5N.h5")
        assert run.drives[0].name == d and run.sensors[0].direction == (0.0, 0.0, 1.0) and run.article == "SF01"
        from acquisition import ModalPlant

        truth = ModalPlant(p.frequencies_hz, 0.001, p.shapes_out, np.array([p.shapes_out[k]])).frf(run.frequency_hz)
        assert np.max(np.abs(run.frf / truth - 1)) < 0.005
        assert np.all(np.abs(run.force_n - 0.5) < 0.01)
    # rerun: completed files are skipped
    assert main(["acquire", str(path), "--driver", "sim", "--out", str(tmp_path / "runs"), "--json"]) == 0
    assert all(r["new_lines"] == 0 for r in json.loads(capsys.readouterr().out)["runs"])


def test_acquire_errors(tmp_path, capsys):
    path = _write(tmp_path)
    assert main(["acquire", str(path), "--driver", "visa", "--out", str(tmp_path / "r")]) == 2
    assert "--hardware" in capsys.readouterr().err
    nosim = _write(tmp_path, PLAN.split("[sim]")[0])
    assert main(["acquire", str(nosim), "--driver", "sim", "--out", str(tmp_path / "r")]) == 2
    assert "no [sim] section" in capsys.readouterr().err
    bad = _write(tmp_path, PLAN.replace("levels_n", "level_n"))
    assert main(["acquire", str(bad), "--dry-run"]) == 2
    assert "force.level_n" in capsys.readouterr().err


def test_read_layout(tmp_path):
    from acquisition import LayoutError, read_layout

    (tmp_path / "l.json").write_text(json.dumps(LAYOUT))
    lay = read_layout(tmp_path / "l.json")
    assert [c.name for c in lay.sensors] == ["acc0", "acc1", "acc2"] and [d.name for d in lay.drives] == ["d1", "d2"]
    assert lay.sensors[0].direction == (0.0, 0.0, 1.0) and lay.sensors[1].grid == 11  # normalized
    assert abs(lay.sensors[0].sensitivity - 0.1 / 9.80665) < 1e-12 and lay.xyz_m["acc1"] == (0.1, 0.0, 0.0)
    for change, msg in ((lambda d: d["channels"][1].update(direction=[0, 0, 0]), r"channels\[1\] \(acc1\).*zero"),
                        (lambda d: d["channels"][0].update(unit="g"), "not the SI unit"),
                        (lambda d: d.update(format="x"), "'format'"),
                        (lambda d: d["drives"].append(dict(d["drives"][0])), "duplicate")):
        data = json.loads(json.dumps(LAYOUT))
        change(data)
        (tmp_path / "b.json").write_text(json.dumps(data))
        with pytest.raises(LayoutError, match=msg):
            read_layout(tmp_path / "b.json")


def test_live_plot_callback_draws(monkeypatch):
    import matplotlib

    matplotlib.use("Agg")
    from frfcal.commands.acquire import _live_plot

    on_line = _live_plot()
    on_line(100.0, np.array([[1.0 + 1j], [2.0]]), None)
    on_line(101.0, np.array([[2.0 + 1j], [3.0]]), None)
    import matplotlib.pyplot as plt

    lines = plt.gcf().axes[0].get_lines()
    assert len(lines) == 2 and np.allclose(lines[0].get_xdata(), [100.0, 101.0])
    plt.close("all")
