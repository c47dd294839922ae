"""Executors: how per-tile work is spread over the machine.

``serial`` runs items one after another in this process (simplest to debug; the stages' own
libraries, Open3D and kiss-icp, already use every core). ``process`` runs items in a pool of
worker processes, for stages that are single-threaded Python/numpy. Workers start from a fork
server, not by forking this process: a fork taken while Open3D's or a KD-tree's threads hold a
lock deadlocks the child (seen when a script generated a survey and then ran the pipeline).
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from typing import Any

from railtraj.hookspecs import hookimpl


@dataclass
class SerialConfig:
    name: str = "serial"


@dataclass
class ProcessConfig:
    name: str = "process"
    workers: int = 0  # 0: one per core


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


class ProcessExecutor:
    """Runs items in a pool of worker processes; results come back in input order."""

    def __init__(self, workers: int = 0) -> None:
        self.workers = workers or os.cpu_count() or 1

    def map(self, fn: Callable, items: Iterable, progress: Callable[[int, int], Any] | None = None) -> list:
        items = list(items)
        if self.workers == 1 or len(items) <= 1:
            return SerialExecutor().map(fn, items, progress)
        out: list = [None] * len(items)
        context = multiprocessing.get_context("forkserver")
        with ProcessPoolExecutor(max_workers=self.workers, mp_context=context) as pool:
            futures = {pool.submit(fn, item): k for k, item in enumerate(items)}
            try:
                for done, fut in enumerate(as_completed(futures), start=1):
                    out[futures[fut]] = fut.result()
                    if progress:
                        progress(done, len(items))
            except BaseException:  # a failed item or a memory stop: queued items never start
                pool.shutdown(wait=False, cancel_futures=True)
                raise
        return out


@hookimpl
def railtraj_register_stages(registry) -> None:
    registry.add("executor", "serial", SerialExecutor, SerialConfig)
    registry.add("executor", "process", ProcessExecutor, ProcessConfig)
