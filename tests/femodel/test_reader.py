"""Reader details: SPC set selection, PS, CORD1R, CONM2 CID=-1, free/large field."""

from __future__ import annotations

import numpy as np
import pytest

import femodel

BULK = (
    "MAT1,1,2.e11,,0.3,7800.\nPBAR,1,1,1.e-3,1.e-7,1.e-7,2.e-7\n"
    "GRID,1,,0.,0.,0.\nGRID,2,,1.,0.,0.\nGRID,3,,2.,0.,0.,,345\n"
    "CBAR,1,1,1,2,0.,1.,0.\nCBAR,2,1,2,3,0.,1.,0.\n"
    "SPC1,1,123456,1\nSPC1,2,123,1\nSPC1,2,2,3\n"
)


def test_case_control_selects_the_spc_set(tmp_path):
    p = tmp_path / "a.bdf"
    p.write_text("SOL 103\nCEND\nSUBCASE 1\n  SPC = 2\nBEGIN BULK\n" + BULK + "ENDDATA\n")
    m = femodel.read_bdf(p)
    got = sorted(zip(m.spc_grid.tolist(), m.spc_component.tolist()))
    assert got == [(1, 1), (1, 2), (1, 3), (3, 2)]
    asm = femodel.assemble(m)
    # GRID 3 PS=345 and SPC 3-T2 removed; grid 1 keeps its rotations
    assert not np.any((asm.aset.grid == 3) & np.isin(asm.aset.component, [2, 3, 4, 5]))
    assert np.sum(asm.aset.grid == 1) == 3


def test_without_case_control_all_spc_sets_apply(tmp_path):
    p = tmp_path / "b.bdf"
    p.write_text("BEGIN BULK\n" + BULK + "ENDDATA\n")
    m = femodel.read_bdf(p)
    assert len(m.spc_grid) == 6 + 3 + 1


def test_spcadd_is_expanded(tmp_path):
    p = tmp_path / "c.bdf"
    p.write_text("SOL 103\nCEND\nSPC = 9\nBEGIN BULK\n" + BULK + "SPCADD,9,1,2\nENDDATA\n")
    m = femodel.read_bdf(p)
    assert len(m.spc_grid) == 10


def test_cord1r_large_field_and_conm2_cid_minus_one(tmp_path):
    p = tmp_path / "d.bdf"
    p.write_text(
        "BEGIN BULK\n"
        "GRID*                 10                              1.              2.\n"
        "*                     0.\n"
        "GRID,11,,1.,2.,1.\nGRID,12,,2.,2.,0.\n"
        "CORD1R,4,10,11,12\n"
        "GRID,13,4,0.,0.,3.\n"
        "CONM2,1,13,-1,5.,1.,2.,4.\n"
        "ENDDATA\n"
    )
    m = femodel.read_bdf(p)
    np.testing.assert_allclose(m.xyz[m.grid_index(13)[0]], [1.0, 2.0, 3.0], atol=1e-14)
    t = m.elements["CONM2"]
    np.testing.assert_allclose(t["offset"][0], [0.0, 0.0, 1.0], atol=1e-14)
    mp = femodel.mass_properties(femodel.assemble(m))
    np.testing.assert_allclose(mp.cg, [1.0, 2.0, 4.0], atol=1e-12)
    assert mp.mass == 5.0


def test_unit_systems_convert_mass_and_length(tmp_path):
    """A 1-unit CONM2 at x=1: 1 t = 1000 kg at 1 mm; 1 lbf s^2/in = 175.127 kg at 1 in."""
    p = tmp_path / "u.bdf"
    p.write_text("BEGIN BULK\nGRID,1,,1.,0.,0.\nCONM2,1,1,,1.0\nENDDATA\n")
    for units, mass, x in (("mm-t-s", 1000.0, 1e-3), ("in-lbf-s", 4.4482216152605 / 0.0254, 0.0254), ("si", 1.0, 1.0)):
        mp = femodel.mass_properties(femodel.assemble(femodel.read_bdf(p, units=units)))
        assert mp.mass == pytest.approx(mass, rel=1e-12)
        assert mp.cg[0] == pytest.approx(x, rel=1e-12)


def test_wtmass_scales_all_mass(tmp_path):
    p = tmp_path / "w.bdf"
    p.write_text(
        "BEGIN BULK\nPARAM,WTMASS,0.5\nMAT1,1,2.e11,,0.3,8000.\nPROD,1,1,1.e-4\n"
        "GRID,1,,0.,0.,0.\nGRID,2,,2.,0.,0.\nCROD,1,1,1,2\nCONM2,2,2,,3.0\nENDDATA\n"
    )
    mp = femodel.mass_properties(femodel.assemble(femodel.read_bdf(p)))
    assert mp.mass == pytest.approx(0.5 * (8000.0 * 1e-4 * 2.0 + 3.0), rel=1e-12)


def test_mpc_of_the_case_control_set_ties_dof(tmp_path):
    """MPC u(3,T2) - 2 u(2,T2) = 0 (set 5 selected); set 6 is not applied."""
    p = tmp_path / "mpc.bdf"
    p.write_text(
        "SOL 103\nCEND\nMPC = 5\nBEGIN BULK\n" + BULK.replace("SPC1,2,2,3\n", "")
        + "MPC,5,3,2,1.,2,2,-2.\nMPC,6,3,3,1.,2,3,-1.\nENDDATA\n"
    )
    m = femodel.read_bdf(p)
    assert m.mpc == ((5, ((3, 2, 1.0), (2, 2, -2.0))),)
    asm = femodel.assemble(m)
    assert not np.any((asm.aset.grid == 3) & (asm.aset.component == 2))
    ua = np.zeros(len(asm.aset))
    ua[asm.aset.index(2, 2)] = 1.5
    ug = asm.expand(ua)
    assert ug[asm.gset.index(3, 2)] == pytest.approx(3.0)
    assert ug[asm.gset.index(3, 3)] == 0.0


# CORD2R 5: origin (1, 0, 0), e1 = +y, e2 = -x, e3 = +z, so local (a, b, c) -> basic (1 - b, a, c).
# Grids 10, 11, 12 are positioned in it at basic (1, 0, 0), (1, 0, 2), (2, 0, 0); the CORD1R 7
# built on them is basic translated by (1, 0, 0).
CHAINED_CORDS = (
    "CORD2R,5,0,1.,0.,0.,1.,0.,1.,+C5\n+C5,1.,1.,0.\n"
    "GRID,10,5,0.,0.,0.\nGRID,11,5,0.,0.,2.\nGRID,12,5,0.,-1.,0.\n"
    "CORD1R,7,10,11,12\n"
    "GRID,20,7,0.5,0.25,3.\n"
)


@pytest.mark.parametrize("units, scale", [("si", 1.0), ("mm-t-s", 1e-3)])
def test_cord1_on_grids_positioned_in_another_system(tmp_path, units, scale):
    """Nastran lets CORD1x use grids given in other systems; they are resolved first."""
    p = tmp_path / "chain.bdf"
    p.write_text("BEGIN BULK\n" + CHAINED_CORDS + "ENDDATA\n")
    m = femodel.read_bdf(p, units=units)
    np.testing.assert_allclose(m.xyz[m.grid_index([10, 11, 12])], np.array([[1, 0, 0], [1, 0, 2], [2, 0, 0]]) * scale,
                               atol=1e-15)
    np.testing.assert_allclose(m.coords[7].origin, np.array([1.0, 0.0, 0.0]) * scale, atol=1e-15)
    np.testing.assert_allclose(m.coords[7].axes, np.eye(3), atol=1e-15)
    np.testing.assert_allclose(m.xyz[m.grid_index(20)[0]], np.array([1.5, 0.25, 3.0]) * scale, atol=1e-15)


def test_cord2r_in_a_cylindrical_rid_scales_lengths_not_angles(tmp_path):
    """CORD2R 8 given as (r, theta, z) points of CORD2C 6; mm-t-s and SI decks put grid 30 at the same place.

    System 8: origin (0, 1, 0), e1 = +y, e2 = -x, e3 = +z; grid 30 at local
    (0.5, 0.2, 0.1) m is at basic (-0.2, 1.5, 0.1) m.
    """
    def deck(L):
        return (
            "BEGIN BULK\nCORD2C,6,0,0.,0.,0.,0.,0.,1.,+C6\n+C6,1.,0.,0.\n"
            f"CORD2R,8,6,{L!r},90.,0.,{L!r},90.,{L!r},+C8\n+C8,{2 * L!r},90.,0.\n"
            f"GRID,30,8,{0.5 * L!r},{0.2 * L!r},{0.1 * L!r}\nENDDATA\n"
        )

    for units, L in (("si", 1.0), ("mm-t-s", 1e3)):
        p = tmp_path / f"rid_{units}.bdf"
        p.write_text(deck(L))
        m = femodel.read_bdf(p, units=units)
        np.testing.assert_allclose(m.xyz[0], [-0.2, 1.5, 0.1], atol=1e-12)
        np.testing.assert_allclose(m.coords[8].axes, [[0, 1, 0], [-1, 0, 0], [0, 0, 1]], atol=1e-12)
