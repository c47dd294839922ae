"""The ``median`` optimizer: the thesis' baseline, a running median of tie midpoints.

The MSc thesis this project replicates notes that its g2o step "is equivalent to moving both
runs to the median point between matched features". This optimizer does just that, so the
other optimizers can be compared with what the thesis did:

1. every tie moves both runs to the midpoint of its two copies, weighted by the runs' reported
   sd (``weighting="sd"``; ``"equal"``, or a run without sd, gives the plain midpoint): one
   correction sample per run, at the time that run saw the feature;
2. per run, the samples sorted by time are smoothed by a running median over ``window``
   samples per axis and interpolated linearly to every epoch;
3. beyond the first and last sample the correction tapers linearly to zero over ``taper_s``
   seconds: ties stop where the tunnel ends and GNSS is good again there, so holding the last
   correction constant would shift the open-air part of the run, which needs none;
4. the posterior sd is, as in the thesis, the scatter of consecutive raw corrections (rolling
   RMS of their differences / sqrt(2) over ``window``); outside the tied span the input sd.

Limits, which is why it is only a baseline: ties are not weighted (the ``weight`` column and
the number of ties per tile pair are ignored); the running median removes isolated wrong
matches but also rounds off sharp changes of drift; weak (degenerate/ambiguous) tile offsets
and control points are not used; and the sd says how repeatable the ties are, not how right
the run is.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from railtraj.data import ControlObservations, Ties, TileOffset, Trajectory
from railtraj.errors import ConfigError
from railtraj.hookspecs import hookimpl

log = logging.getLogger(__name__)


@dataclass
class MedianConfig:
    name: str = "median"
    weighting: str = "sd"      # sd: midpoint weighted by 1/sd^2 of the runs; equal: plain midpoint
    window: int = 15           # running-median length, in correction samples (odd)
    taper_s: float = 10.0      # the correction falls linearly to zero this long beyond the ties
    min_sd_m: float = 0.005    # floor on the reported and the posterior sd
    default_sd_m: float = 1.0  # sd outside the tied span where the trajectory reports none


class MedianOptimizer:
    """Moves the runs to the (sd-weighted) midpoints of their ties, smoothed by a running median."""

    def __init__(self, **options) -> None:
        self.config = cfg = MedianConfig(**options)
        if cfg.weighting not in ("sd", "equal"):
            raise ConfigError(f"optimizer=median weighting={cfg.weighting!r}: choose sd or equal")
        if cfg.window < 1 or cfg.window % 2 == 0:
            raise ConfigError(f"optimizer=median window={cfg.window}: give an odd number of samples >= 1")
        if cfg.taper_s < 0 or cfg.min_sd_m <= 0:
            raise ConfigError("optimizer=median needs taper_s >= 0 and min_sd_m > 0")
        self.diagnostics: dict = {}

    def optimize(self, trajectories: dict[str, Trajectory], ties: Sequence[Ties],
                 offsets: Sequence[TileOffset],
                 control: ControlObservations | None = None) -> dict[str, Trajectory]:
        notes: list[str] = []
        unused = [o.status if not o.ok else "ok without ties" for o in offsets
                  if not o.ok or o.ties is None or not len(o.ties)]
        if unused:
            notes.append(f"optimizer median: {len(unused)} tile pairs with status "
                         f"{', '.join(sorted(set(unused)))} not used "
                         "(this baseline uses ties only)")
        if control is not None and len(control):
            notes.append(f"optimizer median: {len(control)} control observations not used "
                         "(use optimizer=spline)")
        samples: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {r: [] for r in trajectories}
        for t in ties:
            if not len(t):
                continue
            if t.run_a not in trajectories or t.run_b not in trajectories:
                notes.append(f"optimizer median: {len(t)} ties between {t.run_a!r} and {t.run_b!r} "
                             "skipped (no trajectory for that run)")
                continue
            m = self._midpoints(t, trajectories[t.run_a], trajectories[t.run_b])
            samples[t.run_a].append((t.time_a, m - t.xyz_a))
            samples[t.run_b].append((t.time_b, m - t.xyz_b))
        counts = {r: int(sum(len(s[0]) for s in samples[r])) for r in sorted(trajectories)}
        if not any(counts.values()):
            notes.append("optimizer median: no ties; trajectories left unchanged")
        for note in notes:
            log.warning(note)
        self.diagnostics = {"optimizer": "median", "samples": counts, "notes": notes}
        out = dict(trajectories)
        for r, parts in samples.items():
            if parts:
                out[r] = self._correct(trajectories[r], np.concatenate([p[0] for p in parts]),
                                       np.concatenate([p[1] for p in parts]))
        return out

    def _midpoints(self, t: Ties, a: Trajectory, b: Trajectory) -> np.ndarray:
        """The sd-weighted (or plain) midpoint of each tie's two copies, (n, 3)."""
        sd_a, sd_b = a.sd_at(t.time_a), b.sd_at(t.time_b)
        if self.config.weighting == "equal" or sd_a is None or sd_b is None:
            return 0.5 * (t.xyz_a + t.xyz_b)
        w_a = 1.0 / np.maximum(sd_a.mean(axis=1), self.config.min_sd_m) ** 2
        w_b = 1.0 / np.maximum(sd_b.mean(axis=1), self.config.min_sd_m) ** 2
        return (t.xyz_a * w_a[:, None] + t.xyz_b * w_b[:, None]) / (w_a + w_b)[:, None]

    def _correct(self, traj: Trajectory, times: np.ndarray, corr: np.ndarray) -> Trajectory:
        """Apply the running median of one run's correction samples, tapered beyond them."""
        from scipy.ndimage import median_filter, uniform_filter1d  # ~0.1 s: not at registration

        cfg, order = self.config, np.argsort(times, kind="stable")
        ts, raw = times[order], corr[order]
        smooth = median_filter(raw, size=(cfg.window, 1), mode="nearest")
        t = traj.time
        dxyz = np.column_stack([np.interp(t, ts, smooth[:, k]) for k in range(3)])
        beyond = np.maximum.reduce([ts[0] - t, t - ts[-1], np.zeros_like(t)])
        taper = np.clip(1.0 - beyond / cfg.taper_s, 0.0, 1.0) if cfg.taper_s > 0 else (beyond == 0) * 1.0
        dxyz *= taper[:, None]
        sd = traj.sd.copy() if traj.sd is not None else np.full((len(t), 3), cfg.default_sd_m)
        if len(ts) > 1:
            # scatter of consecutive raw corrections: one sample's sd is RMS(diff) / sqrt(2)
            rms = np.sqrt(uniform_filter1d(np.diff(raw, axis=0) ** 2 / 2.0, cfg.window, axis=0, mode="nearest"))
            mid = 0.5 * (ts[1:] + ts[:-1])
            inside = (t >= ts[0]) & (t <= ts[-1])
            sd[inside] = np.column_stack([np.interp(t[inside], mid, rms[:, k]) for k in range(3)])
        return traj.with_positions(traj.xyz + dxyz, np.maximum(sd, cfg.min_sd_m))


@hookimpl
def railtraj_register_stages(registry) -> None:
    registry.add("optimizer", "median", MedianOptimizer, MedianConfig)
