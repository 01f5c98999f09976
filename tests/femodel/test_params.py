"""Parameter file: parsing, strict validation, nominal values from a deck."""

from __future__ import annotations

import textwrap

import numpy as np
import pytest

from femodel._params import ParameterError, nominal_values, read_parameters
from femodel._writeback import _read_deck

DECK = """\
GRID,1,,0.,0.,0.
GRID,2,,1.,0.,0.
GRID,3,,1.,1.,0.
GRID,4,,0.,1.,0.
MAT1,3,210000.,,0.3,7.85-9
PSHELL,5,3,2.5,3
CQUAD4,1,5,1,2,3,4
CONM2,7,3,,0.002
PBUSH,8,K,10.,20.,30.,400.,500.,600.
CBUSH,9,8,1,2,,,,0
PELAS,11,123.
CELAS1,12,11,3,3,4,3
CELAS2,13,45.,1,5,2,5
PARAM,WTMASS,1.
"""

GOOD = """\
[model]
bdf = "deck.bdf"
units = "mm-t-s"

[[parameter]]
name = "E"
card = "MAT1"
id = 3
field = "E"
lower = -0.2
upper = 0.2
unit = "Pa"

[[parameter]]
name = "t"
card = "pshell"
ids = [5]
field = "t"
lower = -0.5
upper = 0.5

[[parameter]]
name = "m"
card = "CONM2"
id = 7
field = "M"
lower = -0.5
upper = 0.5

[[parameter]]
name = "kb"
card = "PBUSH"
id = 8
field = "K4"
lower = -0.5
upper = 0.5

[[parameter]]
name = "ke"
card = "PELAS"
id = 11
field = "K"
lower = -0.5
upper = 0.5

[[parameter]]
name = "kr"
card = "CELAS2"
id = 13
field = "K"
lower = -0.5
upper = 0.5
"""


@pytest.fixture
def deckdir(tmp_path):
    (tmp_path / "deck.bdf").write_text(DECK)
    return tmp_path


def write(tmp_path, text, name="p.toml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def test_good_file_and_si_nominal_values(deckdir):
    ps = read_parameters(write(deckdir, GOOD))
    assert ps.names == ("E", "t", "m", "kb", "ke", "kr")
    assert ps.units == "mm-t-s" and ps.bdf == deckdir / "deck.bdf"
    assert ps.parameters[1].card == "PSHELL" and ps.parameters[1].field == "T"
    np.testing.assert_array_equal(ps.lower, [-0.2, -0.5, -0.5, -0.5, -0.5, -0.5])
    p0 = nominal_values(ps, _read_deck(ps.bdf))
    # MPa -> Pa, mm -> m, t -> kg, N mm/rad -> N m/rad (K4), N/mm -> N/m, N mm/rad -> N m/rad
    expected = [210e9, 2.5e-3, 2.0, 400.0 * 1e-3, 123.0 * 1e3, 45.0 * 1e-3]
    np.testing.assert_allclose([v[0] for v in p0], expected, rtol=1e-14)


def test_wtmass_scales_mass_fields(deckdir):
    (deckdir / "deck.bdf").write_text(DECK.replace("PARAM,WTMASS,1.", "PARAM,WTMASS,0.5"))
    ps = read_parameters(write(deckdir, GOOD))
    p0 = nominal_values(ps, _read_deck(ps.bdf))
    assert p0[2][0] == pytest.approx(1.0, rel=1e-14)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda s: s.replace('unit = "Pa"', 'unit = "Pa"\ncolour = "red"'), "unknown key(s) ['colour']"),
        (lambda s: s.replace('name = "t"', 'name = "E"'), "duplicate parameter name 'E'"),
        (lambda s: s.replace("lower = -0.2", "lower = 0.3"), "lower (0.3) must be less than upper"),
        (lambda s: s.replace("lower = -0.5\nupper = 0.5\n\n[[parameter]]\nname = \"m\"",
                             "lower = -1.0\nupper = 0.5\n\n[[parameter]]\nname = \"m\""), "non-positive"),
        (lambda s: s.replace('field = "t"', 'field = "NSM"'), "PSHELL field NSM cannot be parameterized"),
        (lambda s: s.replace("ids = [5]", "id = 5\nids = [5]"), "exactly one of 'id' or 'ids'"),
        (lambda s: s.replace('units = "mm-t-s"', 'units = "furlong"'), "units must be one of"),
        (lambda s: s.replace("id = 7", "id = 3"), None),  # CONM2 3 missing: caught against the deck
        (lambda s: s.replace("[model]", "[modle]"), "unknown top-level key(s) ['modle']"),
        (lambda s: s.replace("lower = 0.5", "lower = 0.5") .replace("upper = 0.2", "upper = 0.2\nlower2 = 1"), "unknown key"),
        (lambda s: s + "\n[[parameter]]\nname = \"E2\"\ncard = \"MAT1\"\nid = 3\nfield = \"E\"\nlower = -0.1\nupper = 0.1\n",
         "parameters 'E' and 'E2' both scale MAT1 3 field E"),
        (lambda s: s.replace("lower = -0.2", "lower = 0.1"), "nominal point p = 0"),
        (lambda s: s.replace("upper = 0.2", "upper = 0.2 x"), "not valid TOML"),
    ],
)
def test_bad_files_name_file_and_parameter(deckdir, edit, message):
    path = write(deckdir, edit(GOOD))
    if message is None:
        ps = read_parameters(path)
        with pytest.raises(ParameterError, match=r"card CONM2 3 \(field M\) is not in the deck"):
            nominal_values(ps, _read_deck(ps.bdf))
        return
    with pytest.raises(ParameterError) as info:
        read_parameters(path)
    assert str(path) in str(info.value)
    assert message in str(info.value)


def test_missing_card_and_wrong_type_against_deck(deckdir):
    ps = read_parameters(write(deckdir, GOOD.replace("ids = [5]", "ids = [5, 6]")))
    with pytest.raises(ParameterError, match=r"card PSHELL 6 \(field T\) is not in the deck"):
        nominal_values(ps, _read_deck(ps.bdf))
    ps = read_parameters(write(deckdir, GOOD.replace("id = 8\n", "id = 11\n")))
    with pytest.raises(ParameterError, match=r"PBUSH 11 .*is a PELAS"):
        nominal_values(ps, _read_deck(ps.bdf))


def test_zero_nominal_value_is_an_error(deckdir):
    (deckdir / "deck.bdf").write_text(DECK.replace("PELAS,11,123.", "PELAS,11,0."))
    ps = read_parameters(write(deckdir, GOOD))
    with pytest.raises(ParameterError, match="parameter 'ke'.*positive nominal value"):
        nominal_values(ps, _read_deck(ps.bdf))


def test_missing_file_is_a_clear_error(tmp_path):
    with pytest.raises(ParameterError, match="cannot read parameter file"):
        read_parameters(tmp_path / "nope.toml")
