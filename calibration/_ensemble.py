"""Test-article ensembles: FRF similarity and grouping (paper Sec. 2.3.2).

The pairwise square deviation between two articles' FRFs on common lines,
SD_ab = mean |log10(H_a/H_b)|^2, is a symmetric dissimilarity. Articles are
grouped by average-linkage hierarchical clustering of that matrix; without
a requested number of groups the dendrogram is cut at its largest relative
gap (the paper's five subframes fell into two clear groups), and everything
is one group when no gap stands out (ratio < ``min_gap_ratio``).
"""

from __future__ import annotations

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


def group_articles(sd_matrix, n_groups: int | None = None, min_gap_ratio: float = 2.0) -> np.ndarray:
    """Group labels (0-based, by first appearance) from a pairwise SD matrix."""
    from scipy.cluster.hierarchy import fcluster, linkage
    from scipy.spatial.distance import squareform

    D = np.asarray(sd_matrix, float)
    n = D.shape[0]
    if n == 1:
        return np.zeros(1, int)
    Z = linkage(squareform(0.5 * (D + D.T), checks=False), method="average")
    if n_groups is not None:
        labels = fcluster(Z, t=n_groups, criterion="maxclust")
    else:
        heights = Z[:, 2]
        within = np.concatenate([[0.0], heights[:-1]])
        ratio = heights / np.maximum(within, 1e-300)
        k = int(np.argmax(ratio[1:]) + 1) if n > 2 else 1
        if n == 2:
            # two articles: separate only if clearly dissimilar relative to nothing; keep together
            return np.zeros(2, int)
        if ratio[k] < min_gap_ratio:
            return np.zeros(n, int)
        labels = fcluster(Z, t=0.5 * (heights[k - 1] + heights[k]), criterion="distance")
    # relabel by first appearance
    order = {}
    return np.array([order.setdefault(l, len(order)) for l in labels], int)
