"""The reference surface for point-to-plane refinement: local planes fitted on raw points.

The reference cloud is gridded at ``voxel`` (default 5 cm: at 10 cm the along-track estimate
stalled 10-17 mm off in the prototype, at 20 cm 35-52 mm). Each voxel gets a plane fitted to
the *raw* points of the 3 x 3 x 3 voxels around it (15 cm block): its normal is the direction of
least spread and it passes through their mean. Fitting on raw points rather than on voxel
centroids matters when the reference is noisy: a sparse voxel in the noise tail has a centroid
off the surface, but the mean of its block lies on it (unweighted centroids biased the
vertical by 9 mm). Correspondences are found on the voxel centroids (nearest within a radius).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from railtraj.matching.voxel import VoxelGrid, neighbour_sums, voxelize


@dataclass(frozen=True)
class PlaneTarget:
    """Local planes of a reference cloud, one per occupied voxel."""

    grid: VoxelGrid
    anchor: np.ndarray  # (m, 3) mean of the raw points of the block around each voxel
    normal: np.ndarray  # (m, 3) unit normal of that block
    weight: np.ndarray  # (m,) 0 for blocks that are not planar or too sparse, else 1
    tree: cKDTree  # on the voxel centroids
    lo: np.ndarray  # bounding box of the reference points
    hi: np.ndarray

    def nearest(self, p: np.ndarray, max_dist: float) -> tuple[np.ndarray, np.ndarray]:
        """Index of the nearest voxel centroid (-1 beyond ``max_dist``) and the distance."""
        dist, idx = self.tree.query(p, distance_upper_bound=max_dist, workers=-1)
        idx = np.where(np.isfinite(dist), idx, -1)
        return idx, dist

    def inside(self, p: np.ndarray, margin: float) -> np.ndarray:
        """Mask of points at least ``margin`` inside the reference's bounding box (x and y)."""
        return ((p[:, :2] >= self.lo[:2] + margin) & (p[:, :2] <= self.hi[:2] - margin)).all(axis=1)


def build_target(xyz: np.ndarray, voxel: float = 0.05, min_points: int = 6,
                 max_curvature: float = 0.08) -> PlaneTarget:
    """Grid ``xyz`` at ``voxel`` and fit a plane to the raw points around every voxel.

    Blocks with fewer than ``min_points`` points or a surface variation lambda_min / sum above
    ``max_curvature`` (corners, edges, clutter) get weight 0: their normal is not meaningful.
    """
    xyz = np.asarray(xyz, float)
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    grid = voxelize(xyz, voxel)
    m, inv = len(grid), grid.inverse
    local = xyz - grid.origin  # small numbers: the moment sums below stay accurate
    cols = [grid.count.astype(float)] + [np.bincount(inv, local[:, k], m) for k in range(3)]
    pairs = [(i, j) for i in range(3) for j in range(i, 3)]
    cols += [np.bincount(inv, local[:, i] * local[:, j], m) for i, j in pairs]
    s = neighbour_sums(grid, np.column_stack(cols))
    n = s[:, 0]
    mean = s[:, 1:4] / n[:, None]
    cov = np.empty((m, 3, 3))
    for c, (i, j) in enumerate(pairs):
        cov[:, i, j] = cov[:, j, i] = s[:, 4 + c] / n - mean[:, i] * mean[:, j]
    evals, evecs = np.linalg.eigh(cov)
    curvature = evals[:, 0] / np.maximum(evals.sum(axis=1), 1e-12)
    weight = ((n >= min_points) & (curvature <= max_curvature)).astype(float)
    return PlaneTarget(grid, mean + grid.origin, np.ascontiguousarray(evecs[:, :, 0]), weight,
                       cKDTree(grid.xyz), lo, hi)


_cache: list[tuple[np.ndarray, float, PlaneTarget]] = []


def cached_target(xyz: np.ndarray, voxel: float = 0.05) -> PlaneTarget:
    """:func:`build_target`, remembering the last two clouds (by identity) for repeated use.

    A matcher checks several vote peaks and then refines, all against the same reference; the
    cache keeps a reference to the array, so its identity cannot be reused while cached.
    """
    for arr, v, target in _cache:
        if arr is xyz and v == voxel:
            return target
    target = build_target(xyz, voxel)
    _cache.insert(0, (xyz, voxel, target))
    del _cache[2:]
    return target
