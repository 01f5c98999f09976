"""Screening and acceptance kernels of the diagnosis (calibration/_diagnose.py) on the example frame (492 DOF).

The truth is the frame model plus one known effect the calibration model
lacks (a mass at a grid, a contact spring between a cradle grid and the rail
grid above it, a stiffness factor on three bars); the data are its dense
full-order FRFs equalized at ZETA (optionally with log-normal noise). The
candidates are every grid mass, springs to ground, contact springs between
the parts and factors on clusters of three bars: their derivative matrices
come from :meth:`femodel.ParametricModel.with_terms`.
"""

from __future__ import annotations

import numpy as np
import pytest

import femodel
from calibration import (
    CalibrationError,
    FitData,
    FRFModel,
    Objective,
    build_surrogate,
    full_order_frf,
    half_bandwidth_frequencies,
)
from calibration import (
    CandidateTerm,
    accept,
    candidate_jacobian,
    cross_validate,
    extend_with_candidates,
    fit_with,
    holdout_sd,
    rank_separating,
    screen,
    separating_effect,
    shifted_solver,
)
from femodel import AddedMass, AddedSpring, ElementFactor, parametric_model
from tests.calibration._models import frame_sensor_model

ZETA = 0.02
BAND = (5.0, 150.0)
SHIFT_HZ = max(BAND[0] / 4, BAND[1] / 50)
#: the truth's existing parameters (E_ladder, rho_ladder, E_cradle, M_engine, M_tank, k_mount_xy, k_mount_z)
P_OLD = np.array([0.05, -0.03, 0.08, 0.1, -0.1, 0.2, -0.1])


def _contact_pairs(fe):
    """(cradle grid, nearest ladder grid) within 0.15 m that no element or mount spring joins."""
    bars = fe.elements["CBAR"]
    cradle = np.unique(bars["nodes"][bars["pid"] == 3])
    ladder = np.unique(bars["nodes"][bars["pid"] != 3])
    springs = fe.elements["CELAS2"]
    joined = {tuple(sorted(map(int, n))) for n in springs["nodes"]}
    xyz = {int(g): fe.xyz[i] for i, g in enumerate(fe.grid_ids)}
    pairs = []
    for g in cradle:
        d = np.array([np.linalg.norm(xyz[int(g)] - xyz[int(h)]) for h in ladder])
        h = int(ladder[np.argmin(d)])
        if d.min() < 0.15 and tuple(sorted((int(g), h))) not in joined:
            pairs.append((int(g), h))
    return pairs


def _terms(pm):
    fe = pm.assembly.model
    gids = [int(g) for g in fe.grid_ids]
    eids = [int(e) for e in fe.elements["CBAR"].ids]
    terms = [AddedMass(f"m{g}", (g,), 0.5) for g in gids]
    terms += [AddedSpring(f"kg{g}", ((g, 3, 0, 0),), 1e4) for g in gids[::3]]
    terms += [AddedSpring(f"kc{a}_{b}", ((a, 3, b, 3),), 2e5) for a, b in _contact_pairs(fe)]
    terms += [ElementFactor(f"f{eids[i]}", tuple(eids[i:i + 3])) for i in range(0, len(eids) - 2, 3)]
    return terms


def _candidates(pm, terms, p):
    """CandidateTerm of every term: dK/dc, dM/dc at (p, c = 0) from with_terms."""
    ext = pm.with_terms(terms)
    pe = np.r_[p, np.zeros(len(terms))]
    out = []
    for k, t in enumerate(terms):
        j = pm.n_params + k
        dK, dM = ext.dK(pe, j), ext.dM(pe, j)
        out.append(CandidateTerm(t.name, dK if abs(dK).max() > 0 else None, dM if abs(dM).max() > 0 else None,
                                 t.lower, t.upper))
    return out


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    ex = femodel.example_frame(tmp_path_factory.mktemp("diag_frame"))
    pm = parametric_model(ex.params)
    _, _, model = frame_sensor_model(pm)
    sur, T = build_surrogate(model, np.zeros(pm.n_params), BAND)
    terms = _terms(pm)
    cands = _candidates(pm, terms, P_OLD)
    return pm, model, sur, T, terms, cands


def _truth_data(pm, model, term, c, sigma=0.0, seed=0, zeta=ZETA):
    """Equalized FRFs of the frame with ``term`` at magnitude ``c`` (none if term is None), log-normal noise sigma."""
    f = half_bandwidth_frequencies(*BAND, zeta, 3)
    if term is None:
        H = full_order_frf(model, P_OLD, f, zeta)
    else:
        ext = pm.with_terms([term])
        mt = FRFModel(ext.K, ext.M, model.inputs, model.outputs, parameter_names=ext.names, parametric=ext)
        H = full_order_frf(mt, np.r_[P_OLD, c], f, zeta)
    if sigma:
        rng = np.random.default_rng(seed)
        H = H * 10 ** (sigma * (rng.normal(size=H.shape) + 1j * rng.normal(size=H.shape)) / np.sqrt(2))
    return [FitData(f, H, model.output_names)]


def _screen(frame, data, **kw):
    pm, model, sur, T, terms, cands = frame
    return screen(sur, T, np.zeros(pm.n_params), data, ZETA, cands, pm.lower, pm.upper, model=model,
                  shift_hz=SHIFT_HZ, **kw)


def _by_name(cands, name):
    return next(c for c in cands if c.name == name)


def test_candidate_jacobian_is_the_first_order_change_of_the_extended_surrogate(frame):
    pm, model, sur, T, terms, cands = frame
    data = _truth_data(pm, model, AddedMass("m_truth", (30,), 0.5), 1.0)
    contact = next(c.name for c in cands if c.name.startswith("kc"))
    names = ["m30", "m7", contact, "f1", "f40", "kg1"]
    sub = [_by_name(cands, n) for n in names]
    Jc = candidate_jacobian(sur, T, P_OLD, data, ZETA, sub)
    assert Jc.shape == (2 * data[0].n_values, len(sub))
    h = 1e-2  # central: O(h^2); a smaller step meets the rigid modes' numerical frequencies (~5e-3 Hz)
    # crossing the surrogate's rigid threshold, a jump of ~1e-4 in r
    for k, c in enumerate(sub):
        sur_e, _ = extend_with_candidates(sur, T, model, [c], shift_hz=SHIFT_HZ)
        obj = Objective(sur_e, data, ZETA)
        if c.name.startswith("kg"):
            # a spring to ground on the free-free frame turns a rigid mode into one at sqrt(c): its modal
            # damping 2 zeta omega is not differentiable at c = 0; compare with the analytic derivative
            ref = obj.evaluate(np.r_[P_OLD, 0.0])[1][:, -1]
        else:
            ref = (obj.residual(np.r_[P_OLD, h]) - obj.residual(np.r_[P_OLD, -h])) / (2 * h)
        # the candidate's static corrections change the first-order response little: T represents the
        # drive and sensor responses, which is all dH/dc = -Y^T dZ U needs
        err = np.linalg.norm(Jc[:, k] - ref) / np.linalg.norm(ref)
        assert err < (0.03 if c.name.startswith("f") else 0.01), (c.name, err)


def test_candidate_jacobian_is_the_first_order_change_of_the_full_model(frame):
    """Against the full-order model (dense, all modes): the basis without the candidate's static corrections
    carries its first-order effect (the adjoint form needs only the drive and sensor responses)."""
    from calibration._fit import stacked_residual
    from calibration._metric import log_deviation

    pm, model, sur, T, terms, cands = frame
    data = _truth_data(pm, model, AddedMass("m_truth", (30,), 0.5), 1.0)
    f = data[0].freq_hz
    contact = _contact(terms)
    for name, term in (("m30", AddedMass("t", (30,), 0.5)), (contact.name, AddedSpring("t", contact.dofs, 2e5))):
        ext = pm.with_terms([term])
        mt = FRFModel(ext.K, ext.M, model.inputs, model.outputs, parameter_names=ext.names, parametric=ext)

        def r(c):
            return stacked_residual(log_deviation(full_order_frf(mt, np.r_[P_OLD, c], f, ZETA), data[0].frf).ravel())

        h = 1e-2
        fd = (r(h) - r(-h)) / (2 * h)
        jc = candidate_jacobian(sur, T, P_OLD, data, ZETA, [_by_name(cands, name)])[:, 0]
        err = np.linalg.norm(jc - fd) / np.linalg.norm(fd)
        assert err < 0.01, (name, err)
        print(f"{name}: |J_c - FD(full order)| / |FD| = {err:.2e}")


def test_candidate_jacobian_follows_the_objective_weights_and_masks(frame):
    from calibration import log_frequency_weights

    pm, model, sur, T, terms, cands = frame
    d = _truth_data(pm, model, AddedMass("m_truth", (30,), 0.5), 1.0)[0]
    mask = np.random.default_rng(5).random(d.frf.shape) < 0.7
    # two data sets: one line-weighted on a drive subset, one masked
    sets = [FitData(d.freq_hz, d.frf[:, :, [1]], d.outputs, inputs=(model.input_names[1],),
                    weights=log_frequency_weights(d.freq_hz) * np.linspace(0.5, 2, d.freq_hz.size)),
            d.masked(mask)]
    sub = [_by_name(cands, "m30"), _by_name(cands, "kg1")]
    Jc = candidate_jacobian(sur, T, P_OLD, sets, ZETA, sub, chunk_bytes=1)  # one candidate per chunk
    for k, c in enumerate(sub):
        sur_e, _ = extend_with_candidates(sur, T, model, [c], shift_hz=SHIFT_HZ)
        Je = Objective(sur_e, sets, ZETA).evaluate(np.r_[P_OLD, 0.0])[1][:, -1]
        assert np.linalg.norm(Jc[:, k] - Je) < 0.01 * np.linalg.norm(Je), c.name


def test_a_mass_at_a_grid_ranks_first_with_the_density_refitted(frame):
    pm, model, sur, T, terms, cands = frame
    data = _truth_data(pm, model, AddedMass("m_truth", (30,), 0.5), 1.0, sigma=0.005)
    s = _screen(frame, data, n_check=5)
    assert s.sd_baseline < 0.2 * s.sd_start  # the existing parameters (densities, masses) absorb a part
    assert s.best == "m30"
    assert int(np.argmax(s.explained)) == s.names.index("m30")
    assert s.significant[s.names.index("m30")]
    chk = s.check("m30")
    assert chk.c == pytest.approx(1.0, rel=0.2)
    assert chk.explained > 0.9
    # bounds hold; a mass whose best linear magnitude is negative is clipped to 0 and explains nothing
    lo = np.array([c.lower for c in cands])
    assert np.all(s.c_linear >= lo) and np.all(s.explained >= 0)
    assert np.all(s.explained[s.c_linear == 0] == 0) and np.any(s.c_linear == 0)
    # the linearized magnitude is already close (an effect of a fraction of a bandwidth)
    assert s.c_linear[s.names.index("m30")] == pytest.approx(1.0, rel=0.2)
    # the neighbours explain less once [p, c] is re-fitted
    assert all(c.explained < chk.explained for c in s.checks if c.name != "m30")


def test_a_contact_spring_ranks_first(frame):
    pm, model, sur, T, terms, cands = frame
    contact = [t for t in terms if t.name.startswith("kc")]
    true = contact[len(contact) // 2]
    data = _truth_data(pm, model, AddedSpring("k_truth", true.dofs, true.scale), 1.5, sigma=0.005)
    s = _screen(frame, data, n_check=5)
    assert s.best == true.name
    assert s.check(true.name).c == pytest.approx(1.5, rel=0.2)


def test_a_stiffness_loss_on_three_bars_ranks_first(frame):
    pm, model, sur, T, terms, cands = frame
    true = ElementFactor("f_truth", next(t for t in terms if t.name == "f13").elements)
    data = _truth_data(pm, model, true, -0.4, sigma=0.005)
    i = [c.name for c in cands].index("f13")
    # -40 % on three rail bars moves modes by more than a half-power bandwidth at ZETA: the log-ratio
    # metric is far from linear in c there and the linear screen alone misses the effect ...
    alone = _screen(frame, data, n_check=0)
    assert int(np.argsort(-alone.explained).tolist().index(i)) > 10
    # ... at the damping of a continuation stage the metric is smooth and it ranks first
    cont = [(0.05, _truth_data(pm, model, true, -0.4, sigma=0.005, seed=1, zeta=0.05))]
    s = _screen(frame, data, n_check=5, continuation=cont)
    assert int(np.argmax(s.stage_explained[0])) == i
    assert s.best == "f13"
    assert s.check("f13").c == pytest.approx(-0.4, rel=0.2)
    assert s.check("f13").explained > 0.9


def test_nonlinear_checks_in_a_process_pool_match_the_serial_ones(frame):
    """screen(executor=...) runs the re-fits of the checked candidates in workers: the same checks and ranking."""
    from calibration import make_executor

    pm, model, sur, T, terms, cands = frame
    data = _truth_data(pm, model, AddedMass("m_truth", (30,), 0.5), 1.0, sigma=0.005)
    serial = _screen(frame, data, n_check=4)
    with make_executor(None, 2) as ex:
        pooled = _screen(frame, data, n_check=4, executor=ex)
    assert [c.name for c in pooled.checks] == [c.name for c in serial.checks]
    assert pooled.best == serial.best == "m30"
    np.testing.assert_array_equal(pooled.order, serial.order)
    for a, b in zip(pooled.checks, serial.checks):
        assert a.c == pytest.approx(b.c, rel=1e-9, abs=1e-12)
        assert a.sd == pytest.approx(b.sd, rel=1e-9)
        np.testing.assert_allclose(a.p, b.p, rtol=1e-9, atol=1e-12)
    assert serial.check("m30").c == pytest.approx(1.0, rel=0.05)


def test_a_check_stopped_on_its_budget_is_continued_or_ranked_by_its_linear_score(frame):
    """A nonlinear check that stops on max_nfev has not reached its minimum: its stalled fraction is a lower
    bound. It is continued on the last stage (continue_checks); one still unconverged ranks by the larger of
    the stalled and the linear fraction, a converged one by its nonlinear fraction."""
    pm, model, sur, T, terms, cands = frame
    data = _truth_data(pm, model, AddedMass("m_truth", (30,), 0.5), 1.0, sigma=0.005)
    stalled = _screen(frame, data, n_check=4, max_nfev=3, continue_checks=0)
    assert not all(c.converged for c in stalled.checks) and all(c.continued == 0 for c in stalled.checks)
    for c in stalled.checks:
        assert c.explained_linear == stalled.explained[c.index]
        assert c.score == (c.explained if c.converged else max(c.explained, c.explained_linear))
    scores = [c.score for c in stalled.checks]
    assert scores == sorted(scores, reverse=True)
    assert list(stalled.order[:4]) == [c.index for c in stalled.checks]
    # continued from where they stopped (the same baseline and linear stage: same budget): each unconverged
    # check is continued and gets no worse
    cont = _screen(frame, data, n_check=4, max_nfev=3, continue_checks=60)
    np.testing.assert_array_equal(cont.explained, stalled.explained)
    for c in stalled.checks:
        d = cont.check(c.name)
        assert d.sd <= c.sd * (1 + 1e-12)
        if not c.converged:
            assert d.continued >= 1
        assert d.score == (d.explained if d.converged else max(d.explained, d.explained_linear))
    gain = [cont.check(c.name).explained - c.explained for c in stalled.checks if not c.converged]
    assert max(gain) > 0.01  # the budget had stopped them short of their minimum


def test_the_best_candidate_of_every_group_is_checked_too(frame):
    """groups (e.g. the families): besides the n_check best overall, every group's best linear candidate gets
    a nonlinear check, so a family of many near-duplicates does not crowd the others out."""
    pm, model, sur, T, terms, cands = frame
    data = _truth_data(pm, model, AddedMass("m_truth", (30,), 0.5), 1.0, sigma=0.005)
    labels = [c.name.rstrip("0123456789_").rstrip("0123456789") for c in cands]  # m, kg, kc, f
    s = _screen(frame, data, n_check=2, groups=labels)
    top = [int(i) for i in np.argsort(-s.explained, kind="stable")[:2]]
    best_of = {}
    for i in np.argsort(-s.explained, kind="stable"):
        if s.explained[i] > 0:
            best_of.setdefault(labels[i], int(i))
    want = set(top) | set(best_of.values())
    assert {c.index for c in s.checks} == want and len(set(labels)) == 4 and len(want) > 2
    assert s.best == "m30"
    with pytest.raises(CalibrationError, match="group labels"):
        _screen(frame, data, n_check=2, groups=labels[:-1])


def test_without_an_effect_no_candidate_is_significant(frame):
    pm, model, sur, T, terms, cands = frame
    for seed in (0, 1):
        data = _truth_data(pm, model, None, 0.0, sigma=0.01, seed=seed)
        s = _screen(frame, data, n_check=2)
        # the residual is the noise: SD ~ sigma^2 (complex log deviation, sigma^2 / 2 per part)
        assert s.sd_baseline == pytest.approx(0.01**2, rel=0.05)
        # a random direction explains ~1/(n - k) of it
        assert s.noise_explained == pytest.approx(1 / (s.n_residuals - s.rank_p), rel=0.05)
        assert not s.significant.any(), s.names[int(np.argmax(s.explained))]
        assert s.explained.max() < s.threshold[-1]
        assert all(c.explained < s.threshold[-1] for c in s.checks)


def test_screen_rejects_bad_input(frame):
    pm, model, sur, T, terms, cands = frame
    data = _truth_data(pm, model, None, 0.0)
    with pytest.raises(CalibrationError, match="acts on"):
        screen(sur, T, P_OLD, data, ZETA, [CandidateTerm("x", np.eye(3), None, 0, 1)], pm.lower, pm.upper,
               n_check=0)
    with pytest.raises(CalibrationError, match="full-order model"):
        screen(sur, T, P_OLD, data, ZETA, cands[:3], pm.lower, pm.upper, n_check=2)
    with pytest.raises(CalibrationError, match="repeated"):
        screen(sur, T, P_OLD, data, ZETA, [cands[0], cands[0]], pm.lower, pm.upper, n_check=0)
    with pytest.raises(CalibrationError, match="neither dK nor dM"):
        CandidateTerm("zero", np.zeros((4, 4)), None, 0, 1)
    with pytest.raises(CalibrationError, match="bounds"):
        CandidateTerm("b", np.eye(4), None, 1, 0)


def test_zoomed_candidates_score_as_if_screened_from_the_start_and_are_checked(frame):
    """The zoom's candidates are scored at the stages' baselines as they stand: the same linear fractions and
    magnitudes as in one screening of them all; they take part in the significance test (Bonferroni over
    the total) and in the nonlinear checks, and the callback sees the grown list each round."""
    pm, model, sur, T, terms, cands = frame
    data = _truth_data(pm, model, AddedMass("m_truth", (30,), 0.5), 1.0, sigma=0.005)
    held = {"m30", "m31", "m29", next(c.name for c in cands if c.name.startswith("kg"))}
    first = [c for c in cands if c.name not in held]
    later = [c for c in cands if c.name in held]
    calls = []

    def zoom(names, explained):
        calls.append((len(names), len(explained)))
        if len(calls) == 1:  # m29, m30 (in grid order) refine m28
            return [(c, "mass" if c.name.startswith("m") else "spring", "m28") for c in later[:2]]
        if len(calls) == 2:  # and m31 refines m30, the spring m28 too
            return [(c, "mass" if c.name.startswith("m") else "spring", "m30" if c.name == "m31" else "m28")
                    for c in later[2:]]
        return []

    groups = ["mass" if c.name.startswith("m") else "other" for c in first]
    s = screen(sur, T, np.zeros(pm.n_params), data, ZETA, first, pm.lower, pm.upper, model=model, shift_hz=SHIFT_HZ,
               n_check=3, groups=groups, zoom=zoom, zoom_rounds=5)
    full = _screen(frame, data, n_check=0)
    assert calls == [(len(first), len(first)), (len(first) + 2, len(first) + 2), (len(cands), len(cands))]
    assert s.names == tuple(c.name for c in first + later) and set(s.zoomed) == held
    idx = [full.names.index(n) for n in s.names]
    np.testing.assert_allclose(s.explained, full.explained[idx], rtol=1e-9, atol=1e-14)
    np.testing.assert_allclose(s.c_linear, full.c_linear[idx], rtol=1e-9, atol=1e-14)
    np.testing.assert_allclose(s.threshold, full.threshold, rtol=1e-12)  # the same total count
    assert s.best == "m30" and s.check("m30").c == pytest.approx(1.0, rel=0.2)
    # one check per zoom chain: m28 and everything zoomed from it (m29, m30, m31, the spring) are one place
    chain = {"m28"} | held
    assert [c.name for c in s.checks if c.name in chain] == ["m30"]
    assert len(s.checks) >= 3
    assert s.timings_s["zoom"] >= 0 and "zoomed" in s.to_dict()
    # bounded rounds; a candidate offered twice or of the wrong type is refused
    n = []
    _screen(frame, data, n_check=0, zoom=lambda names, e: n.append(1) or [], zoom_rounds=0)
    assert not n
    with pytest.raises(CalibrationError, match="screened already"):
        screen(sur, T, np.zeros(pm.n_params), data, ZETA, first, pm.lower, pm.upper, n_check=0,
               zoom=lambda names, e: [(first[0], "x", first[1].name)])
    with pytest.raises(CalibrationError, match="not screened"):
        screen(sur, T, np.zeros(pm.n_params), data, ZETA, first, pm.lower, pm.upper, n_check=0,
               zoom=lambda names, e: [(later[0], "x", "nope")])
    with pytest.raises(CalibrationError, match="parent name"):
        screen(sur, T, np.zeros(pm.n_params), data, ZETA, first, pm.lower, pm.upper, n_check=0,
               zoom=lambda names, e: [(later[0], "x")])
    with pytest.raises(CalibrationError, match="not CandidateTerm"):
        screen(sur, T, np.zeros(pm.n_params), data, ZETA, first, pm.lower, pm.upper, n_check=0,
               zoom=lambda names, e: [("m30", "x", "m28")])


def _contact(terms):
    contact = [t for t in terms if t.name.startswith("kc")]
    return contact[len(contact) // 2]


def test_fit_with_two_effects_singly_and_combined_and_accept(frame):
    pm, model, sur, T, terms, cands = frame
    sigma = 0.005
    kc = _contact(terms)
    truth = (AddedMass("m_truth", (30,), 0.5), AddedSpring("k_truth", kc.dofs, kc.scale))
    ext = pm.with_terms(truth)
    mt = FRFModel(ext.K, ext.M, model.inputs, model.outputs, parameter_names=ext.names, parametric=ext)
    f = half_bandwidth_frequencies(*BAND, ZETA, 3)
    H = full_order_frf(mt, np.r_[P_OLD, 1.0, 1.5], f, ZETA)

    def article(seed):
        rng = np.random.default_rng(seed)
        noise = sigma * (rng.normal(size=H.shape) + 1j * rng.normal(size=H.shape)) / np.sqrt(2)
        return [FitData(f, H * 10**noise, model.output_names, article=f"a{seed}")]

    data, hold = article(0), article(1)
    base = _screen(frame, data, n_check=0)
    p_b = base.p_baseline
    kw = dict(p0=p_b, shift_hz=SHIFT_HZ)
    m30, kcc = _by_name(cands, "m30"), _by_name(cands, kc.name)
    single = fit_with(sur, T, model, [m30], data, ZETA, pm.lower, pm.upper, c0=[1.0], **kw)
    both = fit_with(sur, T, model, [m30, kcc], data, ZETA, pm.lower, pm.upper, c0=[1.0, 1.0], **kw)
    np.testing.assert_allclose(both.c, [1.0, 1.5], rtol=0.1)
    np.testing.assert_allclose(both.p, P_OLD, atol=0.01)
    assert both.sd == pytest.approx(sigma**2, rel=0.1)  # down to the noise
    assert single.sd > 3 * both.sd > 0 and single.sd < 0.7 * base.sd_baseline  # each explains a part
    # the extended surrogate is a calibration surrogate: hold-out and cross-validation run on it
    hb, h1, h2 = (holdout_sd(sur, p_b, hold[0], ZETA), holdout_sd(single.surrogate, single.x, hold[0], ZETA),
                  holdout_sd(both.surrogate, both.x, hold[0], ZETA))
    assert hb > h1 > h2
    cv = dict(n_realizations=4, seed=3, max_nfev=20)
    cv0 = cross_validate(sur, data, p_b, pm.lower, pm.upper, ZETA, **cv).sd_test
    cv1 = cross_validate(single.surrogate, data, single.x, single.lower, single.upper, ZETA, **cv).sd_test
    cv2 = cross_validate(both.surrogate, data, both.x, both.lower, both.upper, ZETA, **cv).sd_test
    n_ind = 2 * data[0].n_values // 3  # three lines per half-power bandwidth
    a1 = accept(hb, h1, cv0, cv1, sigma**2, 1, n_ind)
    assert a1.accepted and not a1.stop, a1.reason
    a2 = accept(h1, h2, cv1, cv2, sigma**2, 1, n_ind)
    assert a2.accepted and a2.stop, a2.reason
    # a decoy on top: the residual is at the floor, nothing more is accepted
    decoy = fit_with(sur, T, model, [m30, kcc, _by_name(cands, "m7")], data, ZETA, pm.lower, pm.upper,
                     c0=[1.0, 1.5, 0.0], **kw)
    cv3 = cross_validate(decoy.surrogate, data, decoy.x, decoy.lower, decoy.upper, ZETA, **cv).sd_test
    a3 = accept(h2, holdout_sd(decoy.surrogate, decoy.x, hold[0], ZETA), cv2, cv3, sigma**2, 1, n_ind)
    assert not a3.accepted and a3.stop


def test_accept_rule():
    cv_b = np.array([1.00, 1.02, 0.98, 1.01]) * 1e-3
    # clear improvement, far above the floor
    a = accept(1e-3, 5e-4, cv_b, cv_b - 4e-4, 1e-5, 1, 1000)
    assert a.accepted and not a.stop and a.holdout_ratio == pytest.approx(0.5)
    # an improvement inside the cross-validation scatter
    noisy = cv_b - np.array([3e-4, -2e-4, 2e-4, -2.5e-4])
    a = accept(1e-3, 9.9e-4, cv_b, noisy, 1e-5, 1, 1000)
    assert not a.accepted and "scatter" in a.reason
    # the per-parameter penalty: 0.5 % better is not enough for 3 parameters on 300 residuals
    assert np.exp(-3 * np.log(300) / 300) < 0.995
    a = accept(1e-3, 0.995e-3, cv_b, cv_b - 5e-6, 1e-5, 3, 300)
    assert not a.accepted and "penalty" in a.reason
    # at the floor already: stop
    a = accept(1.2e-5, 1e-5, cv_b, cv_b, 1e-5, 1, 1000)
    assert not a.accepted and a.stop
    with pytest.raises(CalibrationError, match="cross-validation"):
        accept(1e-3, 5e-4, [1e-3], [5e-4], 1e-5, 1, 1000)


def test_separating_effect_on_a_3_2_ensemble(frame):
    pm, model, sur, T, terms, cands = frame
    kc = _contact(terms)
    ext = pm.with_terms([AddedSpring("k_truth", kc.dofs, kc.scale)])
    mt = FRFModel(ext.K, ext.M, model.inputs, model.outputs, parameter_names=ext.names, parametric=ext)
    f = half_bandwidth_frequencies(*BAND, ZETA, 3)
    rng = np.random.default_rng(7)
    closed = [1.5, 1.5, 1.5, 0.0, 0.0]  # the gap closed on three articles, open on two
    articles = []
    for k, c in enumerate(closed):
        p = P_OLD * (1 + 0.02 * rng.normal(size=P_OLD.size))  # article-to-article scatter
        H = full_order_frf(mt, np.r_[p, c], f, ZETA)
        H = H * 10 ** (0.005 * (rng.normal(size=H.shape) + 1j * rng.normal(size=H.shape)) / np.sqrt(2))
        articles.append([FitData(f, H, model.output_names, article=f"A{k + 1}")])
    kcc = _by_name(cands, kc.name)
    common = fit_with(sur, T, model, [kcc], [d[0] for d in articles], ZETA, pm.lower, pm.upper, p0=P_OLD,
                      c0=[0.9], shift_hz=SHIFT_HZ)
    groups = [0, 0, 0, 1, 1]
    sep = separating_effect(common.surrogate, common.x, articles, ZETA, groups, common.lower, common.upper)
    assert sep.separates, sep.reason
    assert sep.articles == ("A1", "A2", "A3", "A4", "A5")
    np.testing.assert_allclose(sep.magnitude[:3], 1.5, rtol=0.25)
    np.testing.assert_allclose(sep.magnitude[3:], 0.0, atol=0.2)
    assert sep.gap > 1.0
    per = separating_effect(common.surrogate, common.x, articles, ZETA, groups, common.lower, common.upper,
                            refit_p=True)
    assert per.separates and np.allclose(per.magnitude, closed, atol=0.2)
    mixed = separating_effect(common.surrogate, common.x, articles, ZETA, [0, 1, 0, 1, 0], common.lower,
                              common.upper)
    assert not mixed.separates
    # which effect separates the groups: the contact among decoys of every family
    names = [kc.name, "m30", "f13"]
    ranked = rank_separating(sur, T, model, [_by_name(cands, n) for n in names], articles, ZETA, groups, pm.lower,
                             pm.upper, p0=P_OLD, c0=[0.9, 0.5, 0.0], shift_hz=SHIFT_HZ)
    assert ranked[0][0] == kc.name and ranked[0][2].separates
    # decoys that mimic the contact in part separate the groups too, but leave the articles' residuals
    sd = {name: float(np.mean(sep.sd)) for name, _, sep in ranked}
    # (the contact's articles keep their 2 % scatter of the existing parameters: common p here)
    assert all(sd[n] > 3 * sd[kc.name] for n in names[1:]), sd
    print("mean article SD after the per-article fit:", {n: f"{v:.3g}" for n, v in sd.items()},
          "magnitudes:", np.round(sep.magnitude, 3))


def test_raw_line_refinement_runs_on_the_fitted_extension():
    """The final number: :func:`calibration.refine` on a :class:`CandidateFit`'s surrogate reaches the floor.

    Beam of tests/calibration/_models.py with an unmodelled 0.2 kg point mass
    (the truth); per-mode damping, uneven line grid, 1 % noise, identified
    modes for the damping mapping, as tests/calibration/test_refine.py.
    """
    import scipy.sparse as sp

    from calibration import IdentifiedModes, extended_model, refine
    from calibration._metric import log_deviation, square_deviation
    from identification import identify
    from tests.calibration._models import beam_model

    band, lo, hi = (20.0, 400.0), -0.3 * np.ones(7), 0.3 * np.ones(7)
    p_true = np.array([0.03, -0.04, 0.02, -0.05, 0.04, 0.03, -0.02])
    model, _ = beam_model()
    n = model.K.shape[0]
    node = 12
    dM = sp.csr_matrix(([0.2], ([2 * node], [2 * node])), shape=(n, n))
    cand = CandidateTerm("m_node12", None, dM, 0.0, 5.0)
    truth = extended_model(model, [cand])
    rng = np.random.default_rng(3)
    zeta = 10 ** rng.uniform(np.log10(1e-3), np.log10(3e-3), n)
    f = np.geomspace(band[0], band[1], 400)
    H = full_order_frf(truth, np.r_[p_true, 1.0], f, zeta)
    Hn = H * (1 + 0.01 * (rng.standard_normal(H.shape) + 1j * rng.standard_normal(H.shape)) / np.sqrt(2))
    floor = square_deviation(log_deviation(H, Hn))
    ident = identify(f, Hn, 24, band_hz=band)
    modes = IdentifiedModes(ident.modal.frequency_hz, ident.modal.damping, ident.modal.shapes, model.output_names)
    raw = FitData(f, Hn, model.output_names, article="beam")
    sur, T = build_surrogate(model, np.zeros(7), band)
    # equalized target at 0.02 (the identified model resynthesized; here the truth at uniform damping)
    fe = half_bandwidth_frequencies(*band, 0.02, 3)
    eq = [FitData(fe, full_order_frf(truth, np.r_[p_true, 1.0], fe, 0.02), model.output_names)]
    fit = fit_with(sur, T, model, [cand], eq, 0.02, lo, hi, p0=np.zeros(7), c0=[0.5], shift_hz=8.0)
    assert fit.c[0] == pytest.approx(1.0, rel=0.05)
    ref = refine(fit.surrogate, fit.x, [raw], [(ident, raw.outputs)], [modes], fit.lower, fit.upper, 0.02)
    assert ref.p[-1] == pytest.approx(1.0, rel=0.03)
    assert ref.sd_raw < 2.0 * floor, (ref.sd_raw, floor)
    # without the mass the raw lines stay far from the floor
    ref0 = refine(sur, np.zeros(7), [raw], [(ident, raw.outputs)], [modes], lo, hi, 0.02)
    assert ref0.sd_raw > 10 * floor, (ref0.sd_raw, floor)
    print(f"refine on the extension: c {fit.c[0]:.4f} -> {ref.p[-1]:.4f}, raw SD {ref.sd_raw / floor:.2f} x floor "
          f"(without the candidate {ref0.sd_raw / floor:.1f} x)")


def test_extended_model_is_linear_in_the_candidates(frame):
    from calibration import extended_model

    pm, model, sur, T, terms, cands = frame
    sub = [_by_name(cands, "m30"), _by_name(cands, "f1"), _by_name(cands, "kg1")]
    ext = extended_model(model, sub)
    assert ext.parameter_names == tuple(pm.names) + ("m30", "f1", "kg1")
    x = np.r_[P_OLD, 0.7, -0.2, 1.5]
    K = pm.stiffness(P_OLD) - 0.2 * sub[1].dK + 1.5 * sub[2].dK
    M = pm.mass(P_OLD) + 0.7 * sub[0].dM
    for fast, slow, ref in ((ext.stiffness(x), ext.K.at(x), K), (ext.mass(x), ext.M.at(x), M)):
        scale = abs(ref).max()
        assert abs(fast - ref).max() < 1e-12 * scale and abs(slow - ref).max() < 1e-12 * scale
    assert abs(ext.dM(x, 7) - sub[0].dM).max() == 0 and ext.dK(x, 7).nnz == 0
    assert abs(ext.dK(x, 0) - pm.dK(P_OLD, 0)).max() == 0 and abs(pm.dK(P_OLD, 0)).max() > 0


def test_a_mass_at_the_tank_grid_is_found_beyond_the_tank_mass_parameter(frame):
    """The tank's CONM2 (offset 150 mm, rotary inertia) has a mass parameter: it absorbs most of an added
    0.5 kg at its grid; what it cannot absorb (no offset, no inertia) still points at the grid."""
    pm, model, sur, T, terms, cands = frame
    conm = pm.assembly.model.elements["CONM2"]
    g_tank = int(np.asarray(conm["nodes"]).ravel()[list(conm.ids).index(9003)])
    j_tank = list(pm.names).index("M_tank")
    data = _truth_data(pm, model, AddedMass("m_truth", (g_tank,), 0.5), 1.0, sigma=0.005)
    s = _screen(frame, data, n_check=3)
    # the parameter takes the mass up: -10 % of 6 kg + 0.5 kg is about nominal
    assert s.p_baseline[j_tank] == pytest.approx(-0.1 + 0.5 / 6.0, abs=0.03)
    assert s.sd_baseline < 0.01 * s.sd_start
    # ... and the candidate still explains most of what is left, at its true magnitude
    assert s.best == f"m{g_tank}"
    chk = s.check(f"m{g_tank}")
    assert chk.explained > 0.7 and chk.c == pytest.approx(1.0, rel=0.2)
    np.testing.assert_allclose(chk.p, P_OLD, atol=0.01)


def test_fit_with_warm_from_its_converged_check_ends_where_the_cold_fit_ends(frame):
    """fit_with(warm=check): from the check's (p, c), final stage only; the same optimum as the fit that runs
    the continuation stages from the baseline (an effect that moves modes by more than a bandwidth)."""
    pm, model, sur, T, terms, cands = frame
    true = ElementFactor("f_truth", next(t for t in terms if t.name == "f13").elements)
    data = _truth_data(pm, model, true, -0.4, sigma=0.005)
    cont = [(0.05, _truth_data(pm, model, true, -0.4, sigma=0.005, seed=1, zeta=0.05))]
    s = _screen(frame, data, n_check=3, continuation=cont)
    chk = s.check("f13")
    assert chk.converged
    cand = _by_name(cands, "f13")
    kw = dict(p0=s.p_baseline, c0=[chk.c], continuation=cont, shift_hz=SHIFT_HZ)
    cold = fit_with(sur, T, model, [cand], data, ZETA, pm.lower, pm.upper, **kw)
    warm = fit_with(sur, T, model, [cand], data, ZETA, pm.lower, pm.upper, warm=chk, **kw)
    assert cold.converged and warm.converged
    np.testing.assert_allclose(warm.c, cold.c, rtol=1e-6)
    np.testing.assert_allclose(warm.p, cold.p, atol=1e-6)
    assert warm.sd == pytest.approx(cold.sd, rel=1e-9)
    assert warm.c[0] == pytest.approx(-0.4, rel=0.2)
    # the check of another candidate is not a start for this one
    other = next(c for c in s.checks if c.name != "f13")
    again = fit_with(sur, T, model, [cand], data, ZETA, pm.lower, pm.upper, warm=other, **kw)
    np.testing.assert_array_equal(again.x, cold.x)
    # without its basis the fit goes on on the check's own extension (not built again): the same optimum
    assert chk.surrogate is not None and chk.surrogate.n_params == sur.n_params + 1
    kept = fit_with(sur, T, model, [cand], data, ZETA, pm.lower, pm.upper, warm=chk, with_basis=False, **kw)
    assert kept.surrogate is chk.surrogate and kept.basis is None
    np.testing.assert_allclose(kept.x, warm.x, atol=1e-6)
    assert kept.sd == pytest.approx(warm.sd, rel=1e-6)
    assert "surrogate" not in chk.to_dict()


def test_the_shifted_solver_is_formed_once_per_point(frame):
    """shifted_solver keeps the model's last factorization: the same point and shift return it, another point
    forms (and keeps) a new one; both solve their own K + s M."""
    pm, model, sur, T, terms, cands = frame
    p0 = np.zeros(pm.n_params)
    a = shifted_solver(model, p0, SHIFT_HZ)
    assert shifted_solver(model, p0.copy(), SHIFT_HZ) is a
    p1 = np.full(pm.n_params, 0.05)
    b = shifted_solver(model, p1, SHIFT_HZ)
    assert b is not a and shifted_solver(model, p1, SHIFT_HZ) is b
    s = (2 * np.pi * SHIFT_HZ) ** 2
    F = np.random.default_rng(0).standard_normal((model.K.shape[0], 2))
    for p, solve in ((p0, shifted_solver(model, p0, SHIFT_HZ)), (p1, b)):
        A = model.stiffness(p) + s * model.mass(p)
        np.testing.assert_allclose(A @ solve(F), F, atol=1e-8 * np.abs(F).max())


def test_a_region_takes_one_check_and_its_enclosing_union_is_checked_with_it(frame):
    """``screen(regions=...)``: the alternatives of one contact gap (cells of two pairs tiled from the end of a
    stretch of five cradle-rail pairs, windows of two pairs straddling the cells' boundaries, the union of
    the stretch) take one of the ``n_check`` slots, its best linear member's; with it the union around that
    member and the best member partly overlapping it are checked outside the budget, the union from the
    member's checked stiffness carried over (same total on the shared pairs). The linear score cannot rank
    them: the true window scores below a cell, the true union (a 5 x 2e5 N/m gap) ~0."""
    pm, model, sur, T, terms, cands = frame
    fe = pm.assembly.model
    pairs = sorted(_contact_pairs(fe))[:5]
    assert [a for a, _ in pairs] == [60, 61, 62, 63, 64]  # one stretch along the cradle's side
    sets = {"gap_c1": [0, 1], "gap_c2": [2, 3], "gap_c3": [4], "gap_w1": [1, 2], "gap_w2": [3, 4],
            "gap_join1": [0, 1, 2, 3, 4]}

    def spring(name, idx):
        return AddedSpring(name, tuple((pairs[i][0], 3, pairs[i][1], 3) for i in idx), 2e5)

    others = [c for c in cands if not c.name.startswith("kc")]
    gap = _candidates(pm, [spring(n, i) for n, i in sets.items()], P_OLD)
    every = others + gap
    places = {n: frozenset(g for i in idx for g in pairs[i]) for n, idx in sets.items()}
    regions = [(("contact", "cradle-rail"), places[c.name]) if c.name in places else None for c in every]
    groups = ["gap" if c.name.startswith("gap") else c.name.rstrip("0123456789_") for c in every]

    def run(truth, reg):
        data = _truth_data(pm, model, spring("truth", sets[truth]), 1.0, sigma=0.005)
        return screen(sur, T, np.zeros(pm.n_params), data, ZETA, every, pm.lower, pm.upper, model=model,
                      shift_hz=SHIFT_HZ, n_check=2, groups=groups, regions=reg)

    # a closed window straddling a cell boundary: a cell scores best linearly and takes the region's slot; the
    # union around it and the window (the best member partly overlapping it) are checked with it
    s = run("gap_w1", regions)
    lin = {n: s.explained[s.names.index(n)] for n in sets}
    assert max(lin, key=lin.get) == "gap_c1" and lin["gap_w1"] < lin["gap_c1"]
    checked = [c.name for c in s.checks]
    assert {n for n in checked if n in sets} == {"gap_c1", "gap_join1", "gap_w1"}
    assert sum(n not in sets for n in checked[:3]) == 0 and s.best == "gap_w1"
    assert s.check("gap_w1").c == pytest.approx(1.0, rel=0.05) and s.check("gap_w1").explained > 0.99
    # the region took one slot of the two: the other went to another family's best (a mass here)
    assert sum(n not in sets for n in checked) >= 2
    # the whole gap closed: every member scores ~0 linearly (the first-order score of a large change);
    # the union, checked around the cell from the cell's carried stiffness, is found exactly
    s = run("gap_join1", regions)
    assert s.explained[s.names.index("gap_join1")] < 0.01
    assert s.best == "gap_join1" and s.check("gap_join1").c == pytest.approx(1.0, rel=0.05)
    assert s.check("gap_join1").explained > 0.99
    # without the regions the union gets no check (only the family's best, a cell) and the best check is
    # a cell standing in for the gap, locally stiffer
    s0 = run("gap_join1", None)
    assert s0.check("gap_join1") is None and s0.best in sets and s0.check(s0.best).explained < 0.9
    with pytest.raises(CalibrationError, match="regions for"):
        screen(sur, T, np.zeros(pm.n_params), _truth_data(pm, model, None, 0.0), ZETA, every, pm.lower,
               pm.upper, n_check=0, regions=regions[:-1])
    with pytest.raises(CalibrationError, match="label, places"):
        screen(sur, T, np.zeros(pm.n_params), _truth_data(pm, model, None, 0.0), ZETA, every, pm.lower,
               pm.upper, n_check=0, regions=[("x",)] * len(every))


def test_region_companions_are_the_unions_around_the_checked_member_and_one_overlapping():
    """The rule alone (calibration._diagnose._companions, no fits): a one-pair cell at the end of a stretch of
    8 pairs lies inside 6 windows of 3 pairs, a 6-pair join and the 8-pair union of the part pair; checked,
    it takes with it the two largest around it (join, union) and the best linear other (a window), and no
    member partly overlapping it (there is none). A window checked takes the unions around it and the best
    linear window partly overlapping it; a member of another region or none takes nothing."""
    from calibration._diagnose import _companions, _regions

    pairs = {"cell": {0}, "w1": {0, 1, 2}, "w2": {0, 1, 3}, "w3": {0, 2, 3}, "w4": {0, 1, 4}, "w5": {0, 2, 4},
             "w6": {0, 3, 4}, "w7": {4, 5, 6}, "join": set(range(6)), "all": set(range(8))}
    names = list(pairs) + ["mass"]
    regions = [("gap", frozenset(pairs[n])) for n in pairs] + [None]
    root = {k: k for k in range(len(names))}
    members = _regions(regions, len(names), root)
    assert {root[k] for k in range(len(pairs))} == {0} and root[len(pairs)] == len(pairs)
    lin = np.array([0.30, 0.10, 0.12, 0.08, 0.05, 0.06, 0.07, 0.20, 0.01, 0.0, 0.25])
    got = [(names[k], names[i]) for k, i in _companions([0, len(pairs)], members, lin)]
    assert got == [("all", "cell"), ("join", "cell"), ("w2", "cell")]
    got = [names[k] for k, _ in _companions([names.index("w4")], members, lin)]
    assert got == ["all", "join", "w7"]  # w7 partly overlaps w4 (pair 4) and scores best of those
    assert _companions([len(pairs)], members, lin) == []
    assert _regions(None, len(names), root) == {}
