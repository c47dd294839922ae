"""Runs: one pass of the train along a track, and its TRUE trajectory.

A run drives one track in one direction with a slowly varying speed. Its body origin (the IMU)
rides ``imu_height`` above the rails; heading follows the track tangent (reversed for runs
towards decreasing chainage), pitch follows the grade, and a small roll sways with distance.
Epochs are regular at ``rate_hz``; the scanner works inside the span, a little away from both
ends, so every point's time is covered by the trajectory.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from railtraj.data import Trajectory
from railtraj.geo import attitude_from_direction
from railtraj.sim.geometry import Scene


@dataclass(frozen=True)
class RunSpec:
    """One pass: which track (index into the scene's tracks), which way, how fast, and when."""

    run_id: str
    track: int = 0
    direction: int = 1
    speed: float = 10.0
    speed_variation: float = 0.15
    start_time: float = 300000.0
    roll_deg: float = 0.15
    imu_height: float = 1.2
    margin: float = 4.0


@dataclass(frozen=True)
class TrueRun:
    """A run's true trajectory, the chainage of each epoch and the time span the scanner works."""

    spec: RunSpec
    trajectory: Trajectory
    chainage: np.ndarray
    scan_span: tuple[float, float]


def drive(spec: RunSpec, scene: Scene, rate_hz: float, rng: np.random.Generator) -> TrueRun:
    """Drive ``spec`` through ``scene``: the true trajectory at ``rate_hz`` epochs."""
    if spec.direction not in (1, -1):
        raise ValueError(f"run {spec.run_id}: direction must be 1 or -1, got {spec.direction}")
    tracks = scene.sections.tracks
    if not 0 <= spec.track < len(tracks):
        raise ValueError(f"run {spec.run_id}: track {spec.track} does not exist; the scene has "
                         f"{len(tracks)} track(s), numbered from 0")
    line = scene.centreline
    dist = line.length - 2 * spec.margin
    d = np.linspace(0.0, dist, max(2, int(np.ceil(dist / 0.05)) + 1))
    wave = 2 * np.pi * d / rng.uniform(200.0, 400.0) + rng.uniform(0, 2 * np.pi)
    speed = spec.speed * (1.0 + spec.speed_variation * np.sin(wave))
    inv = 1.0 / speed
    elapsed = np.concatenate([[0.0], np.cumsum((inv[1:] + inv[:-1]) / 2 * np.diff(d))])
    t = np.arange(0.0, elapsed[-1], 1.0 / rate_hz)
    dk = np.interp(t, elapsed, d)
    s = spec.margin + dk if spec.direction > 0 else line.length - spec.margin - dk
    u = tracks[spec.track]
    xyz = line.point(s) + u * line.right(s)
    xyz[:, 2] += spec.imu_height
    roll = spec.roll_deg * np.sin(2 * np.pi * dk / rng.uniform(20.0, 40.0) + rng.uniform(0, 2 * np.pi))
    rpy = attitude_from_direction(spec.direction * line.tangent(s), roll)
    traj = Trajectory(spec.start_time + t, line.to_world(xyz), rpy, run_id=spec.run_id)
    guard = 0.2
    return TrueRun(spec, traj, s, (float(traj.time[0] + guard), float(traj.time[-1] - guard)))
