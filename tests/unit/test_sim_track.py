"""The simulator's alignment: straights, circular curves, grades and the track frame."""

from __future__ import annotations

import numpy as np
import pytest

from railtraj.geo import attitude_from_direction
from railtraj.sim.geometry import GeometrySpec, build_scene
from railtraj.sim.runs import RunSpec, drive
from railtraj.sim.track import Alignment, Centreline


def test_straight_line_follows_heading():
    line = Centreline(Alignment(heading_deg=60.0), 100.0)
    s = np.array([0.0, 10.0, 55.55])
    h = np.radians(60.0)
    np.testing.assert_allclose(line.point(s), np.column_stack([s * np.sin(h), s * np.cos(h), 0 * s]),
                               atol=1e-9)
    np.testing.assert_allclose(line.right(s)[0], [np.cos(h), -np.sin(h), 0.0], atol=1e-12)


def test_curve_is_a_circle_of_the_given_radius():
    radius = 300.0
    line = Centreline(Alignment(heading_deg=0.0, curves=((50.0, 0.0), (200.0, radius), (1e9, 0.0))), 300.0)
    s = np.linspace(50.0, 250.0, 41)
    p = line.point(s)[:, :2]
    centre = line.point([50.0])[0, :2] + radius * line.right([50.0])[0, :2]   # right turn
    np.testing.assert_allclose(np.linalg.norm(p - centre, axis=1), radius, atol=1e-5)
    assert line.heading([250.0])[0] == pytest.approx(200.0 / radius, abs=1e-9)
    # chainage is arc length
    step = np.linalg.norm(np.diff(line.point(np.linspace(60, 240, 1801)), axis=0), axis=1).sum()
    assert step == pytest.approx(180.0, abs=1e-4)


def test_grade_gives_height_and_is_smoothed():
    line = Centreline(Alignment(grades=((100.0, 0.01), (1e9, -0.01)), vertical_curve=20.0), 300.0)
    assert line.point([50.0])[0, 2] == pytest.approx(0.5, abs=1e-3)
    assert line.grade([100.0])[0] == pytest.approx(0.0, abs=1e-3)          # mid vertical curve
    assert line.point([200.0])[0, 2] == pytest.approx(1.0 - 1.0, abs=0.01)
    t = line.tangent(np.array([50.0]))[0]
    assert np.linalg.norm(t) == pytest.approx(1.0)
    assert t[2] / np.hypot(t[0], t[1]) == pytest.approx(0.01, abs=1e-6)


def test_track_frame_mapping():
    line = Centreline(Alignment(origin=(530000.0, 180000.0, 10.0), heading_deg=90.0), 50.0)
    local = line.to_local(np.array([[10.0, 2.0, 3.0]]))
    np.testing.assert_allclose(local, [[10.0, -2.0, 3.0]], atol=1e-9)      # east-bound: right is south
    np.testing.assert_allclose(line.to_world(local), [[530010.0, 179998.0, 13.0]], atol=1e-9)


@pytest.mark.parametrize("direction", [1, -1])
def test_drive_follows_the_track_with_attitude_from_tangent(direction):
    spec = GeometrySpec(sections=(("rect", 120.0),), tracks=2, alignment=Alignment(
        curves=((40.0, 0.0), (1e9, 400.0)), grades=((1e9, 0.005),)))
    scene = build_scene(spec)
    run = drive(RunSpec("r", track=1, direction=direction, roll_deg=0.0), scene, 200.0,
                np.random.default_rng(0))
    traj, s = run.trajectory, run.chainage
    assert np.allclose(np.diff(traj.time), 1 / 200.0)
    assert traj.covers(np.array(run.scan_span)).all()
    line = scene.centreline
    expect = line.to_world(line.point(s) + 2.0 * line.right(s) + [0, 0, 1.2])
    np.testing.assert_allclose(traj.xyz, expect, atol=1e-9)
    rpy = attitude_from_direction(direction * line.tangent(s))
    np.testing.assert_allclose(traj.rpy[:, :2], rpy[:, :2], atol=1e-9)
    dh = (traj.rpy[:, 2] - rpy[:, 2] + 180) % 360 - 180
    assert np.abs(dh).max() < 1e-9
    assert (np.diff(s) * direction > 0).all()
