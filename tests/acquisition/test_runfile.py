"""Run files: round trip, incremental status, resume, validation errors naming the fault, analyses."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from acquisition import ChannelSpec, LineQuality, RunFileError, create_run, read_analysis, read_run, resume_run, write_analysis
from acquisition.runfile import FLAG_FORCE

SENS = tuple(ChannelSpec(f"a{k}", "response", "acceleration", "m/s^2", sensitivity=0.01 * (k + 1), grid=100 + k,
                         direction=(0.0, 0.6, 0.8), serial=f"SN{k}", iepe_current_a=0.004) for k in range(3))
DRV = (ChannelSpec("F", "force", "force", "N", sensitivity=0.0225, grid=100, direction=(0.0, 0.0, -1.0)),)


def _q(k, flags=0):
    return LineQuality(force_n=np.array([1.0 + 1e-3 * k]), std_error=np.full((3, 1), 1e-4 * k), thd=np.full(4, 1e-3),
                       settle_metric=1e-4, flags=flags, drive_v=0.1 * k, time_s=float(k), settle_time_s=0.5,
                       n_blocks=4)


def test_round_trip_and_status(tmp_path):
    rng = np.random.default_rng(0)
    frf = rng.normal(size=(7, 3, 1)) + 1j * rng.normal(size=(7, 3, 1))
    path = tmp_path / "r.h5"
    w = create_run(path, article="SF-03", sensors=SENS, drives=DRV, plan={"lines": [1, 2]}, hardware={"driver": "sim"})
    assert read_run(path).status == "running" and read_run(path).n_lines == 0
    for k in range(7):
        w.append_line(100.0 + k / 3, frf[k], _q(k, FLAG_FORCE if k == 2 else 0))
        assert read_run(path).n_lines == k + 1  # readable while the writer holds it
    w.close("completed")
    run = read_run(path)
    assert run.status == "completed" and run.article == "SF-03" and run.quantity == "accelerance"
    assert np.array_equal(run.frf, frf) and np.array_equal(run.frequency_hz, 100.0 + np.arange(7) / 3)
    assert run.sensors == SENS and run.drives == DRV
    assert run.plan == {"lines": [1, 2]} and run.hardware == {"driver": "sim"}
    assert list(run.valid) == [True, True, False, True, True, True, True]
    assert np.allclose(run.force_n[:, 0], 1 + 1e-3 * np.arange(7)) and run.std_error.shape == (7, 3, 1)
    assert run.created_utc and run.updated_utc and run.software_version.startswith("frfcal")
    with h5py.File(path, "r") as h5:
        assert h5.attrs["status"] == "completed"


def test_append_lines_block_equals_line_by_line(tmp_path):
    # the bulk write (UFF58 import) stores exactly what line-by-line appends store, after earlier lines
    rng = np.random.default_rng(3)
    frf = rng.normal(size=(9, 3, 1)) + 1j * rng.normal(size=(9, 3, 1))
    f = 50.0 + np.arange(9) * 0.25
    qs = [_q(k, FLAG_FORCE if k == 5 else 0) for k in range(9)]
    one, block = tmp_path / "one.h5", tmp_path / "block.h5"
    with create_run(one, article="a", sensors=SENS, drives=DRV) as w:
        for k in range(9):
            w.append_line(f[k], frf[k], qs[k])
    with create_run(block, article="a", sensors=SENS, drives=DRV) as w:
        w.append_line(f[0], frf[0], qs[0])
        w.append_lines(f[1:], frf[1:], qs[1:])
        assert read_run(block).n_lines == 9
        w.append_lines(f[:0], frf[:0], _q(0))  # an empty block is a no-op
    a, b = read_run(one), read_run(block)
    for name in ("frequency_hz", "frf", "std_error", "force_n", "thd", "flags", "drive_v", "time_s", "n_blocks"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    with create_run(tmp_path / "shared.h5", article="a", sensors=SENS, drives=DRV) as w:
        w.append_lines(f, frf, _q(1))  # one quality shared by every line
        with pytest.raises(RunFileError, match=r"frf block must be \(9, 3, 1\)"):
            w.append_lines(f, frf[:, :2], _q(1))
        with pytest.raises(RunFileError, match="2 line qualities for 9 lines"):
            w.append_lines(f, frf, qs[:2])
        with pytest.raises(RunFileError, match="positive and finite"):
            w.append_lines(-f, frf, _q(1))
    assert np.allclose(read_run(tmp_path / "shared.h5").std_error, 1e-4)


def test_context_manager_marks_aborted_and_resume_continues(tmp_path):
    path = tmp_path / "r.h5"
    with pytest.raises(RuntimeError):
        with create_run(path, article="a", sensors=SENS, drives=DRV) as w:
            w.append_line(10.0, np.ones((3, 1)), _q(1))
            raise RuntimeError("boom")
    assert read_run(path).status == "aborted"
    write_analysis(path, "modes", {"f": np.array([1.0, 2.0])}, {"method": "n4sid", "order": 12, "meta": {"a": 1}})
    w = resume_run(path)
    assert list(w.frequency_hz_done) == [10.0] and read_run(path).status == "running"
    w.append_line(11.0, 2 * np.ones((3, 1)), _q(2))
    w.close()
    run = read_run(path)
    assert run.status == "completed" and list(run.frequency_hz) == [10.0, 11.0]
    arrays, attrs = read_analysis(path, "modes")
    assert np.array_equal(arrays["f"], [1.0, 2.0]) and attrs["method"] == "n4sid" and attrs["order"] == 12
    assert attrs["meta"] == '{"a": 1}'


def test_refuses_overwrite_and_bad_lines(tmp_path):
    path = tmp_path / "r.h5"
    w = create_run(path, article="a", sensors=SENS, drives=DRV)
    with pytest.raises(RunFileError, match="exists"):
        create_run(path, article="a", sensors=SENS, drives=DRV)
    with pytest.raises(RunFileError, match=r"frf line must be \(3, 1\)"):
        w.append_line(10.0, np.ones((2, 1)), _q(1))
    with pytest.raises(RunFileError, match="std_error"):
        w.append_line(10.0, np.ones((3, 1)), LineQuality(force_n=np.ones(1), std_error=np.ones(3), thd=np.ones(4)))
    with pytest.raises(RunFileError, match="positive"):
        w.append_line(-1.0, np.ones((3, 1)), _q(1))
    w.close()
    with pytest.raises(RunFileError, match="quantity"):
        create_run(tmp_path / "q.h5", article="a", sensors=SENS, drives=DRV, quantity="inertance")
    with pytest.raises(RunFileError, match="not unique"):
        create_run(tmp_path / "u.h5", article="a", sensors=SENS + SENS[:1], drives=DRV)


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda h5: h5.attrs.__setitem__("format", "other"), "attribute 'format'"),
        (lambda h5: h5.attrs.__setitem__("quantity", "inertance"), "attribute 'quantity'"),
        (lambda h5: h5.__delitem__("lines/frf"), "'/lines/frf' is missing"),
        (lambda h5: h5["lines/count"].__setitem__(0, 99), "'/lines/frequency_hz' holds 2 lines, count says 99"),
        (lambda h5: h5.__delitem__("sensors/grid"), "'/sensors/grid' is missing"),
        (lambda h5: h5["sensors/direction"].__setitem__(0, [1.0, 1.0, 0.0]), "not a unit vector"),
        (lambda h5: h5["status"].__setitem__(0, b"weird"), "'/status' holds 'weird'"),
        (lambda h5: h5.attrs.__setitem__("plan_json", "{"), "plan_json"),
    ],
)
def test_validation_names_what_is_wrong(tmp_path, damage, message):
    path = tmp_path / "r.h5"
    with create_run(path, article="a", sensors=SENS, drives=DRV) as w:
        w.append_line(10.0, np.ones((3, 1)), _q(1))
        w.append_line(11.0, np.ones((3, 1)), _q(2))
    with h5py.File(path, "r+") as h5:
        damage(h5)
    with pytest.raises(RunFileError, match=message) as exc:
        read_run(path)
    assert str(path) in str(exc.value)


def test_not_a_run_file(tmp_path):
    bad = tmp_path / "x.h5"
    bad.write_text("hello")
    with pytest.raises(RunFileError, match="not a readable HDF5"):
        read_run(bad)
    with pytest.raises(RunFileError, match="not found"):
        read_run(tmp_path / "missing.h5")
    with pytest.raises(RunFileError, match="analysis 'nope' not found"):
        path = tmp_path / "r.h5"
        create_run(path, article="a", sensors=SENS, drives=DRV).close()
        read_analysis(path, "nope")


def test_lines_come_back_sorted_by_frequency(tmp_path):
    path = tmp_path / "r.h5"
    with create_run(path, article="a", sensors=SENS, drives=DRV) as w:
        for k, f in enumerate((120.0, 100.0, 119.5, 130.0)):  # refinement steps back down
            w.append_line(f, np.full((3, 1), f + 0j), _q(k))
    run = read_run(path)
    assert list(run.frequency_hz) == [100.0, 119.5, 120.0, 130.0]
    assert np.array_equal(run.frf[:, 0, 0].real, run.frequency_hz)
    assert list(run.time_s) == [1.0, 2.0, 0.0, 3.0]  # measurement order recoverable
