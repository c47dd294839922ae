"""Quality figures a surveyor checks before and after correction.

* tie residuals: distance between the two runs' copies of each matched feature;
* cloud-to-cloud (C2C): distance from a sample of one run's points to the nearest point of the
  other run, in the overlap of a tile pair (the thesis' main QC measure).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from railtraj.data import Ties
from railtraj.georef import Regeoreferencer


def distance_stats(d: np.ndarray) -> dict[str, float | int]:
    """Count, mean, median, RMS, 95th percentile and max of distances (NaN when empty)."""
    d = np.asarray(d, dtype=float)
    d = d[np.isfinite(d)]
    if len(d) == 0:
        return {"n": 0, "mean": float("nan"), "median": float("nan"), "rms": float("nan"),
                "p95": float("nan"), "max": float("nan")}
    return {"n": int(len(d)), "mean": float(d.mean()), "median": float(np.median(d)),
            "rms": float(np.sqrt(np.mean(d**2))), "p95": float(np.percentile(d, 95)), "max": float(d.max())}


def c2c_distances(query: np.ndarray, reference: np.ndarray, max_dist: float = 1.0) -> np.ndarray:
    """Nearest-neighbour distance from every ``query`` point to ``reference`` (inf beyond max_dist)."""
    if len(query) == 0 or len(reference) == 0:
        return np.zeros(0)
    d, _ = cKDTree(reference).query(query, distance_upper_bound=max_dist, workers=-1)
    return d[np.isfinite(d)]


def tie_residuals(ties: Ties, move: Regeoreferencer | None = None) -> np.ndarray:
    """3-D distances between the two copies of every tie; after correction with ``move``."""
    xa, xb = ties.xyz_a, ties.xyz_b
    if move is not None:
        xa = move(ties.run_a, xa, ties.time_a)
        xb = move(ties.run_b, xb, ties.time_b)
    return np.linalg.norm(xa - xb, axis=1)


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


def pair_clouds(result, move: Regeoreferencer | None = None) -> list[PairClouds]:
    """Samples and C2C distances of every tile pair that has points in both runs: each pair's
    samples moved with the corrected trajectories (as re-georeferencing the tiles would), and
    run b's distances to the nearest point of run a's, before and after."""
    out = []
    move = move or Regeoreferencer(result.trajectories, result.corrected)  # one interpolator per run
    for k, pr in enumerate(result.pairs):
        a, b = pr.sample_a, pr.sample_b
        if len(a) == 0 or len(b) == 0:
            continue
        moved = [move(s.run_id, s.xyz, s.gps_time) for s in (a, b)]
        out.append(PairClouds(k, a.xyz, b.xyz, moved[0], moved[1], c2c_distances(b.xyz, a.xyz),
                              c2c_distances(moved[1], moved[0])))
    return out
