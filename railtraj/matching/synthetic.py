"""Small seeded tunnel-like point clouds for the matching tests and benchmarks.

A quick numpy stand-in for :mod:`railtraj.sim` (which ray-casts a full survey): surfaces are
sampled uniformly at ``density`` points per square metre, so a 12 m section has ~200 k points
in a few tens of milliseconds. The geometry is what makes tunnel matching hard: walls and an
arched ceiling (featureless along the track), ribs every 1.5 m and sleepers every 0.65 m
(aliases), rails and a cable tray (continuous lines), and a few wall boxes (the only things
that tell one rib from the next). GPS time grows with x as for a train at ``speed`` m/s.
"""

from __future__ import annotations

import numpy as np

from railtraj.data import PointTile

HALF_WIDTH, WALL_TOP, RADIUS = 3.0, 3.5, 4.0
ARC_Z0 = WALL_TOP - np.sqrt(RADIUS**2 - HALF_WIDTH**2)  # arc centre height
RIB_SPACING, RIB_WIDTH, RIB_DEPTH, RIB_DOWN = 1.5, 0.25, 0.20, 1.0
SLEEPER_SPACING, SLEEPER_WIDTH = 0.65, 0.25


def _rect(rng, density, origin, u, v) -> np.ndarray:
    """Uniform samples on the parallelogram origin + s*u + t*v, s, t in [0, 1]."""
    u, v = np.asarray(u, float), np.asarray(v, float)
    n = rng.poisson(density * np.linalg.norm(np.cross(u, v)))
    s, t = rng.random((2, n, 1))
    return np.asarray(origin, float) + s * u + t * v


def _box(rng, density, lo, hi, skip=()) -> np.ndarray:
    """Samples on the faces of an axis-aligned box; ``skip`` names faces to leave out (e.g. '-z')."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    e = np.diag(hi - lo)
    parts = []
    for k, axis in enumerate("xyz"):
        a, b = e[(k + 1) % 3], e[(k + 2) % 3]
        for sign, base in (("-", lo), ("+", lo + e[k])):
            if sign + axis not in skip:
                parts.append(_rect(rng, density, base, a, b))
    return np.concatenate(parts)


def _arc(rng, density, x0, x1, radius, phi0, phi1) -> np.ndarray:
    """Samples on the ceiling arc of ``radius`` between angles phi0..phi1 (from +y, radians)."""
    n = rng.poisson(density * (x1 - x0) * radius * (phi1 - phi0))
    x = rng.uniform(x0, x1, n)
    phi = rng.uniform(phi0, phi1, n)
    return np.c_[x, radius * np.cos(phi), ARC_Z0 + radius * np.sin(phi)]


def _in_rib(x: np.ndarray) -> np.ndarray:
    return np.mod(x, RIB_SPACING) < RIB_WIDTH


def tunnel_xyz(x0: float, x1: float, density: float = 800.0, seed: int = 0,
               features: bool = True, n_boxes: int = 4, box_seed: int = 7) -> np.ndarray:
    """Noise-free points of the tunnel section x in [x0, x1].

    ``features=False`` gives a featureless tube (floor, walls, arch only). Boxes are placed from
    ``box_seed`` over x in [0, 100) so that overlapping sections share them.
    """
    rng = np.random.default_rng(seed)
    phi_wall = np.arctan2(WALL_TOP - ARC_Z0, HALF_WIDTH)
    L = x1 - x0
    parts = [_rect(rng, density, (x0, -HALF_WIDTH, 0), (L, 0, 0), (0, 2 * HALF_WIDTH, 0))]
    for y in (-HALF_WIDTH, HALF_WIDTH):
        parts.append(_rect(rng, density, (x0, y, 0), (L, 0, 0), (0, 0, WALL_TOP)))
    parts.append(_arc(rng, density, x0, x1, RADIUS, phi_wall, np.pi - phi_wall))
    if features:
        pts = np.concatenate(parts)
        hidden = _in_rib(pts[:, 0]) & ((pts[:, 2] > WALL_TOP - RIB_DOWN) & (np.abs(pts[:, 1]) > HALF_WIDTH - 0.01))
        parts = [pts[~hidden]]
        ks = np.arange(np.floor(x0 / RIB_SPACING), np.ceil(x1 / RIB_SPACING))
        for k in ks:  # ribs: inner arch face, two side faces, wall legs
            xa = k * RIB_SPACING
            parts.append(_arc(rng, density, xa, xa + RIB_WIDTH, RADIUS - RIB_DEPTH, phi_wall, np.pi - phi_wall))
            for xs in (xa, xa + RIB_WIDTH):  # side faces: annular sectors facing along the track
                n = rng.poisson(density * RIB_DEPTH * RADIUS * (np.pi - 2 * phi_wall))
                r = rng.uniform(RADIUS - RIB_DEPTH, RADIUS, n)
                phi = rng.uniform(phi_wall, np.pi - phi_wall, n)
                parts.append(np.c_[np.full(n, xs), r * np.cos(phi), ARC_Z0 + r * np.sin(phi)])
            for s in (-1, 1):
                lo = (xa, s * HALF_WIDTH - (s > 0) * RIB_DEPTH, WALL_TOP - RIB_DOWN)
                parts.append(_box(rng, density, lo, np.add(lo, (RIB_WIDTH, RIB_DEPTH, RIB_DOWN)),
                                  skip=("+z",)))
        for k in np.arange(np.floor(x0 / SLEEPER_SPACING), np.ceil(x1 / SLEEPER_SPACING)):
            xs = k * SLEEPER_SPACING
            parts.append(_box(rng, density, (xs, -1.3, 0), (xs + SLEEPER_WIDTH, 1.3, 0.15), skip=("-z",)))
        for y in (-0.7175, 0.7175):  # rails
            parts.append(_box(rng, density, (x0, y - 0.035, 0.15), (x1, y + 0.035, 0.32), skip=("-z", "-x", "+x")))
        parts.append(_box(rng, density, (x0, 2.6, 2.0), (x1, 2.95, 2.08), skip=("-x", "+x")))  # cable tray
        brng = np.random.default_rng(box_seed)
        for _ in range(n_boxes * 8):  # n_boxes per 12.5 m on average over [0, 100)
            bx, bz = brng.uniform(0, 100), brng.uniform(0.3, 1.8)
            s = brng.choice([-1, 1])
            w, h, dep = brng.uniform(0.4, 1.0), brng.uniform(0.4, 1.0), brng.uniform(0.15, 0.4)
            if bx + w < x0 or bx > x1:
                continue
            lo = (bx, s * HALF_WIDTH - (s > 0) * dep, bz)
            parts.append(_box(rng, density, lo, np.add(lo, (w, dep, h))))
    pts = np.concatenate(parts)
    return pts[(pts[:, 0] >= x0) & (pts[:, 0] < x1)]


def tunnel_tile(x0: float = 0.0, x1: float = 12.0, density: float = 800.0, noise: float = 0.02,
                seed: int = 0, features: bool = True, speed: float = 5.0, run_id: str = "A",
                name: str = "") -> PointTile:
    """A seeded tunnel tile with Gaussian ``noise`` per axis and along-track GPS times."""
    rng = np.random.default_rng(seed + 1000)
    xyz = tunnel_xyz(x0, x1, density, seed, features)
    t = 1000.0 + xyz[:, 0] / speed + rng.normal(0, 1e-3, len(xyz))
    order = np.argsort(t)
    xyz = xyz[order] + rng.normal(0, noise, (len(xyz), 3))
    return PointTile(xyz, t[order], run_id=run_id, name=name or f"{run_id}_{x0:g}")


def second_acquisition(tile: PointTile, shift, noise: float = 0.02, seed: int = 1,
                       run_id: str = "B") -> PointTile:
    """The thesis' synthetic second run: the same points moved by ``shift`` plus fresh noise.

    The offset a matcher should return is ``d = -shift`` (p_a = p_b + d).
    """
    rng = np.random.default_rng(seed)
    xyz = tile.xyz + np.asarray(shift, float) + rng.normal(0, noise, tile.xyz.shape)
    return PointTile(xyz, tile.gps_time.copy(), run_id=run_id, name=f"{run_id}_{tile.name}")


def placed(tile: PointTile, origin=(530000.0, 180000.0, 20.0), heading_deg: float = 30.0) -> PointTile:
    """The tile turned by ``heading_deg`` about z (x axis -> the tunnel axis) and moved to
    ``origin``: survey-grid coordinates, so nothing can rely on an x-aligned tunnel or small
    numbers. A local shift ``s`` becomes ``rotation_z(heading) @ s`` in the survey grid."""
    R = rotation_z(heading_deg)
    return PointTile(tile.xyz @ R.T + np.asarray(origin, float), tile.gps_time, tile.intensity,
                     tile.run_id, tile.name)


def rotation_z(heading_deg: float) -> np.ndarray:
    """The rotation :func:`placed` applies."""
    h = np.radians(heading_deg)
    return np.array([[np.cos(h), -np.sin(h), 0.0], [np.sin(h), np.cos(h), 0.0], [0.0, 0.0, 1.0]])
