"""Turning detector output (voxel indices and a response) into :class:`railtraj.data.Keypoints`."""

from __future__ import annotations

import numpy as np

from railtraj.data import Keypoints, PointTile
from railtraj.matching.voxel import VoxelGrid, nearest_member


def top_n(score: np.ndarray, n: int) -> np.ndarray:
    """Indices of the ``n`` largest scores, best first (all of them when ``n <= 0``)."""
    order = np.argsort(-score, kind="stable")
    return order if n <= 0 else order[:n]


def from_voxels(tile: PointTile, grid: VoxelGrid, idx: np.ndarray, score: np.ndarray,
                max_keypoints: int = 0) -> Keypoints:
    """Keypoints at voxel centroids ``grid.xyz[idx]``, best ``max_keypoints`` by ``score``.

    Each keypoint's gps_time is that of the raw point nearest to it inside its voxel
    (see :mod:`railtraj.matching.voxel`).
    """
    idx = np.asarray(idx, np.int64)
    keep = top_n(np.asarray(score, float), max_keypoints)
    idx, score = idx[keep], np.asarray(score, float)[keep]
    raw = nearest_member(grid, tile.xyz, idx)
    return Keypoints(grid.xyz[idx], tile.gps_time[raw], score)
