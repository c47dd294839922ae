"""The tile pairs' point samples before and after correction: C2C distances and cross-sections.

Every :class:`~railtraj.pipeline.PairResult` carries a sample of each run's points in the pair's
overlap. The report moves them with the corrected trajectories (as re-georeferencing the tiles
would) and measures cloud-to-cloud distances (run b's sample to the nearest point of run a's),
the same measure as ``metrics.json`` ``qc``, keeping the distances for histograms and maps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from railtraj.georef import regeoreference_points
from railtraj.qc import c2c_distances


@dataclass
class PairClouds:
    """One tile pair's samples (survey CRS) before and after, and the C2C distances b -> a."""

    index: int
    a_before: np.ndarray
    b_before: np.ndarray
    a_after: np.ndarray
    b_after: np.ndarray
    c2c_before: np.ndarray
    c2c_after: np.ndarray

    @property
    def median_before(self) -> float:
        return float(np.median(self.c2c_before)) if len(self.c2c_before) else float("nan")

    @property
    def median_after(self) -> float:
        return float(np.median(self.c2c_after)) if len(self.c2c_after) else float("nan")


def pair_clouds(result) -> list[PairClouds]:
    """Samples and C2C distances of every tile pair that has points in both runs."""
    out = []
    for k, pr in enumerate(result.pairs):
        a, b = pr.sample_a, pr.sample_b
        if len(a) == 0 or len(b) == 0:
            continue
        moved = [regeoreference_points(s.xyz, s.gps_time, result.trajectories[s.run_id],
                                       result.corrected[s.run_id]) for s in (a, b)]
        out.append(PairClouds(k, a.xyz, b.xyz, moved[0], moved[1], c2c_distances(b.xyz, a.xyz),
                              c2c_distances(moved[1], moved[0])))
    return out


def cross_section(points: np.ndarray, centre: np.ndarray, direction: np.ndarray,
                  half_width: float) -> np.ndarray:
    """Points within ``half_width`` of the vertical plane across the track through ``centre``,
    as (across-track offset to the right, height) pairs."""
    d = np.asarray(direction, float)[:2]
    right = np.array([d[1], -d[0]])
    rel = points[:, :2] - np.asarray(centre, float)[:2]
    keep = np.abs(rel @ d) <= half_width
    return np.column_stack([rel[keep] @ right, points[keep, 2]])


def slab_width(points: np.ndarray, centre: np.ndarray, direction: np.ndarray,
               want: int = 800, widths=(0.1, 0.2, 0.4, 0.8, 1.6)) -> float:
    """The thinnest slab half-width from ``widths`` holding ``want`` points (else the widest)."""
    rel = points[:, :2] - np.asarray(centre, float)[:2]
    along = np.abs(rel @ np.asarray(direction, float)[:2])
    for w in widths:
        if np.count_nonzero(along <= w) >= want:
            return w
    return widths[-1]


def pick_pairs(clouds: list[PairClouds]) -> list[tuple[str, PairClouds]]:
    """The worst pair (largest C2C median after correction) and a typical one (the median)."""
    usable = [c for c in clouds if np.isfinite(c.median_after)]
    if not usable:
        return []
    ranked = sorted(usable, key=lambda c: c.median_after)
    worst, typical = ranked[-1], ranked[len(ranked) // 2]
    picks = [("worst", worst)]
    if typical is not worst:
        picks.append(("typical", typical))
    return picks
