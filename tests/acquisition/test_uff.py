"""UFF58: exact round trip (58b), ASCII interop, node/direction mapping, CLI."""

from __future__ import annotations

import numpy as np
import pytest

from acquisition import ChannelSpec, LineQuality, UffError, create_run, export_uff, import_uff, read_run
from acquisition._uff import _spread_printed_lines
from frfcal.cli import main

SENS = (
    ChannelSpec("acc1", "response", "acceleration", "m/s^2", grid=101, direction=(0.0, 0.0, 1.0)),
    ChannelSpec("acc2", "response", "acceleration", "m/s^2", grid=102, direction=(-1.0, 0.0, 0.0)),
    ChannelSpec("acc3", "response", "acceleration", "m/s^2", grid=103, direction=(0.0, 0.6, 0.8)),
)
DRV = (ChannelSpec("F1", "force", "force", "N", grid=101, direction=(0.0, 0.0, 1.0)),
       ChannelSpec("F2", "force", "force", "N", grid=205, direction=(0.0, -1.0, 0.0)))


def _run(path):
    rng = np.random.default_rng(5)
    f = np.sort(100 + 450 * rng.random(40))
    frf = rng.normal(size=(40, 3, 2)) * 10.0 ** rng.normal(size=(40, 3, 2)) + 1j * rng.normal(size=(40, 3, 2))
    with create_run(path, article="SF-01", sensors=SENS, drives=DRV) as w:
        for k in range(40):
            w.append_line(f[k], frf[k], LineQuality(force_n=np.ones(2), std_error=np.zeros((3, 2)), thd=np.zeros(5)))
    return f, frf


def test_binary_round_trip_is_exact(tmp_path):
    f, frf = _run(tmp_path / "r.h5")
    assert export_uff(tmp_path / "r.h5", tmp_path / "r.uff") == 6
    run = import_uff(tmp_path / "r.uff", tmp_path / "back.h5")
    assert np.array_equal(run.frequency_hz, f) and np.array_equal(run.frf, frf)
    assert [c.name for c in run.sensors] == ["acc1", "acc2", "acc3"] and [c.name for c in run.drives] == ["F1", "F2"]
    assert [c.grid for c in run.sensors] == [101, 102, 103]
    assert [c.direction for c in run.sensors + run.drives] == [c.direction for c in SENS + DRV]
    assert run.article == "SF-01" and run.quantity == "accelerance"


def test_export_makes_the_folders_of_its_file(tmp_path):
    """``frfcal export-uff RUN --out new/dir/FILE.uff`` as ``import-uff --out`` does: the folders are made."""
    f, frf = _run(tmp_path / "r.h5")
    for binary in (True, False):
        out = tmp_path / ("b" if binary else "a") / "sub" / "r.uff"
        assert export_uff(tmp_path / "r.h5", out, binary=binary) == 6
        back = import_uff(out, tmp_path / f"back_{binary}.h5")
        assert np.allclose(back.frf, frf, rtol=1e-10)


def test_ascii_and_foreign_mapping(tmp_path):
    f, frf = _run(tmp_path / "r.h5")
    export_uff(tmp_path / "r.h5", tmp_path / "a.uff", binary=False)
    run = import_uff(tmp_path / "a.uff", tmp_path / "a.h5")
    assert np.allclose(run.frf, frf, rtol=1e-10)
    assert np.allclose(run.frequency_hz, f, rtol=1e-5)  # ASCII UFF58 keeps 6 digits of the abscissa

    # a file written by another system: node + direction codes only, in g/N
    import pyuff

    sets = []
    for node, d in ((7, 3), (8, -2)):
        ds = pyuff.prepare_58(binary=0, func_type=4, rsp_node=node, rsp_dir=d, ref_node=7, ref_dir=3, ord_data_type=6,
                              abscissa_spacing=1, abscissa_min=10.0, abscissa_inc=0.5, data=np.arange(1, 11) * (1 + 1j),
                              x=10 + 0.5 * np.arange(10), ordinate_spec_data_type=12, orddenom_spec_data_type=13,
                              ordinate_axis_units_lab="g", orddenom_axis_units_lab="N", abscissa_spec_data_type=18)
        ds["type"] = 58
        sets.append(ds)
    pyuff.UFF(str(tmp_path / "foreign.uff")).write_sets(sets, mode="overwrite")
    run = import_uff(tmp_path / "foreign.uff", tmp_path / "foreign.h5", article="other")
    assert [c.grid for c in run.sensors] == [7, 8] and run.sensors[1].direction == (0.0, -1.0, 0.0)
    assert run.drives[0].direction == (0.0, 0.0, 1.0) and run.drives[0].name == "ref_n7+Z"
    assert np.allclose(run.frf[:, 0, 0], 9.80665 * np.arange(1, 11) * (1 + 1j))


def test_errors_and_cli(tmp_path, capsys):
    with pytest.raises(UffError, match="not found"):
        import_uff(tmp_path / "none.uff", tmp_path / "x.h5")
    _run(tmp_path / "r.h5")
    assert main(["export-uff", str(tmp_path / "r.h5"), "--out", str(tmp_path / "c.uff")]) == 0
    assert main(["import-uff", str(tmp_path / "c.uff"), "--out", str(tmp_path / "c.h5"), "--json"]) == 0
    assert '"n_lines": 40' in capsys.readouterr().out
    assert np.array_equal(read_run(tmp_path / "c.h5").frf, read_run(tmp_path / "r.h5").frf)
    assert main(["import-uff", str(tmp_path / "c.uff"), "--out", str(tmp_path / "c.h5")]) == 2  # exists
    assert "exists; pass --force to overwrite it" in capsys.readouterr().err  # the flag, not the Python keyword


# --- MIMO files written by another system (pyuff directly, not export_uff) ---------------------------------------
F_AX = 5.0 + 0.25 * np.arange(16)


def _foreign(path, cells, **common):
    """Write one ASCII UFF58 record per cell: (rsp_node, rsp_dir, ref_node, ref_dir, data, overrides)."""
    import pyuff

    sets = []
    for rn, rd, fn, fd, data, over in cells:
        kw = dict(binary=0, func_type=4, rsp_node=rn, rsp_dir=rd, ref_node=fn, ref_dir=fd, ord_data_type=6,
                  abscissa_spacing=1, abscissa_min=float(F_AX[0]), abscissa_inc=0.25, x=F_AX, data=data,
                  id1="lab system", id2="Acceleration / Force", rsp_ent_name=f"acc{rn}", ref_ent_name="shaker",
                  ordinate_spec_data_type=12, orddenom_spec_data_type=13, abscissa_spec_data_type=18,
                  ordinate_axis_units_lab="m/s^2", orddenom_axis_units_lab="N")
        kw.update(common)
        kw.update(over)
        labels = {k: kw.pop(k) for k in list(kw) if k.endswith("_axis_lab")}  # not prepare_58 arguments
        ds = pyuff.prepare_58(**kw)
        ds.update(labels)
        ds["type"] = 58
        sets.append(ds)
    pyuff.UFF(str(path)).write_sets(sets, mode="overwrite")


def _mimo_cells():
    """20 responses (nodes 101..120, alternating +Z / -Y) x 2 references (1 +Z, 2 -X), reference-major order."""
    out = []
    for ref, (fn, fd) in enumerate(((1, 3), (2, -1))):
        for i in range(20):
            data = (1000 * (ref + 1) + i + 1) * (1.0 + 0.01 * np.arange(F_AX.size)) * np.exp(1j * (0.1 * i + ref))
            out.append((101 + i, 3 if i % 2 == 0 else -2, fn, fd, data, {}))
    return out


def test_coherences_beside_the_frfs_are_left_out_and_listed(tmp_path):
    """An analyzer's export with a coherence per FRF (function type 6, real): the FRFs are the run, the
    coherences are listed as left out (the command prints them), and a file of coherences alone is refused."""
    from frfcal.commands.import_uff import uff_to_run

    cells = _mimo_cells()
    coh = [(rn, rd, fn, fd, np.full(F_AX.size, 0.99), {"func_type": 6, "ord_data_type": 4,
                                                         "ordinate_spec_data_type": 0, "orddenom_spec_data_type": 0,
                                                         "ordinate_axis_units_lab": "", "orddenom_axis_units_lab": ""})
           for rn, rd, fn, fd, _, _ in cells]
    _foreign(tmp_path / "with_coh.uff", [x for pair in zip(cells, coh) for x in pair])  # FRF, coherence, FRF, ...
    info = uff_to_run(tmp_path / "with_coh.uff", tmp_path / "w.h5")
    run = import_uff(tmp_path / "with_coh.uff", tmp_path / "w2.h5")
    assert run.frf.shape == (16, 20, 2)
    for rn, _, fn, _, data, _ in cells:
        np.testing.assert_allclose(run.frf[:, rn - 101, fn - 1], data, rtol=1e-10)
    assert info["skipped_records"] == {"coherence (6)": list(range(2, 81, 2))}
    assert run.plan["skipped_records"] == info["skipped_records"]
    _foreign(tmp_path / "coh.uff", coh)
    with pytest.raises(UffError, match=r"no UFF58 frequency response function records \(function type 4\); "
                                       r"function types found: \[6\]"):
        import_uff(tmp_path / "coh.uff", tmp_path / "c.h5")


def test_foreign_mimo_20x2_keeps_every_reference(tmp_path):
    cells = _mimo_cells()
    _foreign(tmp_path / "mimo.uff", cells)
    run = import_uff(tmp_path / "mimo.uff", tmp_path / "mimo.h5")
    assert run.frf.shape == (16, 20, 2)
    assert [c.grid for c in run.sensors] == list(range(101, 121)) and [c.grid for c in run.drives] == [1, 2]
    assert run.sensors[0].direction == (0.0, 0.0, 1.0) and run.sensors[1].direction == (0.0, -1.0, 0.0)
    assert run.drives[0].direction == (0.0, 0.0, 1.0) and run.drives[1].direction == (-1.0, 0.0, 0.0)
    assert run.sensors[0].name == "acc101 (101+Z)" and run.sensors[1].name == "acc102 (102-Y)"
    assert [c.name for c in run.drives] == ["shaker (1+Z)", "shaker (2-X)"]
    for rn, _, fn, _, data, _ in cells:  # every record lands in its own (response, reference) cell
        np.testing.assert_allclose(run.frf[:, rn - 101, fn - 1], data, rtol=1e-10)  # ASCII: 13 digits
    assert np.allclose(run.frequency_hz, F_AX)

    # blank entity names: the point alone, response and reference kept apart
    _foreign(tmp_path / "bare.uff", cells, rsp_ent_name="NONE", ref_ent_name="NONE")
    run = import_uff(tmp_path / "bare.uff", tmp_path / "bare.h5")
    assert run.sensors[3].name == "n104-Y" and [c.name for c in run.drives] == ["ref_n1+Z", "ref_n2-X"]


def test_mimo_round_trip_is_exact_and_keeps_channels(tmp_path):
    rng = np.random.default_rng(11)
    sens = tuple(ChannelSpec(f"accelerometer_{i:02d}", "response", "acceleration", "m/s^2", grid=300 + i,
                             direction=((0.0, 0.0, -1.0), (0.0, 1.0, 0.0), (0.6, 0.0, -0.8))[i % 3])
                 for i in range(20))
    drv = (ChannelSpec("shaker_vertical", "force", "force", "N", grid=300, direction=(0.0, 0.0, -1.0)),
           ChannelSpec("shaker_lateral", "force", "force", "N", grid=311, direction=(0.0, 1.0, 0.0)))
    f = np.sort(20 + 180 * rng.random(30))
    frf = rng.normal(size=(30, 20, 2)) + 1j * rng.normal(size=(30, 20, 2))
    with create_run(tmp_path / "r.h5", article="SF-07", sensors=sens, drives=drv) as w:
        for k in range(30):
            w.append_line(f[k], frf[k], LineQuality(force_n=np.ones(2), std_error=np.zeros((20, 2)), thd=np.zeros(22)))
    assert export_uff(tmp_path / "r.h5", tmp_path / "r.uff") == 40
    back = import_uff(tmp_path / "r.uff", tmp_path / "b.h5")
    assert np.array_equal(back.frequency_hz, f) and np.array_equal(back.frf, frf)
    for a, b in zip(back.sensors + back.drives, sens + drv):
        assert (a.name, a.grid, a.direction) == (b.name, b.grid, b.direction)
    export_uff(tmp_path / "r.h5", tmp_path / "a.uff", binary=False)
    back = import_uff(tmp_path / "a.uff", tmp_path / "a.h5")
    assert [c.name for c in back.sensors + back.drives] == [c.name for c in sens + drv]
    assert np.allclose(back.frf, frf, rtol=1e-10)


@pytest.mark.parametrize("edit, message", [
    (lambda c: c + [c[5]], r"record 41 \(response 106/-2, reference 1/3\) repeats the \(response, reference\) pair "
                          r"of record 6"),
    (lambda c: c[:7] + c[8:], r"20 responses x 2 references need 40 FRF records, 39 given; missing \(response / "
                              r"reference\): 108-Y / 1\+Z"),
    (lambda c: c[:-1] + [c[-1][:5] + ({"ordinate_spec_data_type": 11},)], r"record 40 .* is mobility, record 1 .* is "
                                                                          r"accelerance"),
    (lambda c: c[:3] + [c[3][:5] + ({"ordinate_axis_units_lab": "g"},)] + c[4:], r"mixed units: m/s\^2/N in records "
                                                                                 r"1, 2, 3, 5, .*; g/N in records 4"),
    (lambda c: c[:-1] + [c[-1][:5] + ({"abscissa_min": 5.5, "x": F_AX + 0.5},)], "record 40 .* different frequency"),
    (lambda c: c[:-1] + [c[-1][:3] + (5,) + c[-1][4:]], r"record 40 .*reference direction code 5 is not a "
                                                          r"translation"),
    (lambda c: c[:-1] + [c[-1][:5] + ({"rsp_ent_name": "accX"},)], r"response 120-Y is named 'acc120' in record "
                                                                    r"20 and 'accX' in record 40"),
])
def test_ambiguous_files_are_refused(tmp_path, edit, message):
    path = tmp_path / "bad.uff"
    _foreign(path, edit(_mimo_cells()))
    with pytest.raises(UffError, match=message) as info:
        import_uff(path, tmp_path / "bad.h5")
    assert str(path) in str(info.value)
    assert not (tmp_path / "bad.h5").exists()


def test_cli_imports_mimo(tmp_path, capsys):
    _foreign(tmp_path / "m.uff", _mimo_cells())
    assert main(["import-uff", str(tmp_path / "m.uff"), "--out", str(tmp_path / "m.h5")]) == 0
    out = capsys.readouterr().out
    assert "20 x 2 accelerance" in out and "references: shaker (1+Z), shaker (2-X)" in out
    # the response names too: they are what a campaign's [channels] lists
    (resp,) = [ln for ln in out.splitlines() if ln.startswith("responses: ")]
    assert len(resp[len("responses: "):].split(", ")) == 20
    assert main(["import-uff", str(tmp_path / "m.uff"), "--out", str(tmp_path / "m.h5"), "--force", "--json"]) == 0
    assert '"drive_grids": [1, 2]' in capsys.readouterr().out
    _foreign(tmp_path / "d.uff", _mimo_cells() + [_mimo_cells()[0]])
    assert main(["import-uff", str(tmp_path / "d.uff"), "--out", str(tmp_path / "d.h5")]) == 2
    assert "repeats the (response, reference) pair" in capsys.readouterr().err


def _labelled(path, num, den, spec=12, value=2.0 + 1.0j):
    import pyuff

    ds = pyuff.prepare_58(binary=0, func_type=4, rsp_node=7, rsp_dir=-3, ref_node=7, ref_dir=3, ord_data_type=6,
                          abscissa_spacing=1, abscissa_min=10.0, abscissa_inc=0.5, data=np.full(10, value),
                          x=10 + 0.5 * np.arange(10), ordinate_spec_data_type=spec, orddenom_spec_data_type=13,
                          ordinate_axis_units_lab=num, orddenom_axis_units_lab=den, abscissa_spec_data_type=18)
    ds["type"] = 58
    pyuff.UFF(str(path)).write_sets([ds], mode="overwrite")
    return path


@pytest.mark.parametrize("num, den, factor", [
    ("m/s²", "N", 1.0),                    # superscript two, as m+p and Testlab exports write it
    ("m/s**2", "N", 1.0),
    ("(m/s^2)/N", "", 1.0),                # the whole ratio in the ordinate label
    ("g", "lbf", 9.80665 / 4.4482216152605),
    ("in/s^2", "lbf", 0.0254 / 4.4482216152605),
    ("g/lbf", "", 9.80665 / 4.4482216152605),
])
def test_unit_labels_labs_write_are_converted(tmp_path, num, den, factor):
    run = import_uff(_labelled(tmp_path / "u.uff", num, den), tmp_path / "u.h5")
    np.testing.assert_allclose(run.frf[:, 0, 0], (2.0 + 1.0j) * factor, rtol=1e-12)


@pytest.mark.parametrize("num, den, spec, message", [
    ("m/s", "N", 12, r"'m/s' is a unit of mobility but the ordinate type 12 says accelerance"),
    ("g", "N", 11, r"'g' is a unit of accelerance but the ordinate type 11 says mobility"),
    ("g/N", "lbf", 12, r"names the force 'n' but the denominator unit is 'lbf'"),
    ("furlong/s^2", "N", 12, r"unknown ordinate unit 'furlong/s\^2' \(known: m/s\^2"),
])
def test_contradictory_or_unknown_unit_labels_are_refused(tmp_path, num, den, spec, message):
    with pytest.raises(UffError, match=message):
        import_uff(_labelled(tmp_path / "u.uff", num, den, spec), tmp_path / "u.h5")


def test_the_dc_line_of_an_analyzer_file_is_left_out(tmp_path, capsys):
    # FFT analyzers write 0 .. fmax: the 0 Hz line (here an exact 0) stopped the import with
    # "r.h5: line frequency must be positive and finite, got 0.0"
    import pyuff

    f = 0.5 * np.arange(12)
    data = (1 + 2j) * np.arange(12.0)
    sets = [pyuff.prepare_58(binary=0, func_type=4, rsp_node=7, rsp_dir=3, ref_node=7, ref_dir=3, ord_data_type=6,
                             abscissa_spacing=1, abscissa_min=0.0, abscissa_inc=0.5, data=data, x=f,
                             ordinate_spec_data_type=12, orddenom_spec_data_type=13, ordinate_axis_units_lab="m/s^2",
                             orddenom_axis_units_lab="N", abscissa_spec_data_type=18)]
    sets[0]["type"] = 58
    pyuff.UFF(str(tmp_path / "dc.uff")).write_sets(sets, mode="overwrite")
    run = import_uff(tmp_path / "dc.uff", tmp_path / "dc.h5")
    assert np.array_equal(run.frequency_hz, f[1:]) and np.array_equal(run.frf[:, 0, 0], data[1:])
    assert run.plan["dropped_hz"] == [0.0]
    assert main(["import-uff", str(tmp_path / "dc.uff"), "--out", str(tmp_path / "cli.h5")]) == 0
    assert "left out 1 line(s) at 0 Hz" in capsys.readouterr().out
    sets[0]["x"] = f - 1.0  # a negative frequency is not a DC line: refused, naming the UFF file
    pyuff.UFF(str(tmp_path / "neg.uff")).write_sets(sets, mode="overwrite")
    with pytest.raises(UffError, match=r"neg.uff: the abscissa has 2 negative or non-finite frequencies"):
        import_uff(tmp_path / "neg.uff", tmp_path / "neg.h5")


def _with_units_dataset(path, length, force, num="NONE", den="NONE", second=None):
    import pyuff

    sets = []
    for lf in [(length, force)] + ([second] if second else []):
        u = pyuff.prepare_164(units_code=9, units_description="lab", temp_mode=2, length=lf[0], force=lf[1],
                              temp=1.0, temp_offset=273.15)
        u["type"] = 164
        sets.append(u)
    ds = pyuff.prepare_58(binary=0, func_type=4, rsp_node=7, rsp_dir=3, ref_node=7, ref_dir=3, ord_data_type=6,
                          abscissa_spacing=1, abscissa_min=10.0, abscissa_inc=0.5, data=np.full(10, 2.0 + 1.0j),
                          x=10 + 0.5 * np.arange(10), ordinate_spec_data_type=12, orddenom_spec_data_type=13,
                          ordinate_axis_units_lab=num, orddenom_axis_units_lab=den, abscissa_spec_data_type=18)
    ds["type"] = 58
    pyuff.UFF(str(path)).write_sets(sets + [ds], mode="overwrite")
    return path


def test_records_without_unit_labels_take_the_units_dataset_164(tmp_path):
    # mm and N (164: length factor 1000, force factor 1) with NONE labels: was read as SI, 1000x too large
    run = import_uff(_with_units_dataset(tmp_path / "mm.uff", 1000.0, 1.0), tmp_path / "mm.h5")
    np.testing.assert_allclose(run.frf[:, 0, 0], (2.0 + 1.0j) / 1000.0, rtol=1e-12)
    # in and lbf (BG-like user system): factors 1/0.0254 and 1/4.448...
    run = import_uff(_with_units_dataset(tmp_path / "in.uff", 1 / 0.0254, 1 / 4.4482216152605), tmp_path / "in.h5")
    np.testing.assert_allclose(run.frf[:, 0, 0], (2.0 + 1.0j) * 0.0254 / 4.4482216152605, rtol=1e-9)
    # explicit labels keep deciding
    run = import_uff(_with_units_dataset(tmp_path / "lab.uff", 1000.0, 1.0, "g", "N"), tmp_path / "lab.h5")
    np.testing.assert_allclose(run.frf[:, 0, 0], (2.0 + 1.0j) * 9.80665, rtol=1e-12)
    with pytest.raises(UffError, match=r"units datasets \(164\) 1, 2 disagree"):
        import_uff(_with_units_dataset(tmp_path / "two.uff", 1000.0, 1.0, second=(1.0, 1.0)), tmp_path / "two.h5")


def _skewed_file(path, geometry):
    """Node 7 (+Z, response) and node 8 (+Y, reference) records with the test geometry ``geometry`` first."""
    import pyuff

    sets = list(geometry)
    for rn, rd in ((7, 3), (8, 2)):
        ds = pyuff.prepare_58(binary=0, func_type=4, rsp_node=rn, rsp_dir=rd, ref_node=8, ref_dir=2, ord_data_type=6,
                              abscissa_spacing=1, abscissa_min=10.0, abscissa_inc=0.5, data=np.full(10, 2.0 + 1.0j),
                              x=10 + 0.5 * np.arange(10), ordinate_spec_data_type=12, orddenom_spec_data_type=13,
                              ordinate_axis_units_lab="m/s^2", orddenom_axis_units_lab="N", abscissa_spec_data_type=18)
        ds["type"] = 58
        sets.append(ds)
    pyuff.UFF(str(path)).write_sets(sets, mode="overwrite")
    return path


def _nodes(disp_cs, kind=2411):
    return {"type": kind, "node_nums": np.array([7.0, 8.0]), "def_cs": np.zeros(2), "disp_cs": np.array(disp_cs, float),
            "color": np.full(2, 11.0), "x": np.array([0.0, 0.1]), "y": np.zeros(2), "z": np.zeros(2)}


def _cs2420(label, R, typ=0):
    # rows 1-3: direction cosines of the local x, y, z axes in global; row 4: origin
    return {"type": 2420, "Part_UID": 1, "Part_Name": "test", "CS_sys_labels": [label], "CS_types": [typ],
            "CS_colors": [8], "CS_names": [f"CS{label}"], "CS_matrices": [np.vstack([np.asarray(R).T, np.zeros(3)])]}


def test_direction_codes_are_in_the_nodes_displacement_system(tmp_path):
    # A skewed accelerometer as test software exports it: its node has a local displacement system (2411
    # + 2420, or 15 + 18) and the record's direction code is along that system's axis. Before, the test
    # geometry was skipped and +Z was taken as global Z, silently.
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    Rx = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])      # local axes as columns: rotated 30 deg about x
    run = import_uff(_skewed_file(tmp_path / "a.uff", [_cs2420(12, Rx), _nodes([12, 0])]), tmp_path / "a.h5")
    np.testing.assert_allclose(run.sensors[0].direction, [0, -s, c], atol=1e-12)   # local +Z
    np.testing.assert_allclose(run.drives[0].direction, [0, 1, 0], atol=1e-12)     # node 8 in global
    assert run.sensors[1].direction == (0.0, 1.0, 0.0)
    # dataset 18 (origin, point on +x, point in the xz plane) and 15: node 8's +Y is local y = global -X
    cs18 = {"type": 18, "cs_num": [3], "cs_type": [0], "ref_cs_num": [0], "color": [8], "method": [1],
            "cs_name": ["rot"], "ref_o": np.zeros((1, 3)), "x_point": np.array([[0.0, 1.0, 0.0]]),
            "xz_point": np.array([[0.0, 0.0, 1.0]])}
    run = import_uff(_skewed_file(tmp_path / "b.uff", [cs18, _nodes([0, 3], kind=15)]), tmp_path / "b.h5")
    np.testing.assert_allclose(run.drives[0].direction, [-1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(run.sensors[0].direction, [0, 0, 1], atol=1e-12)
    # a system the file does not define, or a cylindrical one: refused naming the node
    with pytest.raises(UffError, match="node 7 gives displacement coordinate system 12, which the file does not"):
        import_uff(_skewed_file(tmp_path / "c.uff", [_nodes([12, 0])]), tmp_path / "c.h5")
    with pytest.raises(UffError, match="node 7: displacement coordinate system 12 is cylindrical"):
        import_uff(_skewed_file(tmp_path / "d.uff", [_cs2420(12, Rx, typ=1), _nodes([12, 0])]), tmp_path / "d.h5")


def test_lines_an_ascii_abscissa_printed_the_same_are_kept_in_order_and_unordered_ones_sorted(tmp_path, monkeypatch):
    """ASCII UFF58 keeps the abscissa to 6 digits (E13.5): an over-dense grid prints neighbouring lines the
    same. Every line is kept, spread within half a unit of the last digit in file order, never past a
    neighbour. Distinct lines out of order are sorted."""
    # 150.0702 and 150.0704 Hz both print as 1.50070e+02; three lines at 5.5 (a repeated line)
    x = np.array([5.0, 5.25, 5.5, 5.5, 5.5, 6.0, 150.0702, 150.0704, 150.1])
    data = (1.0 + 0.1 * np.arange(x.size)) * (1 + 1j)
    _foreign(tmp_path / "dup.uff", [(101, 3, 1, 3, data, {"abscissa_spacing": 0, "x": x})])
    run = import_uff(tmp_path / "dup.uff", tmp_path / "dup.h5")
    f = run.frequency_hz
    assert f.size == x.size and np.all(np.diff(f) > 0)
    np.testing.assert_allclose(run.frf[:, 0, 0], data, rtol=1e-12)  # every measurement kept, in file order
    printed = np.array([float(f"{v:.5e}") for v in x])
    assert np.all(np.abs(f - printed) <= 0.5 * 10.0 ** (np.floor(np.log10(printed)) - 5) * (1 + 1e-12))
    assert f[2] < 5.5 < f[4] and f[6] < 150.07 < f[7]  # each group straddles its printed value
    assert run.plan["abscissa_spread"]["groups"] == 2 and run.plan["abscissa_spread"]["lines"] == 5
    # an abscissa written with more digits: a distinct neighbour closer than half a unit of the 6th digit
    # narrows the group's interval to half the gap
    g, spread = _spread_printed_lines(np.array([5.49, 5.5, 5.5, 5.500002]))
    assert np.all(np.diff(g) > 0) and g[2] < 5.500001 and spread == {"groups": 1, "lines": 2,
                                                                       "max_shift_hz": pytest.approx(3e-6)}
    # a binary file's doubles are exact: the same frequency twice is a repeated line, refused (pyuff writes no
    # foreign 58b record with an uneven abscissa, so the file is taken for binary here)
    monkeypatch.setattr("acquisition._uff._is_binary", lambda path: True)
    with pytest.raises(UffError, match=r"dup.uff: line 5.5 Hz appears 3 times in the abscissa \(3 repeated in all\)$"):
        import_uff(tmp_path / "dup.uff", tmp_path / "dup2.h5")
    order = np.array([5.5, 5.0, 6.0, 5.25])
    data = np.array([3.0, 1.0, 4.0, 2.0]) + 0j
    _foreign(tmp_path / "unordered.uff", [(101, 3, 1, 3, data, {"abscissa_spacing": 0, "x": order})])
    run = import_uff(tmp_path / "unordered.uff", tmp_path / "unordered.h5")
    np.testing.assert_array_equal(run.frequency_hz, [5.0, 5.25, 5.5, 6.0])
    np.testing.assert_array_equal(run.frf[:, 0, 0], [1.0, 2.0, 3.0, 4.0])
    # a repeat that only sorting brings side by side is found too
    again = np.array([5.5, 5.0, 5.5, 6.0])
    _foreign(tmp_path / "dup2.uff", [(101, 3, 1, 3, data, {"abscissa_spacing": 0, "x": again})])
    with pytest.raises(UffError, match=r"dup2.uff: line 5.5 Hz appears 2 times"):
        import_uff(tmp_path / "dup2.uff", tmp_path / "dup2.h5")


def test_a_unit_given_only_in_the_axis_label_is_used(tmp_path):
    """Some writers leave the units label blank and write 'Acceleration (g)' as the axis label: read as SI the
    file was 9.81x off. A unit in the axis label's parentheses counts when the units label is blank and it is
    a known unit; another remark in parentheses leaves the blank (SI) reading."""
    data = (1.0 + 0.1 * np.arange(F_AX.size)) * (1 + 1j)
    blank = {"ordinate_axis_units_lab": "", "orddenom_axis_units_lab": ""}
    _foreign(tmp_path / "g.uff", [(101, 3, 1, 3, data, {**blank, "ordinate_axis_lab": "Acceleration (g)",
                                                         "orddenom_axis_lab": "Force [N]"})])
    np.testing.assert_allclose(import_uff(tmp_path / "g.uff", tmp_path / "g.h5").frf[:, 0, 0], 9.80665 * data,
                               rtol=1e-12)
    _foreign(tmp_path / "x.uff", [(101, 3, 1, 3, data, {**blank, "ordinate_axis_lab": "Acceleration (X)"})])
    np.testing.assert_allclose(import_uff(tmp_path / "x.uff", tmp_path / "x.h5").frf[:, 0, 0], data, rtol=1e-12)


def test_a_file_without_frf_records_says_what_it_holds(tmp_path):
    """A universal file with no dataset 58 names the datasets it has, or says none could be delimited (a damaged
    file, e.g. a binary one pyuff rewrote record by record in overwrite mode)."""
    import pyuff

    head = {"type": 151, "model_name": "m", "description": "d", "db_app": "a", "date_db_created": "x",
            "time_db_created": "y", "version_db1": "1", "version_db2": "2", "file_type": 0, "date_db_saved": "x",
            "time_db_saved": "y", "program": "p", "date_file_written": "x", "time_file_written": "y"}
    pyuff.UFF(str(tmp_path / "h.uff")).write_sets([head], mode="overwrite")
    with pytest.raises(UffError, match=r"h.uff: no UFF58 records; it holds datasets 151 x1"):
        import_uff(tmp_path / "h.uff", tmp_path / "h.h5")
    (tmp_path / "junk.uff").write_text("junk\n")
    with pytest.raises(UffError, match=r"junk.uff: no UFF58 records; it holds no dataset pyuff can delimit"):
        import_uff(tmp_path / "junk.uff", tmp_path / "junk.h5")


@pytest.mark.parametrize("binary", [False, True])
def test_a_truncated_file_is_refused_not_imported_in_part(tmp_path, binary):
    """A copy cut inside a record: pyuff drops the unclosed dataset silently, and the records before the cut
    (here the first reference's) would fill a smaller matrix that looks complete. The import refuses it and
    says where the file ends."""
    cells = _mimo_cells()
    if binary:
        f, frf = _run(tmp_path / "src.h5")
        export_uff(tmp_path / "src.h5", tmp_path / "full.uff", binary=True)
    else:
        _foreign(tmp_path / "full.uff", cells)
    full = (tmp_path / "full.uff").read_bytes()
    assert import_uff(tmp_path / "full.uff", tmp_path / "full.h5").frf.shape == ((40, 3, 2) if binary else (16, 20, 2))
    cut = full[: int(0.537 * len(full))]  # inside a record (0.55 x 40 records would end one exactly)
    (tmp_path / "cut.uff").write_bytes(cut)
    with pytest.raises(UffError, match=r"cut.uff: the file ends inside dataset \d+ \(type 58b?, opened at line \d+, "
                                       r"byte \d+\): no closing -1 delimiter line: the file \(\d+ bytes\) is "
                                       r"truncated or damaged; nothing imported"):
        import_uff(tmp_path / "cut.uff", tmp_path / "cut.h5")
    assert not (tmp_path / "cut.h5").exists()
