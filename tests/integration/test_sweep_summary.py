"""A 2-job sweep (`railtraj -m`) on a small simulated survey leaves summary.csv/.md/.png."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow


def test_sweep_writes_a_summary(tmp_path):
    from railtraj.sim import generate

    sim = generate("control", tmp_path / "sim", seed=0, size=0.2)
    sweep = tmp_path / "sweep"
    cmd = [sys.executable, "-m", "railtraj.cli", "-m", "optimizer=spline,median",
           f"survey_dir={sim.survey_dir}", f"out_dir={sweep}",
           f"truth_dir={Path(sim.survey_dir).parent / 'truth'}"]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    with open(sweep / "summary.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert sorted(r["overrides"] for r in rows) == ["optimizer=median", "optimizer=spline"]
    for r in rows:
        assert r["status"] == "ok" and (sweep / r["job"] / "metrics.json").is_file()
        assert int(r["tile_pairs"]) > 0 and float(r["wall_time_s"]) > 0
        assert float(r["truth_rms_h_after_m"]) > 0
    by = {r["overrides"].split("=")[-1]: r for r in rows}
    # the median optimizer cannot move runs without ok pairs; the spline uses control points
    assert float(by["spline"]["truth_rms_h_after_m"]) < float(by["median"]["truth_rms_h_after_m"])
    assert "| overrides |" in (sweep / "summary.md").read_text()
    assert (sweep / "summary.png").read_bytes()[:4] == b"\x89PNG"
