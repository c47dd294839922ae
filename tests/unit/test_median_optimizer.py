"""Known-answer tests for the ``median`` optimizer (the thesis' baseline)."""

from __future__ import annotations

import numpy as np
import pytest

from railtraj.builtins.median_optimizer import MedianOptimizer
from railtraj.data import ControlObservations, Ties, TileOffset, Trajectory
from railtraj.errors import ConfigError
from railtraj.plugins import registry

OFFSET = np.array([0.0, 0.30, -0.10])   # georeferencing error of run b (b sees features here)


def _straight_run(run_id: str, sd: float | None, offset=(0.0, 0.0, 0.0), t0: float = 1000.0) -> Trajectory:
    """60 s along the easting at 10 m/s, with a constant georeferencing error ``offset``."""
    t = t0 + np.arange(0, 60, 0.01)
    xyz = np.column_stack([530000 + 10 * (t - t0), np.full_like(t, 180000.0), np.full_like(t, 10.0)])
    rpy = np.tile([0.0, 0.0, 90.0], (len(t), 1))
    sds = None if sd is None else np.full((len(t), 3), sd)
    return Trajectory(t, xyz + np.asarray(offset), rpy, sds, run_id=run_id)


def _ties(a: Trajectory, b: Trajectory, chainage: np.ndarray, noise: float = 0.0, seed: int = 0) -> Ties:
    """Features at ``chainage`` (m) seen by both runs; b's copy is off by OFFSET (plus noise)."""
    rng = np.random.default_rng(seed)
    n = len(chainage)
    feature = np.column_stack([530000 + chainage, 180000 + rng.uniform(-3, 3, n), 10 + rng.uniform(-1, 4, n)])
    xb = feature + OFFSET + rng.normal(0.0, noise, (n, 3))
    return Ties(a.run_id, b.run_id, a.time[0] + chainage / 10, b.time[0] + chainage / 10, feature, xb, np.ones(n))


def _runs(sd_b: float | None = 1.0) -> tuple[Trajectory, Trajectory]:
    return _straight_run("a", 0.01), _straight_run("b", sd_b, OFFSET, t0=5000.0)


def _optimize(trajs: dict[str, Trajectory], ties: list[Ties], offsets=(), control=None, **options):
    opt = registry().create("optimizer", "median", options)
    return opt.optimize(trajs, ties, list(offsets), control=control), opt


def _tied(traj: Trajectory, t: Ties, side: str = "b") -> np.ndarray:
    times = t.time_b if side == "b" else t.time_a
    return (traj.time >= times.min()) & (traj.time <= times.max())


CHAINAGE = np.sort(np.random.default_rng(1).uniform(50, 550, 200))


def test_registry_builds_it_with_defaults_and_rejects_bad_options():
    opt = registry().create("optimizer", "median", {})
    assert isinstance(opt, MedianOptimizer)
    assert (opt.config.window, opt.config.weighting, opt.config.taper_s) == (15, "sd", 10.0)
    with pytest.raises(ConfigError):
        MedianOptimizer(window=4)
    with pytest.raises(ConfigError):
        MedianOptimizer(weighting="mean")


def test_uncertain_run_moves_onto_the_certain_one():
    a, b = _runs()
    c = _straight_run("c", 0.05, t0=9000.0)                  # not tied: must come back untouched
    ties = _ties(a, b, CHAINAGE)
    out, opt = _optimize({"a": a, "b": b, "c": c}, [ties])
    tied = _tied(b, ties)
    np.testing.assert_allclose(out["b"].xyz[tied] - b.xyz[tied], np.tile(-OFFSET, (tied.sum(), 1)), atol=0.005)
    assert np.abs(out["a"].xyz - a.xyz).max() < 0.001        # weight 1/0.01^2 against 1/1^2
    assert out["c"] is c
    np.testing.assert_array_equal(out["b"].time, b.time)
    np.testing.assert_array_equal(out["b"].rpy, b.rpy)
    assert opt.diagnostics["optimizer"] == "median"
    assert opt.diagnostics["samples"] == {"a": 200, "b": 200, "c": 0}
    assert opt.diagnostics["notes"] == []


def test_equal_weighting_splits_the_offset_in_half():
    a, b = _runs()
    ties = _ties(a, b, CHAINAGE)
    out, _ = _optimize({"a": a, "b": b}, [ties], weighting="equal")
    ta, tb = _tied(a, ties, "a"), _tied(b, ties)
    np.testing.assert_allclose(out["a"].xyz[ta] - a.xyz[ta], np.tile(OFFSET / 2, (ta.sum(), 1)), atol=1e-6)
    np.testing.assert_allclose(out["b"].xyz[tb] - b.xyz[tb], np.tile(-OFFSET / 2, (tb.sum(), 1)), atol=1e-6)


def test_a_run_without_sd_gets_the_plain_midpoint():
    a, b = _runs(sd_b=None)
    ties = _ties(a, b, CHAINAGE)
    out, _ = _optimize({"a": a, "b": b}, [ties])
    tb = _tied(b, ties)
    np.testing.assert_allclose(out["b"].xyz[tb] - b.xyz[tb], np.tile(-OFFSET / 2, (tb.sum(), 1)), atol=1e-6)


def test_isolated_gross_outliers_do_not_move_the_result():
    a, b = _runs()
    ties = _ties(a, b, CHAINAGE, noise=0.005)
    xb = ties.xyz_b.copy()
    bad_rows = [30, 90, 150]
    xb[bad_rows] += [0.0, 2.0, 0.0]                          # three wrong matches, 2 m off
    bad = Ties("a", "b", ties.time_a, ties.time_b, ties.xyz_a, xb, ties.weight)
    clean, _ = _optimize({"a": a, "b": b}, [ties])
    dirty, _ = _optimize({"a": a, "b": b}, [bad])
    # a running mean over 15 samples would move b by 2 m / 15 = 13 cm around each outlier
    assert np.abs(dirty["b"].xyz - clean["b"].xyz).max() < 0.005
    assert np.abs(dirty["a"].xyz - clean["a"].xyz).max() < 0.005


def test_correction_tapers_to_zero_beyond_the_ties():
    a, b = _runs()
    ties = _ties(a, b, np.linspace(200, 400, 101))            # tied from 20 s to 40 s into run b
    out, _ = _optimize({"a": a, "b": b}, [ties])               # taper_s = 10
    rel = b.time - b.time[0]
    corr = out["b"].xyz - b.xyz
    inside = (rel >= 20) & (rel <= 40)
    np.testing.assert_allclose(corr[inside], np.tile(-OFFSET, (inside.sum(), 1)), atol=0.001)
    for k in (np.searchsorted(rel, 15.0), np.searchsorted(rel, 45.0)):    # half way down the taper
        np.testing.assert_allclose(corr[k], -OFFSET / 2, atol=0.001)
    far = (rel <= 10 - 1e-6) | (rel >= 50 + 1e-6)
    assert far.sum() > 1000
    np.testing.assert_array_equal(out["b"].xyz[far], b.xyz[far])
    np.testing.assert_array_equal(out["b"].sd[far], b.sd[far])   # untied: the input sd stays


def test_no_ties_returns_the_input_and_says_so():
    a, b = _runs()
    out, opt = _optimize({"a": a, "b": b}, [Ties.empty("a", "b")])
    assert out["a"] is a and out["b"] is b
    assert opt.diagnostics["samples"] == {"a": 0, "b": 0}
    assert any("no ties" in n for n in opt.diagnostics["notes"])


def test_posterior_sd_comes_from_the_scatter_of_the_ties():
    a, b = _runs()
    ties = _ties(a, b, CHAINAGE, noise=0.02)                  # 2 cm noise per axis on b's copies
    out, _ = _optimize({"a": a, "b": b}, [ties])
    tb, ta = _tied(b, ties), _tied(a, ties, "a")
    sd_b = out["b"].sd[tb]
    assert np.isfinite(out["b"].sd).all() and (out["b"].sd > 0).all()
    assert sd_b.max() < 1.0                                   # the input sd of b was 1 m
    assert 0.012 < np.median(sd_b) < 0.03                     # ~ the 2 cm scatter of one tie
    np.testing.assert_array_equal(out["a"].sd[ta], 0.005)     # a barely moves: its scatter is floored


def test_unused_weak_offsets_and_control_are_noted():
    a, b = _runs()
    ties = _ties(a, b, CHAINAGE)
    offsets = [TileOffset("a", "b", "t1", "t1", status="ok", ties=ties),
               TileOffset("a", "b", "t2", "t2", status="degenerate"),
               TileOffset("a", "b", "t3", "t3", status="ambiguous")]
    control = ControlObservations(["CP1"], ["a"], [1010.0], [[530100.0, 180000.0, 10.0]],
                                  [[530100.0, 180000.0, 10.0]], [[0.002] * 3], [[0.005] * 3], ["picked"])
    _, opt = _optimize({"a": a, "b": b}, [ties], offsets, control)
    notes = opt.diagnostics["notes"]
    assert len(notes) == 2
    assert any("2 tile pairs" in n and "degenerate" in n and "ambiguous" in n for n in notes)
    assert any("1 control" in n for n in notes)
    resolved = offsets + [TileOffset("a", "b", "t4", "t4", status="ok")]  # ok, resolved without ties
    _, opt = _optimize({"a": a, "b": b}, [ties], resolved, None)
    assert any("3 tile pairs" in n and "ok without ties" in n for n in opt.diagnostics["notes"])
