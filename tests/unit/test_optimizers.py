"""Known-answer tests for the optimizers."""

from __future__ import annotations

import numpy as np

from railtraj.data import Ties, Trajectory
from railtraj.plugins import registry


def _straight_run(run_id: str, sd: float, offset=(0.0, 0.0, 0.0), t0: float = 1000.0) -> Trajectory:
    t = t0 + np.arange(0, 60, 0.01)
    xyz = np.column_stack([530000 + 10 * (t - t0), np.full_like(t, 180000.0), np.full_like(t, 10.0)])
    xyz = xyz + np.asarray(offset)
    rpy = np.tile([0.0, 0.0, 90.0], (len(t), 1))
    return Trajectory(t, xyz, rpy, np.full((len(t), 3), sd), run_id=run_id)


def _ties(a: Trajectory, b: Trajectory, n: int = 200, seed: int = 0) -> Ties:
    """Features along the track seen by both runs; b's copy carries b's georeferencing error."""
    rng = np.random.default_rng(seed)
    s = np.sort(rng.uniform(50, 550, n))                     # chainage of the features
    feature = np.column_stack([530000 + s, 180000 + rng.uniform(-3, 3, n), 10 + rng.uniform(-1, 4, n)])
    ta, tb = a.time[0] + s / 10, b.time[0] + s / 10
    err_b = b.interpolate(tb)[0] - (530000 + 10 * (tb - b.time[0]))[:, None] * [1, 0, 0] - [0, 180000, 10]
    xb = feature + err_b
    return Ties(a.run_id, b.run_id, ta, tb, feature, xb, np.ones(n))


def test_gtsam_moves_the_uncertain_run_onto_the_certain_one():
    a = _straight_run("a", sd=0.01)
    b = _straight_run("b", sd=1.0, offset=(0.0, 0.30, -0.10), t0=5000.0)
    ties = _ties(a, b)
    out = registry().create("optimizer", "gtsam", {}).optimize({"a": a, "b": b}, [ties], [])
    # run a hardly moves; run b's offset is removed where the ties are
    assert np.abs(out["a"].xyz - a.xyz).max() < 0.005
    mid = (b.time > b.time[0] + 10) & (b.time < b.time[0] + 50)
    np.testing.assert_allclose(out["b"].xyz[mid] - b.xyz[mid], np.tile([0, -0.30, 0.10], (mid.sum(), 1)), atol=0.01)
    # the posterior sd of b shrinks from 1 m to centimetres where it is tied
    assert out["b"].sd[mid].max() < 0.05
    np.testing.assert_array_equal(out["b"].time, b.time)


def test_gtsam_ignores_a_gross_outlier_tie():
    a = _straight_run("a", sd=0.01)
    b = _straight_run("b", sd=1.0, offset=(0.0, 0.20, 0.0), t0=5000.0)
    ties = _ties(a, b)
    xb = ties.xyz_b.copy()
    xb[100] += [0.0, 2.0, 0.0]                       # one wrong match, 2 m off
    bad = Ties("a", "b", ties.time_a, ties.time_b, ties.xyz_a, xb, ties.weight)
    out = registry().create("optimizer", "gtsam", {}).optimize({"a": a, "b": b}, [bad], [])
    k = np.searchsorted(b.time, ties.time_b[100])
    assert abs((out["b"].xyz[k] - b.xyz[k])[1] + 0.20) < 0.03


def test_identity_returns_input():
    a = _straight_run("a", sd=0.01)
    out = registry().create("optimizer", "identity", {}).optimize({"a": a}, [], [])
    assert out["a"] is a


def test_gtsam_uses_degenerate_offsets_only_across_and_up():
    from railtraj.data import TileOffset

    a = _straight_run("a", sd=0.01)
    b = _straight_run("b", sd=1.0, offset=(0.5, 0.30, -0.10), t0=5000.0)   # x is along the track
    offsets = []
    for s in np.arange(50, 550, 25.0):                                     # one tile pair every 25 m
        ta, tb = a.time[0] + s / 10, b.time[0] + s / 10
        # the matcher saw the true across/up offset but could not tell along-track (alias 1.5 m off)
        d = np.array([-0.5 + 1.5, -0.30, 0.10])
        cov = np.diag([3.0**2, 0.005**2, 0.005**2])
        offsets.append(TileOffset("a", "b", f"t{s}", f"t{s}", d=d, cov=cov, status="degenerate",
                                  info={"time_a": ta, "time_b": tb}))
    opt = registry().create("optimizer", "gtsam", {})
    out = opt.optimize({"a": a, "b": b}, [], offsets)
    mid = (b.time > b.time[0] + 10) & (b.time < b.time[0] + 50)
    corr = out["b"].xyz[mid] - b.xyz[mid]
    np.testing.assert_allclose(corr[:, 1:], np.tile([-0.30, 0.10], (mid.sum(), 1)), atol=0.01)
    assert np.abs(corr[:, 0]).max() < 0.3        # along-track: the alias is not believed
    assert out["b"].sd[mid, 1].max() < 0.05 and out["b"].sd[mid, 0].min() > 3 * out["b"].sd[mid, 1].max()
    off = registry().create("optimizer", "gtsam", {"use_weak_offsets": False}).optimize({"a": a, "b": b}, [], offsets)
    np.testing.assert_array_equal(off["b"].xyz, b.xyz)
