"""The correction model: one continuous position correction c_r(t) per run, linear between knots.

A run's corrected position is ``x_r(t) + c_r(t)``; attitude is kept. ``c_r`` is a 3-vector at
knots spaced evenly along the run, linear in between, so an observation at any time attaches to
its two neighbouring knots with interpolation weights (never snapped to the nearest knot: at
18 mm/m of drift that alone puts a tie 45-90 mm off when knots are 5-10 m apart).

Knots are spaced in metres travelled (``unit="m"``, the default) or in seconds (``unit="s"``):

* metres, because observations (ties, tile pairs, control) are spread along the track, not in
  time: a slow run and a fast one get the same number of knots per metre, so each run's prior
  weighs the same at a given place and the common (absolute) correction is the sd-weighted
  average of the runs, the best that relative information allows;
* seconds for surveys where the train stands for long (the correction still changes with time
  while the distance stands still); the smoothness is scaled by time in both cases.

Unknowns are numbered ``3 * knot + axis``, knots of all runs concatenated in run-name order,
then the knots of the runs' GNSS biases (:mod:`railtraj.adjust.gnss_bias`), one per correction
knot of each run ``biased``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from railtraj.data import Trajectory
from railtraj.errors import ConfigError

UNITS = ("m", "s")


@dataclass(frozen=True)
class RunKnots:
    """Knots of one run: parameter values (metres travelled or seconds) and the knot times."""

    first: int  # global index of the run's first knot
    spacing: float
    epoch_param: np.ndarray  # parameter at each trajectory epoch (non-decreasing)
    epoch_time: np.ndarray
    knot_time: np.ndarray  # gps_time at each knot
    knot_distance: np.ndarray  # metres travelled at each knot

    @property
    def count(self) -> int:
        return len(self.knot_time)

    def param_at(self, times: np.ndarray) -> np.ndarray:
        return np.interp(times, self.epoch_time, self.epoch_param)


class CorrectionModel:
    """Knot layout of every run and the interpolation weights of observations on it."""

    def __init__(self, trajectories: dict[str, Trajectory], spacing: float = 5.0, unit: str = "m",
                 biased: tuple[str, ...] = ()) -> None:
        if unit not in UNITS:
            raise ConfigError(f"optimizer knot_unit={unit!r} is not valid; use 'm' (metres travelled) or 's'")
        if not spacing > 0:
            raise ConfigError(f"optimizer knot_spacing={spacing} must be positive (metres or seconds)")
        self.unit, self.spacing = unit, float(spacing)
        self.runs: dict[str, RunKnots] = {}
        first = 0
        for run_id in sorted(trajectories):
            traj = trajectories[run_id]
            distance = traj.travelled()
            param = distance if unit == "m" else traj.time - traj.time[0]
            n = max(2, int(np.ceil(param[-1] / self.spacing)) + 1)
            knot_param = self.spacing * np.arange(n)
            knot_time = _invert(knot_param, param, traj.time)
            knot_distance = np.interp(knot_time, traj.time, distance)
            self.runs[run_id] = RunKnots(first, self.spacing, param, traj.time, knot_time, knot_distance)
            first += n
        self.n_knots = first
        self.bias_first: dict[str, int] = {}  # global index of a biased run's first bias knot
        for run_id in sorted(biased):
            self.bias_first[run_id] = first
            first += self.runs[run_id].count
        self.n_bias_knots = first - self.n_knots

    @property
    def n_unknowns(self) -> int:
        return 3 * (self.n_knots + self.n_bias_knots)

    def weights(self, run_id: str, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Global knot indices (n, 2) and linear interpolation weights (n, 2) at ``times``."""
        rk = self.runs[run_id]
        u = rk.param_at(np.asarray(times, float)) / rk.spacing
        k = np.clip(np.floor(u).astype(np.int64), 0, rk.count - 2)
        f = np.clip(u - k, 0.0, 1.0)
        return rk.first + np.column_stack([k, k + 1]), np.column_stack([1.0 - f, f])

    def knot_metres(self, run_id: str, floor: float = 0.5) -> np.ndarray:
        """Distance travelled between consecutive knots of a run (n_knots - 1,), at least ``floor``."""
        return np.maximum(np.diff(self.runs[run_id].knot_distance), floor)

    def run_of_knot(self) -> np.ndarray:
        """Run index (in sorted order) of every knot."""
        return np.repeat(np.arange(len(self.runs)), [rk.count for rk in self.runs.values()])


def _invert(knot_param: np.ndarray, param: np.ndarray, time: np.ndarray) -> np.ndarray:
    """gps_time at which the run reached each knot's parameter (first time, when it stood still)."""
    keep = np.concatenate([[True], np.diff(param) > 0])
    return np.interp(knot_param, param[keep], time[keep])
