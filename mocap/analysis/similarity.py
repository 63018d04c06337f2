"""Similarity of digs, their unsupervised grouping, and relations between parameters.

- Distance between two digs: dynamic time warping (dtaidistance) of their paths over
  normalised arc length, positions in units of the session's median dig length and the
  bucket angle in radians, so that a metre-scale difference of path and a radian of angle
  weigh alike.
- Grouping: average-linkage hierarchical clustering (scipy) of that distance; the number of
  groups is the one of best mean silhouette (2..8), one group when no split reaches a
  silhouette of `min_silhouette`; a group too small to be a type is outliers (a dig unlike
  any other, or a glitch of the reconstruction). More groups than the three classes hint at
  types beyond the paper's.
- Relations: per class, the bucket angle against the direction of the tip's path
  (a straight line, least squares, with its correlation); Pearson correlations of the
  per-cycle parameters.

Shapes: K digs, N arc-length samples, P parameters.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from dtaidistance import dtw_ndim
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.spatial.distance import squareform


@dataclass(frozen=True)
class Grouping:
    """groups (K,) 1-based group of each dig, 0 for an outlier (a dig in a group too small
    to be a type); count of groups (outliers not counted); silhouette (mean, outliers 0;
    NaN for one group)."""

    groups: np.ndarray
    count: int
    silhouette: float


@dataclass(frozen=True)
class Relation:
    """Bucket angle = intercept + slope · path direction (rad), over `samples`, with
    Pearson `r`."""

    label: str
    slope: float
    intercept: float
    r: float
    samples: int


def dtw_matrix(path: np.ndarray) -> np.ndarray:
    """Symmetric DTW distances (K, K) between digs' paths (K, N, 3): dx, dz (m), angle (rad)."""
    k = len(path)
    if k < 2:
        return np.zeros((k, k))
    length = np.median(np.abs(path[:, -1, :2]).sum(axis=1))
    unit = np.array([max(length, 1e-6)] * 2 + [1.0])
    series = [np.ascontiguousarray(p / unit, dtype=np.double) for p in path]
    # pruned by each pair's Euclidean distance (an upper bound of its DTW): a quarter faster,
    # the same distances; a pair whose DTW is its Euclidean distance (the diagonal warping)
    # comes back infinite from the pruning and is taken again unpruned
    d = np.asarray(dtw_ndim.distance_matrix(series, use_c=True, parallel=True, use_pruning=True), dtype=float)
    i, j = np.triu_indices(k, 1)
    lost = ~np.isfinite(d[i, j])
    for a, b in zip(i[lost], j[lost]):
        d[a, b] = dtw_ndim.distance_fast(series[a], series[b], use_pruning=False)
    d = np.where(np.isfinite(d), d, d.T)
    np.fill_diagonal(d, 0.0)
    return np.minimum(d, d.T)


def silhouette(d: np.ndarray, groups: np.ndarray) -> float:
    """Mean silhouette of a grouping under distances d (K, K)."""
    labels = np.unique(groups)
    member = groups[:, None] == labels[None]  # (K, G)
    total = d @ member  # (K, G) sum of distances to each group
    size = member.sum(axis=0)
    own = member.argmax(axis=1)
    a = total[np.arange(len(d)), own] / np.maximum(size[own] - 1, 1)
    other = np.where(member, np.inf, total / size)
    b = other.min(axis=1)
    s = np.where(size[own] > 1, (b - a) / np.maximum(np.maximum(a, b), 1e-12), 0.0)
    return float(s.mean())


def group_digs(d: np.ndarray, max_groups: int = 8, min_silhouette: float = 0.5) -> Grouping:
    """Hierarchical grouping of digs under distances d (K, K); a group of fewer than
    max(2, 3 % of the digs) is outliers (at most a tenth of the digs, or one), each with a
    silhouette of 0."""
    k = len(d)
    if k < 3:
        return Grouping(np.ones(k, dtype=int), 1, float("nan"))
    tree = linkage(squareform(d, checks=False), method="average")
    min_size = max(2, int(np.ceil(0.03 * k)))
    best = Grouping(np.ones(k, dtype=int), 1, float("nan"))
    for count in range(2, min(max_groups, k - 1) + 1):
        groups = fcluster(tree, count, criterion="maxclust")
        small = np.bincount(groups)[groups] < min_size
        kept = np.unique(groups[~small])
        if len(kept) < 2 or small.sum() > max(1, 0.1 * k):  # outliers are a few digs at most
            continue
        # an outlier counts as silhouette 0, as a group of one does: setting digs apart must pay
        score = silhouette(d[np.ix_(~small, ~small)], groups[~small]) * float(np.mean(~small))
        if score >= min_silhouette and (best.count == 1 or score > best.silhouette):
            best = Grouping(np.where(small, 0, np.searchsorted(kept, groups) + 1), len(kept), score)
    return best


def direction_relation(label: str, path: np.ndarray) -> Relation:
    """Bucket angle against the path's direction over the digs (K, N, 3) of one class."""
    direction = np.arctan2(np.gradient(path[:, :, 1], axis=1), np.gradient(path[:, :, 0], axis=1))
    x, y = direction[:, 2:-2].ravel(), path[:, 2:-2, 2].ravel()
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if len(x) < 3 or np.std(x) < 1e-9:
        return Relation(label, float("nan"), float("nan"), float("nan"), len(x))
    slope, intercept = np.polyfit(x, y, 1)
    return Relation(label, float(slope), float(intercept), float(np.corrcoef(x, y)[0, 1]), len(x))


def correlations(table: dict[str, np.ndarray], names: tuple[str, ...]) -> np.ndarray:
    """Pearson correlations (P, P) of the named columns over the cycles where all are finite."""
    data = np.column_stack([np.asarray(table[n], dtype=float) for n in names])
    data = data[np.isfinite(data).all(axis=1)]
    if len(data) < 3:
        return np.full((len(names), len(names)), np.nan)
    sd = data.std(axis=0)
    z = (data - data.mean(axis=0)) / np.where(sd > 0, sd, np.nan)
    return (z.T @ z) / len(data)
