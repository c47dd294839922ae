"""Peak memory in metrics.json and the ``max_memory_gb`` stop (railtraj.memory)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from railtraj.errors import MemoryLimitError, RailtrajError
from railtraj.memory import GIB, MemoryMonitor, peak_rss_gb, resident_gb


def test_report_has_the_peaks_in_gib():
    with MemoryMonitor(interval=0.05) as memory:
        hold = np.ones(int(0.1 * GIB / 8))  # 100 MiB, touched
        report = memory.report()
    assert hold[-1] == 1.0
    assert report["max_memory_gb"] == 0.0
    assert report["peak_sampled_gb"] >= 0.1
    assert report["peak_self_gb"] >= 0.1
    assert report["peak_children_gb"] >= 0.0
    assert peak_rss_gb()["self"] >= report["peak_self_gb"] - 1e-3


def test_limit_interrupts_the_main_thread_with_a_railtraj_error():
    limit = resident_gb() + 0.05
    with pytest.raises(MemoryLimitError, match=r"above max_memory_gb=.*executor.workers=1") as err:
        with MemoryMonitor(limit_gb=limit, interval=0.02):
            hold = [np.ones(int(0.2 * GIB / 8))]  # 200 MiB over the limit (may be interrupted here)
            for _ in range(500):  # or in this wait
                time.sleep(0.02)
            hold.clear()
    assert isinstance(err.value, RailtrajError)  # the CLI prints it as one line, exit status 2
    assert "\n" not in str(err.value)


def test_under_the_limit_nothing_happens_and_the_handler_is_restored():
    import signal

    before = signal.getsignal(signal.SIGUSR1)
    with MemoryMonitor(limit_gb=resident_gb() + 4.0, interval=0.02) as memory:
        time.sleep(0.1)
    assert memory.exceeded_gb == 0.0
    assert signal.getsignal(signal.SIGUSR1) is before


def test_negative_limit_is_refused():
    with pytest.raises(ValueError):
        MemoryMonitor(limit_gb=-1.0)
