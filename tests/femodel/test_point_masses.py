"""CMASS1/PMASS, CMASS2 and CONM1: read, assembled as Nastran defines them, calibrated and written back.

Each check is against a hand-built reference: the analytic spring-mass
frequency, the 2 x 2 scalar-mass matrices, the rigid-body mass matrix of an
offset mass with inertia (what a CONM2 is, written out as a CONM1), the
unit conversions of every block, and the write-back round trip.
"""

from __future__ import annotations

import numpy as np
import pytest

import femodel
from femodel import ModelError, assemble, parametric_model, read_bdf
from femodel._params import ParameterError, parameters_from_dict


def _deck(tmp_path, body: str, name: str = "deck.bdf", head: str = "") -> str:
    path = tmp_path / name
    path.write_text("BEGIN BULK\n" + head + body + "ENDDATA\n")
    return str(path)


def _km(path, units="si"):
    asm = assemble(read_bdf(path, units=units))
    return asm.stiffness().toarray(), asm.mass().toarray()


def _mg(path, units="si"):
    """The g-set mass (a grid with mass only would be AUTOSPC'd out of the independent set)."""
    return assemble(read_bdf(path, units=units)).mass_g().toarray()


TWO_DOF = """GRID,1,,0.,0.,0.,,12456
GRID,2,,1.,0.,0.,,12456
CELAS2,1,4.e4,1,3
CELAS2,3,1.e4,1,3,2,3
PMASS,7,2.
CMASS1,4,7,1,3
CMASS2,5,1.,2,3
CMASS2,6,0.5,1,3,2,3
"""


def test_grounded_scalar_mass_on_a_spring_has_the_analytic_frequency(tmp_path):
    path = _deck(tmp_path, "GRID,1,,0.,0.,0.,,12456\nCELAS2,1,4.e4,1,3\nCMASS2,2,2.5,1,3\n")
    K, M = _km(path)
    assert K.shape == M.shape == (1, 1)
    f = femodel.normal_modes(K, M, 1, solver="dense").frequencies_hz[0]
    assert f == pytest.approx(np.sqrt(4e4 / 2.5) / (2 * np.pi), rel=1e-12)


def test_scalar_masses_between_two_dof_and_to_ground(tmp_path):
    """CMASS between two DOF adds m [[1, -1], [-1, 1]]; to ground m on the diagonal (as CELAS for K)."""
    K, M = _km(_deck(tmp_path, TWO_DOF))
    np.testing.assert_allclose(K, [[5e4, -1e4], [-1e4, 1e4]], rtol=1e-15)
    np.testing.assert_allclose(M, [[2.0 + 0.5, -0.5], [-0.5, 1.0 + 0.5]], rtol=1e-15)


def test_scalar_mass_components_follow_the_displacement_system(tmp_path):
    """A CMASS2 on component 1 of a grid whose CD is rotated 90 deg about z is a mass along basic y."""
    body = ("CORD2R,5,,0.,0.,0.,0.,0.,1.,\n,0.,1.,0.\n"
            "GRID,1,,0.,0.,0.,5,3456\nCMASS2,2,3.,1,1\nCELAS2,3,1.,1,1\nCELAS2,4,1.,1,2\n")
    fe = read_bdf(_deck(tmp_path, body))
    asm = assemble(fe)
    assert fe.elements["CMASS2"]["m"][0] == 3.0
    M = asm.mass_g().toarray()
    assert np.count_nonzero(M) == 1 and M[0, 0] == 3.0  # on the CD component (the g-set's), as a CELAS rate


def _rigid_mass(m, x, J):
    """6 x 6 mass matrix at a grid of a point mass m at offset x with inertia J about its CG (basic)."""
    S = np.array([[0.0, -x[2], x[1]], [x[2], 0.0, -x[0]], [-x[1], x[0], 0.0]])
    out = np.zeros((6, 6))
    out[:3, :3] = m * np.eye(3)
    out[:3, 3:] = -m * S
    out[3:, :3] = m * S
    out[3:, 3:] = J - m * S @ S
    return out


def _conm1_card(eid, grid, cid, M6):
    low = [M6[i, j] for i in range(6) for j in range(i + 1)]
    f = [repr(float(v)) for v in low]
    return (f"CONM1,{eid},{grid},{cid or ''},{','.join(f[:5])}\n,{','.join(f[5:13])}\n,{','.join(f[13:])}\n")


def test_conm1_equals_the_conm2_it_writes_out(tmp_path):
    """A CONM2 (mass, offset, inertia) and the CONM1 holding its rigid-body 6 x 6 matrix assemble alike."""
    m, x = 2.0, np.array([0.1, -0.2, 0.05])
    J = np.array([[0.3, -0.01, 0.0], [-0.01, 0.4, -0.02], [0.0, -0.02, 0.5]])
    grid = "GRID,1,,0.,0.,0.\n"
    conm2 = f"CONM2,9,1,,{m},{x[0]},{x[1]},{x[2]}\n,0.3,0.01,0.4,0.,0.02,0.5\n"
    M2 = _mg(_deck(tmp_path, grid + conm2, "c2.bdf"))
    M1 = _mg(_deck(tmp_path, grid + _conm1_card(9, 1, 0, _rigid_mass(m, x, J)), "c1.bdf"))
    np.testing.assert_allclose(M2, _rigid_mass(m, x, J), rtol=0, atol=1e-14)
    np.testing.assert_allclose(M1, M2, rtol=0, atol=1e-14)


def test_conm1_matrix_in_a_rotated_system(tmp_path):
    """CID rotates the whole 6 x 6 matrix to basic: R M R^T block-diagonally."""
    a = np.deg2rad(30.0)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    cord = (f"CORD2R,4,,0.,0.,0.,0.,0.,1.,\n,{R[0, 0]!r},{R[1, 0]!r},0.\n")
    M6 = np.diag([1.0, 2.0, 3.0, 0.1, 0.2, 0.3])
    M6[4, 0] = M6[0, 4] = 0.05
    M = _mg(_deck(tmp_path, cord + "GRID,1,,0.,0.,0.\n" + _conm1_card(3, 1, 4, M6)))
    Rb = np.kron(np.eye(2), R)
    np.testing.assert_allclose(M, Rb @ M6 @ Rb.T, rtol=0, atol=1e-12)


def test_units_and_wtmass(tmp_path):
    """mm-t-s: t on translations, t mm on couplings, t mm^2 on rotations; WTMASS on every mass."""
    body = ("GRID,1,,0.,0.,0.\nGRID,2,,0.,0.,0.,,12456\n"
            "CMASS2,1,0.0025,2,3\nCMASS2,2,1000.,1,4\n"
            + _conm1_card(5, 1, 0, np.array([[0.002, 0, 0, 0, 1.0, 0], [0, 0.002, 0, 0, 0, 0], [0, 0, 0.002, 0, 0, 0],
                                             [0, 0, 0, 500.0, 0, 0], [1.0, 0, 0, 0, 500.0, 0],
                                             [0, 0, 0, 0, 0, 500.0]])))
    M = _mg(_deck(tmp_path, body), "mm-t-s")  # grid 1's DOF 0-5, grid 2's 6-11
    assert M[8, 8] == pytest.approx(2.5, rel=1e-12)
    assert M[3, 3] == pytest.approx(1.0 + 0.5, rel=1e-12)  # CMASS2 on R4 plus the CONM1's M44 (kg m^2)
    assert M[0, 0] == pytest.approx(2.0, rel=1e-12)
    assert M[4, 0] == pytest.approx(1.0, rel=1e-12) and M[0, 4] == pytest.approx(1.0, rel=1e-12)
    assert M[5, 5] == pytest.approx(0.5, rel=1e-12)
    Mw = _mg(_deck(tmp_path, body, "w.bdf", head="PARAM,WTMASS,0.5\n"), "mm-t-s")
    np.testing.assert_allclose(Mw, 0.5 * M, rtol=1e-15)


def test_bad_point_mass_cards_name_card_and_id(tmp_path):
    with pytest.raises(ModelError, match="CMASS1 4 references undefined PMASS 8"):
        read_bdf(_deck(tmp_path, "GRID,1,,0.,0.,0.\nCMASS1,4,8,1,3\n", "a.bdf"))
    with pytest.raises(ModelError, match="CMASS2 5: component C1=7"):
        read_bdf(_deck(tmp_path, "GRID,1,,0.,0.,0.\nCMASS2,5,1.,1,7\n", "b.bdf"))
    with pytest.raises(ModelError, match="CMASS2 5"):
        read_bdf(_deck(tmp_path, "GRID,1,,0.,0.,0.\nCMASS2,5,1.,9,3\n", "c.bdf"))
    with pytest.raises(ModelError, match="CONM1 6: mass matrix is not positive semi-definite"):
        read_bdf(_deck(tmp_path, "GRID,1,,0.,0.,0.\nCONM1,6,1,,-1.\n", "d.bdf"))


def test_scalar_mass_parameters_calibrate_and_write_back(tmp_path):
    """CMASS2 M and PMASS M are parameters: the parametric mass is the written-back deck's, in SI.

    The deck has BEGIN BULK but no executive or case control (as read_bdf accepts): the parameter
    table's nominal check and the write-back read it too."""
    body = TWO_DOF.replace("GRID,1,,0.,0.,0.,,12456", "GRID,1,,0.,0.,0.,,1256") + "CMASS2,8,500.,1,4\n"
    src = _deck(tmp_path, body)  # grid 1's R4 free, with a rotary scalar mass of 500 t mm^2 on it
    ps = parameters_from_dict({"model": {"bdf": src, "units": "mm-t-s"}, "parameter": [
        {"name": "m_sensor", "card": "CMASS2", "id": 5, "field": "M", "lower": -0.5, "upper": 0.5,
         "nominal": 1000.0, "unit": "kg"},
        {"name": "m_pair", "card": "PMASS", "id": 7, "field": "M1", "lower": -0.5, "upper": 0.5},  # Nastran's name
        {"name": "j_rot", "card": "CMASS2", "id": 8, "field": "M", "lower": -0.5, "upper": 0.5,
         "nominal": 0.5, "unit": "kg*m^2"},
    ]})
    pm = parametric_model(ps)
    p = np.array([0.2, -0.3, 0.1])
    out = pm.write_bdf(tmp_path / "p.bdf", p)
    _, M = _km(out, "mm-t-s")
    np.testing.assert_allclose(pm.mass(p).toarray(), M, rtol=1e-13, atol=0)
    fe = read_bdf(out, units="mm-t-s")
    tab = fe.elements["CMASS2"]
    assert tab["m"][list(tab.ids).index(5)] == pytest.approx(1.2 * 1000.0, rel=1e-12)  # 1 t -> 1000 kg
    assert tab["m"][list(tab.ids).index(8)] == pytest.approx(1.1 * 0.5, rel=1e-12)  # 500 t mm^2
    assert fe.elements["CMASS1"]["m"][0] == pytest.approx(0.7 * 2000.0, rel=1e-12)


def test_scalar_mass_parameter_unit_must_match_its_components(tmp_path):
    src = _deck(tmp_path, TWO_DOF)
    with pytest.raises(ParameterError, match="unit 'kg\\*m\\^2' is a rot mass unit, but CMASS2 5 M is a mass"):
        parameters_from_dict({"model": {"bdf": src, "units": "si"}, "parameter": [
            {"name": "m", "card": "CMASS2", "id": 5, "field": "M", "lower": -0.5, "upper": 0.5,
             "nominal": 1.0, "unit": "kg*m^2"}]})


def test_nastran_field_names_of_pelas_and_pmass_are_accepted():
    """PELAS K1 and PMASS M1 (the cards' own field names) are the table's K and M."""
    ps = parameters_from_dict({"model": {"units": "si"}, "parameter": [
        {"name": "k", "card": "pelas", "id": 1, "field": "K1", "lower": -0.1, "upper": 0.1},
        {"name": "m", "card": "PMASS", "id": 2, "field": "m1", "lower": -0.1, "upper": 0.1}]})
    assert [(q.card, q.field) for q in ps.parameters] == [("PELAS", "K"), ("PMASS", "M")]
