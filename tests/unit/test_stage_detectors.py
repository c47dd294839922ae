"""The iss and harris3d detectors on a seeded tunnel tile in survey-grid coordinates."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from railtraj.builtins.iss import PRESETS
from railtraj.data import PointTile
from railtraj.matching.synthetic import placed, rotation_z, second_acquisition, tunnel_tile
from railtraj.plugins import registry

SHIFT = np.array([0.5, 1.5, 0.1])


@pytest.fixture(scope="module")
def pair():
    a = tunnel_tile(0, 12, density=800, seed=0)
    b = second_acquisition(a, SHIFT, seed=1)
    return placed(a), placed(b), rotation_z(30) @ SHIFT


@pytest.mark.parametrize("name,options", [("iss", {}), ("iss", PRESETS["tunnel"]), ("harris3d", {})])
def test_keypoints_repeat_between_acquisitions(pair, name, options):
    a, b, shift = pair
    det = registry().create("detector", name, options)
    ka, kb = det.detect(a), det.detect(b)
    assert len(ka) >= 30 and len(kb) >= 30
    dist, _ = cKDTree(ka.xyz).query(kb.xyz - shift)
    assert np.mean(dist < 0.25) > 0.4  # the prototype measured 50-63 % within 0.25 m


@pytest.mark.parametrize("name", ["iss", "harris3d"])
def test_keypoint_time_is_that_of_a_raw_point_next_to_it(pair, name):
    a, _, _ = pair
    kp = registry().create("detector", name, {}).detect(a)
    dist, idx = cKDTree(a.xyz).query(kp.xyz)
    assert dist.max() < 0.1  # a keypoint is a 10 cm voxel centroid
    raw_times = set(a.gps_time.tolist())
    assert all(t in raw_times for t in kp.gps_time.tolist())  # measured, not averaged
    # the train moves 5 m/s: a keypoint's time is that of the points around it
    assert np.abs(kp.gps_time - a.gps_time[idx]).max() < 0.1 / 5 + 0.01


@pytest.mark.parametrize("name,options", [("iss", {"non_max_radius": 0.3, "gamma_21": 0.8, "gamma_32": 0.8}),
                                          ("harris3d", {"threshold": 1e-4})])
def test_max_keypoints_keeps_the_most_salient(pair, name, options):
    a, _, _ = pair
    reg = registry()
    every = reg.create("detector", name, dict(options, max_keypoints=0)).detect(a)
    best = reg.create("detector", name, dict(options, max_keypoints=40)).detect(a)
    assert len(every) > 40 and len(best) == 40
    assert np.all(np.diff(best.score) <= 0)
    np.testing.assert_allclose(best.score, np.sort(every.score)[::-1][:40])


def test_harris_finds_box_corners_not_walls():
    rng = np.random.default_rng(2)
    n = 40000
    wall = np.c_[rng.uniform(0, 4, n), np.zeros(n), rng.uniform(0, 3, n)]
    faces = []
    for axis in range(3):  # a 0.5 m box standing out of the wall at x 1.5..2, z 1..1.5
        for side in (0.0, 0.5):
            p = rng.uniform(0, 0.5, (3000, 3))
            p[:, axis] = side
            faces.append(p + [1.5, 0.0, 1.0])
    xyz = np.vstack([wall[~((wall[:, 0] > 1.5) & (wall[:, 0] < 2) & (wall[:, 2] > 1) & (wall[:, 2] < 1.5))]]
                    + faces) + rng.normal(0, 0.005, (1, 3))
    tile = PointTile(xyz, np.arange(len(xyz)) * 1e-5)
    kp = registry().create("detector", "harris3d", {"max_keypoints": 8}).detect(tile)
    corners = np.array([[x, y, z] for x in (1.5, 2.0) for y in (0.0, 0.5) for z in (1.0, 1.5)])
    dist, _ = cKDTree(corners).query(kp.xyz)
    assert len(kp) >= 4 and np.median(dist) < 0.15


@pytest.mark.parametrize("name", ["iss", "harris3d"])
def test_empty_and_tiny_tiles_give_no_keypoints(name):
    det = registry().create("detector", name, {})
    assert len(det.detect(PointTile(np.zeros((0, 3)), np.zeros(0)))) == 0
    assert len(det.detect(PointTile(np.random.default_rng(0).random((3, 3)), np.zeros(3)))) == 0
