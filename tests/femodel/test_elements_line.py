"""Line-element kernels: static patch/cantilever solutions and section properties."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse.linalg as spla

import femodel
from tests.femodel._decks import NU, E, cantilever_deck


def _tip(tmp_path, direction, load_dir, **kw):
    asm = femodel.assemble(femodel.read_bdf(cantilever_deck(tmp_path / "c.bdf", direction=direction, **kw)))
    n_el = kw.get("n_el", 8)
    C = femodel.sensor_matrix(asm, [n_el + 1], [load_dir])
    f = np.asarray(C.toarray()).ravel()  # unit force at the tip along load_dir
    u = spla.spsolve(asm.stiffness().tocsc(), f)
    return float((C @ u)[0])


@pytest.mark.parametrize("direction", [(1.0, 0.0, 0.0), (1.0, 2.0, 2.0)])
def test_cantilever_euler_bernoulli_tip_deflection(tmp_path, direction):
    d = np.asarray(direction) / np.linalg.norm(direction)
    # plane 1 contains the element axis and v=(0,0,1): bending in plane 1 uses I1
    ez = np.cross(d, [0.0, 0.0, 1.0])
    ez /= np.linalg.norm(ez)
    ey = np.cross(ez, d)
    L, I1, I2, A = 2.0, 2e-7, 3e-7, 1e-3
    # load along element y (plane 1) -> I1; along element z (plane 2) -> I2
    assert _tip(tmp_path, direction, ey) == pytest.approx(L**3 / (3 * E * I1), rel=1e-10)
    assert _tip(tmp_path, direction, ez) == pytest.approx(L**3 / (3 * E * I2), rel=1e-10)
    assert _tip(tmp_path, direction, d) == pytest.approx(L / (E * A), rel=1e-10)


def test_cantilever_timoshenko_adds_shear_flexibility(tmp_path):
    k = 0.85
    d = np.array([1.0, 2.0, 2.0]) / 3.0
    ez = np.cross(d, [0.0, 0.0, 1.0])
    ez /= np.linalg.norm(ez)
    ey = np.cross(ez, d)
    L, I1, A = 2.0, 2e-7, 1e-3
    G = E / (2 * (1 + NU))
    want = L**3 / (3 * E * I1) + L / (k * A * G)
    assert _tip(tmp_path, tuple(d), ey, k_shear=k) == pytest.approx(want, rel=1e-10)


def test_pbarl_and_pbeaml_sections(tmp_path):
    p = tmp_path / "s.bdf"
    p.write_text(
        "BEGIN BULK\nMAT1,1,2.e11,,0.3,7800.\n"
        "PBARL,1,1,,ROD\n,0.01\n"
        "PBARL,2,1,,TUBE\n,0.02,0.015\n"
        "PBARL,3,1,,BAR\n,0.02,0.01\n"
        "PBEAML,4,1,,ROD\n,0.01\n"
        "GRID,1,,0.,0.,0.\nGRID,2,,1.,0.,0.\n"
        "CBAR,1,1,1,2,0.,1.,0.\nCBAR,2,2,1,2,0.,1.,0.\nCBAR,3,3,1,2,0.,1.,0.\nCBEAM,4,4,1,2,0.,1.,0.\n"
        "ENDDATA\n"
    )
    model = femodel.read_bdf(p)
    pb = model.properties["PBAR"]
    r = pb.rows([1, 2, 3, 4])
    np.testing.assert_allclose(pb["A"][r], [np.pi * 1e-4, np.pi * (4e-4 - 2.25e-4), 2e-4, np.pi * 1e-4], rtol=1e-12)
    np.testing.assert_allclose(pb["I1"][r[0]], np.pi * 0.01**4 / 4, rtol=1e-12)
    np.testing.assert_allclose(pb["J"][r[3]], np.pi * 0.01**4 / 2, rtol=1e-12)
    # ROD shear factor 0.9 (as MSC Nastran, confirmed on the beam_modes reference)
    assert pb["k1"][r[0]] == 0.9 and pb["k1"][r[3]] == 0.9


def test_cbar_lumped_mass_has_no_rotary_inertia_cbeam_has_torsion(tmp_path):
    p = tmp_path / "m.bdf"
    p.write_text(
        "BEGIN BULK\nMAT1,1,2.e11,,0.3,8000.\nPBAR,1,1,1.e-3,1.e-7,1.e-7,2.e-7\n"
        "PBEAM,2,1,1.e-3,1.e-7,1.e-7,,2.e-7\n"
        "GRID,1,,0.,0.,0.\nGRID,2,,2.,0.,0.\nGRID,3,,0.,0.,0.\nGRID,4,,2.,0.,0.\n"
        "CBAR,1,1,1,2,0.,1.,0.\nCBEAM,2,2,3,4,0.,1.,0.\nENDDATA\n"
    )
    asm = femodel.assemble(femodel.read_bdf(p))
    M = asm.mass_g().toarray()
    g = asm.gset
    half = 0.5 * 8000.0 * 1e-3 * 2.0
    for grid in (1, 2, 3, 4):
        for c in (1, 2, 3):
            assert M[g.index(grid, c), g.index(grid, c)] == pytest.approx(half, rel=1e-12)
    assert M[g.index(1, 4), g.index(1, 4)] == 0.0 and M[g.index(1, 5), g.index(1, 5)] == 0.0
    assert M[g.index(3, 4), g.index(3, 4)] == pytest.approx(0.5 * 8000.0 * 2e-7 * 2.0, rel=1e-12)


def test_cbush_stiffness_in_its_cid_axes(tmp_path):
    """A grounded CBUSH with K only along its CID x axis resists only that direction."""
    p = tmp_path / "b.bdf"
    p.write_text(
        "BEGIN BULK\nCORD2R,7,0,0.,0.,0.,0.,0.,1.,+C\n+C,1.,1.,0.\n"
        "PBUSH,1,K,1000.\nGRID,1,,0.,0.,0.\nCBUSH,1,1,1,,,,,7\nENDDATA\n"
    )
    asm = femodel.assemble(femodel.read_bdf(p))
    K = asm.stiffness_g().toarray()[:3, :3]
    e = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
    np.testing.assert_allclose(K, 1000.0 * np.outer(e, e), atol=1e-9)


def test_pin_flags_release_end_moments(tmp_path):
    """Two collinear bars clamped at both far ends, joined at grid 2.

    With PA=456 on bar 2 (rotations released at grid 2) the transverse
    stiffness at grid 2 is 3EI/L^3 (cantilever) + 3EI/L^3 (clamped-pinned
    member) = 6EI/L^3; without pins it is 24EI/L^3 (fixed-fixed, 2L span).
    """
    L, I = 1.0, 2e-7

    def stiffness(pa):
        p = tmp_path / f"p{pa}.bdf"
        p.write_text(
            f"BEGIN BULK\nMAT1,1,{E!r},,0.3,7800.\nPBAR,1,1,1.e-3,{I!r},{I!r},4.e-7\n"
            "GRID,1,,0.,0.,0.\nGRID,2,,1.,0.,0.\nGRID,3,,2.,0.,0.\n"
            f"CBAR,1,1,1,2,0.,0.,1.\nCBAR,2,1,2,3,0.,0.,1.,,+P\n+P,{pa}\nSPC1,1,123456,1,3\nENDDATA\n"
        )
        asm = femodel.assemble(femodel.read_bdf(p))
        C = femodel.sensor_matrix(asm, [2], [[0.0, 1.0, 0.0]])
        u = spla.spsolve(asm.stiffness().tocsc(), np.asarray(C.toarray()).ravel())
        return 1.0 / float((C @ u)[0])

    assert stiffness(456) == pytest.approx(6 * E * I / L**3, rel=1e-10)
    assert stiffness("") == pytest.approx(24 * E * I / L**3, rel=1e-10)
