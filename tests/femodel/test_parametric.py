"""ParametricModel: exactness against fresh assemblies, derivatives, units, round trips."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

import femodel
from femodel import ParameterError, assemble, example_subframe, parametric_model, read_bdf, read_parameters

# A small deck with every parameter kind the subframe lacks: PBUSH K, PELAS K,
# CELAS2 K, plus shells (E, RHO, T), a CONM2 and an RBE2.
SPRINGS_DECK = """\
SOL 103
CEND
BEGIN BULK
GRID,1,,0.,0.,0.
GRID,2,,200.,0.,0.
GRID,3,,200.,150.,0.
GRID,4,,0.,150.,0.
GRID,5,,400.,0.,0.
GRID,6,,400.,150.,0.
GRID,7,,500.,75.,20.
GRID,8,,520.,75.,20.
MAT1,3,210000.,,0.3,7.85-9
PSHELL,5,3,2.5,3,,3
PSHELL,6,3,4.0,3,,3
CQUAD4,1,5,1,2,3,4
CQUAD4,2,6,2,5,6,3
RBE2,20,7,123456,5,6
CONM2,30,8,,0.002
PBUSH,40,K,1000.,2000.,3000.,4.+5,5.+5,6.+5
CBUSH,41,40,7,8,,,,0
PELAS,50,123.
CELAS1,51,50,1,3,8,3
CELAS1,52,50,4,1,8,1
CELAS2,60,45.,4,5,8,5
"""
SPRINGS_DECK_END = "ENDDATA\n"

SPRINGS_PARAMS = """\
[model]
bdf = "springs.bdf"
units = "mm-t-s"

[[parameter]]
name = "E"
card = "MAT1"
id = 3
field = "E"
lower = -0.5
upper = 0.5

[[parameter]]
name = "rho"
card = "MAT1"
id = 3
field = "RHO"
lower = -0.5
upper = 0.5

[[parameter]]
name = "t"
card = "PSHELL"
ids = [5, 6]
field = "T"
lower = -0.5
upper = 0.5

[[parameter]]
name = "m"
card = "CONM2"
id = 30
field = "M"
lower = -0.5
upper = 0.5

[[parameter]]
name = "kx"
card = "PBUSH"
id = 40
field = "K1"
lower = -0.5
upper = 0.5

[[parameter]]
name = "krz"
card = "PBUSH"
id = 40
field = "K6"
lower = -0.5
upper = 0.5

[[parameter]]
name = "kelas"
card = "PELAS"
id = 50
field = "K"
lower = -0.5
upper = 0.5

[[parameter]]
name = "kcelas2"
card = "CELAS2"
id = 60
field = "K"
lower = -0.5
upper = 0.5
"""

RNG = np.random.default_rng(3)


def rel(a, b) -> float:
    d = (a - b).tocsr() if sp.issparse(a) else a - b
    scale = abs(b).max() if sp.issparse(b) else np.abs(b).max()
    return float(abs(d).max() / scale) if sp.issparse(d) else float(np.abs(d).max() / scale)


def fresh(path, units):
    asm = assemble(read_bdf(path, units=units))
    return asm, asm.stiffness(), asm.mass()


@pytest.fixture(scope="module")
def springs(tmp_path_factory):
    d = tmp_path_factory.mktemp("springs")
    (d / "springs.bdf").write_text(SPRINGS_DECK + SPRINGS_DECK_END)
    (d / "p.toml").write_text(SPRINGS_PARAMS)
    return d, parametric_model(d / "p.toml")


@pytest.fixture(scope="module")
def subframe(tmp_path_factory):
    d = tmp_path_factory.mktemp("subframe")
    ex = example_subframe(d, target_dof=5000, units="mm-t-s")
    return d, ex, parametric_model(ex.params)


def test_nominal_terms_sum_to_the_assembly(springs, subframe):
    for _, pm in (springs, subframe[::2]):
        p0 = np.zeros(pm.n_params)
        assert rel(pm.stiffness(p0), pm.assembly.stiffness()) < 1e-14
        assert rel(pm.mass(p0), pm.assembly.mass()) < 1e-14
        assert pm.K.shape == (len(pm.aset),) * 2


def test_every_kind_equals_fresh_assembly_of_written_deck(springs, tmp_path):
    d, pm = springs
    np.testing.assert_allclose(
        pm.nominal, [210e9, 7850.0, 2.5e-3, 2.0, 1e6, 6e5 * 1e-3, 123e3, 45e-3], rtol=1e-13
    )
    for j, name in enumerate(pm.parameters.names):
        p = np.zeros(pm.n_params)
        p[j] = 0.37 if j % 2 else -0.29
        out = pm.write_bdf(tmp_path / f"{name}.bdf", p)
        asm, K, M = fresh(out, "mm-t-s")
        np.testing.assert_array_equal(asm.aset.keys, pm.aset.keys)
        assert rel(pm.stiffness(p), K) < 1e-13, name
        assert rel(pm.mass(p), M) < 1e-13, name
        # the change itself (not drowned by the large shell terms) matches the deck's change
        K0, M0 = pm.assembly.stiffness(), pm.assembly.mass()
        dk_deck, dm_deck = (K - K0).tocsr(), (M - M0).tocsr()
        assert abs(dk_deck).max() + abs(dm_deck).max() > 0, name
        for ours, deck, ref in ((pm.stiffness(p) - K0, dk_deck, K0), (pm.mass(p) - M0, dm_deck, M0)):
            # round-off of the large terms is ~1e-16 |K0|; the change must match beyond it
            assert abs(ours - deck).max() <= 1e-12 * abs(deck).max() + 1e-15 * abs(ref).max(), name
    # all at once, random point inside the bounds
    p = RNG.uniform(pm.lower, pm.upper)
    asm, K, M = fresh(pm.write_bdf(tmp_path / "all.bdf", p), "mm-t-s")
    assert rel(pm.stiffness(p), K) < 1e-13 and rel(pm.mass(p), M) < 1e-13
    vals = pm.physical(p)
    assert vals["t"] == pytest.approx(2.5e-3 * (1 + p[2]), rel=1e-15)
    np.testing.assert_allclose(pm.normalized(vals), p, rtol=0, atol=1e-15)


def test_subframe_parameters_equal_fresh_assembly(subframe, tmp_path):
    _, ex, pm = subframe
    assert pm.parameters.names[0] == "E_main" and pm.n_params == 17
    p = RNG.uniform(pm.lower, pm.upper)
    asm, K, M = fresh(pm.write_bdf(tmp_path / "p.bdf", p), "mm-t-s")
    assert rel(pm.stiffness(p), K) < 1e-13
    assert rel(pm.mass(p), M) < 1e-13
    # total mass follows rho, t and the bushing masses
    assert pm.assembly.model.units == "mm-t-s"


def test_derivatives_equal_central_differences(springs, subframe):
    for pm in (springs[1], subframe[2]):
        p = RNG.uniform(0.5 * pm.lower, 0.5 * pm.upper)
        h = 1e-4
        for j in range(pm.n_params):
            e = np.zeros(pm.n_params)
            e[j] = h
            fd_k = (pm.stiffness(p + e) - pm.stiffness(p - e)) / (2 * h)
            fd_m = (pm.mass(p + e) - pm.mass(p - e)) / (2 * h)
            dk, dm = pm.dK(p, j), pm.dM(p, j)
            # truncation: h^2/6 * (third derivative) <= ~1e-8 relative for t^3 terms;
            # round-off: eps * |A(p)| / h from the large terms of the full matrix
            for exact, fd, full in ((dk, fd_k, pm.stiffness(p)), (dm, fd_m, pm.mass(p))):
                tol = 1e-7 * abs(exact).max() + 20 * 2.2e-16 * abs(full).max() / h
                assert abs(fd - exact).max() <= tol, pm.parameters.names[j]


def test_derivatives_equal_differences_of_assembled_decks(springs, tmp_path):
    """dK/dp from the parametric form vs central differences of fresh assemblies of written decks."""
    d, pm = springs
    p = np.zeros(pm.n_params)
    h = 1e-3
    for j, name in enumerate(pm.parameters.names):
        e = np.zeros(pm.n_params)
        e[j] = h
        _, Kp, Mp = fresh(pm.write_bdf(tmp_path / "a.bdf", p + e), "mm-t-s")
        _, Km, Mm = fresh(pm.write_bdf(tmp_path / "b.bdf", p - e), "mm-t-s")
        dk, dm = pm.dK(p, j), pm.dM(p, j)
        for exact, fd in ((dk, (Kp - Km) / (2 * h)), (dm, (Mp - Mm) / (2 * h))):
            if abs(exact).max() > 0:
                assert rel(fd, exact) < 1e-6, name  # t^3: truncation h^2 = 1e-6
            else:
                assert abs(fd).max() == 0.0, name


def test_reassembly_shares_one_pattern(subframe):
    _, _, pm = subframe
    a = pm.stiffness(np.zeros(17))
    b = pm.stiffness(np.full(17, 0.1))
    assert a.indices is not b.indices and np.array_equal(a.indices, b.indices) and np.array_equal(a.indptr, b.indptr)
    assert (pm.K.at(np.full(17, 0.1)) - b).count_nonzero() == 0 or rel(pm.K.at(np.full(17, 0.1)), b) < 1e-15


def test_two_thread_sum_on_the_shared_pattern_equals_one_thread_bit_for_bit(subframe, monkeypatch):
    """K(p), M(p) and dK/dp_j summed on two threads (each over half the rows) equal the one-thread sum exactly."""
    import femodel._pattern as pattern

    _, _, pm = subframe
    p = np.linspace(-0.2, 0.2, 17)
    monkeypatch.setattr(pattern, "_THREADED_COMBINE", 1 << 40)  # one thread
    one = [pm.stiffness(p), pm.mass(p), pm.dK(p, 3), pm.dM(p, 1)]
    monkeypatch.setattr(pattern, "_THREADED_COMBINE", 1)  # two threads at any size
    two = [pm.stiffness(p), pm.mass(p), pm.dK(p, 3), pm.dM(p, 1)]
    for a, b in zip(one, two):
        assert a.nnz > 1000 and np.array_equal(a.data, b.data) and np.array_equal(a.indices, b.indices)
    assert np.abs(one[0].data).max() > 0 and np.abs(one[2].data).max() > 0


def test_round_trip_at_nominal_gives_identical_matrices(subframe, tmp_path):
    _, ex, pm = subframe
    out = pm.write_bdf(tmp_path / "same.bdf", np.zeros(17))
    asm, K, M = fresh(out, "mm-t-s")
    K0, M0 = pm.assembly.stiffness(), pm.assembly.mass()
    assert abs(K - K0).max() == 0.0 and abs(M - M0).max() == 0.0


def test_mm_and_si_decks_give_the_same_physics(tmp_path):
    a = example_subframe(tmp_path / "mm", 5000, units="mm-t-s")
    b = example_subframe(tmp_path / "si", 5000, units="si")
    pa, pb = parametric_model(a.params), parametric_model(b.params)
    np.testing.assert_allclose(pa.nominal, pb.nominal, rtol=1e-15)
    p = np.linspace(-0.15, 0.15, 17)
    assert rel(pa.stiffness(p), pb.stiffness(p)) < 1e-12
    assert rel(pa.mass(p), pb.mass(p)) < 1e-12
    fa = pa.modes(p, 26).frequencies_hz
    fb = femodel.normal_modes(pb.stiffness(p), pb.mass(p), 26).frequencies_hz
    np.testing.assert_allclose(fa[6:], fb[6:], rtol=1e-9)


def test_bad_parameters(springs, tmp_path):
    d, _ = springs
    bad = SPRINGS_PARAMS.replace("id = 60\n", "id = 61\n")
    (d / "bad.toml").write_text(bad)
    with pytest.raises(ParameterError, match=r"'kcelas2': card CELAS2 61 \(field K\) is not in the deck"):
        parametric_model(d / "bad.toml")
    # a property no element uses does not enter K or M
    (d / "unused.bdf").write_text(SPRINGS_DECK + "PSHELL,7,3,1.0,3,,3\n" + SPRINGS_DECK_END)
    ps = read_parameters(d / "p.toml")
    unused = SPRINGS_PARAMS.replace('bdf = "springs.bdf"', 'bdf = "unused.bdf"').replace("ids = [5, 6]", "ids = [7]")
    (d / "unused.toml").write_text(unused)
    with pytest.raises(ParameterError, match="'t' .*does not enter K or M"):
        parametric_model(d / "unused.toml")
    pm = parametric_model(ps)
    with pytest.raises(ValueError, match="expected 8 normalized parameters"):
        pm.physical(np.zeros(3))
    with pytest.raises(ValueError, match="non-positive physical value"):
        pm.stiffness(np.full(8, -1.0))
    with pytest.raises(ParameterError, match="no parameter named 'zz'"):
        pm.dK(np.zeros(8), "zz")


def test_in_lbf_s_deck_with_wtmass_round_trips(tmp_path):
    deck = SPRINGS_DECK.replace("BEGIN BULK\n", "BEGIN BULK\nPARAM,WTMASS,0.00259\n") + SPRINGS_DECK_END
    (tmp_path / "springs.bdf").write_text(deck)
    (tmp_path / "p.toml").write_text(SPRINGS_PARAMS.replace('units = "mm-t-s"', 'units = "in-lbf-s"'))
    pm = parametric_model(tmp_path / "p.toml")
    slinch = 4.4482216152605 / 0.0254  # kg per lbf s^2/in
    assert pm.nominal[3] == pytest.approx(0.002 * 0.00259 * slinch, rel=1e-14)  # CONM2 M, SI kg
    assert pm.nominal[1] == pytest.approx(7.85e-9 * 0.00259 * slinch / 0.0254**3, rel=1e-14)
    p = RNG.uniform(pm.lower, pm.upper)
    asm, K, M = fresh(pm.write_bdf(tmp_path / "o.bdf", p), "in-lbf-s")
    assert rel(pm.stiffness(p), K) < 1e-13 and rel(pm.mass(p), M) < 1e-13


def test_projection_stays_exact_in_p(subframe):
    """V^T K(p) V from the projected terms equals projecting K(p): the surrogate is exact in p."""
    _, _, pm = subframe
    assert isinstance(pm.K, femodel.SeriesAffineMatrix) and np.any(pm.K.series_ratio > 0)
    V = np.random.default_rng(5).standard_normal((pm.K.shape[0], 6))
    Kr, Mr = pm.K.projected(V), pm.M.projected(V)
    for p in (np.zeros(17), RNG.uniform(pm.lower, pm.upper)):
        for red, full in ((Kr, pm.stiffness(p)), (Mr, pm.mass(p))):
            ref = V.T @ (full @ V)
            np.testing.assert_allclose(red.at(p), 0.5 * (ref + ref.T), rtol=0, atol=1e-12 * np.abs(ref).max())
        j = 4  # a thickness: series terms
        ref = V.T @ (pm.dK(p, j) @ V)
        np.testing.assert_allclose(Kr.derivative(p, j), 0.5 * (ref + ref.T), rtol=0, atol=1e-12 * np.abs(ref).max())


REFERENCE_DECKS = [
    pytest.param("dakota_cylinder", "modal.bdf", id="dakota_cylinder"),
    pytest.param("beam_modes", "beam_modes.dat", id="beam_modes"),
    pytest.param("cofe_three_element_types", "noReduction-000.dat", id="cofe"),
    pytest.param("femap_exhaust", "modal_example_from_op2.bdf", id="femap_exhaust", marks=pytest.mark.slow),
]


@pytest.mark.parametrize("folder, name", REFERENCE_DECKS)
def test_real_nastran_decks_round_trip(folder, name, tmp_path):
    """Real decks: write-back at p = 0 gives identical matrices; at p the parametric form matches."""
    from tests.conftest import reference_path

    from femodel._params import parameters_from_dict

    path = reference_path("nastran", folder, name)
    fe = read_bdf(path, units="consistent")
    mats = fe.materials["MAT1"]
    params = []
    for mid in mats.ids[:2].tolist():
        params.append(dict(name=f"E{mid}", card="MAT1", id=mid, field="E", lower=-0.3, upper=0.3))
        if mats["RHO"][mats.rows([mid])[0]] > 0:
            params.append(dict(name=f"rho{mid}", card="MAT1", id=mid, field="RHO", lower=-0.3, upper=0.3))
    if "PSHELL" in fe.properties:
        for pid in fe.properties["PSHELL"].ids[:3].tolist():
            params.append(dict(name=f"t{pid}", card="PSHELL", id=pid, field="T", lower=-0.3, upper=0.3))
    ps = parameters_from_dict({"model": {"bdf": str(path), "units": "consistent"}, "parameter": params})
    pm = parametric_model(ps)
    _, K0, M0 = fresh(pm.write_bdf(tmp_path / "same.bdf", np.zeros(len(ps))), "consistent")
    assert abs(K0 - pm.assembly.stiffness()).max() == 0.0 and abs(M0 - pm.assembly.mass()).max() == 0.0
    p = np.random.default_rng(1).uniform(-0.25, 0.25, len(ps))
    _, K, M = fresh(pm.write_bdf(tmp_path / "p.bdf", p), "consistent")
    # exact to round-off; an irregular shell mesh bins its shear series terms (bound reported)
    assert rel(pm.stiffness(p), K) <= max(1e-13, pm.series_error_bound)
    assert rel(pm.mass(p), M) < 1e-13


def test_series_coefficients_and_jacobian():
    """c(0) = 1, r = 0 reduces to the monomial, the Jacobian equals central differences."""
    rng = np.random.default_rng(7)
    n_terms, n_par = 6, 4
    a = rng.integers(0, 4, (n_terms, n_par)).astype(float)
    b = rng.integers(0, 4, (n_terms, n_par)).astype(float)
    r = np.array([0.0, 0.1, 1.0, 3.0, 50.0, 1e-3])
    mats = tuple(sp.identity(3, format="csr") * (k + 1) for k in range(n_terms))
    S = femodel.SeriesAffineMatrix(mats, a, b, r)
    A = femodel.AffineMatrix(mats, a)
    np.testing.assert_allclose(S.coefficients(np.zeros(n_par)), 1.0, rtol=1e-15)
    p = rng.uniform(-0.4, 0.4, n_par)
    assert S.coefficients(p)[0] == pytest.approx(A.coefficients(p)[0], rel=1e-15)
    u, v = A.coefficients(p), femodel.AffineMatrix(mats, b).coefficients(p)
    np.testing.assert_allclose(S.coefficients(p), (1 + r) / (1 / u + r / v), rtol=1e-14)
    h = 1e-6
    fd = np.column_stack([(S.coefficients(p + h * e) - S.coefficients(p - h * e)) / (2 * h) for e in np.eye(n_par)])
    np.testing.assert_allclose(S.coefficient_jacobian(p), fd, rtol=1e-7, atol=1e-9)
    with pytest.raises(ValueError, match="series_ratio"):
        femodel.SeriesAffineMatrix(mats, a, b, -r - 1)


def test_corner_thickness_elements_are_refused(tmp_path):
    deck = SPRINGS_DECK.replace("CQUAD4,1,5,1,2,3,4", "CQUAD4,1,5,1,2,3,4\n,,,2.5,2.5,2.6,2.6") + SPRINGS_DECK_END
    (tmp_path / "springs.bdf").write_text(deck)
    (tmp_path / "p.toml").write_text(SPRINGS_PARAMS)
    with pytest.raises(ParameterError, match=r"parameter 't': CQUAD4 \[1\] give their own corner thicknesses"):
        parametric_model(tmp_path / "p.toml")


@pytest.mark.parametrize("folder, name", REFERENCE_DECKS)
def test_real_decks_batched_cluster_derivatives_equal_one_by_one(folder, name):
    """term_derivatives on real decks (shells, beams, solids): the element clusters of both kinds assembled
    together in one pass are the ones assembled alone, entry for entry."""
    from tests.conftest import reference_path

    from femodel import CandidateOptions, generate_candidates
    from femodel._params import parameters_from_dict

    path = reference_path("nastran", folder, name)
    fe = read_bdf(path, units="consistent")
    mid = int(fe.materials["MAT1"].ids[0])
    ps = parameters_from_dict({"model": {"bdf": str(path), "units": "consistent"},
                               "parameter": [dict(name="E", card="MAT1", id=mid, field="E", lower=-0.3, upper=0.3)]})
    pm = parametric_model(ps)
    cands = generate_candidates(pm, families=["element_cluster"],
                                options=CandidateOptions(cluster_kinds=("K", "M"), max_per_family=60))
    assert len(cands) >= 2, f"{folder}: fewer than two element clusters"  # every deck listed has MAT1 groups
    terms = [c.term for c in cands]
    p = np.array([0.1])
    for t, d in zip(terms, pm.term_derivatives(terms, p)):
        ref = pm.term_derivative(t, p)
        for kind in ("K", "M"):
            assert (d[kind] is None) == (ref[kind] is None), (t.name, kind)
            if ref[kind] is not None:
                assert abs(d[kind] - ref[kind]).max() <= 1e-13 * abs(ref[kind]).max(), (t.name, kind)


def test_pcomp_laminates_beside_pshell_parameters(tmp_path):
    """A deck with CQUAD4 on PSHELL and on PCOMP laminates (plus bars, beams, rods, solids, an INCLUDE):
    PSHELL and PBAR parameters build and round-trip exactly (the laminates are constant terms; the shell
    shear series skips them); a MAT1 that is also a ply material is refused with the laminates named,
    since the write-back would change the laminates the model holds constant."""
    from tests.conftest import reference_path

    from femodel._params import parameters_from_dict

    path = reference_path("nastran", "solid_shell_bar", "mode_solid_shell_bar.bdf")
    model = {"bdf": str(path), "units": "consistent"}
    ok = parameters_from_dict({"model": model, "parameter": [
        dict(name="t4", card="PSHELL", id=4, field="T", lower=-0.3, upper=0.3),
        dict(name="A1", card="PBAR", id=1, field="A", lower=-0.3, upper=0.3)]})
    pm = parametric_model(ok)
    assert "PCOMP" in pm.assembly.model.properties
    p = np.array([0.2, -0.1])
    _, K, M = fresh(pm.write_bdf(tmp_path / "p.bdf", p), "consistent")
    assert rel(pm.stiffness(p), K) <= max(1e-13, pm.series_error_bound)
    assert rel(pm.mass(p), M) < 1e-13
    bad = parameters_from_dict({"model": model, "parameter": [
        dict(name="E1", card="MAT1", id=1, field="E", lower=-0.3, upper=0.3)]})
    with pytest.raises(ParameterError, match=r"'E1'.*ply of PCOMP \[6, 7\].*own MAT1"):
        parametric_model(bad)
