"""The reference surface for point-to-plane refinement: local planes fitted on raw points.

The reference cloud is gridded at ``voxel`` (default 5 cm: at 10 cm the along-track estimate
stalled 10-17 mm off in the prototype, at 20 cm 35-52 mm). Each voxel gets a plane fitted to
the *raw* points of the 3 x 3 x 3 voxels around it (15 cm block): its normal is the direction of
least spread and it passes through their mean. Fitting on raw points rather than on voxel
centroids matters when the reference is noisy: a sparse voxel in the noise tail has a centroid
off the surface, but the mean of its block lies on it (unweighted centroids biased the
vertical by 9 mm). Correspondences are found on the voxel centroids (nearest within a radius).

A block too sparse for a plane (a far wall, a sparse scanner) has none; :func:`filled_target`
gives it the plane of the block twice its size, for the across-and-up fits of a pair's windows.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from railtraj.data import extent
from railtraj.matching.memo import ArrayMemo
from railtraj.matching.neighbours import smallest_eigen
from railtraj.matching.threads import query_workers
from railtraj.matching.voxel import (
    VoxelGrid,
    block_covariance,
    neighbour_sums,
    pack,
    voxel_coords,
    voxelize,
)


@dataclass(frozen=True)
class PlaneTarget:
    """Local planes of a reference cloud, one per occupied voxel."""

    grid: VoxelGrid
    anchor: np.ndarray  # (m, 3) mean of the raw points of the block around each voxel
    normal: np.ndarray  # (m, 3) unit normal of that block
    weight: np.ndarray  # (m,) 0 for blocks that are not planar or too sparse, else 1
    normal_var: np.ndarray  # (m,) variance of the fitted normal's tilt (rad^2), from the fit
    line_like: np.ndarray  # (m,) the block's points lie along a line: its normal may turn about it
    tree: cKDTree  # on the voxel centroids
    lo: np.ndarray  # bounding box of the reference points
    hi: np.ndarray
    surface: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # anchor, normal, has-plane: where points fit (fits)
    surface_reach: float = 0.0  # m; how far from a voxel centroid a point may still lie on its plane (fits)

    def fits(self, q: np.ndarray, idx: np.ndarray, dist: np.ndarray, radius: float) -> np.ndarray:
        """Mask of the points ``q`` that lie on the reference within ``radius``: their nearest voxel
        centroid (``idx``, ``dist``, from :meth:`nearest` searched at least ``surface_reach`` far)
        lies within ``radius``, or, with :attr:`surface` planes, within ``surface_reach`` and its
        plane within ``radius``.

        A sparse scan samples a wall in rows of points along the track as far apart as a
        profile's points; another run's rows fall between them, half a row spacing from the
        nearest point but on the wall. Counted by distance to a centroid, a held-out run at 140
        points per profile (rows 0.136 m apart) fitted by 0.22-0.57 at the true offset, where a
        run whose rows happened to fall on run a's fitted by 0.90-0.98, and its pairs were
        refused as no overlap; counted on the filled planes (:func:`filled_target`) within a row
        spacing, by 0.74-0.92. On dense scans ``surface_reach`` is below the radius: nothing changes.
        """
        hit = dist <= radius
        if self.surface is None or self.surface_reach <= radius:
            return hit
        far = np.flatnonzero(~hit & (dist <= self.surface_reach))
        anchor, normal, has_plane = self.surface
        j = idx[far]
        off = np.abs(np.einsum("ij,ij->i", normal[j], q[far] - anchor[j]))
        hit[far] = has_plane[j] & (off <= radius)
        return hit

    def nearest(self, p: np.ndarray, max_dist: float) -> tuple[np.ndarray, np.ndarray]:
        """Index of the nearest voxel centroid (-1 beyond ``max_dist``) and the distance."""
        dist, idx = self.tree.query(p, distance_upper_bound=max_dist, workers=query_workers(len(p)))
        idx = np.where(np.isfinite(dist), idx, -1)
        return idx, dist

    def tracker(self, max_dist: float) -> NearestTracker:
        """:meth:`nearest` for one set of points that moves in small steps (see NearestTracker)."""
        return NearestTracker(self.tree, max_dist)

    def inside(self, p: np.ndarray, margin: float) -> np.ndarray:
        """Mask of points at least ``margin`` inside the reference's bounding box (x and y)."""
        return ((p[:, :2] >= self.lo[:2] + margin) & (p[:, :2] <= self.hi[:2] - margin)).all(axis=1)


class NearestTracker:
    """:meth:`PlaneTarget.nearest` (same indices, same distances to the bit) for points that move
    a little between calls, as in the Gauss-Newton iterations of a point-to-plane fit.

    Each search also finds the second-nearest centroid, within ``max_dist + slack``. A point that
    has since moved by ``delta`` keeps its nearest centroid while ``d1 + delta < d2 - delta``
    (no other centroid can have come closer) and stays without one while ``reach - delta >
    max_dist``; only the other points are searched again. Distances to kept centroids are
    recomputed as the KD-tree computes them (squared coordinate differences summed in order,
    found when below ``max_dist**2``), so nothing differs from a fresh query. After the first
    steps of a fit most points move by less than a millimetre and are not searched again.
    """

    MARGIN = 1e-9  # m; far above rounding (1e-17 m), so a kept answer is never a near tie

    def __init__(self, tree: cKDTree, max_dist: float, slack: float = 0.02) -> None:
        self.tree, self.max_dist, self.reach = tree, max_dist, max_dist + slack
        self.q0 = self.idx = self.d1 = self.d2 = None
        self.searched = 0  # points searched so far (for tests and benchmarks)

    def __call__(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q = np.asarray(q, float)
        if self.q0 is None or len(q) != len(self.q0):
            self.q0, self.idx = q.copy(), np.zeros(len(q), np.int64)
            self.d1, self.d2 = np.full(len(q), np.inf), np.full(len(q), np.inf)
            redo = np.arange(len(q))
        else:
            delta = np.sqrt(((q - self.q0) ** 2).sum(axis=1))
            found = np.isfinite(self.d1)
            kept = np.where(found, self.d1 + delta < np.minimum(self.d2, self.reach) - delta - self.MARGIN,
                            self.reach - delta > self.max_dist + self.MARGIN)
            redo = np.flatnonzero(~kept)
        if len(redo):
            d, i = self.tree.query(q[redo], k=2, distance_upper_bound=self.reach, workers=query_workers(len(redo)))
            tie = np.flatnonzero(np.isfinite(d[:, 0]) & (d[:, 0] == d[:, 1]))
            if len(tie):  # two centroids equally near (1 mm LAS coordinates): take the one k=1 takes
                i[tie, 0] = self.tree.query(q[redo[tie]], distance_upper_bound=self.reach,
                                            workers=query_workers(len(tie)))[1]
            self.q0[redo], self.idx[redo], self.d1[redo], self.d2[redo] = q[redo], i[:, 0], d[:, 0], d[:, 1]
            self.searched += len(redo)
        idx = np.where(np.isfinite(self.d1), self.idx, -1)
        dist = np.full(len(q), np.inf)
        has = np.flatnonzero(idx >= 0)
        diff = q[has] - self.tree.data[idx[has]]
        d2 = diff[:, 0] * diff[:, 0] + diff[:, 1] * diff[:, 1] + diff[:, 2] * diff[:, 2]
        near = d2 < self.max_dist * self.max_dist
        dist[has[near]] = np.sqrt(d2[near])
        idx[has[~near]] = -1
        return idx, dist


#: raw points a plane block needs, and the largest surface variation it may have (build_target)
MIN_BLOCK_POINTS = 6
MAX_CURVATURE = 0.15
#: a block whose second spread is below this share of its first holds a line of points, not a
#: plane (filled_target)
MIN_SPREAD_RATIO = 0.05


def build_target(xyz: np.ndarray, voxel: float = 0.05, min_points: int = MIN_BLOCK_POINTS,
                 max_curvature: float = MAX_CURVATURE) -> PlaneTarget:
    """Grid ``xyz`` at ``voxel`` and fit a plane to the raw points around every voxel.

    Blocks with fewer than ``min_points`` points or a surface variation lambda_min / sum above
    ``max_curvature`` (corners, edges, clutter) get weight 0: their normal is not meaningful.
    With 2 cm noise a flat 15 cm block already has a variation of ~0.095 and an edge ~0.14, so
    the threshold is 0.15; at 0.10 most planar blocks were dropped and along-track accuracy fell
    from <1 mm to ~5 mm on a dense simulated tile.
    """
    xyz = np.asarray(xyz, float)
    lo, hi = extent(xyz)
    grid = voxelize(xyz, voxel)
    n, mean, cov = block_covariance(xyz, grid)
    planar, normal, normal_var, line_like = _block_planes(n, cov, min_points, max_curvature)
    return PlaneTarget(grid, mean, normal, planar.astype(float), normal_var, line_like, cKDTree(grid.xyz), lo, hi)


def _block_planes(n: np.ndarray, cov: np.ndarray, min_points: int,
                  max_curvature: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Whether each block (``n`` points, covariance ``cov``) is a plane, its normal, the
    normal's tilt variance, and whether its points lie along a line (see filled_target)."""
    evals, normal = smallest_eigen(cov)
    curvature = evals[:, 0] / np.maximum(evals.sum(axis=1), 1e-12)
    line_like = evals[:, 1] < MIN_SPREAD_RATIO * evals[:, 2]
    return (n >= min_points) & (curvature <= max_curvature), normal, tilt_variance(n, evals), line_like


def filled_target(xyz: np.ndarray, target: PlaneTarget, min_points: int = MIN_BLOCK_POINTS,
                  max_curvature: float = MAX_CURVATURE) -> PlaneTarget:
    """``target`` (built on ``xyz``) with each block too sparse for a plane given the plane of
    the block twice its size, where that one is planar.

    A sparse scanner's far wall holds a point or two per profile line in a 15 cm block: no
    plane. At a tile's corner, where the near wall is outside the tile, across then rested on
    rails and ceiling details the runs see from opposite sides: a pair's windows 4-7 cm off
    across (mixed 72, 350 points per profile; 45 % of run a's voxels without a plane), within 3
    mm with these planes. Only the windows' across-and-up fits use them: in the vote checks and
    along-track profiles, flat far walls that fit every alias made a 50 m-tile survey's pairs
    ambiguous (0.012 -> 0.67 m).

    Sparser still, a block holds one point of each of a few profiles: a line along the track, as
    flat as a plane (its surface variation is nil) but with a normal free to turn about it. At
    120 points per profile (17-40 cm apart along each) such lines were 18-94 % of the planar
    blocks, and windows sat 9-26 cm off across with a claimed sd of 3-8 mm; they get the plane of
    the block twice the size too (within 7 mm), or none. Denser scans have few (none among the
    planar blocks of the demo's, a tube's and a commensurate tunnel's tiles).
    """
    block_points = neighbour_sums(target.grid, target.grid.count[:, None].astype(float))[:, 0]
    line = target.line_like & (target.weight > 0)
    redo = np.flatnonzero((block_points < min_points) | line)  # blocks dropped for their curvature stay dropped
    if not len(redo):
        return target
    found, mean, normal, var = _coarse_planes(xyz, target.grid, redo, min_points, max_curvature)
    taken = redo[found]
    anchor, normals, weight, normal_var = (target.anchor.copy(), target.normal.copy(), target.weight.copy(),
                                           target.normal_var.copy())
    weight[line] = 0.0
    anchor[taken], normals[taken], weight[taken], normal_var[taken] = mean, normal, 1.0, var
    return replace(target, anchor=anchor, normal=normals, weight=weight, normal_var=normal_var)


def _coarse_planes(xyz: np.ndarray, grid: VoxelGrid, voxels: np.ndarray, min_points: int,
                   max_curvature: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Planes of the blocks twice the size for the ``voxels`` of ``grid``: which found a planar
    one (mask over ``voxels``), and those blocks' mean, normal and tilt variance.

    The coarse grid's corners are every other corner of ``grid`` (twice its voxel, its origin
    one coarse voxel back), so each voxel's centroid lies in the coarse voxel holding its points.
    """
    size = 2 * grid.size
    origin = grid.origin - size
    coarse = voxelize(xyz, size, origin)
    slot = np.searchsorted(coarse.keys, pack(voxel_coords(grid.xyz[voxels], size, origin)))
    n, mean, cov = block_covariance(xyz, coarse)
    planar, normal, normal_var, line_like = _block_planes(n[slot], cov[slot], min_points, max_curvature)
    found = planar & ~line_like
    return found, mean[slot][found], normal[found], normal_var[found]


def tilt_variance(n: np.ndarray, evals: np.ndarray) -> np.ndarray:
    """Expected squared tilt (rad^2) of a normal fitted to ``n`` noisy points, per in-plane axis.

    Noise variance ``s2 = l0 n / (n - 3)`` (the smallest sample eigenvalue is biased low) and the
    true in-plane spreads ``l_k - s2``; errors in all coordinates add the factor ``1 + s2 / l_k``.
    Checked by Monte Carlo on 15 cm blocks with 0.5-2 cm noise: within 10 % from 20 points up,
    conservative (too large) below; the plain ``l0 / (n l_k)`` was 1.5-2.3x too small at 2 cm.
    """
    s2 = evals[:, 0] * n / np.maximum(n - 3, 1)
    spread = np.maximum(evals[:, 1:] - s2[:, None], 0.25 * evals[:, 1:])
    spread = np.maximum(spread, 1e-12)
    var = (s2[:, None] / (np.maximum(n, 1)[:, None] * spread) * (1 + s2[:, None] / spread)).mean(axis=1)
    return np.minimum(var, 0.5)


_targets = ArrayMemo(build_target)
_filled = ArrayMemo(lambda xyz, voxel: filled_target(xyz, _targets(xyz, voxel)))


def cached_target(xyz: np.ndarray, voxel: float = 0.05) -> PlaneTarget:
    """:func:`build_target`, remembered for the last two clouds while those arrays are alive
    (:mod:`railtraj.matching.memo`).

    A matcher checks several vote peaks and then refines, all against the same reference, and a
    tile is the reference of up to three tile pairs; a finished tile's target goes with its array.
    """
    return _targets(xyz, voxel)


def with_surface(target: PlaneTarget, planes: PlaneTarget, reach: float) -> PlaneTarget:
    """``target`` on which points fit also where ``planes`` (its :func:`filled_target`: the same
    grid) have a plane that passes within the fitness radius of them, its centroid within
    ``reach`` (:meth:`PlaneTarget.fits`)."""
    return replace(target, surface=(planes.anchor, planes.normal, planes.weight > 0), surface_reach=reach)


def cached_filled_target(xyz: np.ndarray, voxel: float = 0.05) -> PlaneTarget:
    """:func:`filled_target` of :func:`cached_target`, remembered the same way."""
    return _filled(xyz, voxel)
