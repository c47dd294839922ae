"""A weak pair's along-track direction comes from the trajectory, grade included."""

from __future__ import annotations

import numpy as np

from railtraj.adjust.offsets import offset_covariance
from railtraj.alongtrack import AlongTrackOptions, resolve_along_track
from railtraj.data import Ties, TileOffset, Trajectory
from railtraj.track_direction import (
    fitted_direction_note,
    on_travel_direction,
    pair_travel,
    rotation_between,
)

HEADING = np.radians(35.0)  # a tunnel crossing the tiles diagonally
GRADE = 0.02  # 2 % down-grade: 20 mm a metre


def _tunnel_direction() -> np.ndarray:
    v = np.array([np.cos(HEADING), np.sin(HEADING), -GRADE])
    return v / np.linalg.norm(v)


def _run(run_id: str, t0: float) -> Trajectory:
    t = t0 + np.arange(0.0, 40.0, 0.05)
    xyz = np.array([530000.0, 180000.0, 10.0]) + 10.0 * (t - t0)[:, None] * _tunnel_direction()
    rpy = np.tile([0.0, 0.0, 90.0 - np.degrees(HEADING)], (len(t), 1))
    return Trajectory(t, xyz, rpy, np.full((len(t), 3), 0.3), run_id=run_id)


def _aliased_pair(fitted_off_deg: float) -> tuple[TileOffset, np.ndarray]:
    """An ``ambiguous`` pair whose matcher sits on the 3.0 m alias, with a levelled fitted axis
    ``fitted_off_deg`` off the tunnel (as 2 cm range noise left it), and the true offset."""
    h = HEADING + np.radians(fitted_off_deg)
    fitted = np.array([np.cos(h), np.sin(h), 0.0])
    d_true = np.array([0.40, -0.25, 0.05])
    d = d_true + 3.0 * _tunnel_direction()
    fit_cov = np.diag([0.008, 0.002, 0.002]) ** 2  # along, across, up in the fitted frame
    frame = np.vstack([fitted, np.cross([0.0, 0.0, 1.0], fitted), [0.0, 0.0, 1.0]])
    fit_cov = frame.T @ fit_cov @ frame
    cov = fit_cov + 3.0**2 * np.outer(fitted, fitted)
    info = {"time_a": 300010.0, "time_b": 300610.0,
            "piecewise": {"axis": fitted.tolist(), "gradient": [0.0, 0.0, 0.0], "fit_cov": fit_cov.tolist(),
                          "ref_point": [530080.0, 180057.0, 8.0]}}
    o = TileOffset("run_a", "run_b", "t", "t", d=d, cov=cov, status="ambiguous",
                   ties=Ties.empty("run_a", "run_b"), info=info)
    return o, d_true


def _mahalanobis(o: TileOffset, d_true: np.ndarray) -> float:
    e = o.d - d_true
    return float(np.sqrt(e @ np.linalg.solve(offset_covariance(o), e)))


def test_an_alias_is_no_error_across_or_up_once_the_pair_lies_along_its_trajectory():
    trajectories = {"run_a": _run("run_a", 300000.0), "run_b": _run("run_b", 300600.0)}
    o, d_true = _aliased_pair(fitted_off_deg=1.5)
    # along the fitted, levelled axis the 3 m alias leaves 8 cm across and 6 cm in height that
    # the pair claims to 2 mm
    assert _mahalanobis(o, d_true) > 20
    turned = on_travel_direction(o, trajectories)
    assert np.allclose(turned.info["piecewise"]["axis"], _tunnel_direction(), atol=1e-6)
    assert np.allclose(turned.d, o.d)  # the measurement itself is untouched
    assert _mahalanobis(turned, d_true) < 1.0
    # across and up it stays as sharp as it was
    left = np.cross(_tunnel_direction(), [0.0, 0.0, 1.0])
    left /= np.linalg.norm(left)
    assert np.sqrt(left @ offset_covariance(turned) @ left) < 0.003


def test_the_along_track_stage_turns_every_pair_onto_its_run_direction():
    trajectories = {"run_a": _run("run_a", 300000.0), "run_b": _run("run_b", 300600.0)}
    o, d_true = _aliased_pair(fitted_off_deg=-1.2)
    out, _ = resolve_along_track([o], trajectories, AlongTrackOptions())
    assert _mahalanobis(out[0], d_true) < 1.0


def test_a_pair_without_observation_times_keeps_its_fitted_axis():
    o, _ = _aliased_pair(fitted_off_deg=1.5)
    o = TileOffset(o.run_a, o.run_b, o.tile_a, o.tile_b, o.d, o.cov, status=o.status, ties=o.ties,
                   info=dict(o.info, time_a=np.nan))
    assert on_travel_direction(o, {"run_a": _run("run_a", 300000.0)}) is o


def test_rotation_between_takes_one_direction_onto_the_other():
    u = np.array([1.0, 0.0, 0.0])
    v = _tunnel_direction()
    R = rotation_between(u, v)
    assert np.allclose(R @ u, v)
    assert np.allclose(R @ R.T, np.eye(3))


def test_a_pair_where_the_train_stood_still_keeps_its_fitted_axis_and_says_so():
    standing = _run("run_a", 300000.0)
    standing = Trajectory(standing.time, np.repeat(standing.xyz[:1], len(standing.time), axis=0), standing.rpy,
                          standing.sd, run_id="run_a")
    o, _ = _aliased_pair(fitted_off_deg=1.5)
    kept = on_travel_direction(o, {"run_a": standing})
    assert kept is o
    note = fitted_direction_note([kept, on_travel_direction(o, {"run_a": _run("run_a", 300000.0)})])
    assert note is not None and note.startswith("1 tile pair(s) keep")
    assert fitted_direction_note([on_travel_direction(o, {"run_a": _run("run_a", 300000.0)})]) is None


def test_a_pairs_direction_of_travel_is_where_its_run_crosses_the_pairs_box():
    """Levelled (the grade left out: the matcher's track direction is horizontal), either way
    along the track, and None where the run never enters the box or stands still in it."""
    run = _run("run_a", 300000.0)  # 400 m at 35 degrees from (530000, 180000)
    lo, hi = np.array([530100.0, 180050.0, -np.inf]), np.array([530125.0, 180075.0, np.inf])
    travel = pair_travel(run, lo, hi)
    np.testing.assert_allclose(travel, [np.cos(HEADING), np.sin(HEADING), 0.0], atol=1e-9)
    back = Trajectory(run.time, run.xyz[::-1], run.rpy, run.sd, run_id="run_b")
    np.testing.assert_allclose(pair_travel(back, lo, hi), -travel, atol=1e-9)
    assert pair_travel(run, lo + [0.0, 100.0, 0.0], hi + [0.0, 100.0, 0.0]) is None  # beside the track
    standing = Trajectory(run.time, np.repeat(run.xyz[200:201], len(run.time), axis=0), run.rpy, run.sd)
    assert pair_travel(standing, lo, hi) is None
