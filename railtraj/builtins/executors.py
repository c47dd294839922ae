"""Executors: how per-tile work is spread over the machine.

``serial`` runs items one after another in this process (simplest to debug; the stages' own
libraries, Open3D and SciPy's KD-tree, already use a second core for part of the work). ``process``
runs items in a pool of worker processes. Workers start from a fork server, not by forking this
process: a fork taken while Open3D's or a KD-tree's threads hold a lock deadlocks the child (seen
when a script generated a survey and then ran the pipeline).

The pool is kept for the job's later stages (its workers keep their tile caches and have
imported Open3D already) and shut down by :meth:`ProcessExecutor.close`. Items go to the workers
in contiguous chunks: the pipeline orders its items so that the pairs sharing a tile are
neighbours, so one worker builds that tile's plane target and KD-tree once instead of each
worker building it again. Each worker runs its libraries on one thread: with two workers on two
cores, threads of their own only fight for the same cores. Results are the same as ``serial``'s
(nothing computed depends on which process or thread did it).
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from typing import Any

from railtraj.hookspecs import hookimpl
from railtraj.matching.threads import available_cores


@dataclass
class SerialConfig:
    name: str = "serial"


@dataclass
class ProcessConfig:
    name: str = "process"
    workers: int = 0  # 0: one per core this process may use (its CPU affinity)


class SerialExecutor:
    """Runs every item in this process, in order."""

    def map(self, fn: Callable, items: Iterable, progress: Callable[[int, int], Any] | None = None) -> list:
        items = list(items)
        out = []
        for k, item in enumerate(items):
            out.append(fn(item))
            if progress:
                progress(k + 1, len(items))
        return out


#: items per chunk at most: the pairs sharing a reference tile (one per other run) are
#: neighbours in the pipeline's order, so a few items keep them together, and small chunks
#: leave little for one worker to finish alone at the end (demo, 2 workers: 55.7 s of matching
#: in 12-pair chunks, 56.1 s in 4-pair chunks; the smaller ones balance larger surveys better)
MAX_CHUNK = 4


def chunks(n: int, workers: int) -> list[range]:
    """Contiguous index ranges covering ``range(n)``: at least two per worker, ``MAX_CHUNK`` items
    at most each."""
    size = max(1, min(MAX_CHUNK, n // (2 * workers)))
    return [range(k, min(k + size, n)) for k in range(0, n, size)]


def run_chunk(fn: Callable, items: list) -> list:
    """``fn`` over ``items`` in a worker, with the libraries' own threads off: the pool (or the
    dask cluster) already fills the cores, and threads of their own only fight for them."""
    from railtraj.matching.threads import single_threaded_worker

    single_threaded_worker()
    return [fn(item) for item in items]


def _serve(job_pid: int) -> None:
    """Pool initializer: the worker serves the job process ``job_pid`` and dies with it. A job
    killed with SIGKILL left its workers blocked on their task queues for ever (and their fork
    server with them), after they had finished their chunks and stored results it never
    counted. Now a worker stores nothing once the job is gone (:func:`railtraj.resume.job_gone`,
    checked before a result takes its name) and exits within a second."""
    import threading
    import time

    from railtraj import resume

    resume.serve_job(job_pid)

    def watch() -> None:
        while not resume.job_gone():
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, name="railtraj-job-watch", daemon=True).start()


class ProcessExecutor:
    """Runs items in a pool of worker processes, in contiguous chunks; results come back in input
    order. The pool lives until :meth:`close` (the CLI closes it when the job ends)."""

    def __init__(self, workers: int = 0) -> None:
        self.workers = workers or available_cores()
        self._pool: ProcessPoolExecutor | None = None
        self._abandoned: list[ProcessPoolExecutor] = []

    def map(self, fn: Callable, items: Iterable, progress: Callable[[int, int], Any] | None = None) -> list:
        items = list(items)
        if self.workers == 1 or len(items) <= 1:
            return SerialExecutor().map(fn, items, progress)
        out: list = [None] * len(items)
        pool = self._start()
        futures = {pool.submit(run_chunk, fn, items[r.start:r.stop]): r for r in chunks(len(items), self.workers)}
        try:
            done = 0
            for fut in as_completed(futures):
                part = futures[fut]
                out[part.start:part.stop] = fut.result()
                done += len(part)
                if progress:
                    progress(done, len(items))
        except BaseException:  # a failed item or a memory stop: queued chunks never start
            self._abandon()
            raise
        return out

    def close(self) -> None:
        """Shut the pool down (its workers exit); the next map starts a new one. The workers of
        a pool a failed map left are stopped at once (a memory stop should not wait for them)."""
        for pool in self._abandoned:
            for worker in list((getattr(pool, "_processes", None) or {}).values()):
                worker.terminate()
            pool.shutdown(wait=True)
        self._abandoned.clear()
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def _abandon(self) -> None:
        """Stop feeding the pool, without waiting for its running chunks: a memory stop repeats
        its interrupt every half second, and a shutdown that waited could be cut short in the
        middle, leaving the pool half shut (Python's exit then printed a traceback of its own).
        :meth:`close`, called once the job has stopped, ends its workers."""
        pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)
            self._abandoned.append(pool)

    def __getstate__(self) -> dict:
        # stages travel to the workers with each job: the pool stays here
        return {"workers": self.workers, "_pool": None, "_abandoned": []}

    def _start(self) -> ProcessPoolExecutor:
        if self._pool is None:
            context = multiprocessing.get_context("forkserver")
            self._pool = ProcessPoolExecutor(max_workers=self.workers, mp_context=context,
                                             initializer=_serve, initargs=(os.getpid(),))
        return self._pool


@hookimpl
def railtraj_register_stages(registry) -> None:
    registry.add("executor", "serial", SerialExecutor, SerialConfig)
    registry.add("executor", "process", ProcessExecutor, ProcessConfig)
