"""railtraj.georef: the fast pose interpolation matches Trajectory, re-georeferencing round-trips."""

from __future__ import annotations

import numpy as np
import pytest

from railtraj.data import PointTile, Trajectory
from railtraj.errors import TrajectoryError
from railtraj.georef import PoseInterpolator, regeoreference


def _wobbly(seed: int = 0, n: int = 2000) -> Trajectory:
    rng = np.random.default_rng(seed)
    t = 300000.0 + np.arange(n) * 0.005
    u = t - t[0]
    xyz = np.column_stack([530000.0 + 10 * u, 180000.0 + np.sin(u), 10.0 + 0.1 * u])
    rpy = np.column_stack([0.3 * np.sin(3 * u), 1.0 + 0.2 * np.cos(u), np.mod(355.0 + 8.0 * u, 360.0)])
    rpy += rng.normal(0, 0.01, rpy.shape)
    return Trajectory(t, xyz, rpy, run_id="w")


def test_matches_trajectory_methods():
    traj = _wobbly()
    rng = np.random.default_rng(1)
    t = np.sort(rng.uniform(traj.time[0], traj.time[-1], 50000))
    t[:3] = traj.time[[0, 10, -1]]                                      # exactly on epochs too
    p = rng.normal(0, 5, (len(t), 3))
    pose = PoseInterpolator(traj)
    np.testing.assert_allclose(pose.body_to_world(t, p), traj.body_to_world(t, p), atol=1e-8)
    w = traj.body_to_world(t, p)
    np.testing.assert_allclose(pose.world_to_body(t, w), p, atol=1e-8)
    np.testing.assert_allclose(pose.position(t), traj.interpolate(t)[0], atol=1e-8)
    mats, rate = pose.matrices(t[:100])
    np.testing.assert_allclose(mats, traj.pose_at(t[:100])[1], atol=1e-12)
    assert rate.shape == (100, 3)


def test_refuses_times_outside_the_trajectory():
    traj = _wobbly()
    with pytest.raises(TrajectoryError):
        PoseInterpolator(traj).body_to_world(np.array([traj.time[-1] + 1.0]), np.zeros((1, 3)))


def test_regeoreference_moves_points_with_the_trajectory():
    truth = _wobbly(0)
    shift = np.array([0.4, -0.3, 0.05])
    drifted = truth.with_positions(truth.xyz + shift)
    rng = np.random.default_rng(2)
    t = np.sort(rng.uniform(truth.time[0], truth.time[-1], 20000))
    body = rng.normal(0, 5, (len(t), 3))
    tile = PointTile(drifted.body_to_world(t, body), t, np.zeros(len(t), np.uint16), "w", "x.laz")
    back = regeoreference(tile, drifted, truth)
    np.testing.assert_allclose(back.xyz, truth.body_to_world(t, body), atol=1e-8)
    np.testing.assert_allclose(back.xyz - tile.xyz, np.broadcast_to(-shift, back.xyz.shape), atol=1e-8)
    assert back.name == "x.laz" and np.array_equal(back.gps_time, t)
    same = regeoreference(tile, drifted, drifted)
    np.testing.assert_allclose(same.xyz, tile.xyz, atol=1e-8)
    assert len(regeoreference(tile.subset(np.zeros(len(t), bool)), drifted, truth)) == 0
