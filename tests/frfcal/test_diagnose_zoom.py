"""The zoom of the point families (issue 14): a lumped mass at a grid the spread sample does not hold is found.

The spread sample of ``lumped_mass`` / ``ground_spring`` puts candidates at ``spread_grids`` grids; a mass
between them is explained only in part by the nearest sampled one (on outside data a stiffness cluster at
the same place was accepted instead). The zoom screens the family's candidates at the grids around the best
ones (``femodel.zoom_candidates`` through ``point_zoom`` and ``calibration.screen(zoom=...)``). The frame
example (82 grids, 492 DOF) with ``spread_grids = 8``, 10 sensors, 2 drives; truth = the calibration model
(offset parameters) + a mass of the family's p = 1 (1 % of the total mass, 1.31 kg) at a grid that is not a
candidate of the spread sample; full-order FRFs with 0.5 % log-normal noise, equalized damping.
"""

from __future__ import annotations

import numpy as np
import pytest

import femodel
from calibration import FitData, FRFModel, build_surrogate, full_order_frf, half_bandwidth_frequencies, screen
from femodel import AddedMass, CandidateOptions, candidate_context, generate_candidates, parametric_model
from frfcal.campaign._diagnose import candidate_term, point_zoom
from tests.calibration._models import frame_sensor_model

ZETA = 0.02
BAND = (5.0, 150.0)
SHIFT_HZ = max(BAND[0] / 4, BAND[1] / 50)
P_TRUE = np.array([0.05, -0.03, 0.08, 0.1, -0.1, 0.2, -0.1])


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    ex = femodel.example_frame(tmp_path_factory.mktemp("zoom_frame"))
    pm = parametric_model(ex.params)
    grids, dirs, model = frame_sensor_model(pm)
    sur, T = build_surrogate(model, np.zeros(pm.n_params), BAND)
    ctx = candidate_context(pm, sensors=grids, drives=[(grids[0], dirs[0]), (grids[5], dirs[5])],
                            options=CandidateOptions(spread_grids=8))
    return pm, model, sur, T, ctx


def _data(pm, model, grid, kg):
    f = half_bandwidth_frequencies(*BAND, ZETA, 3)
    ext = pm.with_terms([AddedMass("m_truth", (grid,), kg)])
    mt = FRFModel(ext.K, ext.M, model.inputs, model.outputs, parameter_names=ext.names, parametric=ext)
    H = full_order_frf(mt, np.r_[P_TRUE, 1.0], f, ZETA)
    rng = np.random.default_rng(0)
    H = H * 10 ** (0.005 * (rng.normal(size=H.shape) + 1j * rng.normal(size=H.shape)) / np.sqrt(2))
    return [FitData(f, H, model.output_names)]


def _screen(frame, data, zoom: bool):
    pm, model, sur, T, ctx = frame
    p0 = np.zeros(pm.n_params)
    cands = list(generate_candidates(pm, families=["lumped_mass", "ground_spring"], context=ctx))
    terms = [candidate_term(pm, c, p0) for c in cands]
    z = point_zoom(ctx, pm, p0, cands, terms) if zoom else None
    s = screen(sur, T, p0, data, ZETA, terms, pm.lower, pm.upper, model=model, shift_hz=SHIFT_HZ, n_check=3,
               groups=[c.family for c in cands], zoom=z, zoom_rounds=ctx.options.zoom_rounds)
    return s, {c.name: c for c in cands}


@pytest.mark.parametrize("grid", [45, 12])
def test_a_mass_between_the_spread_grids_is_found_by_the_zoom(frame, grid):
    pm, model, sur, T, ctx = frame
    sample = {c.grids[0] for c in generate_candidates(pm, families=["lumped_mass"], context=ctx)}
    assert grid not in sample and grid not in ctx.sensors  # not a candidate of the spread sample
    kg = ctx.options.lumped_mass_fraction * ctx.total_mass
    data = _data(pm, model, grid, kg)
    at = ctx.xyz[int(ctx.grid_index([grid])[0])]

    def where(cand):
        return float(np.linalg.norm(ctx.xyz[int(ctx.grid_index([cand.grids[0]])[0])] - at))

    # without the zoom the best is a sampled mass elsewhere, explaining a part, at a wrong magnitude
    s0, c0 = _screen(frame, data, zoom=False)
    b0 = c0[s0.best]
    assert b0.grids[0] != grid and where(b0) > 3 * b0.size * ctx.length_m
    assert s0.check(s0.best).explained < 0.5
    # with it: the mass at its grid (within one element size), its magnitude within 20 %, nearly all of the
    # residual explained; the zoom screened tens of candidates, not every grid
    s, cands = _screen(frame, data, zoom=True)
    b = cands[s.best]
    assert b.family == "lumped_mass" and where(b) <= b.size * ctx.length_m
    chk = s.check(s.best)
    assert chk.c * kg == pytest.approx(kg, rel=0.2)
    assert chk.explained > 0.9
    assert 0 < len(s.zoomed) < 80 and len(s.names) == len(cands)
    assert f"mass_g{grid}" in s.zoomed


def test_the_zoom_again_in_a_re_screening_adds_only_new_candidates(frame):
    """As the diagnosis re-screens after an accepted effect: the other candidates again, with the same zoom,
    which offers only grids never screened (the accepted one and the first zoom's included) and appends their
    terms to the campaign's lists."""
    pm, model, sur, T, ctx = frame
    kg = ctx.options.lumped_mass_fraction * ctx.total_mass
    data = _data(pm, model, 45, kg)
    p0 = np.zeros(pm.n_params)
    cands = list(generate_candidates(pm, families=["lumped_mass", "ground_spring"], context=ctx))
    terms = [candidate_term(pm, c, p0) for c in cands]
    z = point_zoom(ctx, pm, p0, cands, terms)
    s1 = screen(sur, T, p0, data, ZETA, terms, pm.lower, pm.upper, n_check=0, zoom=z)
    n1 = len(terms)
    assert len(cands) == n1 == len(s1.names) and s1.best == "mass_g45"
    rest = [t for t in terms if t.name != s1.best]
    s2 = screen(sur, T, p0, data, ZETA, rest, pm.lower, pm.upper, n_check=0, zoom=z)
    assert len(terms) == len(cands) == n1 + len(s2.zoomed)
    assert s2.zoomed and not set(s2.zoomed) & set(s1.names)
    assert [t.name for t in terms[n1:]] == list(s2.zoomed) == [c.name for c in cands[n1:]]
    assert "mass_g45" not in s2.names


def test_the_log_says_which_point_families_are_sampled(frame):
    """A spread sample is said (the verdict's hint to sample densely depends on it); every grid is not."""
    from frfcal.campaign._diagnose import _sampled_points

    pm, _, _, _, ctx = frame
    cands = list(generate_candidates(pm, families=["lumped_mass", "ground_spring"], context=ctx))
    said = _sampled_points(ctx, cands)
    assert said.startswith("lumped_mass at ") and ", ground_spring at 8 of 82 grids" in said
    full = candidate_context(pm, sensors=ctx.sensors, drives=ctx.drives)  # default: every grid of this frame
    assert _sampled_points(full, list(generate_candidates(pm, families=["lumped_mass", "ground_spring"],
                                                          context=full))) == ""
