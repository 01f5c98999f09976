"""Per-family evidence of the diagnosis on a shell model (issue 14, docs/diagnosis.md "Per-family evidence").

The shell counterpart of tests/frfcal/test_diagnose_families.py (the beam/frame model): the example subframe
(welded CQUAD4 sheet-metal shells, 17 parameters) at a coarse size (``example_subframe(target_dof=1500)``,
1584 DOF, SI deck), 16 single-axis sensors of the pretest EfI layout for the elastic modes in the band and its
two drive points (``pretest.plan_pretest``), 1 article, UFF58 import, ``frfcal diagnose``. One undeclared
effect of :func:`frfcal.effects.standard_effects` at a time; the truth is synthesized with
``synthesize(effects=...)`` (``ParametricModel.with_terms``, exact), independently of the candidate generator
and of the calibration surrogate. The issue's criteria are asserted:

* the residual after the plain calibration is flagged as significant;
* the true effect ranks first: family right, location within two element sizes, magnitude (the accepted,
  refined value) within 20 %;
* after adding it the held-out SD falls to within 2x the floor (the truth against its own noise on the
  hold-out channels);
* the control (the deck as it is): nothing accepted.

A criterion a family does not meet for a reason measured and not fixed here is an ``xfail(strict=True)``
naming the reason (``XFAIL``).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

import femodel
from frfcal.cli import main
from tests.frfcal.test_diagnose_families import FAMILIES as _FRAME_FAMILIES
from tests.frfcal.test_diagnose_families import assert_accepted_at_the_floor, assert_ranks_first

#: the calibration band: the subframe's first 15 elastic modes (137-576 Hz at 1584 DOF)
BAND = (100.0, 600.0)
#: grid DOF of the coarse subframe
SHELL_DOF = 1500

#: candidate families (femodel.generate_candidates) that are the right family for each undeclared effect
FAMILIES = dict(_FRAME_FAMILIES, lumped_mass=("lumped_mass",))

#: the measured cause common to every family (docs/diagnosis.md "Per-family evidence", shell): the screening and
#: the acceptance's trials work on the equalized target, resynthesized from the identified model, and on this
#: shell the identified model (automatic order 32) does not fit its own data: fit SD 0.17-0.20, mostly below 300 Hz
#: (mean squared log error 1.0-1.25 at 90-120 Hz, below the first elastic mode at 147 Hz where the rigid-body mass
#: line dominates, 0.18-0.56 at 120-300 Hz, <= 0.15 above; the 352.0 and 565.9 Hz modes are stable poles labelled
#: negligible, importance 0.22 and 0.15 < 1), and the equalized SD of the calibrated model is 0.29 on the control
#: itself, against raw residuals of 0.002 (control) to 0.02 (an effect). The
#: equalized residual is then the identification's error, the same in every case: the same ground springs in y
#: (grids 110, 108, 124, 98, 250) and a mass at grid 251 rank first with 2-9 % explained whatever the truth is,
#: and their trials raise the raw hold-out 1.5-25 x.


#: that was measured with ``[diagnosis] target = "equalized"`` (the screening's target before the
#: debiased raw lines became the default); with ``"debiased"`` the element cluster passes every criterion
#: (truth ranked 1st by the screening, 92.2 % explained; accepted, factor 0.699; hold-out 6.98e-4 = 1.2 x the
#: floor 5.8e-4), and so does the lumped mass (mass_g44 ranked 1st, 25.8 %; accepted, 0.230 kg (+3 %); hold-out
#: 1.36e-3 = 1.08 x the floor 1.26e-3), the ground spring (ground_g15_z 1st, 17.4 %; accepted 7.17e4 N/m, -1 %;
#: refined hold-out 1.32e-3) and the sensor mass (1st, 11.7 %; accepted 1.70 g, +2 %; refined hold-out 1.00e-3), the
#: test's assertions evaluated on one run each; the shaker attachment passes through pytest (below)

#: (family, test) -> measured reason the criterion is not met (strict xfail: a fix turns it into a failure).
#: With target = debiased the shaker attachment passes too (its two strict xfails, measured with the
#: equalized target, XPASSed on main f805f7f: `pytest -m slow tests/frfcal/test_diagnose_shell.py -k shaker`).
#: Before, with target = equalized: the true attachment mass ranked 20th of 496 (1.6 %), its stinger 430th, a
#: 2-element PSHELL 20 cluster first; nothing accepted (raw hold-out 0.150 -> 0.23-0.32).
#: The ground spring failed on main 6eaf6ae (debiased target + zoom): ground_g27_z accepted 0.100 m (2.5 element
#: sizes) from the truth's grid 15 at +40 %: the springs near the rail end tie in the screening (14.4-14.7 % linear,
#: 17.3-17.6 % re-fitted) and grid 15 was never checked nor tried; the acceptance now recalibrates the places that
#: tie with the best point effect and keeps the lowest hold-out SD (frfcal/campaign/_diagnose.py _tied_places).
XFAIL: dict = {}

#: every family case is slow (a 1584-DOF case is 220-280 s CPU: 105-175 s in the main process, 105-120 s in the
#: pool); the control (74 s CPU) runs by default
_FAST: tuple = ()


def _shell_campaign(tmp, effects_family, *, gap_mm=None, target_dof=SHELL_DOF, gap_closed=None):
    """Synthesize the coarse subframe (1 article; one standard effect or none), import the UFF, write the campaign.

    Returns (campaign path, parametric model, effects, SynthCampaign, hold-out channel names).
    """
    from pretest import PretestConfig, plan_pretest

    from frfcal.effects import standard_effects
    from frfcal.synth import SynthChannel, synthesize

    ex = femodel.example_subframe(tmp / "model", target_dof, units="si", gap_mm=gap_mm)
    pm = femodel.parametric_model(ex.params)
    plan = plan_pretest(pm.assembly.model, PretestConfig(n_sensors=16, band_hz=BAND, n_drives=2),
                        assembly=pm.assembly)
    sensors = [SynthChannel(f"s{i + 1}", int(g), tuple(float(x) for x in d))
               for i, (g, d) in enumerate(zip(plan.sensors.grids, plan.sensors.directions))]
    # the subframe is mirror-symmetric: its two best drive points tie exactly and their order follows round-off
    # (it differs between processes); sorted by grid id, F1 is always the same one
    order = np.argsort(plan.drives.grids, kind="stable")
    drives = [SynthChannel(f"F{i + 1}", int(plan.drives.grids[k]), tuple(float(x) for x in plan.drives.directions[k]))
              for i, k in enumerate(order)]
    effects = ()
    if effects_family:
        gap = ex.gap_pairs if gap_closed is None else [ex.gap_pairs[i] for i in gap_closed]
        effects = standard_effects(pm, sensors, drives, gap=gap or None, band_hz=BAND)[effects_family]
    sc = synthesize(ex.bdf, ex.params, tmp / "data", sensors=sensors, drives=drives, band_hz=BAND, n_articles=1,
                    seed=3, scatter=0.003, effects=effects, parametric=pm)
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
        + '[calibration]\nstarts = 4\n[crossvalidation]\nrealizations = 3\n[execution]\nworkers = 2\n'
        + f'[output]\ndir = "{tmp / "out"}"\nfigures = false\n'
    )
    return camp, pm, effects, sc, hold


def _xfail(request, family, test):
    reason = XFAIL.get((family, test))
    if reason:
        request.applymarker(pytest.mark.xfail(strict=True, reason=reason))


@pytest.fixture(scope="module", params=[f if f in _FAST else pytest.param(f, marks=pytest.mark.slow)
                                        for f in FAMILIES])
def case(request, tmp_path_factory):
    family = request.param
    tmp = tmp_path_factory.mktemp(f"shell_{family}")
    camp, pm, effects, sc, hold = _shell_campaign(tmp, family)
    assert main(["diagnose", str(camp), "--quiet"]) == 0
    d = json.loads((tmp / "out" / "diagnosis.json").read_text())
    return family, pm, effects, d["members"][0], sc.floor_sd(channels=hold)


def test_shell_residual_after_the_plain_calibration_is_significant(case):
    # not under the rank/accept xfails: measured on every family (3.6-12.7 x the floor)
    m = case[3]
    r = m["residual"]
    assert r["significant"] and r["ratio"] > 2 and m["verdict"] != "nothing to explain"
    assert m["screening"] is not None and m["candidates"]  # the candidates were screened


def test_shell_residual_is_significant_and_the_true_effect_ranks_first(case, request):
    family, pm, effects, m, _ = case
    _xfail(request, family, "rank")
    assert_ranks_first(m, pm, effects[0], FAMILIES[family])


def test_shell_true_effect_is_accepted_with_its_magnitude_and_the_holdout_falls_to_the_floor(case, request):
    family, pm, effects, m, floor = case
    _xfail(request, family, "accept")
    assert_accepted_at_the_floor(m, pm, effects[0], family, FAMILIES[family], floor)


@pytest.fixture(scope="module")
def shell_control(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("shell_control")
    camp, _, _, sc, hold = _shell_campaign(tmp, None)
    assert main(["diagnose", str(camp), "--quiet"]) == 0
    return json.loads((tmp / "out" / "diagnosis.json").read_text()), sc.floor_sd(channels=hold)


@pytest.mark.heavy
def test_shell_control_without_an_effect_accepts_nothing(shell_control):
    d, _ = shell_control
    m = d["members"][0]
    assert not m["accepted"] and m["verdict"] in ("nothing to explain", "no effect accepted")
    assert d["gates"][0]["nonlinearity"] is None


@pytest.mark.slow  # 411 s wall (synthesis, identification, calibration, screening 165 s, acceptance)
def test_a_gap_closed_on_two_of_its_five_pairs_is_found_on_those_pairs(tmp_path):
    """The subframe at 2808 DOF with its 2 mm gap (5 facing pairs), closed on the middle two only: the
    family's cells and windows hold 2-5 pairs, the best holds 4. The acceptance fits a rate per pair of it
    (frfcal/campaign/_diagnose.py ``_contact_shape``) and accepts the pairs that carry one. Measured: the
    per-pair fit over 4 pairs keeps exactly the two closed ones (18.6 s); accepted at 9.62e4 N/m per pair
    (truth 9.627e4), refined hold-out 0.00525 = 1.00 x the truth's floor."""
    camp, pm, effects, sc, hold = _shell_campaign(tmp_path, "contact_spring", gap_mm=2.0, target_dof=3000,
                                                  gap_closed=(1, 2))
    (eff,) = effects
    assert main(["diagnose", str(camp), "--quiet"]) == 0
    m = json.loads((tmp_path / "out" / "diagnosis.json").read_text())["members"][0]
    assert m["residual"]["significant"]
    (a,) = m["accepted"]
    truth = {int(d[k]) for d in eff.term.dofs for k in (0, 2)}
    assert a["family"] == "contact_spring" and set(a["grids"]) == truth and a.get("shaped_from")
    assert a["value"] == pytest.approx(eff.value, rel=0.2)
    floor = sc.floor_sd(channels=hold)
    assert m["sd"]["after"]["holdout_refined"] < 2 * floor
