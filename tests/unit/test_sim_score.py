"""Scoring against the truth: trajectory errors, consistency and cloud-to-cloud distances."""

from __future__ import annotations

import json

import numpy as np
import pytest

from railtraj.data import Trajectory
from railtraj.sim.score import c2c, chainage_from_truth, score_trajectories


def _run(run_id: str, direction: int, offset_n: float = 0.0, n: int = 3001) -> Trajectory:
    t = 300000.0 + np.arange(n) / 100.0
    s = 10.0 * (t - t[0]) if direction > 0 else 300.0 - 10.0 * (t - t[0])
    xyz = np.column_stack([530000.0 + s, np.full(n, 180000.0 + offset_n), np.full(n, 10.0)])
    rpy = np.column_stack([np.zeros(n), np.zeros(n), np.full(n, 90.0 if direction > 0 else 270.0)])
    return Trajectory(t, xyz, rpy, run_id=run_id)


def _shifted(traj: Trajectory, err: np.ndarray) -> Trajectory:
    return traj.with_positions(traj.xyz + err)


@pytest.fixture()
def truth():
    return {"a": _run("a", 1), "b": _run("b", -1, offset_n=4.0)}


def test_perfect_correction_scores_zero(truth):
    score = score_trajectories(truth, dict(truth))
    assert score["overall"]["rms_3d"] == pytest.approx(0.0, abs=1e-9)
    assert score["consistency"]["a~b"]["max_3d"] == pytest.approx(0.0, abs=1e-9)
    json.dumps(score)                                                     # JSON-serialisable


def test_no_correction_scores_the_drift(truth):
    s_a = 10.0 * np.arange(3001) / 100.0
    bump = np.exp(-(((s_a - 150.0) / 50.0) ** 2))                      # 1 m peak at chainage 150
    err_a = np.column_stack([bump, 0 * bump, 0.1 * bump])
    err_b = np.column_stack([0 * bump, -0.5 * bump[::-1], 0 * bump])   # b drives the other way
    est = {"a": _shifted(truth["a"], err_a), "b": _shifted(truth["b"], err_b)}
    chain = {"a": s_a, "b": 300.0 - s_a}
    score = score_trajectories(truth, est, chain, bin_m=50.0)
    a = score["runs"]["a"]
    assert a["max_h"] == pytest.approx(1.0, abs=1e-3) and a["max_v"] == pytest.approx(0.1, abs=1e-3)
    assert a["rms_h"] == pytest.approx(np.sqrt(np.mean(bump ** 2)), rel=1e-3)
    bins = {b["chainage"]: b for b in a["bins"]}
    assert bins[175.0]["max_h"] > 0.9 > 0.1 > bins[25.0]["max_h"]
    # at the same chainage the runs disagree by (1, 0.5) m horizontally at the peak
    assert score["consistency"]["a~b"]["max_h"] == pytest.approx(np.hypot(1.0, 0.5), abs=2e-3)
    # derived chainage gives the same consistency figure
    derived = score_trajectories(truth, est)
    assert derived["consistency"]["a~b"]["max_h"] == pytest.approx(np.hypot(1.0, 0.5), abs=5e-3)


def test_chainage_from_truth_is_common(truth):
    ch = chainage_from_truth(truth)
    np.testing.assert_allclose(ch["a"], 10.0 * np.arange(3001) / 100.0, atol=1e-9)
    np.testing.assert_allclose(ch["b"], 300.0 - ch["a"], atol=0.06)


def _plane_cloud(rng, n, noise=0.0):
    xy = rng.uniform(0, 10, (n, 2))
    return np.column_stack([xy, noise * rng.standard_normal(n)]) + [530000.0, 180000.0, 10.0]


def test_c2c_identical_offset_and_disjoint():
    rng = np.random.default_rng(0)
    a, b = _plane_cloud(rng, 20000), _plane_cloud(rng, 40000)
    same = c2c(a, b)
    assert same["median"] < 1e-9 and same["overlap"] == 1.0
    assert 0 < same["nn_median"] < 0.05                                 # plain NN sees the spacing
    up = c2c(a + [0, 0, 0.1], b)
    assert up["median"] == pytest.approx(0.1, abs=1e-6) and up["p95"] == pytest.approx(0.1, abs=1e-6)
    sideways = c2c(a + [0.5, 0, 0], b)                                   # along the plane: invisible
    assert sideways["median"] < 1e-9
    far = c2c(a + [0, 0, 5.0], b, max_dist=1.0)
    assert far["n"] == 0 and far["overlap"] == 0.0
    noisy = c2c(_plane_cloud(rng, 20000, 0.005), _plane_cloud(rng, 40000, 0.005))
    assert 0.002 < noisy["median"] < 0.006
