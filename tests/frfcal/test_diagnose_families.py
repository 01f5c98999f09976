"""Per-family evidence of the diagnosis (issue 14, docs/diagnosis.md "Per-family evidence").

For each undeclared effect of :func:`frfcal.effects.standard_effects` (sensor_mass, shaker_attachment,
ground_spring, element_cluster) the example frame (492 DOF) is synthesized with that one effect (1 article,
16 sensors x 2 drives, 60-350 Hz), imported from UFF58 and run through ``frfcal diagnose``; the issue's
criteria are asserted:

* the residual after the plain calibration is flagged as significant;
* the true effect ranks first: family right, location within two element sizes, magnitude (the accepted,
  refined value) within 20 %;
* after adding it the held-out SD falls to within 2x the floor (the truth against its own noise on the
  hold-out channels).

lumped_mass is in tests/frfcal/test_diagnose.py (with the control: the frame without any effect, nothing
screened, nothing accepted); contact_spring is the gap ensemble's (h-gap). A criterion a family does not meet
for a reason measured and not fixed here is an ``xfail(strict=True)`` naming the reason (``XFAIL``).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from frfcal.cli import main
from tests.frfcal.test_diagnose import _frame_campaign

#: candidate families (femodel.generate_candidates) that are the right family for each undeclared effect
FAMILIES = {
    "sensor_mass": ("sensor_mass",),
    "shaker_attachment": ("shaker_attachment", "shaker_attachment_mass"),
    "ground_spring": ("ground_spring",),
    "element_cluster": ("element_cluster",),
}

#: (family, test) -> measured reason the criterion is not met (strict xfail: a fix turns it into a failure)
XFAIL: dict = {}

#: the two fastest cases run in `make test-heavy` (CI), the others with -m slow
_SLOW = ("shaker_attachment", "ground_spring")


def _xfail(request, family, test):
    reason = XFAIL.get((family, test))
    if reason:
        request.applymarker(pytest.mark.xfail(strict=True, reason=reason))


@pytest.fixture(scope="module", params=[pytest.param(f, marks=pytest.mark.slow if f in _SLOW else pytest.mark.heavy)
                                        for f in FAMILIES])
def case(request, tmp_path_factory):
    family = request.param
    tmp = tmp_path_factory.mktemp(f"diag_{family}")
    camp, pm, effects, sc, hold = _frame_campaign(tmp, family)
    assert main(["diagnose", str(camp), "--quiet"]) == 0
    d = json.loads((tmp / "out" / "diagnosis.json").read_text())
    return family, pm, effects, d["members"][0], sc.floor_sd(channels=hold)


def _truth_center(pm, eff) -> np.ndarray:
    """Where the true effect acts, basic coordinates (m: the frame is SI)."""
    fe = pm.assembly.model
    term = eff.term
    if hasattr(term, "elements"):  # ElementFactor: mean of its elements' centres
        pts = []
        for card, t in fe.elements.items():
            if "pid" not in t.fields:
                continue
            ids = np.asarray(t.ids)
            sel = np.isin(ids, term.elements)
            if np.any(sel):
                nodes = np.asarray(t.fields["nodes"])[sel]
                pts.append(fe.xyz[fe.grid_index(nodes.ravel()).reshape(nodes.shape)].mean(axis=1))
        return np.concatenate(pts).mean(axis=0)
    grids = term.grids if hasattr(term, "grids") else [d[0] for d in term.dofs]
    return fe.xyz[fe.grid_index(list(grids))].mean(axis=0)


def _magnitude(eff) -> float:
    """The size that is compared: a mass (kg), a spring rate (N/m), a stiffness change 1 - factor."""
    return 1.0 - eff.value if eff.family == "element_cluster" else eff.value


def assert_ranks_first(m, pm, eff, families) -> None:
    """The issue's rank criterion on one member of diagnosis.json: residual significant, the first-ranked
    candidate of the right family within two element sizes of the true effect ``eff``."""
    r = m["residual"]
    assert r["significant"] and r["ratio"] > 2 and m["verdict"] != "nothing to explain"
    top = m["ranked"][0]
    assert top["family"] in families, f"ranked first: {top['description']}"
    # (the shaker attachment's first effect is its mass: it dominates, its spring is sized for a quarter shift)
    dist = float(np.linalg.norm(_truth_center(pm, eff) - np.asarray(top["center"])))
    assert dist <= 2 * top["element_size"], f"{top['name']} {dist:.3f} m from the truth"


def assert_accepted_at_the_floor(m, pm, eff, family, families, floor) -> None:
    """The issue's acceptance criterion: the first accepted effect of the right family, within two element
    sizes, magnitude within 20 %, refined hold-out SD within 2x the floor."""
    assert m["accepted"], f"nothing accepted: {[t.get('decision', {}).get('reason') for t in m['trials']]}"
    a = m["accepted"][0]
    assert a["family"] in families, f"accepted first: {a['description']}"
    dist = float(np.linalg.norm(_truth_center(pm, eff) - np.asarray(a["center"])))
    assert dist <= 2 * a["element_size"], f"{a['name']} {dist:.3f} m from the truth"
    got = 1.0 - a["value"] if family == "element_cluster" else a["value"]
    assert got == pytest.approx(_magnitude(eff), rel=0.2)
    after = m["sd"]["after"]
    assert after["holdout_refined"] < 2 * floor, (
        f"hold-out {m['sd']['holdout']:.3g} -> {after['holdout_refined']:.3g} = "
        f"{after['holdout_refined'] / floor:.2f} x floor {floor:.3g}")


def test_the_residual_is_significant_and_the_true_effect_ranks_first(case, request):
    family, pm, effects, m, _ = case
    _xfail(request, family, "rank")
    assert_ranks_first(m, pm, effects[0], FAMILIES[family])


def test_the_true_effect_is_accepted_with_its_magnitude_and_the_holdout_falls_to_the_floor(case, request):
    family, pm, effects, m, floor = case
    _xfail(request, family, "accept")
    assert_accepted_at_the_floor(m, pm, effects[0], family, FAMILIES[family], floor)
