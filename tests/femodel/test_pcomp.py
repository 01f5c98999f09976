"""PCOMP laminates (MAT1 and MAT8 plies) read into shell constitutive input."""

from __future__ import annotations

import numpy as np

import femodel

GRIDS = "GRID,1,,0.,0.,0.\nGRID,2,,0.5,0.,0.\nGRID,3,,0.5,0.4,0.05\nGRID,4,,0.,0.4,0.\nGRID,5,,1.,0.,0.\nGRID,6,,1.,0.4,0.\n"


def _asm(tmp_path, name, props, theta=("", "")):
    p = tmp_path / name
    p.write_text(
        "BEGIN BULK\nMAT1,1,7.e10,,0.3,2700.\nMAT8,2,1.4e11,1.e10,0.3,5.e9,4.e9,3.e9,1600.\n"
        + GRIDS
        + props
        + f"CQUAD4,1,7,1,2,3,4,{theta[0]}\nCTRIA3,2,7,2,5,6,{theta[1]}\nCTRIA3,3,7,2,6,3,{theta[1]}\nENDDATA\n"
    )
    return femodel.assemble(femodel.read_bdf(p))


def test_pcomp_of_isotropic_plies_equals_pshell(tmp_path):
    a = _asm(tmp_path, "a.bdf", "PCOMP,7,,0.1\n,1,0.001,0.,,1,0.001,0.,\n,1,0.001,0.\n")
    # MID3 with TS/T = 5/6 and NSM 0.1 kg/m^2
    b = _asm(tmp_path, "b.bdf", "PSHELL,7,1,0.003,1,,1,0.833333333333,0.1\n")
    for x, y in ((a.stiffness_g(), b.stiffness_g()), (a.mass_g(), b.mass_g())):
        assert abs(x - y).max() <= 1e-6 * abs(y).max()
    assert all(t.factors == () for t in a.terms)  # a laminate is not a monomial of card fields


def test_pcomp_element_theta_equals_ply_angle(tmp_path):
    a = _asm(tmp_path, "c.bdf", "PCOMP,7\n,2,0.002,30.\n", theta=("0.", "0."))
    b = _asm(tmp_path, "d.bdf", "PCOMP,7\n,2,0.002,0.\n", theta=("30.", "30."))
    c = _asm(tmp_path, "e.bdf", "PCOMP,7\n,2,0.002,0.\n", theta=("0.", "0."))
    ka, kb, kc = a.stiffness_g(), b.stiffness_g(), c.stiffness_g()
    assert abs(ka - kb).max() <= 1e-8 * abs(ka).max()
    assert abs(ka - kc).max() > 1e-3 * abs(ka).max()  # the angle matters
    mp = femodel.mass_properties(a)
    area = 0.5 * 0.4 + 0.5 * 0.4  # quad (projected, warped 0.05) + two triangles, lumped
    assert 0.99 * 1600 * 0.002 * area < mp.mass < 1.02 * 1600 * 0.002 * area
