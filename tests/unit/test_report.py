"""The QC report's pieces on small in-memory results: verdicts, sections and a page that still
renders when pairs have no points, no truth and no control."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np

from railtraj.data import TileOffset
from railtraj.qc import distance_stats
from railtraj.report.chainage import Chainage
from railtraj.report.html import write_report
from railtraj.report.sections import (
    ALIGNED,
    REFUSED,
    UNRESOLVED,
    WEAK,
    PairPlace,
    sections,
    verdict,
)


def test_verdicts_follow_the_final_status():
    statuses = ("ok", "degenerate", "ambiguous", "no_consensus", "no_overlap")
    assert [verdict(s) for s in statuses] == [ALIGNED, WEAK, UNRESOLVED, REFUSED, REFUSED]


def test_sections_merge_consecutive_pairs_per_run_pair():
    def place(k, runs, s, v):
        return PairPlace(k, runs, "t", "t", np.zeros(2), s, "", v)

    places = [place(0, "a / b", 30, ALIGNED), place(1, "a / b", 10, ALIGNED),
              place(2, "a / b", 50, REFUSED), place(3, "a / c", 10, ALIGNED),
              place(4, "a / b", 70, ALIGNED)]
    got = [(s.runs, s.start, s.end, s.pairs, s.verdict) for s in sections(places)]
    assert got == [("a / b", 10, 30, [1, 0], ALIGNED), ("a / b", 50, 50, [2], REFUSED),
                   ("a / b", 70, 70, [4], ALIGNED), ("a / c", 10, 10, [3], ALIGNED)]


def test_chainage_runs_along_the_reference(make_trajectory):
    traj = make_trajectory(n=300, speed=10.0)
    ch = Chainage(traj)
    assert abs(ch.length - 30.0) < 0.5
    assert abs(ch.at(traj.xyz[150, :2])[0] - 15.0) < 0.2
    heading = np.radians(30)
    assert np.allclose(ch.direction(15.0), [np.sin(heading), np.cos(heading)], atol=0.05)


def _result(make_trajectory, make_tile):
    trajs = {r: make_trajectory(n=300, seed=k, run_id=r) for k, r in enumerate("ab")}
    corrected = {r: replace(t, xyz=t.xyz + [0.01, -0.02, 0.005]) for r, t in trajs.items()}
    origin = trajs["a"].xyz[100]
    tiles = [make_tile(n=3000, seed=k, origin=origin, size=5.0, run_id=r, name="t.laz")
             for k, r in enumerate("ab")]
    ok = TileOffset("a", "b", "t.laz", "t.laz", d=np.array([0.01, 0.0, 0.0]), cov=np.eye(3) * 1e-4,
                    inliers=40, status="ok", info={"time_a": float(trajs["a"].time[100])})
    bad = TileOffset("a", "b", "u.laz", "u.laz", status="no_consensus", info={"keypoints_a": 3})
    pairs = [SimpleNamespace(offset=ok, sample_a=tiles[0], sample_b=tiles[1], seconds={}),
             SimpleNamespace(offset=bad, sample_a=tiles[0].subset(np.zeros(0, int)),
                             sample_b=tiles[1].subset(np.zeros(0, int)), seconds={})]
    survey = SimpleNamespace(root="mem", runs={r: SimpleNamespace(tiles=[]) for r in "ab"})
    options = SimpleNamespace(mode="global", reference_run=None)
    return SimpleNamespace(survey=survey, options=options,
                           trajectories=trajs, corrected=corrected, pairs=pairs)


def test_report_renders_without_truth_or_control(tmp_path, make_trajectory, make_tile):
    result = _result(make_trajectory, make_tile)
    empty = distance_stats(np.zeros(0))
    metrics = {"counts": {"runs": 2, "tiles": 2, "tile_pairs": 2, "ties": 0, "anchors": 0},
               "qc": {"tie_residual_before_m": empty, "tie_residual_after_m": empty,
                      "c2c_before_m": distance_stats(np.ones(3)),
                      "c2c_after_m": distance_stats(np.ones(3))},
               "seconds": {"match": 1.0}, "notes": ["a warning"], "adjustment": {}, "control": [],
               "config": {"detector": {"name": "iss"}}}
    path = tmp_path / "report.html"
    write_report(path, result, metrics)
    text = path.read_text()
    assert text.count("<img") >= 5 and "a warning" in text
    assert "no_consensus" in text and "too few keypoint pairs" in text
    assert "Against the simulator" not in text and "Control points" not in text


def test_report_lists_runs_whose_reported_sd_was_widened():
    from test_sd_check import _survey

    from railtraj.report.html import adjustment
    from railtraj.sd_check import check_reported_sd

    trajs, offsets, _ = _survey()
    summary = check_reported_sd(trajs, offsets).summary
    html = adjustment({"adjustment": {"sd_check": summary}})
    assert "Reported sd contradicted" in html and "run_a" in html and "run_b, run_c" in html
    unbiased = _survey(biased=False)
    assert adjustment({"adjustment": {"sd_check": check_reported_sd(*unbiased[:2]).summary}}) == ""


def test_report_names_the_stretches_not_resolved_along_the_track():
    from railtraj.report.html import adjustment

    coverage = {"run_a~run_b": {"length_m": 380.0, "resolved_m": 106.2, "share": 0.279, "unresolved": [
        {"time_b": [300616.63, 300635.58], "length_m": 177.1, "worst_sd_m": 0.072},
        {"time_b": [300604.28, 300606.36], "length_m": 20.8, "worst_sd_m": None}]},
        "run_a~run_c": {"length_m": 379.2, "resolved_m": 379.2, "share": 1.0, "unresolved": []}}
    html = adjustment({"adjustment": {"alongtrack_coverage": coverage}})
    assert "106 of 380" in html and "28%" in html and "300616.6-300635.6, 177, 0.072" in html
    assert "300604.3-300606.4, 21<" in html and "379 of 379" in html
