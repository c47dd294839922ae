"""The ``dask`` executor: per-tile work on dask.distributed, on this machine or a cluster.

With no ``address`` it starts a LocalCluster of ``workers`` processes, one thread each, the first
time it is given work, and keeps it for the job's later stages (starting workers and importing
Open3D in them costs seconds); :meth:`DaskExecutor.close` (called by the CLI when the job ends,
also on error) shuts it down. With ``address=tcp://host:8786`` it connects to a running
scheduler instead (``dask scheduler``, ``dask worker tcp://host:8786``); its workers need railtraj
installed and must see the survey and out folders under the same paths.

Workers log only critical messages: a failed task reaches the user as the exception it raised,
re-raised here. Items go out in contiguous chunks, as with the ``process`` executor (the pairs
sharing a tile in one worker, the libraries' own threads off), scattered to the workers rather
than embedded in the tasks, so large keypoint sets travel worker to worker, not through the
scheduler. Results come back in the order of the items, whatever order they finish in, so the
output matches the ``serial`` executor's bit for bit.
"""

from __future__ import annotations

import logging
import weakref
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from railtraj.errors import ConfigError
from railtraj.hookspecs import hookimpl
from railtraj.matching.threads import available_cores

log = logging.getLogger(__name__)

#: how long to wait for a scheduler given by ``address`` to answer, then to have a worker, seconds
CONNECT_TIMEOUT_S = 10
WORKERS_TIMEOUT_S = 60


@dataclass
class DaskConfig:
    name: str = "dask"
    workers: int = 0  # LocalCluster worker processes (one thread each); 0: one per core this process may use
    address: str = ""  # an existing scheduler, e.g. tcp://10.0.0.5:8786; empty: a LocalCluster


class DaskExecutor:
    """Runs items as dask.distributed tasks; results come back in input order."""

    def __init__(self, workers: int = 0, address: str = "") -> None:
        self.workers = workers or available_cores()
        self.address = address
        self._client: Any = None
        self._finalizer: weakref.finalize | None = None

    def map(self, fn: Callable, items: Iterable, progress: Callable[[int, int], Any] | None = None) -> list:
        items = list(items)
        if not items:
            return []
        from distributed import as_completed

        from railtraj.builtins.executors import chunks, run_chunk

        client = self._connect()
        parts = chunks(len(items), self.workers)
        data = client.scatter([items[r.start:r.stop] for r in parts], hash=False)
        futures = [client.submit(run_chunk, fn, d, pure=False) for d in data]
        index = {f.key: r for r, f in zip(parts, futures, strict=True)}
        out: list = [None] * len(items)
        try:
            done = 0
            for fut in as_completed(futures):
                part = index[fut.key]
                out[part.start:part.stop] = fut.result()
                done += len(part)
                if progress:
                    progress(done, len(items))
        finally:
            client.cancel([*futures, *data])   # after an error: nothing left running
        return out

    def close(self) -> None:
        """Disconnect; shut the LocalCluster down (a remote scheduler keeps running)."""
        if self._finalizer is not None:
            self._finalizer()
        self._client = self._finalizer = None

    def __enter__(self) -> DaskExecutor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __getstate__(self) -> dict:
        # stages travel to the workers with each job: the client stays here
        return {"workers": self.workers, "address": self.address, "_client": None, "_finalizer": None}

    def _connect(self):
        if self._client is not None:
            return self._client
        from distributed import Client, LocalCluster

        quiet = _Quiet()  # dask's INFO lines (scheduler, nanny, client) would drown railtraj's log
        cluster = None
        if self.address:
            try:
                client = Client(self.address, timeout=CONNECT_TIMEOUT_S)
            except OSError as exc:
                quiet.restore()
                raise ConfigError(f"executor.address={self.address}: no dask scheduler answers ({exc}); "
                                  "start one with `dask scheduler` and workers with `dask worker "
                                  "<address>`, or leave executor.address empty for a local cluster") from None
            try:
                client.wait_for_workers(1, timeout=WORKERS_TIMEOUT_S)
            except TimeoutError:
                client.close()
                quiet.restore()
                raise ConfigError(f"the dask scheduler at {self.address} has no workers: start some with "
                                  f"`dask worker {self.address}`") from None
        else:
            import dask

            # dask's workers return freed memory to the system at once (MALLOC_TRIM_THRESHOLD_
            # 64 KiB); the matcher's large temporary arrays then fault their pages in again on
            # every allocation: the demo's matching took 130 s of worker time instead of 104 s.
            # Nor do they sample their tasks' stacks every 10 ms for dask's dashboard profile.
            with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
                                  "distributed.worker.profile.enabled": False}):
                cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1, processes=True,
                                       dashboard_address=None, silence_logs=logging.CRITICAL)
            client = Client(cluster)
        log.info("dask: %s with %d workers", self.address or "local cluster",
                 len(client.scheduler_info(n_workers=-1)["workers"]))
        self._client = client
        self._finalizer = weakref.finalize(self, _shutdown, client, cluster, quiet)
        return client


class _Quiet:
    """Only errors from the ``distributed`` loggers of this process, until :meth:`restore`."""

    def __init__(self) -> None:
        self.logger = logging.getLogger("distributed")
        self.level = self.logger.level
        self.logger.setLevel(max(self.level, logging.ERROR))

    def restore(self) -> None:
        self.logger.setLevel(self.level)


def _shutdown(client, cluster, quiet: _Quiet) -> None:
    """Close the client first, then the cluster, so no worker logs a lost connection."""
    try:
        client.close()
        if cluster is not None:
            cluster.close()
    finally:
        quiet.restore()


@hookimpl
def railtraj_register_stages(registry) -> None:
    registry.add("executor", "dask", DaskExecutor, DaskConfig)
