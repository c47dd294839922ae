"""A rotating profile LiDAR on the train: rays across the track, cast against the scene.

The scanner turns in the body's y-z plane (optionally tilted), ``profile_rate`` turns a second,
``points_per_profile`` pulses a turn. Every pulse has its own time, and its ray is placed with the
TRUE pose interpolated at that time, so motion during a profile is modelled. The first triangle a
ray meets is its return (occlusion), the range gets Gaussian noise, and the measurement is kept
in the body frame: georeferencing (with the true or the drifted trajectory) is the writer's job.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from railtraj.georef import PoseInterpolator
from railtraj.sim.geometry import Scene
from railtraj.sim.surfaces import intensity


@dataclass(frozen=True)
class ScannerSpec:
    """Profile scanner settings. ``lever_arm`` is the scanner origin in the body frame
    (x forward, y right, z down), metres; ``tilt_deg`` leans the scan plane forward."""

    profile_rate: float = 250.0
    points_per_profile: int = 500
    range_noise: float = 0.005
    min_range: float = 0.5
    max_range: float = 80.0
    tilt_deg: float = 0.0
    lever_arm: tuple[float, float, float] = (-0.5, 0.0, -1.6)
    intensity_noise: float = 0.06


@dataclass(frozen=True)
class Scan:
    """One run's returns: time, body-frame point, intensity and surface class per return."""

    gps_time: np.ndarray
    p_body: np.ndarray
    intensity: np.ndarray
    surface: np.ndarray

    def __len__(self) -> int:
        return len(self.gps_time)


def beam_directions(spec: ScannerSpec, phase: float = 0.0) -> np.ndarray:
    """Unit ray directions (n, 3) of one profile in the body frame, starting straight up and
    turning clockwise seen from behind (up, right, down, left)."""
    theta = phase + 2 * np.pi * np.arange(spec.points_per_profile) / spec.points_per_profile
    tau = np.radians(spec.tilt_deg)
    return np.column_stack([np.sin(tau) * np.cos(theta), np.sin(theta), -np.cos(tau) * np.cos(theta)])


def scan(scene: Scene, pose: PoseInterpolator, t0: float, t1: float, spec: ScannerSpec,
         rng: np.random.Generator, chunk_profiles: int = 500) -> Scan:
    """Scan from ``t0`` to ``t1`` with the trajectory ``pose`` (which must cover that span)."""
    n_prof = int(np.floor((t1 - t0) * spec.profile_rate))
    npp = spec.points_per_profile
    dirs = beam_directions(spec, rng.uniform(0, 2 * np.pi / npp))
    lever = np.asarray(spec.lever_arm, dtype=float)
    origin = np.asarray(scene.spec.alignment.origin)
    normals = scene.normals
    dt = np.arange(npp) / (npp * spec.profile_rate)              # pulse time within a profile
    parts = []
    for j0 in range(0, n_prof, chunk_profiles):
        tj = t0 + np.arange(j0, min(n_prof, j0 + chunk_profiles)) / spec.profile_rate
        t = (tj[:, None] + dt[None, :]).reshape(-1)
        # attitude at pulse time = W_j exp(dt w_j): first order in dt is exact to ~1e-9 rad here
        w_mat, rate = pose.matrices(tj)
        spin = np.cross(rate[:, None, :], dirs[None, :, :]) * dt[None, :, None]
        w_t = np.ascontiguousarray(w_mat.transpose(0, 2, 1))
        d = np.matmul(dirs[None] + spin, w_t).reshape(-1, 3)
        arm = np.cross(rate[:, None, :], lever[None, None, :]) * dt[None, :, None] + lever
        o = (pose.position(t) - origin) + np.matmul(arm, w_t).reshape(-1, 3)
        t_hit, tri = scene.cast(o, d)
        ok = np.isfinite(t_hit) & (t_hit >= spec.min_range) & (t_hit <= spec.max_range)
        k = np.nonzero(ok)[0]
        r = t_hit[k] + spec.range_noise * rng.standard_normal(len(k))
        cls = scene.surface[tri[k]]
        cos_inc = np.einsum("ij,ij->i", normals[tri[k]], d[k])
        d_body = dirs[k % npp]
        gain = None if scene.marks is None else scene.marks.gain(o[k] + t_hit[k, None] * d[k])
        parts.append(Scan(t[k], lever + r[:, None] * d_body,
                          intensity(cls, cos_inc, r, rng, spec.intensity_noise, gain), cls))
    if not parts:
        return Scan(np.zeros(0), np.zeros((0, 3)), np.zeros(0, np.uint16), np.zeros(0, np.uint8))
    return Scan(*(np.concatenate([getattr(p, k) for p in parts])
                  for k in ("gps_time", "p_body", "intensity", "surface")))
