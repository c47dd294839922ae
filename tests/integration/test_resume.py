"""Resume and determinism, end to end: a rerun in the same out_dir reuses finished tiles and
pairs (also after SIGKILL) and gives byte-identical outputs; serial and process executors agree.

metrics.json is compared without its wall-clock timings (every ``seconds`` key) and ``resume``
(what that run reused); every other output file is compared byte for byte.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.slow
CACHE = ".railtraj-cache"


def railtraj_cmd(survey: Path, out: Path, *args: str) -> list[str]:
    return [sys.executable, "-m", "railtraj.cli", f"survey_dir={survey}", f"out_dir={out}", *args]


def run(survey: Path, out: Path, *args: str) -> dict:
    """Run railtraj to completion and return its metrics.json."""
    res = subprocess.run(railtraj_cmd(survey, out, *args), capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]
    return json.loads((out / "metrics.json").read_text())


def _without_timings(obj):
    if isinstance(obj, dict):
        return {k: _without_timings(v) for k, v in obj.items() if k not in ("seconds", "resume", "memory")}
    if isinstance(obj, list):
        return [_without_timings(v) for v in obj]
    return obj


def outputs(out: Path) -> dict[str, bytes]:
    """The output files that must not change between equal runs, by name."""
    files = {p.relative_to(out).as_posix(): p.read_bytes()
             for pattern in ("trajectories/*", "offsets.csv", "ties.csv", "anchors.csv")
             for p in sorted(out.glob(pattern))}
    metrics = _without_timings(json.loads((out / "metrics.json").read_text()))
    files["metrics.json without timings"] = json.dumps(metrics, indent=1).encode()
    return files


def assert_same_outputs(out: Path, reference: Path) -> None:
    got, want = outputs(out), outputs(reference)
    assert sorted(got) == sorted(want)
    differ = [name for name in want if got[name] != want[name]]
    assert not differ, f"outputs differ from {reference}: {differ}"


def cached(out: Path, kind: str) -> int:
    return len(list((out / CACHE / kind).glob("*.pkl")))


@pytest.fixture(scope="module")
def survey(tmp_path_factory) -> Path:
    from railtraj.sim import generate

    root = tmp_path_factory.mktemp("sim")
    return Path(generate("thesis", root, seed=3, size=0.3).survey_dir)


@pytest.fixture(scope="module")
def baseline(survey, tmp_path_factory) -> tuple[Path, dict]:
    """One uninterrupted serial run: the reference outputs and their cache."""
    out = tmp_path_factory.mktemp("baseline") / "out"
    metrics = run(survey, out)
    assert metrics["resume"] == {"tiles_reused": 0, "pairs_reused": 0}
    assert metrics["counts"]["tile_pairs"] >= 5
    assert cached(out, "pairs") == metrics["counts"]["tile_pairs"] and cached(out, "tiles") >= 2
    return out, metrics


def counts(out: Path) -> tuple[int, int]:
    """(tiles, pairs) of the finished run in ``out``: its cache holds one entry for each."""
    return cached(out, "tiles"), cached(out, "pairs")


def test_rerun_reuses_everything_and_writes_the_same_files(baseline, survey, tmp_path):
    reference, _ = baseline
    out = tmp_path / "out"
    shutil.copytree(reference, out)
    metrics = run(survey, out)
    tiles, pairs = counts(reference)
    assert metrics["resume"] == {"tiles_reused": tiles, "pairs_reused": pairs}
    assert_same_outputs(out, reference)


def test_changed_matcher_option_rematches_but_keeps_keypoints(baseline, survey, tmp_path):
    reference, _ = baseline
    out = tmp_path / "out"
    shutil.copytree(reference, out)
    metrics = run(survey, out, "matcher.ambiguity_ratio=0.79")
    tiles, pairs = counts(reference)
    assert metrics["resume"] == {"tiles_reused": tiles, "pairs_reused": 0}
    assert cached(out, "pairs") == pairs   # the entries of the old option were pruned


def test_changed_tile_redetects_that_tile_and_rematches_its_pairs(baseline, survey, tmp_path):
    reference, _ = baseline
    out = tmp_path / "out"
    shutil.copytree(reference, out)
    offsets = (reference / "offsets.csv").read_text().splitlines()[1:]
    name = offsets[0].split(",")[2]    # tile_a of the first pair
    tile = sorted(survey.glob(f"*/tiles/{name}"))[0]
    st = tile.stat()
    os.utime(tile, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))   # "rewritten"
    try:
        metrics = run(survey, out)
    finally:
        os.utime(tile, ns=(st.st_atime_ns, st.st_mtime_ns))
    tiles, pairs = counts(reference)
    run_id = tile.parent.parent.name
    with_tile = sum(1 for row in offsets
                    if (row.split(",")[0], row.split(",")[2]) == (run_id, name)
                    or (row.split(",")[1], row.split(",")[3]) == (run_id, name))
    assert metrics["resume"] == {"tiles_reused": tiles - 1, "pairs_reused": pairs - with_tile}
    assert_same_outputs(out, reference)


def test_killed_runs_resume_to_the_same_outputs(baseline, survey, tmp_path):
    """SIGKILL during matching at three seeded points, each rerun resuming the last; the final
    rerun finishes the remaining pairs and writes what an uninterrupted run wrote."""
    reference, _ = baseline
    _, pairs = counts(reference)
    rng = np.random.default_rng(7)
    stops = sorted(rng.choice(np.arange(1, pairs), size=3, replace=False))
    out = tmp_path / "out"
    for stop in stops:
        proc = subprocess.Popen(railtraj_cmd(survey, out), stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
        try:
            while cached(out, "pairs") < stop:
                assert proc.poll() is None, "railtraj finished before it could be killed"
                time.sleep(0.02)
            time.sleep(rng.uniform(0.0, 0.5))   # somewhere inside the next pair
        finally:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
    done = cached(out, "pairs")
    assert stops[-1] <= done <= pairs
    metrics = run(survey, out)
    assert metrics["resume"]["pairs_reused"] == done
    assert_same_outputs(out, reference)
    assert not list((out / CACHE).rglob(".*.part")), "temporary files of killed runs left behind"


def test_serial_and_process_executors_write_the_same_files(baseline, survey, tmp_path):
    """On process workers, in a copy of the serial run's out_dir with ``resume=false``: a clean
    run that reads nothing of the cache there and still writes the same files."""
    reference, _ = baseline
    out = tmp_path / "out"
    shutil.copytree(reference, out)
    started = time.time() - 1.0   # (file times may be coarser than a second)
    metrics = run(survey, out, "executor=process", "executor.workers=2", "resume=false")
    assert metrics["resume"] == {"tiles_reused": 0, "pairs_reused": 0}
    assert counts(out) == counts(reference)   # workers stored their results, over the old ones
    assert min(p.stat().st_mtime for p in (out / CACHE).rglob("*.pkl")) >= started
    assert_same_outputs(out, reference)
