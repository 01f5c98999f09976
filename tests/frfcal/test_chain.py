"""The whole chain on data generated independently of it: synthesize -> UFF58 -> import -> identify ->
equalize -> calibrate -> refine -> validate, through the command line, against the noise floor.

Truth: the example frame (CBAR with Nastran's default lumped mass, so M is singular and the model is
under 1500 DOF; CONM2 masses; CELAS2 mounts) at parameter offsets of 5-15 %, 0.3 % article scatter,
damping 0.05-0.3 % varying from mode to mode, free-free (rigid-body mass line), modes to 3x the band
top plus the exact residual of the higher ones, 0.5-1 % noise proportional to |H| plus a floor, an
uneven line grid dense at each article's resonances (``frfcal.synth``). Two drives: a MIMO UFF58
file per article, and response/drive pairs the frame barely couples.

The floor is the SD of the truth itself against its own noisy lines, on the same pairs the campaign
keeps.
"""

import json

import numpy as np
import pytest

import femodel
from frfcal.cli import main
from frfcal.synth import SynthChannel, synthesize

pytestmark = pytest.mark.heavy  # two campaign fixtures of ~30 s each: `make test-heavy`

BAND = (60.0, 350.0)
SCATTER = 0.003


@pytest.fixture(scope="module")
def frame_chain(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("frame_chain")
    ex = femodel.example_frame(tmp / "model")
    pm = femodel.parametric_model(ex.params)
    g = np.asarray(pm.assembly.model.grid_ids)
    pick = g[np.linspace(2, len(g) - 3, 16).astype(int)]
    dirs = [(0.0, 0.0, 1.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), (1.0, 0.0, 0.0)]  # some sensors point -Z
    sensors = [SynthChannel(f"s{i + 1}", int(gid), dirs[i % 4]) for i, gid in enumerate(pick)]
    drives = [SynthChannel("F1", int(pick[3]), (0.0, 0.0, 1.0)), SynthChannel("F2", int(pick[10]), (0.0, 1.0, 0.0))]
    sc = synthesize(ex.bdf, ex.params, tmp / "data", sensors=sensors, drives=drives, band_hz=BAND, n_articles=2,
                    seed=3, scatter=SCATTER)
    runs = []
    for a, uff in zip(sc.articles, sc.uff_paths):
        out = tmp / "runs" / f"{a}.h5"
        assert main(["import-uff", str(uff), "--out", str(out), "--article", a]) == 0
        runs.append(out)
    names = [s.name for s in sensors]
    cal = names[0::2] + names[1::4]
    hold = [n for n in names if n not in cal]
    camp = tmp / "campaign.toml"
    camp.write_text(
        f'[model]\nparameters = "{ex.params}"\n'
        + "".join(f'[[run]]\npath = "{r}"\n' for r in runs)
        + f"[channels]\ncalibrate = {json.dumps(cal)}\nholdout = {json.dumps(hold)}\n"
        + f"[band]\nlow_hz = {BAND[0]}\nhigh_hz = {BAND[1]}\n"
        + '[calibration]\nstarts = 4\nensemble = "article"\n'
        + "[crossvalidation]\nrealizations = 3\n[execution]\nworkers = 2\n"
        + f'[output]\ndir = "{tmp / "out"}"\nfigures = false\n'
    )
    assert main(["calibrate", str(camp), "--quiet"]) == 0
    result = json.loads((tmp / "out" / "calibration.json").read_text())
    return sc, pm, result, cal, hold, runs


def test_frame_deck_is_mass_singular_and_small():
    """The case the dense path failed on: lumped-mass bars (massless rotations), <= 1500 DOF."""
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as d:
        ex = femodel.example_frame(Path(d))
        pm = femodel.parametric_model(ex.params)
        M = pm.mass(np.zeros(pm.n_params)).tocsr()
        assert pm.K.shape[0] <= 1500
        assert np.sum(M.diagonal() == 0) > pm.K.shape[0] // 3


def test_mimo_uff_import_keeps_both_references(frame_chain):
    from acquisition.runfile import read_run

    sc, _, _, _, _, runs = frame_chain
    run = read_run(runs[0])
    assert [d.name for d in run.drives] == ["F1", "F2"]
    assert [d.grid for d in run.drives] == [d.grid for d in sc.drives]
    assert np.asarray(run.frf).shape[1:] == (16, 2)
    assert [tuple(s.direction) for s in run.sensors][:2] == [(0.0, 0.0, 1.0), (0.0, 0.0, -1.0)]


def test_frame_chain_reaches_the_noise_floor(frame_chain):
    """Hold-out SD within 2x the floor (campaign's own figure, and with the truth's damping); raw lines too."""
    sc, _, result, cal, hold, _ = frame_chain
    for m in result["members"]:
        (a,) = m["articles"]
        p = np.array([row["p"] for row in m["parameters"]])
        floor_hold = sc.floor_sd(hold, BAND, [a])
        floor_cal = sc.floor_sd(cal, BAND, [a])
        assert m["validation"]["sd_nominal"] > 100 * floor_hold  # there was something to calibrate
        assert m["validation"]["sd_calibrated"] < 2.0 * floor_hold, (a, m["validation"]["sd_calibrated"], floor_hold)
        # with the truth's damping: measured 1.00x on both articles (1.01x and 1.31x with uniform raw-line weights)
        assert sc.model_sd(p, a, hold, BAND) < 1.2 * floor_hold
        assert m["sd_raw_calibration"] < 2.0 * floor_cal


def _standard_error_floor(sc, channels, article):
    """The floor the true standard errors would print (noise_floor_sd's formula on the noisy lines)."""
    from calibration._metric import log_noise_floor

    z = sc.truth()
    idx, lo, hi, (i,) = sc._selection(channels, BAND, [article])
    f = z[f"frequency_hz_{i}"]
    sel = (f >= lo) & (f <= hi)
    q = log_noise_floor(z[f"noisy_{i}"][sel][:, idx], z[f"sigma_{i}"][sel][:, idx])
    return float(np.mean(q[:, sc.signal_pairs(i, [str(z["sensors"][k]) for k in idx], (lo, hi))]))


def test_uff_campaign_prints_floors_estimated_from_the_lines(frame_chain):
    """UFF58 carries no standard errors: the hold-out and raw-line floors are estimated from the lines
    (calibration.estimate_std_error) and said so; the hold-out's within 30 % of the truth's own floor, both
    within 30 % of the floor the true standard errors give. (On the raw calibration lines the truth's own
    floor was 2x lower on A1: one pair, s14 / F2, at SNR near 1 on its anti-resonances held most of the mean
    of (sigma/|H|)^2, where |log10(H_noisy/H)|^2 saturates. Since stop 33 both floors are the exact
    E|log10(1 + n/H)|^2, which saturates too: the first-order reference gave 1.0e-3 there against the
    estimate's 5.3e-4.)"""
    sc, _, result, cal, hold, _ = frame_chain
    for m in result["members"]:
        (a,) = m["articles"]
        v = m["validation"]
        assert v["floor_source"] == "estimated from adjacent lines"
        assert abs(v["sd_floor"] / sc.floor_sd(hold, BAND, [a]) - 1) < 0.3, (a, v["sd_floor"])
        assert abs(v["sd_floor"] / _standard_error_floor(sc, hold, a) - 1) < 0.3, (a, v["sd_floor"])
        assert m["sd_raw_floor_source"] == "estimated from adjacent lines"
        assert abs(m["sd_raw_floor"] / _standard_error_floor(sc, cal, a) - 1) < 0.3, (a, m["sd_raw_floor"])
        # the verdict keeps its words; the floor ratio is the calibrated SD over the estimated floor
        assert v["verdict"] == "improved" and v["floor_ratio"] == pytest.approx(v["sd_calibrated"] / v["sd_floor"])


def test_frame_chain_parameters_within_three_times_the_article_scatter(frame_chain):
    sc, _, result, _, _, _ = frame_chain
    for m in result["members"]:
        (a,) = m["articles"]
        p = np.array([row["p"] for row in m["parameters"]])
        p_true = sc.p_true[sc.articles.index(a)]
        err = np.abs((1 + p) / (1 + p_true) - 1)
        ident = np.array([row["identifiable"] for row in m["parameters"]])
        assert ident.all(), [row["identifiability"] for row in m["parameters"]]
        assert err[ident].max() < 3 * SCATTER, err
        assert all(row["cv_percent"] is not None for row in m["parameters"])


SHELL_BAND = (100.0, 400.0)


@pytest.fixture(scope="module")
def shell_chain(tmp_path_factory):
    """The shell example (17 parameters) with a pretest layout: 20 sensors, the paper's 11/9 split."""
    tmp = tmp_path_factory.mktemp("shell_chain")
    ex = femodel.example_subframe(tmp / "model", target_dof=4500, units="mm-t-s")
    layout = tmp / "layout.json"
    assert main(["pretest", str(ex.bdf), "--units", "mm-t-s", "--sensors", "20", "--modes", "20",
                 "--out", str(layout)]) == 0
    lay = json.loads(layout.read_text())
    sensors = [SynthChannel(c["name"], int(c["grid"]), tuple(c["direction"])) for c in lay["channels"]]
    drives = [SynthChannel(d["name"], int(d["grid"]), tuple(d["direction"])) for d in lay["drives"]]
    sc = synthesize(ex.bdf, ex.params, tmp / "data", sensors=sensors, drives=drives, band_hz=SHELL_BAND,
                    n_articles=1, seed=5, units="mm-t-s", scatter=SCATTER)
    run = tmp / "runs" / "A1.h5"
    assert main(["import-uff", str(sc.uff_paths[0]), "--out", str(run), "--article", "A1"]) == 0
    names = [s.name for s in sensors]
    cal = [names[i] for i in (0, 4, 6, 9, 11, 12, 13, 14, 17, 18, 19)]
    hold = [n for n in names if n not in cal]
    camp = tmp / "campaign.toml"
    camp.write_text(
        f'[model]\nparameters = "{ex.params}"\n[[run]]\npath = "{run}"\n'
        + f"[channels]\ncalibrate = {json.dumps(cal)}\nholdout = {json.dumps(hold)}\n"
        + f"[band]\nlow_hz = {SHELL_BAND[0]}\nhigh_hz = {SHELL_BAND[1]}\n"
        + "[calibration]\nstarts = 6\n[crossvalidation]\nrealizations = 5\n[execution]\nworkers = 2\n"
        + f'[output]\ndir = "{tmp / "out"}"\nfigures = false\n'
    )
    assert main(["calibrate", str(camp), "--quiet"]) == 0
    return sc, json.loads((tmp / "out" / "calibration.json").read_text()), cal, hold


def test_shell_chain_reaches_the_floor_and_flags_what_it_cannot_tell_apart(shell_chain):
    sc, result, cal, hold = shell_chain
    (m,) = result["members"]
    p = np.array([row["p"] for row in m["parameters"]])
    floor_hold, floor_cal = sc.floor_sd(hold, SHELL_BAND), sc.floor_sd(cal, SHELL_BAND)
    assert m["validation"]["sd_nominal"] > 100 * floor_hold
    assert m["validation"]["sd_calibrated"] < 2.0 * floor_hold, (m["validation"]["sd_calibrated"], floor_hold)
    # with the truth's damping: measured 1.00x (1.51x with uniform raw-line weights)
    assert sc.model_sd(p, 0, hold, SHELL_BAND) < 1.3 * floor_hold
    assert m["sd_raw_calibration"] < 2.0 * floor_cal
    err = np.abs((1 + p) / (1 + sc.p_true[0]) - 1)
    ident = np.array([row["identifiable"] for row in m["parameters"]])
    # 11 channels and the 7 modes of 100-400 Hz see the arm-region thicknesses only in combinations at relative
    # singular values of 5e-4..5e-3; the noise-weighted raw-line fit still finds every parameter (measured:
    # all 17 within 0.18 %; with every value weighted alike the arm thicknesses came back 2.8-14 % off), and
    # the 5 cross-validation refits clear all but two of the flagged ones (measured 15 of 17)
    assert 10 <= ident.sum()
    assert err.max() < 3 * SCATTER, dict(zip([r["name"] for r in m["parameters"]], np.round(100 * err, 3)))
    for row in m["parameters"]:
        if not row["identifiable"]:
            assert "combination" in row["identifiability"] or "bound" in row["identifiability"]
