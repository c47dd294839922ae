"""The ``icp`` matcher: refine a tile offset from ``initial`` (or zero) and say what is constrained.

``method="plane"`` (default): translation-only (or 6-DoF) point-to-plane Gauss-Newton of up to
``max_points`` raw points of tile b against local planes of tile a on a 5 cm grid
(:mod:`railtraj.matching.refine`); it recovers along-track offsets to about a millimetre where
ribs, boxes or sleepers face along the track. ``method="kiss"``: kiss-icp's point-to-point
6-DoF registration (it slides along a tunnel: started 0.8 m off it stayed 0.7 m off in the
prototype), used for the rotation and a coarse translation, then polished translation-only
point-to-plane. Either way the covariance comes from the point-to-plane normal matrix at the
result, corrected for normal noise, so a featureless stretch shows its weak along-track
direction. A converged fit one sleeper or rib away looks as good as the right one, so by
default (``alias_check``) tile b is slid along the weak axis across the search window: a
clearly better alias is taken, an equally good one makes the pair ``ambiguous``.
Status: ``no_overlap`` (tiles apart or fitness below ``min_fitness``), ``ambiguous``,
``degenerate`` (sd along the weakest direction above ``max_sd``), ``ok``. ``info["constraint"]``
is the weakest information per point: roughly the share of points facing that way.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace

import numpy as np

from railtraj.data import Keypoints, PointTile, TileOffset
from railtraj.errors import ConfigError
from railtraj.hookspecs import hookimpl
from railtraj.matching.consensus import (
    Checked,
    alias_rivals,
    boxes_overlap,
    check_peaks,
    choose,
    consensus,
    failed,
    make_ties,
)
from railtraj.matching.refine import Fit, crop, directions, point_to_plane, sample
from railtraj.matching.target import PlaneTarget, cached_target
from railtraj.matching.voting import Peak, pair_translations

log = logging.getLogger(__name__)


@dataclass
class IcpConfig:
    name: str = "icp"
    method: str = "plane"  # plane (point-to-plane GN) | kiss (kiss-icp, point-to-point, 6-DoF)
    translation_only: bool = True  # plane only; kiss always estimates rotation too
    max_misalignment: float = 3.0  # m; the search window: caps the sd of unconstrained directions
    target_voxel: float = 0.05  # m; grid of the reference planes
    max_points: int = 100_000  # raw points of tile b used
    iterations: int = 20
    max_dist: float = 0.25  # m; correspondence search radius
    kernel: float = 0.05  # m; Huber threshold on point-to-plane residuals
    crop_margin: float = 0.3  # m; use only b points this far inside tile a's box
    fitness_radius: float = 0.05  # m; fitness = share of points this close to tile a
    min_fitness: float = 0.5
    max_sd: float = 0.03  # m; sd along the weakest direction above this: degenerate
    tie_radius: float = 0.1  # m; keypoint pairs this close to agreeing with d become ties
    tie_positions: str = "offset"  # offset | keypoints (see matching.consensus.make_ties)
    kiss_voxel: float = 0.25  # m; kiss-icp map voxel
    alias_check: bool = True  # slide tile b along the weak axis to find a better or equal alias
    ambiguity_ratio: float = 0.8  # misfit of the result / of a distinct alias; above: ambiguous


class IcpMatcher:
    """Refines the translation that moves tile b onto tile a (see module docstring)."""

    def __init__(self, method: str = "plane", translation_only: bool = True, max_misalignment: float = 3.0,
                 target_voxel: float = 0.05, max_points: int = 100_000, iterations: int = 20,
                 max_dist: float = 0.25, kernel: float = 0.05, crop_margin: float = 0.3,
                 fitness_radius: float = 0.05, min_fitness: float = 0.5, max_sd: float = 0.03,
                 tie_radius: float = 0.1, tie_positions: str = "offset", kiss_voxel: float = 0.25,
                 alias_check: bool = True, ambiguity_ratio: float = 0.8) -> None:
        if method not in ("plane", "kiss"):
            raise ConfigError(f"matcher=icp method={method!r}: choose plane or kiss")
        if tie_positions not in ("offset", "keypoints"):
            raise ConfigError(f"tie_positions={tie_positions!r}: choose offset or keypoints")
        self.method, self.translation_only, self.window = method, translation_only, max_misalignment
        self.target_voxel, self.max_points, self.iterations = target_voxel, max_points, iterations
        self.max_dist, self.kernel, self.crop_margin = max_dist, kernel, crop_margin
        self.fitness_radius, self.min_fitness, self.max_sd = fitness_radius, min_fitness, max_sd
        self.tie_radius, self.tie_positions, self.kiss_voxel = tie_radius, tie_positions, kiss_voxel
        self.alias_check, self.ambiguity_ratio = alias_check, ambiguity_ratio

    def match(self, tile_a: PointTile, kp_a: Keypoints, tile_b: PointTile, kp_b: Keypoints,
              initial: TileOffset | None = None) -> TileOffset:
        t0 = time.perf_counter()
        d0 = np.zeros(3)
        if initial is not None and np.isfinite(initial.d).all():
            d0 = np.asarray(initial.d, float)
        info: dict = {"timings": {}, "method": self.method, "initial": d0.tolist()}
        if len(tile_a) == 0 or len(tile_b) == 0 or not boxes_overlap(tile_a, tile_b, d0, 0.0):
            return failed(tile_a, tile_b, "no_overlap", info)
        target = cached_target(tile_a.xyz, self.target_voxel)
        moving = crop(target, sample(tile_b.xyz, self.max_points), d0, self.crop_margin)
        info["timings"]["target"] = time.perf_counter() - t0
        if len(moving) < 100:
            return failed(tile_a, tile_b, "no_overlap", info)
        t1 = time.perf_counter()
        fit = self._fit(tile_a, target, moving, d0)
        info["timings"]["refine"] = time.perf_counter() - t1
        weak_sd = np.sqrt(np.linalg.eigvalsh(fit.cov)[-1])
        if self.alias_check and fit.fitness >= self.min_fitness and weak_sd <= self.max_sd:
            t2 = time.perf_counter()
            fit, rival = self._aliases(tile_a, tile_b, target, moving, fit, d0, info)
            info["timings"]["alias_check"] = time.perf_counter() - t2
            if rival >= self.ambiguity_ratio:
                info["timings"]["total"] = time.perf_counter() - t0
                return failed(tile_a, tile_b, "ambiguous", info, fit.d, fit.cov)
        return self._result(tile_a, kp_a, tile_b, kp_b, fit, info, t0)

    def _fit(self, tile_a: PointTile, target: PlaneTarget, moving: np.ndarray, d0: np.ndarray) -> Fit:
        if self.method == "kiss":
            return self._kiss(tile_a, moving, target, d0)
        return point_to_plane(target, moving, d0, translation_only=self.translation_only,
                              iterations=self.iterations, max_dist=self.max_dist, kernel=self.kernel,
                              fitness_radius=self.fitness_radius, max_sd=self.window)

    def _aliases(self, tile_a, tile_b, target, moving, fit: Fit, d0, info) -> tuple[Fit, float]:
        """A local optimum one sleeper or rib away looks converged: slide along the weak axis,
        move to a clearly better alias, and report how close the best distinct rival comes."""
        small = sample(tile_b.xyz, 20_000, seed=1)
        here = check_peaks(target, small, [Peak(fit.d, 0)], iterations=0, fitness_radius=self.fitness_radius)
        here = [Checked(here[0].peak, replace(here[0].fit, information=fit.information))]
        rivals, info["alias_profile"] = alias_rivals(target, small, here[0], d0, self.window,
                                                     self.fitness_radius, 2 * self.tie_radius)
        checked = here + rivals
        best, rival = choose(checked, self.tie_radius)
        info["alias_fitness"] = [[*c.fit.d.tolist(), c.fit.fitness] for c in checked]
        if best != 0:
            log.debug("icp %s/%s: moved to an alias that fits better", tile_a.name, tile_b.name)
            info["moved_to_alias"] = (checked[best].fit.d - fit.d).tolist()
            fit = self._fit(tile_a, target, moving, checked[best].fit.d)
        info["rival_misfit_ratio"] = rival
        return fit, rival

    def _result(self, tile_a, kp_a, tile_b, kp_b, fit: Fit, info: dict, t0: float) -> TileOffset:
        dirs = directions(fit.information)
        weak_sd = float(np.sqrt(np.linalg.eigvalsh(fit.cov)[-1]))
        info.update(fitness=fit.fitness, sigma=fit.sigma, points=fit.n_used, iterations=fit.iterations,
                    converged=fit.converged, weak_sd=weak_sd, information=dirs,
                    constraint=dirs["eigenvalues"][0] / max(fit.n_used, 1),
                    rotation_deg=np.degrees(np.linalg.norm(_rotvec(fit.rotation))).item())
        status = "ok"
        if not fit.fitness >= self.min_fitness:
            status = "no_overlap"
        elif not weak_sd <= self.max_sd:
            status = "degenerate"
        ties, ia = None, np.zeros(0, np.int64)
        if status == "ok" and len(kp_a) and len(kp_b):
            votes = pair_translations(kp_a.xyz, kp_b.xyz, fit.d, self.tie_radius)
            ia, ib = consensus(votes, fit.d, self.tie_radius)
            ties = make_ties(tile_a, tile_b, kp_a, kp_b, ia, ib, fit.d, self.tie_positions)
        info["timings"]["total"] = time.perf_counter() - t0
        if status != "ok":
            return failed(tile_a, tile_b, status, info, fit.d, fit.cov)
        log.debug("icp %s/%s: d=%s fitness=%.3f", tile_a.name, tile_b.name, fit.d, fit.fitness)
        return TileOffset(tile_a.run_id, tile_b.run_id, tile_a.name, tile_b.name, d=fit.d, cov=fit.cov,
                          inliers=len(ia), status=status, ties=ties, info=info)

    def _kiss(self, tile_a: PointTile, moving: np.ndarray, target: PlaneTarget, d0: np.ndarray) -> Fit:
        """kiss-icp point-to-point 6-DoF from d0, then a translation-only point-to-plane polish
        with kiss' rotation held: point-to-point slides along a tunnel (37 mm along-track left
        on a ray-cast tile where point-to-plane got 4 mm)."""
        from kiss_icp.mapping import VoxelHashMap
        from kiss_icp.registration import Registration
        from kiss_icp.voxelization import voxel_down_sample

        v = self.kiss_voxel
        origin = target.grid.origin  # kiss works in float64, but keep numbers small anyway
        vmap = VoxelHashMap(voxel_size=v, max_distance=1e9, max_points_per_voxel=20)
        vmap.add_points(voxel_down_sample(tile_a.xyz - origin, v * 0.5))
        src = voxel_down_sample(moving - origin, v * 1.5)
        guess = np.eye(4)
        guess[:3, 3] = d0
        T = Registration(max_num_iterations=500, convergence_criterion=1e-4).align_points_to_map(
            points=src, voxel_map=vmap, initial_guess=guess, max_correspondance_distance=3 * self.kernel,
            kernel=self.kernel / 3)
        R, t = T[:3, :3], T[:3, 3]
        center = moving.mean(axis=0)
        d = R @ (center - origin) + t + origin - center  # translation of tile b's centre
        rotated = (moving - center) @ R.T + center
        polish = point_to_plane(target, rotated, d, iterations=self.iterations, max_dist=self.max_dist,
                                kernel=self.kernel, fitness_radius=self.fitness_radius, max_sd=self.window)
        return replace(polish, rotation=R, center=center)


def _rotvec(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()


@hookimpl
def railtraj_register_stages(registry) -> None:
    registry.add("matcher", "icp", IcpMatcher, IcpConfig)
