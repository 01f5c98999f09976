"""The layout file: one reader and one writer, its defaults, and an error that names file and field for every rule."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from labdata import (
    LayoutChannel,
    LayoutError,
    layout_document,
    layout_from_dict,
    read_layout_file,
    write_layout_file,
)

DOC = {
    "format": "frfcal-layout", "version": 1, "model": {"path": "deck/m.bdf", "units": "mm-t-s"},
    "channels": [
        {"name": "acc1", "role": "response", "quantity": "acceleration", "unit": "m/s^2", "grid": 11,
         "direction": [0, 3, 4], "xyz_m": [0.1, 0.0, 0.0]},
        {"name": "acc2", "grid": 12, "direction": [0, 0, -2]},
    ],
    "drives": [{"name": "drive1", "role": "force", "quantity": "force", "unit": "N", "grid": 11,
                "direction": [1, 0, 0], "xyz_m": [0.1, 0.0, 0.0], "sensitivity_v_per_unit": 0.0225}],
    "target_modes_hz": [120.5, 240.0],
    "metrics": {"fim_condition": 12.5, "something_new": [1, 2]},
}


def _write(tmp_path, doc, name="layout.json") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(doc))
    return path


def test_read_defaults_normalization_and_model_path(tmp_path):
    lay = read_layout_file(_write(tmp_path, DOC))
    a1, a2 = lay.channels
    # directions become unit vectors: (0, 3, 4)/5 and (0, 0, -1)
    assert a1.direction == (0.0, 0.6, 0.8) and a2.direction == (0.0, 0.0, -1.0)
    # an entry with only name, grid, direction takes the response defaults
    assert (a2.role, a2.quantity, a2.unit) == ("response", "acceleration", "m/s^2")
    assert all(math.isnan(v) for v in a2.xyz_m) and a2.sensitivity_v_per_unit is None
    assert lay.drives[0].sensitivity_v_per_unit == 0.0225 and lay.drives[0].role == "force"
    # the model path is resolved against the layout's folder, units as written
    assert lay.model_path == str((tmp_path / "deck" / "m.bdf").resolve()) and lay.model_units == "mm-t-s"
    np.testing.assert_array_equal(lay.grids(), [11, 12])
    np.testing.assert_array_equal(lay.grids("drives"), [11])
    np.testing.assert_allclose(lay.directions(), [[0, 0.6, 0.8], [0, 0, -1]])
    assert lay.names() == ("acc1", "acc2") and lay.names("drives") == ("drive1",)
    np.testing.assert_array_equal(lay.target_modes_hz, [120.5, 240.0])
    assert lay.metrics["something_new"] == [1, 2]  # unknown metrics are kept, not interpreted


def test_minimal_file_is_valid(tmp_path):
    """Only format, version and channels (name, grid, direction) are required (docs/layout.md)."""
    doc = {"format": "frfcal-layout", "version": 1, "channels": [{"name": "a", "grid": 5, "direction": [1, 0, 0]}]}
    lay = read_layout_file(_write(tmp_path, doc))
    assert lay.drives == () and lay.model_path is None and lay.model_units is None
    assert lay.target_modes_hz.shape == (0,) and lay.metrics == {}


def test_write_read_round_trip(tmp_path):
    ch = [LayoutChannel("acc01x", "response", "acceleration", "m/s^2", 7, (1.0, 0.0, 0.0), (0.5, 0.25, 0.0)),
          LayoutChannel("vel02", "response", "velocity", "m/s", 8, (0.0, 1.0, 0.0), (0.0, 0.0, 0.125)),
          LayoutChannel("mon", "monitor", "voltage", "V", 9, (0.0, 0.0, 1.0), range_v=5.0, physical="ai7")]
    dr = [LayoutChannel("drive1", "force", "force", "N", 7, (0.0, 0.0, -1.0), (0.5, 0.25, 0.0), serial="F123")]
    model = tmp_path / "models" / "plate.bdf"
    out = tmp_path / "run" / "layout.json"
    doc = layout_document(ch, dr, model_path=model, units="si", target_modes_hz=np.array([10.0, 20.0]),
                          metrics={"n_channels": 3}, relative_to=out.parent)
    assert doc["model"]["path"] == str(Path("..") / "models" / "plate.bdf")  # stored relative to the file
    assert "xyz_m" not in doc["channels"][2]  # unknown position is omitted, not written as NaN
    write_layout_file(out, doc)
    back = read_layout_file(out)
    assert back.model_path == str(model.resolve()) and back.model_units == "si"
    assert back.channels[:2] == tuple(ch[:2]) and back.drives == tuple(dr)
    assert back.channels[2].range_v == 5.0 and back.channels[2].physical == "ai7"
    assert json.loads(out.read_text()) == doc


def test_writer_refuses_an_invalid_document_and_writes_nothing(tmp_path):
    doc = layout_document([LayoutChannel("a", "response", "acceleration", "m/s^2", 3, (0.0, 0.0, 0.0))])
    out = tmp_path / "sub" / "bad.json"
    with pytest.raises(LayoutError, match=r"bad\.json: channels\[0\] \(a\): 'direction' is the zero vector"):
        write_layout_file(out, doc)
    assert not out.exists()


def _set(key, value):
    return lambda d: d.update({key: value})


def _entry(k, key, value, where="channels"):
    return lambda d: d[where][k].update({key: value})


def _drop(k, key, where="channels"):
    return lambda d: d[where][k].pop(key)


CASES = [
    (_set("format", "frfcal-run"), r"'format' must be 'frfcal-layout'"),
    (_set("version", 2), r"'version' is 2, this reader knows 1"),
    (_set("version", True), r"'version' is True"),
    (_set("channels", []), r"'channels' must be a non-empty list"),
    (lambda d: d.pop("channels"), r"'channels' must be a non-empty list"),
    (_set("drives", {"name": "d"}), r"'drives' must be a list"),
    (lambda d: d["channels"].append(3), r"channels\[2\] must be an object, got int"),
    (_drop(0, "name"), r"channels\[0\] has no 'name'"),
    (_entry(1, "name", ""), r"channels\[1\] has no 'name'"),
    (_entry(0, "role", "force"), r"channels\[0\] \(acc1\): 'role' must be one of \['response', 'monitor'\]"),
    (_entry(0, "role", "response", "drives"), r"drives\[0\] \(drive1\): 'role' must be one of \['force'\]"),
    (_entry(0, "quantity", "strain"), r"channels\[0\] \(acc1\): unknown quantity 'strain'"),
    (_entry(0, "quantity", "force"), r"channels\[0\] \(acc1\): unknown quantity 'force' for role 'response'"),
    (_entry(0, "unit", "g"), r"channels\[0\] \(acc1\): unit 'g' is not the SI unit 'm/s\^2' of acceleration"),
    (_entry(0, "quantity", "velocity"), r"unit 'm/s\^2' is not the SI unit 'm/s' of velocity"),
    (_drop(0, "grid", "drives"), r"drives\[0\] \(drive1\): 'grid' is missing"),
    (_entry(0, "grid", 0), r"channels\[0\] \(acc1\): 'grid' must be a Nastran grid id \(integer >= 1\), got 0"),
    (_entry(0, "grid", 11.5), r"'grid' must be a Nastran grid id .* got 11\.5"),
    (_entry(0, "grid", True), r"'grid' must be a Nastran grid id .* got True"),
    (_entry(0, "grid", "G11"), r"'grid' must be a Nastran grid id .* got 'G11'"),
    (_drop(1, "direction"), r"channels\[1\] \(acc2\): 'direction' is missing"),
    (_entry(1, "direction", [0, 0, 0]), r"channels\[1\] \(acc2\): 'direction' is the zero vector"),
    (_entry(1, "direction", [0, 1]), r"channels\[1\] \(acc2\): 'direction' must be 3 finite numbers, got \[0, 1\]"),
    (_entry(1, "direction", [0, float("nan"), 1]), r"'direction' must be 3 finite numbers"),
    (_entry(1, "direction", ["0", "0", "1"]), r"'direction' must be 3 finite numbers"),
    (_entry(0, "xyz_m", [0.1, 0.2]), r"channels\[0\] \(acc1\): 'xyz_m' must be 3 finite numbers"),
    (_entry(0, "sensitivity_v_per_unit", -0.01, "drives"),
     r"drives\[0\] \(drive1\): 'sensitivity_v_per_unit' must be a finite number > 0, got -0\.01"),
    (_entry(0, "range_v", 0), r"'range_v' must be a finite number > 0"),
    (_entry(0, "iepe_current_a", -0.004), r"'iepe_current_a' must be a finite number >= 0"),
    (_entry(0, "serial", 123), r"channels\[0\] \(acc1\): 'serial' must be a string, got 123"),
    (_entry(0, "name", "acc1", "drives"), r"duplicate channel names \['acc1'\]"),
    (_set("model", ["m.bdf"]), r"'model' must be an object"),
    (_set("model", {"path": 5}), r"'model\.path' must be a non-empty string or null, got 5"),
    (_set("model", {"units": ""}), r"'model\.units' must be a non-empty string or null"),
    (_set("target_modes_hz", [100.0, "x"]), r"'target_modes_hz' must be a list of finite numbers \(Hz\)"),
    (_set("metrics", [1, 2]), r"'metrics' must be an object, got list"),
]


@pytest.mark.parametrize("change, message", CASES, ids=[m[:40] for _, m in CASES])
def test_every_rule_has_an_error_naming_file_and_field(tmp_path, change, message):
    doc = json.loads(json.dumps(DOC))
    change(doc)
    path = _write(tmp_path, doc, "broken.json")
    with pytest.raises(LayoutError, match=message) as info:
        read_layout_file(path)
    assert str(info.value).startswith(f"{path}: ")
    # the dictionary form applies the same rules
    with pytest.raises(LayoutError, match=message):
        layout_from_dict(doc, path)


def test_file_level_errors(tmp_path):
    with pytest.raises(LayoutError, match=r"nowhere\.json: layout file not found"):
        read_layout_file(tmp_path / "nowhere.json")
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "frfcal-layout",')
    with pytest.raises(LayoutError, match=r"bad\.json: not valid JSON"):
        read_layout_file(bad)
    with pytest.raises(LayoutError, match=r"<layout>: 'format'"):
        layout_from_dict([1, 2])


def test_tolerated_forms_stay_valid(tmp_path):
    """Files both old readers accepted keep reading the same way."""
    doc = json.loads(json.dumps(DOC))
    doc["channels"][0]["grid"] = 11.0  # integral float
    doc["channels"][1]["grid"] = "12"  # digits in a string
    doc["model"] = None
    doc.pop("target_modes_hz")
    lay = read_layout_file(_write(tmp_path, doc))
    assert lay.grids().tolist() == [11, 12] and lay.model_path is None


def test_layers_share_the_one_reader(tmp_path):
    import acquisition
    import pretest

    assert pretest.LayoutChannel is LayoutChannel and acquisition.LayoutError is LayoutError
    path = _write(tmp_path, DOC)
    p, a = pretest.read_layout(path), acquisition.read_layout(path)
    assert [c.name for c in a.sensors] == list(p.names()) and a.drives[0].grid == p.drives[0].grid == 11
    assert a.sensors[0].direction == p.channels[0].direction == (0.0, 0.6, 0.8)
    assert a.drives[0].sensitivity == 0.0225 and a.sensors[1].sensitivity == pytest.approx(0.1 / 9.80665)
    assert a.model["path"] == p.model_path
    broken = json.loads(json.dumps(DOC))
    broken["channels"][1]["direction"] = [0, 0, 0]
    path = _write(tmp_path, broken, "broken.json")
    # one message; pretest's error is both a PretestError and a LayoutError
    with pytest.raises(pretest.PretestError, match=r"channels\[1\] \(acc2\): 'direction' is the zero vector") as info:
        pretest.read_layout(path)
    assert isinstance(info.value, LayoutError)
    with pytest.raises(LayoutError, match=r"channels\[1\] \(acc2\): 'direction' is the zero vector"):
        acquisition.read_layout(path)
    # acquisition's own rule on top: a sweep needs a drive
    nodrive = json.loads(json.dumps(DOC))
    nodrive["drives"] = []
    path = _write(tmp_path, nodrive, "nodrive.json")
    assert pretest.read_layout(path).drives == ()
    with pytest.raises(LayoutError, match=r"nodrive\.json: 'drives' must be a non-empty list"):
        acquisition.read_layout(path)
