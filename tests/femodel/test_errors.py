"""Bad input gets one clear ModelError naming the file, card and id."""

from __future__ import annotations

import warnings

import pytest

import femodel

BASE = "BEGIN BULK\nMAT1,1,2.e11,,0.3,7800.\nPBAR,1,1,1.e-3,1.e-7,1.e-7,2.e-7\nGRID,1,,0.,0.,0.\nGRID,2,,1.,0.,0.\n"


def _deck(tmp_path, body, name="d.bdf"):
    p = tmp_path / name
    p.write_text(BASE + body + "ENDDATA\n")
    return p


def test_unsupported_cards_listed_once_with_counts(tmp_path):
    body = (
        "CBAR,1,1,1,2,0.,1.,0.\nGRID,3,,0.,1.,0.\nGRID,4,,1.,1.,0.\nGRID,5,,0.5,0.5,0.\n"
        "CQUAD8,10,7,1,2,4,3\nCQUAD8,11,7,1,2,4,3\nPSHELL,7,1,0.01,1\n"
        "CDAMP2,5,1.,1,1,2,1\n"
    )
    p = _deck(tmp_path, body)
    with pytest.raises(femodel.ModelError) as exc:
        femodel.read_bdf(p)
    msg = str(exc.value)
    assert "CQUAD8 x2" in msg and "CDAMP2 x1" in msg and str(p) in msg
    assert msg.count("unsupported card types") == 1
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        model = femodel.read_bdf(p, allow_unsupported=True)
    assert any("CQUAD8 x2" in str(x.message) for x in w)
    assert model.ignored_cards["CQUAD8"] == 2
    assert len(model.elements["CBAR"]) == 1


def test_neutral_cards_are_accepted(tmp_path):
    p = _deck(tmp_path, "CBAR,1,1,1,2,0.,1.,0.\nEIGRL,1,,,5\nFORCE,3,2,,1.,0.,0.,1.\nPARAM,POST,-1\n")
    assert len(femodel.read_bdf(p).elements["CBAR"]) == 1


def test_missing_property_names_card_id_element_and_file(tmp_path):
    p = _deck(tmp_path, "CBAR,7,99,1,2,0.,1.,0.\n")
    model = femodel.read_bdf(p)
    with pytest.raises(femodel.ModelError, match=r"CBAR.*99") as exc:
        femodel.assemble(model)
    msg = str(exc.value)
    assert "by element(s) [7]" in msg and msg.endswith(f"in {p}")


def test_missing_grid_names_element(tmp_path):
    p = _deck(tmp_path, "CBAR,7,1,1,42,0.,1.,0.\n")
    with pytest.raises(femodel.ModelError, match=r"CBAR 7 .*GRID 42"):
        femodel.read_bdf(p)


def test_orientation_parallel_to_axis(tmp_path):
    p = _deck(tmp_path, "CBAR,8,1,1,2,1.,0.,0.\n")
    with pytest.raises(femodel.ModelError, match=r"CBAR \[8\].*parallel"):
        femodel.assemble(femodel.read_bdf(p))


def test_missing_material(tmp_path):
    p = tmp_path / "m.bdf"
    p.write_text("BEGIN BULK\nPROD,1,5,1.e-4\nGRID,1,,0.,0.,0.\nGRID,2,,1.,0.,0.\nCROD,3,1,1,2\nENDDATA\n")
    with pytest.raises(femodel.ModelError, match=r"MAT1.*5"):
        femodel.assemble(femodel.read_bdf(p))


def test_spc_on_rbe2_dependent_dof(tmp_path):
    p = _deck(tmp_path, "CBAR,1,1,1,2,0.,1.,0.\nGRID,3,,2.,0.,0.\nRBE2,9,2,123456,3\nSPC1,1,1,3\n")
    with pytest.raises(femodel.ModelError, match=r"SPC on DOF that rigid elements make dependent.*\(3, 1\)"):
        femodel.assemble(femodel.read_bdf(p))


def test_dof_dependent_twice(tmp_path):
    p = _deck(tmp_path, "CBAR,1,1,1,2,0.,1.,0.\nGRID,3,,2.,0.,0.\nRBE2,9,2,123456,3\nRBE2,10,1,123,3\n")
    with pytest.raises(femodel.ModelError, match=r"GRID 3 .*RBE2 9.*RBE2 10"):
        femodel.assemble(femodel.read_bdf(p))


def test_unknown_units_and_missing_file(tmp_path):
    p = _deck(tmp_path, "CBAR,1,1,1,2,0.,1.,0.\n")
    with pytest.raises(femodel.ModelError, match="furlongs"):
        femodel.read_bdf(p, units="furlongs")
    with pytest.raises(OSError, match="nothere"):
        femodel.read_bdf(tmp_path / "nothere.bdf")


def test_bad_field_is_reported_with_file(tmp_path):
    p = _deck(tmp_path, "CBAR,1,1,1,2,abc,1.,0.\n")
    with pytest.raises(femodel.ModelError, match=r"d\.bdf"):
        femodel.read_bdf(p)


def test_circular_cord1_names_the_file_and_systems(tmp_path):
    """CORD1R 7 on grids positioned in CORD1R 7 itself can never be resolved."""
    p = _deck(tmp_path, "GRID,10,7,0.,0.,0.\nGRID,11,7,0.,0.,1.\nGRID,12,,1.,0.,0.\nCORD1R,7,10,11,12\n")
    with pytest.raises(femodel.ModelError, match=r"d\.bdf: coordinate systems \[7\] cannot be resolved"):
        femodel.read_bdf(p)


def test_rejected_cards_are_counted_never_zero(tmp_path):
    """pyNastran holds RADLST (no converter of its own) as rejected raw cards; both are listed."""
    from femodel._reader import card_counts

    p = _deck(tmp_path, "CBAR,1,1,1,2,0.,1.,0.\nRADLST,1,2,3\nRADLST,2,2,3\n")
    with pytest.raises(femodel.ModelError, match=r"unsupported card types: RADLST x2 "):
        femodel.read_bdf(p)
    # counted once whether or not pyNastran's own count has them
    assert card_counts({"GRID": 2}, [["RADLST", "1"], ["radlst*", "2"]]) == {"GRID": 2, "RADLST": 2}
    assert card_counts({"GRID": 2, "RADLST": 2}, [["RADLST", "1"], ["RADLST", "2"]]) == {"GRID": 2, "RADLST": 2}


def test_a_parse_error_is_one_line_and_prints_nothing(tmp_path, capfd):
    # A PELAS and a PBUSH sharing id 21 (one property id space in Nastran): pyNastran printed its
    # multi-line report on stdout too, which broke `frfcal modes --json` (stdout is one JSON object)
    from frfcal.cli import main

    p = _deck(tmp_path, "PELAS,21,300.\nPBUSH,21,K,800.\nCELAS1,5,21,1,3,2,3\n")
    with pytest.raises(femodel.ModelError) as exc:
        femodel.read_bdf(p)
    msg = str(exc.value)
    assert "\n" not in msg and "not unique=[21]" in msg and str(p) in msg
    capfd.readouterr()
    assert main(["modes", str(p), "--json"]) == 2
    out, err = capfd.readouterr()
    assert out == "" and err.count("\n") == 1 and "not unique" in err
