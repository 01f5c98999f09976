"""Monte Carlo cross-validation (paper Sec. 2.2.4 and Table 2.1).

Each realization splits the calibration data at random into two halves of
equal size (element-wise over frequency x channel x drive), recalibrates on
one half from the calibrated point with a few Gauss-Newton type
(trust-region least-squares) steps on the same surrogate, and takes the
square deviation on the other half. RSE is the mean of those hold-out
square deviations; the parameter estimates give a mean and a coefficient of
variation per parameter (of the physical value P = P0 (1 + p)).

A parameter that ends at a bound in a realization has no spread to measure
there (the bound is not an estimate): every such realization is counted,
and when any realization pins it its CV is reported as not meaningful
(``None`` with the reason), never as a small number such as 0.000 %.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from calibration._executor import SerialExecutor
from calibration._fit import FitData, Objective, check_bounds, run_start, single_thread


@dataclass(frozen=True)
class CrossValidation:
    """Cross-validation outcome.

    p : (n_real, n_p) normalized estimates ; sd_fit, sd_test : (n_real,)
    rse : mean of sd_test ; mean_p : (n_p,) ; cv_percent : (n_p,) CV of P/P0 in %
    parameter_names : tuple ; time_s : float
    n_at_bound : (n_p,) int, realizations in which the parameter ended at a bound
    cv_reason : tuple of str, why a CV is not meaningful ("" where it is)
    """

    p: np.ndarray
    sd_fit: np.ndarray
    sd_test: np.ndarray
    rse: float
    mean_p: np.ndarray
    cv_percent: np.ndarray
    parameter_names: tuple
    time_s: float
    n_at_bound: np.ndarray
    cv_reason: tuple

    def cv(self, j: int) -> float | None:
        """CV in % of parameter j, or None when it is not meaningful (see ``cv_reason[j]``)."""
        return None if self.cv_reason[j] else float(self.cv_percent[j])

    def to_dict(self) -> dict:
        return {
            "realizations": int(self.p.shape[0]),
            "rse": self.rse,
            "sd_fit": self.sd_fit.tolist(),
            "sd_test": self.sd_test.tolist(),
            "p": self.p.tolist(),
            "mean_p": self.mean_p.tolist(),
            "cv_percent": [self.cv(j) for j in range(self.cv_percent.size)],
            "cv_not_meaningful": [r or None for r in self.cv_reason],
            "n_at_bound": self.n_at_bound.tolist(),
            "parameter_names": list(self.parameter_names),
            "time_s": self.time_s,
        }


def split_halves(data, rng) -> tuple[list, list]:
    """Random complementary halves of every data set (as masked copies)."""
    a, b = [], []
    for d in data:
        base = np.ones(d.frf.shape, bool) if d.mask is None else d.mask
        idx = np.flatnonzero(base.ravel())
        pick = rng.permutation(idx)[: idx.size // 2]
        ma = np.zeros(base.size, bool)
        ma[pick] = True
        ma = ma.reshape(base.shape)
        a.append(d.masked(ma))
        b.append(d.masked(base & ~ma))
    return a, b


def _objective(sur, data, zeta0, quantity, damping):
    if damping is None:
        return Objective(sur, data, zeta0, quantity)
    from calibration._refine import ModalDampingObjective

    zeta, p_ref = damping
    return ModalDampingObjective(sur, data, zeta, p_ref, 0.0, quantity)


def _realization(args):
    sur, fit, test, p_start, lower, upper, zeta0, quantity, max_nfev, damping = args
    with single_thread():
        obj = _objective(sur, fit, zeta0, quantity, damping)  # run_start solves it compressed (same steps)
        out = run_start((obj, p_start, lower, upper, max_nfev, 1e-8))
        # both halves' SDs as the paper defines them (every value alike), whatever weights the fit used;
        # an unweighted fit's own SD is already that
        plain = all(d.weights is None for d in fit)
        sd_fit = out.sd if plain else _objective(sur, [replace(d, weights=None) for d in fit], zeta0, quantity,
                                                 damping).sd(out.p)
        sd_test = _objective(sur, [replace(d, weights=None) for d in test], zeta0, quantity, damping).sd(out.p)
    return out.p, sd_fit, sd_test


def cross_validate(
    surrogate,
    data,
    p_calibrated,
    lower,
    upper,
    zeta0: float = 0.01,
    n_realizations: int = 20,
    seed: int | None = 0,
    executor=None,
    quantity: str = "accelerance",
    max_nfev: int = 30,
    damping=None,
    bound_tol: float = 1e-3,
) -> CrossValidation:
    """Monte Carlo half/half cross-validation from the calibrated point.

    Parameters
    ----------
    surrogate : Surrogate (basis at or near ``p_calibrated``)
    data : sequence of FitData, the calibration data
    p_calibrated : (n_p,) start of every recalibration
    n_realizations : int (paper: 20 in the text, 10 in the timing)
    damping : (zeta, p_ref), optional
        Per-mode damping of every data set (a sequence of (r,) arrays assigned
        at ``p_ref``): the recalibrations then fit the raw-line model with
        that damping (:class:`calibration._refine.ModalDampingObjective`), as
        the refinement stage does, instead of the uniform ``zeta0``.
    bound_tol : float
        A realization's estimate within ``bound_tol * (upper - lower)`` of a bound counts as at the bound.
    """
    t0 = time.perf_counter()
    lower, upper = check_bounds(lower, upper, surrogate.n_params)
    data = [data] if isinstance(data, FitData) else list(data)
    rng = np.random.default_rng(seed)
    jobs = []
    for _ in range(n_realizations):
        fit, test = split_halves(data, rng)
        jobs.append((surrogate, fit, test, np.asarray(p_calibrated, float), lower, upper, zeta0, quantity, max_nfev,
                     damping))
    res = (executor or SerialExecutor()).map(_realization, jobs)
    P = np.array([r[0] for r in res])
    sd_fit = np.array([r[1] for r in res])
    sd_test = np.array([r[2] for r in res])
    phys = 1.0 + P
    mean = phys.mean(axis=0)
    cv = 100.0 * phys.std(axis=0, ddof=1) / mean if len(res) > 1 else np.full_like(mean, np.nan)
    span = upper - lower
    n_at = np.sum((P <= lower + bound_tol * span) | (P >= upper - bound_tol * span), axis=0)
    reasons = []
    for j in range(P.shape[1]):
        if n_at[j]:
            reasons.append(f"at a bound in {n_at[j]} of {P.shape[0]} realizations: the spread of a pinned "
                           "parameter is not a measure of its uncertainty")
        elif P.shape[0] < 2:
            reasons.append("one realization has no spread")
        else:
            reasons.append("")
    return CrossValidation(
        p=P,
        sd_fit=sd_fit,
        sd_test=sd_test,
        rse=float(sd_test.mean()),
        mean_p=mean - 1.0,
        cv_percent=cv,
        parameter_names=surrogate.parameter_names,
        time_s=time.perf_counter() - t0,
        n_at_bound=n_at,
        cv_reason=tuple(reasons),
    )
