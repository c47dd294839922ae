"""Voxel grids that remember which raw points they hold, so keypoints keep a real GPS time.

Detectors run on a voxel grid (ISS on raw mobile-mapping density is ~400x slower) but a
keypoint must be tied to the trajectory by the time its point was measured. We therefore keep
each raw point's voxel (``inverse``) and give a keypoint the gps_time of the raw point nearest
to it *within its voxel*: a time that was actually measured, never an average of two passes of
the scanner over the same spot (a voxel mean time would be, for a train that stopped).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from railtraj.data import extent


@dataclass(frozen=True)
class VoxelGrid:
    """Occupied voxels of a cloud: count-weighted centroid, point count and raw-point membership."""

    size: float
    xyz: np.ndarray  # (m, 3) mean of the raw points in each voxel
    count: np.ndarray  # (m,) raw points per voxel
    inverse: np.ndarray  # (n,) voxel index of each raw point
    keys: np.ndarray  # (m,) sorted int64 voxel keys (see :func:`pack`); size <= 0: point indices
    origin: np.ndarray  # (3,) corner the integer voxel coordinates count from

    def __len__(self) -> int:
        return len(self.xyz)


_BITS = 21  # 2**21 voxels per axis: 200 km at 10 cm; keys fit in int64


def voxel_coords(xyz: np.ndarray, size: float, origin: np.ndarray) -> np.ndarray:
    """Integer voxel coordinates (n, 3) of points relative to ``origin``."""
    return np.floor((xyz - origin) / size).astype(np.int64)


def pack(ijk: np.ndarray) -> np.ndarray:
    """One int64 key per integer voxel coordinate (coordinates must lie in [0, 2**21))."""
    return (ijk[:, 0] << (2 * _BITS)) | (ijk[:, 1] << _BITS) | ijk[:, 2]


def voxelize(xyz: np.ndarray, size: float, origin: np.ndarray | None = None) -> VoxelGrid:
    """Group points into cubic voxels of edge ``size``; ``size <= 0`` keeps every point."""
    xyz = np.asarray(xyz, dtype=float)
    n = len(xyz)
    if origin is None:
        origin = extent(xyz)[0] - size if n else np.zeros(3)
    if size <= 0 or n == 0:
        keys = np.arange(n, dtype=np.int64)
        return VoxelGrid(size, xyz.copy(), np.ones(n, np.int64), keys.copy(), keys, np.asarray(origin))
    keys, inverse, count = np.unique(pack(voxel_coords(xyz, size, origin)),
                                     return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    centroid = np.column_stack([np.bincount(inverse, xyz[:, k], len(keys)) for k in range(3)])
    return VoxelGrid(size, centroid / count[:, None], count, inverse, keys, np.asarray(origin, float))


def nearest_member(grid: VoxelGrid, raw_xyz: np.ndarray, voxel_idx: np.ndarray,
                   positions: np.ndarray | None = None) -> np.ndarray:
    """For each voxel in ``voxel_idx``, the raw index of its point nearest to ``positions``.

    ``positions`` defaults to the voxel centroids. Voxels listed twice get the same answer.
    """
    voxel_idx = np.asarray(voxel_idx, dtype=np.int64)
    if len(voxel_idx) == 0:
        return np.zeros(0, np.int64)
    pos = grid.xyz[voxel_idx] if positions is None else np.asarray(positions, float)
    slot = np.full(len(grid), -1, np.int64)
    slot[voxel_idx] = np.arange(len(voxel_idx))
    members = np.flatnonzero(slot[grid.inverse] >= 0)
    k = slot[grid.inverse[members]]  # which requested voxel each member belongs to
    d2 = ((raw_xyz[members] - pos[k]) ** 2).sum(axis=1)
    order = np.lexsort((d2, k))
    first = order[np.r_[True, np.diff(k[order]) != 0]]
    best = np.empty(len(voxel_idx), np.int64)
    best[k[first]] = members[first]
    return best[slot[voxel_idx]]


def neighbour_sums(grid: VoxelGrid, values: np.ndarray) -> np.ndarray:
    """Sum of per-voxel ``values`` (m, c) over the 3 x 3 x 3 block of voxels around each voxel.

    Neighbours are found by key with ``np.searchsorted``, so this works on sparse grids of any
    extent. z is the fastest-varying part of a key, so one search per (dx, dy) column finds the
    up to three voxels dz = -1, 0, 1 at consecutive positions. Missing neighbours read a zero row.
    """
    keys, m = grid.keys, len(grid.keys)
    padded = np.vstack([values, np.zeros((1,) + values.shape[1:])])
    out = np.zeros_like(values)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            target = keys + ((dx << (2 * _BITS)) + (dy << _BITS))
            pos = np.searchsorted(keys, target - 1)
            for s in range(3):
                idx = np.minimum(pos + s, m - 1)
                k = keys[idx]
                idx[(k < target - 1) | (k > target + 1) | (pos + s >= m)] = m
                out += np.take(padded, idx, axis=0)
    return out


def block_covariance(xyz: np.ndarray, grid: VoxelGrid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Point count (m,), mean (m, 3) and covariance (m, 3, 3) of the *raw* points in the
    3 x 3 x 3 block of voxels around each voxel: a local plane fit that sees every point."""
    m, inv = len(grid), grid.inverse
    local = np.asarray(xyz, float) - grid.origin  # small numbers keep the moment sums accurate
    pairs = [(i, j) for i in range(3) for j in range(i, 3)]
    cols = [grid.count.astype(float)] + [np.bincount(inv, local[:, k], m) for k in range(3)]
    cols += [np.bincount(inv, local[:, i] * local[:, j], m) for i, j in pairs]
    s = neighbour_sums(grid, np.column_stack(cols))
    n = s[:, 0]
    mean = s[:, 1:4] / n[:, None]
    cov = np.empty((m, 3, 3))
    for c, (i, j) in enumerate(pairs):
        cov[:, i, j] = cov[:, j, i] = s[:, 4 + c] / n - mean[:, i] * mean[:, j]
    return n, mean + grid.origin, cov
