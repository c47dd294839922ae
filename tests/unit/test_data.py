"""Data model and the attitude convention of SPEC.md."""

from __future__ import annotations

import numpy as np
import pytest

from railtraj.data import Keypoints, PointTile, Ties, Trajectory
from railtraj.errors import TrajectoryError
from railtraj.geo import attitude_from_direction, attitude_to_rotation, rotation_to_attitude


def _traj(rpy, t=(0.0, 1.0), xyz=((100.0, 200.0, 10.0), (110.0, 200.0, 10.0))):
    return Trajectory(np.array(t), np.array(xyz), np.array(rpy, dtype=float))


@pytest.mark.parametrize("rpy,p_body,expected", [
    ([0, 0, 0], [1, 0, 0], [0, 1, 0]),        # forward, heading north -> +northing
    ([0, 0, 90], [1, 0, 0], [1, 0, 0]),       # heading east -> +easting
    ([0, 0, 90], [0, 1, 0], [0, -1, 0]),      # right of an east-facing body is south
    ([0, 0, 0], [0, 0, 1], [0, 0, -1]),       # body z is down
    ([0, 10, 0], [1, 0, 0], [0, np.cos(np.radians(10)), np.sin(np.radians(10))]),  # nose up climbs
    ([10, 0, 0], [0, 1, 0], [np.cos(np.radians(10)), 0, -np.sin(np.radians(10))]),  # roll right: y dips
])
def test_spec_convention_worked_examples(rpy, p_body, expected):
    tr = _traj([rpy, rpy])
    w = tr.body_to_world(np.array([0.0]), np.array([p_body])) - tr.xyz[0]
    np.testing.assert_allclose(w[0], expected, atol=1e-12)


def test_world_body_round_trip_and_interpolation():
    tr = _traj([[1, 2, 350], [3, -2, 10]])            # heading crosses north
    t = np.array([0.25, 0.5, 0.75])
    p = np.random.default_rng(0).normal(size=(3, 3))
    np.testing.assert_allclose(tr.world_to_body(t, tr.body_to_world(t, p)), p, atol=1e-9)
    _, rot = tr.interpolate(np.array([0.5]))
    assert rotation_to_attitude(rot)[0, 2] == pytest.approx(0.0, abs=0.05) or \
        rotation_to_attitude(rot)[0, 2] == pytest.approx(360.0, abs=0.05)   # slerp goes the short way
    xyz, _ = tr.interpolate(np.array([0.5]))
    np.testing.assert_allclose(xyz[0], [105, 200, 10])


def test_attitude_round_trip():
    rpy = np.array([[1.5, -2.0, 123.0], [0.0, 0.0, 359.5]])
    np.testing.assert_allclose(rotation_to_attitude(attitude_to_rotation(rpy)), rpy, atol=1e-9)
    a = attitude_from_direction(np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.1]]))
    np.testing.assert_allclose(a[:, 2], [90.0, 0.0])
    assert a[1, 1] == pytest.approx(np.degrees(np.arctan(0.1)))


def test_trajectory_validation_messages():
    with pytest.raises(TrajectoryError, match="not strictly increasing at epoch 1"):
        _traj([[0, 0, 0], [0, 0, 0]], t=(1.0, 1.0))
    with pytest.raises(TrajectoryError, match="NaN"):
        _traj([[0, 0, np.nan], [0, 0, 0]])
    tr = _traj([[0, 0, 0], [0, 0, 0]])
    with pytest.raises(TrajectoryError, match="does not cover 1 of 2"):
        tr.check_covers(np.array([0.5, 2.0]))


def test_tile_keypoints_ties_shapes():
    tile = PointTile(np.zeros((4, 3)), np.arange(4.0), run_id="a", name="t")
    assert len(tile.subset(np.array([True, False, True, False]))) == 2
    with pytest.raises(ValueError):
        PointTile(np.zeros((4, 3)), np.arange(3.0))
    kp = Keypoints(np.zeros((2, 3)), np.zeros(2))
    assert kp.score.shape == (2,)
    t1 = Ties("a", "b", [1.0], [2.0], [[0, 0, 0]], [[1, 1, 1]], [1.0])
    merged = Ties.concat([t1, t1, Ties.empty("a", "c")])
    assert len(merged) == 1 and len(merged[0]) == 2
