"""PBAR A, I1, I2, J as calibration parameters of CBAR frames.

A CBAR's stiffness is E A (axial), E I1 and E I2 (the two bending planes)
and G J (torsion) times fixed matrices when the section has no shear factors
(Nastran's default), with pin flags condensed block by block; its mass is
rho A. The parametric model must therefore equal, to round-off, the
assembly of the deck written back at any p (the same check as every other
parameter kind), with offsets, pins, both mass formulations and mm-t-s.
"""

from __future__ import annotations

import numpy as np
import pytest

from femodel import assemble, parametric_model, read_bdf
from femodel._params import ParameterError, parameters_from_dict

# a free-free planar-ish frame: four CBARs of two PBARs, one with end offsets, one with a pin, a CONM2
FRAME = """SOL 103
CEND
BEGIN BULK
{coupmass}GRID,1,,0.,0.,0.
GRID,2,,500.,0.,0.
GRID,3,,500.,300.,0.
GRID,4,,0.,300.,40.
GRID,5,,250.,150.,20.
MAT1,1,210000.,,0.3,7.85-9
MAT1,2,70000.,26000.,0.33,2.7-9
PBAR,10,1,120.,2400.,1500.,3000.,0.
PBAR,11,2,80.,900.,1100.,1600.,0.1-6
{pbarl}CBAR,100,10,1,2,0.,0.,1.
CBAR,101,10,2,3,0.,0.,1.,,
,,,0.,0.,5.,0.,0.,5.
CBAR,102,11,3,4,0.,0.,1.,,
,,56,
CBAR,103,11,4,1,0.,0.,1.
CBAR,104,10,1,5,0.,0.,1.
CONM2,200,5,,0.002
ENDDATA
"""


def _frame(tmp_path, coupmass=False, pbarl=""):
    path = tmp_path / "frame.bdf"
    path.write_text(FRAME.format(coupmass="PARAM,COUPMASS,1\n" if coupmass else "", pbarl=pbarl))
    return path


def _params(path, extra=()):
    return parameters_from_dict({"model": {"bdf": str(path), "units": "mm-t-s"}, "parameter": [
        {"name": "A10", "card": "PBAR", "id": 10, "field": "A", "lower": -0.5, "upper": 0.5,
         "nominal": 1.2e-4, "unit": "m^2"},
        {"name": "I1_10", "card": "PBAR", "id": 10, "field": "I1", "lower": -0.5, "upper": 0.5,
         "nominal": 2400.0, "unit": "mm^4"},
        {"name": "I2_10", "card": "PBAR", "id": 10, "field": "I2", "lower": -0.5, "upper": 0.5},
        {"name": "J10", "card": "PBAR", "id": 10, "field": "J", "lower": -0.5, "upper": 0.5},
        {"name": "I1_11", "card": "PBAR", "id": 11, "field": "I1", "lower": -0.5, "upper": 0.5},
        {"name": "A11", "card": "PBAR", "id": 11, "field": "A", "lower": -0.5, "upper": 0.5},
        {"name": "E1", "card": "MAT1", "id": 1, "field": "E", "lower": -0.3, "upper": 0.3},
        *extra]})


def _rel(a, b) -> float:
    return float(abs(a - b).max() / abs(b).max())


@pytest.mark.parametrize("coupmass", [False, True], ids=["lumped", "coupled"])
def test_pbar_section_parameters_equal_the_written_back_deck(tmp_path, coupmass):
    path = _frame(tmp_path, coupmass)
    pm = parametric_model(_params(path))
    asm0 = assemble(read_bdf(path, units="mm-t-s"))
    assert _rel(pm.stiffness(np.zeros(7)), asm0.stiffness()) < 1e-14
    p = np.array([0.3, -0.2, 0.15, -0.4, 0.25, -0.1, 0.05])
    out = pm.write_bdf(tmp_path / "p.bdf", p)
    asm = assemble(read_bdf(out, units="mm-t-s"))
    assert _rel(pm.stiffness(p), asm.stiffness()) < 1e-13
    assert _rel(pm.mass(p), asm.mass()) < 1e-13
    prop = read_bdf(out, units="mm-t-s").properties["PBAR"]
    r10, r11 = prop.rows([10])[0], prop.rows([11])[0]
    assert prop["A"][r10] == pytest.approx(1.3 * 120e-6, rel=1e-12)
    assert prop["I1"][r10] == pytest.approx(0.8 * 2400e-12, rel=1e-12)
    assert prop["J"][r10] == pytest.approx(0.6 * 3000e-12, rel=1e-12)
    assert prop["I1"][r11] == pytest.approx(1.25 * 900e-12, rel=1e-12)
    # the derivative in I1 of PBAR 10 is what doubling I1 on the card adds (a hand-edited deck, not the
    # write-back), and the mass does not depend on it
    doubled = tmp_path / "doubled.bdf"
    doubled.write_text(path.read_text().replace("PBAR,10,1,120.,2400.,", "PBAR,10,1,120.,4800.,"))
    added = assemble(read_bdf(doubled, units="mm-t-s")).stiffness() - asm0.stiffness()
    assert _rel(pm.dK(np.zeros(7), 1), added) < 1e-12
    assert abs(pm.dM(np.zeros(7), 1)).max() == 0.0


def test_section_parameters_of_shear_flexible_or_pbarl_sections_are_refused(tmp_path):
    path = tmp_path / "k.bdf"
    path.write_text(FRAME.format(coupmass="", pbarl="").replace(
        "PBAR,10,1,120.,2400.,1500.,3000.,0.", "PBAR,10,1,120.,2400.,1500.,3000.,0.\n,,,,,,,,\n,0.83,0.83"))
    with pytest.raises(ParameterError, match=r"PBAR 10 has shear factors K1/K2: its bending stiffness is not a "
                                             r"monomial of A"):
        parametric_model(_params(path))
    pbarl = "PBARL,12,1,,BAR\n,10.,12.\n"
    path = _frame(tmp_path, pbarl=pbarl)
    path.write_text(path.read_text().replace("CBAR,104,10,", "CBAR,104,12,"))
    with pytest.raises(ParameterError, match=r"property 12 is a PBARL; I1 is a parameter of PBAR sections only"):
        parametric_model(_params(path, [{"name": "I12", "card": "PBAR", "id": 12, "field": "I1", "lower": -0.5,
                                         "upper": 0.5}]))


def test_section_units_are_checked(tmp_path):
    path = _frame(tmp_path)
    with pytest.raises(ParameterError, match=r"nominal = 2400.0 mm\^2 .*|unit 'mm\^2' is not a unit of PBAR I1"):
        parameters_from_dict({"model": {"bdf": str(path), "units": "mm-t-s"}, "parameter": [
            {"name": "I", "card": "PBAR", "id": 10, "field": "I1", "lower": -0.5, "upper": 0.5, "nominal": 2400.0,
             "unit": "mm^2"}]})


ROD = """BEGIN BULK
GRID,1,,0.,0.,0.
GRID,2,,300.,40.,-20.
MAT1,1,210000.,,0.3,7.85-9
{prop}
{elem}
ENDDATA
"""


def test_ctube_is_the_crod_of_its_tube_section(tmp_path):
    """CTUBE/PTUBE: A = pi/4 (OD^2 - ID^2), J = pi/32 (OD^4 - ID^4) (T blank: solid) on the rod kernel."""
    def mats(prop, elem, name):
        path = tmp_path / name
        path.write_text(ROD.format(prop=prop, elem=elem))
        asm = assemble(read_bdf(path, units="mm-t-s"))
        return asm.stiffness_g().toarray(), asm.mass_g().toarray()

    od, t = 20.0, 2.0
    di = od - 2 * t
    area, tors = np.pi / 4 * (od**2 - di**2), np.pi / 32 * (od**4 - di**4)
    K1, M1 = mats(f"PTUBE,7,1,{od},{t},1.-7", "CTUBE,9,7,1,2", "tube.bdf")
    K2, M2 = mats(f"PROD,7,1,{area!r},{tors!r},,1.-7", "CROD,9,7,1,2", "rod.bdf")
    assert np.abs(K1).max() > 0
    np.testing.assert_allclose(K1, K2, rtol=0, atol=1e-12 * np.abs(K2).max())
    np.testing.assert_allclose(M1, M2, rtol=0, atol=1e-12 * np.abs(M2).max())
    Ks, _ = mats(f"PTUBE,7,1,{od}", "CTUBE,9,7,1,2", "solid.bdf")  # T blank: a solid rod of diameter OD
    Kr, _ = mats(f"PROD,7,1,{np.pi / 4 * od**2!r},{np.pi / 32 * od**4!r}", "CROD,9,7,1,2", "solidrod.bdf")
    np.testing.assert_allclose(Ks, Kr, rtol=0, atol=1e-12 * np.abs(Kr).max())
    from femodel import ModelError

    with pytest.raises(ModelError, match="PTUBE 7: a tapered tube"):
        mats(f"PTUBE,7,1,{od},{t},,{od + 4}", "CTUBE,9,7,1,2", "taper.bdf")


def test_prod_area_and_torsion_constant_are_parameters(tmp_path):
    """PROD A (axial E A, mass rho A) and J (G J): the parametric model equals the written-back deck."""
    path = tmp_path / "truss.bdf"
    path.write_text("""BEGIN BULK
GRID,1,,0.,0.,0.
GRID,2,,300.,0.,0.
GRID,3,,150.,200.,30.
GRID,4,,150.,-100.,250.
MAT1,1,210000.,,0.3,7.85-9
PROD,5,1,50.,400.
PROD,6,1,80.,900.
CROD,10,5,1,2
CROD,11,5,2,3
CROD,12,6,3,1
CROD,13,6,1,4
CROD,14,5,2,4
CROD,15,6,3,4
CONM2,20,4,,0.001
ENDDATA
""")
    ps = parameters_from_dict({"model": {"bdf": str(path), "units": "mm-t-s"}, "parameter": [
        {"name": "A5", "card": "PROD", "id": 5, "field": "A", "lower": -0.5, "upper": 0.5, "nominal": 50.0,
         "unit": "mm^2"},
        {"name": "J6", "card": "PROD", "id": 6, "field": "J", "lower": -0.5, "upper": 0.5},
        {"name": "A6", "card": "PROD", "id": 6, "field": "A", "lower": -0.5, "upper": 0.5}]})
    pm = parametric_model(ps)
    p = np.array([0.3, -0.25, 0.2])
    asm = assemble(read_bdf(pm.write_bdf(tmp_path / "p.bdf", p), units="mm-t-s"))
    assert _rel(pm.stiffness(p), asm.stiffness()) < 1e-13
    assert _rel(pm.mass(p), asm.mass()) < 1e-13
    assert read_bdf(tmp_path / "p.bdf", units="mm-t-s").properties["PROD"]["A"][0] == pytest.approx(65e-6, rel=1e-12)
