"""The frame example: lumped (singular) mass, rigid modes, symmetry, parameters, units, springs, CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

import femodel
from femodel import example_frame, read_parameters
from femodel._example_frame import (
    E_ALU_PA, E_STEEL_PA, ENGINE_MASS_KG, K_MOUNT_XY_N_M, K_MOUNT_Z_N_M, RHO_STEEL_KG_M3, TANK_MASS_KG,
)
from frfcal.cli import main


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    d = tmp_path_factory.mktemp("frame")
    ex = example_frame(d / "si", units="si")
    pm = femodel.parametric_model(ex.params)
    p0 = np.zeros(pm.n_params)
    modes = pm.modes(p0, 40)
    return ex, pm, modes


def test_unpacks_as_paths_and_size_knob(tmp_path):
    bdf, params = example_frame(tmp_path / "a")
    assert bdf.name == "frame.bdf" and params.name == "frame_params.toml"
    for n in (2, 6, 12, 17):
        ex = example_frame(tmp_path / f"n{n}", elements_per_member=n)
        assert ex.n_dof == 84 * n - 12 and ex.n_elements == 14 * n
    assert example_frame(tmp_path / "d").n_dof < 1500


def test_deterministic(tmp_path):
    a = example_frame(tmp_path / "a")
    b = example_frame(tmp_path / "b")
    assert a.bdf.read_bytes() == b.bdf.read_bytes() and a.params.read_bytes() == b.params.read_bytes()


def test_cards_and_lumped_mass(frame):
    ex, pm, _ = frame
    fe = pm.assembly.model
    assert set(fe.elements) == {"CBAR", "CELAS2", "CONM2"}
    assert len(fe.elements["CBAR"]) == ex.n_elements and len(fe.elements["CELAS2"]) == 12
    assert not fe.coupmass
    M = pm.mass(np.zeros(pm.n_params)).toarray()
    conm2_grids = fe.elements["CONM2"]["nodes"][:, 0]
    rot = pm.aset.component >= 4
    bar_rot = rot & ~np.isin(pm.aset.grid, conm2_grids)
    # default lumped mass: bar rotations carry no mass at all (only the three CONM2 grids have rotary
    # inertia), so M is singular
    assert np.all(M[bar_rot] == 0) and np.all(M[:, bar_rot] == 0)
    assert np.all(np.diag(M)[~bar_rot] > 0)
    assert np.linalg.matrix_rank(M) == int(np.sum(~bar_rot)) == len(pm.aset) - 3 * (ex.n_grids - 3)
    # total mass: bars + engine + tank, from the deck
    mp = femodel.mass_properties(pm.assembly)
    assert mp.mass == pytest.approx(ex.mass_kg, rel=1e-9)
    bars = ex.mass_kg - 2 * ENGINE_MASS_KG - TANK_MASS_KG
    assert 40.0 < bars < 120.0


def test_symmetric_and_rigid_modes(frame):
    _, pm, modes = frame
    p = np.full(pm.n_params, 0.1)
    for A in (pm.stiffness(p), pm.mass(p)):
        assert abs(A - A.T).max() <= 1e-12 * abs(A).max()
    assert modes.n_rigid == 6
    f = modes.frequencies_hz
    assert np.all(np.abs(f[:6]) < 1e-2)
    elastic = f[6:]
    assert 20.0 < elastic[0] < 80.0, elastic[:3]
    assert 15 <= np.sum(elastic < 500.0) <= 30, elastic  # 26 at the default mesh
    # mass-normalized shapes despite the singular mass matrix
    Phi = modes.shapes
    np.testing.assert_allclose(Phi.T @ (pm.mass(np.zeros(pm.n_params)) @ Phi), np.eye(Phi.shape[1]), atol=1e-9)


def test_parameter_file(frame):
    ex, pm, _ = frame
    ps = read_parameters(ex.params)
    assert ps.names == ("E_ladder", "rho_ladder", "E_cradle", "M_engine", "M_tank", "k_mount_xy", "k_mount_z")
    assert ps.units == "si" and ps.bdf.name == "frame.bdf"
    nominal = dict(zip(ps.names, pm.nominal))
    assert nominal["E_ladder"] == pytest.approx(E_STEEL_PA, rel=1e-12)
    assert nominal["rho_ladder"] == pytest.approx(RHO_STEEL_KG_M3, rel=1e-12)
    assert nominal["E_cradle"] == pytest.approx(E_ALU_PA, rel=1e-12)
    assert nominal["M_engine"] == pytest.approx(ENGINE_MASS_KG, rel=1e-12)
    assert nominal["M_tank"] == pytest.approx(TANK_MASS_KG, rel=1e-12)
    assert nominal["k_mount_xy"] == pytest.approx(K_MOUNT_XY_N_M, rel=1e-12)
    assert nominal["k_mount_z"] == pytest.approx(K_MOUNT_Z_N_M, rel=1e-12)
    assert np.all(ps.lower < 0) and np.all(ps.upper > 0) and np.all(ps.lower > -1)


def test_every_parameter_moves_the_band_modes(frame):
    """Each parameter, the mount springs included, changes the first 12 elastic frequencies."""
    _, pm, modes = frame
    f0 = modes.frequencies_hz[6:18]
    for j, name in enumerate(pm.parameters.names):
        p = np.zeros(pm.n_params)
        p[j] = 0.2
        f = pm.modes(p, 18).frequencies_hz[6:18]
        assert np.max(np.abs(f / f0 - 1)) > 1e-3, name
    # the springs carry load: stiffer mounts raise every elastic mode (Rayleigh)
    p = np.zeros(pm.n_params)
    p[[5, 6]] = 0.4
    assert np.all(pm.modes(p, 18).frequencies_hz[6:18] >= f0 * (1 - 1e-9))


def test_mm_t_s_equals_si(frame, tmp_path):
    _, _, modes = frame
    ex = example_frame(tmp_path, units="mm-t-s")
    pm = femodel.parametric_model(ex.params)
    assert pm.units == "mm-t-s"
    f = pm.modes(np.zeros(pm.n_params), 40).frequencies_hz
    np.testing.assert_allclose(f[6:], modes.frequencies_hz[6:], rtol=1e-9)
    assert ex.mass_kg == pytest.approx(frame[0].mass_kg, rel=1e-12)


def test_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="units must be one of"):
        example_frame(tmp_path, units="furlong")
    with pytest.raises(ValueError, match="elements_per_member must be an integer >= 2"):
        example_frame(tmp_path, elements_per_member=1)


def test_cli_example_frame_then_modes(tmp_path, capsys):
    assert main(["example", "frame", "--out", str(tmp_path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["structure"] == "frame" and info["units"] == "si" and info["n_dof"] == 492
    assert len(info["parameters"]) == 7 and info["parameters"][5]["ids"][0] == info["parameters"][5]["id"]
    assert main(["example", "frame", "--elements-per-member", "8", "--units", "mm-t-s",
                 "--out", str(tmp_path / "mm")]) == 0
    text = capsys.readouterr().out
    assert "7 parameters" in text and "k_mount_z" in text and "660 grid DOF" in text
    assert main(["modes", str(tmp_path / "frame.bdf"), "--n", "12", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["n_rigid"] == 6
    assert main(["example", "frame", "--elements-per-member", "1", "--out", str(tmp_path)]) == 2
    assert "--elements-per-member must be at least 2" in capsys.readouterr().err
