"""The whole campaign in one command: ``frfcal run`` on a campaign of UFF58 files, resume after SIGKILL,
the calibration through a Dask LocalCluster on loopback, servers on loopback, one-line errors, no
executed or unpickled user input.

The campaign: the example frame (492 DOF, 7 parameters) with two articles manufactured by
``frfcal.synth`` (10 sensors, one drive, 60-250 Hz), given as UFF58 files (the import stage),
1 start, 6 cross-validation realizations, a fixed identification order (the automatic choice of
this data, so no order scan), 2 local worker processes.
"""

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import femodel
from frfcal.cli import main
from frfcal.synth import SynthChannel, synthesize

REPO = Path(__file__).resolve().parents[2]
BAND = (60.0, 250.0)
CORE = ["load", "identify", "equalize", "group", "calibrate", "validate", "crossvalidate"]
LATE = ["diagnose", "report"]  # the late stages frfcal run adds after cross-validation


def _campaign_text(params, uffs, names, out="out", extra=""):
    cal, hold = names[0::2], names[1::2]
    return (f'[model]\nparameters = "{params}"\n'
            + "".join(f'[[run]]\nuff = "{u}"\narticle = "{a}"\n' for a, u in uffs)
            + f"[channels]\ncalibrate = {json.dumps(cal)}\nholdout = {json.dumps(hold)}\n"
            + f"[band]\nlow_hz = {BAND[0]}\nhigh_hz = {BAND[1]}\n"
            + "[identification]\norder = 54\n"
            + "[calibration]\nstarts = 1\n[crossvalidation]\nrealizations = 6\n"
            + f"[execution]\nworkers = 2\n{extra}"
            + f'[output]\ndir = "{out}"\nfigures = false\n')


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """The frame campaign (UFF58 entries) and its uninterrupted run in a fresh process."""
    tmp = tmp_path_factory.mktemp("campaign_run")
    ex = femodel.example_frame(tmp / "model")
    pm = femodel.parametric_model(ex.params)
    g = np.asarray(pm.assembly.model.grid_ids)
    pick = g[np.linspace(2, len(g) - 3, 10).astype(int)]
    dirs = [(0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (1.0, 0.0, 0.0)]
    sensors = [SynthChannel(f"s{i + 1}", int(gid), dirs[i % 3]) for i, gid in enumerate(pick)]
    drives = [SynthChannel("F1", int(pick[3]), (0.0, 0.0, 1.0))]
    sc = synthesize(ex.bdf, ex.params, tmp / "data", sensors=sensors, drives=drives, band_hz=BAND, n_articles=2,
                    seed=3, base_lines=150, lines_per_bandwidth=3)
    camp = tmp / "small.toml"
    camp.write_text(_campaign_text(ex.params, zip(sc.articles, sc.uff_paths), [s.name for s in sensors]))
    ref = _frfcal("run", str(camp), "--json", "--quiet", "--out", str(tmp / "ref"))
    return tmp, camp, ref


def _env():
    """This checkout first on the path; one BLAS thread, as Dask's nanny gives its workers (a threaded
    BLAS sums in another order: 1e-9 differences after the minimizer, which are not the executor's)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.update({k: "1" for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")})
    return env


def _frfcal(*argv):
    """``python -m frfcal ARGV --json`` in a fresh process; its JSON result."""
    done = subprocess.run([sys.executable, "-m", "frfcal", *argv], cwd=REPO, env=_env(), capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout)


def _params(res):
    return np.array([[r["p"] for r in m["parameters"]] for m in res["members"]])


def _status(res):
    return {k: v["status"] for k, v in res["stages"].items()}


def test_uninterrupted_run_imports_the_uff_files_and_runs_every_stage(small):
    tmp, camp, ref = small
    assert list(ref["stages"]) == ["import", *CORE, *LATE]
    assert set(_status(ref).values()) == {"ran"}
    assert (tmp / "ref" / "report.html").exists() and (tmp / "ref" / "diagnosis.json").exists()
    assert sorted(p.name for p in (tmp / "ref" / "runs").glob("*.h5")) == ["A1.h5", "A2.h5"]
    # the calibration moved every parameter off nominal towards the truth (5-15 % offsets)
    truth = np.load(tmp / "data" / "truth.npz")
    p_pop = truth["p_population"]
    assert np.max(np.abs(_params(ref)[0] - p_pop)) < 0.03 < np.min(np.abs(p_pop))
    v = ref["members"][0]["validation"]
    assert v["sd_calibrated"] < 0.1 * v["sd_nominal"]


def test_killed_run_resumes_after_the_last_stored_stage_with_the_same_result(small):
    tmp, camp, ref = small
    out = tmp / "killed"
    proc = subprocess.Popen([sys.executable, "-m", "frfcal", "run", str(camp), "--out", str(out)], cwd=REPO,
                            env=_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    marker = out / "stages" / "calibrate.json"
    t0 = time.monotonic()
    while not marker.exists():
        assert proc.poll() is None, f"run ended before the calibrate stage was stored:\n{proc.stdout.read()[-3000:]}"
        assert time.monotonic() - t0 < 600
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=60)
    proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL
    assert not (out / "stages" / "crossvalidate.json").exists() and not (out / "calibration.json").exists()

    done = subprocess.run([sys.executable, "-m", "frfcal", "run", str(camp), "--out", str(out)], cwd=REPO,
                          env=_env(), capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    log = done.stdout
    # the stages stored before the kill are read back, not recomputed: no identification, no calibration ran
    for k, name in enumerate(["import", "load", "identify", "equalize", "group", "calibrate"], start=1):
        assert f"[{k}/10] {name}: inputs unchanged, stored result reused" in log
    assert "[8/10] crossvalidate: done in" in log and "[10/10] report: done in" in log
    assert "identified order" not in log and "calibrating on" not in log
    res = json.loads((out / "calibration.json").read_text())
    st = _status(res)
    assert all(st[s] == "reused" for s in ("import", "load", "identify", "equalize", "group", "calibrate"))
    assert st["crossvalidate"] == "ran"
    # the reported parameters are the calibration stored before the kill, exactly
    from frfcal.campaign import StageStore

    stored = StageStore(out / "stages").load("calibrate", res["stages"]["calibrate"]["fingerprint"])
    assert _params(res)[0].tolist() == stored.members[0].p.tolist()
    # and the uninterrupted run's, to the run-to-run scatter of the calibrate stage itself: eigsh's Lanczos
    # start vector (scipy >= 1.15 draws it from OS entropy) and the two-thread basis projection move p by
    # 1e-9..3e-8 and the SDs by ~5e-7 relative between two fresh runs of the same campaign
    np.testing.assert_allclose(_params(res), _params(ref), rtol=0, atol=1e-6)
    m0, m1 = ref["members"][0], res["members"][0]
    assert m1["validation"]["sd_calibrated"] == pytest.approx(m0["validation"]["sd_calibrated"], rel=1e-5)
    assert m1["crossvalidation"]["rse"] == pytest.approx(m0["crossvalidation"]["rse"], rel=1e-5)


def _stored(tmp, ref, name):
    from frfcal.campaign import StageStore

    got = StageStore(tmp / "ref" / "stages").load(name, ref["stages"][name]["fingerprint"])
    assert got is not None, name
    return got


def _executor_comparison(stages_dir, fingerprints, campaign):
    """The campaign's executor work through the local pool and through a loopback LocalCluster.

    What the calibrate and crossvalidate stages hand to the executor: the multi-start (4 starts,
    damping continuation, on the campaign's stored nominal surrogate and equalized data) and the
    cross-validation realizations (on the stored calibration). The stages as a whole are not
    bit-reproducible between two runs whatever the executor: eigsh (scipy >= 1.15) draws its Lanczos
    start vector from OS entropy, and the basis projection sums on two threads (calibration/_surrogate.py),
    which moves the refined p by 1e-9..3e-8 from run to run. Run in a fresh process
    (``python tests/frfcal/test_campaign_run.py``) with one BLAS thread from the start, here and in
    the pool's workers, as Dask's nanny gives its workers.
    """
    import distributed

    from calibration import DaskExecutor, FitOptions, ProcessExecutor, calibrate
    from frfcal.campaign import StageStore, crossvalidate_stage, load_campaign

    store = StageStore(stages_dir)
    got = {n: store.load(n, fingerprints[n]) for n in ("load", "identify", "equalize", "calibrate")}
    camp = load_campaign(campaign)
    articles = got["identify"].attached(got["load"].articles)
    eq, cal = got["equalize"], got["calibrate"]
    c = camp.calibration
    pm = femodel.parametric_model(camp.resolve(camp.model.parameters))
    lower, upper = pm.lower, pm.upper
    data, cont = eq.member(range(len(articles)))
    opts = FitOptions(n_starts=4, seed=c.seed, quantity=articles[0].quantity, max_nfev=c.max_evaluations)

    def work(executor):
        ms = calibrate(cal.surrogate, data, lower, upper, c.zeta0, opts, executor=executor, continuation=cont)
        cv = crossvalidate_stage(camp, articles, eq, cal, (lower, upper), pm.parameters.names, executor,
                                 log=lambda m: None).members[0].crossvalidation
        return {"p": ms.p.tolist(), "starts": [o.p.tolist() for o in ms.outcomes], "sd": ms.sd,
                "cv_p": cv.p.tolist(), "rse": cv.rse}

    out = {}
    with ProcessExecutor(2) as pool:
        out["pool"] = work(pool)
    with distributed.LocalCluster(host="127.0.0.1", n_workers=2, processes=True, threads_per_worker=1,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        out["scheduler"] = cluster.scheduler_address
        out["workers"] = sorted(client.scheduler_info()["workers"])
        out["dask"] = work(DaskExecutor(client=client))
    return out


def test_calibration_through_a_dask_localcluster_on_loopback_equals_the_local_pool(small):
    pytest.importorskip("distributed")
    tmp, camp, ref = small
    fps = {n: r["fingerprint"] for n, r in ref["stages"].items()}
    done = subprocess.run([sys.executable, str(Path(__file__).resolve()), str(tmp / "ref" / "stages"), json.dumps(fps),
                           str(camp)], cwd=REPO, env=_env(), capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    got = json.loads(done.stdout.strip().splitlines()[-1])
    assert got["scheduler"].startswith("tcp://127.0.0.1:")
    assert len(got["workers"]) == 2 and all(w.startswith("tcp://127.0.0.1:") for w in got["workers"])
    pool, dask = got["pool"], got["dask"]
    assert len(pool["starts"]) == 5 and len(pool["cv_p"]) == 6  # the work the executors did
    for k in ("p", "starts", "cv_p"):
        np.testing.assert_allclose(dask[k], pool[k], rtol=0, atol=1e-10, err_msg=k)
    assert dask["sd"] == pytest.approx(pool["sd"], rel=1e-10) and dask["rse"] == pytest.approx(pool["rse"], rel=1e-10)
    # on the nominal basis the multi-start lands within the re-basis step (1e-5) of the campaign's equalized optimum
    np.testing.assert_allclose(pool["p"], _stored(tmp, ref, "calibrate").members[0].cycle.p, rtol=0, atol=1e-4)


def test_a_local_dask_cluster_the_toolkit_starts_listens_on_loopback():
    pytest.importorskip("distributed")
    from calibration import make_executor

    ex = make_executor("local", 1)
    try:
        addr = ex.client.scheduler.address
        assert addr.startswith("tcp://127.0.0.1:"), addr
        workers = ex.client.scheduler_info()["workers"]
        assert workers and all(w.startswith("tcp://127.0.0.1:") for w in workers)
        assert ex.map(abs, [-1, -2, 3]) == [1, 2, 3]
    finally:
        ex.close()


def test_the_loopback_scpi_lab_binds_127_0_0_1():
    from acquisition._scpi_server import LoopbackLab

    class Plant:
        def frf(self, f):
            return np.ones((np.size(f), 1, 1), complex)

    with LoopbackLab(Plant(), lifetime_s=30) as lab:
        addrs = lab.addresses()
        assert addrs and {a for a, _ in addrs.values()} == {"127.0.0.1"}
        assert lab.generator_resource.startswith("TCPIP::127.0.0.1::")


def test_stage_commands_on_a_campaign_run_up_to_their_stage_and_reuse_the_stored_ones(small, capsys):
    tmp, camp, ref = small
    same = tmp / "small_ref.toml"  # the same campaign, writing where the uninterrupted run wrote
    same.write_text(camp.read_text().replace('dir = "out"', 'dir = "ref"'))
    capsys.readouterr()
    assert main(["identify", str(same), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["upto"] == "identify" and _status(res) == {"import": "reused", "load": "reused", "identify": "reused"}
    assert main(["acquire", str(same), "--json"]) == 0  # a campaign of UFF58 files acquires by importing them
    assert _status(json.loads(capsys.readouterr().out)) == {"import": "reused"}
    assert main(["calibrate", str(same), "--json", "--quiet"]) == 0  # the classic form: through cross-validation
    res = json.loads(capsys.readouterr().out)
    assert set(_status(res).values()) == {"reused"}
    np.testing.assert_array_equal(_params(res), _params(ref))
    # --force (alias --redo) recomputes from a stage on
    assert main(["run", str(same), "--redo", "validate", "--json", "--quiet"]) == 0
    st = _status(json.loads(capsys.readouterr().out))
    assert st["calibrate"] == "reused" and st["validate"] == "ran" and st["crossvalidate"] == "ran"
    # a stage the campaign does not have: one line saying what to add
    assert main(["pretest", str(same)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no [pretest] section: add one" in err[0]



def _plant(params, layout, out, p, zeta=0.01):
    """Modal plant of the frame at ``p`` seen by the layout's channels and drives (free modes only)."""
    from labdata import read_layout_file

    pm = femodel.parametric_model(params)
    lay = read_layout_file(layout)
    c_out = femodel.sensor_matrix(pm.assembly, lay.grids("channels"), lay.directions("channels"))
    c_in = femodel.sensor_matrix(pm.assembly, lay.grids("drives"), lay.directions("drives"))
    modes = pm.modes(p, 30)
    f, sh = modes.frequencies_hz[modes.n_rigid:], modes.shapes[:, modes.n_rigid:]
    np.savez(out, frequencies_hz=f, damping=np.full(f.shape, zeta), shapes_out=np.asarray(c_out @ sh),
             shapes_in=np.asarray(c_in @ sh))


def _acquiring_campaign(tmp, noise=1e-5):
    ex = femodel.example_frame(tmp / "model")
    grids = [int(g) for g in femodel.parametric_model(ex.params).assembly.model.grid_ids]
    camp = tmp / "acq.toml"
    camp.write_text(f"""[model]
parameters = "{ex.params}"
[pretest]
sensors = 8
modes = 6
direction = "z"
candidates = {grids}
figures = false
[acquisition]
driver = "sim"
[acquisition.plan]
name = "frame"
sample_rate_hz = 4096.0
lines = {{ kind = "linear", start_hz = 50.0, stop_hz = 300.0, step_hz = 5.0 }}
measure = {{ blocks = 2 }}
ensemble = {{ articles = ["T1"] }}
sim = {{ model = "plant.npz", noise_rms = {noise}, shaker = "ideal" }}
[channels]
calibrate = ["acc01", "acc03", "acc05", "acc07"]
holdout = ["acc02", "acc04", "acc06", "acc08"]
[band]
low_hz = 60.0
high_hz = 250.0
[output]
dir = "out"
figures = false
""")
    return ex, camp


def test_an_acquiring_campaign_plans_the_layout_then_acquires_and_resumes_an_interrupted_sweep(tmp_path, capsys,
                                                                                             monkeypatch):
    import frfcal.campaign._front as front
    from acquisition.runfile import read_run

    ex, camp = _acquiring_campaign(tmp_path)
    assert main(["pretest", str(camp), "--json"]) == 0  # the layout first: the simulated plant is built on it
    res = json.loads(capsys.readouterr().out)
    assert _status(res) == {"pretest": "ran"}
    layout = tmp_path / "out" / "layout.json"
    assert [c["name"] for c in json.loads(layout.read_text())["channels"]] == [f"acc{k:02d}" for k in range(1, 9)]
    _plant(ex.params, layout, tmp_path / "plant.npz", np.full(7, 0.05))

    # the sweep is interrupted at its 21st line (Ctrl-C in the driver): the drive ramps down, the lines stay
    real = front.driver_factory

    def interrupted(camp_, plan):
        make, channels = real(camp_, plan)

        def make_once(*a):
            drv = make(*a)
            lines = set()
            set_drive = drv.set_drive

            def counting(frequency_hz, amplitude_v):
                lines.add(round(frequency_hz, 6))
                if len(lines) > 20:
                    raise KeyboardInterrupt
                return set_drive(frequency_hz, amplitude_v)

            drv.set_drive = counting
            return drv

        return make_once, channels

    monkeypatch.setattr(front, "driver_factory", interrupted)
    assert main(["acquire", str(camp)]) == 130
    assert capsys.readouterr().err.strip() == "frfcal: interrupted"
    run_file = tmp_path / "out" / "runs" / "frame_T1_drive1_1N.h5"
    partial = read_run(run_file)
    assert partial.status == "aborted" and partial.n_lines == 20
    monkeypatch.setattr(front, "driver_factory", real)
    assert main(["acquire", str(camp), "--json"]) == 0  # resumes the sweep, keeps the lines measured before
    res = json.loads(capsys.readouterr().out)
    assert _status(res) == {"pretest": "reused", "acquire": "ran"}
    run = read_run(run_file)
    assert run.status == "completed" and run.n_lines == 51
    np.testing.assert_array_equal(run.frf[: partial.n_lines], partial.frf)
    assert main(["acquire", str(camp), "--json"]) == 0
    assert _status(json.loads(capsys.readouterr().out)) == {"pretest": "reused", "acquire": "reused"}

    # other acquisition settings: the old runs are set aside (never deleted), the sweep starts afresh
    camp.write_text(camp.read_text().replace("noise_rms = 1e-05", "noise_rms = 2e-05"))
    assert main(["acquire", str(camp), "--json"]) == 0
    assert _status(json.loads(capsys.readouterr().out)) == {"pretest": "reused", "acquire": "ran"}
    kept = tmp_path / "out" / "runs.superseded-1" / run_file.name
    assert read_run(kept).n_lines == 51 and read_run(run_file).status == "completed"



def test_a_rerun_that_reuses_the_calibration_starts_no_workers_and_no_analysis(small, capsys, monkeypatch):
    """The multi-start's workers (started before the parametric model) and CHOLMOD's analysis ahead of the
    first basis are started only when the calibrate stage will run."""
    import frfcal.campaign._run as run

    tmp, camp, ref = small
    same = tmp / "small_ref_rerun.toml"
    same.write_text(camp.read_text().replace('dir = "out"', 'dir = "ref"'))
    started = []
    make, ahead = run.make_executor, run.analyze_ahead
    monkeypatch.setattr(run, "make_executor", lambda *a, **k: started.append("workers") or make(*a, **k))
    monkeypatch.setattr(run, "analyze_ahead", lambda *a, **k: started.append("analysis") or ahead(*a, **k))
    assert main(["calibrate", str(same), "--json", "--quiet"]) == 0
    assert set(_status(json.loads(capsys.readouterr().out)).values()) == {"reused"}
    assert started == []


@pytest.mark.parametrize("text, expect", [
    ("[model]\nparameters = 'p.toml'\n[channels]\ncalibrate = ['a']\n[band]\nlow_hz = 1.0\nhigh_hz = 2.0\n",
     "no data: give [[run]] entries"),
    ("[model]\nparameters = 'p.toml'\n[[run]]\npath = 'a.h5'\nuff = 'a.uff'\n[channels]\ncalibrate = ['a']\n"
     "[band]\nlow_hz = 1.0\nhigh_hz = 2.0\n", "run.0: Value error, give exactly one of path (run file) or uff"),
    ("[model]\nparameters = 'p.toml'\n[[run]]\npath = 'a.h5'\n[channels]\ncalibrate = ['a']\n"
     "[band]\nlow_hz = 1.0\nhigh_hz = 2.0\n[calibration]\nstrats = 3\n", "calibration.strats: unknown field"),
    ("[model]\nparameters = 'p.toml'\n[pretest]\n[layout]\nfile = 'l.json'\n[acquisition]\nplan = 'p.toml'\n"
     "[channels]\ncalibrate = ['a']\n[band]\nlow_hz = 1.0\nhigh_hz = 2.0\n", "give [pretest]"),
    ("[model]\nparameters = 'p.toml'\n[acquisition]\nplan = 'p.toml'\ndriver = 'ni'\n[channels]\n"
     "calibrate = ['a']\n[band]\nlow_hz = 1.0\nhigh_hz = 2.0\n", "driver 'ni' needs hardware"),
    ("[model]\nparameters = 'p.toml'\n[[run]]\npath = 'a.h5'\n[channels]\ncalibrate = ['a']\n"
     "[band]\nlow_hz = 1.0\nhigh_hz = 2.0\n[lines]\nstart_hz = 1.0\n",
     {"run": "lines: unknown field", "calibrate": "lines: unknown field", "identify": "both a campaign",
      "acquire": "both a campaign"}),
    ("[model]\nparameters = 'p.toml'\n[[run]]\npath = 'missing.h5'\n[channels]\ncalibrate = ['a']\n"
     "[band]\nlow_hz = 1.0\nhigh_hz = 2.0\n", {"acquire": "nothing to acquire: add an [acquisition] section"}),
])
@pytest.mark.parametrize("command", ["run", "calibrate", "identify", "acquire"])
def test_campaign_errors_are_one_line_saying_what_to_fix_and_v_gives_the_traceback(tmp_path, capsys, text, expect,
                                                                                command):
    """Through `frfcal run`/`calibrate` and the campaign form of the stage commands (a dict: per command)."""
    camp = tmp_path / "c.toml"
    camp.write_text(text)
    if isinstance(expect, dict):
        expect = expect.get(command, "missing.h5: cannot read")
    assert main([command, str(camp)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"frfcal {command}: error: ") and expect in err[0], err
    with pytest.raises(ValueError, match=re.escape(expect)):
        main([command, str(camp), "-v"])  # -v after the sub-command: the exception and its traceback


def test_later_stages_plug_in_with_a_line_each_and_are_stored_like_the_others(small, monkeypatch):
    """How diagnosis and the report join the campaign: StageSpec entries in LATE_STAGES."""
    import frfcal.campaign._run as run_mod
    from frfcal.campaign import StageSpec, load_campaign, run_campaign, section

    tmp, camp_path, ref = small
    same = tmp / "small_late.toml"
    same.write_text(camp_path.read_text().replace('dir = "out"', 'dir = "ref"'))
    calls = []

    def diagnose(ctx):
        calls.append("diagnose")
        assert ctx.outputs is None and ctx.camp.run[0].path.name == "A1.h5"
        m, v = ctx.results["calibrate"].members[0], ctx.results["validate"].members[0].validation
        return {"p": m.p, "sd_holdout": v.sd_calibrated}

    def report(ctx):
        calls.append("report")
        assert ctx.results["diagnose"]["sd_holdout"] == ctx.outputs["members"][0]["validation"]["sd_calibrated"]
        return {"members": len(ctx.outputs["members"])}

    monkeypatch.setattr(run_mod, "LATE_STAGES", [
        StageSpec("diagnose", ("calibrate", "validate"), lambda c: section(c, "band"), diagnose),
        StageSpec("report", ("diagnose",), lambda c: section(c, "output", "write_bdf"), report, after_outputs=True),
    ])
    camp = load_campaign(same)
    logged = []
    res = run_campaign(camp, log=logged.append)
    assert list(res["stages"]) == ["import", *CORE, "diagnose", "report"]
    assert _status(res)["diagnose"] == "ran" and _status(res)["report"] == "ran" and calls == ["diagnose", "report"]
    assert "[9/10] diagnose: done in" in "\n".join(logged)
    np.testing.assert_array_equal(_stored(tmp, res, "diagnose")["p"], _params(ref)[0])
    again = run_campaign(camp, log=lambda m: None)
    assert set(_status(again).values()) == {"reused"} and calls == ["diagnose", "report"]
    # `frfcal calibrate` stops after cross-validation: the later stages are not its business
    upto = run_campaign(camp, log=lambda m: None, upto="crossvalidate")
    assert list(upto["stages"]) == ["import", *CORE]
    # a changed setting redoes the stage that reads it, and only that one
    changed = camp.model_copy(update={"output": camp.output.model_copy(update={"write_bdf": False})})
    st = _status(run_campaign(changed, log=lambda m: None))
    assert st["report"] == "ran" and st["diagnose"] == "reused" and calls == ["diagnose", "report", "report"]


def test_an_internal_fault_is_two_lines_and_v_shows_it(tmp_path, capsys, monkeypatch):
    import frfcal.commands.run as run_cmd

    def broken(args, upto):
        raise ZeroDivisionError("division by zero")

    monkeypatch.setattr(run_cmd, "run_stage", broken)
    assert main(["run", str(tmp_path / "c.toml")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["frfcal run: internal error: ZeroDivisionError: division by zero",
                   "frfcal run: rerun with -v for the traceback and report it"]
    with pytest.raises(ZeroDivisionError):
        main(["-v", "run", str(tmp_path / "c.toml")])


#: code that would execute or unpickle what a user hands in
_UNSAFE = re.compile(r"\beval\(|\bexec\(|\bimport pickle\b|\bfrom pickle\b|\bpickle\.loads?\(|allow_pickle\s*=\s*True"
                     r"|\bmarshal\.loads?\(|\bshelve\.open\(|\byaml\.(unsafe_)?load\(|\bcloudpickle\.loads?\("
                     r"|\bdill\.|\bjoblib\.load\(|\btorch\.load\(|__import__\(")


def test_nothing_a_user_loads_is_executed_or_unpickled():
    hits = []
    for pkg in ("frfcal", "calibration", "femodel", "acquisition", "identification", "pretest", "labdata"):
        for f in sorted((REPO / pkg).rglob("*.py")):
            for n, line in enumerate(f.read_text().splitlines(), 1):
                if _UNSAFE.search(line.split("#")[0]):
                    hits.append(f"{f.relative_to(REPO)}:{n}: {line.strip()}")
    assert not hits, "\n".join(hits)
    # the stored stage results are rebuilt only as frfcal's own types, arrays read without pickle
    store = (REPO / "frfcal" / "campaign" / "_store.py").read_text()
    assert "allow_pickle=False" in store and "_ALLOWED" in store



def test_the_documented_campaign_files_are_valid():
    """docs/campaign.md: the reference block, the complete example, and it turned into an acquiring campaign."""
    import tomllib

    from frfcal.campaign import campaign_from_dict

    blocks = [tomllib.loads(b) for b in re.findall(r"```toml\n(.*?)```", (REPO / "docs" / "campaign.md").read_text(),
                                                   re.S)]
    front, reference, example, inline, simulation = blocks
    assert [e.uff is not None for e in campaign_from_dict(reference).run] == [False, True]
    assert [str(e.uff) for e in campaign_from_dict(example).run] == ["data/A1.uff", "data/A2.uff"]
    acquiring = {k: v for k, v in example.items() if k != "run"}
    acquiring.update(pretest=front["pretest"], acquisition=inline["acquisition"])
    camp = campaign_from_dict(acquiring)
    assert camp.acquisition.driver == "sim" and camp.pretest.sensors == 20 and not camp.run
    with pytest.raises(ValueError, match="not both"):
        campaign_from_dict({**acquiring, "run": example["run"]})
    sim = campaign_from_dict({**acquiring, "simulation": simulation["simulation"]}).simulation  # the [simulation] block
    assert sim.effect[0].kind == "spring" and sim.loose_part.article == "SF5"


if __name__ == "__main__":  # the executor comparison in a fresh process (see _executor_comparison)
    print(json.dumps(_executor_comparison(Path(sys.argv[1]), json.loads(sys.argv[2]), sys.argv[3])))


def test_report_of_a_uff_campaign_reads_the_runs_the_import_stage_wrote(small, capsys):
    # `frfcal report` after `frfcal run` on UFF58 entries: it refused ("uff = ... is not imported yet")
    tmp, camp, ref = small
    assert main(["report", str(camp), "--out", str(tmp / "ref"), "--quiet"]) == 0
    assert f"report: {tmp / 'ref' / 'report.html'}" in capsys.readouterr().out
    html = (tmp / "ref" / "report.html").read_text()
    assert "Hold-out" in html or "hold-out" in html
    # without a stored import stage (another output directory) it says what to run
    assert main(["report", str(camp), "--out", str(tmp / "nothing-here"), "--quiet"]) == 2
    assert "no stored import stage matching the campaign" in capsys.readouterr().err
