"""Neighbourhood statistics without Python loops over points.

Radius neighbourhoods come from scipy's cKDTree as index lists or index pairs; everything after
that is flat numpy (``np.repeat`` + ``np.bincount``), so a few hundred thousand neighbourhoods
cost well under a second.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def ball_members(tree: cKDTree, centers: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Flat (center index, point index) arrays of every point within ``radius`` of each center."""
    lists = tree.query_ball_point(np.asarray(centers, float), radius, workers=-1)
    lengths = np.fromiter((len(x) for x in lists), np.int64, len(lists))
    if lengths.sum() == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.repeat(np.arange(len(lists)), lengths), np.concatenate(lists).astype(np.int64)


def grouped_covariance(group: np.ndarray, xyz: np.ndarray, n_groups: int,
                       weight: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted mean (m, 3), covariance (m, 3, 3) and weight sum (m,) of points grouped by ``group``."""
    w = np.ones(len(group)) if weight is None else np.asarray(weight, float)
    s = np.bincount(group, w, n_groups)
    safe = np.where(s > 0, s, 1.0)
    mean = np.column_stack([np.bincount(group, w * xyz[:, k], n_groups) for k in range(3)]) / safe[:, None]
    c = xyz - mean[group]
    cov = np.empty((n_groups, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            cov[:, i, j] = cov[:, j, i] = np.bincount(group, w * c[:, i] * c[:, j], n_groups) / safe
    return mean, cov, s


def local_covariance(tree: cKDTree, centers: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Covariance (m, 3, 3) of the tree's points within ``radius`` of each center, and the counts."""
    group, member = ball_members(tree, centers, radius)
    _, cov, count = grouped_covariance(group, tree.data[member], len(centers))
    return cov, count.astype(np.int64)


def pair_neighbourhoods(tree: cKDTree, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Symmetric (i, j) pairs of tree points closer than ``radius``, each point paired with itself."""
    pairs = tree.query_pairs(radius, output_type="ndarray")
    n = tree.n
    i = np.concatenate([pairs[:, 0], pairs[:, 1], np.arange(n)])
    j = np.concatenate([pairs[:, 1], pairs[:, 0], np.arange(n)])
    return i, j


def neighbour_max(values: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Largest ``values[j]`` over the pairs (i, j) of each i (``-inf`` for points without pairs)."""
    out = np.full(len(values), -np.inf)
    np.maximum.at(out, i, values[j])
    return out
