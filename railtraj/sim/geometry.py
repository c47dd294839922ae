"""The simulated scene: sections laid along the alignment, furnished, meshed and ray-castable.

:func:`build_scene` turns a :class:`GeometrySpec` into a :class:`Scene`: one triangle mesh (in
local east-north-up metres, float32 for Open3D's ``RaycastingScene``) with a surface class per
triangle, the chainage spans of each section kind, and the surveyed positions of control targets.
Object placement is random but comes from ``layout_seed`` alone, so every seed of the error model
sees the same tunnel.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from railtraj.sim import objects
from railtraj.sim.marks import Marks, lay_marks
from railtraj.sim.mesh import Hole, MeshBuilder, chainage_breaks
from railtraj.sim.sections import KINDS, NICHE_TOP, SectionSet
from railtraj.sim.surfaces import Surface
from railtraj.sim.track import Alignment, Centreline


@dataclass(frozen=True)
class GeometrySpec:
    """What the tunnel looks like. Lengths in metres; spacings of 0 or None switch a feature off."""

    sections: tuple[tuple[str, float], ...] = (("cutting", 40.0), ("rect", 200.0), ("cutting", 40.0))
    alignment: Alignment = field(default_factory=Alignment)
    tracks: int = 1
    track_spacing: float = 4.0
    rib_spacing: float = 1.5
    ring_spacing: float | None = None  # segmental lining: a ring joint step every so many metres (circular)
    sleeper_spacing: float | None = 0.65  # not a divisor of rib_spacing: no exact 3 m alias
    slab_track_in_circular: bool = True
    niche_spacing: float = 150.0
    box_spacing: float = 70.0
    tray_length: float = 90.0
    mast_spacing: float = 50.0
    pillar_spacing: float = 8.0
    control_spacing: float | None = None
    lining_marks: float = 0.0  # intensity marks (stains, paint) per 100 m of tunnel: railtraj.sim.marks
    layout_seed: int = 7
    max_step: float = 1.0

    @property
    def length(self) -> float:
        return float(sum(length for _, length in self.sections))


@dataclass
class Scene:
    """The meshed scene plus what the rest of the simulator needs to know about it."""

    spec: GeometrySpec
    centreline: Centreline
    sections: SectionSet
    spans: list[tuple[str, float, float]]
    vertices: np.ndarray
    triangles: np.ndarray
    surface: np.ndarray
    control: dict[str, np.ndarray]
    marks: Marks | None = None
    _raycaster: object = None

    @property
    def normals(self) -> np.ndarray:
        """Unit normal per triangle (local ENU), sign arbitrary."""
        v = self.vertices[self.triangles]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)

    def kind_at(self, s: np.ndarray) -> np.ndarray:
        """Section kind per chainage (strings)."""
        ends = np.array([e for _, _, e in self.spans])
        k = np.minimum(np.searchsorted(ends, np.asarray(s, dtype=float), side="right"), len(ends) - 1)
        return np.array([kind for kind, _, _ in self.spans])[k]

    def open_sky(self, s: np.ndarray) -> np.ndarray:
        """True where GNSS sees the sky (outside tunnels, in the cuttings)."""
        return self.kind_at(s) == "cutting"

    def portals(self) -> list[float]:
        """Chainages where the line enters or leaves a covered section."""
        out = []
        for (k0, _, e), (k1, _, _) in zip(self.spans[:-1], self.spans[1:], strict=True):
            if (k0 == "cutting") != (k1 == "cutting"):
                out.append(e)
        return out

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First hit of each ray (local ENU): distance (inf if none) and triangle index."""
        from railtraj.o3d import o3d  # imported here so that building specs stays light

        if self._raycaster is None:
            mesh = o3d.t.geometry.TriangleMesh(o3d.core.Tensor(self.vertices.astype(np.float32)),
                                               o3d.core.Tensor(self.triangles.astype(np.uint32)))
            self._raycaster = o3d.t.geometry.RaycastingScene()
            self._raycaster.add_triangles(mesh)
        rays = np.hstack([origins, directions]).astype(np.float32)
        hit = self._raycaster.cast_rays(o3d.core.Tensor(rays))
        return hit["t_hit"].numpy().astype(float), hit["primitive_ids"].numpy().astype(np.int64)


def build_scene(spec: GeometrySpec) -> Scene:
    """Lay out, furnish and mesh the tunnel described by ``spec``."""
    for kind, _ in spec.sections:
        if kind not in KINDS:
            raise ValueError(f"unknown section kind {kind!r}; choose from {', '.join(KINDS)}")
    rng = np.random.default_rng(spec.layout_seed)
    secs = SectionSet.for_tracks(spec.tracks, spec.track_spacing)
    ends = np.cumsum([length for _, length in spec.sections])
    spans = [(k, float(e - length), float(e)) for (k, length), e in zip(spec.sections, ends, strict=True)]
    b = MeshBuilder()
    control: list[tuple[float, float, float]] = []
    for kind, s0, s1 in spans:
        holes, breaks = _furnish(b, spec, secs, kind, s0, s1, rng, control)
        prof = secs.profiles[kind]
        b.sweep(prof.uv, prof.cls, chainage_breaks(s0, s1, spec.max_step, breaks), holes)
        for u in secs.tracks:
            sleepers = None if (kind == "circular" and spec.slab_track_in_circular) else spec.sleeper_spacing
            objects.track(b, s0, s1, u, sleepers, spec.max_step)
    _end_walls(b, secs, spans)
    centreline = Centreline(spec.alignment, spec.length)
    vertices, triangles, surface = b.build(centreline)
    ids = [f"CP{k + 1:03d}" for k in range(len(control))]
    world = centreline.to_world(centreline.to_local(np.array(control).reshape(-1, 3)))
    scene = Scene(spec, centreline, secs, spans, vertices, triangles, surface, dict(zip(ids, world, strict=True)))
    if spec.lining_marks > 0:  # a generator of their own: the layout of a survey without marks is kept
        scene.marks = lay_marks(scene, spec.lining_marks, np.random.default_rng([spec.layout_seed, 1]))
    return scene


def _end_walls(b: MeshBuilder, secs: SectionSet, spans: list[tuple[str, float, float]]) -> None:
    """Where the cross-section changes, the plane outside both outlines is a wall (portal
    headwalls, station end walls)."""
    for (k0, _, s), (k1, _, _) in zip(spans[:-1], spans[1:], strict=True):
        if k0 == k1:
            continue
        p0, p1 = secs.profiles[k0], secs.profiles[k1]
        both = np.vstack([p0.outline, p1.outline])
        bounds = (both[:, 0].min() - 1, both[:, 0].max() + 1, both[:, 1].min() - 0.5, both[:, 1].max() + 1)
        for p in (p0, p1):
            b.ring(p.outline, p.centre, bounds, s, Surface.RETAINING)


def _spots(rng: np.random.Generator, s0: float, s1: float, spacing: float | None, margin: float) -> np.ndarray:
    """Irregular positions about ``spacing`` apart (uniform jitter of +-35 %)."""
    if not spacing or s1 - s0 <= 2 * margin:
        return np.zeros(0)
    base = np.arange(s0 + margin + rng.uniform(0, spacing), s1 - margin, spacing)
    return np.clip(base + rng.uniform(-0.35, 0.35, len(base)) * spacing, s0 + margin, s1 - margin)


def _furnish(b: MeshBuilder, spec: GeometrySpec, secs: SectionSet, kind: str, s0: float, s1: float,
             rng: np.random.Generator, control: list) -> tuple[list[Hole], list[float]]:
    """Add the objects of one section; return holes to cut into its walls and extra breaks."""
    prof, hw = secs.profiles[kind], secs.rect_half_width
    holes: list[Hole] = []
    breaks: list[float] = []
    busy: list[tuple[float, float, int]] = []

    def free(s: float, side: int, half: float) -> bool:
        return all(sd != side or s + half < a or s - half > e for a, e, sd in busy)

    if kind == "cutting":
        objects.masts(b, s0, s1, spec.mast_spacing, prof.wall_u(0.0, 1) - 0.5, secs.tracks,
                      rng.uniform(0.2, 0.8))
        return holes, breaks
    if kind == "rect" and spec.rib_spacing:
        objects.ribs(b, s0, s1, hw, spec.rib_spacing)
    if kind == "circular" and spec.ring_spacing:
        objects.ring_joints(b, s0, s1, prof, spec.ring_spacing)
    if kind == "rect":
        for s in _spots(rng, s0, s1, spec.niche_spacing, 5.0):
            side = int(rng.choice([-1, 1]))
            holes.append(objects.niche(b, s, side, hw))
            breaks += [holes[-1][0], holes[-1][1]]
            busy.append((s - 1.5, s + 1.5, side))
    if kind == "station":
        edge = secs.profiles["station"].uv[1, 0]
        objects.pillars(b, s0, s1, spec.pillar_spacing, edge + 2.5, 0.95, 5.5)
    if kind in ("rect", "circular"):
        for s in _spots(rng, s0, s1, spec.box_spacing, 3.0):
            side = int(rng.choice([-1, 1]))
            if free(s, side, 1.0):
                objects.wall_box(b, prof, s, side, 1.0, 1.0 + rng.uniform(0.6, 1.0),
                                 rng.uniform(0.4, 0.9), rng.uniform(0.2, 0.4), Surface.METAL)
                busy.append((s - 0.6, s + 0.6, side))
        if spec.tray_length:
            for side in (-1, 1):
                a = s0 + rng.uniform(2.0, 20.0)
                while a < s1 - 10.0:
                    e = min(s1 - 2.0, a + rng.uniform(0.5, 1.5) * spec.tray_length)
                    objects.cable_tray(b, prof, a, e, side, NICHE_TOP + 0.1, max_step=spec.max_step)
                    a = e + rng.uniform(3.0, 25.0)
    for s in _spots(rng, s0, s1, spec.control_spacing, 4.0):
        side = int(rng.choice([-1, 1]))
        if not free(s, side, 0.5):
            side = -side
        v = 1.5 if kind != "station" else 2.5
        control.append(objects.wall_box(b, prof, s, side, v - 0.1, v + 0.1, 0.2, 0.03, Surface.TARGET))
        busy.append((s - 0.3, s + 0.3, side))
    return holes, breaks
