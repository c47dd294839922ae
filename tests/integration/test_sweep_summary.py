"""A 2-job sweep (`railtraj -m`) on a small simulated survey leaves summary.csv/.md/.png, its jobs
sharing one cache."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest

from railtraj.resume import CACHE_DIR, Cache, prune_sweep

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
    # the jobs share one cache: the second (median) reuses the first's keypoints and matches,
    # and after the sweep the cache holds one entry per tile and pair, no job's list of them
    resume = {name: json.loads((sweep / by[name]["job"] / "metrics.json").read_text())["resume"]
              for name in by}
    assert resume["spline"] == {"tiles_reused": 0, "pairs_reused": 0}
    assert resume["median"]["pairs_reused"] == int(by["median"]["tile_pairs"]) > 0
    cache = sweep / CACHE_DIR
    assert len(list(cache.glob("pairs/*.pkl"))) == int(by["median"]["tile_pairs"])
    assert len(list(cache.glob("tiles/*.pkl"))) == resume["median"]["tiles_reused"] > 0
    assert not list(cache.glob("used-*")) and not list(sweep.glob(f"*/{CACHE_DIR}"))


def test_prune_sweep_keeps_what_any_job_used(tmp_path):
    """Entries used by either job stay; others, killed jobs' parts and the jobs' lists go."""
    entries = {name: tmp_path / kind / f"{name}.pkl" for kind, name in
               [("tiles", "a"), ("tiles", "b"), ("pairs", "ab"), ("pairs", "stale"), ("tiles", "old")]}
    part = tmp_path / "pairs" / ".x.pkl.part"
    for path in [*entries.values(), part]:
        path.parent.mkdir(exist_ok=True)
        path.write_bytes(b"")
    first = Cache(tmp_path, {}, job="first")
    first.used = {entries["a"], entries["ab"]}
    first.prune()
    second = Cache(tmp_path, {}, job="second")
    second.used = {entries["b"], entries["ab"]}
    second.prune()
    assert all(path.exists() for path in [*entries.values(), part])  # nothing goes during the sweep
    assert prune_sweep(tmp_path, jobs=2) == 2
    assert sorted(p.name for p in tmp_path.rglob("*") if p.is_file()) == ["a.pkl", "ab.pkl", "b.pkl"]


def test_prune_sweep_keeps_everything_when_a_job_failed(tmp_path):
    """A job that failed (bad input) listed nothing: no entry goes, only the lists."""
    entry = tmp_path / "tiles" / "a.pkl"
    entry.parent.mkdir()
    entry.write_bytes(b"")
    job = Cache(tmp_path, {}, job="only")
    job.prune()  # it used nothing, and a second job failed before listing anything
    assert prune_sweep(tmp_path, jobs=2) is None
    assert entry.exists() and not list(tmp_path.glob("used-*"))
