"""Peak memory of a job, and a limit that stops it with a clear error before the machine swaps.

:class:`MemoryMonitor` samples the resident memory of this process and its live children
(executor workers) every ``interval`` seconds in a daemon thread (psutil) and remembers the
largest total. With a limit (``max_memory_gb``), the first sample above it (or the first after
this process's own peak, ``getrusage``, passed it between two samples) interrupts the main
thread with :class:`railtraj.errors.MemoryLimitError`, which the command line prints as one line
and exits 2 on; pending executor work is cancelled on the way out. Any other error that leaves
the job once the limit was crossed (code that caught the interrupt and raised its own) is
reported as the memory stop too. Without a limit it only
measures. :meth:`MemoryMonitor.report` adds the kernel's own peaks (``getrusage`` ru_maxrss) of
this process and of its largest finished child, for metrics.json.
"""

from __future__ import annotations

import logging
import resource
import signal
import threading

from railtraj.errors import MemoryLimitError

log = logging.getLogger(__name__)

GIB = 2**30


def peak_rss_gb() -> dict[str, float]:
    """Peak resident memory (GiB) of this process and of its largest finished child process
    (``getrusage`` ru_maxrss, KiB on Linux); live children are not counted by the kernel yet."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / GIB
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024 / GIB
    return {"self": own, "children": children}


def resident_gb() -> float:
    """Resident memory (GiB) of this process plus all its live descendants, now."""
    import psutil

    me = psutil.Process()
    total = me.memory_info().rss
    for child in me.children(recursive=True):
        try:
            total += child.memory_info().rss
        except psutil.Error:  # it ended between listing and reading
            continue
    return total / GIB


class MemoryMonitor:
    """Samples memory while a job runs; stops the job above ``limit_gb`` (0: no limit).

    Use as a context manager around the job, from the main thread (the interrupt is a signal).
    """

    def __init__(self, limit_gb: float = 0.0, interval: float = 0.5) -> None:
        if limit_gb < 0:
            raise ValueError("limit_gb must be >= 0 (0: no limit)")
        self.limit_gb = float(limit_gb)
        self.interval = interval
        self.peak_gb = 0.0
        self.exceeded_gb = 0.0  # the sample that crossed the limit, 0 while under it
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._previous_handler = None

    def __enter__(self) -> MemoryMonitor:
        if self.limit_gb:
            self._previous_handler = signal.signal(signal.SIGUSR1, self._interrupt)
        self.sample()
        self._thread = threading.Thread(target=self._run, name="railtraj-memory", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if self.limit_gb:
            signal.signal(signal.SIGUSR1, self._previous_handler)
        if exc is not None and self.exceeded_gb and not isinstance(exc, MemoryLimitError):
            # the interrupt landed in code that turned it into its own error (e.g. a failed import)
            raise self.error() from exc

    def sample(self) -> float:
        """Measure now; remember the peak; return the reading (GiB): the larger of the current
        total (this process and its workers) and the kernel's peak of this process, which also
        catches a spike that came and went between two samples."""
        now = resident_gb()
        self.peak_gb = max(self.peak_gb, now)
        return max(now, peak_rss_gb()["self"])

    def _run(self) -> None:
        main = threading.main_thread().ident
        while not self._stop.wait(self.interval):
            now = self.sample()
            if self.limit_gb and now > self.limit_gb:
                self.exceeded_gb = max(self.exceeded_gb, now)
                # re-sent each interval until the job stops: a broad `except` may swallow one
                signal.pthread_kill(main, signal.SIGUSR1)

    def _interrupt(self, signum, frame) -> None:
        while frame is not None:
            if frame.f_code.co_filename.startswith("<frozen importlib"):
                return  # never leave a module half-imported (Open3D then fails at exit): next interval
            frame = frame.f_back
        raise self.error()

    def error(self) -> MemoryLimitError:
        return MemoryLimitError(
            f"railtraj used {self.exceeded_gb:.2f} GiB (this process and its workers), above "
            f"max_memory_gb={self.limit_gb:g}: stopped before the machine swaps; use fewer workers "
            "(executor.workers=1), a smaller pipeline.tile_cache_gb, or raise max_memory_gb "
            "(0: no limit)")

    def report(self) -> dict[str, float]:
        """Peaks for metrics.json (GiB): sampled total of this process and its live workers,
        and the kernel's peak of this process and of its largest finished child."""
        self.sample()
        kernel = peak_rss_gb()
        return {"peak_sampled_gb": round(self.peak_gb, 3), "peak_self_gb": round(kernel["self"], 3),
                "peak_children_gb": round(kernel["children"], 3), "max_memory_gb": self.limit_gb}
