"""frfcal.synth: truth data against an independent direct solve, noise floor, files, line grid, seeds."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

import femodel
from acquisition.runfile import read_run
from frfcal.cli import main
from frfcal.synth import SynthChannel, SynthError, line_grid, modes_up_to, synthesize

BAND = (40.0, 110.0)


def frame_channels(pm):
    """Seven sensors (one pointing -Z, one oblique) and two drives on the frame."""
    g = np.asarray(pm.assembly.model.grid_ids)
    picks = [(3, (0, 0, 1)), (10, (0, 0, -1)), (20, (0, 1, 0)), (30, (0, 0, 1)), (45, (1, 0, 0)),
             (60, (0.6, 0.0, 0.8)), (70, (0, 0, 1))]
    sensors = [SynthChannel(f"acc{i + 1}", int(g[j]), d) for i, (j, d) in enumerate(picks)]
    drives = [SynthChannel("force1", int(g[5]), (0, 0, 1)), SynthChannel("force2", int(g[33]), (0.5, 0.3, 0.8))]
    return sensors, drives


@pytest.fixture(scope="module")
def frame_campaign(tmp_path_factory):
    d = tmp_path_factory.mktemp("synth_frame")
    bdf, params = femodel.example_frame(d / "model", units="mm-t-s")
    pm = femodel.parametric_model(params)
    sensors, drives = frame_channels(pm)
    camp = synthesize(bdf, params, d / "out", sensors=sensors, drives=drives, band_hz=BAND, n_articles=2,
                      base_lines=60, seed=7, parametric=pm)
    return camp, pm


def direct_accelerance(K, M, Phi, zeta, f_modes_hz, C, B, f_hz):
    """(K + i w Cd - w^2 M) x = B, dense, with Cd = M Phi diag(2 zeta w_k) Phi^T M; accelerance -w^2 C x."""
    K, M = K.toarray(), M.toarray()
    U = M @ Phi
    Cd = U @ np.diag(2 * zeta * 2 * np.pi * f_modes_hz) @ U.T
    Cm = C.toarray()
    out = []
    for f in f_hz:
        w = 2 * np.pi * f
        x = np.linalg.solve(K + 1j * w * Cd - w * w * M, B)
        out.append(-w * w * (Cm @ x))
    return np.array(out)


def check_against_direct(camp, pm, article, n_lines_each=4):
    """Relative error (per line, Frobenius over channels) of the stored truth vs the direct solve."""
    z = camp.truth()
    p = camp.p_true[article]
    K, M = pm.stiffness(p), pm.mass(p)
    modes, _ = modes_up_to(K, M, 3.0 * camp.band_hz[1])
    np.testing.assert_allclose(modes.frequencies_hz, z[f"modes_hz_{article}"], rtol=1e-9, atol=1e-12)  # ARPACK start vector
    C = femodel.sensor_matrix(pm.assembly, [s.grid for s in camp.sensors], [s.direction for s in camp.sensors])
    B = femodel.sensor_matrix(pm.assembly, [s.grid for s in camp.drives], [s.direction for s in camp.drives]).T.toarray()
    f = z[f"frequency_hz_{article}"]
    # lines at the peaks (closest to each in-range mode), plus a spread of off-resonance lines
    fm = z[f"modes_hz_{article}"]
    fm = fm[(fm > f[0]) & (fm < f[-1])]
    peaks = np.unique([np.argmin(np.abs(f - x)) for x in fm])[:n_lines_each]
    idx = np.unique(np.concatenate([peaks, np.linspace(0, f.size - 1, n_lines_each).astype(int)]))
    Hd = direct_accelerance(K, M, modes.shapes, z[f"zeta_{article}"], modes.frequencies_hz, C, B, f[idx])
    Ht = z[f"truth_{article}"][idx]
    return np.linalg.norm(Ht - Hd, axis=(1, 2)) / np.linalg.norm(Hd, axis=(1, 2))


def test_frame_truth_equals_direct_solve(frame_campaign):
    """Modes to 3 x band top + the higher-mode series reproduce the damped direct solve.

    The series is truncated at r^n/(1-r) < 1e-10 (r ~ 0.13 here), the modes
    are exact (dense eigensolver): agreement is at round-off, bound 1e-8.
    """
    camp, pm = frame_campaign
    for a in range(len(camp.articles)):
        err = check_against_direct(camp, pm, a)
        assert err.max() < 1e-8, err


def test_subframe_truth_equals_direct_solve(tmp_path):
    """The shell subframe (sparse Lanczos path, CQUAD4 drive points with a large residual)."""
    ex = femodel.example_subframe(tmp_path / "model", 1000, units="si")
    pm = femodel.parametric_model(ex.params)
    g = np.asarray(pm.assembly.model.grid_ids)
    gi = np.linspace(2, len(g) - 3, 5).astype(int)
    dirs = [(0, 0, 1), (0, 1, 0), (1, 0, 0), (0, 0, -1), (0, 0, 1)]
    sensors = [SynthChannel(f"acc{i + 1}", int(g[j]), d) for i, (j, d) in enumerate(zip(gi, dirs))]
    drives = [SynthChannel("force1", int(g[gi[1]]), (0, 1, 0))]
    camp = synthesize(ex.bdf, ex.params, tmp_path / "out", sensors=sensors, drives=drives, band_hz=(150.0, 400.0),
                      n_articles=1, base_lines=20, lines_per_bandwidth=1, write_uff=False, parametric=pm)
    assert pm.aset.grid.size > 600  # not the dense eigensolver path
    err = check_against_direct(camp, pm, 0, n_lines_each=3)
    assert err.max() < 1e-7, err

    # conventions shared with the calibration layer (units, e^{+iwt}, directions, rigid modes): its own
    # reduced model at p_true with the true damping reproduces the truth to its basis error
    from calibration import FRFModel, build_surrogate, modal_frf, reduced_modes

    z = camp.truth()
    C = femodel.sensor_matrix(pm.assembly, [s.grid for s in sensors], [s.direction for s in sensors])
    B = femodel.sensor_matrix(pm.assembly, [d.grid for d in drives], [d.direction for d in drives]).T.toarray()
    f = z["frequency_hz_0"]
    sur, _ = build_surrogate(FRFModel(pm.K, pm.M, B, C, parametric=pm), camp.p_true[0], (f[0], f[-1]),
                             basis_factor=4.0, enrich=False)
    lam, X = reduced_modes(sur, camp.p_true[0])
    f_red = np.sqrt(np.clip(lam, 0, None)) / (2 * np.pi)
    zeta = np.interp(f_red, z["modes_hz_0"], z["zeta_0"])
    H = modal_frf(lam, sur.outputs @ X, X.T @ sur.inputs, f, zeta, "accelerance", sur.rigid_hz)
    sd = np.mean(np.abs(np.log10(H / z["truth_0"])) ** 2)
    assert sd < 1e-7, sd  # 1.3e-9 measured on the 3000-DOF subframe; the noise floor is ~1e-4


def test_floor_sd_matches_noise_level(tmp_path, frame_campaign):
    camp, pm = frame_campaign
    s = 0.01
    quiet = synthesize(pm.bdf, camp.parameters, tmp_path, sensors=camp.sensors, drives=camp.drives, band_hz=BAND,
                       n_articles=2, base_lines=60, seed=3, noise_range=(s, s), noise_floor=0.0, write_uff=False,
                       parametric=pm)
    # relative complex noise of rms s: |log10(1 + n)|^2 ~ s^2 / ln(10)^2 (thousands of samples: +-5 %)
    expected = s**2 / np.log(10.0) ** 2
    assert quiet.floor_sd() == pytest.approx(expected, rel=0.1)
    assert quiet.floor_sd(["acc1", "acc2"], (60.0, 120.0)) == pytest.approx(expected, rel=0.2)
    # the default adds per-sensor levels in [0.005, 0.01] and an absolute floor (antiresonances): not below
    # the smallest relative level
    sd = camp.floor_sd()
    assert 0.005**2 / np.log(10.0) ** 2 < sd < 1e-2
    z = camp.truth()
    for a in range(2):
        r = (z[f"noisy_{a}"] - z[f"truth_{a}"]) / z[f"sigma_{a}"]
        assert np.mean(np.abs(r) ** 2) == pytest.approx(1.0, rel=0.1)
    with pytest.raises(SynthError, match="unknown channel"):
        camp.floor_sd(["acc99"])


def test_run_file_and_uff_round_trip(frame_campaign, tmp_path):
    camp, pm = frame_campaign
    z = camp.truth()
    for a, (path, uff) in enumerate(zip(camp.run_paths, camp.uff_paths)):
        run = read_run(path)
        assert run.article == camp.articles[a] and run.quantity == "accelerance" and run.status == "completed"
        assert [s.name for s in run.sensors] == [s.name for s in camp.sensors]
        for spec, ch in zip(run.sensors + run.drives, camp.sensors + camp.drives):
            assert spec.grid == ch.grid
            np.testing.assert_allclose(spec.direction, ch.direction, atol=1e-15)
        np.testing.assert_array_equal(run.frequency_hz, z[f"frequency_hz_{a}"])
        np.testing.assert_array_equal(run.frf, z[f"noisy_{a}"])
        np.testing.assert_array_equal(run.std_error, z[f"sigma_{a}"])
        assert run.valid.all() and run.plan["p_true"] == pytest.approx(camp.p_true[a].tolist())
        out = tmp_path / f"{a}.h5"
        assert main(["import-uff", str(uff), "--out", str(out)]) == 0
        back = read_run(out)
        np.testing.assert_array_equal(back.frequency_hz, run.frequency_hz)
        np.testing.assert_array_equal(back.frf, run.frf)
        assert [s.name for s in back.sensors] == [s.name for s in camp.sensors]


def test_direction_sign_and_reciprocity(frame_campaign):
    """A -Z sensor sees minus the +Z FRF; accelerance is reciprocal (H_ij = H_ji)."""
    camp, pm = frame_campaign
    from frfcal.synth import article_truth

    p = camp.p_true[0]
    g = camp.sensors[1].grid
    C = femodel.sensor_matrix(pm.assembly, [g, g, camp.drives[0].grid], [(0, 0, -1), (0, 0, 1), (0, 0, 1)])
    B = C.T.toarray()[:, [0, 2]]
    tr = article_truth(pm.stiffness(p), pm.mass(p), C, B, p, f_cut_hz=450.0, f_max_hz=165.0,
                       zeta_of_mode=lambda n: np.full(n, 1e-3), shift_hz=36.0)
    H = tr.frf(np.array([45.0, 77.0, 140.0]))
    np.testing.assert_allclose(H[:, 0, :], -H[:, 1, :], rtol=1e-13)
    np.testing.assert_allclose(H[:, 2, 0], H[:, 0, 1], rtol=1e-9)
    # the rigid-body modes give the mass line: far below the first elastic mode the accelerance is constant
    lo = tr.frf(np.array([0.5, 1.0]))
    np.testing.assert_allclose(lo[0], lo[1], rtol=2e-3)


def test_line_grid_is_denser_at_resonances(frame_campaign):
    camp, _ = frame_campaign
    z = camp.truth()
    for a in range(len(camp.articles)):
        f = z[f"frequency_hz_{a}"]
        fm, zm = z[f"modes_hz_{a}"], z[f"zeta_{a}"]
        base_ratio = (f[-1] / f[0]) ** (1 / 59) - 1  # relative step of the 60 base lines
        for fk, zk in zip(fm, zm):
            if zk == 0 or not f[0] < fk < f[-1]:
                continue
            near = f[np.abs(f - fk) <= 2.0001 * zk * fk]
            assert near.size >= 8, (fk, near.size)  # 4 per half-power bandwidth over +-1 bandwidth
            assert np.max(np.diff(near)) <= 0.51 * zk * fk + 1e-9 and 2 * zk < base_ratio / 5
    # different articles have their own lines
    assert z["frequency_hz_0"].size != z["frequency_hz_1"].size or np.any(z["frequency_hz_0"] != z["frequency_hz_1"])
    g = line_grid((10.0, 100.0), 5, [50.0], [0.01], 2)
    assert g.size == 5 + 13 and np.all(np.diff(g) > 0)


def test_seed_reproducibility(frame_campaign, tmp_path):
    camp, pm = frame_campaign
    kw = dict(sensors=camp.sensors[:3], drives=camp.drives[:1], band_hz=(40.0, 80.0), n_articles=1, base_lines=30,
              lines_per_bandwidth=2, write_uff=False, parametric=pm)
    one = synthesize(pm.bdf, camp.parameters, tmp_path / "a", seed=7, **kw)
    again = synthesize(pm.bdf, camp.parameters, tmp_path / "b", seed=7, **kw)
    z0, z1 = one.truth(), again.truth()
    for k in z0:
        np.testing.assert_array_equal(z0[k], z1[k], err_msg=k)
    other = synthesize(pm.bdf, camp.parameters, tmp_path / "c", seed=8, **kw)
    assert not np.allclose(other.p_true, one.p_true)
    assert not np.allclose(other.truth()["noisy_0"][:5], z0["noisy_0"][:5])
    # population offsets: 5-15 % magnitude (inside 90 % of the bounds), articles scattered about them by ~0.003
    mag = np.abs(camp.p_population)
    assert np.all((mag >= 0.05 - 1e-12) | np.isclose(mag, 0.9 * np.minimum(-pm.lower, pm.upper)))
    assert np.all(mag <= 0.15)
    assert 0.0005 < np.std(camp.p_true - camp.p_population) < 0.01


def test_mm_t_s_and_si_decks_give_the_same_truth(frame_campaign, tmp_path):
    """The deck's unit system is a boundary matter: the SI truth is the same from either deck."""
    camp, pm = frame_campaign  # mm-t-s
    bdf, params = femodel.example_frame(tmp_path / "si", units="si")
    kw = dict(sensors=camp.sensors[:3], drives=camp.drives[:1], band_hz=(40.0, 80.0), n_articles=1, base_lines=30,
              lines_per_bandwidth=2, write_uff=False, seed=5)
    mm = synthesize(pm.bdf, camp.parameters, tmp_path / "mm", parametric=pm, **kw).truth()
    si = synthesize(bdf, params, tmp_path / "si_out", **kw).truth()
    np.testing.assert_allclose(si["frequency_hz_0"], mm["frequency_hz_0"], rtol=1e-10)
    np.testing.assert_allclose(si["modes_hz_0"], mm["modes_hz_0"], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(si["truth_0"], mm["truth_0"], rtol=1e-7)
    np.testing.assert_allclose(si["noisy_0"], mm["noisy_0"], rtol=1e-7)


def test_all_modes_kept_small_model():
    """A 2-mass spring chain with every finite mode below the cut: modes only, exact."""
    from frfcal.synth import article_truth

    K = sp.csr_matrix(np.array([[2e4, -1e4], [-1e4, 1e4]]))
    M = sp.csr_matrix(np.diag([1.0, 2.0]))
    C = sp.csr_matrix(np.eye(2))
    B = np.array([[0.0], [1.0]])
    tr = article_truth(K, M, C, B, np.zeros(0), f_cut_hz=100.0, f_max_hz=30.0,
                       zeta_of_mode=lambda n: np.full(n, 0.01), shift_hz=1.0)
    assert np.isinf(tr.next_hz) and tr.series_ratio == 0.0 and tr.frequencies_hz.size == 2
    np.testing.assert_allclose(tr.residual, 0.0, atol=1e-18)
    f = np.array([3.0, 11.0, 25.0])
    w = 2 * np.pi * f
    lam, Phi = np.linalg.eigh(np.linalg.solve(np.sqrt(M.toarray()), np.linalg.solve(np.sqrt(M.toarray()), K.toarray()).T))
    Phi = np.linalg.solve(np.sqrt(M.toarray()), Phi)
    Cd = M @ Phi @ np.diag(2 * 0.01 * np.sqrt(lam)) @ Phi.T @ M
    want = np.array([-wk**2 * np.linalg.solve(K.toarray() + 1j * wk * Cd - wk**2 * M.toarray(), B) for wk in w])
    np.testing.assert_allclose(tr.frf(f), want, rtol=1e-10)


def test_offsets_and_campaign_file(frame_campaign, tmp_path):
    camp, pm = frame_campaign
    from frfcal.campaign import load_campaign

    path = camp.write_campaign(tmp_path / "camp" / "campaign.toml", calibrate=["acc1", "acc3", "acc5", "acc7"],
                               holdout=["acc2", "acc4", "acc6"], calibration={"starts": 2, "zeta0": 0.002},
                               output={"dir": "out", "figures": False})
    c = load_campaign(path)
    assert [r.article for r in c.run] == list(camp.articles)
    assert c.resolve(c.run[0].path).resolve() == camp.run_paths[0].resolve()
    assert c.resolve(c.model.parameters).resolve() == camp.parameters.resolve()
    assert c.band.low_hz == BAND[0] and c.calibration.starts == 2 and c.output.figures is False
    with pytest.raises(SynthError, match="not a synthesized sensor"):
        camp.write_campaign(tmp_path / "x.toml", calibrate=["nope"])
    one = synthesize(pm.bdf, camp.parameters, tmp_path / "o", sensors=camp.sensors, drives=camp.drives,
                     band_hz=BAND, n_articles=1, base_lines=20, offsets={"E_ladder": 0.1, "k_mount_z": -0.2},
                     scatter=0.0, write_uff=False, parametric=pm)
    expect = np.zeros(pm.n_params)
    expect[[0, 6]] = 0.1, -0.2
    np.testing.assert_array_equal(one.p_population, expect)
    np.testing.assert_array_equal(one.p_true[0], expect)


def test_errors(frame_campaign, tmp_path):
    camp, pm = frame_campaign
    kw = dict(sensors=camp.sensors, drives=camp.drives, parametric=pm)
    with pytest.raises(SynthError, match="unknown parameter"):
        synthesize(pm.bdf, camp.parameters, tmp_path, band_hz=BAND, offsets={"E_nope": 0.1}, **kw)
    with pytest.raises(SynthError, match="band_hz"):
        synthesize(pm.bdf, camp.parameters, tmp_path, band_hz=(100.0, 50.0), **kw)
    with pytest.raises(SynthError, match="mode_factor"):
        synthesize(pm.bdf, camp.parameters, tmp_path, band_hz=BAND, mode_factor=1.2, **kw)
    with pytest.raises(SynthError, match="duplicate channel"):
        synthesize(pm.bdf, camp.parameters, tmp_path, band_hz=BAND, sensors=camp.sensors + camp.sensors[:1],
                   drives=camp.drives, parametric=pm)
    with pytest.raises(SynthError, match="acc9.*grid 999999|grid 999999"):
        synthesize(pm.bdf, camp.parameters, tmp_path, band_hz=BAND,
                   sensors=[SynthChannel("acc9", 999999, (0, 0, 1))], drives=camp.drives, parametric=pm)
    with pytest.raises(SynthError, match="direction"):
        SynthChannel("acc1", 1, (0, 0, 0))
    assert sp.issparse(femodel.sensor_matrix(pm.assembly, [camp.sensors[0].grid], [(0, 0, 1)]))
