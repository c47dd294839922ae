"""How many threads a KD-tree query uses.

SciPy's ``cKDTree`` queries with ``workers=-1`` split the points over one Python thread per core,
started anew on every call. That pays from a few thousand points; below, starting the threads
costs more than it saves, and a point-to-plane fit makes thousands of small queries (its tracker
re-searches only the few hundred points that may have changed correspondence). In the process
executor's workers the pool already fills the cores, so there every query stays on its thread.
Results do not depend on it.
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
