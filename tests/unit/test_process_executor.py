"""executor=process: results in item order whatever order chunks finish in, contiguous chunks, one
pool for the whole job (workers and their caches survive between maps), single-threaded workers,
errors re-raised with the pool shut down, and no worker outliving close()."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from railtraj.builtins.executors import ProcessExecutor, chunks


def slow_square(x: int) -> int:
    time.sleep(0.02 * (x % 3))  # later chunks may finish first
    if x < 0:
        raise ValueError(f"negative item {x}")
    return x * x


def whoami(_: int) -> tuple[int, bool]:
    from railtraj.matching import threads

    return os.getpid(), threads.query_workers(10**6) == 1


def test_chunks_are_contiguous_cover_every_item_once_and_balance_the_workers():
    for n in (1, 2, 7, 91, 1000):
        parts = chunks(n, 2)
        assert [k for r in parts for k in r] == list(range(n))
        assert len(parts) >= min(n, 4) and max(len(r) for r in parts) <= 4
    assert chunks(91, 2)[0] == range(0, 4)  # neighbours (pairs sharing a tile) stay together


def test_results_in_item_order_with_progress_one_pool_and_clean_shutdown():
    executor = ProcessExecutor(workers=2)
    calls = []
    items = list(range(23))
    assert executor.map(slow_square, items, progress=lambda d, n: calls.append((d, n))) == [x * x for x in items]
    assert calls[-1] == (23, 23) and [d for d, _ in calls] == sorted(d for d, _ in calls)
    pool = executor._pool
    first = executor.map(whoami, range(8))
    second = executor.map(whoami, range(8))
    pids = {pid for pid, _ in first + second}
    assert executor._pool is pool and pids <= set(pool._processes)  # one pool serves every map
    assert all(single for _, single in first + second), "workers must not start threads of their own"
    with pytest.raises(ValueError, match="negative item -1"):
        executor.map(slow_square, [1, -1, 2, 4, 5, 6, 7, 8, 9])
    assert executor._pool is None  # a failed map stops feeding its pool ...
    assert executor.map(slow_square, [3, 4]) == [9, 16]  # ... and the next map starts a new one
    executor.close()
    assert executor._pool is None and not executor._abandoned
    assert not _survivors(pids), "a worker still running after close()"


def test_the_serial_process_keeps_its_threads():
    from railtraj.matching import threads

    assert threads.query_workers(10**6) == threads.available_cores() and threads.query_workers(100) == 1


HELD = """
import os
os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
from railtraj.builtins.dask_executor import DaskExecutor
from railtraj.builtins.executors import ProcessExecutor
from railtraj.matching import threads
print(ProcessExecutor().workers, DaskExecutor().workers, threads.query_workers(10**6), threads._cores())
"""


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="CPU affinity is Linux only")
def test_a_job_held_to_one_core_starts_one_worker_and_one_thread():
    """Under ``taskset -c 0`` (or a batch scheduler's CPU set) "every core" is that one: a worker
    or thread per machine core would only take turns on it."""
    res = subprocess.run([sys.executable, "-c", HELD], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.split() == ["1", "1", "1", "1"]


JOB = """
import os, sys, time
from railtraj.builtins.executors import ProcessExecutor

def slow(x):
    os.write(1, f"{os.getpid()}\\n".encode())  # one write: two workers' lines never interleave
    time.sleep(60)

if __name__ == "__main__":
    ProcessExecutor(workers=2).map(slow, range(8))
"""


def test_workers_die_with_a_killed_job(tmp_path):
    """A job killed with SIGKILL takes its workers with it: none goes on computing and storing
    results the job will never count (a resumed run found one pair more than the killed one)."""
    script = tmp_path / "job.py"
    script.write_text(JOB)
    job = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    pids: set[int] = set()
    while len(pids) < 2:  # both workers are inside a task
        line = job.stdout.readline()
        assert line, "the job ended before its workers started"
        if line.strip().isdigit():
            pids.add(int(line))
    job.send_signal(signal.SIGKILL)
    job.wait()
    assert not _survivors(pids), "a worker outlived its killed job"


def _survivors(pids: set[int], seconds: float = 10.0) -> set[int]:
    """The processes among ``pids`` still running (not zombies) after waiting up to ``seconds``."""
    deadline = time.monotonic() + seconds
    while True:
        alive = {pid for pid in pids if _alive(pid)}
        if not alive or time.monotonic() >= deadline:
            return alive
        time.sleep(0.05)


def _alive(pid: int) -> bool:
    stat = Path(f"/proc/{pid}/stat")
    try:
        return stat.read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False
