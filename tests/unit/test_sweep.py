"""Sweep summary from jobs' metrics.json: rows, failed jobs, the accuracy figure chosen."""

from __future__ import annotations

import json
import math

from railtraj.sweep import COLUMNS, Job, find_jobs, write_sweep_summary


def _job(root, name, metrics=None):
    folder = root / name
    (folder / ".hydra").mkdir(parents=True)
    if metrics is not None:
        (folder / "metrics.json").write_text(json.dumps(metrics))
    return folder


def _metrics(c2c_after, truth_h=None):
    m = {"counts": {"tile_pairs": 4, "tile_pairs_by_status": {"ok": 3, "ambiguous": 1}},
         "qc": {"c2c_before_m": {"median": 0.1}, "c2c_after_m": {"median": c2c_after},
                "tie_residual_after_m": {"rms": None}},
         "seconds": {"load": 1.0, "match": 2.5, "per_stage_total": {"match": 2.0}}}
    if truth_h is not None:
        overall = {"rms_h": truth_h, "rms_v": 0.01}
        m["truth"] = {"before": {"overall": {"rms_h": 0.5}}, "after": {
            "overall": overall, "consistency": {"a~b": {"rms_h": 0.02}, "a~c": {"rms_h": 0.04}}}}
    return m


def test_rows_failed_jobs_and_c2c_fallback(tmp_path):
    _job(tmp_path, "matcher=a", _metrics(0.02))
    _job(tmp_path, "matcher=b", _metrics(0.01))
    _job(tmp_path, "matcher=c")  # bad input: no metrics.json
    rows = write_sweep_summary(tmp_path)
    assert [r["job"] for r in rows] == ["matcher=a", "matcher=b", "matcher=c"]
    assert rows[0]["tile_pairs_ok"] == 3 and rows[0]["wall_time_s"] == 3.5   # stage clocks summed
    assert rows[2]["status"] == "failed" and math.isnan(rows[2]["c2c_median_after_m"])
    assert math.isnan(rows[0]["tie_rms_after_m"])
    lines = (tmp_path / "summary.csv").read_text().splitlines()
    assert lines[0] == ",".join(COLUMNS) and len(lines) == 4
    md = (tmp_path / "summary.md").read_text()
    assert "sorted by C2C median" in md and "truth RMS" not in md   # no truth: no truth columns
    assert md.index("matcher=b") < md.index("matcher=a") < md.index("matcher=c")   # best first
    assert (tmp_path / "summary.png").read_bytes()[:4] == b"\x89PNG"


def test_truth_figures_and_measured_wall_time(tmp_path):
    a = _job(tmp_path, "x=1", _metrics(0.02, truth_h=0.03))
    b = _job(tmp_path, "x=2", _metrics(0.01, truth_h=0.05))
    rows = write_sweep_summary(tmp_path, [Job(a, "x=1", 12.0), Job(b, "x=2", 7.0)])
    assert [r["wall_time_s"] for r in rows] == [12.0, 7.0]
    assert rows[0]["truth_rms_h_after_m"] == 0.03
    assert rows[0]["truth_interrun_rms_h_after_m"] == 0.04
    md = (tmp_path / "summary.md").read_text()
    assert "sorted by RMS horizontal error vs truth" in md and md.index("x=1") < md.index("x=2")
    assert [j.folder.name for j in find_jobs(tmp_path)] == ["x=1", "x=2"]
