"""The ``voxel_corner`` detector: keypoints where the local geometry is 3-D, one per voxel.

A wall or a floor spreads its points in two directions, a cable in one; a corner, a niche edge
or a box spreads them in three. Per voxel we take the covariance of its points and score it by
``lambda_min / lambda_max``; the ``max_keypoints`` voxels with the highest score (and at least
``min_points`` points) become keypoints at their centroid, with the mean gps_time of their points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from railtraj.data import Keypoints, PointTile
from railtraj.hookspecs import hookimpl


@dataclass
class VoxelCornerConfig:
    name: str = "voxel_corner"
    voxel_size: float = 0.4      # metres; about the size of the objects to find
    min_points: int = 20         # voxels with fewer points are too noisy to score
    min_score: float = 0.05      # lambda_min / lambda_max below this is a plane or a line
    max_keypoints: int = 700     # the best-scored voxels kept


class VoxelCornerDetector:
    def __init__(self, voxel_size: float = 0.4, min_points: int = 20, min_score: float = 0.05,
                 max_keypoints: int = 700) -> None:
        if voxel_size <= 0:
            raise ValueError("voxel_corner: voxel_size must be positive")
        self.voxel_size, self.min_points = voxel_size, min_points
        self.min_score, self.max_keypoints = min_score, max_keypoints

    def detect(self, tile: PointTile) -> Keypoints:
        if len(tile) == 0:
            return Keypoints(np.zeros((0, 3)), np.zeros(0), np.zeros(0))
        origin = tile.xyz.min(axis=0)
        local = tile.xyz - origin
        cells = np.floor(local / self.voxel_size).astype(np.int64)
        _, inverse, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
        inverse = inverse.ravel()
        n = len(counts)
        mean = np.stack([np.bincount(inverse, local[:, k], n) for k in range(3)], axis=1) / counts[:, None]
        second = np.empty((n, 3, 3))
        for i in range(3):
            for j in range(i, 3):
                second[:, i, j] = second[:, j, i] = np.bincount(inverse, local[:, i] * local[:, j], n) / counts
        cov = second - mean[:, :, None] * mean[:, None, :]
        eig = np.linalg.eigvalsh(cov)                     # ascending, per voxel
        score = eig[:, 0] / np.maximum(eig[:, 2], 1e-12)
        keep = np.flatnonzero((counts >= self.min_points) & (score >= self.min_score))
        keep = keep[np.argsort(-score[keep])][: self.max_keypoints]
        t_mean = np.bincount(inverse, tile.gps_time - tile.gps_time.min(), n) / counts + tile.gps_time.min()
        return Keypoints(mean[keep] + origin, t_mean[keep], score[keep])


@hookimpl
def railtraj_register_stages(registry) -> None:
    registry.add("detector", "voxel_corner", VoxelCornerDetector, VoxelCornerConfig)
