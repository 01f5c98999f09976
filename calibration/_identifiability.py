"""Identifiability of calibrated parameters: bounds, Jacobian singular values, correlation.

A calibrated value is only a measurement when the data constrain it. At the
calibrated point ``p*`` this module reports, per parameter,

* whether it ended at a bound (then the estimate is the bound, not a result);
* its standard deviation from the linearized covariance
  ``C = s^2 (J^T J)^+`` with ``s^2 = |r|^2 / (m - n)`` the residual variance
  (``m`` residuals, ``n`` parameters; the objective's scaling by
  ``1/sqrt(N)`` cancels between ``s^2`` and ``J^T J``);
* its correlation with the other estimates;
* the singular values of the Jacobian with unit-norm columns (scale-free:
  1 for an orthogonal set, near 0 for a combination the data cannot see)
  and, for the weak ones, the parameter combination in words
  (``+0.71 E +0.70 rho``: changing these relative parameters together in
  these proportions hardly changes the compared FRFs);

and a verdict ``identifiable`` with the reasons when it is not.

Thresholds (keyword arguments, module constants as defaults):

``BOUND_TOL = 1e-3``
    a parameter is *at a bound* when within this fraction of its range of it.
``MAX_STD_RANGE = 0.05``
    not identifiable when its standard deviation exceeds this fraction of its
    range ``upper - lower`` (1.5 % of p for a +-30 % range would pass, 3 %
    would not).
``WEAK_RATIO = 0.1``
    a singular value below this fraction of the largest marks a *weak*
    combination (two unit columns with correlation c give
    ``sqrt(1 - |c|)``: 0.1 is |c| ~ 0.99).
``MAX_CORRELATION = 0.95`` and ``CORRELATED_STD_RANGE = 0.01``
    a parameter that takes part in a weak combination (|component| >= 0.3)
    and whose estimate correlates with another by more than 0.95 is not
    identifiable separately unless its standard deviation is below 1 % of
    its range (five times stricter than ``MAX_STD_RANGE``: model error and
    correlated residuals move the estimate along exactly that combination,
    which the independent-residual std does not see). E and rho of a beam
    correlate by ~0.96 and are still found to 0.1 % with good data; that
    case passes.
``FLAT_RATIO = 1e-2``
    a parameter taking part (|component| >= 0.3) in a combination whose
    relative singular value is below 1e-2 is not identifiable, whatever its
    std: along such a direction the metric is flat over a range where the
    linearization fails. Measured on the 17-parameter shell example (11
    channels, 100-400 Hz, noise at its floor): the arm thicknesses in the
    combinations at 1e-3..4e-3 came back 15-21 % off with a formal std of
    1-1.7 %, and t_arm_RHS and M1, taking part with components 0.2-0.5 and
    correlations 0.76-0.996, 3.5-5 % off with a formal std of 0.3-0.5 %. The rule
    is conservative: there E_main and rho_main (in a combination at 9e-3) came
    back within 0.1 % and are still reported as hard to separate, which they are
    from these channels. Those figures were measured with the raw-line fit
    weighting every value alike; with the noise weights of the campaign
    (``refine_weights = "noise"``) the same arm thicknesses come back within
    0.2 % at a formal std of 0.15-0.54 %, so the rule now flags parameters the
    data do hold: the reason then says the formal std is small (within
    ``correlated_std_range`` of the range) and that the cross-validation refits
    decide, and :func:`with_spread` clears them when they agree (15 of 17 on
    that case with 5 refits).
``NULL_RATIO = 1e-8``
    below this relative singular value a combination has no influence at all;
    parameters taking part get an infinite standard deviation.

Correlated residuals. The covariance above assumes independent residuals.
A fit's residuals are correlated along frequency (systematic misfit of a
resonance spans its half-power band; the equalized test model is smooth),
which makes ``s^2 (J^T J)^+`` optimistic. With ``stride`` (the distance in the
residual vector between the same channel/drive at adjacent frequencies) the
lag-1 autocorrelation rho of the residual along frequency is estimated and
the covariance multiplied by the AR(1) variance inflation
``(1 + rho) / (1 - rho)`` (rho clipped to [0, 0.99]); ``inflation`` reports
the factor. Even so the std is local: at a point that is not the optimum
(an unconverged or wrong-basin fit) it says nothing about the distance to
the truth; the correlations and weak combinations are the more robust
signals.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from calibration._errors import CalibrationError

BOUND_TOL = 1e-3
MAX_STD_RANGE = 0.05
WEAK_RATIO = 0.1
MAX_CORRELATION = 0.95
CORRELATED_STD_RANGE = 0.01
NULL_RATIO = 1e-8
FLAT_RATIO = 1e-2
#: smallest |component| of a weak combination for a parameter to "take part" in it
PARTICIPATION = 0.3
#: smallest |component| printed in a combination
SHOWN_COMPONENT = 0.1


def combination_text(vector, names, min_component: float = SHOWN_COMPONENT) -> str:
    """A unit vector over parameters in words, largest components first: ``"+0.71 E -0.70 rho"``."""
    v = np.asarray(vector, float)
    order = np.argsort(-np.round(np.abs(v), 9), kind="stable")  # ties to round-off: in parameter order
    parts = [f"{v[j]:+.2f} {names[j]}" for j in order if abs(v[j]) >= min_component]
    return " ".join(parts) if parts else "(none)"


@dataclass(frozen=True)
class Identifiability:
    """Per-parameter identifiability at a calibrated point.

    Attributes
    ----------
    names : tuple of str, (n,)
    p, lower, upper : (n,) normalized parameters (P = P0 (1 + p)) and bounds
    at_bound : (n,) int: -1 at the lower bound, +1 at the upper, 0 inside
    std : (n,) standard deviation of p (inf when not resolved at all)
    correlation : (n, n) correlation of the estimates (NaN where std is 0 or inf)
    singular_values : (n,) of the unit-column Jacobian, descending
    directions : (n, n) columns: unit combination of p for each singular value
    residual_variance : float, s^2 = |r|^2 / (m - n)
    inflation : float, AR(1) variance inflation applied to the covariance (1 without ``stride``)
    identifiable : (n,) bool
    reasons : tuple of str, "" where identifiable
    thresholds : dict of the thresholds used
    spread : (n,) or None
        Standard deviation of p over cross-validation refits (NaN where a
        refit pinned the parameter), set by :func:`with_spread`; None before.
    std_formal : (n,) or None
        The linearized std before :func:`with_spread` raised ``std`` to the
        refits' spread where that is larger; None before.
    """

    names: tuple
    p: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    at_bound: np.ndarray
    std: np.ndarray
    correlation: np.ndarray
    singular_values: np.ndarray
    directions: np.ndarray
    residual_variance: float
    inflation: float
    identifiable: np.ndarray
    reasons: tuple
    thresholds: dict
    spread: np.ndarray | None = None
    std_formal: np.ndarray | None = None

    @property
    def n_identifiable(self) -> int:
        return int(np.sum(self.identifiable))

    def weak(self) -> list[tuple[float, str]]:
        """(relative singular value, combination in words) for every weak combination, weakest first."""
        s = self.singular_values
        rel = s / s[0] if s.size and s[0] > 0 else np.zeros_like(s)
        out = [(float(rel[k]), combination_text(self.directions[:, k], self.names))
               for k in range(s.size) if rel[k] < self.thresholds["weak_ratio"]]
        return out[::-1]

    def max_correlation(self, j: int) -> tuple[float, str]:
        """Largest |correlation| of parameter j with another one: (signed value, other name)."""
        c = np.array(self.correlation[j], float)
        c[j] = 0.0
        c = np.where(np.isfinite(c), c, 0.0)
        if c.size < 2:
            return 0.0, ""
        k = int(np.argmax(np.abs(c)))
        return float(c[k]), self.names[k]

    def to_dict(self) -> dict:
        s = self.singular_values
        rel = s / s[0] if s.size and s[0] > 0 else np.zeros_like(s)
        params = []
        for j, n in enumerate(self.names):
            c, other = self.max_correlation(j)
            params.append({
                "name": n,
                "p": float(self.p[j]),
                "at_bound": {-1: "lower", 1: "upper"}.get(int(self.at_bound[j])),
                "std_p": float(self.std[j]) if np.isfinite(self.std[j]) else None,
                **({} if self.spread is None else
                   {"spread_p": float(self.spread[j]) if np.isfinite(self.spread[j]) else None,
                    "std_formal_p": float(self.std_formal[j]) if np.isfinite(self.std_formal[j]) else None}),
                "max_correlation": c,
                "correlated_with": other,
                "identifiable": bool(self.identifiable[j]),
                "reason": self.reasons[j] or None,
            })
        return {
            "parameters": params,
            "n_identifiable": self.n_identifiable,
            "singular_values": s.tolist(),
            "relative_singular_values": rel.tolist(),
            "weak_combinations": [{"relative_singular_value": r, "combination": t} for r, t in self.weak()],
            "correlation": np.where(np.isfinite(self.correlation), self.correlation, np.nan).tolist(),
            "residual_variance": self.residual_variance,
            "inflation": self.inflation,
            "thresholds": dict(self.thresholds),
        }

    def table(self) -> str:
        """Plain-text table: parameter, p %, std %, bound, max correlation, verdict."""
        w = max([9] + [len(n) for n in self.names]) + 2
        head = f"{'parameter':<{w}}{'p %':>8}{'std %':>9}" + ("" if self.spread is None else
                                                              f"{'formal %':>9}{'CV s.d.%':>9}")
        lines = [f"{head}  {'bound':<6}{'max corr':>9}  {'with':<{w}}verdict"]
        for j, n in enumerate(self.names):
            c, other = self.max_correlation(j)
            sd = f"{100 * self.std[j]:9.3f}" if np.isfinite(self.std[j]) else f"{'inf':>9}"
            if self.spread is not None:
                f = self.std_formal[j]
                sd += f"{100 * f:9.3f}" if np.isfinite(f) else f"{'inf':>9}"
                sd += f"{100 * self.spread[j]:9.3f}" if np.isfinite(self.spread[j]) else f"{'pinned':>9}"
            b = {-1: "lower", 1: "upper"}.get(int(self.at_bound[j]), "")
            verdict = "identifiable" if self.identifiable[j] else f"NOT identifiable: {self.reasons[j]}"
            lines.append(f"{n:<{w}}{100 * self.p[j]:+8.2f}{sd}  {b:<6}{c:+9.3f}  {other:<{w}}{verdict}")
        weak = self.weak()
        if weak:
            lines.append("weak combinations (relative singular value of the unit-column Jacobian):")
            lines += [f"  {r:.2e}  {t}" for r, t in weak]
        if self.inflation != 1.0:
            lines.append(f"std include x{np.sqrt(self.inflation):.2f} for residuals correlated along frequency")
        if self.spread is not None:
            lines.append("std: the larger of the formal (linearized) std and CV s.d., the std of p over the "
                         "cross-validation refits (pinned: at a bound in one of them)")
        lines.append(f"{self.n_identifiable} of {len(self.names)} parameters identifiable from these channels and band")
        return "\n".join(lines)


def identifiability(
    jacobian,
    residual,
    p,
    lower,
    upper,
    names,
    bound_tol: float = BOUND_TOL,
    max_std_range: float = MAX_STD_RANGE,
    weak_ratio: float = WEAK_RATIO,
    max_correlation: float = MAX_CORRELATION,
    correlated_std_range: float = CORRELATED_STD_RANGE,
    null_ratio: float = NULL_RATIO,
    stride: int | None = None,
) -> Identifiability:
    """Identifiability of the parameters at a calibrated point (see the module docstring).

    Parameters
    ----------
    jacobian : (m, n) real
        d residual / d p at ``p`` (e.g. ``Objective.jacobian(p)``).
    residual : (m,) real
        Residual at ``p`` (e.g. ``Objective.residual(p)``).
    p, lower, upper : (n,) normalized parameters and bounds
    names : sequence of n str
    stride : int, optional
        Distance in ``residual`` between adjacent frequencies of one
        channel/drive (``n_out * n_in`` for unmasked data stacked frequency-major,
        as :class:`Objective` does); enables the correlated-residual inflation.

    Returns
    -------
    Identifiability
    """
    J = np.asarray(jacobian, float)
    r = np.asarray(residual, float).ravel()
    p = np.asarray(p, float).ravel()
    lo = np.asarray(lower, float).ravel()
    hi = np.asarray(upper, float).ravel()
    names = tuple(names)
    n = p.size
    if J.ndim != 2 or J.shape[1] != n or J.shape[0] != r.size:
        raise CalibrationError(f"identifiability: Jacobian {J.shape} must be ({r.size} residuals, {n} parameters)")
    if lo.size != n or hi.size != n or len(names) != n:
        raise CalibrationError(f"identifiability: {n} parameters but {lo.size}/{hi.size} bounds, {len(names)} names")
    if not (np.all(np.isfinite(J)) and np.all(np.isfinite(r))):
        raise CalibrationError("identifiability: Jacobian or residual holds NaN/inf")
    span = hi - lo
    at = np.zeros(n, int)
    at[p <= lo + bound_tol * span] = -1
    at[p >= hi - bound_tol * span] = 1

    dof = max(r.size - n, 1)
    s2 = float(r @ r) / dof
    inflation = 1.0
    if stride is not None:
        k = int(stride)
        if k < 1 or k >= r.size:
            raise CalibrationError(f"identifiability: stride {stride} outside 1..{r.size - 1}")
        rho = float(np.clip(np.dot(r[:-k], r[k:]) / max(float(r @ r), 1e-300), 0.0, 0.99))
        inflation = (1 + rho) / (1 - rho)
        s2 *= inflation
    norms = np.linalg.norm(J, axis=0)
    scale = np.where(norms > 0, norms, 1.0)
    Js = J / scale
    _, sv, Vt = np.linalg.svd(Js, full_matrices=False)
    V = Vt.T
    smax = sv[0] if sv.size and sv[0] > 0 else 1.0
    rel = sv / smax
    null = rel < null_ratio
    # covariance in p: p = x / scale, C_x = s2 V S^-2 V^T over the resolved directions
    inv = np.where(null, 0.0, 1.0 / np.where(null, 1.0, sv) ** 2)
    Cx = (V * inv) @ V.T * s2
    C = Cx / np.outer(scale, scale)
    std_resolved = np.sqrt(np.clip(np.diag(C), 0, None))
    unresolved = (norms == 0) | np.any(np.abs(V[:, null]) >= SHOWN_COMPONENT, axis=1)
    std = np.where(unresolved, np.inf, std_resolved)
    # correlation over the resolved directions (a null pair comes out at +-1: they move together)
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = C / np.outer(std_resolved, std_resolved)
    corr[~np.isfinite(corr)] = np.nan
    # directions in p (relative parameter changes), unit length, sign: largest component positive; of components
    # equal in size to round-off (a +-0.71 pair), the first parameter's, so the words do not follow LAPACK's sign
    D = V / scale[:, None]
    D = D / np.linalg.norm(D, axis=0)
    big = np.abs(D) >= (1 - 1e-9) * np.abs(D).max(axis=0, initial=0.0)
    D = D * np.where(D[np.argmax(big, axis=0), np.arange(n)] < 0, -1.0, 1.0)
    # parameters sharing a null combination: the limit of the covariance as its singular value -> 0
    for k in np.flatnonzero(null):
        idx = np.flatnonzero(np.abs(V[:, k]) >= SHOWN_COMPONENT)
        corr[np.ix_(idx, idx)] = np.sign(np.outer(D[idx, k], D[idx, k]))
    np.fill_diagonal(corr, 1.0)
    weak = rel < weak_ratio

    reasons = []
    for j in range(n):
        why = []
        if at[j]:
            side = "lower" if at[j] < 0 else "upper"
            why.append(f"at the {side} bound ({100 * (lo[j] if at[j] < 0 else hi[j]):+.1f} %): the estimate is the bound")
        if norms[j] == 0:
            why.append("no influence on these channels and band")
        elif unresolved[j]:
            why.append("not resolved from these channels and band (null combination)")
        elif std[j] > max_std_range * span[j]:
            why.append(f"std {100 * std[j]:.2g} % exceeds {100 * max_std_range:.0f} % of its range")
        c = corr[j].copy()
        c[j] = 0.0
        c = np.where(np.isfinite(c), c, 0.0)
        k = int(np.argmax(np.abs(c))) if n > 1 else j
        part = np.flatnonzero(weak & (np.abs(V[j]) >= PARTICIPATION))
        # taking part: a component >= 0.3 in the unit-column direction or in the printed relative change
        flat = np.flatnonzero((rel < FLAT_RATIO) & ~null
                              & ((np.abs(V[j]) >= PARTICIPATION) | (np.abs(D[j]) >= PARTICIPATION)))
        if flat.size and n > 1 and not unresolved[j]:
            kk = flat[np.argmin(rel[flat])]
            why.append(f"in weak combination {combination_text(D[:, kk], names)} "
                       f"(relative singular value {rel[kk]:.1e}: the data hardly see it)"
                       + (f"; its formal std {100 * std[j]:.2g} % is small, so the cross-validation refits decide "
                          "(identifiable when they agree)" if std[j] <= correlated_std_range * span[j] else ""))
        elif part.size and n > 1 and abs(c[k]) > max_correlation and not std[j] <= correlated_std_range * span[j]:
            kk = part[np.argmin(rel[part])]
            why.append(f"in weak combination {combination_text(D[:, kk], names)} "
                       f"(corr {c[k]:+.3f} with {names[k]})")
        reasons.append("; ".join(why))
    ident = np.array([not w for w in reasons], bool)
    return Identifiability(
        names=names, p=p, lower=lo, upper=hi, at_bound=at, std=std, correlation=corr,
        singular_values=sv, directions=D, residual_variance=s2, inflation=inflation, identifiable=ident, reasons=tuple(reasons),
        thresholds={"bound_tol": bound_tol, "max_std_range": max_std_range, "weak_ratio": weak_ratio,
                    "max_correlation": max_correlation, "correlated_std_range": correlated_std_range, "null_ratio": null_ratio},
    )


#: refits needed before their spread can readmit a parameter of a weak combination
MIN_REFITS = 5


def _weak_only(idf: Identifiability, j: int, reason: str) -> bool:
    """Parameter ``j`` is judged not identifiable only by taking part in a weak combination (not at a bound,
    resolved, formal std within the rule): the cross-validation refits may readmit it (:func:`with_spread`)."""
    limit = idf.thresholds["max_std_range"] * (idf.upper[j] - idf.lower[j])
    return (not idf.identifiable[j] and not idf.at_bound[j] and bool(np.isfinite(idf.std[j]))
            and idf.std[j] <= limit and reason.startswith("in weak combination"))


def with_spread(idf: Identifiability, p_refits, bound_tol: float | None = None) -> Identifiability:
    """The verdict checked against what the estimates do when the data change: cross-validation refits.

    The formal std is local (linearized at the optimum, independent
    residuals). Refits on random halves of the lines, each started from the
    calibrated point, measure the same thing without those assumptions: for
    a linear problem the spread of the half-data estimates about their mean
    is the full-data std (Var(p_half - p_full) = 2 s^2 - s^2). Where the two
    disagree the model is nonlinear over the range the estimate moves in, or
    the fit follows model error; the spread is then the honest figure.

    A parameter judged identifiable is not when, in the refits,

    * its spread exceeds ``max_std_range`` of its range (the rule the formal
      std is held to); measured on the 17-parameter 200k shell example: M1 at
      a formal std of 0.36 % had a refit spread of 3.1 % and came back 4.3 %
      off (its +-50 % range lets that pass the rule; +-30 % would not);
    * it ended at a bound in any refit (a bound is not an estimate).

    And the converse: a parameter judged not identifiable *only* because it
    takes part in a weak combination (the flat-direction and correlation
    rules: the linearization is not trusted there) is identifiable when at
    least ``MIN_REFITS`` refits, none at a bound, agree to within the strict
    rule's ``correlated_std_range`` (1 %) of its range: the refits move along
    the flat direction as the data change (on the 200k benchmark the arm
    thicknesses in those combinations spread 4.5-5 %), so a small spread is
    the data holding it. Measured there: E_main, rho_main, t_top_skin and
    t_bottom_skin (weak combinations at 1.6e-3 and 4.4e-3) spread
    0.07-0.49 % and came back 0.0-0.6 % off (at most 2.3 of their spread).

    Parameters
    ----------
    idf : Identifiability at the calibrated point
    p_refits : (n_refits, n) normalized estimates of the refits
    bound_tol : float, optional
        Fraction of the range within which a refit counts as at a bound
        (default: the one ``idf`` was made with).

    The reported ``std`` becomes the larger of the two (the formal one is
    kept in ``std_formal``): on the same benchmark M1 (range +-50 %, so its
    3.1 % spread passes the 5 % rule) is reported at 3.1 % instead of 0.36 %,
    and its 4.3 % error (0.037 in p) is 1.2 of its std instead of 10.

    Returns
    -------
    Identifiability with ``spread`` and ``std_formal`` set (spread NaN for a
    parameter pinned in a refit), ``std`` raised to the spread where larger,
    and the verdicts and reasons amended.
    """
    P = np.atleast_2d(np.asarray(p_refits, float))
    n = len(idf.names)
    if P.shape[1] != n:
        raise CalibrationError(f"with_spread: refits have {P.shape[1]} parameters, the identifiability {n}")
    few = (f"; {P.shape[0]} cross-validation refit{'s' if P.shape[0] != 1 else ''} cannot decide: at least "
           f"{MIN_REFITS} are needed ([crossvalidation] realizations)")
    if P.shape[0] < 2:
        reasons = tuple(r + few if _weak_only(idf, j, r) else r for j, r in enumerate(idf.reasons))
        return replace(idf, spread=np.full(n, np.nan), std_formal=idf.std, reasons=reasons)
    tol = idf.thresholds["bound_tol"] if bound_tol is None else bound_tol
    span = idf.upper - idf.lower
    pinned = np.sum((P <= idf.lower + tol * span) | (P >= idf.upper - tol * span), axis=0)
    spread = np.where(pinned > 0, np.nan, P.std(axis=0, ddof=1))
    limit = idf.thresholds["max_std_range"] * span
    ident = np.array(idf.identifiable, bool).copy()
    reasons = list(idf.reasons)
    strict = idf.thresholds["correlated_std_range"] * span
    for j in range(n):
        if not ident[j]:
            # judged only by taking part in a weak combination (not at a bound, resolved, formal std within the
            # rule): refits that agree to the strict rule's 1 % of the range show the data do hold it
            if _weak_only(idf, j, reasons[j]):
                if P.shape[0] < MIN_REFITS:  # say so: the verdict stays, but the refits could have changed it
                    reasons[j] += few
                elif not pinned[j] and spread[j] <= strict[j]:
                    ident[j] = True
                    reasons[j] = ""
            continue
        if pinned[j]:
            why = (f"at a bound in {pinned[j]} of {P.shape[0]} cross-validation refits (formal std "
                   f"{100 * idf.std[j]:.2g} %): the data do not hold it")
        elif spread[j] > limit[j]:
            why = (f"cross-validation spread {100 * spread[j]:.2g} % exceeds {100 * idf.thresholds['max_std_range']:.0f}"
                   f" % of its range (std over {P.shape[0]} refits on half the lines; the formal std "
                   f"{100 * idf.std[j]:.2g} % is optimistic: the metric is not linear where the estimate moves)")
        else:
            continue
        ident[j] = False
        reasons[j] = why
    std = np.where(np.isfinite(spread), np.maximum(idf.std, np.nan_to_num(spread)), idf.std)
    return replace(idf, spread=spread, std_formal=idf.std, std=std, identifiable=ident, reasons=tuple(reasons))
