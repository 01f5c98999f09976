"""Candidate effects generated from a deck and a test set-up; term derivatives without rebuilding the model."""

from __future__ import annotations

import json
from collections import Counter

import numpy as np
import pytest

from femodel import (
    CANDIDATE_FAMILIES,
    POINT_FAMILIES,
    AddedMass,
    CandidateOptions,
    ParameterError,
    ParameterSet,
    Parameter,
    candidate_context,
    candidate_regions,
    example_frame,
    example_subframe,
    generate_candidates,
    parametric_model,
    read_bdf,
    register_family,
    zoom_candidates,
)

from ._decks import frame_deck

H = 0.01  # mesh spacing of the gap deck, m
GAP = 0.002  # the air gap, m


def gap_deck(path, h=H, dx=0.0):
    """Two steel plates (PSHELL 1 at z = 0, PSHELL 2 at z = 2 mm) overlapping on 3 x 3 facing grids.

    Plate A: grids 1..12 at x = 0..30 mm, y = 0..20 mm (spacing ``h``).
    Plate B: grids 101..112 at x = 10..40 mm (+ ``dx``), same y, z = 2 mm. Three of the nine facing
    pairs are joined: (2, 101) by a CELAS2, (6, 105) by a CELAS1 (PELAS 9),
    (12, 111) by an RBE2. A CBAR (PBAR 3) hangs off grid 4 away from plate
    B: grid 4 is a PSHELL 1 / PBAR 3 junction facing plate B, so (4, 103) is a
    contact candidate of its own (part "PBAR 3+PSHELL 1" against "PSHELL 2";
    :func:`_plain` leaves it out). No element joins the other five. SI.
    """
    lines = ["SOL 103", "CEND", "BEGIN BULK", "MAT1,1,2.1+11,,0.3,7850.", "PSHELL,1,1,0.002,1,,1",
             "PSHELL,2,1,0.0015,1,,1", "PBAR,3,1,1.0-5,1.0-10,1.0-10,2.0-10", "PELAS,9,1.0+5"]
    ga = {}
    gb = {}
    for j in range(3):
        for i in range(4):
            ga[i, j] = 1 + i + 4 * j
            gb[i, j] = 101 + i + 4 * j
            lines.append(f"GRID,{ga[i, j]},,{i * h!r},{j * h!r},0.")
            lines.append(f"GRID,{gb[i, j]},,{(i + 1) * h + dx!r},{j * h!r},{GAP!r}")
    eid = 1
    for g, pid in ((ga, 1), (gb, 2)):
        for j in range(2):
            for i in range(3):
                lines.append(f"CQUAD4,{eid},{pid},{g[i, j]},{g[i + 1, j]},{g[i + 1, j + 1]},{g[i, j + 1]}")
                eid += 1
    lines.append(f"GRID,50,,{3 * h + 0.05!r},0.,-0.05")
    lines.append("CBAR,20,3,4,50,0.,1.,0.")
    lines.append("CELAS2,30,1.0+5,2,3,101,3")
    lines.append("CELAS1,31,9,6,1,105,1")
    lines.append("RBE2,32,111,123456,12")
    lines.append("ENDDATA")
    path.write_text("\n".join(lines) + "\n")
    facing = {(ga[i + 1, j], gb[i, j]) for i in range(3) for j in range(3)}
    joined = {(2, 101), (6, 105), (12, 111)}
    assert joined < facing and (4, 103) in facing
    return path, facing - joined - {(4, 103)}, joined


@pytest.fixture(scope="module")
def frame_pm(tmp_path_factory):
    ex = example_frame(tmp_path_factory.mktemp("frame"))
    return parametric_model(ex.params)


@pytest.fixture(scope="module")
def shell_pm(tmp_path_factory):
    ex = example_subframe(tmp_path_factory.mktemp("sf1500"), target_dof=1500)
    return parametric_model(ex.params)


def _setup(pm, n_sensors=10):
    g = pm.assembly.model.grid_ids
    sensors = [int(x) for x in g[:: max(1, g.size // n_sensors)][:n_sensors]]
    return sensors, [(sensors[1], (0.1, 0.2, -1.0))]


def _plain(cands):
    """The candidates between single-part grids (the junction grid 4 facing plate B is a part pair of its own;
    the whole gap across both part pairs is the ``_gap`` candidate)."""
    return tuple(c for c in cands if not any("+" in p for p in c.parts) and "_gap" not in c.name)


def _contact_pairs(c):
    return {(min(g1, g2), max(g1, g2)) for g1, _, g2, _ in c.term.dofs}


def _element_sets(fe):
    return [set(int(x) for x in row if x > 0) for tab in fe.elements.values() for row in np.asarray(tab["nodes"])]


@pytest.mark.parametrize("h", [H, 0.005])
def test_gap_deck_contact_finds_exactly_the_unjoined_facing_pairs_of_single_part_grids(tmp_path, h):
    # at h = 5 mm the diagonal neighbours (5.4 mm) are within 1.5 element sizes too: only facing pairs count
    path, expected, joined = gap_deck(tmp_path / "gap.bdf", h)
    fe = read_bdf(path)
    every = generate_candidates(fe, families=["contact_spring"])
    (junction,) = [c for c in every if c not in _plain(every) and "_gap" not in c.name]
    assert _contact_pairs(junction) == {(4, 103)} and junction.parts == ("PBAR 3+PSHELL 1", "PSHELL 2")
    # the junction pair and the plain pairs are one gap: one candidate holds them all, one rate, on z
    (gap,) = [c for c in every if "_gap" in c.name]
    assert gap.parts == ("PSHELL 1", "PSHELL 2")
    assert _contact_pairs(gap) == {(min(a, b), max(a, b)) for a, b in expected} | {(4, 103)}
    assert {(d[1], d[3]) for d in gap.term.dofs} == {(3, 3)}
    cands = _plain(every)
    assert len(cands) == 1
    c = cands[0]
    assert _contact_pairs(c) == {(min(a, b), max(a, b)) for a, b in expected}
    assert not _contact_pairs(c) & joined
    # the gap is along z: one spring per pair on component 3
    assert {(d[1], d[3]) for d in c.term.dofs} == {(3, 3)}
    assert c.parts == ("PSHELL 1", "PSHELL 2")
    assert "2 mm" in c.description and "PSHELL 1" in c.description and "PSHELL 2" in c.description
    # location: the middle of the five pairs' grids, at most two element sizes off
    pts = np.array([fe.xyz[fe.grid_index([g])[0]] for g in c.grids])
    assert np.linalg.norm(np.array(c.center) - pts.mean(axis=0)) < 1e-12
    assert c.size == pytest.approx(h, rel=0.02)
    # p = 1 is a tenth of the smaller K diagonal at the sprung DOF (median over pairs)
    ctx = candidate_context(fe)
    kd = [min(ctx.stiffness_diagonal[fe.grid_index([a])[0], 2], ctx.stiffness_diagonal[fe.grid_index([b])[0], 2])
          for a, b in expected]
    assert c.term.scale == pytest.approx(0.1 * np.median(kd), rel=1e-12)


def test_contact_pairs_leave_out_the_overhang_whatever_the_grid_numbering(tmp_path):
    # plate B (z = 2 mm) covers x = h..4h of plate A (x = 0..3h); plate A's column x = 0 overhangs. Its grids
    # are numbered below plate B's, and plate B's below the rest of plate A: the overhang grid pairs with
    # plate B's edge grid only if "each is the other's nearest grid of its part" is checked from one end
    lines = ["SOL 103", "CEND", "BEGIN BULK", "MAT1,1,2.1+11,,0.3,7850.", "PSHELL,1,1,0.002,1,,1",
             "PSHELL,2,1,0.0015,1,,1"]
    h = 0.005  # the overhang grid (5.4 mm from plate B's edge grid) within 1.5 element sizes
    ga = {(i, j): (1 + j if i == 0 else 31 + 3 * (i - 1) + j) for i in range(4) for j in range(3)}
    gb = {(i, j): 11 + 3 * i + j for i in range(4) for j in range(3)}
    for (i, j), g in ga.items():
        lines.append(f"GRID,{g},,{i * h!r},{j * h!r},0.")
    for (i, j), g in gb.items():
        lines.append(f"GRID,{g},,{(i + 1) * h!r},{j * h!r},{GAP!r}")
    eid = 1
    for g, pid in ((ga, 1), (gb, 2)):
        for j in range(2):
            for i in range(3):
                lines.append(f"CQUAD4,{eid},{pid},{g[i, j]},{g[i + 1, j]},{g[i + 1, j + 1]},{g[i, j + 1]}")
                eid += 1
    path = tmp_path / "overhang.bdf"
    path.write_text("\n".join(lines + ["ENDDATA"]) + "\n")
    facing = {(min(ga[i + 1, j], gb[i, j]), max(ga[i + 1, j], gb[i, j])) for i in range(3) for j in range(3)}
    got = set().union(*(_contact_pairs(c) for c in generate_candidates(read_bdf(path), families=["contact_spring"])))
    assert got == facing


@pytest.mark.parametrize("dx, comps", [(0.0003, {(3, 3)}), (0.001, {(1, 1), (2, 2), (3, 3)})])
def test_contact_spring_components_follow_the_gap_direction(tmp_path, dx, comps):
    # gap (dx, 0, 2 mm): 8.5 deg off z -> z only; 26.6 deg (> contact_axis_deg = 20) -> x, y and z
    path, expected, _ = gap_deck(tmp_path / "gap.bdf", dx=dx)
    (c,) = _plain(generate_candidates(read_bdf(path), families=["contact_spring"]))
    assert _contact_pairs(c) == {(min(a, b), max(a, b)) for a, b in expected}
    assert {(d[1], d[3]) for d in c.term.dofs} == comps
    assert len(c.term.dofs) == len(expected) * len(comps)


def test_gap_deck_contact_distance_cap_and_patches(tmp_path):
    path, expected, _ = gap_deck(tmp_path / "gap.bdf")
    fe = read_bdf(path)
    assert generate_candidates(fe, families=["contact_spring"],
                               options=CandidateOptions(contact_max_gap_m=0.0019)) == ()
    plain = lambda **kw: _plain(generate_candidates(fe, families=["contact_spring"], **kw))  # noqa: E731
    # patches of at most one element size: the five pairs split, each pair in exactly one patch
    small = plain(options=CandidateOptions(contact_patch=1.0))
    patches = [c for c in small if not c.name.endswith(("_all", "_join1")) and "_w" not in c.name]
    assert len(patches) > 1
    pairs = [p for c in patches for p in _contact_pairs(c)]
    assert len(pairs) == len(set(pairs)) == len(expected)
    # and the whole gap once more as one term (its patches are one connected stretch): one common rate on
    # every pair, so a gap closed over its whole length is one effect
    (union,) = [c for c in small if c not in patches and "_w" not in c.name]
    assert union.name.endswith("_join1") and _contact_pairs(union) == set(pairs)
    assert union.term.scale == pytest.approx(plain()[0].term.scale)
    # windows of the patch size centred on each pair: more than one pair (here, one element size, none),
    # never a cell again, all distinct
    windows = [_contact_pairs(c) for c in small if "_w" in c.name]
    assert all(len(w) > 1 for w in windows)
    assert len({frozenset(w) for w in windows} | {frozenset(_contact_pairs(c)) for c in patches}) == \
        len(windows) + len(patches)
    # one-hop exclusion only: the same pairs (none of them shares a neighbour grid across the plates)
    one = plain(options=CandidateOptions(contact_hops=1))
    assert _contact_pairs(one[0]) == _contact_pairs(plain()[0])


@pytest.mark.parametrize("which", ["frame", "shell"])
def test_contact_springs_never_join_grids_an_element_already_joins(which, frame_pm, shell_pm, tmp_path):
    pm = frame_pm if which == "frame" else shell_pm
    cands = generate_candidates(pm, families=["contact_spring"])
    sets = _element_sets(pm.assembly.model)
    for c in cands:
        for a, b in _contact_pairs(c):
            assert not any(a in s and b in s for s in sets), (c.name, a, b)
    # the frame's members meet at shared grids: nothing faces anything within the contact distance
    if which == "frame":
        assert cands == ()


def test_clusters_partition_each_property_group(shell_pm, frame_pm):
    for pm in (shell_pm, frame_pm):
        ctx = candidate_context(pm)
        cands = generate_candidates(pm, families=["element_cluster"], options=CandidateOptions(cluster_radii=()))
        by_part: dict = {}
        for c in cands:
            assert len(c.parts) == 1 and c.term.kind == "K"
            by_part.setdefault(c.parts[0], []).append(set(c.term.elements))
        for part, sets in by_part.items():
            union = set().union(*sets)
            assert sum(len(s) for s in sets) == len(union)  # disjoint
            want = set(ctx.element_ids[ctx.factorable & (ctx.element_parts == part)].tolist())
            assert union == want  # cover
        assert set(by_part) == set(ctx.element_parts[ctx.factorable].tolist())
        # a cluster spans about cluster_size element sizes: no element centre farther than sqrt(3) * 3 sizes
        for c in cands:
            rows = np.flatnonzero(np.isin(ctx.element_ids, c.term.elements))
            span = np.ptp(ctx.element_centers[rows], axis=0)
            assert np.all(span <= 3.0 * np.median(ctx.element_sizes[rows]) * 1.5 + 1e-12)


def test_element_centred_clusters_match_a_region_the_cubes_split(frame_pm):
    """The frame's standard cluster (frfcal.effects: 5 bars within 2 element sizes of element 9) falls on three
    cubes of the tiling; the element-centred balls (default radii 1 and 2 element sizes) offer it whole."""
    ctx = candidate_context(frame_pm)
    truth = {7, 8, 9, 10, 11}
    cubes = generate_candidates(frame_pm, families=["element_cluster"], options=CandidateOptions(cluster_radii=()))
    split = [set(c.term.elements) & truth for c in cubes if set(c.term.elements) & truth]
    assert len(split) == 3 and max(len(s) for s in split) == 2
    cands = generate_candidates(frame_pm, families=["element_cluster"])
    sets = [frozenset(c.term.elements) for c in cands]
    assert len(set(sets)) == len(sets)  # no element set offered twice
    assert {frozenset(s) for s in ({8, 9, 10}, truth)} <= set(sets)  # radius 1 and 2 around element 9
    ball = next(c for c in cands if set(c.term.elements) == truth)
    assert ball.term.name == "cluster_PBAR1_e9_r2_K" and "within 0.2 of element 9" in ball.description
    assert np.allclose(ball.center, [0.85, -0.4, 0.0]) and ball.size == pytest.approx(0.1)
    for c in cands:  # every ball lies within its radius of its seed, in one property group
        rows = np.flatnonzero(np.isin(ctx.element_ids, c.term.elements))
        assert len(c.parts) == 1 and set(ctx.element_parts[rows].tolist()) == set(c.parts)
    # the seeds are capped per group and radius
    few = generate_candidates(frame_pm, families=["element_cluster"], options=CandidateOptions(cluster_seeds=2))
    assert len(cubes) < len(few) <= len(cubes) + 3 * 2 * 2


def test_cluster_mass_kind_and_bounds_by_option(frame_pm):
    opts = CandidateOptions(cluster_kinds=("K", "M"), factor_bounds=(-0.5, 2.0))
    cands = generate_candidates(frame_pm, families=["element_cluster"], options=opts)
    kinds = Counter(c.term.kind for c in cands)
    assert kinds["K"] == kinds["M"] > 0
    assert all((c.term.lower, c.term.upper) == (-0.5, 2.0) for c in cands)


def test_setup_families_at_the_given_grids(frame_pm):
    sensors, drives = _setup(frame_pm)
    cands = generate_candidates(frame_pm, sensors=sensors + [sensors[0]], drives=drives)
    fam = {f: [c for c in cands if c.family == f] for f in CANDIDATE_FAMILIES}
    total = candidate_context(frame_pm).total_mass
    assert total == pytest.approx(131.28608, rel=1e-6)  # FrameExample.mass_kg
    (common,) = fam["sensor_mass"]
    assert common.term.grids == tuple(sensors) and common.term.scale == pytest.approx(1e-3 * total)
    # the drive grid's mass is the shaker attachment's, not offered twice
    assert [c.term.grids for c in fam["sensor_masses"]] == [(g,) for g in sensors if g != drives[0][0]]
    (shaker,) = fam["shaker_attachment_mass"]
    assert shaker.term.grids == (drives[0][0],)
    (stinger,) = fam["stinger_spring"]
    # drive direction (0.1, 0.2, -1): dominant axis z, grounded spring, p = 1 bounces the frame at 10 Hz
    assert stinger.term.dofs == ((drives[0][0], 3, 0, 0),)
    assert stinger.term.scale == pytest.approx(total * (2 * np.pi * 10.0) ** 2)
    assert all(c.term.grids[0] not in sensors for c in fam["lumped_mass"])
    # a small model (82 grids): every grid but the sensors' gets a mass, every grid three ground springs
    n_grids = len(fe_grids := {int(g) for g in frame_pm.assembly.model.grid_ids})
    assert len(fam["lumped_mass"]) == len(fe_grids - set(sensors)) and len(fam["ground_spring"]) == 3 * n_grids
    # the spread reaches the frame's extremes: x range of the ground-spring grids = the deck's
    fe = frame_pm.assembly.model
    gx = np.array([c.center[0] for c in fam["ground_spring"]])
    assert gx.min() == pytest.approx(fe.xyz[:, 0].min()) and gx.max() == pytest.approx(fe.xyz[:, 0].max())
    for c in cands:
        if c.term.absolute:  # added springs and masses: [0, 100]; element factors keep factor_bounds
            assert (c.term.lower, c.term.upper) == (0.0, 100.0)
        back = json.loads(json.dumps(c.to_dict()))
        assert back["name"] == c.name and back["family"] == c.family and back["grids"] == list(c.grids)


@pytest.mark.parametrize("which", ["frame", "shell"])
def test_every_candidate_builds_and_its_derivative_is_the_with_terms_one(which, frame_pm, shell_pm):
    pm = frame_pm if which == "frame" else shell_pm
    sensors, drives = _setup(pm)
    cands = generate_candidates(pm, sensors=sensors, drives=drives,
                                options=CandidateOptions(spread_grids=8, max_per_family=25))
    assert len({c.name for c in cands}) == len(cands)
    rng = np.random.default_rng(3)
    p = rng.uniform(-0.1, 0.1, pm.n_params)
    for c in cands:
        d = pm.term_derivative(c.term, p)
        ext = pm.with_terms([c.term])
        q = np.r_[p, 0.0]
        for kind, fn in (("K", ext.dK), ("M", ext.dM)):
            ref = fn(q, pm.n_params)
            if d[kind] is None:
                assert abs(ref).max() == 0.0, (c.name, kind)
            else:
                assert d[kind].shape == ref.shape
                assert abs(ref - d[kind]).max() <= 1e-14 * abs(ref).max(), (c.name, kind)
        # an element factor's derivative at p is its elements' matrices at p: K(p) changes by it
        if hasattr(c.term, "kind"):
            assert d["K" if c.term.kind == "M" else "M"] is None


def _model_and_setup(which, frame_pm, shell_pm, tmp_path):
    """(parametric model, sensors, drives): the frame, the shell, or a deck with bars, rods, cylindrical
    displacement systems and SPC'd grids."""
    if which == "generic":
        path = frame_deck(tmp_path / "all.bdf", cd_cyl=True, spc=True)
        pm = parametric_model(ParameterSet((Parameter("E1", "MAT1", (1,), "E", -0.2, 0.2),)), path)
        return pm, [1, 9, 13], [(13, (1.0, 0.0, 0.0))]
    pm = frame_pm if which == "frame" else shell_pm
    return (pm, *_setup(pm))


@pytest.mark.parametrize("which", ["frame", "shell", "generic"])
def test_term_derivatives_batch_equals_one_by_one(which, frame_pm, shell_pm, tmp_path):
    """The batched derivatives (element subsets of one kind in one assembly pass, each on its own copy of its
    grids) are the one-by-one ones entry for entry: stiffness and mass clusters, cylindrical displacement
    systems, bars and rods, and every other family through the one-by-one path, in order."""
    pm, sensors, drives = _model_and_setup(which, frame_pm, shell_pm, tmp_path)
    opts = CandidateOptions(spread_grids=8, max_per_family=80, cluster_kinds=("K", "M"))
    terms = [c.term for c in generate_candidates(pm, sensors=sensors, drives=drives, options=opts)]
    assert sum(hasattr(t, "kind") for t in terms) >= 4
    p = np.random.default_rng(5).uniform(-0.1, 0.1, pm.n_params)
    batch = pm.term_derivatives(terms, p)
    assert len(batch) == len(terms)
    for t, d in zip(terms, batch):
        ref = pm.term_derivative(t, p)
        for kind in ("K", "M"):
            if ref[kind] is None:
                assert d[kind] is None, (t.name, kind)
            else:
                assert d[kind].shape == ref[kind].shape and d[kind].format == "csr"
                assert abs(d[kind] - ref[kind]).max() <= 1e-14 * abs(ref[kind]).max(), (t.name, kind)


@pytest.mark.parametrize("which", ["frame", "shell", "generic"])
def test_spring_and_mass_terms_map_to_the_aset_as_the_reduction_does(which, frame_pm, shell_pm, tmp_path):
    """Added springs and masses go to the a-set entry by entry (no g-set-sized matrix): bit for bit the
    matrices the reduction by T gives (constrained grids, cylindrical displacement systems included)."""
    import scipy.sparse as sp

    from femodel._pattern import _canonical, _to_aset

    pm, sensors, drives = _model_and_setup(which, frame_pm, shell_pm, tmp_path)
    cands = [c for c in generate_candidates(pm, sensors=sensors, drives=drives,
                                            options=CandidateOptions(spread_grids=8, max_per_family=40))
             if not hasattr(c.term, "kind")]
    assert len({c.family for c in cands}) >= 4
    asm, amap = pm.assembly, pm._amap()
    for c in cands:
        for kind, d in pm._term_parts(c.term, "test").items():
            m = d[0][0]
            ref = _to_aset(asm, amap, _canonical(c.term.g_matrices(asm.model)[kind]), drop_zeros=True)
            ref.eliminate_zeros()
            ref = _canonical(ref)
            assert sp.isspmatrix_csr(m) and m.shape == ref.shape, c.name
            for a in ("indptr", "indices", "data"):
                np.testing.assert_array_equal(getattr(m, a), getattr(ref, a), err_msg=f"{c.name} {a}")


def test_compound_effects_join_the_member_families_at_the_same_grids(frame_pm):
    """A shaker attachment is one effect with two terms: its mass and its stinger spring at the drive grid;
    one compound per drive grid, only complete sets."""
    from femodel import COMPOUND_EFFECTS, compound_candidates

    sensors, drives = _setup(frame_pm)
    g2 = sensors[3]
    cands = generate_candidates(frame_pm, sensors=sensors, drives=drives + [(g2, (0.0, 1.0, 0.0))])
    comps = compound_candidates(cands)
    assert COMPOUND_EFFECTS["shaker_attachment"] == ("shaker_attachment_mass", "stinger_spring")
    assert sorted(n for n, _ in comps) == sorted(f"shaker_attachment_g{g}" for g in (drives[0][0], g2))
    for name, (mass, spring) in comps:
        assert mass.family == "shaker_attachment_mass" and spring.family == "stinger_spring"
        assert mass.grids == spring.grids and name.endswith(f"_g{mass.grids[0]}")
    # without the stinger family nothing is compound
    assert compound_candidates([c for c in cands if c.family != "stinger_spring"]) == []


def test_term_derivative_of_element_factor_scales_with_the_deck_parameters(frame_pm):
    c = generate_candidates(frame_pm, families=["element_cluster"])[0]
    p0 = np.zeros(frame_pm.n_params)
    d0 = frame_pm.term_derivative(c.term, p0)["K"]
    # the factor's K is linear in E of its material: dK/dp_factor at E (1 + 0.2) is 1.2 times the nominal one
    names = frame_pm.names
    j = [i for i, n in enumerate(names) if n.startswith("E_")]
    p1 = p0.copy()
    p1[j] = 0.2
    d1 = frame_pm.term_derivative(c.term, p1)["K"]
    assert abs(d1 - 1.2 * d0).max() <= 1e-12 * abs(d0).max()


def test_generic_deck_with_every_card_and_cylindrical_displacement_systems(tmp_path):
    path = frame_deck(tmp_path / "all.bdf", cd_cyl=True, spc=True)
    fe = read_bdf(path)
    params = ParameterSet((Parameter("E1", "MAT1", (1,), "E", -0.2, 0.2),))
    pm = parametric_model(params, path)
    cands = generate_candidates(pm, sensors=[1, 9, 13], drives=[(13, (1.0, 0.0, 0.0))],
                                options=CandidateOptions(spread_grids=6))
    fams = Counter(c.family for c in cands)
    # grid 1 is clamped: no sensor mass there; grid 13 is the drive: its mass is the shaker attachment's
    assert fams["sensor_masses"] == 1 and fams["stinger_spring"] == 1 and fams["element_cluster"] > 0
    # CONROD, CELAS, CBUSH, CONM2 are never in an element factor; the CBEAM's PBEAML is (since stop 34)
    ctx = candidate_context(pm)
    clustered = {e for c in cands if c.family == "element_cluster" for e in c.term.elements}
    cards = dict(zip(ctx.element_ids.tolist(), ctx.element_cards.tolist()))
    assert "CBEAM" in {cards[e] for e in clustered} <= {"CBAR", "CROD", "CBEAM"}
    p = np.zeros(pm.n_params)
    for c in cands:
        pm.with_terms([c.term])  # builds: no constrained-only term, no unknown grid
        pm.term_derivative(c.term, p)
    # grids 1 and 2 are clamped: no ground spring or lumped mass there
    assert not {g for c in cands if c.family in ("ground_spring", "lumped_mass") for g in c.grids} & {1, 2}
    assert fe.n_grids == 14


def test_counts_on_the_5k_shell(tmp_path):
    ex = example_subframe(tmp_path, target_dof=5000)
    pm = parametric_model(ex.params)
    sensors, drives = _setup(pm, n_sensors=24)
    cands = generate_candidates(pm, sensors=sensors, drives=drives)
    fams = Counter(c.family for c in cands)
    assert 200 <= len(cands) <= 2000
    assert fams["element_cluster"] >= 100 and fams["sensor_masses"] == 23 and fams["ground_spring"] == 120
    ctx = candidate_context(pm)
    # cubes of three element sizes: about (group extent / 3 h) cells per group, far fewer than elements;
    # element-centred balls at most cluster_seeds per group and radius
    n_fac = int(ctx.factorable.sum())
    n_cubes = len(generate_candidates(pm, families=["element_cluster"], options=CandidateOptions(cluster_radii=())))
    assert n_cubes < n_fac / 3
    n_parts = len(set(ctx.element_parts[ctx.factorable].tolist()))
    assert fams["element_cluster"] <= min(n_cubes + n_parts * 60 * 2, 500)
    # the cap spreads evenly and deterministically
    capped = generate_candidates(pm, sensors=sensors, drives=drives, options=CandidateOptions(max_per_family=30))
    assert max(Counter(c.family for c in capped).values()) == 30
    again = generate_candidates(pm, sensors=sensors, drives=drives, options=CandidateOptions(max_per_family=30))
    assert [c.name for c in capped] == [c.name for c in again]


def test_registry_user_family_and_errors(frame_pm, monkeypatch):
    monkeypatch.setattr("femodel._candidates.CANDIDATE_FAMILIES", dict(CANDIDATE_FAMILIES))
    from femodel import _candidates

    def heavy_corner(ctx):
        """A 1 kg-per-unit-p mass at the grid with the largest x."""
        r = int(np.argmax(ctx.xyz[:, 0]))
        g = int(ctx.grid_ids[r])
        yield ctx.candidate("heavy_corner", AddedMass("corner_mass", (g,), 1.0), (g,), f"mass at {ctx.grid_label(g)}")

    register_family("heavy_corner", heavy_corner)
    assert "heavy_corner" in _candidates.CANDIDATE_FAMILIES
    (c,) = generate_candidates(frame_pm, families=["heavy_corner"])
    assert c.family == "heavy_corner" and c.center[0] == pytest.approx(frame_pm.assembly.model.xyz[:, 0].max())
    frame_pm.with_terms([c.term])
    with pytest.raises(ParameterError, match="already registered"):
        register_family("heavy_corner", heavy_corner)
    register_family("heavy_corner", heavy_corner, replace=True)
    with pytest.raises(ParameterError, match="must match"):
        register_family("Bad Name", heavy_corner)
    with pytest.raises(ParameterError, match="callable"):
        register_family("notcallable", 3)
    with pytest.raises(ParameterError, match=r"unknown candidate families \['nope'\].*contact_spring"):
        generate_candidates(frame_pm, families=["nope"])

    def wrong(ctx):
        yield from heavy_corner(ctx)

    register_family("wrong", wrong)
    with pytest.raises(ParameterError, match="not a Candidate of family 'wrong'"):
        generate_candidates(frame_pm, families=["wrong"])

    def clash(ctx):
        g = int(ctx.grid_ids[0])
        yield ctx.candidate("clash", AddedMass(frame_pm.names[0], (g,), 1.0), (g,), "clash")

    register_family("clash", clash)
    with pytest.raises(ParameterError, match="already used"):
        generate_candidates(frame_pm, families=["clash"])


@pytest.mark.parametrize("kwargs, field", [
    (dict(contact_factor=-1.0), "contact_factor"),
    (dict(contact_max_gap_m=float("nan")), "contact_max_gap_m"),
    (dict(contact_hops=0), "contact_hops"),
    (dict(contact_axis_deg=90.0), "contact_axis_deg"),
    (dict(cluster_kinds=("K", "X")), "cluster_kinds"),
    (dict(cluster_radii=(1.0, -2.0)), "cluster_radii"),
    (dict(cluster_seeds=0), "cluster_seeds"),
    (dict(factor_bounds=(0.1, 2.0)), "factor_bounds"),
    (dict(ground_components=(4,)), "ground_components"),
    (dict(spread_grids=2.5), "spread_grids"),
    (dict(max_per_family=0), "max_per_family"),
    (dict(zoom_rounds=-1), "zoom_rounds"),
    (dict(zoom_top=0), "zoom_top"),
    (dict(zoom_grids=1.5), "zoom_grids"),
    (dict(f_ref_hz=True), "f_ref_hz"),
])
def test_options_validated_with_the_field_named(kwargs, field):
    with pytest.raises(ParameterError, match=f"CandidateOptions.{field}"):
        CandidateOptions(**kwargs)


def test_candidate_checks_its_fields():
    from femodel import Candidate

    term = AddedMass("m1", (1,), 1.0)
    c = Candidate("lumped_mass", term, [np.int64(1)], ["PBAR 1"], np.array([0.0, 1.0, 2.0]), 0.1, "mass")
    assert c.grids == (1,) and c.center == (0.0, 1.0, 2.0) and c.parts == ("PBAR 1",)
    with pytest.raises(ParameterError, match="term must be"):
        Candidate("lumped_mass", "m1", (1,), (), (0, 0, 0), 0.1, "mass")
    with pytest.raises(ParameterError, match="center"):
        Candidate("lumped_mass", term, (1,), (), (0, 0), 0.1, "mass")


def test_setup_errors_name_the_grid(frame_pm):
    with pytest.raises(ParameterError, match=r"sensor grid \[99999\]"):
        generate_candidates(frame_pm, sensors=[1, 99999])
    with pytest.raises(ParameterError, match="drive grid"):
        generate_candidates(frame_pm, drives=[(99998, (0, 0, 1))])
    with pytest.raises(ParameterError, match="non-zero"):
        generate_candidates(frame_pm, drives=[(1, (0, 0, 0))])
    with pytest.raises(ParameterError, match="FEModel or a ParametricModel"):
        generate_candidates("frame.bdf")


def test_lumped_masses_also_far_from_every_sensor_and_drive(frame_pm):
    """Besides the spread grids, spread_grids // 4 grids spread away from the measured grids: the first is the
    grid farthest from every sensor and drive (where an unmeasured mass hides; frfcal.effects puts its
    lumped mass there)."""
    sensors, drives = _setup(frame_pm)
    ctx = candidate_context(frame_pm, sensors=sensors, drives=drives)
    opts = CandidateOptions(spread_grids=4)
    got = generate_candidates(frame_pm, sensors=sensors, drives=drives, families=["lumped_mass"], options=opts)
    rows = np.flatnonzero(np.array([bool(p) for p in ctx.grid_parts]))
    rows = rows[np.any(ctx.free[rows, :3], axis=1) & ~np.isin(ctx.grid_ids[rows], sensors)]
    measured = ctx.xyz[ctx.grid_index(list(sensors) + [g for g, _ in drives])]
    far = np.min(np.linalg.norm(ctx.xyz[rows][:, None] - measured[None], axis=2), axis=1)
    farthest = int(ctx.grid_ids[rows[np.argmax(far)]])
    grids = [c.grids[0] for c in got]
    assert farthest in grids and not set(grids) & set(sensors)
    plain = generate_candidates(frame_pm, families=["lumped_mass"], options=opts)  # no set-up: spread only
    assert len(plain) == 4 and 4 < len(got) <= 5
    # away_from: the farthest point from the given ones comes first, then farthest from those and it
    pts = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0], [10, 0, 0]])
    assert ctx.spread(pts, 1, away_from=[[0.0, 0, 0]]).tolist() == [4]
    assert ctx.spread(pts, 2, away_from=[[0.0, 0, 0]]).tolist() == [3, 4]  # 3 is 3 from 0 and 7 from 10


def test_a_small_model_has_its_point_families_at_every_grid(frame_pm):
    """spread_grids None (default): every eligible grid when the family's candidates at every grid fit
    max_per_family (an undeclared mass between spread grids is a candidate itself, not left to the zoom:
    outside data where the zoom missed it, docs/diagnosis.md); else the spread sample of SPREAD_GRIDS."""
    from femodel import point_coverage
    from femodel._candidates import SPREAD_GRIDS

    sensors, drives = _setup(frame_pm)
    ctx = candidate_context(frame_pm, sensors=sensors, drives=drives)
    assert ctx.options.spread_grids is None
    got = generate_candidates(frame_pm, families=["lumped_mass", "ground_spring"], context=ctx)
    cov = point_coverage(ctx, got)
    assert set(cov) == {("lumped_mass", None), ("ground_spring", 1), ("ground_spring", 2), ("ground_spring", 3)}
    assert all(n == n_all > SPREAD_GRIDS for n, n_all in cov.values()), cov
    n_mass = cov[("lumped_mass", None)][1]
    assert n_mass == len({int(g) for g in ctx.grid_ids[[bool(p) for p in ctx.grid_parts]]} - set(sensors))
    # the same model with a cap below the family's full count: the spread sample (plus the far grids for masses)
    small = CandidateOptions(max_per_family=n_mass - 1)
    got = generate_candidates(frame_pm, sensors=sensors, drives=drives, families=["lumped_mass", "ground_spring"],
                              options=small)
    ctx2 = candidate_context(frame_pm, sensors=sensors, drives=drives, options=small)
    cov = point_coverage(ctx2, got)
    assert SPREAD_GRIDS <= cov[("lumped_mass", None)][0] <= SPREAD_GRIDS + SPREAD_GRIDS // 4 < n_mass
    # (the 3 x 40 ground springs then go through the family cap too)
    assert sum(cov[("ground_spring", c)][0] for c in (1, 2, 3)) == n_mass - 1
    # an explicit spread_grids is kept as given
    got = generate_candidates(frame_pm, families=["lumped_mass"], options=CandidateOptions(spread_grids=7))
    assert len(got) == 7


def test_spread_never_repeats_a_point_when_points_coincide(frame_pm):
    # ground springs give three candidates (x, y, z) per grid at one centre, and two parts' grids can
    # coincide (a bolted plate over a frame): once every distinct place is taken the distances left are
    # all 0, and the spread took index 0 again ("term name 'ground_g10000_x' is already used")
    ctx = candidate_context(frame_pm)
    pts = np.repeat(np.array([[0.0, 0, 0], [1, 0, 0], [5, 0, 0]]), 3, axis=0)
    got = ctx.spread(pts, 7)
    assert len(set(got.tolist())) == 7
    assert sorted({tuple(pts[i]) for i in got}) == [(0.0, 0, 0), (1, 0, 0), (5, 0, 0)]  # every place first
    assert len(set(ctx.spread(pts, 5, away_from=[[5.0, 0, 0]]).tolist())) == 5
    n = len(generate_candidates(frame_pm, families=["ground_spring"], options=CandidateOptions(spread_grids=1000)))
    capped = generate_candidates(frame_pm, families=["ground_spring"],
                                 options=CandidateOptions(spread_grids=1000, max_per_family=n - 1))
    assert len({c.term.name for c in capped}) == n - 1


def test_a_gap_facing_a_welded_corner_is_one_contact_candidate(tmp_path):
    # the subframe's doubler faces rail grids that are web/skin junctions: a junction grid may face a third part
    ex = example_subframe(tmp_path, target_dof=1500, gap_mm=2.0)
    cands = generate_candidates(parametric_model(ex.params), families=["contact_spring"])
    gap = {(min(a, b), max(a, b)) for a, b in ex.gap_pairs}
    whole = [c for c in cands if _contact_pairs(c) == gap]
    assert len(whole) == 1 and "PSHELL 21" in whole[0].parts
    assert all(_contact_pairs(c) <= gap for c in cands)  # nothing else faces anything in this deck
    plain = example_subframe(tmp_path / "plain", target_dof=1500)
    assert generate_candidates(parametric_model(plain.params), families=["contact_spring"]) == ()


def _grid_xyz(ctx, grids):
    return ctx.xyz[ctx.grid_index(list(grids))]


@pytest.mark.parametrize("family", ["lumped_mass", "ground_spring"])
def test_zoom_offers_the_family_at_the_untested_grids_nearest_the_best(frame_pm, family):
    """The zoom's neighbourhood of a point candidate: the grids, eligible for its family and kind, whose nearest
    screened grid is the candidate's (its Voronoi cell among the screened grids), none screened; spread over
    the cell when it holds more than ``n``; repeated around a new best it reaches every grid of the family."""
    sensors, drives = _setup(frame_pm)
    ctx = candidate_context(frame_pm, sensors=sensors, drives=drives, options=CandidateOptions(spread_grids=6))
    screened = [c for c in generate_candidates(frame_pm, families=[family], context=ctx)]
    if family == "ground_spring":
        screened_kind = [c for c in screened if c.term.dofs[0][1] == 3]
    else:
        screened_kind = screened
    best = screened_kind[len(screened_kind) // 2]
    new = zoom_candidates(ctx, screened, best, n=1000)
    assert new and all(c.family == family and len(c.grids) == 1 for c in new)
    if family == "ground_spring":  # the same component as the best: z
        assert all(c.term.dofs == ((c.grids[0], 3, 0, 0),) for c in new)
    tested = {c.grids[0] for c in screened_kind}
    got = {c.grids[0] for c in new}
    assert not got & tested
    # exactly the cell: every eligible untested grid nearer best than any other screened grid
    every = {c.grids[0] for c in generate_candidates(
        frame_pm, families=[family], context=candidate_context(
            frame_pm, sensors=sensors, drives=drives, options=CandidateOptions(spread_grids=10_000)))
        if family == "lumped_mass" or c.term.dofs[0][1] == 3}
    untested = sorted(every - tested)
    d_best = np.linalg.norm(_grid_xyz(ctx, untested) - _grid_xyz(ctx, best.grids), axis=1)
    d_near = np.min(np.linalg.norm(_grid_xyz(ctx, untested)[:, None] - _grid_xyz(ctx, sorted(tested))[None], axis=2),
                    axis=1)
    assert got == {g for g, a, b in zip(untested, d_best, d_near) if a <= b * (1 + 1e-9)}
    # at most n, spread over the cell: the farthest cell grid from the best comes first
    few = zoom_candidates(ctx, screened, best, n=2)
    far = max(got, key=lambda g: np.linalg.norm(_grid_xyz(ctx, [g]) - _grid_xyz(ctx, best.grids)))
    assert len(few) == 2 and far in {c.grids[0] for c in few}
    # candidates are the family's own (the same terms as generated), so the names never clash
    assert all(c.name.startswith("mass_g" if family == "lumped_mass" else "ground_g") for c in new)
    # zooming around whatever is best next, the family's every grid of the kind is reached
    seen = list(screened)
    for _ in range(200):
        nxt = [c for b in list(seen) if b.family == family and (family == "lumped_mass" or b.term.dofs[0][1] == 3)
               for c in zoom_candidates(ctx, seen, b, n=3)]
        if not nxt:
            break
        seen += list({c.name: c for c in nxt}.values())
    assert {c.grids[0] for c in seen if family == "lumped_mass" or c.term.dofs[0][1] == 3} == every


def test_zoom_errors_and_user_point_family(frame_pm, monkeypatch):
    monkeypatch.setattr("femodel._candidates.CANDIDATE_FAMILIES", dict(CANDIDATE_FAMILIES))
    monkeypatch.setattr("femodel._candidates.POINT_FAMILIES", dict(POINT_FAMILIES))
    from femodel import PointFamily, _candidates

    ctx = candidate_context(frame_pm, options=CandidateOptions(spread_grids=4))
    cluster = generate_candidates(frame_pm, families=["element_cluster"], context=ctx)[0]
    with pytest.raises(ParameterError, match="not a point family"):
        zoom_candidates(ctx, [], cluster)

    def clamp_at(ctx, like, row):
        g = int(ctx.grid_ids[row])
        return ctx.candidate("clamp", AddedMass(f"clamp_g{g}", (g,), 0.5), (g,), f"clamp at {ctx.grid_label(g)}")

    def clamps(ctx):
        rows = np.flatnonzero(ctx.xyz[:, 0] > np.median(ctx.xyz[:, 0]))
        yield from (clamp_at(ctx, None, r) for r in rows[ctx.spread(ctx.xyz[rows], 3)])

    with pytest.raises(ParameterError, match="PointFamily"):
        register_family("clamp", clamps, point=clamp_at)
    register_family("clamp", clamps, point=PointFamily(
        rows=lambda ctx, like: np.flatnonzero(ctx.xyz[:, 0] > np.median(ctx.xyz[:, 0])), at=clamp_at))
    assert "clamp" in _candidates.POINT_FAMILIES
    first = generate_candidates(frame_pm, families=["clamp"], context=ctx)
    assert len(first) == 3
    new = zoom_candidates(ctx, first, first[0])
    assert new and all(c.family == "clamp" for c in new) and not {c.name for c in new} & {c.name for c in first}
    register_family("clamp", clamps, replace=True)  # replaced without point: no longer zoomed
    assert "clamp" not in _candidates.POINT_FAMILIES
    with pytest.raises(ParameterError, match="not beside context"):
        generate_candidates(frame_pm, families=["clamp"], context=ctx, options=CandidateOptions())


def test_a_contact_straddling_two_cells_has_a_window_of_its_own(tmp_path):
    # The second outside case (tests/frfcal/outside2_case.py): the rail flange lies 4 mm over the panel on
    # x = 350-600 mm (12 facing pairs in two rows); its gap closes on x = 450-600 (8 pairs). The cells of
    # 4 element sizes are tiled from x = 350: 350-550 and 550-600, so before the windows the closed part had
    # no candidate (the union of all 12 was accepted and left the hold-out SD 11x the floor).
    from tests.frfcal import outside2_case as oc

    path = tmp_path / "floor.bdf"
    path.write_text(oc.deck_text(oc.NOMINAL))
    cands = generate_candidates(read_bdf(path, units="mm-t-s"), families=["contact_spring"])
    closed = {(oc.rail_grid(1, i, k), oc.panel_grid(i, 3 + k)) for i in range(9, oc.NX + 1) for k in range(2)}
    closed = {(min(a, b), max(a, b)) for a, b in closed}
    sets = {c.name: _contact_pairs(c) for c in cands}
    assert [n for n, s in sets.items() if s == closed] == ["contact_PSHELL1_PSHELL2_w4"]
    assert all(len(s) <= 12 for s in sets.values()) and len(sets) == len({frozenset(s) for s in sets.values()})
    # one region (the part pair): the screening gives it one check slot; around the window: the union of the
    # stretch (all 12 pairs) and a wider window (10), which the screening checks with it (screen(regions=...))
    regions = candidate_regions(cands)
    assert len({r[0] for r in regions}) == 1 and regions[0][0] == ("contact_spring", ("PSHELL 1", "PSHELL 2"))
    places = {c.name: r[1] for c, r in zip(cands, regions)}
    assert all(places[c.name] == frozenset(c.grids) for c in cands)
    w4 = places["contact_PSHELL1_PSHELL2_w4"]
    around = [n for n, g in places.items() if w4 < g]
    assert sorted(around) == ["contact_PSHELL1_PSHELL2_join1", "contact_PSHELL1_PSHELL2_w3"]
    assert all(sets[n] > closed for n in around) and len(sets["contact_PSHELL1_PSHELL2_join1"]) == 12


def test_a_contact_on_chosen_pairs_of_a_candidate(tmp_path):
    # the acceptance's per-pair fit (frfcal/campaign/_diagnose.py _contact_shape) makes one spring term per
    # pair of a contact candidate and then one candidate on the pairs that carry the contact
    from femodel import candidate_pairs, contact_on_pairs
    from tests.frfcal import outside2_case as oc

    path = tmp_path / "floor.bdf"
    path.write_text(oc.deck_text(oc.NOMINAL))
    fe = read_bdf(path, units="mm-t-s")
    ctx = candidate_context(fe)
    cands = generate_candidates(fe, families=["contact_spring"], context=ctx)
    (union,) = [c for c in cands if c.name == "contact_PSHELL1_PSHELL2_join1"]
    pairs = candidate_pairs(union)
    assert len(pairs) == 12 and {(min(a, b), max(a, b)) for a, b in pairs} == _contact_pairs(union)
    one = contact_on_pairs(ctx, union, [pairs[4]], "one_pair")
    assert candidate_pairs(one) == (pairs[4],) and one.parts == union.parts and one.family == "contact_spring"
    assert one.term.dofs == tuple(d for d in union.term.dofs if (d[0], d[2]) == pairs[4])
    some = contact_on_pairs(ctx, union, pairs[2:7], "five_pairs")
    assert candidate_pairs(some) == pairs[2:7] and "5 grid pairs" in some.description
    # the scale is the family's rule on these pairs: a fraction of the median stiffness of the sprung DOF
    kd = [min(ctx.stiffness_diagonal[fe.grid_index([a])[0], c - 1],
              ctx.stiffness_diagonal[fe.grid_index([b])[0], c - 1]) for a, c, b, _ in some.term.dofs]
    assert some.term.scale == pytest.approx(ctx.options.contact_fraction * np.median(kd), rel=1e-12)
    with pytest.raises(ParameterError, match="no grid pairs"):
        contact_on_pairs(ctx, union, [], "none")
    with pytest.raises(ParameterError, match="not contact_spring"):
        candidate_pairs(next(c for c in generate_candidates(fe, families=["lumped_mass"], context=ctx)))
