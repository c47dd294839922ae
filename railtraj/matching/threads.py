"""How many threads the numerical libraries use while tiles are detected and matched.

* SciPy's ``cKDTree`` queries with ``workers=-1`` split the points over one Python thread per
  core, started anew on every call. That pays from a few thousand points; below, starting the
  threads costs more than it saves, and a point-to-plane fit makes thousands of small queries (its
  tracker re-searches only the few hundred points that may have changed correspondence).
* OpenBLAS splits even the matcher's small products (n x 3 by n x 3) over every core, and
  spends more starting and joining its threads than it saves: on the demo survey, matching took
  73 s serial with OpenBLAS on 2 threads and 64 s on one (42.7 instead of 56 s with the process
  executor), byte for byte the same results. The adjustment keeps BLAS's threads (a large banded
  Cholesky gains from them).
* A tile pair's windows (:mod:`railtraj.matching.piecewise`) and vote peaks
  (:mod:`railtraj.matching.consensus`) are fitted in threads, one per core: their KD-tree pair
  searches and numpy work release the GIL (4 window searches: 0.64 s on one thread, 0.28-0.31 s
  on two). The replica pair's matching 3.3 -> 2.4-2.9 s.
* In an executor's worker every library stays on its thread: the pool already fills the cores.
  ``threads=1`` (:func:`set_threads`) keeps the main process on one core too.
* "Every core" means the cores this process may run on (:func:`available_cores`): under
  ``taskset -c 0`` or a batch scheduler's CPU set, a run that counted the machine's cores started
  threads and workers that took turns on one core (two test runs side by side, each held to one
  core: 40 s with a thread and a worker per machine core, 32 s with one).

Results do not depend on any of it.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

#: queries below this many points run on the calling thread: SciPy starts Python threads for
#: ``workers=-1`` on every call (~0.3 ms each), which costs more than it saves below ~3000
#: points (measured: 100 points 0.05 ms on one thread, 0.27 ms on two)
MIN_THREADED_QUERY = 3_000
_threads = -1  # threads this process may use: -1 every core; 1 in the executors' workers


def available_cores() -> int:
    """How many cores this process may run on: its CPU affinity where the system has one
    (Linux: ``taskset``, cgroup CPU sets, a batch scheduler's allocation), else every core."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


def set_threads(n: int) -> None:
    """Threads of this process's KD-tree queries, window fits and Open3D: ``n`` (0 or -1: every
    core; 1: one, as in an executor's worker). Results do not depend on it."""
    global _threads
    _threads = -1 if n <= 0 else int(n)
    from railtraj.o3d import o3d

    o3d.utility.set_max_threads(_cores())


def query_workers(n: int) -> int:
    """``workers`` for a KD-tree query of ``n`` points (results do not depend on it)."""
    return _cores() if n >= MIN_THREADED_QUERY else 1


def _cores() -> int:
    """How many cores this process may use."""
    return available_cores() if _threads == -1 else _threads


def map_threads(fn, n: int) -> list:
    """``[fn(k) for k in range(n)]``, in threads (one per core) unless this process is held to one."""
    workers = min(n, _cores())
    if workers < 2:
        return [fn(k) for k in range(n)]
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(fn, range(n)))


def in_background(fn, *args):
    """Start ``fn(*args)`` on another thread unless this process is held to one core; returns a
    function that waits for its result (or, held to one core, computes it then)."""
    if _cores() < 2:
        return lambda: fn(*args)
    pool = ThreadPoolExecutor(max_workers=1)
    future = pool.submit(fn, *args)
    pool.shutdown(wait=False)
    return future.result


def blas_one_thread():
    """Context manager: BLAS (OpenBLAS, MKL) on one thread inside, as before outside."""
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1, user_api="blas")


_worker_ready = False


def single_threaded_worker() -> None:
    """Keep this process's libraries on one thread each from now on (an executor's worker)."""
    global _worker_ready
    if _worker_ready:
        return
    from threadpoolctl import threadpool_limits

    set_threads(1)
    threadpool_limits(limits=1, user_api="blas")
    _worker_ready = True
