"""OUT/trajectories/<run_id>.tum: read by evo, positions and orientations as in the CSV, and
evo's APE agrees with railtraj's own scoring against the truth (end to end: test_cli.py)."""

from __future__ import annotations

import numpy as np
import pytest
from evo.tools.file_interface import read_tum_trajectory_file

from railtraj.data import Trajectory
from railtraj.io.outputs import TUM_COLUMNS, body_to_map_quaternions, write_trajectory_tum
from railtraj.io.trajectory_csv import read_trajectory_csv, write_trajectory_csv
from railtraj.sim.score import score_trajectories


def _random_attitudes(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-30, 30, n), rng.uniform(-30, 30, n),
                            rng.uniform(0, 360, n)])


def test_evo_reads_the_csv_epochs_and_positions(tmp_path, make_trajectory):
    traj = make_trajectory(n=300, seed=1, heading_deg=123.0)
    write_trajectory_csv(tmp_path / "a.csv", traj)
    write_trajectory_tum(tmp_path / "a.tum", traj)
    assert (tmp_path / "a.tum").read_text().splitlines()[0] == "# " + " ".join(TUM_COLUMNS)
    tum = read_tum_trajectory_file(str(tmp_path / "a.tum"))
    csv = read_trajectory_csv(tmp_path / "a.csv")
    np.testing.assert_allclose(tum.timestamps, csv.time, rtol=0, atol=1e-9)
    np.testing.assert_allclose(tum.positions_xyz, csv.xyz, rtol=0, atol=1e-6)
    quat = tum.orientations_quat_wxyz
    np.testing.assert_allclose(np.linalg.norm(quat, axis=1), 1.0, atol=1e-8)
    assert (quat[:, 0] >= 0).all()


@pytest.mark.parametrize(("rpy", "qxyzw"), [
    ((0.0, 0.0, 90.0), (1.0, 0.0, 0.0, 0.0)),            # facing east: 180 deg about east
    ((0.0, 0.0, 0.0), (0.5 ** 0.5, 0.5 ** 0.5, 0.0, 0.0)),  # facing north: 180 deg about NE
    ((0.0, 0.0, 180.0), (0.5 ** 0.5, -(0.5 ** 0.5), 0.0, 0.0)),
])
def test_known_headings_give_the_documented_quaternion(tmp_path, rpy, qxyzw):
    traj = Trajectory(time=np.array([1.0, 2.0]), xyz=np.array([[500000.0, 200000.0, 10.0]] * 2),
                      rpy=np.array([rpy] * 2))
    write_trajectory_tum(tmp_path / "k.tum", traj)
    line = (tmp_path / "k.tum").read_text().splitlines()[1].split()
    np.testing.assert_allclose([float(v) for v in line[4:]], qxyzw, atol=1e-9)
    rot = read_tum_trajectory_file(str(tmp_path / "k.tum")).poses_se3[0][:3, :3]
    if rpy[2] == 90.0:   # docs/formats.md worked example: forward -> east, right -> south
        np.testing.assert_allclose(rot @ [1, 0, 0], [1, 0, 0], atol=1e-9)
        np.testing.assert_allclose(rot @ [0, 1, 0], [0, -1, 0], atol=1e-9)
        np.testing.assert_allclose(rot @ [0, 0, 1], [0, 0, -1], atol=1e-9)


def test_evo_orientation_is_body_to_map_for_any_attitude(tmp_path):
    """Body x (forward) and y (right) axes, by evo, against closed forms of SPEC's convention."""
    n = 200
    rpy = _random_attitudes(n, seed=2)
    traj = Trajectory(time=np.arange(n, dtype=float), xyz=np.zeros((n, 3)), rpy=rpy)
    write_trajectory_tum(tmp_path / "r.tum", traj)
    rot = np.array(read_tum_trajectory_file(str(tmp_path / "r.tum")).poses_se3)[:, :3, :3]
    r, p, h = np.radians(rpy).T
    forward = np.column_stack([np.sin(h) * np.cos(p), np.cos(h) * np.cos(p), np.sin(p)])
    right_ned = np.column_stack([np.sin(r) * np.sin(p) * np.cos(h) - np.cos(r) * np.sin(h),
                                 np.sin(r) * np.sin(p) * np.sin(h) + np.cos(r) * np.cos(h),
                                 np.sin(r) * np.cos(p)])
    right = np.column_stack([right_ned[:, 1], right_ned[:, 0], -right_ned[:, 2]])
    np.testing.assert_allclose(rot[:, :, 0], forward, atol=1e-8)
    np.testing.assert_allclose(rot[:, :, 1], right, atol=1e-8)


def test_quaternions_are_vectorised_and_match_single_epochs():
    rpy = _random_attitudes(50, seed=3)
    many = body_to_map_quaternions(rpy)
    one = np.vstack([body_to_map_quaternions(rpy[i:i + 1]) for i in range(0, 50, 7)])
    np.testing.assert_allclose(many[::7], one, atol=1e-12)


def test_evo_ape_agrees_with_railtraj_scoring(tmp_path, make_trajectory, evo_ape):
    truth = make_trajectory(n=2000, seed=4, run_id="a", speed=20.0)
    t = (truth.time - truth.time[0]) / np.ptp(truth.time)
    drift = np.column_stack([0.4 * t ** 2, -0.2 * np.sin(3 * t), 0.05 * t])
    rng = np.random.default_rng(5)
    keep = slice(10, -25)   # the estimate covers only part of the truth
    est = Trajectory(time=truth.time[keep], xyz=(truth.xyz + drift + rng.normal(0, 0.01, drift.shape))[keep],
                     rpy=truth.rpy[keep], run_id="a")
    write_trajectory_tum(tmp_path / "truth.tum", truth)
    write_trajectory_tum(tmp_path / "est.tum", est)
    rmse, worst, n = evo_ape(tmp_path / "truth.tum", tmp_path / "est.tum")
    ours = score_trajectories({"a": truth}, {"a": est})["runs"]["a"]
    assert n == ours["n"] == len(est)
    assert rmse > 0.1   # a real error, so agreeing to 1 mm means something
    assert abs(rmse - ours["rms_3d"]) < 1e-3 and abs(worst - ours["max_3d"]) < 1e-3
