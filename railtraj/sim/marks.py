"""Marks on the lining: patches that return more or less light than the surface around them.

A real lining is not one even grey: water stains, soot, grout repairs, painted chainage and
cable-route markers. Geometry does not show them; the scanner's intensity does, and in a plain
section (a slab-track circular tunnel) they are the only thing that says where along the track a
point is. Each mark is a disc on whatever the ray from the tunnel axis meets first (lining,
tray, box), of 0.2-0.6 m radius, darker (x0.5-0.75) or brighter (x1.4-2.0) than its surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

#: radius range (m) of a mark, and its gain ranges: dark (stains, soot) and bright (paint, grout)
RADIUS = (0.2, 0.6)
DARK, BRIGHT = (0.5, 0.75), (1.4, 2.0)
#: directions marks are laid in, degrees from straight up either side (walls and vault, not the floor)
MAX_ANGLE = 110.0
#: height above top of rail (m) of the point the rays start from
EYE_HEIGHT = 2.0


@dataclass(frozen=True)
class Marks:
    """Discs (spheres cut by the surface) that scale the intensity of the points inside them."""

    centres: np.ndarray  # (m, 3) local ENU, on the surface
    radii: np.ndarray  # (m,)
    gains: np.ndarray  # (m,)

    def __len__(self) -> int:
        return len(self.radii)

    def gain(self, xyz: np.ndarray) -> np.ndarray:
        """Intensity factor per point ``xyz`` (local ENU): a mark's gain inside it, else 1."""
        out = np.ones(len(xyz))
        if not len(self) or not len(xyz):
            return out
        dist, k = cKDTree(self.centres).query(xyz, distance_upper_bound=RADIUS[1])
        hit = np.isfinite(dist)
        hit[hit] = dist[hit] <= self.radii[k[hit]]
        out[hit] = self.gains[k[hit]]
        return out


def lay_marks(scene, per_100m: float, rng: np.random.Generator) -> Marks:
    """About ``per_100m`` marks per 100 m of covered tunnel (Poisson), at random chainages and
    directions, on the first surface a ray from the axis meets."""
    pieces = []
    for kind, s0, s1 in scene.spans:
        if kind != "cutting":
            pieces.append(rng.uniform(s0, s1, rng.poisson(per_100m * (s1 - s0) / 100.0)))
    s = np.concatenate(pieces) if pieces else np.zeros(0)
    angle = np.radians(rng.uniform(-MAX_ANGLE, MAX_ANGLE, len(s)))
    radii = rng.uniform(*RADIUS, len(s))
    bright = rng.random(len(s)) < 0.5
    gains = np.where(bright, rng.uniform(*BRIGHT, len(s)), rng.uniform(*DARK, len(s)))
    eye = scene.centreline.to_local(np.column_stack([s, np.zeros_like(s), np.full_like(s, EYE_HEIGHT)]))
    ray = np.cos(angle)[:, None] * np.array([0.0, 0.0, 1.0]) + np.sin(angle)[:, None] * scene.centreline.right(s)
    t_hit, _ = scene.cast(eye, ray) if len(s) else (np.zeros(0), None)
    ok = np.isfinite(t_hit)
    return Marks(eye[ok] + t_hit[ok, None] * ray[ok], radii[ok], gains[ok])
