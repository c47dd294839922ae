"""The ``pair_voting`` matcher: the thesis' exhaustive-pair outlier removal, fast and careful.

Every keypoint pair (a_i, b_j) proposes the translation a_i - b_j; the translation with the most
agreeing pairs wins (thesis Algorithm 2 without descriptors, the variant the thesis ended up
using). Here the votes are counted in translation space inside the search window (700 x 700
keypoints in ~0.1 s instead of over an hour), all agreeing pairs are kept (not a fixed top
10), the few best distinct peaks are checked on the dense clouds to pick among rib aliases,
and the winner is refined point-to-plane by the ``icp`` matcher. ``info`` holds the timings,
``peak_ratio`` (runner-up / best votes), ``vote_peaks`` ([dx, dy, dz, votes, fitness] rows),
``vote_slices`` (histograms for :func:`railtraj.report.votes.plot_votes`) and the information
eigen-decomposition. Statuses: few_keypoints, no_overlap, no_consensus, ambiguous, degenerate, ok.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, replace

import numpy as np

from railtraj.builtins.icp import IcpMatcher
from railtraj.data import Keypoints, PointTile, TileOffset
from railtraj.errors import ConfigError
from railtraj.hookspecs import hookimpl
from railtraj.matching.consensus import boxes_overlap, failed
from railtraj.matching.resolve import REVERSE_GAP_RATIO, VoteSettings, resolve
from railtraj.matching.spacing import point_spacing, radius_scale
from railtraj.matching.voting import pair_translations


@dataclass
class VotingOptions:
    """Options both voting matchers (``pair_voting``, ``mutual_nn``) take."""

    max_misalignment: float = 3.0  # m; search window around the initial offset (or zero)
    inlier_radius: float = 0.1  # m; a keypoint pair agrees with a translation this closely
    min_keypoints: int = 10  # per tile; fewer: few_keypoints
    min_inliers: int = 5  # agreeing pairs the best translation needs to be ok
    min_check_votes: int = 2  # fewer than min_inliers but this many: checked densely, at best ambiguous
    n_peaks: int = 5  # distinct vote peaks checked on the dense clouds
    check_points: int = 20_000  # raw points of tile b for that check
    min_fitness: float = 0.5  # share of points on run a's surface at the best peak (Fit.overlap); below: no_overlap
    search_m: float = 0.5  # m; where no vote peak fits, the dense clouds are searched this far about the initial offset (0: off)
    ambiguity_ratio: float = 0.8  # misfit of the best / of a distinct rival peak; above: ambiguous
    max_sd: float = 0.01  # m; sd of the offset in any direction above this: degenerate
    refine: bool = True  # point-to-plane refinement (windows along the track, or one rigid fit)
    target_voxel: float = 0.05  # m; reference grid for the check and the refinement
    tie_positions: str = "offset"  # offset | keypoints
    window_length: float = 5.0  # m; refine per window along the track, fit a curve (0: one rigid ICP)
    min_windows: int = 4  # windows an ok offset needs (shorter overlaps: degenerate)
    intensity: bool = True  # place windows without edges by intensity marks (stains, paint) where the tiles have them
    objects: bool = True  # ... and by short objects on a plain lining (boxes, cabinets, doors: 0.2-2 m along the track)
    # run b's scan profiles this many times further apart than run a's (a faster train): the windows fit
    # run a's points onto run b's, the denser onto the sparser (0: never; docs/method.md, "Session 61")
    reverse_gap_ratio: float = REVERSE_GAP_RATIO


@dataclass
class PairVotingConfig(VotingOptions):
    name: str = "pair_voting"


def vote_setup(matcher: str, o: VotingOptions) -> tuple[VoteSettings, IcpMatcher | None]:
    """Check the options shared by the voting matchers; build their settings and refiner."""
    if o.max_misalignment <= 0 or o.inlier_radius <= 0:
        raise ConfigError(f"matcher={matcher} needs max_misalignment > 0 and inlier_radius > 0")
    if o.window_length < 0:
        raise ConfigError(f"matcher={matcher} window_length={o.window_length}: give metres > 0, or 0 for one rigid fit")
    if o.min_check_votes < 1:
        raise ConfigError(f"matcher={matcher} min_check_votes={o.min_check_votes}: give 1 or more votes "
                          f"(min_check_votes >= min_inliers={o.min_inliers} checks no pair below min_inliers)")
    if not 0 <= o.search_m <= o.max_misalignment:
        raise ConfigError(f"matcher={matcher} search_m={o.search_m}: give metres from 0 (off) to "
                          f"max_misalignment={o.max_misalignment}")
    if not (o.reverse_gap_ratio == 0 or o.reverse_gap_ratio >= 1):
        raise ConfigError(f"matcher={matcher} reverse_gap_ratio={o.reverse_gap_ratio}: give 1 or more (how many times "
                          "further apart run b's scan profiles lie than run a's), or 0 to never fit run a onto run b")
    if o.tie_positions not in ("offset", "keypoints"):
        raise ConfigError(f"tie_positions={o.tie_positions!r}: choose offset or keypoints")
    settings = VoteSettings(inlier_radius=o.inlier_radius, n_peaks=o.n_peaks, min_inliers=o.min_inliers,
                            min_check_votes=o.min_check_votes,
                            check_points=o.check_points, min_fitness=o.min_fitness, search_m=o.search_m,
                            ambiguity_ratio=o.ambiguity_ratio, max_sd=o.max_sd, target_voxel=o.target_voxel,
                            tie_positions=o.tie_positions, window_length=o.window_length,
                            min_windows=o.min_windows, intensity=o.intensity,
                            objects=o.objects, reverse_gap_ratio=o.reverse_gap_ratio)
    icp = IcpMatcher(max_misalignment=o.max_misalignment, target_voxel=o.target_voxel, min_fitness=o.min_fitness,
                     max_sd=o.max_sd, tie_radius=o.inlier_radius, tie_positions=o.tie_positions,
                     alias_check=False) if o.refine else None
    return settings, icp


class VotingMatcher:
    """What the voting matchers share: their options, the opening checks and the ending
    (:func:`railtraj.matching.resolve.resolve`). Subclasses only say which pairs vote."""

    kind = "voting"

    def __init__(self, **options) -> None:
        o = VotingOptions(**options)
        self.window, self.min_keypoints = o.max_misalignment, o.min_keypoints
        self.settings, self.icp = vote_setup(self.kind, o)

    def widened(self, window: float) -> VotingMatcher:
        """This matcher searching within ``window`` metres (``max_misalignment``): the pipeline
        matches a run pair's tiles again so where the along-track chains put the runs further
        apart than it searched (:func:`railtraj.pipeline.run_pipeline`)."""
        out = copy.copy(self)
        out.window = window
        if self.icp is not None:
            out.icp = copy.copy(self.icp)
            out.icp.window = window
        return out

    def open(self, tile_a: PointTile, kp_a: Keypoints, tile_b: PointTile, kp_b: Keypoints,
             initial: TileOffset | None) -> tuple[np.ndarray, dict, TileOffset | None]:
        """Search centre (the initial estimate, or zero), the diagnostics dict every match starts
        with, and the refusal when there are too few keypoints or the tiles cannot overlap."""
        center = np.zeros(3)
        if initial is not None and np.isfinite(initial.d).all():
            center = np.asarray(initial.d, float)
        info = {"timings": {}, "keypoints": [len(kp_a), len(kp_b)], "window": self.window,
                "center": center.tolist()}
        refusal = None
        if min(len(kp_a), len(kp_b)) < self.min_keypoints:
            refusal = failed(tile_a, tile_b, "few_keypoints", info)
        elif not boxes_overlap(tile_a, tile_b, center, self.window):
            refusal = failed(tile_a, tile_b, "no_overlap", info)
        return center, info, refusal

    def finish(self, tile_a: PointTile, kp_a: Keypoints, tile_b: PointTile, kp_b: Keypoints, votes,
               info: dict, t0: float) -> TileOffset:
        """Resolve the votes (dense check, refinement) and record the matcher's total time."""
        refiner = self.icp.match if self.icp is not None else None
        scale, info["profile_spacing"] = radius_scale(tile_a, tile_b)
        info["point_spacing"] = point_spacing(tile_a, tile_b)
        s = self.settings
        if scale > 1.0:  # sparser scan profiles than the defaults were set for: radii follow them
            s = replace(s, fitness_radius=s.fitness_radius * scale, target_voxel=s.target_voxel * scale,
                        inlier_radius=s.inlier_radius * scale)
            info["radius_scale"] = scale
        # a sparse scan samples a wall in rows as far apart as a profile's points: run b's rows lie
        # between run a's, half that from the nearer, and fit where run a's planes are
        # (PlaneTarget.fits; no further than the fitness radius on dense scans: nothing changes)
        s = replace(s, surface_reach=float(np.nan_to_num(np.hypot(point_spacing(tile_a) / 2, s.target_voxel / 2))))
        out = resolve(tile_a, kp_a, tile_b, kp_b, votes, s, refiner, info)
        out.info["timings"]["total"] = time.perf_counter() - t0
        return out


class PairVotingMatcher(VotingMatcher):
    """Translation voting over all keypoint pairs within the search window (see module docstring)."""

    kind = "pair_voting"

    def match(self, tile_a: PointTile, kp_a: Keypoints, tile_b: PointTile, kp_b: Keypoints,
              initial: TileOffset | None = None) -> TileOffset:
        t0 = time.perf_counter()
        center, info, refusal = self.open(tile_a, kp_a, tile_b, kp_b, initial)
        if refusal is not None:
            return refusal
        votes = pair_translations(kp_a.xyz, kp_b.xyz, center, self.window)
        info["timings"]["vote"] = time.perf_counter() - t0
        return self.finish(tile_a, kp_a, tile_b, kp_b, votes, info, t0)


@hookimpl
def railtraj_register_stages(registry) -> None:
    registry.add("matcher", "pair_voting", PairVotingMatcher, PairVotingConfig)
