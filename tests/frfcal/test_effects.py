"""Undeclared effects in synthetic truth data: each family moves the truth, the calibration model lacks it.

The frame (504 DOF with its bump stops) carries the per-family and ensemble
checks; a coarse shell subframe with a doubler (1752 DOF) the shell checks.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

import femodel
from acquisition.runfile import read_run
from calibration import grouping, pairwise_sd
from frfcal.cli import main
from frfcal.effects import CLUSTER_FACTOR, Effect, EffectError, first_order_shifts, mode_shifts, standard_effects
from frfcal.synth import SynthChannel, SynthError, synthesize

BAND = (40.0, 110.0)
FAMILIES = ("sensor_mass", "shaker_attachment", "contact_spring", "ground_spring", "element_cluster", "lumped_mass")
FAST = dict(base_lines=60, lines_per_bandwidth=3)


def frame_channels(pm):
    """Seven sensors (one pointing -Z, one oblique) and two drives on the frame (as tests/frfcal/test_synth.py)."""
    g = np.asarray(pm.assembly.model.grid_ids)
    picks = [(3, (0, 0, 1)), (10, (0, 0, -1)), (20, (0, 1, 0)), (30, (0, 0, 1)), (45, (1, 0, 0)),
             (60, (0.6, 0.0, 0.8)), (70, (0, 0, 1))]
    sensors = [SynthChannel(f"acc{i + 1}", int(g[j]), d) for i, (j, d) in enumerate(picks)]
    drives = [SynthChannel("force1", int(g[5]), (0, 0, 1)), SynthChannel("force2", int(g[33]), (0.5, 0.3, 0.8))]
    return sensors, drives


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    d = tmp_path_factory.mktemp("effects_frame")
    ex = femodel.example_frame(d / "model", gap_mm=3.0)
    pm = femodel.parametric_model(ex.params)
    sensors, drives = frame_channels(pm)
    std = standard_effects(pm, sensors, drives, gap=ex.gap_pairs, band_hz=BAND)
    return d, ex, pm, sensors, drives, std


@pytest.fixture(scope="module")
def family_campaign(frame):
    """Six articles, article k with the effect(s) of family k only."""
    d, ex, pm, sensors, drives, std = frame
    effects = [dataclasses.replace(e, articles=(k,)) for k, fam in enumerate(FAMILIES) for e in std[fam]]
    camp = synthesize(ex.bdf, ex.params, d / "families", sensors=sensors, drives=drives, band_hz=BAND,
                      n_articles=len(FAMILIES), seed=3, parametric=pm, effects=effects, **FAST)
    return camp


def test_standard_effects_of_the_frame(frame):
    """One effect per family at a plausible size, each moving an in-band mode by several half-power bandwidths."""
    d, ex, pm, sensors, drives, std = frame
    assert set(std) == set(FAMILIES)
    assert [e.term.name for e in std["shaker_attachment"]] == ["shaker_mass", "stinger_spring"]
    mass = ex.mass_kg
    (sm,), (lm,), (gs,), (cs,), (cl,) = (std[f] for f in ("sensor_mass", "lumped_mass", "ground_spring",
                                                             "contact_spring", "element_cluster"))
    assert set(sm.term.grids) == {s.grid for s in sensors} and sm.unit == "kg"
    assert 0.005 < sm.value * len(sm.term.grids) / mass < 0.05  # 1-5 % of the structure in sensors
    assert lm.value < 0.01 * mass and lm.term.grids[0] not in {c.grid for c in sensors + drives}
    assert gs.term.dofs[0][1:] == (3, 0, 0) and gs.unit == "N/m"
    assert sorted((a, b) for a, c1, b, c2 in cs.term.dofs) == sorted(ex.gap_pairs)
    assert {c1 for _, c1, _, _ in cs.term.dofs} == {3}  # along the gap (z)
    assert cl.value == CLUSTER_FACTOR and 3 <= len(cl.term.elements) <= 8
    pids = np.asarray(pm.assembly.model.elements["CBAR"].fields["pid"])[
        np.isin(pm.assembly.model.elements["CBAR"].ids, cl.term.elements)]
    assert len(set(pids.tolist())) == 1  # a sub-region of one property group
    for fam in FAMILIES:
        ms = mode_shifts(pm, std[fam], band_hz=BAND)
        bw = ms.bandwidths(zeta=1e-3)
        assert bw.max() > 2.5, f"{fam}: largest shift {bw.max():.2f} half-power bandwidths at 0.1 %"
        assert np.abs(ms.relative).max() < 0.1 and ms.mac.min() > 0.8, fam
    # the sizing rule: each spring or mass has a largest first-order shift of exactly 1 % (contact 10 %)
    ref_rule = {"sensor_mass": 0.01, "lumped_mass": 0.01, "ground_spring": 0.01, "contact_spring": 0.1}
    from frfcal.effects import _reference_modes

    ref = _reference_modes(pm, np.zeros(pm.n_params), BAND, 10)
    for fam, target in ref_rule.items():
        (e,) = std[fam]
        assert np.abs(first_order_shifts(pm, e.term, e.value, ref)).max() == pytest.approx(target, rel=1e-9)


def test_truth_has_the_effect_and_the_model_lacks_it(family_campaign):
    """model_sd at the true p: far above the floor without the effect, exactly the floor with it."""
    camp = family_campaign
    for a, fam in enumerate(FAMILIES):
        es = camp.article_effects(a)
        assert {e.family for e in es} == {fam}
        floor = camp.floor_sd(articles=[a])
        lacking = camp.model_sd(camp.p_true[a], a)
        extended = camp.model_sd(camp.p_true[a], a, terms=[e.term for e in es], values=[e.value for e in es])
        assert extended == pytest.approx(floor, rel=1e-6), fam
        assert lacking > 10 * floor, f"{fam}: model without the effect {lacking:.3g} vs floor {floor:.3g}"


def test_every_family_at_once(frame, tmp_path):
    """All seven terms on one article (two springs to ground lift two rigid modes); the other has none."""
    d, ex, pm, sensors, drives, std = frame
    effects = [dataclasses.replace(e, articles=("A1",)) for es in std.values() for e in es]
    camp = synthesize(ex.bdf, ex.params, tmp_path, sensors=sensors, drives=drives, band_hz=BAND, n_articles=2,
                      seed=4, parametric=pm, effects=effects, write_uff=False, **FAST)
    z = camp.truth()
    assert np.sum(z["modes_hz_0"] == 0.0) == 4 and np.sum(z["modes_hz_1"] == 0.0) == 6
    assert len(camp.article_effects(0)) == 7 and camp.article_effects(1) == ()
    es = camp.article_effects(0)
    full = camp.model_sd(camp.p_true[0], 0, terms=[e.term for e in es], values=[e.value for e in es])
    assert full == pytest.approx(camp.floor_sd(articles=[0]), rel=1e-6)
    assert camp.model_sd(camp.p_true[1], 1) == pytest.approx(camp.floor_sd(articles=[1]), rel=1e-6)
    assert camp.model_sd(camp.p_true[0], 0) > 100 * camp.floor_sd(articles=[0])
    # a ground spring 1e-4 of the standard one lifts a rigid-body mode to a fraction of a Hz and changes
    # nothing in the band: the in-band modes keep their damping (matched by frequency, not shifted by index)
    (g,) = std["ground_spring"]
    soft = camp.model_sd(camp.p_true[1], 1, terms=[g.term], values=[1e-4 * g.value])
    assert soft == pytest.approx(camp.floor_sd(articles=[1]), rel=0.02)


def test_a_lifted_rigid_mode_is_a_damped_low_mode(family_campaign):
    """Springs to ground make one rigid mode elastic: below the band, with the top of zeta_range."""
    camp = family_campaign
    z = camp.truth()
    for fam in ("shaker_attachment", "ground_spring"):
        a = FAMILIES.index(fam)
        f, zeta = z[f"modes_hz_{a}"], z[f"zeta_{a}"]
        assert np.sum(f == 0.0) == 5 and 0 < f[5] < BAND[0]
        assert zeta[5] == 3e-3 and np.all(zeta[6:] < 3e-3 * 1.25)


def test_effects_are_recorded(family_campaign, tmp_path):
    """truth.npz, SynthCampaign and each run file's plan carry the effects; UFF58 round-trips via import-uff."""
    camp = family_campaign
    z = camp.truth()
    records = json.loads(str(z["effects"]))
    assert records == [json.loads(json.dumps(r)) for r in camp.effects]
    by_name = {r["name"]: r for r in records}
    assert by_name["contact_spring"]["family"] == "contact_spring" and by_name["contact_spring"]["unit"] == "N/m"
    assert by_name["contact_spring"]["articles"] == [camp.articles[FAMILIES.index("contact_spring")]]
    assert by_name["cluster_K"]["unit"] == "factor" and by_name["cluster_K"]["value"] == CLUSTER_FACTOR
    assert by_name["cluster_K"]["elements"] and by_name["sensor_mass"]["grids"]
    for a in (0, 1):  # sensor mass; shaker mass + stinger
        run = read_run(camp.run_paths[a])
        names = [r["name"] for r in run.plan["effects"]]
        assert names == [e.name for e in camp.article_effects(a)]
        assert [r["value"] for r in run.plan["effects"]] == [e.value for e in camp.article_effects(a)]
        out = tmp_path / f"{a}.h5"
        assert main(["import-uff", str(camp.uff_paths[a]), "--out", str(out)]) == 0
        back = read_run(out)
        np.testing.assert_array_equal(back.frf, run.frf)
        np.testing.assert_array_equal(back.frf, z[f"noisy_{a}"])


def _base_lines(run, base):
    """Indices of the base (log-spaced, common to all articles) lines in a run's line grid."""
    idx = np.searchsorted(run.frequency_hz, base)
    idx = np.clip(idx, 0, run.frequency_hz.size - 1)
    assert np.allclose(run.frequency_hz[idx], base, rtol=1e-9)
    return idx


def test_three_closed_two_open_group_apart(frame, tmp_path):
    """Contact on 3 of 5 articles: the imported UFF58 FRFs group 3/2 by pairwise SD; without it, one group."""
    d, ex, pm, sensors, drives, std = frame
    (contact,) = std["contact_spring"]
    labels = {}
    for case, effects in (("gap", [dataclasses.replace(contact, articles=(0, 2, 4))]), ("none", None)):
        # grouping reads the common base lines only: one dense line per bandwidth keeps the run files short
        camp = synthesize(ex.bdf, ex.params, tmp_path / case, sensors=sensors, drives=drives, band_hz=BAND,
                          n_articles=5, seed=11, parametric=pm, effects=effects, base_lines=FAST["base_lines"],
                          lines_per_bandwidth=1)
        base = np.geomspace(camp.data_hz[0], camp.data_hz[1], FAST["base_lines"])
        frfs = []
        for a, uff in enumerate(camp.uff_paths):
            out = tmp_path / case / f"imported_{a}.h5"
            assert main(["import-uff", str(uff), "--out", str(out)]) == 0
            run = read_run(out)
            frfs.append(run.frf[_base_lines(run, base)])
        labels[case] = grouping(pairwise_sd(frfs)).labels
        if effects:
            assert [r["articles"] for r in camp.effects] == [["A1", "A3", "A5"]]
    assert labels["gap"].tolist() == [0, 1, 0, 1, 0]
    assert labels["none"].tolist() == [0, 0, 0, 0, 0]


def test_effect_validation(frame, tmp_path):
    d, ex, pm, sensors, drives, std = frame
    (sm,) = std["sensor_mass"]
    with pytest.raises(EffectError, match="positive"):
        Effect(sm.term, -1.0)
    with pytest.raises(EffectError, match="term must be"):
        Effect("spring", 1.0)
    with pytest.raises(EffectError, match="factor of exactly 1"):
        Effect(std["element_cluster"][0].term, 1.0)
    with pytest.raises(SynthError, match="article 7"):
        synthesize(ex.bdf, ex.params, tmp_path, sensors=sensors, drives=drives, band_hz=BAND, n_articles=2,
                   parametric=pm, effects=[dataclasses.replace(sm, articles=(7,))], write_uff=False)
    with pytest.raises(SynthError, match="used twice"):
        synthesize(ex.bdf, ex.params, tmp_path, sensors=sensors, drives=drives, band_hz=BAND, n_articles=2,
                   parametric=pm, effects=[sm, sm], write_uff=False)


# ----------------------------------------------------------------------------
# a shell model
# ----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def shell(tmp_path_factory):
    d = tmp_path_factory.mktemp("effects_shell")
    ex = femodel.example_subframe(d / "model", 1500, gap_mm=3.0)
    pm = femodel.parametric_model(ex.params)
    fe = pm.assembly.model
    gids = np.asarray(fe.grid_ids)

    def near(p_mm):
        return int(gids[np.argmin(np.linalg.norm(fe.xyz - np.asarray(p_mm) * 1e-3, axis=1))])

    picks = [((0, 0, 50), (0, 0, 1)), ((1000, 600, 50), (0, 0, 1)), ((500, 0, 25), (0, 1, 0)),
             ((300, 300, 50), (0, 0, 1)), ((700, 560, 130), (0, 0, 1)), ((860, 300, 0), (0, 0, 1)),
             ((280, 0, 0), (0, 1, 0))]  # the last one on the web next to the doubler
    sensors = [SynthChannel(f"acc{i + 1}", near(p), u) for i, (p, u) in enumerate(picks)]
    drives = [SynthChannel("force1", near((100, 600, 0)), (0, 0, 1))]
    return d, ex, pm, sensors, drives


def test_shell_effects_and_a_closed_gap(shell):
    """On the shell subframe every family shifts an in-band mode; the closed doubler gap is missing from the model."""
    d, ex, pm, sensors, drives = shell
    band = (120.0, 320.0)
    std = standard_effects(pm, sensors, drives, gap=ex.gap_pairs, band_hz=band)
    assert set(std) == set(FAMILIES)
    (sm,) = std["sensor_mass"]
    assert 0.001 < sm.value < 0.05  # kg: an accelerometer with its mount on a 16 kg subframe
    for fam in FAMILIES:
        bw = mode_shifts(pm, std[fam], band_hz=band).bandwidths(zeta=1e-3)
        assert bw.max() > 2.5, f"{fam}: {bw.max():.2f} half-power bandwidths"
    (contact,) = std["contact_spring"]
    assert {c for _, c, _, _ in contact.term.dofs} == {2}  # the doubler faces the web along y
    camp = synthesize(ex.bdf, ex.params, d / "gap", sensors=sensors, drives=drives, band_hz=band, n_articles=2,
                      seed=5, parametric=pm, effects=[dataclasses.replace(contact, articles=("A1",))],
                      write_uff=False, **FAST)
    closed, open_ = 0, 1
    floor_c, floor_o = camp.floor_sd(articles=[closed]), camp.floor_sd(articles=[open_])
    # model_sd solves up to the truth's top mode with Lanczos (sparse above 600 DOF): floor to ~1e-4
    assert camp.model_sd(camp.p_true[open_], open_) == pytest.approx(floor_o, rel=1e-3)
    assert camp.model_sd(camp.p_true[closed], closed) > 10 * floor_c
    assert camp.model_sd(camp.p_true[closed], closed, terms=[contact.term], values=[contact.value]) == \
        pytest.approx(floor_c, rel=1e-3)
