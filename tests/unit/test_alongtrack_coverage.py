"""railtraj.alongtrack_coverage: which stretches of a run pair are resolved along the track."""

from __future__ import annotations

import numpy as np
import pytest

from railtraj.alongtrack_coverage import along_track_coverage
from railtraj.data import TileOffset, Trajectory


def _run(run_id: str, t0: float, direction: float, sd_open: float = 0.01, sd_tunnel: float = 0.5) -> Trajectory:
    """400 m east (or west) at 10 m/s; its reported sd small in the first and last 40 m (open
    cuttings), large in between (the tunnel)."""
    t = t0 + np.arange(0.0, 40.0, 0.1)
    x = 10.0 * (t - t0) if direction > 0 else 400.0 - 10.0 * (t - t0)
    xyz = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    open_sky = (x < 40.0) | (x > 360.0)
    sd = np.where(open_sky, sd_open, sd_tunnel)[:, None] * np.ones(3)
    return Trajectory(t, xyz, np.zeros_like(xyz), sd, run_id=run_id)


RUNS = {"run_a": _run("run_a", 1000.0, 1.0), "run_b": _run("run_b", 2000.0, -1.0)}


def _pair(x: float, status: str, resolved: bool = False) -> TileOffset:
    """A tile pair 25 m long centred at x (m), observed at the runs' times there."""
    info = {"time_a": 1000.0 + x / 10.0, "time_b": 2000.0 + (400.0 - x) / 10.0}
    if resolved:
        info["resolved"] = "joint"
    return TileOffset("run_a", "run_b", f"{x:.0f}", f"{x:.0f}", np.zeros(3), np.eye(3) * 1e-4, status=status, info=info)


def _chain(statuses: list[tuple[str, bool]], predicted_sd: list[float | None]):
    xs = 12.5 + 25.0 * np.arange(len(statuses))
    offsets = [_pair(x, s, r) for x, (s, r) in zip(xs, statuses, strict=True)]
    report = [{"pair": k, "predicted_sd_m": sd} for k, sd in enumerate(predicted_sd) if sd is not None]
    return offsets, report


def test_a_stretch_without_a_fixed_pair_or_a_sure_prediction_is_reported_with_run_b_times():
    # 16 pairs over 400 m: fixed at both ends, nothing fixed from 100 m to 300 m in; the chain
    # predicts two of those within 5 cm (next to fixed pairs), the rest not or not at all
    statuses = [("ok", False)] * 4 + [("ambiguous", False)] * 8 + [("coarse", True)] * 4
    sd = [0.01] * 4 + [0.03, 0.2, None, 0.4, None, 0.3, 0.2, 0.04] + [0.01] * 4
    coverage, note = along_track_coverage(*_chain(statuses, sd), RUNS, resolved_sd=0.05)
    row = coverage["run_a~run_b"]
    # the 6 unresolved pairs (137.5-262.5 m) own the track up to the resolved pairs either side
    # (112.5 and 287.5 m): 175 m; the other 10 the rest of 400 m
    assert row["length_m"] == pytest.approx(400.0) and row["resolved_m"] == pytest.approx(225.0)
    assert row["share"] == pytest.approx(0.5625, abs=1e-3)
    [stretch] = row["unresolved"]
    assert stretch["length_m"] == pytest.approx(175.0) and stretch["worst_sd_m"] == pytest.approx(0.4)
    # run b drives west: 287.5 m east is 11.25 s after its start, 112.5 m 28.75 s
    assert stretch["time_b"] == pytest.approx([2011.25, 2028.75])
    assert note is not None and "run_a~run_b over 225 of 400 m" in note and "2011.2-2028.8 s (175 m)" in note


def test_where_the_runs_report_a_small_sd_a_pair_with_nothing_to_match_is_no_gap():
    # the end pairs in the open cuttings could not be matched; GNSS places the runs there
    statuses = [("no_consensus", False)] + [("ok", False)] * 14 + [("few_keypoints", False)]
    coverage, note = along_track_coverage(*_chain(statuses, [None] + [0.01] * 14 + [None]), RUNS, resolved_sd=0.05)
    assert coverage["run_a~run_b"]["share"] == 1.0 and coverage["run_a~run_b"]["unresolved"] == []
    assert note is None
    # ... but in a tunnel, where their sd is large, the same pairs are gaps, up to the next pair
    vague = {r: _run(r, t.time[0], 1.0 if r == "run_a" else -1.0, sd_open=0.5) for r, t in RUNS.items()}
    coverage, note = along_track_coverage(*_chain(statuses, [None] + [0.01] * 14 + [None]), vague, resolved_sd=0.05)
    assert [s["length_m"] for s in coverage["run_a~run_b"]["unresolved"]] == pytest.approx([37.5, 37.5])
    assert note is not None
