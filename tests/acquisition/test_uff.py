"""UFF58: exact round trip (58b), ASCII interop, node/direction mapping, CLI."""

from __future__ import annotations

import numpy as np
import pytest

from acquisition import ChannelSpec, LineQuality, UffError, create_run, export_uff, import_uff, read_run
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
    assert "exists" in capsys.readouterr().err
