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
        with pytest.raises(ParameterError, match=r"parameter 'm': card CONM2 3 \(field M\) is not in the deck"):
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


# --- JSON tables and the fields a lab's own table carries (nominal, absolute bounds, unit) -------------------------
def _set(deckdir, params, model=True, name="p.json"):
    import json

    data = {"parameter": params}
    if model:
        data["model"] = {"bdf": "deck.bdf", "units": "mm-t-s"}
    path = deckdir / name
    path.write_text(json.dumps(data, indent=2))
    return read_parameters(path)


def _t(**extra):
    return dict(name="t", card="PSHELL", id=5, field="T", **extra)


def test_toml_and_json_read_to_the_same_set(deckdir):
    import json
    import tomllib

    lab = GOOD.replace('unit = "Pa"', 'unit = "GPa"\nnominal = 210.0\ndescription = "steel"').replace(
        'ids = [5]\nfield = "t"\nlower = -0.5\nupper = 0.5', 'ids = [5]\nfield = "t"\nlower_value = 1.25\nupper = 0.5')
    from_toml = read_parameters(write(deckdir, lab))
    data = tomllib.loads(lab)
    data["parameter"][2]["description"] = None  # JSON null: the key left out
    (deckdir / "p.json").write_text(json.dumps(data, indent=1))
    from_json = read_parameters(deckdir / "p.json")
    assert from_json == from_toml and from_json.source == deckdir / "p.json"
    e, t = from_toml.parameters[:2]
    assert (e.nominal, e.unit, e.description, e.lower) == (210.0, "GPa", "steel", -0.2)
    assert t.lower == -0.5 and t.lower_value == 1.25 and t.nominal == 2.5  # converted with the deck's T = 2.5 mm


@pytest.mark.parametrize("text, message", [
    ('{"parameter": [\n  {"name": "t",\n   "card": "PSHELL" "id": 5}]}', r"not valid JSON: Expecting ',' delimiter at "
                                                                         r"line 3, column 21"),
    ('{"parameter": [{"name": "t", "name": "u"}]}', "key 'name' appears twice"),
    ('[1, 2]', "must be a table .* or an object"),
    ('{"parameter": [{"name": "t", "card": "PSHELL", "id": 5, "field": "T", "upper": 0.1}]}',
     r"parameter 't': missing required key 'lower' \(or 'lower_value'"),
    ('{"parameter": [{"name": "t", "card": "PSHELL", "id": 5, "field": "T", "lower": -0.1, "upper": 0.1, '
     '"nominal_value": 2.5}]}', r"unknown key\(s\) \['nominal_value'\]"),
])
def test_bad_json_names_file_and_position(tmp_path, text, message):
    path = tmp_path / "lab.json"
    path.write_text(text)
    with pytest.raises(ParameterError, match=message) as info:
        read_parameters(path)
    assert str(path) in str(info.value)


def test_other_extensions_are_refused(tmp_path):
    (tmp_path / "p.yaml").write_text("parameter: []")
    with pytest.raises(ParameterError, match=r"p.yaml: a parameter file must be .toml or .json, not '.yaml'"):
        read_parameters(tmp_path / "p.yaml")


@pytest.mark.parametrize("field, ok", [
    # the deck is mm-t-s: E in MPa, T in mm, RHO in t/mm^3, PELAS K (translational) in N/mm
    (dict(card="MAT1", id=3, field="E", nominal=210000.0), True),               # deck units: as on the card
    (dict(card="MAT1", id=3, field="E", nominal=210.0, unit="GPa"), True),
    (dict(card="MAT1", id=3, field="E", nominal=2.1e11, unit="Pa"), True),
    (dict(card="MAT1", id=3, field="E", nominal=2.1e11), False),                 # SI without a unit: deck units meant
    (dict(card="MAT1", id=3, field="RHO", nominal=7850.0, unit="kg/m3"), True),
    (dict(card="MAT1", id=3, field="RHO", nominal=7.85e-9, unit="t/mm^3"), True),
    (dict(card="PSHELL", id=5, field="T", nominal=2.5002), True),                # 8e-5 relative: within 1e-4
    (dict(card="PSHELL", id=5, field="T", nominal=2.5003), False),               # 1.2e-4 relative
    (dict(card="PSHELL", id=5, field="T", nominal=2.5, unit="m"), False),
    (dict(card="PSHELL", id=5, field="T", nominal=0.0025, unit="m"), True),
    (dict(card="PELAS", id=11, field="K", nominal=1.23e5, unit="N/m"), True),
    (dict(card="PBUSH", id=8, field="K4", nominal=0.4, unit="N*m/rad"), True),   # 400 N mm/rad
    (dict(card="PBUSH", id=8, field="K4", nominal=0.4, unit="N m/rad"), True),
    (dict(card="MAT1", id=3, field="RHO", nominal=0.2836, unit="lb/in^3"), True),    # a US table: pound-mass
    (dict(card="CONM2", id=7, field="M", nominal=4.409, unit="lb"), True),           # 2 kg
    (dict(card="CONM2", id=7, field="M", nominal=4.409, unit="lbf*s^2/in"), False),  # 772 kg: not the pound
])
def test_nominal_is_checked_against_the_deck(deckdir, field, ok):
    prm = dict(name="x", lower=-0.1, upper=0.1, **field)
    if ok:
        assert _set(deckdir, [prm]).parameters[0].nominal == field["nominal"]
        return
    with pytest.raises(ParameterError) as info:
        _set(deckdir, [prm])
    msg = str(info.value)
    assert "parameter 'x': nominal" in msg and f"{field['card']} {field['id']} field {field['field']}" in msg
    assert "disagrees with the deck" in msg and "> 0.0001" in msg


def test_wtmass_and_the_unit_of_nominal(deckdir):
    (deckdir / "deck.bdf").write_text(DECK.replace("PARAM,WTMASS,1.", "PARAM,WTMASS,0.5"))
    rho = dict(name="rho", card="MAT1", id=3, field="RHO", lower=-0.1, upper=0.1)
    assert _set(deckdir, [dict(rho, nominal=7.85e-9)]).parameters[0].nominal == 7.85e-9  # as on the card
    assert _set(deckdir, [dict(rho, nominal=3925.0, unit="kg/m^3")]).parameters[0].nominal == 3925.0  # WTMASS applied
    with pytest.raises(ParameterError, match=r"RHO.*= 7.85e-09 \(mm-t-s\) = 3925 kg/m\^3"):
        _set(deckdir, [dict(rho, nominal=7850.0, unit="kg/m^3")])


def test_absolute_bounds_become_normalized_bounds(deckdir):
    # deck units (T = 2.5 mm on the card), nominal taken from the deck
    t = _set(deckdir, [_t(lower_value=2.0, upper_value=3.5)]).parameters[0]
    assert (t.lower, t.upper) == pytest.approx((-0.2, 0.4), rel=1e-14) and t.nominal == 2.5
    # a unit of the table's own; a normalized bound beside an agreeing absolute one is kept as written
    t = _set(deckdir, [_t(lower_value=0.002, upper_value=0.0035, upper=0.4, unit="m")]).parameters[0]
    assert (t.lower, t.upper) == (pytest.approx(-0.2, rel=1e-12), 0.4) and t.nominal == pytest.approx(0.0025)
    # no deck: the declared nominal converts them
    t = _set(deckdir, [_t(nominal=2.5, lower_value=2.0, upper_value=3.5)], model=False).parameters[0]
    assert (t.lower, t.upper) == pytest.approx((-0.2, 0.4), rel=1e-14)
    # a declared nominal is checked later, against the deck the caller reads
    ps = _set(deckdir, [_t(nominal=2.6, lower=-0.1, upper=0.1)], model=False)
    with pytest.raises(ParameterError, match=r"parameter 't': nominal = 2.6 \(deck units\) disagrees with the deck: "
                                             r"PSHELL 5 field T = 2.5"):
        nominal_values(ps, _read_deck(deckdir / "deck.bdf"), units="mm-t-s")


@pytest.mark.parametrize("extra, message", [
    (dict(lower_value=2.0, upper_value=3.5), "need 'nominal' or a deck"),
    (dict(nominal=2.5, lower_value=3.5, upper_value=2.0), r"lower_value \(3.5\) must be less than upper_value \(2.0\)"),
    (dict(nominal=2.5, lower_value=2.6, upper_value=3.0), "nominal value 2.5 .* must lie within the bounds, "
                                                          "lower_value is 2.6"),
    (dict(nominal=2.5, lower_value=2.0, lower=-0.3, upper=0.2), r"lower = -0.3 and lower_value = 2.0 \(deck units\) "
                                                                "disagree"),
    (dict(nominal=2.5, lower_value=-1.0, upper=0.2), "lower_value must be positive"),
    (dict(nominal=2.5, lower=-0.1, upper=0.1, unit="furlong"), "unit 'furlong' is not a unit of PSHELL T"),
])
def test_bad_absolute_bounds(deckdir, extra, message):
    with pytest.raises(ParameterError, match=message) as info:
        _set(deckdir, [_t(**extra)], model=False)
    assert "p.json" in str(info.value) and "parameter 't'" in str(info.value)


def test_spring_units_and_groups_need_the_deck(deckdir):
    with pytest.raises(ParameterError, match=r"unit 'N mm/rad' is a rot spring unit, but PELAS 11 K is a trans spring"):
        _set(deckdir, [dict(name="k", card="PELAS", id=11, field="K", nominal=123.0, unit="N mm/rad", lower=-0.1,
                            upper=0.1)])
    (deckdir / "deck.bdf").write_text(DECK + "PSHELL,6,3,3.0,3\nCQUAD4,2,6,1,2,3,4\n")
    group = dict(name="t", card="PSHELL", ids=[5, 6], field="T", lower_value=2.0, upper_value=3.5)
    with pytest.raises(ParameterError, match="on a group need equal deck values, but PSHELL 5 T = 2.5 and PSHELL 6 T "
                                             "= 3.0"):
        _set(deckdir, [group])
    with pytest.raises(ParameterError, match=r"nominal = 2.5 \(deck units\) disagrees with the deck: PSHELL 6 field T"):
        _set(deckdir, [dict(group, nominal=2.5)])
