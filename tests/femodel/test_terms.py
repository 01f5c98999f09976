"""Added term families: exact coefficients and derivatives, write-back that re-reads to the same K and M."""

from __future__ import annotations

import re

import numpy as np
import pytest
import scipy.sparse as sp

import femodel
from femodel import (
    AddedMass,
    AddedSpring,
    ElementFactor,
    ExtendedAffineMatrix,
    Parameter,
    ParameterError,
    ParameterSet,
    example_subframe,
    fixed_field_card,
    parametric_model,
)


def frame_deck(path):
    """A free-free ladder frame of CBARs (two PBARs, two MAT1s) with a second part on six CELAS2 springs.

    Rail A: grids 1..7 along x at y = 0; rail B: 11..17 at y = 0.5; cross
    members at x = 0, 0.6, 1.2. Part 2: grids 21..24 at z = 0.3, aluminium,
    joined to grid 2 by CELAS2 101..106. A 0.5 kg CONM2 (200) at grid 7 and
    small CONM2s with rotary inertia at every grid (the bar mass has no
    rotary inertia; a definite M keeps dense reference solves possible). SI.
    """
    lines = ["SOL 103", "CEND", "BEGIN BULK", "PARAM,COUPMASS,1",
             "MAT1,1,2.1+11,,0.3,7850.", "MAT1,2,7.0+10,,0.33,2700.",
             "PBAR,1,1,4.4-4,1.0-7,1.2-7,1.6-7", "PBAR,2,2,2.0-4,2.0-8,2.5-8,3.0-8"]
    for i in range(7):
        lines.append(f"GRID,{1 + i},,{0.2 * i!r},0.,0.")
        lines.append(f"GRID,{11 + i},,{0.2 * i!r},0.5,0.")
    for i in range(4):
        lines.append(f"GRID,{21 + i},,{0.2 + 0.2 * i!r},0.,0.3")
    eid = 1
    for a, b in [(k, k + 1) for k in range(1, 7)] + [(k, k + 1) for k in range(11, 17)] + [(1, 11), (4, 14), (7, 17)]:
        lines.append(f"CBAR,{eid},1,{a},{b},0.,0.,1.")
        eid += 1
    for a in range(21, 24):
        lines.append(f"CBAR,{eid},2,{a},{a + 1},0.,0.,1.")
        eid += 1
    for c in range(1, 7):
        lines.append(f"CELAS2,{100 + c},{1.0e6 if c <= 3 else 1.0e4},21,{c},2,{c}")
    lines.append("CONM2,200,7,0,0.5")
    for k, g in enumerate(list(range(1, 8)) + list(range(11, 18)) + list(range(21, 25))):
        lines.append(f"CONM2,{300 + k},{g},0,0.01,,,,,+I{k}")
        lines.append(f"+I{k},1.-5,,1.-5,,,1.-5")
    lines.append("ENDDATA")
    path.write_text("\n".join(lines) + "\n")
    return path


FRAME_PARAMS = ParameterSet((
    Parameter("E", "MAT1", (1,), "E", -0.3, 0.3),
    Parameter("rho", "MAT1", (1,), "RHO", -0.3, 0.3),
    Parameter("m_tip", "CONM2", (200,), "M", -0.5, 0.5),
))

#: contact spring between the parts, sensor mass, spring to ground, stiffness factor on three rail-B bars
FRAME_TERMS = (
    AddedSpring("k_contact", ((24, 3, 5, 3),), 1e5),
    AddedMass("m_sensor", (16,), 0.1),
    AddedSpring("k_ground", ((1, 1, 0, 0), (1, 2, 0, 0), (1, 3, 0, 0)), 1e4),
    ElementFactor("f_railB", (7, 8, 9)),
)
FRAME_P = np.array([0.03, -0.02, 0.1, 0.8, 1.2, 0.6, -0.25])


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    d = tmp_path_factory.mktemp("frame")
    pm = parametric_model(FRAME_PARAMS, frame_deck(d / "frame.bdf"))
    return d, pm, pm.with_terms(FRAME_TERMS)


@pytest.fixture(scope="module")
def subframe(tmp_path_factory):
    d = tmp_path_factory.mktemp("subframe")
    ex = example_subframe(d, 4500)
    pm = parametric_model(ex.params)
    fe = pm.assembly.model
    quads = fe.elements["CQUAD4"]

    def grids_of(pid):
        return np.unique(quads["nodes"][quads["pid"] == pid])

    arm, bracket = grids_of(8), grids_of(4)  # arm RHS and bracket RHS: two parts of the frame
    ga, gb = int(arm[len(arm) // 2]), int(bracket[len(bracket) // 2])
    local = quads.ids[quads["pid"] == 3][:12]  # a local change in part of the webs' property group
    terms = (
        AddedSpring("k_contact", ((ga, 3, gb, 3), (ga, 2, gb, 2)), 1e5),
        AddedMass("m_sensor", (int(bracket[0]),), 0.05),
        AddedSpring("k_ground", ((int(fe.grid_ids[0]), 3, 0, 0),), 1e4),
        ElementFactor("f_web", tuple(int(e) for e in local)),
    )
    return d, pm, pm.with_terms(terms)


def _assert_same(A, B, what):
    A, B = sp.csr_matrix(A), sp.csr_matrix(B)
    scale = abs(B).max()
    diff = abs(A - B)
    assert diff.max() <= 1e-12 * scale, (what, diff.max() / scale)
    # entry by entry, each against its own size or, where terms cancel, sqrt(|B_ii B_jj|)
    d = (A - B).tocoo()
    diag = np.abs(B.diagonal())
    ref = np.maximum(np.abs(np.asarray(B[d.row, d.col]).ravel()), np.sqrt(diag[d.row] * diag[d.col]))
    assert np.all(np.abs(d.data) <= 1e-12 * ref), (what, np.max(np.abs(d.data) / np.maximum(ref, 1e-300)))


def _round_trip(tmp, pm, p, units):
    out = pm.write_bdf(tmp / "written.bdf", p)
    asm = femodel.assemble(femodel.read_bdf(out, units=units))
    assert asm.T.shape == pm.assembly.T.shape
    _assert_same(asm.stiffness(), pm.stiffness(p), "K")
    _assert_same(asm.mass(), pm.mass(p), "M")
    return out


def test_extended_affine_derivatives_match_finite_differences():
    rng = np.random.default_rng(0)
    mats = tuple((lambda m: (m + m.T).tocsr())(sp.random(6, 6, 0.5, random_state=k)) for k in range(4))
    a = np.array([[1, 0, 0], [3, 1, 0], [0, 0, 0], [1, 0, 0]], float)
    b = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 0], [1, 0, 0]], float)
    A = ExtendedAffineMatrix(mats, a, b, np.array([0.0, 0.7, 0.0, 0.0]), np.array([-1, -1, 2, 2]))
    p = np.array([0.1, -0.2, 0.4])
    c = A.coefficients(p)
    # term 1: shear-bending series; term 2: p_2 alone; term 3: p_2 (1 + p_0)
    u, v = (1.1**3) * 0.8, 0.8
    assert c[1] == pytest.approx(1.7 * u * v / (v + 0.7 * u), rel=1e-14)
    assert c[2] == 0.4 and c[3] == pytest.approx(0.4 * 1.1, rel=1e-15)
    J = A.coefficient_jacobian(p)
    h = 1e-6
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        fd = (A.coefficients(p + e) - A.coefficients(p - e)) / (2 * h)
        np.testing.assert_allclose(J[:, j], fd, rtol=1e-8, atol=1e-10)
    # projection keeps the coefficient rule
    T = rng.standard_normal((6, 2))
    R = A.projected(T)
    np.testing.assert_allclose(R.at(p), T.T @ A.at(p).toarray() @ T, rtol=1e-12, atol=1e-12)


def test_with_terms_leaves_the_model_and_extends_parameters(frame):
    _, pm, ext = frame
    assert pm.n_params == 3 and pm.terms == () and type(pm.K).__name__ != "ExtendedAffineMatrix"
    assert ext.n_params == 7 and ext.names[3:] == ("k_contact", "m_sensor", "k_ground", "f_railB")
    np.testing.assert_array_equal(ext.lower[3:], [0, 0, 0, -0.5])
    np.testing.assert_array_equal(ext.nominal[3:], [0, 0, 0, 1])
    # at the nominal point of the new terms nothing changes
    p0 = np.r_[FRAME_P[:3], 0, 0, 0, 0]
    _assert_same(ext.stiffness(p0), pm.stiffness(FRAME_P[:3]), "K at p_new = 0")
    _assert_same(ext.mass(p0), pm.mass(FRAME_P[:3]), "M at p_new = 0")
    phys = ext.physical(FRAME_P)
    assert phys["k_contact"] == pytest.approx(8e4) and phys["m_sensor"] == pytest.approx(0.12)
    assert phys["k_ground"] == pytest.approx(6e3) and phys["f_railB"] == pytest.approx(0.75)
    np.testing.assert_allclose(ext.normalized(phys), FRAME_P, rtol=1e-14, atol=1e-15)


def test_added_spring_and_mass_are_the_physical_matrices(frame):
    _, pm, ext = frame
    p = np.r_[0, 0, 0, 0.8, 1.2, 0.6, 0.0]
    dK = (ext.stiffness(p) - pm.stiffness(np.zeros(3))).toarray()
    dM = (ext.mass(p) - pm.mass(np.zeros(3))).toarray()
    aset = pm.aset
    idx = {(int(g), int(c)): i for i, (g, c) in enumerate(zip(aset.grid, aset.component))}
    a, b = idx[(24, 3)], idx[(5, 3)]
    assert dK[a, a] == pytest.approx(8e4) and dK[a, b] == pytest.approx(-8e4) and dK[b, b] == pytest.approx(8e4)
    for c in (1, 2, 3):
        assert dK[idx[(1, c)], idx[(1, c)]] == pytest.approx(6e3)
        assert dM[idx[(16, c)], idx[(16, c)]] == pytest.approx(0.12)
    assert np.count_nonzero(dK) == 4 + 3 and np.count_nonzero(dM) == 3
    # the x-translation mass (r^T M r, r = unit x motion of every grid) grows by the sensor mass
    r = np.zeros(dM.shape[0])
    r[[idx[(g, 1)] for g in aset.grid[aset.component == 1]]] = 1.0
    assert r @ ext.mass(p) @ r - r @ pm.mass(np.zeros(3)) @ r == pytest.approx(0.12, rel=1e-12)


def test_element_factor_is_p_times_the_subset_stiffness(frame):
    _, pm, ext = frame
    p = np.r_[FRAME_P[:3], 0, 0, 0, 0]
    k0 = ext.stiffness(p)
    for f in (-0.25, 0.5):
        q = p.copy()
        q[6] = f
        d1 = ext.stiffness(q) - k0
        q[6] = 2 * f
        d2 = ext.stiffness(q) - k0
        _assert_same(d2, 2 * d1, "linear in the factor")
    # the subset touches only the grids of bars 7..9 (rail B grids 11..14)
    q[6] = 0.5
    rows = np.unique(sp.coo_matrix(ext.stiffness(q) - k0).row)
    assert set(pm.aset.grid[rows].tolist()) == {11, 12, 13, 14}
    # the masses do not move with a stiffness factor
    _assert_same(ext.mass(q), ext.mass(p), "M")


def test_element_factor_on_every_shell_equals_the_E_parameters(subframe):
    """A stiffness factor on all shells of the subframe is E_main and E_weld moved together (G follows E);
    this includes the shell transverse-shear series terms, which are homogeneous of degree one."""
    _, pm, _ = subframe
    quads = pm.assembly.model.elements["CQUAD4"]
    ext = pm.with_terms([ElementFactor("f_all", tuple(int(e) for e in quads.ids), upper=1.0)])
    rng = np.random.default_rng(1)
    p = 0.1 * rng.standard_normal(pm.n_params)
    x = 0.23
    q = p.copy()
    for name in ("E_main", "E_weld"):
        j = pm.parameters.index(name)
        q[j] = (1 + p[j]) * (1 + x) - 1
    _assert_same(ext.stiffness(np.r_[p, x]), pm.stiffness(q), "K")


def test_derivatives_of_the_extended_model_are_exact(frame):
    _, _, ext = frame
    h = 1e-4  # central differences: truncation ~h^2 (cubic in t at most), round-off ~eps |K| / h
    for j in range(ext.n_params):
        e = np.zeros(ext.n_params)
        e[j] = h
        for f, df in ((ext.stiffness, ext.dK), (ext.mass, ext.dM)):
            fd = (f(FRAME_P + e) - f(FRAME_P - e)) / (2 * h)
            d = df(FRAME_P, j)
            tol = 1e-6 * abs(d).max() + 1e-14 * abs(f(FRAME_P)).max() / h
            assert abs(fd - d).max() <= tol, (ext.names[j], f.__name__)
    assert abs(ext.dK(FRAME_P, "m_sensor")).max() == 0.0


def test_frame_write_back_rereads_to_the_same_matrices(frame):
    d, pm, ext = frame
    out = _round_trip(d, ext, FRAME_P, "si")
    text = out.read_text()
    added = text.split("$ cards written by frfcal")[1]
    new_cards = [ln for ln in added.splitlines()[1:] if ln and not ln.startswith(("MAT1,", "CONM2,", "ENDDATA"))]
    # the added cards are fixed format (no commas), 8- or 16-character fields
    assert new_cards and not any("," in ln for ln in new_cards)
    assert all(len(ln) <= 80 for ln in new_cards)
    celas = [ln for ln in new_cards if ln.startswith("CELAS2")]
    conm2 = [ln for ln in new_cards if ln.startswith("CONM2")]
    assert len(celas) == 4 and len(conm2) == 1
    # fresh ids above the deck's (elements incl. masses up to 317, property 2, material 2)
    ids = [int(ln[8:16]) for ln in celas + conm2]
    assert min(ids) > 317 and len(set(ids)) == 5
    # the grounded springs leave G2, C2 blank
    assert sum(len(ln.split()) == 5 for ln in celas) == 3
    # bars 7..9 point to a new PBAR whose MAT1 copy has E = E0 (1 + p_E) 0.75 and the same RHO
    fe = femodel.read_bdf(out)
    bars = fe.elements["CBAR"]
    pids = bars["pid"][np.isin(bars.ids, [7, 8, 9])]
    assert len(set(pids.tolist())) == 1 and int(pids[0]) > 2
    mat = fe.materials["MAT1"]
    new_mid = int(mat.ids.max())
    assert new_mid > 2
    r = mat.rows([new_mid])[0]
    assert mat["E"][r] == pytest.approx(2.1e11 * 1.03 * 0.75, rel=1e-13)
    assert mat["RHO"][r] == pytest.approx(7850.0 * 0.98, rel=1e-13)


def test_frame_write_back_of_a_mass_factor(frame, tmp_path):
    _, pm, _ = frame
    ext = pm.with_terms([ElementFactor("f_m", (16, 17, 18), kind="M"), AddedSpring("kr", ((3, 4, 13, 4),), 1e3)])
    p = np.array([0.05, 0.1, -0.2, 0.4, 2.5])
    _round_trip(tmp_path, ext, p, "si")


def _beam_deck(path):
    """A free-free frame of CBEAMs: a PBEAM rail (with NSM) and a PBEAML BOX rail (with NSM), joined by two PBAR
    cross members; Nastran's default lumped mass (no rotary inertia of the bar mass: small CONM2s keep M
    definite). SI."""
    lines = ["SOL 103", "CEND", "BEGIN BULK", "MAT1,1,2.1+11,,0.3,7850.", "MAT1,2,7.0+10,,0.33,2700.",
             "PBEAM,1,1,4.4-4,1.0-7,1.2-7,,1.6-7,0.3", "PBEAML,2,2,,BOX,,,,,+P2", "+P2,0.05,0.04,0.003,0.003,0.2",
             "PBAR,3,1,2.0-4,2.0-8,2.5-8,3.0-8"]
    for i in range(6):
        lines.append(f"GRID,{1 + i},,{0.2 * i!r},0.,0.")
        lines.append(f"GRID,{11 + i},,{0.2 * i!r},0.4,0.")
    eid = 1
    for a in range(1, 6):
        lines.append(f"CBEAM,{eid},1,{a},{a + 1},0.,0.,1.")
        lines.append(f"CBEAM,{eid + 10},2,{a + 10},{a + 11},0.,0.,1.")
        eid += 1
    lines += ["CBAR,21,3,1,11,0.,0.,1.", "CBAR,22,3,6,16,0.,0.,1."]
    for k, g in enumerate(list(range(1, 7)) + list(range(11, 17))):
        lines += [f"CONM2,{300 + k},{g},0,0.01,,,,,+I{k}", f"+I{k},1.-5,,1.-5,,,1.-5"]
    lines.append("ENDDATA")
    path.write_text("\n".join(lines) + "\n")
    return path


def test_beam_element_factors_write_back_and_are_cluster_candidates(tmp_path):
    """PBEAM and PBEAML groups take element-subset factors like PBAR: stiffness and mass (with each station's
    NSM) re-read from the written deck to the same K and M, and element_cluster offers them."""
    params = ParameterSet((Parameter("E", "MAT1", (1,), "E", -0.3, 0.3),))
    pm = parametric_model(params, _beam_deck(tmp_path / "beams.bdf"))
    ext = pm.with_terms([ElementFactor("f_pbeam", (2, 3)), ElementFactor("f_pbeaml_m", (12, 13, 14), kind="M"),
                         ElementFactor("f_pbeaml_k", (15,))])
    p = np.array([0.05, 0.4, -0.3, 1.5])
    for j in range(1, 4):  # each factor changes its matrix (the terms are not empty)
        assert abs(ext.dM(p, j) if j == 2 else ext.dK(p, j)).max() > 0
    out = _round_trip(tmp_path, ext, p, "si")
    fe = femodel.read_bdf(out)
    beams = fe.elements["CBEAM"]
    assert len(set(beams["pid"][np.isin(beams.ids, [12, 13, 14])].tolist()) - {1, 2}) == 1
    cands = femodel.generate_candidates(pm, families=["element_cluster"])
    parts = {c.parts[0] for c in cands}
    assert {"PBEAM 1", "PBEAML 2", "PBAR 3"} <= parts, parts


def test_subframe_write_back_rereads_to_the_same_matrices(subframe):
    d, pm, ext = subframe
    rng = np.random.default_rng(2)
    p = np.r_[0.1 * rng.uniform(-1, 1, pm.n_params), 0.7, 1.3, 0.4, -0.3]
    out = _round_trip(d, ext, p, ext.units)
    # mm-t-s deck: the 70 kN/m contact spring is 70 N/mm, the 65 g sensor 6.5e-5 t
    text = out.read_text()
    assert re.search(r"^CELAS2 +\d+ +70\. ", text, re.M)
    assert re.search(r"^CONM2\*? .*6\.5-5", text, re.M)


def test_fixed_field_card_formats():
    assert fixed_field_card(["CELAS2", 7, 1.5e5, 3, 1]) == "CELAS2         7   1.5+5       3       1\n"
    # a real that has no exact 8-character spelling goes to large field, with 13+ digits
    card = fixed_field_card(["CONM2", 9, 17, 0, 1 / 3])
    assert card.startswith("CONM2*") and float(card.split()[-1]) == pytest.approx(1 / 3, rel=1e-14)
    long = fixed_field_card(["PBAR", 3, 3, 4.4e-4, 1e-7, 1.2e-7, 1.6e-7, 0.0, 0.0, 0.0, 0.0, 1.0])
    assert long.count("\n") == 2 and long.splitlines()[1].startswith(" " * 8)
    with pytest.raises(ParameterError, match="field"):
        fixed_field_card(["CELAS2", 123456789, 1.0])


def test_errors_name_the_term(frame):
    _, pm, ext = frame
    with pytest.raises(ParameterError, match="k_contact.*already used"):
        ext.with_terms([AddedMass("k_contact", (3,), 1.0)])
    with pytest.raises(ParameterError, match="element 8 is in both"):
        ext.with_terms([ElementFactor("f2", (8, 10))])
    with pytest.raises(ParameterError, match=r"grid \[999\]"):
        pm.with_terms([AddedMass("m", (999,), 1.0)])
    with pytest.raises(ParameterError, match=r"elements \[999\]"):
        pm.with_terms([ElementFactor("f", (7, 999))])
    with pytest.raises(ParameterError, match="CONM2"):
        pm.with_terms([ElementFactor("f", (200,))])
    with pytest.raises(ParameterError, match="CELAS2"):
        pm.with_terms([ElementFactor("f", (101,))])
    with pytest.raises(ParameterError, match="mix translations and rotations"):
        AddedSpring("k", ((1, 1, 2, 4),), 1.0)
    with pytest.raises(ParameterError, match="lower < upper"):
        AddedMass("m", (1,), 1.0, lower=-0.5)
    with pytest.raises(ParameterError, match="lower must be > -1"):
        ElementFactor("f", (1,), lower=-1.0)
    with pytest.raises(ParameterError, match="not one of"):
        pm.with_terms([Parameter("E2", "MAT1", (2,), "E", -0.1, 0.1)])


def test_element_factor_takes_the_element_when_a_conm2_reuses_its_id(frame, tmp_path):
    """pyNastran keeps masses apart from elements, so a deck may give a CONM2 the id of a CBAR (an outside
    frame: CBAR 101 and CONM2 101); a factor on that element scales the bar, not the mass."""
    d, pm, _ = frame
    text = (d / "frame.bdf").read_text().replace("CONM2,200,7,", "CONM2,8,7,")
    (tmp_path / "reused.bdf").write_text(text)
    params = ParameterSet((Parameter("E", "MAT1", (1,), "E", -0.3, 0.3),))
    a = parametric_model(params, d / "frame.bdf").with_terms([ElementFactor("f", (7, 8, 9))])
    b = parametric_model(params, tmp_path / "reused.bdf").with_terms([ElementFactor("f", (7, 8, 9))])
    q = np.array([0.1, 0.5])
    _assert_same(b.stiffness(q), a.stiffness(q), "K with the factor")
    _assert_same(b.mass(q), a.mass(q), "M")
    with pytest.raises(ParameterError, match=r"CONM2 \[301\]"):  # a mass id that is no element's
        parametric_model(params, tmp_path / "reused.bdf").with_terms([ElementFactor("f", (8, 301))])


def test_term_on_constrained_dof_is_rejected(tmp_path):
    deck = frame_deck(tmp_path / "frame.bdf")
    deck.write_text(deck.read_text().replace("ENDDATA", "SPC1,1,123456,1\nENDDATA"))
    text = deck.read_text().replace("CEND", "SPC = 1\nCEND")
    deck.write_text(text)
    pm = parametric_model(FRAME_PARAMS, deck)
    with pytest.raises(ParameterError, match="k_g.*constrained"):
        pm.with_terms([AddedSpring("k_g", ((1, 3, 0, 0),), 1.0)])


def test_added_cards_of_a_fitted_magnitude_are_small_field(frame, tmp_path):
    # a fitted magnitude has 17 significant digits; its CELAS2/CONM2 are written in small field, rounded to
    # 8 characters (relative change below 1e-4), and read back as written
    d, pm, ext = frame
    p = FRAME_P.copy()
    p[3:6] = [0.812345678901, 1.23456789012, 0.61234567891]
    out = ext.write_bdf(tmp_path / "fitted.bdf", p)
    added = out.read_text().split("$ cards written by frfcal")[1]
    new = [ln for ln in added.splitlines() if ln.startswith(("CELAS2", "CONM2")) and "," not in ln]  # not 200's
    assert len(new) == 5 and not any(ln.startswith(("CELAS2*", "CONM2*")) for ln in new)
    asm = femodel.assemble(femodel.read_bdf(out, units="si"))
    for A, B in ((asm.stiffness(), ext.stiffness(p)), (asm.mass(), ext.mass(p))):
        diff = abs(sp.csr_matrix(A) - sp.csr_matrix(B))
        assert diff.max() <= 1e-4 * abs(sp.csr_matrix(B)).max()



def _same_csr(A, B):
    A, B = sp.csr_matrix(A), sp.csr_matrix(B)
    return (A.shape == B.shape and np.array_equal(A.indptr, B.indptr) and np.array_equal(A.indices, B.indices)
            and np.array_equal(A.data, B.data))


def _both_paths(pm, factor):
    """(terms on the subset's own grids or None, terms on the full g-set) of an ElementFactor."""
    from femodel._grouping import _local_subset_terms, _subset_terms

    local = _local_subset_terms(pm.assembly, pm.parameters, factor, pm._amap())
    full = _subset_terms(pm.assembly, pm.parameters, factor)  # no a-set map: the full-size path
    if local is not None:
        (mats, a, b, r), lift = local
        local = ([lift(m) for m in mats], a, b, r)
    return local, full


@pytest.mark.parametrize("kind", ["K", "M"])
def test_subset_assembled_on_its_own_grids_is_the_full_size_assembly(subframe, tmp_path, kind):
    """ElementFactor terms assembled on the subset's grids alone (the fast path of term_derivative and
    with_terms) equal, entry for entry, the subset assembled on the full g-set and reduced by the full T:
    shells with shear series terms, and bars next to SPC'd grids (removed DOF). A subset touching a
    rigid-element dependent DOF takes the full-size path, with the same derivative."""
    from ._decks import frame_deck as full_frame_deck

    _, pm_shell, _ = subframe
    quads = pm_shell.assembly.model.elements["CQUAD4"]
    pm_bars = parametric_model(ParameterSet((Parameter("E", "MAT1", (1,), "E", -0.3, 0.3),
                                             Parameter("rho", "MAT1", (1,), "RHO", -0.3, 0.3))),
                               full_frame_deck(tmp_path / "all.bdf", cd_cyl=True, spc=True))
    cases = [(pm_shell, tuple(int(e) for e in quads.ids[quads["pid"] == 3][:12]), True),
             (pm_bars, (1, 2, 3, 4), True),  # grids 1, 2 SPC'd
             (pm_bars, (4, 5), False)]  # grid 5 follows RBE2 30
    for pm, elements, fast in cases:
        factor = ElementFactor("f", elements, kind=kind)
        local, full = _both_paths(pm, factor)
        assert (local is not None) == fast, elements
        if fast:
            assert len(local[0]) == len(full[0]) > 0
            assert all(_same_csr(a, b) for a, b in zip(local[0], full[0]))
            for x, y in zip(local[1:], full[1:]):
                assert np.array_equal(x, y)
        p = np.linspace(-0.1, 0.1, pm.n_params)
        d = pm.term_derivative(factor, p)[kind]
        ext = pm.with_terms([factor])
        ref = ext.dK(np.r_[p, 0.0], pm.n_params) if kind == "K" else ext.dM(np.r_[p, 0.0], pm.n_params)
        _assert_same(d, ref, f"{elements} d{kind}")
