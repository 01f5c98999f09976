"""The demo as a campaign: simulated articles (truth plants), their sweeps, calibration, level dependence.

* The simulated lab's plant of an article *is* frfcal.synth's exact truth
  (free-free rigid-body modes, per-mode damping, the higher-mode residual).
* A reduced campaign (1,600-DOF subframe, 3 articles, short sweeps, the high
  level on two of them) runs acquire -> calibrate; the in-class article's
  hold-out SD lands within a few x its own noise floor.
* The loose article's runs differ between levels (level_dependence flags it);
  an in-class article measured at the same two levels is not flagged.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

import femodel
from acquisition import ChannelSpec, ShakerModel, SimulatedLab, read_run
from acquisition._plan import plan_from_dict
from frfcal.campaign._acquire import (SimulationError, acquire_simulated, level_checks, runs_by_level,
                                      simulated_articles, truth_plant)
from frfcal.campaign._schema import SimulationSection, campaign_from_dict

BAND = (100.0, 400.0)
DATA = (80.0, 500.0)


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    ex = femodel.example_subframe(tmp_path_factory.mktemp("sf"), target_dof=1500)
    pm = femodel.parametric_model(ex.params)
    return ex, pm


def _channels(pm, n=12):
    """n sensors (normal to the mostly horizontal shells: Z) spread over the grids, drive at one of them."""
    grids = np.asarray(pm.assembly.model.grid_ids)
    pick = grids[np.linspace(3, grids.size - 4, n).astype(int)]
    sensors = [dict(name=f"acc{i + 1}", grid=int(g), direction=(0.0, 0.0, 1.0)) for i, g in enumerate(pick)]
    drive = dict(name="force1", role="force", quantity="force", grid=int(pick[min(4, n - 1)]), direction=(0.0, 0.0, 1.0))
    return sensors, drive


def _specs(entries):
    return [ChannelSpec(name=e["name"], role=e.get("role", "response"), quantity=e.get("quantity", "acceleration"),
                        unit="N" if e.get("role") == "force" else "m/s^2", grid=e["grid"], direction=e["direction"])
            for e in entries]


def test_plant_is_the_synth_truth(model):
    """Plant FRF = ArticleTruth FRF (rigid modes at 0 Hz, residual of the higher modes) to 1e-9 relative."""
    _, pm = model
    sensors, drive = _channels(pm)
    sim = SimulationSection(mode_factor=1.5)
    (art,) = simulated_articles(sim, pm, ["A1"], _specs(sensors), _specs([drive]), data_hz=DATA,
                                log=lambda *_: None)
    f = np.linspace(DATA[0], DATA[1], 3001)
    f = np.sort(np.concatenate([f, art.plant.frequencies_hz[(art.plant.frequencies_hz > DATA[0])
                                                            & (art.plant.frequencies_hz < DATA[1])]]))
    H_truth = art.truth.frf(f, "accelerance")
    H_plant = art.plant.frf(f)
    rel = np.abs(H_plant - H_truth) / np.abs(H_truth)
    assert rel.max() < 1e-9, rel.max()
    assert art.truth.n_rigid == 6 and np.all(art.plant.frequencies_hz > 1.0)  # free-free, rigid modes not states
    # without the feedthrough (rigid-body mass line + higher modes) the plant would be far off
    rel_modes = np.abs(H_plant - art.plant.feedthrough(f) - H_truth) / np.abs(H_truth)
    assert rel_modes.max() > 0.1
    # the receptance form agrees too (rigid modes: -phi phi^T / w^2)
    rp = truth_plant(art.truth, "receptance")
    assert np.max(np.abs(rp.frf(f) - art.truth.frf(f, "receptance")) / np.abs(art.truth.frf(f, "receptance"))) < 1e-9


def test_simulated_lab_steady_state_is_the_plant_frf(model):
    """The lab's measured FRF at one line (feedthrough applied to the delivered force) equals plant.frf."""
    _, pm = model
    sensors, drive = _channels(pm, n=4)
    (art,) = simulated_articles(SimulationSection(mode_factor=1.5), pm, ["A1"], _specs(sensors), _specs([drive]),
                                data_hz=DATA, log=lambda *_: None)
    lab = SimulatedLab(art.plant, shaker=ShakerModel(), noise_rms=0.0, adc_bits=32)
    chans = [ChannelSpec(name=s["name"], role="response", quantity="acceleration", unit="m/s^2",
                         physical=f"sim/{k}") for k, s in enumerate(sensors)]
    chans.append(ChannelSpec(name="force1", role="force", quantity="force", unit="N", physical="sim/force"))
    lab.configure(chans, 4096.0)
    f0 = 137.0
    lab.set_drive(f0, 0.2)
    lab.read_block(int(f0 * 30))  # 30 s: transients of damping >= 1e-3 decay by > exp(-25)
    blk = lab.read_block(400)
    t = blk.t0_s + np.arange(blk.samples.shape[1]) / blk.rate_hz
    e = np.exp(-2j * np.pi * f0 * t)
    X = blk.samples @ e
    H = X[:-1] / X[-1]
    ref = art.plant.frf(f0)[0, :, 0]
    assert np.max(np.abs(H / ref - 1)) < 1e-5


def _plan(pm, articles, levels):
    # no known poles: the articles' resonances differ from the nominal model's by a few per cent, more than the
    # dense region of a predicted pole covers; the controller finds them on a 1 % background and refines them
    sensors, drive = _channels(pm)
    return plan_from_dict(dict(
        name="t", sample_rate_hz=1280.0, channels=sensors + [drive],
        lines=dict(kind="bandwidth", start_hz=DATA[0], stop_hz=DATA[1], background_step=0.01, lines_per_bandwidth=3,
                   span_bandwidths=2),
        force=dict(levels_n=levels), settle=dict(tolerance=3e-3, assumed_damping=0.002),
        measure=dict(blocks=3, n_harmonics=1),
        refine=dict(enabled=True, lines_per_bandwidth=3, span_bandwidths=2, peak_ratio=1.02),
        ensemble=dict(articles=articles)))


@pytest.fixture(scope="module")
def acquired(model, tmp_path_factory):
    ex, pm = model
    out = tmp_path_factory.mktemp("camp")
    sensors, drive = _channels(pm)
    grids = np.asarray(pm.assembly.model.grid_ids)
    sim = SimulationSection.model_validate(dict(
        scatter=0.003, seed=3, mode_factor=1.5, noise_rms=2e-5,
        effect=[dict(name="contact", kind="spring", articles=["A2"], pairs=[(int(grids[10]), int(grids[200]))],
                     rate_n_per_m=2e6)],
        loose_part=dict(article="A3", shift=0.003, from_level_n=4.0)))
    plan = _plan(pm, ["A1", "A2", "A3"], [1.0, 4.0])
    arts, runs = acquire_simulated(sim, plan, pm, out / "runs", levels={"A1": [1.0, 4.0], "A2": [1.0], "A3": [1.0, 4.0]},
                                   log=lambda *_: None)
    return ex, pm, out, arts, runs, sensors


@pytest.mark.heavy
def test_runs_per_article_and_level(acquired):
    _, _, _, arts, runs, _ = acquired
    by = runs_by_level([r.path for r in runs])  # the levels come back from the run files' plans
    assert {a: [lv for lv, _ in v] for a, v in by.items()} == {"A1": [1.0, 4.0], "A2": [1.0], "A3": [1.0, 4.0]}
    assert [r.nonlinear for r in runs] == [False, False, False, False, True]
    for r in runs:
        run = read_run(r.path)
        assert run.status == "completed" and run.valid.mean() > 0.95, (r.path, np.unique(run.flags))
        assert abs(np.median(run.force_n) / r.level_n - 1) < 0.03
    # the contact spring is in A2's truth only, and it shifts its modes
    eff = {a.name: dict(a.effects)["contact"] for a in arts}
    assert eff == {"A1": 0.0, "A2": 1.0, "A3": 0.0}


@pytest.mark.heavy
def test_level_dependence_flags_the_loose_article_only(acquired):
    _, _, _, arts, runs, _ = acquired
    checks = level_checks(runs_by_level(runs), settle_tolerance=3e-3)
    assert set(checks) == {"A1", "A3"}
    assert checks["A3"].flagged, checks["A3"].to_dict()
    assert not checks["A1"].flagged, checks["A1"].to_dict()
    # given the article's modes (as the campaign passes its identified ones), the change is located at the
    # loose mode: a flagged mode row or the model-free difference's largest line nearest to it
    a3 = next(a for a in arts if a.name == "A3")
    fm = np.asarray(a3.plant.frequencies_hz, float)
    fm = fm[(fm > DATA[0]) & (fm < DATA[1])]
    loose_hz = float(a3.plant.frequencies_hz[a3.loose_mode])
    given = level_checks(runs_by_level(runs), settle_tolerance=3e-3, modes_hz={"A3": fm.tolist()})["A3"]
    assert given.flagged, given.to_dict()
    where = [c.frequency_hz for c in given.changes if c.flagged] + [p.peak_hz for p in given.pairs if p.flagged]
    near = [fm[np.argmin(np.abs(fm - w))] for w in where]
    assert near and all(abs(n - loose_hz) < 1e-6 * loose_hz for n in near), (loose_hz, where, fm)


@pytest.mark.heavy
def test_reduced_campaign_calibrates_to_the_noise_floor(acquired):
    """acquire -> calibrate on the in-class article A1 (1 N): hold-out SD within a few x its noise floor."""
    from frfcal.campaign import run_campaign

    ex, pm, out, arts, runs, sensors = acquired
    names = [s["name"] for s in sensors]
    calibrate, holdout = names[0::2], names[1::2]
    a1 = next(r for r in runs if r.article == "A1" and r.level_n == 1.0)
    camp = campaign_from_dict({
        "model": {"parameters": str(ex.params), "units": "mm-t-s"},
        "run": [{"path": str(a1.path)}],
        "channels": {"calibrate": calibrate, "holdout": holdout},
        "band": {"low_hz": BAND[0], "high_hz": BAND[1]},
        "calibration": {"starts": 2, "max_cycles": 2},
        "crossvalidation": {"realizations": 0},
        "output": {"dir": str(out / "cal"), "figures": False, "write_bdf": False},
    }, base_dir=out)
    run_campaign(camp, log=lambda *_: None, upto="crossvalidate")
    res = json.loads((out / "cal" / "calibration.json").read_text())
    v = res["members"][0]["validation"]
    # the floor: the noiseless truth against the measured hold-out lines in the band
    run = read_run(a1.path)
    art = next(a for a in arts if a.name == "A1")
    f = run.frequency_hz
    sel = (f >= BAND[0]) & (f <= BAND[1]) & run.valid
    idx = [names.index(c) for c in holdout]
    truth = art.truth.frf(f[sel])[:, idx]
    floor = float(np.mean(np.abs(np.log(truth / run.frf[sel][:, idx])) ** 2) / np.log(10) ** 2)
    print(f"A1 hold-out SD {v['sd_nominal']:.3g} -> {v['sd_calibrated']:.3g}; noise floor {floor:.3g} "
          f"({v['sd_calibrated'] / floor:.2f}x)")
    assert v["sd_calibrated"] < 5 * floor, (v, floor)
    assert v["sd_nominal"] > 100 * floor  # the paper's offsets are far outside the noise


def test_simulation_errors_name_the_field(model):
    _, pm = model
    sensors, drive = _channels(pm)
    with pytest.raises(SimulationError, match="loose_part.article 'B9'"):
        simulated_articles(SimulationSection(loose_part=dict(article="B9", from_level_n=4.0)), pm, ["A1"],
                           _specs(sensors), _specs([drive]), data_hz=DATA)
    with pytest.raises(SimulationError, match="offsets: unknown parameter"):
        simulated_articles(SimulationSection(offsets={"nope": 0.1}), pm, ["A1"], _specs(sensors), _specs([drive]),
                           data_hz=DATA)
    from calibration import CalibrationError

    with pytest.raises(CalibrationError, match="effect 'g': kind 'spring' needs pairs"):
        campaign_from_dict({"model": {"parameters": "p.toml"}, "run": [{"path": "r.h5"}],
                            "channels": {"calibrate": ["a"]}, "band": {"low_hz": 1, "high_hz": 2},
                            "simulation": {"effect": [{"name": "g", "kind": "spring", "articles": ["A1"]}]}})


def _result(accepted: bool) -> dict:
    """A run_campaign result as the demo's two groups leave it: group1 (gap closed) significant, group2 with the
    loose article flagged by the level check."""
    cal = [{"member": "group1", "articles": ["SF1", "SF2", "SF3"], "sd_calibration_nominal": 0.61,
            "sd_calibration": 0.12, "sd_raw_calibration_start": 0.35, "sd_raw_calibration": 0.21,
            "validation": {"sd_nominal": 0.52, "sd_calibrated": 0.31, "sd_floor": 4.2e-5}},
           {"member": "group2", "articles": ["SF4", "SF5"], "sd_calibration_nominal": 0.58,
            "sd_calibration": 0.004, "sd_raw_calibration_start": 0.01, "sd_raw_calibration": 0.0005,
            "validation": {"sd_nominal": 0.38, "sd_calibrated": 0.0073, "sd_floor": 4.2e-5}}]
    ranked = [{"rank": 1, "name": "contact_PSHELL21_PSHELL2_1", "family": "contact_spring", "size": "3.1e+05 N/m",
               "explained": 0.62, "description": "contact springs (z) between PSHELL 21 and PSHELL 2", "c": 8.0},
              {"rank": 2, "name": "lumped_mass_7", "family": "lumped_mass", "size": "0.21 kg", "explained": 0.05,
               "description": "lumped mass at grid 7", "c": 1.0}]
    g1 = {"member": "group1", "articles": ["SF1", "SF2", "SF3"], "ranked": ranked, "candidates": {"contact_spring": 4},
          "sd": {"floor": 1.6e-5, "scatter": 0.0052},
          "verdict": "effect(s) found" if accepted else "no effect accepted",
          "reason": "accepted: ..." if accepted else "the screening ranks contact_spring ... first; not accepted: x",
          "accepted": [dict(ranked[0], decision={"accepted": True})] if accepted else []}
    if accepted:
        g1["sd"]["after"] = {"calibration_equalized": 0.01, "calibration_raw": 0.0009, "holdout": 0.002,
                             "holdout_refined": 0.0011}
    g2 = {"member": "group2", "articles": ["SF4", "SF5"], "verdict": "nonlinear", "reason": "SF5: level dependence",
          "sd": {"floor": 1.6e-5, "scatter": 0.0004}, "ranked": [], "accepted": []}
    gates = [{"article": a, "nonlinearity": {"flagged": a == "SF5", "verdict": "nonlinear" if a == "SF5" else "linear",
                                             "modes": [{"frequency_hz": 389.0, "quantity": "frequency_hz",
                                                        "levels": [0.25, 1.0], "values": [389.0, 387.8], "z": 41.0}]
                                             if a == "SF5" else []}} for a in ("SF1", "SF2", "SF3", "SF4", "SF5")]
    return {"members": cal, "articles": ["SF1", "SF2", "SF3", "SF4", "SF5"], "grouping": {"labels": [0, 0, 0, 1, 1]},
            "stages": {"calibrate": {"status": "ran", "time_s": 80.0}}, "report": "/x/campaign/report.html",
            "diagnosis": {"gates": gates, "members": [g1, g2], "separating_effects": []}}


@pytest.mark.parametrize("accepted", [True, False])
def test_closing_summary_headline(accepted):
    """The demo's closing lines name the report, the groups, the SD before/after beside the floor, the effect found
    (or what ranked first) and the nonlinear article; the headline JSON carries the same numbers."""
    from frfcal.commands.demo import closing_summary

    lines, head = closing_summary(_result(accepted))
    text = "\n".join(lines)
    assert lines[0].startswith("report: /x/campaign/report.html")
    assert "grouping: 2 article group(s): SF1, SF2, SF3 | SF4, SF5" in text
    row = next(ln for ln in lines if ln.strip().startswith("hold-out, raw lines"))
    vals = row.split()[-4:]
    assert vals[0] == "0.52" and vals[1] == "0.31" and vals[3] == "4.2e-05"
    assert vals[2] == ("0.0011" if accepted else "-")  # the refined hold-out after the effect, else none
    assert "nonlinear article(s): SF5 (mode at 389 Hz: frequency_hz 389 -> 387.8 from 0.25 to 1 N (41 sigma))" in text
    assert head["nonlinear"] == ["SF5"] and head["groups"] == [["SF1", "SF2", "SF3"], ["SF4", "SF5"]]
    g1 = head["members"][0]
    assert g1["sd"]["hold-out, raw lines"]["calibrated"] == 0.31
    if accepted:
        assert "effect found: group1: contact_spring contact_PSHELL21_PSHELL2_1 (3.1e+05 N/m)" in text
        assert g1["accepted"][0]["name"] == "contact_PSHELL21_PSHELL2_1"
    else:
        assert "effect found: none accepted" in text
        assert "ranked 1: contact_spring contact_PSHELL21_PSHELL2_1 (3.1e+05 N/m), explains 62.0 %" in text
        assert g1["ranked_first"] == "contact_PSHELL21_PSHELL2_1" and g1["accepted"] == []
    # the group whose verdict is "nonlinear" gives its reason, not a ranking
    assert "SF5: level dependence" in text


def test_closing_summary_without_diagnosis():
    """Without the diagnose stage the summary says so and takes the nonlinear articles from the level checks."""
    from frfcal.commands.demo import closing_summary

    res = _result(False)
    del res["diagnosis"], res["report"]
    lines, head = closing_summary(res, checks={"SF4": False, "SF5": True, "SF1": "one level"})
    text = "\n".join(lines)
    assert "report: not written" in text and "effect found: the diagnose stage did not run" in text
    assert "nonlinear article(s) (level check of the acquired runs): SF5" in text and head["nonlinear"] == ["SF5"]
