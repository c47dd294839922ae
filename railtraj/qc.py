"""Quality figures a surveyor checks before and after correction.

* tie residuals: distance between the two runs' copies of each matched feature;
* cloud-to-cloud (C2C): distance from a sample of one run's points to the nearest point of the
  other run, in the overlap of a tile pair (the thesis' main QC measure).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from railtraj.data import Ties, Trajectory
from railtraj.georef import regeoreference_points


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


def tie_residuals(ties: Ties, trajectories: dict[str, Trajectory],
                  corrected: dict[str, Trajectory] | None = None) -> np.ndarray:
    """3-D distances between the two copies of every tie, optionally after correction."""
    xa, xb = ties.xyz_a, ties.xyz_b
    if corrected is not None:
        xa = regeoreference_points(xa, ties.time_a, trajectories[ties.run_a], corrected[ties.run_a])
        xb = regeoreference_points(xb, ties.time_b, trajectories[ties.run_b], corrected[ties.run_b])
    return np.linalg.norm(xa - xb, axis=1)
