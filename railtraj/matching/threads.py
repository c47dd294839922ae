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
* In an executor's worker every library stays on its thread: the pool already fills the cores.

Results do not depend on any of it.
"""

from __future__ import annotations

#: queries below this many points run on the calling thread: SciPy starts Python threads for
#: ``workers=-1`` on every call (~0.3 ms each), which costs more than it saves below ~3000
#: points (measured: 100 points 0.05 ms on one thread, 0.27 ms on two)
MIN_THREADED_QUERY = 3_000
_threaded = True  # off in the process executor's workers (railtraj.builtins.executors)


def set_query_threads(on: bool) -> None:
    """Let large KD-tree queries of this process use every core (the default), or not."""
    global _threaded
    _threaded = on


def query_workers(n: int) -> int:
    """``workers`` for a KD-tree query of ``n`` points (results do not depend on it)."""
    return -1 if _threaded and n >= MIN_THREADED_QUERY else 1


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

    from railtraj.o3d import o3d

    set_query_threads(False)
    o3d.utility.set_max_threads(1)
    threadpool_limits(limits=1, user_api="blas")
    _worker_ready = True
