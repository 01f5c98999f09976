"""Test-article ensembles: FRF similarity and grouping (paper Sec. 2.3.2).

The pairwise square deviation between two articles' FRFs on common lines,
SD_ab = mean |log10(H_a/H_b)|^2, is a symmetric dissimilarity. Articles are
grouped by average-linkage hierarchical clustering of that matrix.

Without a requested number of groups, a partition is accepted only when the
articles' own repeatability does not explain it. Every cut of the
dendrogram into k = 2 .. n-1 groups is a candidate; for it

    B = the lowest linkage height above the cut (the smallest average SD
        between two groups that the cut keeps apart: every split it makes
        must stand out, not just the largest),
    W = the mean SD over all within-group pairs of the candidate (the
        scatter of articles that belong together: production scatter,
        mounting, identification error), pooled over every group,
    N = the mean of ``floor_a + floor_b`` over all pairs, ``floor`` each
        article's noise floor of the SD from its lines' standard errors
        (two noisy measurements of one FRF differ by about the sum),

and the ratio ``B / max(W, N)``. With four or more articles a candidate
must keep at least two within-group pairs (one pair can be close by
chance, and the raw-line noise floor N is usually far below the article
scatter, so it cannot stand in for W); with three, one pair. Two articles
always form one group: nothing measures their scatter (N alone would split
any two real articles); ask for ``n_groups = 2`` or ``ensemble = "article"``
to calibrate them apart. The candidate with the largest ratio is taken if that
ratio exceeds ``gap_factor``; otherwise all articles form one group. So two
articles always stay one group unless their noise floors are known.

Why ``gap_factor = 6``: for articles from one population with deviation
vectors delta (covariance S), an article k's mean SD to the others is about
``|delta_k|^2 + tr S`` while pairs inside the group average ``2 tr S``; a
ratio of 6 needs ``|delta_k|^2 ~ 11 tr S``, a > 3-sigma outlier even if all
the scatter lay in one direction. The former default (cut at the largest
relative jump of successive linkage heights) split alike articles whenever
two of them happened to be very close.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration._errors import CalibrationError
from calibration._metric import log_deviation, square_deviation


def pairwise_sd(frfs, masks=None) -> np.ndarray:
    """(n_a, n_a) symmetric square deviation between articles' FRFs on common lines.

    Parameters
    ----------
    frfs : sequence of (n_f, n_out, n_in) complex arrays on the same lines/channels
    masks : sequence of bool arrays (valid values), optional
    """
    n = len(frfs)
    if n == 0:
        raise CalibrationError("no articles to compare")
    shapes = {np.shape(h) for h in frfs}
    if len(shapes) != 1:
        raise CalibrationError(f"articles' FRFs differ in shape {sorted(shapes)}: resample to common lines first")
    D = np.zeros((n, n))
    for a in range(n):
        for b in range(a + 1, n):
            m = np.ones(np.shape(frfs[a]), bool)
            if masks is not None:
                m = np.asarray(masks[a], bool) & np.asarray(masks[b], bool)
            D[a, b] = D[b, a] = square_deviation(log_deviation(np.asarray(frfs[a])[m], np.asarray(frfs[b])[m]))
    return D


@dataclass(frozen=True)
class Grouping:
    """Grouping of articles with the tests that decided it.

    labels : (n_a,) int, 0-based group labels by first appearance
    splits : tuple of dict, one per candidate cut (k, groups, between_sd, within_sd, within_pairs, noise_sd,
        ratio, accepted)
    gap_factor : float ; n_groups_requested : int or None
    """

    labels: np.ndarray
    splits: tuple
    gap_factor: float
    n_groups_requested: int | None = None

    def describe(self, names) -> str:
        """The candidate partitions and the decision in words."""
        if self.n_groups_requested is not None:
            return f"{self.n_groups_requested} groups requested (n_groups)"
        if not self.splits:
            return "one group: too few articles to judge a split"
        chosen = [t for t in self.splits if t["accepted"]]
        best = max(chosen, key=lambda t: t["ratio"]) if chosen else max(self.splits, key=lambda t: t["ratio"])
        groups = " | ".join(",".join(names[i] for i in g) for g in best["groups"])
        ref = max(best["within_sd"], best["noise_sd"])
        verdict = "split" if chosen else f"kept as one group (needs > {self.gap_factor:g}x)"
        return (f"best cut {groups}: between-group SD {best['between_sd']:.3g} = {best['ratio']:.1f}x the "
                f"within-group/noise SD {ref:.3g} -> {verdict}")

    def to_dict(self) -> dict:
        return {"labels": self.labels.tolist(), "gap_factor": self.gap_factor,
                "n_groups_requested": self.n_groups_requested,
                "splits": [{k: (list(v) if isinstance(v, tuple) else v) for k, v in t.items()} for t in self.splits]}


def _relabel(labels) -> np.ndarray:
    order = {}
    return np.array([order.setdefault(int(v), len(order)) for v in labels], int)


def grouping(sd_matrix, n_groups: int | None = None, noise_sd=None, gap_factor: float = 6.0) -> Grouping:
    """Group articles from a pairwise SD matrix (see the module docstring for the criterion).

    Parameters
    ----------
    sd_matrix : (n_a, n_a) symmetric pairwise SD (:func:`pairwise_sd`)
    n_groups : int, optional
        Cut the dendrogram into exactly this many groups instead.
    noise_sd : (n_a,) float, optional
        Each article's noise floor of the SD (e.g. ``noise_floor_sd`` of its
        lines' standard errors); a lower bound of the within-group reference.
    gap_factor : float
        Between-group SD over the within-group/noise reference needed to split.

    Returns
    -------
    Grouping
    """
    from scipy.cluster.hierarchy import fcluster, linkage
    from scipy.spatial.distance import squareform

    D = np.asarray(sd_matrix, float)
    n = D.shape[0]
    if D.ndim != 2 or D.shape != (n, n) or not np.all(np.isfinite(D)):
        raise CalibrationError(f"pairwise SD matrix must be square and finite, got shape {D.shape}")
    D = 0.5 * (D + D.T)
    floor = np.zeros(n) if noise_sd is None else np.asarray(noise_sd, float)
    if floor.shape != (n,) or np.any(floor < 0) or not np.all(np.isfinite(floor)):
        raise CalibrationError(f"noise floors must be {n} non-negative numbers, got {noise_sd!r}")
    if n == 1:
        return Grouping(np.zeros(1, int), (), gap_factor, n_groups)
    Z = linkage(squareform(D, checks=False), method="average")
    if n_groups is not None:
        if not 1 <= n_groups <= n:
            raise CalibrationError(f"n_groups = {n_groups} for {n} articles")
        return Grouping(_relabel(fcluster(Z, t=n_groups, criterion="maxclust")), (), gap_factor, n_groups)
    heights = Z[:, 2]
    iu = np.triu_indices(n, 1)
    N = float(np.mean(floor[iu[0]] + floor[iu[1]]))
    tests = []
    for k in range(2, n):
        lab = fcluster(Z, t=k, criterion="maxclust")
        if lab.max() != k:  # tied heights: this k is not a cut of its own
            continue
        same = lab[iu[0]] == lab[iu[1]]
        W = float(np.mean(D[iu][same])) if same.any() else 0.0
        B = float(heights[n - k])
        ref = max(W, N)
        # one within pair can be close by chance: with four or more articles a cut needs two
        judged = same.sum() >= min(2, n - 2) and ref > 0
        ratio = B / ref if judged else 0.0
        tests.append({"k": k, "groups": tuple(tuple(np.flatnonzero(lab == g).tolist()) for g in np.unique(lab)),
                      "between_sd": B, "within_sd": W, "within_pairs": int(same.sum()), "noise_sd": N,
                      "ratio": ratio, "accepted": bool(ratio > gap_factor)})
    ok = [t for t in tests if t["accepted"]]
    labels = np.zeros(n, int)
    if ok:
        best = max(ok, key=lambda t: t["ratio"])
        for g, members in enumerate(best["groups"]):
            labels[list(members)] = g
    return Grouping(_relabel(labels), tuple(tests), gap_factor, None)


def group_articles(sd_matrix, n_groups: int | None = None, noise_sd=None, gap_factor: float = 6.0) -> np.ndarray:
    """Group labels (0-based, by first appearance) from a pairwise SD matrix: ``grouping(...).labels``."""
    return grouping(sd_matrix, n_groups, noise_sd, gap_factor).labels
