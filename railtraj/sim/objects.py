"""The things in and along a tunnel that make one place distinguishable from another.

Repeated structure (arch ribs, sleepers, masts, pillars) aliases along the track; sparse,
irregularly placed objects (emergency-exit niches, signal boxes, cable-tray ends, survey targets)
break the ambiguity. Each function adds one kind of object to a :class:`MeshBuilder` in the
track frame. Wall-mounted objects ask the section profile where its wall is at their height, so
they sit correctly on vertical and curved walls alike.
"""

from __future__ import annotations

import numpy as np

from railtraj.sim.mesh import Hole, MeshBuilder, chainage_breaks
from railtraj.sim.sections import FLOOR, NICHE_TOP, Profile, rib_outlines
from railtraj.sim.surfaces import Surface

GAUGE = 1.435
RAIL_TOP, RAIL_FOOT, RAIL_HEAD = 0.0, -0.17, 0.07
SLEEPER_LENGTH, SLEEPER_WIDTH = 2.6, 0.25


def track(b: MeshBuilder, s0: float, s1: float, u: float, sleeper_spacing: float | None,
          max_step: float) -> None:
    """Two rails on ``u`` and, unless ``sleeper_spacing`` is None (slab track), sleepers."""
    s = chainage_breaks(s0, s1, max_step)
    for side in (-1, 1):
        c = u + side * (GAUGE + RAIL_HEAD) / 2
        h = RAIL_HEAD / 2
        b.prism(np.array([[c - h, RAIL_FOOT], [c + h, RAIL_FOOT], [c + h, RAIL_TOP], [c - h, RAIL_TOP]]),
                s, Surface.RAIL)
    if sleeper_spacing:
        mid = np.arange(s0 + sleeper_spacing / 2, s1 - SLEEPER_WIDTH / 2, sleeper_spacing)
        n = len(mid)
        b.boxes(np.column_stack([mid - SLEEPER_WIDTH / 2, mid + SLEEPER_WIDTH / 2,
                                 np.full(n, u - SLEEPER_LENGTH / 2), np.full(n, u + SLEEPER_LENGTH / 2),
                                 np.full(n, FLOOR), np.full(n, RAIL_FOOT)]),
                Surface.SLEEPER, faces=("s0", "s1", "u0", "u1", "v1"))


def ribs(b: MeshBuilder, s0: float, s1: float, half_width: float, spacing: float,
         width: float = 0.25, depth: float = 0.2) -> None:
    """Steel arch ribs every ``spacing`` metres, up the walls and over the roof."""
    outer, inner = rib_outlines(half_width, depth)
    for s in np.arange(s0 + spacing / 2, s1 - width, spacing):
        b.band(outer, inner, s, s + width, Surface.RIB)


def ring_joints(b: MeshBuilder, s0: float, s1: float, profile: Profile, spacing: float,
                width: float = 0.08, depth: float = 0.025) -> None:
    """Segmental lining: a raised band ``depth`` thick at every ring joint of a bored tunnel."""
    outer = profile.uv[1:] if len(profile.uv) > 2 else profile.uv
    centre = np.asarray(profile.centre, float)
    radial = outer - centre
    inner = centre + radial * (1.0 - depth / np.linalg.norm(radial, axis=1, keepdims=True))
    for s in np.arange(s0 + spacing / 2, s1 - width, spacing):
        b.band(outer, inner, s, s + width, Surface.LINING)


def niche(b: MeshBuilder, s: float, side: int, half_width: float, length: float = 1.4,
          depth: float = 0.9) -> Hole:
    """An emergency-exit niche cut into a vertical wall, with a door at its back.

    Returns the hole to leave out of the wall.
    """
    s0, s1, w = s - length / 2, s + length / 2, half_width
    if side > 0:
        u0, u1, opening, door = w, w + depth, "u0", (w + depth - 0.03, w + depth)
    else:
        u0, u1, opening, door = -w - depth, -w, "u1", (-w - depth, -w - depth + 0.03)
    b.boxes([s0, s1, u0, u1, FLOOR, NICHE_TOP], Surface.NICHE,
            faces=[f for f in ("s0", "s1", "u0", "u1", "v0", "v1") if f != opening])
    b.boxes([s0 + 0.25, s1 - 0.25, *door, FLOOR, 1.7], Surface.DOOR)
    return (s0, s1, side * w - 0.05, side * w + 0.05, FLOOR - 0.01, NICHE_TOP + 0.01)


def wall_box(b: MeshBuilder, profile: Profile, s: float, side: int, v0: float, v1: float,
             length: float, depth: float, cls: int) -> tuple[float, float, float]:
    """A box fixed to the wall (signal box, cabinet, survey target); returns the (s, u, v) of the
    centre of its face towards the track."""
    walls = [profile.wall_u(v, side) for v in np.linspace(v0, v1, 5)]
    near, far = min(walls) - depth, max(walls) + 0.05
    u0, u1 = (near, far) if side > 0 else (-far, -near)
    b.boxes([s - length / 2, s + length / 2, u0, u1, v0, v1], cls)
    return s, side * near, (v0 + v1) / 2


def cable_tray(b: MeshBuilder, profile: Profile, s0: float, s1: float, side: int,
               v: float = 2.3, width: float = 0.3, height: float = 0.08, max_step: float = 2.0) -> None:
    """A cable tray along a wall between ``s0`` and ``s1``; its ends are distinctive."""
    w = profile.wall_u(v, side)
    u0, u1 = w - width, w + 0.02
    if side < 0:
        u0, u1 = -u1, -u0
    b.prism(np.array([[u0, v], [u1, v], [u1, v + height], [u0, v + height]]),
            chainage_breaks(s0, s1, max_step), Surface.CABLE_TRAY)


def masts(b: MeshBuilder, s0: float, s1: float, spacing: float, mast_u: float,
          tracks: tuple[float, ...], phase: float = 0.3) -> None:
    """Overhead-line masts beside the track with a cantilever arm over the nearest track."""
    for k, s in enumerate(np.arange(s0 + phase * spacing, s1 - 0.5, spacing)):
        side = 1 if (len(tracks) > 1 or k % 2 == 0) else -1
        for sd in ((-1, 1) if len(tracks) > 1 else (side,)):
            u = sd * mast_u
            b.boxes([s - 0.15, s + 0.15, u - 0.15, u + 0.15, FLOOR, 6.0], Surface.MAST)
            target = min(tracks, key=lambda t, u=u: abs(t - u))
            lo, hi = sorted((u, target))
            b.boxes([s - 0.05, s + 0.05, lo, hi, 5.6, 5.72], Surface.MAST)


def pillars(b: MeshBuilder, s0: float, s1: float, spacing: float, u: float, v0: float,
            v1: float, size: float = 0.5) -> None:
    """Rows of square pillars on both sides at |u|, from ``v0`` to ``v1``."""
    mid = np.arange(s0 + spacing / 2, s1 - size, spacing)
    rows = [np.column_stack([mid - size / 2, mid + size / 2, np.full(len(mid), c - size / 2),
                             np.full(len(mid), c + size / 2), np.full(len(mid), v0),
                             np.full(len(mid), v1)]) for c in (-u, u)]
    b.boxes(np.concatenate(rows), Surface.PILLAR, faces=("s0", "s1", "u0", "u1"))
