"""Cross-sections, mesh primitives and the assembled scene."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from railtraj.sim.geometry import GeometrySpec, build_scene
from railtraj.sim.mesh import MeshBuilder
from railtraj.sim.sections import CROWN, FLOOR, NICHE_TOP, WALL_TOP, SectionSet
from railtraj.sim.surfaces import Surface
from railtraj.sim.track import Alignment, Centreline


def _shoot(scene, s, u, v, direction_suv):
    """Cast one ray from track-frame point (s, u, v) along a track-frame direction."""
    line = scene.centreline
    o = line.to_local(np.array([[s, u, v]]))
    d = line.to_local(np.array([[s, u, v]]) + np.asarray(direction_suv, float)) - o
    t, tri = scene.cast(o, d / np.linalg.norm(d))
    return t[0], Surface(scene.surface[tri[0]]) if np.isfinite(t[0]) else None


@pytest.mark.parametrize("tracks", [1, 2])
def test_profiles_are_consistent(tracks):
    secs = SectionSet.for_tracks(tracks)
    for kind, prof in secs.profiles.items():
        assert len(prof.cls) == len(prof.uv) - 1, kind
        assert np.allclose(prof.outline[0], prof.outline[-1]), kind      # outlines are closed
        assert prof.wall_u(0.5, 1) == pytest.approx(prof.wall_u(0.5, -1)), kind   # symmetric
        for t in secs.tracks:   # the track bed is wide enough for the sleepers
            assert prof.wall_u(FLOOR + 0.01, 1) > abs(t) + 1.3, kind
    rect = secs.profiles["rect"]
    assert rect.uv[:, 1].max() == pytest.approx(CROWN, abs=1e-9)
    assert NICHE_TOP in rect.uv[:, 1] and WALL_TOP in rect.uv[:, 1]


def test_box_and_ring_primitives():
    b = MeshBuilder()
    b.boxes([[0, 1, 0, 2, 0, 3], [5, 6, 0, 1, 0, 1]], Surface.METAL)
    square = np.array([[-1, 0], [1, 0], [1, 2], [-1, 2], [-1, 0]], float)
    b.ring(square, (0.0, 1.0), (-3.0, 3.0, -1.0, 4.0), 10.0, Surface.RETAINING)
    v, tri, cls = b.build(Centreline(Alignment(heading_deg=90.0), 20.0))
    assert tri.max() < len(v) and len(tri) == len(cls)
    assert (cls[:24] == Surface.METAL).all()
    # the ring covers the rectangle minus the square: total area 6 * 5 - 2 * 2 = 26
    ring = v[tri[cls == Surface.RETAINING]]
    area = 0.5 * np.linalg.norm(np.cross(ring[:, 1] - ring[:, 0], ring[:, 2] - ring[:, 0]), axis=1).sum()
    assert area == pytest.approx(26.0, rel=1e-9)


@pytest.fixture(scope="module")
def scene():
    spec = GeometrySpec(sections=(("cutting", 30.0), ("rect", 60.0), ("station", 40.0),
                                  ("circular", 40.0), ("cutting", 30.0)),
                        tracks=2, niche_spacing=25.0, box_spacing=15.0, control_spacing=20.0)
    return build_scene(spec)


def test_scene_layout(scene):
    assert scene.portals() == [30.0, 170.0]
    assert scene.open_sky(np.array([10.0, 50.0, 110.0, 150.0, 190.0])).tolist() == [True, False, False, False, True]
    assert scene.triangles.max() < len(scene.vertices)
    present = set(np.unique(scene.surface).tolist())
    for cls in (Surface.LINING, Surface.RAIL, Surface.SLEEPER, Surface.RIB, Surface.PLATFORM,
                Surface.PILLAR, Surface.NICHE, Surface.DOOR, Surface.EARTH, Surface.MAST,
                Surface.TARGET, Surface.CABLE_TRAY, Surface.METAL):
        assert cls in present, cls.name
    assert len(scene.control) >= 5


def test_cross_sections_by_ray(scene):
    hw = scene.sections.rect_half_width
    # rect: straight up from the axis hits a rib or the lining at the crown
    t, cls = _shoot(scene, 50.0, 0.0, 2.0, (0, 0, 1))
    assert cls in (Surface.LINING, Surface.RIB) and t == pytest.approx(CROWN - 2.0, abs=0.25)
    # cutting: no roof, open sky
    t, cls = _shoot(scene, 10.0, 0.0, 2.0, (0, 0, 1))
    assert cls is None
    # station: ceiling at 5.5 m; platform edge to the side below platform level
    t, cls = _shoot(scene, 112.5, 0.0, 3.0, (0, 0, 1))
    assert cls == Surface.CEILING and t == pytest.approx(2.5, abs=1e-4)
    # circular: sideways to the lining
    radius = hw + 0.35
    t, cls = _shoot(scene, 150.0, 0.0, 1.2, (0, 1, 0))
    assert cls == Surface.LINING and t == pytest.approx(radius, abs=0.01)


def test_niche_is_a_recess(scene):
    hw = scene.sections.rect_half_width
    # find a niche: its door is further away than the wall
    hits = [(_shoot(scene, s, 0.0, 1.0, (0, side, 0)), side) for s in np.arange(31.0, 90.0, 0.25)
            for side in (-1, 1)]
    doors = [t for (t, cls), _ in hits if cls == Surface.DOOR]
    assert doors and min(doors) > hw + 0.5


def test_control_targets_sit_on_the_walls(scene):
    line = scene.centreline
    ch = np.arange(0, line.length, 0.05)
    for xyz in scene.control.values():
        local = xyz - np.asarray(scene.spec.alignment.origin)
        k = np.argmin(np.linalg.norm(line.point(ch)[:, :2] - local[:2], axis=1))
        right = line.right(ch[[k]])[0]
        side = np.sign((local - line.point(ch[[k]])[0]) @ right)
        # a ray from 1 m in front of the target, towards the wall, hits the target's face
        t, tri = scene.cast((local - side * right)[None], (side * right)[None])
        assert scene.surface[tri[0]] == Surface.TARGET
        assert t[0] == pytest.approx(1.0, abs=1e-3)


def test_lining_marks_lie_on_the_tunnel_surface_and_leave_its_shape_alone():
    spec = GeometrySpec(sections=(("cutting", 20.0), ("circular", 80.0), ("cutting", 20.0)), lining_marks=20.0)
    marked, plain = build_scene(spec), build_scene(replace(spec, lining_marks=0.0))
    assert plain.marks is None and np.array_equal(marked.vertices, plain.vertices)
    assert 5 <= len(marked.marks) <= 35  # Poisson, 16 expected over the 80 m tunnel
    axis = marked.centreline.to_local(np.column_stack([np.linspace(0, 120, 1201), np.zeros(1201), np.full(1201, 2.0)]))
    nearest = np.linalg.norm(marked.marks.centres[:, None] - axis[None], axis=2)
    s = np.argmin(nearest, axis=1) * 0.1
    assert np.all((s > 20.0) & (s < 100.0))  # in the tunnel, not in the cuttings
    assert np.all((nearest.min(axis=1) > 1.5) & (nearest.min(axis=1) < 4.0))  # on the lining
    assert np.array_equal(marked.marks.gain(marked.marks.centres), marked.marks.gains)
    assert np.all(marked.marks.gain(axis) == 1.0)  # off the discs
