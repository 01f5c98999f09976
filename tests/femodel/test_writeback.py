"""Write-back: new values in the deck exactly, everything else unchanged."""

from __future__ import annotations

import numpy as np
import pytest

from femodel._params import ParameterError, read_parameters
from femodel._writeback import _read_deck, free_field_card, write_bdf
from tests.femodel.test_params import DECK, GOOD


@pytest.fixture
def deckdir(tmp_path):
    (tmp_path / "deck.bdf").write_text(DECK)
    (tmp_path / "p.toml").write_text(GOOD)
    return tmp_path


def test_values_round_trip_exactly_and_rest_unchanged(deckdir):
    ps = read_parameters(deckdir / "p.toml")
    new = {"E": 2.2345678901234567e11, "t": 2.6789012345678901e-3, "m": 2.3456789e0,
           "kb": 0.41234567890123, "ke": 1.3e5, "kr": 0.05}
    out = write_bdf(ps.bdf, deckdir / "out.bdf", new, parameters=ps,
                    added_cards=[["CONM2", 99, 4, 0, 0.0123456789012345678], "$ a comment"])
    a, b = _read_deck(ps.bdf), _read_deck(out)
    # deck units: mm-t-s; SI -> deck division is the only rounding (one ulp)
    assert b.materials[3].e == pytest.approx(new["E"] / 1e6, rel=2e-16)
    assert b.properties[5].t == pytest.approx(new["t"] / 1e-3, rel=2e-16)
    assert b.masses[7].mass == pytest.approx(new["m"] / 1e3, rel=2e-16)
    assert b.properties[8].Ki[3] == pytest.approx(new["kb"] / 1e-3, rel=2e-16)
    assert b.properties[11].k == pytest.approx(new["ke"] / 1e3, rel=2e-16)
    assert b.elements[13].k == pytest.approx(new["kr"] / 1e-3, rel=2e-16)
    assert b.masses[99].mass == 0.0123456789012345678  # field lists are exact
    # G was blank: it stays blank so it follows the new E
    mat1 = [ln for ln in out.read_text().splitlines() if ln.startswith("MAT1,3,")][0]
    assert mat1.split(",")[3] == ""
    assert b.materials[3].g == pytest.approx(b.materials[3].e / 2.6, rel=1e-15)
    # Z1, Z2 were blank (-T/2, T/2): they stay blank, following the new T, not the old T's fibres (outside
    # trial, stop 33: written as explicit -1.0e-3/1.0e-3 beside a new T)
    pshell = [ln for ln in out.read_text().splitlines() if ln.startswith("PSHELL,5,")][0].split(",")
    assert pshell[6:9] == ["", "", ""][: len(pshell[6:9])]
    assert (b.properties[5].z1, b.properties[5].z2) == (-b.properties[5].t / 2, b.properties[5].t / 2)
    # everything else identical
    for nid, n in a.nodes.items():
        np.testing.assert_array_equal(n.xyz, b.nodes[nid].xyz)
    assert b.materials[3].rho == a.materials[3].rho and b.materials[3].nu == a.materials[3].nu
    assert [b.properties[8].Ki[i] for i in (0, 1, 2, 4, 5)] == [a.properties[8].Ki[i] for i in (0, 1, 2, 4, 5)]
    assert sorted(b.elements) == sorted(a.elements)
    assert sorted(set(b.card_count) - {"ENDDATA"}) == sorted(set(a.card_count) - {"ENDDATA"})


def test_exact_write_of_si_deck_is_bitwise(tmp_path):
    (tmp_path / "d.bdf").write_text(DECK.replace("210000.", "2.1+11"))
    v = 2.2345678901234567e11
    out = write_bdf(tmp_path / "d.bdf", tmp_path / "o.bdf", {("MAT1", 3, "E"): v}, units="si")
    assert _read_deck(out).materials[3].e == v


def test_group_scales_all_cards_by_one_factor(tmp_path):
    deck = DECK + "PSHELL,6,3,4.0,3\nCQUAD4,2,6,1,2,3,4\n"
    (tmp_path / "d.bdf").write_text(deck)
    (tmp_path / "p.toml").write_text(
        '[model]\nbdf = "d.bdf"\nunits = "mm-t-s"\n[[parameter]]\nname = "t"\ncard = "PSHELL"\n'
        'ids = [5, 6]\nfield = "T"\nlower = -0.5\nupper = 0.5\n'
    )
    ps = read_parameters(tmp_path / "p.toml")
    out = write_bdf(ps.bdf, tmp_path / "o.bdf", {"t": 3.0e-3}, parameters=ps)
    b = _read_deck(out)
    assert b.properties[5].t == pytest.approx(3.0, rel=1e-15)
    assert b.properties[6].t == pytest.approx(4.0 * 1.2, rel=1e-15)


def test_bad_write_requests(deckdir):
    ps = read_parameters(deckdir / "p.toml")
    with pytest.raises(ParameterError, match="no parameter named 'nope'"):
        write_bdf(ps.bdf, deckdir / "o.bdf", {"nope": 1.0}, parameters=ps)
    with pytest.raises(ParameterError, match="must be positive"):
        write_bdf(ps.bdf, deckdir / "o.bdf", {"t": -1e-3}, parameters=ps)
    with pytest.raises(ParameterError, match="PSHELL 77 .*not in the deck"):
        write_bdf(ps.bdf, deckdir / "o.bdf", {("PSHELL", 77, "T"): 1e-3}, units="mm-t-s")
    with pytest.raises(ParameterError, match="needs parameters"):
        write_bdf(ps.bdf, deckdir / "o.bdf", {"t": 1e-3})
    with pytest.raises(ParameterError, match="first field must be the card name"):
        write_bdf(ps.bdf, deckdir / "o.bdf", {}, added_cards=[[1, 2, 3]])
    with pytest.raises(FileNotFoundError):
        write_bdf(deckdir / "missing.bdf", deckdir / "o.bdf", {})


def test_free_field_card_layout_reads_back(tmp_path):
    text = free_field_card(["PBUSH", 7, "K", 1.0000000000000002, 2.0, None, 4.0, 5.5e-300, 6.0])
    (tmp_path / "c.bdf").write_text("GRID,1,,0.,0.,0.\n" + text)
    b = _read_deck(tmp_path / "c.bdf")
    assert b.properties[7].Ki[0] == 1.0000000000000002
    assert b.properties[7].Ki[4] == 5.5e-300
    long = free_field_card(["RBE3", 5, None, 1, "123456", 1.0, "123"] + list(range(2, 30)))
    assert all(len(line.split(",")) <= 9 for line in long.splitlines())


def test_free_field_reals_round_trip_bitwise(tmp_path):
    """Any finite double written by the free-field writer reads back as the same double."""
    rng = np.random.default_rng(11)
    values = np.concatenate([
        10.0 ** rng.uniform(-300, 300, 40) * rng.choice([-1.0, 1.0], 40),
        rng.uniform(0, 1, 20),
        [np.nextafter(2.1e11, 3e11), 5e-324, 1.7976931348623157e308, 0.1 + 0.2, 1.0 / 3.0],
    ])
    cards = "".join(free_field_card(["CONM2", 100 + i, 1, 0, float(v)]) for i, v in enumerate(values))
    (tmp_path / "c.bdf").write_text("GRID,1,,0.,0.,0.\n" + cards)
    b = _read_deck(tmp_path / "c.bdf")
    got = np.array([b.masses[100 + i].mass for i in range(len(values))])
    np.testing.assert_array_equal(got, values)


def test_include_structure_is_kept(tmp_path):
    src = tmp_path / "src"
    (src / "parts").mkdir(parents=True)
    (src / "main.bdf").write_text(
        "SOL 103\nCEND\nBEGIN BULK\nINCLUDE 'parts/geom.inc'\nMAT1,3,210000.,,0.3,7.85-9\nPSHELL,5,3,2.5,3,,3\nENDDATA\n"
    )
    (src / "parts" / "geom.inc").write_text(
        "GRID,1,,0.,0.,0.\nGRID,2,,1.,0.,0.\nGRID,3,,1.,1.,0.\nGRID,4,,0.,1.,0.\nCQUAD4,1,5,1,2,3,4\n"
    )
    out = write_bdf(src / "main.bdf", tmp_path / "out" / "main.bdf", {("PSHELL", 5, "T"): 3.1e-3}, units="mm-t-s")
    text = out.read_text()
    assert "INCLUDE 'parts/geom.inc'" in text and "GRID" not in text.split("INCLUDE")[0]
    assert (tmp_path / "out" / "parts" / "geom.inc").is_file()
    b = _read_deck(out)
    assert len(b.nodes) == 4 and b.properties[5].t == pytest.approx(3.1, rel=1e-15)
    # writing beside the source would overwrite the include: flattened instead
    flat = write_bdf(src / "main.bdf", src / "new.bdf", {}, units="mm-t-s")
    assert "\nINCLUDE" not in flat.read_text() and len(_read_deck(flat).nodes) == 4
    assert (src / "parts" / "geom.inc").read_text().startswith("GRID,1,,0.")
    # asked to flatten
    flat2 = write_bdf(src / "main.bdf", tmp_path / "flat" / "m.bdf", {}, units="mm-t-s", keep_includes=False)
    assert "\nINCLUDE" not in flat2.read_text()
