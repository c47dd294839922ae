"""Runs on the same track compared position by position where both report GNSS."""

from __future__ import annotations

import numpy as np

from railtraj.builtins.spline_optimizer import SplineOptimizer
from railtraj.data import Ties, TileOffset, Trajectory
from railtraj.same_track import SameTrackOptions, same_track_offsets, summary
from railtraj.sd_check import check_reported_sd, with_fading_margin

SPEED, LENGTH = 10.0, 300.0
TRAP = (100.0, 160.0)  # where run a's GNSS is biased across the track (y)
BIAS = 0.3


def _run(run_id: str, t0: float, across: float = 0.0, biased: bool = False, sd: float = 0.02,
         tunnel: tuple[float, float] | None = None) -> Trajectory:
    """A run along x at ``across`` m from the track (y), its GNSS ``BIAS`` off across in TRAP,
    its reported sd 0.5 m in ``tunnel``."""
    time = t0 + np.arange(0, LENGTH / SPEED, 0.1)
    s = (time - t0) * SPEED
    xyz = np.column_stack([530000 + s, np.full_like(s, 180000.0 + across), np.full_like(s, 10.0)])
    if biased:
        xyz[:, 1] += BIAS * np.sin(np.pi * np.clip((s - TRAP[0]) / (TRAP[1] - TRAP[0]), 0, 1)) ** 2
    sds = np.full((len(s), 3), sd)
    if tunnel is not None:
        sds[(s > tunnel[0]) & (s < tunnel[1])] = 0.5
    return Trajectory(time, xyz, np.tile([0.0, 0.0, 90.0], (len(s), 1)), sds, run_id=run_id)


def _chainage(run: Trajectory, t: float) -> float:
    return float(np.interp(t, run.time, run.xyz[:, 0]) - 530000)


def test_runs_on_one_track_show_a_bias_across_where_both_report_gnss():
    """Every 5 m where both report GNSS, run a's position less run b's nearest, across and up:
    the bias within millimetres, nothing along the track, nothing in the tunnel; a constant
    between them (a lever arm) is taken out."""
    runs = {"run_a": _run("run_a", 1000.0, biased=True, tunnel=(180.0, 260.0)),
            "run_b": _run("run_b", 2000.0, across=0.05, tunnel=(180.0, 260.0))}
    out = same_track_offsets(runs, SameTrackOptions())
    assert 30 <= len(out) <= 45 and {o.status for o in out} == {"ambiguous"}
    where = np.array([_chainage(runs["run_a"], o.info["time_a"]) for o in out])
    d = np.array([o.d for o in out])
    assert not ((where > 180) & (where < 260)).any()
    truth = BIAS * np.sin(np.pi * np.clip((where - TRAP[0]) / (TRAP[1] - TRAP[0]), 0, 1)) ** 2
    np.testing.assert_allclose(d[:, 1], truth, atol=0.003)
    np.testing.assert_allclose(d[:, 2], 0.0, atol=1e-9)
    np.testing.assert_allclose(d[:, 0], 0.0, atol=0.005)  # (across run a's own track, which the bias tilts)
    assert len({o.tile_a for o in out}) == len({int(w // 25) for w in where})  # one tile pair per 25 m
    metrics, note = summary(out)
    np.testing.assert_allclose(metrics["run_pairs"]["run_a~run_b"]["constant_across_up_m"], [-0.05, 0.0], atol=1e-9)
    assert metrics["run_pairs"]["run_a~run_b"]["places"] == len(out) and "run_a~run_b" in note and "-5.0 cm across" in note


def test_runs_on_other_tracks_are_not_compared():
    """Twin tracks 4 m apart; and a run turning off onto the next track (a 1:9 turnout) after
    200 m: compared only before it turns."""
    runs = {"run_a": _run("run_a", 1000.0), "run_b": _run("run_b", 2000.0, across=4.0)}
    assert same_track_offsets(runs, SameTrackOptions()) == []
    turning = _run("run_b", 2000.0)
    s = turning.xyz[:, 0] - 530000
    turning.xyz[:, 1] += np.clip((s - 200.0) / 9.0, 0.0, 4.0)
    out = same_track_offsets({"run_a": _run("run_a", 1000.0), "run_b": turning}, SameTrackOptions())
    where = np.array([_chainage(turning, o.info["time_b"]) for o in out])
    assert len(out) > 30 and where.max() < 202.0
    np.testing.assert_allclose([o.d for o in out], 0.0, atol=0.003)
    assert same_track_offsets({"run_a": _run("run_a", 1000.0), "run_b": _run("run_b", 2000.0)},
                              SameTrackOptions(sd_m=0.0)) == []


def test_a_bias_no_tile_pair_shows_is_found_and_corrected_on_the_same_track():
    """Run a's GNSS 0.3 m off across at a portal where no tile pair fits; three runs on one
    track. Compared with runs b and c there, run a is convicted and the adjustment holds it to
    them where its bias had faded: within 3 cm of the truth; without the comparison it keeps
    the bias claiming 2 cm."""
    runs = {r: _run(r, t0, biased=r == "run_a") for r, t0 in (("run_a", 1000.0), ("run_b", 2000.0), ("run_c", 3000.0))}
    offsets = []  # tile pairs only outside the trap, every 25 m: ties that agree
    for b in ("run_b", "run_c"):
        for start in (0.0, 25.0, 50.0, 175.0, 200.0, 225.0, 250.0, 275.0):
            s = np.arange(start + 1.25, start + 25.0, 2.5)
            t_a, t_b = 1000.0 + s / SPEED, (2000.0 if b == "run_b" else 3000.0) + s / SPEED
            ties = Ties("run_a", b, t_a, t_b, runs["run_a"].position_at(t_a), runs[b].position_at(t_b),
                        np.full(len(s), 0.1))
            offsets.append(TileOffset("run_a", b, f"{start:.0f}", f"{start:.0f}", np.zeros(3), np.eye(3) * 1e-4, len(s),
                                      "ok", ties, {"time_a": float(t_a.mean()), "time_b": float(t_b.mean())}))
    ties = [o.ties for o in offsets]
    error = {}
    for sd_m in (0.0, 0.02):
        options = SameTrackOptions(sd_m=sd_m)
        checked = check_reported_sd(runs, offsets + same_track_offsets(runs, options))
        track = same_track_offsets(runs, options, trusted=checked.trajectories)
        corrected = with_fading_margin(SplineOptimizer().optimize(runs, ties, track, widening=checked.widening), checked)
        error[sd_m] = np.abs(corrected["run_a"].xyz[:, 1] - 180000.0)
        if sd_m:
            assert set(checked.summary["runs"]) == {"run_a"}
            assert np.all(error[sd_m] <= 3 * corrected["run_a"].sd[:, 1])
    assert error[0.0].max() > 0.8 * BIAS  # nothing showed it
    assert error[0.02].max() < 0.03
