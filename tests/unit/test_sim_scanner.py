"""The profile scanner: timing, occlusion and ranges against a known cross-section."""

from __future__ import annotations

import numpy as np
import pytest

from railtraj.georef import PoseInterpolator
from railtraj.sim.geometry import GeometrySpec, build_scene
from railtraj.sim.runs import RunSpec, drive
from railtraj.sim.scanner import ScannerSpec, beam_directions, scan
from railtraj.sim.sections import FLOOR
from railtraj.sim.surfaces import Surface


def _ray_polyline(o: np.ndarray, d: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Distance along 2-D rays (o, d (n, 2)) to the first crossing of a polyline (k, 2)."""
    a, e = poly[:-1], poly[1:] - poly[:-1]                             # segments a + l e
    den = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]
    w = a[None] - o
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[..., 0] * e[None, :, 1] - w[..., 1] * e[None, :, 0]) / den
        lam = (w[..., 0] * d[:, None, 1] - w[..., 1] * d[:, None, 0]) / den
    t = np.where((lam >= 0) & (lam <= 1) & (t > 0), t, np.inf)
    return t.min(axis=1)


def _distance_to_polyline(p: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Distance of 2-D points (n, 2) to a polyline (k, 2)."""
    a, e = poly[:-1], poly[1:] - poly[:-1]
    lam = np.clip(np.einsum("nkj,kj->nk", p[:, None] - a[None], e) / (e * e).sum(1), 0, 1)
    return np.linalg.norm(p[:, None] - (a[None] + lam[..., None] * e[None]), axis=2).min(axis=1)


@pytest.fixture(scope="module")
def bore():
    """A bare circular single-track bore: slab track, nothing on the walls, straight and level."""
    spec = GeometrySpec(sections=(("circular", 60.0),), tracks=1, box_spacing=0, tray_length=0,
                        niche_spacing=0)
    scene = build_scene(spec)
    run = drive(RunSpec("r", roll_deg=0.0, speed_variation=0.0, margin=10.0), scene, 200.0,
                np.random.default_rng(0))
    return scene, run


def test_beams_are_unit_and_in_the_profile_plane():
    d = beam_directions(ScannerSpec(points_per_profile=360))
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    assert np.allclose(d[:, 0], 0.0)
    np.testing.assert_allclose(d[0], [0, 0, -1], atol=1e-12)            # first beam straight up
    np.testing.assert_allclose(d[90], [0, 1, 0], atol=1e-12)            # then to the right
    tilted = beam_directions(ScannerSpec(points_per_profile=4, tilt_deg=10.0))
    assert tilted[0, 0] == pytest.approx(np.sin(np.radians(10.0)))


def test_ranges_match_the_known_circle(bore):
    scene, run = bore
    spec = ScannerSpec(points_per_profile=720, range_noise=0.0)
    t0 = run.scan_span[0]
    res = scan(scene, PoseInterpolator(run.trajectory), t0, t0 + 0.1, spec, np.random.default_rng(1))
    assert 0 < len(res) <= 25 * 720
    lever = np.asarray(spec.lever_arm)
    ray = res.p_body - lever
    r = np.linalg.norm(ray, axis=1)
    d = ray / r[:, None]
    cos_up, right = -d[:, 2], d[:, 1]
    # scanner 1.2 + 1.6 m above top of rail on the axis: ranges to the section's polygon
    poly = scene.sections.profiles["circular"].uv
    expect = _ray_polyline(np.array([0.0, 2.8]), np.column_stack([right, cos_up]), poly)
    lining = res.surface == Surface.LINING
    assert lining.sum() > 500
    np.testing.assert_allclose(r[lining], expect[lining], atol=1e-4)
    bed = res.surface == Surface.BED
    assert bed.any()
    np.testing.assert_allclose(r[bed] * -cos_up[bed], 2.8 - FLOOR, atol=2e-4)
    assert (res.surface == Surface.RAIL).any()                          # rails occlude the bed


def test_time_stamps_and_noise(bore):
    scene, run = bore
    spec = ScannerSpec(points_per_profile=400, range_noise=0.01)
    t0 = run.scan_span[0]
    a = scan(scene, PoseInterpolator(run.trajectory), t0, t0 + 0.2, spec, np.random.default_rng(5))
    b = scan(scene, PoseInterpolator(run.trajectory), t0, t0 + 0.2, spec, np.random.default_rng(5))
    assert np.array_equal(a.p_body, b.p_body) and np.array_equal(a.intensity, b.intensity)
    assert (np.diff(a.gps_time) > 0).all()
    assert a.gps_time[0] >= t0 and a.gps_time[-1] < t0 + 0.2
    steps = np.unique(np.round(np.diff(a.gps_time) * spec.profile_rate * spec.points_per_profile, 6))
    assert steps.min() == pytest.approx(1.0, abs=1e-4)                 # one pulse period apart
    clean = scan(scene, PoseInterpolator(run.trajectory), t0, t0 + 0.2, ScannerSpec(
        points_per_profile=400, range_noise=0.0), np.random.default_rng(5))
    noise = np.linalg.norm(a.p_body, axis=1) - np.linalg.norm(clean.p_body, axis=1)
    assert 0.005 < np.std(noise) < 0.015
    assert a.intensity.dtype == np.uint16
    target = a.intensity[a.surface == Surface.RAIL].mean()
    assert target > a.intensity[a.surface == Surface.BED].mean()


def test_points_land_on_the_surface_when_georeferenced_with_the_truth(bore):
    scene, run = bore
    spec = ScannerSpec(points_per_profile=500, range_noise=0.0)
    t0 = run.scan_span[0]
    pose = PoseInterpolator(run.trajectory)
    res = scan(scene, pose, t0, t0 + 1.0, spec, np.random.default_rng(2))
    world = pose.body_to_world(res.gps_time, res.p_body) - np.asarray(scene.spec.alignment.origin)
    line = scene.centreline
    along = line.tangent(np.zeros(1))[0]
    s = world @ along                                                   # straight: chainage
    rel = world - line.point(s)
    uv = np.column_stack([rel @ line.right(s[:1])[0], rel[:, 2]])
    lining = res.surface == Surface.LINING
    dist = _distance_to_polyline(uv[lining][::20], scene.sections.profiles["circular"].uv)
    assert dist.max() < 2e-4
