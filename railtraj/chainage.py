"""Chainage: one along-track coordinate for runs that may be driven either way and start anywhere.

Time since a run's start does not line runs up. Distance travelled along a reference run's input
trajectory does, carried to other positions by the nearest reference epoch in plan; positions
beside the ends of the reference run get its end chainage. The report places everything by it
(tile pairs, corrections, verdicts), and the adjustment re-centres the runs along it.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from railtraj.data import Trajectory


class Chainage:
    """Distance along ``reference`` (metres from its first epoch) for any plan position."""

    def __init__(self, reference: Trajectory) -> None:
        self.run_id = reference.run_id
        self.xy = np.asarray(reference.xyz[:, :2], float)
        steps = np.linalg.norm(np.diff(self.xy, axis=0), axis=1)
        self.distance = np.concatenate([[0.0], np.cumsum(steps)])
        self._tree = cKDTree(self.xy)

    @property
    def length(self) -> float:
        return float(self.distance[-1]) if len(self.distance) else 0.0

    def at(self, xy: np.ndarray, max_distance: float = np.inf) -> np.ndarray:
        """Chainage of each plan position ``xy`` (n, 2); NaN where the reference run passes no
        nearer than ``max_distance``."""
        xy = np.atleast_2d(np.asarray(xy, float))[:, :2]
        if len(xy) == 0:
            return np.zeros(0)
        dist, nearest = self._tree.query(xy)
        return np.where(dist <= max_distance, self.distance[nearest], np.nan)

    def of_trajectory(self, traj: Trajectory, max_distance: float = np.inf) -> np.ndarray:
        """Chainage of every epoch of ``traj`` (NaN beyond ``max_distance`` of the reference)."""
        return self.at(traj.xyz[:, :2], max_distance)

    def direction(self, s: float) -> np.ndarray:
        """Unit plan direction of travel of the reference run at chainage ``s``."""
        k = int(np.clip(np.searchsorted(self.distance, s), 1, len(self.distance) - 1))
        lo = int(np.searchsorted(self.distance, self.distance[k] - 2.0))
        hi = int(np.searchsorted(self.distance, self.distance[k] + 2.0))
        hi = min(len(self.distance) - 1, hi)
        lo, hi = min(lo, k - 1), max(hi, k)
        v = self.xy[hi] - self.xy[lo]
        n = np.linalg.norm(v)
        return v / n if n > 0 else np.array([1.0, 0.0])


__all__ = ["Chainage"]
