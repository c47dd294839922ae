"""The ``gtsam`` optimizer: smooth position corrections per run, fitted to the ties (GTSAM).

The thesis' g2o graph with fixed attitude, made N-run, weighted and robust. Each run's
correction is a 3-D vector at knots every ``knot_interval_s`` seconds, linear in between:

* **prior** per knot: correction 0 with the trajectory's reported sd (small where GNSS was good,
  large deep in the tunnel), so corrections go where the GNSS/INS smoother was unsure;
* **smoothness** between consecutive knots: a random walk of ``smoothness_m_per_sqrt_s``;
* **ties**: the two runs' copies of a feature coincide after correction,
  ``c_b(t_b) - c_a(t_a) = x_a - x_b``, with ``tie_sigma_m / sqrt(weight)`` and a Huber kernel
  so wrong matches cannot pull the solution;
* **weak tile offsets** (``use_weak_offsets``): a tile pair that is ``degenerate`` or
  ``ambiguous`` along the track still fixes across-track and height; its offset enters with its
  full covariance (metres of sd along the track), observed at the overlap's median times.

The problem is linear in the corrections; Levenberg-Marquardt converges in one or two steps and
``gtsam.Marginals`` gives the posterior sd written to the corrected trajectories.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from railtraj.adjust.offsets import WEAK_STATUSES
from railtraj.data import Ties, TileOffset, Trajectory
from railtraj.hookspecs import hookimpl

log = logging.getLogger(__name__)
RUN_STRIDE = 10_000_000  # key = run index * RUN_STRIDE + knot index


@dataclass
class GtsamConfig:
    name: str = "gtsam"
    knot_interval_s: float = 0.5          # spacing of correction knots along each run
    smoothness_m_per_sqrt_s: float = 0.05  # random-walk sigma of the correction
    tie_sigma_m: float = 0.02             # 1-sigma of one tie (keypoint localisation)
    huber_k: float = 1.345                # robust kernel threshold, in sigmas
    default_sd_m: float = 1.0             # prior sigma where the trajectory reports no sd
    min_sd_m: float = 0.005               # floor on the reported sd
    use_weak_offsets: bool = True         # use degenerate/ambiguous pairs in their constrained directions


class GtsamOptimizer:
    """Fits smooth per-run position corrections to the ties with a GTSAM factor graph."""

    def __init__(self, knot_interval_s: float = 0.5, smoothness_m_per_sqrt_s: float = 0.05,
                 tie_sigma_m: float = 0.02, huber_k: float = 1.345, default_sd_m: float = 1.0,
                 min_sd_m: float = 0.005, use_weak_offsets: bool = True) -> None:
        self.dt, self.rw = knot_interval_s, smoothness_m_per_sqrt_s
        self.tie_sigma, self.huber_k = tie_sigma_m, huber_k
        self.default_sd, self.min_sd = default_sd_m, min_sd_m
        self.use_weak_offsets = use_weak_offsets

    def _knots(self, traj: Trajectory) -> np.ndarray:
        n = int(np.ceil((traj.time[-1] - traj.time[0]) / self.dt)) + 1
        return traj.time[0] + self.dt * np.arange(n)

    def optimize(self, trajectories: dict[str, Trajectory], ties: Sequence[Ties],
                 offsets: Sequence[TileOffset]) -> dict[str, Trajectory]:
        weak = [o for o in offsets if self.use_weak_offsets and _usable_weak(o, trajectories)]
        if not any(len(t) for t in ties) and not weak:
            log.warning("gtsam optimizer: no ties and no usable tile offsets, trajectories left unchanged")
            return dict(trajectories)
        import gtsam  # here, not at import: loading it takes ~0.3 s of every `railtraj --help`

        runs = sorted(trajectories)
        index = {r: i for i, r in enumerate(runs)}
        knots = {r: self._knots(trajectories[r]) for r in runs}
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        rw = gtsam.noiseModel.Isotropic.Sigma(3, self.rw * np.sqrt(self.dt))
        for r in runs:
            traj, base = trajectories[r], index[r] * RUN_STRIDE
            sd = traj.sd_at(knots[r])
            sd = np.full((len(knots[r]), 3), self.default_sd) if sd is None else np.maximum(sd, self.min_sd)
            for k in range(len(knots[r])):
                values.insert(base + k, np.zeros(3))
                graph.add(gtsam.PriorFactorPoint3(base + k, np.zeros(3), gtsam.noiseModel.Diagonal.Sigmas(sd[k])))
                if k:
                    graph.add(gtsam.BetweenFactorPoint3(base + k - 1, base + k, np.zeros(3), rw))
        huber = gtsam.noiseModel.mEstimator.Huber.Create(self.huber_k)
        n_ties = 0
        for t in ties:
            ka = self._key(t.time_a, trajectories[t.run_a], index[t.run_a], len(knots[t.run_a]))
            kb = self._key(t.time_b, trajectories[t.run_b], index[t.run_b], len(knots[t.run_b]))
            sig = self.tie_sigma / np.sqrt(np.clip(t.weight, 1e-6, None))
            for i in range(len(t)):
                if ka[i] == kb[i]:
                    continue
                noise = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Isotropic.Sigma(3, float(sig[i])))
                graph.add(gtsam.BetweenFactorPoint3(int(ka[i]), int(kb[i]), t.xyz_a[i] - t.xyz_b[i], noise))
                n_ties += 1
        for o in weak:
            ka = self._key(np.array([o.info["time_a"]]), trajectories[o.run_a], index[o.run_a], len(knots[o.run_a]))
            kb = self._key(np.array([o.info["time_b"]]), trajectories[o.run_b], index[o.run_b], len(knots[o.run_b]))
            cov = o.cov + self.tie_sigma**2 * np.eye(3)
            noise = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Gaussian.Covariance(cov))
            graph.add(gtsam.BetweenFactorPoint3(int(ka[0]), int(kb[0]), np.asarray(o.d, float), noise))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(50)
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        marginals = gtsam.Marginals(graph, result)
        log.info("gtsam optimizer: %d runs, %d knots, %d tie factors, %d weak tile offsets", len(runs),
                 values.size(), n_ties, len(weak))
        out = {}
        for r in runs:
            traj, base = trajectories[r], index[r] * RUN_STRIDE
            corr = np.array([result.atPoint3(base + k) for k in range(len(knots[r]))])
            var = np.array([np.diag(marginals.marginalCovariance(base + k)) for k in range(len(knots[r]))])
            dxyz = np.column_stack([np.interp(traj.time, knots[r], corr[:, j]) for j in range(3)])
            sd = np.sqrt(np.column_stack([np.interp(traj.time, knots[r], var[:, j]) for j in range(3)]))
            out[r] = traj.with_positions(traj.xyz + dxyz, sd)
        return out

    def _key(self, times: np.ndarray, traj: Trajectory, run_index: int, n_knots: int) -> np.ndarray:
        k = np.clip(np.rint((times - traj.time[0]) / self.dt).astype(np.int64), 0, n_knots - 1)
        return run_index * RUN_STRIDE + k


def _usable_weak(o: TileOffset, trajectories: dict[str, Trajectory]) -> bool:
    """A degenerate/ambiguous pair with a finite offset, covariance and observation times."""
    if o.status not in WEAK_STATUSES or o.run_a not in trajectories or o.run_b not in trajectories:
        return False
    times = [o.info.get("time_a", np.nan), o.info.get("time_b", np.nan)]
    return bool(np.isfinite(o.d).all() and np.isfinite(o.cov).all() and np.isfinite(times).all())


@hookimpl
def railtraj_register_stages(registry) -> None:
    registry.add("optimizer", "gtsam", GtsamOptimizer, GtsamConfig)
