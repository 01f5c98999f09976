"""Manufactured truth: calibration, cross-validation, validation, ensembles, executors."""

import numpy as np
import pytest

from calibration import (
    CalibrationError,
    FitData,
    IdentifiedModes,
    ProcessExecutor,
    SerialExecutor,
    build_surrogate,
    calibrate,
    calibrate_cycles,
    cross_validate,
    full_order_frf,
    group_articles,
    half_bandwidth_frequencies,
    mac,
    pair_modes,
    pairwise_sd,
    reduced_modes,
    validate,
)
from tests.calibration._models import beam_model

BAND = (20.0, 400.0)
LO, HI = -0.3 * np.ones(7), 0.3 * np.ones(7)
P_TRUE = np.array([0.0047, 0.1802, -0.1423, 0.1795, -0.0753, -0.0307, 0.1311])  # up to +-20 %
SCHEDULE = (0.08, 0.03)


def _data(model, p, zeta, noise=0.0, rng=None, outputs=None):
    f = half_bandwidth_frequencies(*BAND, zeta, 3)
    H = full_order_frf(model, p, f, zeta)
    names = model.output_names
    if outputs is not None:
        H, names = H[:, outputs], tuple(names[i] for i in outputs)
    if noise:
        H = H * (1 + noise * (rng.standard_normal(H.shape) + 1j * rng.standard_normal(H.shape)) / np.sqrt(2))
    return [FitData(f, H, names)]


@pytest.fixture(scope="module")
def beam():
    model, _ = beam_model()
    sur, _ = build_surrogate(model, np.zeros(7), BAND)
    return model, sur


def test_noise_free_recovery_from_every_start(beam):
    model, sur = beam
    cont = [(z, _data(model, P_TRUE, z)) for z in SCHEDULE]
    cal = calibrate(sur, _data(model, P_TRUE, 0.01), LO, HI, 0.01, n_starts=10, seed=3, continuation=cont,
                    adaptive_starts=False)
    assert len(cal.outcomes) == 11 and not cal.stopped_early
    for o in cal.outcomes:
        err = np.abs((1 + o.p) / (1 + P_TRUE) - 1)
        assert err.max() < 0.005, (o.start, o.p)
        assert o.converged and o.jacobian_rank == 7
    assert cal.sd < 1e-8 < cal.sd_nominal


def test_without_continuation_some_start_stalls(beam):
    """Why damping continuation is the default: a resonator mode starting 20 % off stalls at zeta0."""
    model, sur = beam
    x0 = np.array([0.296, -0.17, -0.019, -0.108, 0.198, -0.21, -0.089])
    cal = calibrate(sur, _data(model, P_TRUE, 0.01), LO, HI, 0.01, n_starts=0, p_start=x0, max_nfev=30)
    assert cal.sd > 1e-3
    cont = [(z, _data(model, P_TRUE, z)) for z in SCHEDULE]
    cal = calibrate(sur, _data(model, P_TRUE, 0.01), LO, HI, 0.01, n_starts=0, p_start=x0, continuation=cont)
    assert np.abs((1 + cal.p) / (1 + P_TRUE) - 1).max() < 0.005


@pytest.mark.parametrize("rebasis", ["iterated", "kept", "solved"])
def test_cycles_rebasis_converge_to_truth(rebasis):
    model, _ = beam_model()
    data = _data(model, P_TRUE, 0.01)
    res = calibrate_cycles(model, data, BAND, LO, HI, n_starts=0, max_cycles=4, tol=1e-5,
                           continuation=[(z, _data(model, P_TRUE, z)) for z in SCHEDULE], rebasis=rebasis)
    assert np.abs((1 + res.p) / (1 + P_TRUE) - 1).max() < 1e-4
    assert len(res.cycles) >= 2 and res.cycles[-1]["max_dp"] < 1e-5


def test_cycles_end_when_the_basis_is_adequate():
    """basis_tol: the cycles end at the first point where the basis holds the modes; the result is as accurate."""
    model, _ = beam_model()
    data = _data(model, P_TRUE, 0.01)
    cont = [(z, _data(model, P_TRUE, z)) for z in SCHEDULE]
    res = calibrate_cycles(model, data, BAND, LO, HI, n_starts=0, max_cycles=4, tol=1e-5, continuation=cont,
                           basis_tol=0.05)
    checks = [c["basis_check"] for c in res.cycles if "basis_check" in c]
    assert checks and checks[-1]["adequate"] and checks[-1]["eta_max"] <= 4 * 0.05 * 0.01
    assert all(not c["adequate"] for c in checks[:-1])  # a re-basis only after a failed check
    assert len(res.cycles) < 4  # fewer builds than the p-move rule (which runs until max |dp| < 1e-5)
    assert np.abs((1 + res.p) / (1 + P_TRUE) - 1).max() < 1e-3


def test_noisy_truth_inside_cross_validation_scatter(beam):
    model, sur = beam
    rng = np.random.default_rng(7)
    noise = 0.03
    data = _data(model, P_TRUE, 0.01, noise, rng)
    cont = [(z, _data(model, P_TRUE, z, noise, rng)) for z in SCHEDULE]
    cal = calibrate(sur, data, LO, HI, 0.01, n_starts=2, seed=1, continuation=cont)
    cv = cross_validate(sur, data, cal.p, LO, HI, 0.01, n_realizations=12, seed=2)
    phys = 1 + cv.p
    lo_, hi_ = phys.min(axis=0), phys.max(axis=0)
    spread = hi_ - lo_
    truth = 1 + P_TRUE
    # truth inside the CV scatter widened by a standard deviation (12 realizations)
    sd = phys.std(axis=0, ddof=1)
    assert np.all((truth > lo_ - 2 * sd) & (truth < hi_ + 2 * sd)), (truth, lo_, hi_)
    assert np.all(spread > 0)
    # RSE of a correct model is the noise floor: |log10(1+n)|^2 ~ noise^2 / ln(10)^2
    floor = noise**2 / np.log(10) ** 2
    assert 0.5 * floor < cv.rse < 2.0 * floor
    assert cv.cv_percent.shape == (7,) and np.all(cv.cv_percent < 5)


def test_validation_holdout_improves_and_maps_damping(beam):
    model, sur = beam
    cal_out, hold_out = [0, 2, 4, 6, 8], [1, 3, 5, 7, 9]
    data = _data(model, P_TRUE, 0.01, outputs=cal_out)
    cont = [(z, _data(model, P_TRUE, z, outputs=cal_out)) for z in SCHEDULE]
    cal = calibrate(sur, data, LO, HI, 0.01, n_starts=0, continuation=cont)
    # "raw" hold-out data: the truth with its own modal damping 0.3 %, on a fine line grid
    f = np.arange(20.0, 400.0, 0.25)
    raw = full_order_frf(model, P_TRUE, f, 0.003)[:, hold_out]
    names = tuple(model.output_names[i] for i in hold_out)
    # identified modes of the truth at all channels (damping 0.3 %)
    lam, X = reduced_modes(sur, P_TRUE)
    fe_hz = np.sqrt(np.clip(lam, 0, None)) / (2 * np.pi)
    sel = (fe_hz > 15) & (fe_hz < 450)
    modes = IdentifiedModes(fe_hz[sel], np.full(sel.sum(), 0.003), (sur.outputs @ X)[:, sel] + 0j,
                            model.output_names)
    v = validate(sur, sur, cal.p, FitData(f, raw, names), modes, 0.01, target_sd=1e-3)
    assert v.improved and v.below_target and v.verdict == "improved, below target 0.001"
    assert v.sd_calibrated < 1e-4 < v.sd_nominal
    assert len(v.pairs_calibrated[0]) == sel.sum()
    assert all(pr["mac"] > 0.99 for pr in v.pairs_calibrated[0])


def test_mac_and_pairing():
    rng = np.random.default_rng(0)
    A = rng.standard_normal((12, 4))
    B = A[:, [2, 0, 3, 1]] * np.array([2.0, -1.0, 1j, 0.5])
    M = mac(A, B)
    assert np.allclose(np.diag(M[:, [1, 3, 0, 2]]), 1.0)
    assert pair_modes(M, 0.9) == [(0, 1, pytest.approx(1.0)), (1, 3, pytest.approx(1.0)),
                                  (2, 0, pytest.approx(1.0)), (3, 2, pytest.approx(1.0))]
    # with frequencies: a shape match 1.6x away in frequency is no pair (a few sensors make such MACs)
    fa = np.array([20.0, 40.0, 60.0, 80.0])
    fb = np.array([62.0, 21.0, 130.0, 41.0])  # b3 is a3's shape at 1.6x its frequency
    assert pair_modes(M, 0.9, fa, fb) == [(0, 1, pytest.approx(1.0)), (1, 3, pytest.approx(1.0)),
                                          (2, 0, pytest.approx(1.0))]


def test_articles_group_by_similarity():
    model, _ = beam_model()
    f = half_bandwidth_frequencies(*BAND, 0.01, 3)
    # two families (e.g. an air gap closed/open changes the bushing spring by 15 %)
    ps = [np.array([0, 0, 0, 0, 0, 0, d]) + e for d, e in
          [(0.0, 0.0), (0.0, 0.003), (0.15, 0.0), (0.0, -0.003), (0.15, 0.003)]]
    frfs = [full_order_frf(model, p, f) for p in ps]
    D = pairwise_sd(frfs)
    assert np.allclose(D, D.T) and np.all(np.diag(D) == 0)
    labels = group_articles(D)
    assert labels.tolist() == [0, 0, 1, 0, 1]
    assert group_articles(D, n_groups=1).tolist() == [0] * 5


def test_bad_data_errors(beam):
    model, sur = beam
    f = half_bandwidth_frequencies(*BAND, 0.01, 3)
    H = full_order_frf(model, P_TRUE, f)
    H[10, 2, 0] = np.nan
    with pytest.raises(CalibrationError, match="acc8"):
        FitData(f, H, model.output_names)
    with pytest.raises(CalibrationError, match="no frequency lines"):
        FitData(f[:0], H[:0], model.output_names)
    with pytest.raises(CalibrationError, match="nosuch"):
        calibrate(sur, [FitData(f, H[:, :1], ("nosuch",))], LO, HI, n_starts=0)
    with pytest.raises(CalibrationError, match="bounds"):
        calibrate(sur, _data(model, P_TRUE, 0.01), HI, LO, n_starts=0)
    # flagged (masked-out) NaN lines are excluded, not an error
    mask = np.ones(H.shape, bool)
    mask[10] = False
    d = FitData(f, H, model.output_names, mask=mask)
    assert d.n_values == H.size - H.shape[1]


def _square(x):
    return x * x


def test_process_executor_spawn():
    with ProcessExecutor(2) as ex:
        assert ex.map(_square, range(5)) == [0, 1, 4, 9, 16]
    assert SerialExecutor().map(_square, [3]) == [9]


def test_process_executor_started_early_imports_in_the_workers():
    import os

    with ProcessExecutor(2) as ex:
        ex.start(("calibration._fit",))  # returns at once; workers spawn and import meanwhile
        pids = set(ex.map(_worker_has_fit, range(6)))
    assert all(loaded for _, loaded in pids)
    assert os.getpid() not in {pid for pid, _ in pids}
    with ProcessExecutor(2) as ex:  # a failed warm-up import does not leak into later work
        ex.start(("calibration._no_such_module",))
        assert ex.map(_square, range(4)) == [0, 1, 4, 9]


def _started_at(_):
    import time

    return time.time()


def test_process_executor_runs_a_generators_items_while_it_yields_the_next():
    import time

    done = {}

    def slow():  # the caller's work between items (the screening builds the next check's extension)
        for i in range(4):
            yield i
            time.sleep(0.5)
        done["t"] = time.time()

    with ProcessExecutor(2) as ex:
        ex.map(_square, [1, 2])  # workers up
        started = ex.map(_started_at, slow())
    assert len(started) == 4
    assert min(started) < done["t"] - 1.0  # the first item ran while the generator was still producing


def _worker_has_fit(_):
    import os
    import sys

    return os.getpid(), "calibration._fit" in sys.modules


def test_dask_local_cluster_matches_serial(beam):
    distributed = pytest.importorskip("distributed")
    from calibration import DaskExecutor

    model, sur = beam
    data = _data(model, P_TRUE, 0.01)
    cont = [(z, _data(model, P_TRUE, z)) for z in SCHEDULE]
    serial = calibrate(sur, data, LO, HI, n_starts=2, seed=5, continuation=cont)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False, protocol="tcp://",
                                  dashboard_address=None, host="127.0.0.1") as cluster:
        with DaskExecutor(cluster.scheduler_address) as ex:
            remote = calibrate(sur, data, LO, HI, n_starts=2, seed=5, executor=ex, continuation=cont)
    for a, b in zip(serial.outcomes, remote.outcomes):
        np.testing.assert_allclose(a.p, b.p, atol=1e-10)


def test_fit_data_takes_weights_per_line_or_per_value():
    """Per-line weights spread over a line's values; per-value weights (the raw-line noise weights) kept as
    they are, under the mask; any other shape is refused with the article named."""
    from calibration import CalibrationError, FitData

    f = np.array([10.0, 20.0, 30.0])
    H = np.ones((3, 2, 1), complex)
    mask = np.ones(H.shape, bool)
    mask[1, 0, 0] = False
    per_line = FitData(f, H, ("a", "b"), ("F",), mask=mask, weights=np.array([1.0, 4.0, 9.0]))
    np.testing.assert_allclose(per_line.value_weights(), [1, 1, 2, 3, 3])
    w = np.arange(1.0, 7.0).reshape(3, 2, 1)
    per_value = FitData(f, H, ("a", "b"), ("F",), mask=mask, weights=w)
    np.testing.assert_allclose(per_value.value_weights(), np.sqrt([1, 2, 4, 5, 6]))
    with pytest.raises(CalibrationError, match="A7: weights must be 3 .* or \\(3, 2, 1\\)"):
        FitData(f, H, ("a", "b"), ("F",), article="A7", weights=np.ones((3, 2)))


def test_bayesian_stopping_rule_counts():
    """Boender and Rinnooy Kan's rule: w (n - 1) / (n - w - 2) < w + 1/2 first holds at 8, 17, 30 starts."""
    from calibration._fit import MIN_STARTS, enough_starts

    first = {w: next(n for n in range(1, 200) if enough_starts(n, w)) for w in (1, 2, 3)}
    assert first == {1: 8, 2: 17, 3: 30} and MIN_STARTS == 8
    assert not enough_starts(0, 0) and not enough_starts(50, 0)


def test_distinct_minima_and_stopping_point():
    from calibration._fit import distinct_minima, stopping_point

    one = [1.0, 1.0 + 1e-9, 1.0 - 5e-8, np.inf, 1.0]
    assert distinct_minima(one) == 1
    assert distinct_minima([1.0, 1.02, 1.0, 3.0, np.nan]) == 3
    assert distinct_minima([]) == 0
    # noise-free minima are round-off: equal within the absolute tolerance, not relatively
    assert distinct_minima([1e-12, 3e-11, 5e-13]) == 3 and distinct_minima([1e-12, 3e-11, 5e-13], atol=1e-10) == 1
    # one minimum: the 8th successful start ends it; a failed start does not count
    assert stopping_point([2.0] * 8) == 8
    assert stopping_point([2.0] * 3 + [np.inf] + [2.0] * 6) == 9
    assert stopping_point([2.0] * 7) is None
    # noise-free: minima of round-off, one minimum within 1e-8 of the SD at the starts
    assert stopping_point([1e-12, 3e-11] + [5e-13] * 6) is None
    assert stopping_point([1e-12, 3e-11] + [5e-13] * 6, [1e-2] * 8) == 8
    # a second minimum among the first eight: 17 starts are needed
    sds = [2.0, 2.5] + [2.0] * 20
    assert stopping_point(sds) == 17


def test_multistart_stops_by_the_rule_and_keeps_the_best(beam, monkeypatch):
    """All starts of the noise-free beam end in one minimum: the rule stops after 8 of 21 with the same
    optimum as the full multi-start, and rounds of two workers give the serial result start by start."""
    from calibration._fit import _multistart

    model, sur = beam
    cont = [(z, _data(model, P_TRUE, z)) for z in SCHEDULE]
    data = _data(model, P_TRUE, 0.01)
    full = calibrate(sur, data, LO, HI, 0.01, n_starts=20, seed=3, continuation=cont, adaptive_starts=False)
    short = calibrate(sur, data, LO, HI, 0.01, n_starts=20, seed=3, continuation=cont)
    assert len(full.outcomes) == 21 and len(short.outcomes) == 8 and short.starts_planned == 21
    assert short.stopped_early and "8 of 21 starts" in short.describe_starts()
    assert short.to_dict()["distinct_minima"] == 1
    for a, b in zip(short.outcomes, full.outcomes):
        np.testing.assert_array_equal(a.p, b.p)
    np.testing.assert_allclose(short.p, full.p, atol=1e-6)

    class Rounds:  # an executor of width 3 that records its rounds
        width = 3

        def __init__(self):
            self.rounds = []

        def map(self, fn, items):
            items = list(items)
            self.rounds.append(len(items))
            return [fn(x) for x in items]

    ex = Rounds()
    fake = [((), None, None, None, None, None)] * 21
    import calibration._fit as F

    seq = iter([1.0, 1.0, 1.5] + [1.0] * 30)  # a second minimum at start 3: the rule needs 17
    monkeypatch.setattr(F, "run_start",
                        lambda job: F.StartOutcome(np.zeros(1), np.zeros(1), 0.0, next(seq), True, "", 0, 0, 1, 1.0, 0.0))
    out = _multistart(ex, fake)
    assert len(out) == 17 and ex.rounds == [9, 3, 3, 3]  # 9 (>= 8 in rounds of 3), then rounds up to 18, cut to 17
