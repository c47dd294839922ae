"""executor=dask: results in item order, errors re-raised and the LocalCluster shut down, and the
whole pipeline on 2 dask workers writing byte for byte what the serial executor writes (metrics.json
without timings and configuration: equal).

The pipeline runs match the survey's first three tile pairs (``pipeline.max_pairs=3``): what is
checked is the executor (order, pickling, the workers' single threads), and all five pairs took
85-107 s of a CI worker (serial against process workers on every pair: test_resume.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("distributed")

from railtraj.builtins.dask_executor import DaskExecutor  # noqa: E402

pytestmark = pytest.mark.slow
COMPARED = ("offsets.csv", "ties.csv", "anchors.csv", "trajectories/*")


def test_results_in_item_order_progress_and_clean_shutdown_after_an_error():
    def slow_square(x):  # pickled by value (cloudpickle): later items finish first
        import time

        time.sleep(0.05 * (5 - x))
        if x < 0:
            raise ValueError(f"negative item {x}")
        return x * x

    calls = []
    with DaskExecutor(workers=2) as executor:
        assert executor.map(slow_square, range(5), progress=lambda d, n: calls.append((d, n))) == \
            [0, 1, 4, 9, 16]
        assert calls == [(k, 5) for k in range(1, 6)]
        pids = list(executor._client.run(os.getpid).values())
        assert len(pids) == 2
        with pytest.raises(ValueError, match="negative item -1"):
            executor.map(slow_square, [1, -1, 2])
        assert executor.map(slow_square, [3]) == [9]   # still usable after a failed map
    assert executor._client is None
    for pid in pids:   # no worker outlives close()
        deadline = time.monotonic() + 10
        while _alive(pid) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not _alive(pid), f"dask worker {pid} still running"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return Path(f"/proc/{pid}").exists() and "Z" not in Path(f"/proc/{pid}/stat").read_text().split()[2]


@pytest.fixture(scope="module")
def survey(tmp_path_factory) -> Path:
    from railtraj.sim import generate

    return Path(generate("thesis", tmp_path_factory.mktemp("sim"), seed=3, size=0.2).survey_dir)


def run(survey: Path, out: Path, *args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "railtraj.cli", f"survey_dir={survey}", f"out_dir={out}", *args]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    return res


def _without(obj, keys=("seconds", "resume", "config", "memory")):
    """metrics.json without wall-clock timings, peak memory, what was reused and the configuration."""
    if isinstance(obj, dict):
        return {k: _without(v) for k, v in obj.items() if k not in keys}
    return [_without(v) for v in obj] if isinstance(obj, list) else obj


def test_pipeline_on_two_dask_workers_matches_serial_byte_for_byte(survey, tmp_path):
    run(survey, tmp_path / "serial", "executor=serial", "pipeline.max_pairs=3")
    res = run(survey, tmp_path / "dask", "executor=dask", "executor.workers=2", "pipeline.max_pairs=3")
    want = {p.relative_to(tmp_path / "serial"): p.read_bytes()
            for pattern in COMPARED for p in sorted((tmp_path / "serial").glob(pattern))}
    assert len(want) >= 5
    for name, data in want.items():
        assert (tmp_path / "dask" / name).read_bytes() == data, f"{name} differs from serial"
    metrics = [_without(json.loads((tmp_path / d / "metrics.json").read_text())) for d in ("serial", "dask")]
    assert metrics[0] == metrics[1]
    log = res.stdout + res.stderr
    assert "dask: local cluster with 2 workers" in log
    noise = [line for line in log.splitlines() if "distributed." in line or "Warning" in line]
    assert not noise, "dask logged:\n" + "\n".join(noise[:10])
