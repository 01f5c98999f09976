"""Accepting a candidate effect, and the effect that separates article groups (issue 14).

Acceptance (:func:`accept`) is a pure decision on numbers the caller has
measured before and after adding the effect's parameters:

1. **Floor.** When the hold-out SD before is already within ``floor_factor``
   of the noise floor SD, nothing more is to be explained: reject, stop.
2. **Hold-out, penalized.** A BIC-like penalty per added parameter: with n
   independent residuals and k added parameters the hold-out SD must fall
   by more than the factor exp(-k ln(n) / n) (for Gaussian residuals the
   BIC difference n ln(SD_after / SD_before) + k ln n must be negative).
   FRF residuals are correlated over the lines of a half-power bandwidth,
   so n is the caller's count of *independent* residuals (e.g. compared
   values / lines per half-power bandwidth), not the number of values.
3. **Beyond the scatter.** The cross-validation test SDs (one per
   realization, the same splits before and after: pass the same seed) must
   improve on average by more than their scatter: mean(d) > ``n_sigma`` x
   sd(d), d the paired differences before - after (unpaired: the pooled
   standard deviation of the two sets), and the hold-out improvement must
   exceed the same scatter.

Accepted when 2 and 3 hold; ``stop`` says the residual after is at the floor
(no further effect to look for).

Separation (:func:`separating_effect`): with the existing parameters common
(or re-fitted per article), an effect's magnitude c is fitted per article;
it separates the given groups when the smallest difference between group
means exceeds ``n_sigma`` times the pooled within-group standard deviation
(plus an absolute resolution ``c_tol``) and the groups' ranges do not
overlap.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration._errors import CalibrationError
from calibration._fit import Objective, check_bounds, run_start
from calibration._surrogate import Surrogate


@dataclass(frozen=True)
class Acceptance:
    """Decision on one effect (or set of effects) by :func:`accept`.

    Attributes
    ----------
    accepted : bool
    stop : bool, the residual is at the floor (before, when rejected for that reason, or after)
    reason : str, one line
    holdout_ratio : float, hold-out SD after / before
    penalty_ratio : float, the largest ratio the per-parameter penalty allows
    cv_improvement : float, mean improvement of the cross-validation test SD
    cv_scatter : float, scatter of that improvement (standard deviation over realizations)
    floor_ratio_before, floor_ratio_after : float, hold-out SD / floor SD
    """

    accepted: bool
    stop: bool
    reason: str
    holdout_ratio: float
    penalty_ratio: float
    cv_improvement: float
    cv_scatter: float
    floor_ratio_before: float
    floor_ratio_after: float

    def to_dict(self) -> dict:
        """Plain values; a ratio to a zero floor (inf) becomes None."""
        out = {}
        for k, v in self.__dict__.items():
            if isinstance(v, (bool, np.bool_)):
                v = bool(v)
            elif isinstance(v, (float, np.floating)):
                v = float(v) if np.isfinite(v) else None
            out[k] = v
        return out


def accept(
    holdout_before: float,
    holdout_after: float,
    cv_before,
    cv_after,
    floor_sd: float,
    n_added: int,
    n_residuals: int,
    *,
    n_sigma: float = 1.0,
    floor_factor: float = 1.5,
) -> Acceptance:
    """Accept an effect if hold-out and cross-validation improve beyond scatter and penalty (see the module doc).

    Parameters
    ----------
    holdout_before, holdout_after : float
        Hold-out SD without and with the effect.
    cv_before, cv_after : (n_real,) array
        Cross-validation test SDs without and with the effect (same splits:
        paired when of equal length).
    floor_sd : float
        Noise floor SD of the hold-out data (:func:`calibration.noise_floor_sd`).
    n_added : int
        Parameters the effect adds (>= 1).
    n_residuals : int
        Independent residuals of the hold-out comparison (see the module doc).
    n_sigma : float
        Improvement required in units of the scatter.
    floor_factor : float
        SD within this factor of the floor counts as at the floor.

    Returns
    -------
    Acceptance
    """
    hb, ha, fl = float(holdout_before), float(holdout_after), float(floor_sd)
    cb, ca = np.atleast_1d(np.asarray(cv_before, float)), np.atleast_1d(np.asarray(cv_after, float))
    if not (hb > 0 and ha >= 0 and fl >= 0) or not np.all(np.isfinite([hb, ha, fl])):
        raise CalibrationError(f"accept: hold-out SDs must be finite, before > 0 (got {hb}, {ha}), floor >= 0 ({fl})")
    if n_added < 1 or n_residuals < 2:
        raise CalibrationError(f"accept: need n_added >= 1 and n_residuals >= 2, got {n_added}, {n_residuals}")
    if cb.size < 2 or ca.size < 2 or not (np.all(np.isfinite(cb)) and np.all(np.isfinite(ca))):
        raise CalibrationError("accept: need at least 2 finite cross-validation SDs before and after")
    if cb.size == ca.size:
        d = cb - ca
        imp, scatter = float(d.mean()), float(d.std(ddof=1))
    else:
        imp = float(cb.mean() - ca.mean())
        scatter = float(np.sqrt(0.5 * (cb.var(ddof=1) + ca.var(ddof=1))))
    ratio = ha / hb
    allowed = float(np.exp(-n_added * np.log(n_residuals) / n_residuals))
    fb = hb / fl if fl > 0 else np.inf
    fa = ha / fl if fl > 0 else np.inf
    common = dict(holdout_ratio=ratio, penalty_ratio=allowed, cv_improvement=imp, cv_scatter=scatter,
                  floor_ratio_before=fb, floor_ratio_after=fa)
    if fb <= floor_factor:
        return Acceptance(False, True, f"hold-out SD already at the floor ({fb:.2f} x floor): nothing to explain",
                          **common)
    if ratio >= allowed:
        return Acceptance(False, False, f"hold-out SD ratio {ratio:.4f} not below {allowed:.4f} "
                          f"(penalty for {n_added} parameter(s) on {n_residuals} residuals)", **common)
    if not imp > n_sigma * scatter:
        return Acceptance(False, False, f"cross-validation improves by {imp:.3g}, not beyond {n_sigma:g} x its "
                          f"scatter {scatter:.3g}", **common)
    if not hb - ha > n_sigma * scatter:
        return Acceptance(False, False, f"hold-out improves by {hb - ha:.3g}, not beyond {n_sigma:g} x the "
                          f"cross-validation scatter {scatter:.3g}", **common)
    stop = fa <= floor_factor
    return Acceptance(True, stop, f"hold-out SD x{ratio:.3f}, cross-validation -{imp:.3g} (scatter {scatter:.3g})"
                      + ("; at the floor now" if stop else ""), **common)


def negligible_effect(holdout_with: float, holdout_without: float, n_residuals: int, n_params: int = 1) -> tuple:
    """Whether an accepted effect, at its final (refined) size, is negligible: setting it to zero in the final
    model raises the hold-out SD by less than the acceptance's penalty for its parameters (:func:`accept`, rule
    2: the factor exp(k ln(n) / n)); the data then do not see it at that size and the model is as good
    without it (e.g. a spring refined to 1e-37 N/m: the ratio is exactly 1).

    Parameters
    ----------
    holdout_with, holdout_without : float
        Hold-out SD of the final model, and of the same model with the effect's magnitude set to 0 (no re-fit).
    n_residuals : int
        Independent residuals of the hold-out comparison (as for :func:`accept`).
    n_params : int
        The effect's parameters.

    Returns
    -------
    (negligible: bool, ratio with / without: float, the penalty ratio exp(-k ln(n) / n): float)
    """
    hw, h0 = float(holdout_with), float(holdout_without)
    if not (hw >= 0 and h0 > 0) or not np.isfinite([hw, h0]).all():
        raise CalibrationError(f"negligible_effect: hold-out SDs must be finite and >= 0 (> 0 without the "
                               f"effect), got {hw}, {h0}")
    if n_params < 1 or n_residuals < 2:
        raise CalibrationError(f"negligible_effect: need n_params >= 1 and n_residuals >= 2, got {n_params}, "
                               f"{n_residuals}")
    allowed = float(np.exp(-n_params * np.log(n_residuals) / n_residuals))
    ratio = hw / h0
    return bool(ratio >= allowed), float(ratio), allowed


@dataclass(frozen=True)
class Separation:
    """Per-article magnitude of an effect and whether it separates article groups.

    Attributes
    ----------
    articles : tuple of str
    groups : (n_a,) int group labels
    magnitude : (n_a,) fitted normalized magnitude c per article
    p : (n_a, n_p) existing parameters per article (all equal when common)
    sd : (n_a,) square deviation of each article at its fit
    group_mean : (n_g,) ; within_sd : float, pooled within-group standard deviation of c
    gap : float, smallest difference between group means
    separates : bool ; reason : str
    """

    articles: tuple
    groups: np.ndarray
    magnitude: np.ndarray
    p: np.ndarray
    sd: np.ndarray
    group_mean: np.ndarray
    within_sd: float
    gap: float
    separates: bool
    reason: str

    def to_dict(self) -> dict:
        return {"articles": list(self.articles), "groups": self.groups.tolist(), "magnitude": self.magnitude.tolist(),
                "p": self.p.tolist(), "sd": self.sd.tolist(), "group_mean": self.group_mean.tolist(),
                "within_sd": self.within_sd, "gap": self.gap, "separates": self.separates, "reason": self.reason}


def separating_effect(
    sur: Surrogate,
    x,
    article_data,
    zeta: float,
    groups,
    lower,
    upper,
    *,
    index: int = -1,
    refit_p: bool = False,
    quantity: str = "accelerance",
    max_nfev: int = 50,
    n_sigma: float = 3.0,
    c_tol: float = 0.0,
    continuation=(),
) -> Separation:
    """Fit an effect's magnitude per article and test whether it separates the article groups.

    Parameters
    ----------
    sur : Surrogate
        A surrogate that has the effect as a parameter (e.g.
        :attr:`CandidateFit.surrogate`).
    x : (n,) its parameters (common start: existing parameters and magnitudes).
    article_data : sequence of sequence of FitData
        Equalized data of every article (``FitData.article`` names it).
    zeta : float
    groups : (n_a,) labels of the articles' groups (e.g. from :func:`calibration.grouping`).
    lower, upper : (n,) bounds of ``x``.
    index : int
        Position of the effect's magnitude in ``x`` (default the last).
    refit_p : bool
        Re-fit all parameters per article (default: only the magnitude, the
        others held at ``x``).
    n_sigma : float
        Required gap between group means in pooled within-group standard deviations.
    c_tol : float
        Absolute resolution of c added to the scatter (a gap must exceed it too).
    continuation : sequence of (zeta, article_data)
        Damping-continuation stages run first (wider damping first), each
        with the articles' data equalized at that damping, in the order of
        ``article_data``. An effect that moves modes by many half-power
        bandwidths between the groups (a gap closed on some articles, open
        on others) leaves the articles of the other group far outside the
        metric's smooth range at ``zeta``; the wider stages bring them in.

    Returns
    -------
    Separation
    """
    x = np.asarray(x, float)
    lower, upper = check_bounds(lower, upper, sur.n_params)
    if x.shape != (sur.n_params,):
        raise CalibrationError(f"separating_effect: x has shape {x.shape}, the surrogate {sur.n_params} parameters")
    sets = [list(d) for d in article_data]
    labels = np.asarray(groups)
    if labels.shape != (len(sets),):
        raise CalibrationError(f"separating_effect: {labels.size} group labels for {len(sets)} articles")
    uniq = np.unique(labels)
    if uniq.size < 2:
        raise CalibrationError("separating_effect needs at least two groups")
    stages = [(float(z), [list(d) for d in stage]) for z, stage in continuation]
    for z, stage in stages:
        if len(stage) != len(sets):
            raise CalibrationError(f"separating_effect: continuation stage at zeta {z:g} has {len(stage)} articles, "
                                   f"article_data {len(sets)}")
    j = int(index) % sur.n_params
    mags, ps, sds, names = [], [], [], []
    for k, d in enumerate(sets):
        objs = [Objective(sur, stage[k], z, quantity) for z, stage in stages] + [Objective(sur, d, zeta, quantity)]
        names.append(d[0].article or f"article {k}")
        if refit_p:
            out = run_start((objs, x, lower, upper, max_nfev, 1e-10))
            xk = out.p
        else:
            subs = [_OneParameter(obj, x, j) for obj in objs]
            out = run_start((subs, x[[j]], lower[[j]], upper[[j]], max_nfev, 1e-10))
            xk = x.copy()
            xk[j] = out.p[0]
        mags.append(xk[j])
        ps.append(np.delete(xk, j))
        sds.append(out.sd)
    mags = np.array(mags)
    means = np.array([mags[labels == g].mean() for g in uniq])
    dev = np.concatenate([mags[labels == g] - mags[labels == g].mean() for g in uniq])
    dof = mags.size - uniq.size
    within = float(np.sqrt(np.sum(dev**2) / dof)) if dof > 0 else 0.0
    sm = np.sort(means)
    gap = float(np.min(np.diff(sm)))
    ranges = sorted((mags[labels == g].min(), mags[labels == g].max()) for g in uniq)
    overlap = any(a[1] >= b[0] for a, b in zip(ranges, ranges[1:]))
    need = n_sigma * within + c_tol
    if dof == 0:
        reason = "every group has one article: no within-group scatter to compare with"
        ok = False
    elif overlap:
        reason = f"group ranges of c overlap (gap between means {gap:.3g}, within-group sd {within:.3g})"
        ok = False
    elif gap <= need:
        reason = f"gap between group means {gap:.3g} not beyond {n_sigma:g} x within-group sd {within:.3g} + {c_tol:g}"
        ok = False
    else:
        reason = f"gap between group means {gap:.3g} > {n_sigma:g} x within-group sd {within:.3g} + {c_tol:g}"
        ok = True
    return Separation(tuple(names), labels, mags, np.array(ps), np.array(sds), means, within, gap, ok, reason)


class _OneParameter:
    """An objective in one parameter j of another, the others held at x."""

    def __init__(self, obj, x, j: int):
        self.obj, self.x, self.j = obj, np.asarray(x, float), j

    def _full(self, y):
        z = self.x.copy()
        z[self.j] = float(np.asarray(y).ravel()[0])
        return z

    def residual(self, y):
        return self.obj.residual(self._full(y))

    def jacobian(self, y):
        return self.obj.jacobian(self._full(y))[:, [self.j]]


def separation_score(sep: Separation) -> float:
    """Gap between group means in pooled within-group standard deviations (inf for no scatter, 0 for no gap)."""
    if sep.gap <= 0:
        return 0.0
    return float(sep.gap / sep.within_sd) if sep.within_sd > 0 else np.inf


def rank_separating(
    sur: Surrogate,
    basis,
    model,
    candidates,
    article_data,
    zeta: float,
    groups,
    lower,
    upper,
    *,
    p0,
    c0=None,
    shift_hz: float | None = None,
    solve=None,
    quantity: str = "accelerance",
    refit_p: bool = False,
    n_sigma: float = 3.0,
    c_tol: float = 0.0,
    max_nfev: int = 50,
) -> list:
    """Which candidate's magnitude separates the article groups: each fitted on all articles, then per article.

    For every candidate: :func:`calibration.fit_with` on the data of all
    articles together (common p and c, the ensemble's calibration with the
    candidate), then :func:`separating_effect` from that point.

    Parameters
    ----------
    sur, basis, model : as :func:`calibration.fit_with`.
    candidates : sequence of CandidateTerm (e.g. the screening's top few).
    article_data : sequence of sequence of FitData, one per article.
    zeta, groups, lower, upper : as :func:`separating_effect` (``lower``, ``upper`` of the existing parameters).
    p0 : (n_p,) start of the existing parameters; c0 : (n_c,) start magnitudes (default 0).
    shift_hz, solve : static solves of the extension (``solve`` is formed once when not given).
    refit_p, n_sigma, c_tol : as :func:`separating_effect`.

    Returns
    -------
    list of (name, CandidateFit, Separation)
        Separating candidates first, each group by the mean of the articles'
        SD after their per-article fit (ascending). A decoy that mimics the
        true effect in part separates the groups too (its fitted magnitude
        takes up part of the group difference), but leaves more of every
        article's residual: the effect that separates *and* explains the
        articles comes first.
    """
    from calibration._diagnose import fit_with, shifted_solver

    cands = list(candidates)
    c0 = np.zeros(len(cands)) if c0 is None else np.asarray(c0, float)
    if c0.shape != (len(cands),):
        raise CalibrationError(f"rank_separating: c0 has shape {c0.shape}, expected ({len(cands)},)")
    if solve is None:
        if model is None or not (shift_hz is not None and shift_hz > 0):
            raise CalibrationError("rank_separating needs the model and shift_hz > 0, or solve")
        solve = shifted_solver(model, sur.p_basis, shift_hz)
    pooled = [d for art in article_data for d in art]
    out = []
    for cand, c_start in zip(cands, c0):
        fit = fit_with(sur, basis, model, [cand], pooled, zeta, lower, upper, p0=p0, c0=[c_start], solve=solve,
                       quantity=quantity, max_nfev=max_nfev)
        sep = separating_effect(fit.surrogate, fit.x, article_data, zeta, groups, fit.lower, fit.upper,
                                refit_p=refit_p, quantity=quantity, max_nfev=max_nfev, n_sigma=n_sigma, c_tol=c_tol)
        out.append((cand.name, fit, sep))
    out.sort(key=lambda t: (not t[2].separates, float(np.mean(t[2].sd))))
    return out
