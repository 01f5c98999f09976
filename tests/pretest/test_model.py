"""pretest on FE models: normals, candidate sets, the example subframe end to end, layout file, CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

import femodel
import pretest
from pretest import PretestConfig, PretestError


def _plate_deck(path, *, tilt_deg=30.0, nx=4, ny=3, lx=0.4, ly=0.3):
    """A flat steel plate (SI) rotated by ``tilt_deg`` about the x axis."""
    c, s = np.cos(np.radians(tilt_deg)), np.sin(np.radians(tilt_deg))
    lines = ["SOL 103", "CEND", "BEGIN BULK", "MAT1,1,2.1e11,,0.3,7850.", "PSHELL,1,1,0.002,1,,1"]
    gid = lambda i, j: 1 + i + (nx + 1) * j  # noqa: E731
    for j in range(ny + 1):
        for i in range(nx + 1):
            x, y = lx * i / nx, ly * j / ny
            lines.append(f"GRID,{gid(i, j)},,{x:.6f},{y * c:.6f},{y * s:.6f}")
    eid = 1
    for j in range(ny):
        for i in range(nx):
            lines.append(f"CQUAD4,{eid},1,{gid(i, j)},{gid(i + 1, j)},{gid(i + 1, j + 1)},{gid(i, j + 1)}")
            eid += 1
    lines.append("ENDDATA")
    path.write_text("\n".join(lines) + "\n")
    return path


def _angle_deck(path, rot_deg=0.0):
    """An L-shaped section: a plate in the x-y plane (PID 1) meeting a plate in the x-z plane (PID 2),
    the whole rotated by ``rot_deg`` about the x axis."""
    lines = ["SOL 103", "CEND", "BEGIN BULK", "MAT1,1,2.1e11,,0.3,7850.", "PSHELL,1,1,0.002,1,,1", "PSHELL,2,1,0.003,1,,1"]
    n = 4
    c, s = np.cos(np.radians(rot_deg)), np.sin(np.radians(rot_deg))

    def grid(gid, x, y, z):
        lines.append(f"GRID,{gid},,{x:.9f},{c * y - s * z:.9f},{s * y + c * z:.9f}")

    for i in range(n + 1):
        for j in range(3):
            grid(100 + 10 * i + j, 0.1 * i, 0.1 * j, 0.0)
        for k in (1, 2):
            grid(200 + 10 * i + k, 0.1 * i, 0.0, 0.1 * k)
    eid = 1
    for i in range(n):
        for j in range(2):
            a = 100 + 10 * i + j
            lines.append(f"CQUAD4,{eid},1,{a},{a + 10},{a + 11},{a + 1}")
            eid += 1
        ring = [100 + 10 * i, 201 + 10 * i, 202 + 10 * i]
        for k in range(2):
            lines.append(f"CQUAD4,{eid},2,{ring[k]},{ring[k] + 10},{ring[k + 1] + 10},{ring[k + 1]}")
            eid += 1
    lines.append("ENDDATA")
    path.write_text("\n".join(lines) + "\n")
    return path


def test_surface_normals_tilted_plate(tmp_path):
    model = femodel.read_bdf(_plate_deck(tmp_path / "plate.bdf", tilt_deg=30.0))
    normals = pretest.surface_normals(model, model.grid_ids)
    expect = np.array([0.0, -np.sin(np.radians(30)), np.cos(np.radians(30))])
    np.testing.assert_allclose(normals, np.broadcast_to(expect, normals.shape), atol=1e-5)  # 6-digit deck


def test_normals_pids_box_on_angle_section(tmp_path):
    model = femodel.read_bdf(_angle_deck(tmp_path / "angle.bdf"))
    flange = pretest.candidate_grids(model, pids=[1])
    web = pretest.candidate_grids(model, pids=[2])
    assert set(flange.tolist()) == {100 + 10 * i + j for i in range(5) for j in range(3)}
    assert 201 in web and 112 not in web
    # away from the corner line each plate's own normal; the corner grids are shared
    inner_flange = np.array([101, 112, 142])
    np.testing.assert_allclose(np.abs(pretest.surface_normals(model, inner_flange)), [[0, 0, 1]] * 3, atol=1e-12)
    np.testing.assert_allclose(np.abs(pretest.surface_normals(model, [202, 232])), [[0, 1, 0]] * 2, atol=1e-12)
    boxed = pretest.candidate_grids(model, box_m=[-1, -1, 0.05, 1, 1, 1])
    assert set(boxed.tolist()) == {200 + 10 * i + k for i in range(5) for k in (1, 2)}
    both = pretest.candidate_grids(model, pids=[1], box_m=[0.15, -1, -1, 1, 1, 1])
    assert set(both.tolist()) == {100 + 10 * i + j for i in (2, 3, 4) for j in range(3)}


@pytest.mark.parametrize("rot_deg", [0.0, 30.0, 117.0])
def test_edge_grids_get_a_face_normal(tmp_path, rot_deg):
    # grids on the corner line (two flange and two web elements: a tie between the two face
    # normals) get one face's normal, never a mix of the two
    model = femodel.read_bdf(_angle_deck(tmp_path / "angle.bdf", rot_deg=rot_deg))
    c, s = np.cos(np.radians(rot_deg)), np.sin(np.radians(rot_deg))
    faces = np.array([[0.0, -s, c], [0.0, c, s]])  # flange and web normals, rotated
    corner = pretest.surface_normals(model, [110, 120, 130])
    for n in corner:
        assert np.max(np.abs(faces @ n)) == pytest.approx(1.0, abs=1e-7)
    big = np.argmax(np.abs(corner), axis=1)
    assert np.all(corner[np.arange(3), big] > 0)  # sign convention: largest component positive


def test_candidate_errors_name_the_culprit(tmp_path):
    model = femodel.read_bdf(_angle_deck(tmp_path / "angle.bdf"))
    with pytest.raises(PretestError, match=r"\[999\]"):
        pretest.candidate_grids(model, grids=[100, 999])
    with pytest.raises(PretestError, match=r"property id\(s\) \[7\]"):
        pretest.candidate_grids(model, pids=[7])
    with pytest.raises(PretestError, match="no grid"):
        pretest.candidate_grids(model, box_m=[5, 5, 5, 6, 6, 6])
    with pytest.raises(PretestError, match="direction"):
        pretest.candidate_set(model, [100], direction="sideways")
    # any given vector is stored as a unit vector
    cs = pretest.candidate_set(model, [100, 101], direction=np.array([0.0, 3.0, 4.0]))
    np.testing.assert_allclose(cs.directions, [[0, 0.6, 0.8]] * 2)
    with pytest.raises(PretestError, match="band"):
        pretest.select_target_modes([0.0, 0.0, 10.0, 20.0], 2, band_hz=(50.0, 90.0))
    with pytest.raises(PretestError, match="only 2"):
        pretest.select_target_modes([0.0, 0.0, 10.0, 20.0], 2, n_modes=5)
    with pytest.raises(ValueError, match="extra"):
        PretestConfig(n_sensor=3)


# --------------------------------------------------------------------------- the example subframe


@pytest.fixture(scope="module")
def subframe(tmp_path_factory):
    out = tmp_path_factory.mktemp("subframe")
    ex = femodel.example_subframe(out, target_dof=5000, units="mm-t-s")
    model = femodel.read_bdf(ex.bdf, units="mm-t-s")
    asm = femodel.assemble(model)
    target = pretest.compute_target_modes(asm, n_modes=20)
    return ex, model, asm, target


def test_subframe_20_sensors_20_modes(subframe, tmp_path):
    ex, model, asm, target = subframe
    assert target.n_rigid == 6 and target.indices.size == 20 and np.all(target.frequencies_hz > 1.0)
    res = pretest.plan_pretest(model, PretestConfig(n_sensors=20, n_modes=20), assembly=asm, target=target)
    m = res.metrics
    assert res.sensors.n_rows == 20 and len(set(res.sensors.grids.tolist())) == 20
    assert np.isfinite(m.fim_condition) and m.fim_condition < 1e4
    assert m.automac_max_offdiag < 0.9
    # the layout beats random layouts of the same size on det(FIM) by a wide margin
    cands = res.candidates
    phi = np.asarray(femodel.sensor_matrix(asm, cands.grids, cands.directions) @ target.shapes)
    rng = np.random.default_rng(0)
    rand = [pretest.layout_metrics(phi[rng.choice(cands.n_rows, 20, replace=False)]).fim_log10_det for _ in range(50)]
    assert m.fim_log10_det > np.max(rand)
    # mass loading: 20 x 0.5 g + 5 g on a ~16 kg structure lowers every target mode slightly
    assert np.all(res.mass_loading.shift_hz <= 0) and np.all(res.mass_loading.relative_shift > -0.02)
    # drive collocated with a sensor and co-oriented
    d = res.drives
    k = np.flatnonzero(res.sensors.grids == d.grids[0])
    assert k.size == 1 and np.allclose(res.sensors.directions[k[0]], d.directions[0])


def test_layout_file_round_trip_and_acquisition_reads_it(subframe, tmp_path):
    ex, model, asm, target = subframe
    res = pretest.plan_pretest(model, PretestConfig(n_sensors=12, n_modes=10, min_distance_m=0.08), assembly=asm,
                               target=pretest.compute_target_modes(asm, n_modes=10))
    path = pretest.write_layout(tmp_path / "lay" / "layout.json", res, model_path=ex.bdf, units="mm-t-s")
    lay = pretest.read_layout(path)
    assert lay.model_units == "mm-t-s"
    assert lay.model_path == str(ex.bdf.resolve())
    np.testing.assert_array_equal(lay.grids(), res.sensors.grids)
    np.testing.assert_allclose(lay.directions(), res.sensors.directions, atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(lay.directions(), axis=1), 1.0)
    # coordinates in metres, from the model's own (SI) grid positions
    np.testing.assert_allclose([c.xyz_m for c in lay.channels], model.xyz[model.grid_index(lay.grids())])
    xyz = np.array([c.xyz_m for c in lay.channels])
    dist = np.linalg.norm(xyz[:, None] - xyz[None], axis=-1) + np.eye(len(xyz)) * 1e9
    assert dist.min() >= 0.08
    # metrics of the layout re-evaluated from the file equal the planner's
    again = pretest.evaluate_channels(asm, lay.grids(), lay.directions(), res.target)
    assert again.fim_condition == pytest.approx(res.metrics.fim_condition, rel=1e-9)
    assert again.automac_max_offdiag == pytest.approx(res.metrics.automac_max_offdiag, rel=1e-9)
    from acquisition import read_layout as acq_read

    acq = acq_read(path)
    assert [c.name for c in acq.sensors] == [c.name for c in lay.channels]
    assert [c.grid for c in acq.drives] == [c.grid for c in lay.drives]


def test_triax_layout_and_constraints_on_model(subframe):
    ex, model, asm, target = subframe
    t10 = pretest.compute_target_modes(asm, n_modes=10)
    free = pretest.plan_pretest(model, PretestConfig(n_sensors=6, n_modes=10, triax=True), assembly=asm, target=t10)
    assert free.sensors.n_rows == 18
    grids, counts = np.unique(free.sensors.grids, return_counts=True)
    assert grids.size == 6 and np.all(counts == 3)
    assert free.channel_names[:3] == ("acc01x", "acc01y", "acc01z")
    include = [int(model.grid_ids[5])]
    exclude = grids[:2].tolist()
    res = pretest.plan_pretest(
        model, PretestConfig(n_sensors=6, n_modes=10, triax=True, include_grids=include, exclude_grids=exclude),
        assembly=asm, target=t10)
    chosen = set(res.sensors.grids.tolist())
    assert include[0] in chosen and not chosen & set(exclude)


def test_bad_input_on_model(subframe):
    ex, model, asm, target = subframe
    with pytest.raises(PretestError, match=r"include grid\(s\) \[99999999\] not defined"):
        pretest.plan_pretest(model, PretestConfig(n_sensors=5, include_grids=(99999999,)), assembly=asm, target=target)
    with pytest.raises(PretestError, match="only"):
        pretest.plan_pretest(model, PretestConfig(n_sensors=100000), assembly=asm, target=target)
    with pytest.raises(PretestError, match="no elastic mode in the band"):
        pretest.compute_target_modes(asm, band_hz=(1.0, 5.0))


def test_cli_json_and_errors(subframe, tmp_path, capsys):
    from frfcal.cli import main

    ex = subframe[0]
    out = tmp_path / "cli" / "layout.json"
    rc = main(["pretest", str(ex.bdf), "--units", "mm-t-s", "--sensors", "10", "--modes", "8",
               "--out", str(out), "--json", "--shaker-candidates", "3"])
    assert rc == 0
    data = json.loads(capsys.readouterr().out)
    assert data["format"] == "frfcal-layout" and len(data["channels"]) == 10 and len(data["drives"]) == 1
    assert len(data["target_modes_hz"]) == 8 and len(data["metrics"]["drive_candidates"]) == 3
    assert out.exists() and all((tmp_path / "cli" / f).exists() for f in ("layout_layout.png", "layout_automac.png"))
    assert json.loads(out.read_text())["channels"] == data["channels"]
    # the same layout evaluated from its file reproduces the planner's metrics
    rc = main(["pretest", str(ex.bdf), "--units", "mm-t-s", "--modes", "8", "--evaluate", str(out), "--json"])
    assert rc == 0
    ev = json.loads(capsys.readouterr().out)
    assert ev["metrics"]["fim_condition"] == pytest.approx(data["metrics"]["fim_condition"], rel=1e-8)
    assert ev["metrics"]["automac_max_offdiag"] == pytest.approx(data["metrics"]["automac_max_offdiag"], rel=1e-8)
    assert ev["mass_loading_shift_hz"] == pytest.approx(data["metrics"]["mass_loading"]["shift_hz"], rel=1e-8)
    rc = main(["pretest", str(ex.bdf), "--units", "mm-t-s", "--include", "99999999", "--out", str(out)])
    assert rc == 2
    assert "99999999" in capsys.readouterr().err
    rc = main(["pretest", str(ex.bdf), "--units", "mm-t-s", "--sensors", "100000", "--out", str(out)])
    assert rc == 2
    assert "only" in capsys.readouterr().err


@pytest.mark.slow
def test_real_shell_deck_femap_exhaust():
    """20 normal sensors for the first 20 modes of a real NX shell deck (in-lbf-s, constrained)."""
    from tests.conftest import reference_path

    deck = reference_path("nastran", "femap_exhaust", "modal_example_from_op2.bdf")
    model = femodel.read_bdf(deck, units="in-lbf-s")
    res = pretest.plan_pretest(model, PretestConfig(n_sensors=20, n_modes=20))
    assert res.target.n_rigid == 0 and res.target.indices[0] == 0
    assert res.sensors.n_rows == 20 and len(set(res.sensors.grids.tolist())) == 20
    assert res.metrics.fim_condition < 1e4 and res.metrics.automac_max_offdiag < 0.9
    # normals of the chosen sensors are unit vectors normal to the attached shells
    np.testing.assert_allclose(np.linalg.norm(res.sensors.directions, axis=1), 1.0)


def test_plan_with_automac_refinement(subframe):
    ex, model, asm, target = subframe
    res = pretest.plan_pretest(model, PretestConfig(n_sensors=20, n_modes=20, refine_automac_decades=1.0),
                               assembly=asm, target=target)
    ref = res.extra["automac_refinement"]
    assert res.metrics.automac_max_offdiag == pytest.approx(ref["automac_after"], rel=1e-9)
    assert ref["automac_after"] < ref["automac_before"]
    assert res.metrics.fim_log10_det >= ref["log10_det_before"] - 1.0 - 1e-9
    assert pretest.layout_dict(res)["metrics"]["automac_refinement"]["swaps"] == ref["swaps"] > 0


def test_cli_text_triax_free_drive(subframe, tmp_path, capsys):
    from frfcal.cli import main

    ex = subframe[0]
    out = tmp_path / "t.json"
    rc = main(["pretest", str(ex.bdf), "--units", "mm-t-s", "--sensors", "4", "--modes", "6", "--triax",
               "--min-distance", "0.15", "--free-drive", "--drive-criterion", "product", "--out", str(out),
               "--no-figures"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "largest off-diagonal" in text and "drive1: grid" in text and "acc04z" in text
    data = json.loads(out.read_text())
    assert len(data["channels"]) == 12 and data["metrics"]["drive_criterion"] == "product"
    xyz = np.array([c["xyz_m"] for c in data["channels"]])
    d = np.linalg.norm(xyz[:, None] - xyz[None], axis=-1)
    assert d[d > 0].min() >= 0.15
    rc = main(["pretest", str(ex.bdf), "--units", "mm-t-s", "--modes", "6", "--evaluate", str(out)])
    assert rc == 0 and "condition number" in capsys.readouterr().out
    rc = main(["pretest", str(ex.bdf), "--units", "mm-t-s", "--direction", "sideways", "--out", str(out)])
    assert rc == 2 and "direction" in capsys.readouterr().err
