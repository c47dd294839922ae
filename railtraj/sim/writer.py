"""Writing a simulated survey (SPEC.md layout) and its truth (a separate folder).

Survey: ``<run_id>/trajectory.csv`` (the DRIFTED trajectory with its reported sd),
``<run_id>/tiles/<E>_<N>.laz`` (points georeferenced with the drifted trajectory, cut on a
common grid, named by the grid cell's lower-left corner) and, when the scenario has control
targets, ``control.csv``. Truth: ``trajectories/<run_id>.csv`` (true trajectories, SPEC
format), ``chainage/<run_id>.csv`` (time,chainage per epoch), ``control.csv`` (true target
positions) and ``scenario.json``. railtraj never reads the truth when correcting.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pyproj

from railtraj.data import PointTile, Trajectory
from railtraj.io.atomic import atomic_write
from railtraj.io.las import write_tile
from railtraj.io.outputs import write_json
from railtraj.io.trajectory_csv import write_trajectory_csv

CONTROL_COLUMNS = ("id", "x", "y", "z", "sd_x", "sd_y", "sd_z")


def tile_name(corner_e: float, corner_n: float) -> str:
    """Tile file name from its grid cell's lower-left corner, e.g. ``530000_180025.laz``."""
    return f"{int(round(corner_e))}_{int(round(corner_n))}.laz"


def cut_tiles(xyz: np.ndarray, tile_size: float) -> list[tuple[str, np.ndarray]]:
    """Split points onto a ``tile_size`` grid: (file name, point indices) per non-empty cell.

    Indices keep their input order (time order, for the simulator's points).
    """
    if not len(xyz):
        return []
    cell = np.floor(xyz[:, :2] / tile_size).astype(np.int64)
    lo = cell.min(axis=0)
    span = cell.max(axis=0) - lo + 1
    flat = (cell[:, 0] - lo[0]) * span[1] + (cell[:, 1] - lo[1])
    counts = np.bincount(flat, minlength=int(span[0] * span[1]))
    used = np.flatnonzero(counts)
    compact = np.zeros(len(counts), dtype=np.int64)
    compact[used] = np.arange(len(used))
    ids = compact[flat]
    # a stable sort of small integers is a radix sort: O(n) and keeps time order within a tile
    order = np.argsort(ids.astype(np.int16 if len(used) < 2 ** 15 else np.int32), kind="stable")
    groups = np.split(order, np.cumsum(counts[used])[:-1])
    corners = np.column_stack([used // span[1] + lo[0], used % span[1] + lo[1]]) * tile_size
    return [(tile_name(*c), g) for c, g in zip(corners, groups, strict=True)]


def write_run(survey_dir: Path, run_id: str, traj: Trajectory, xyz: np.ndarray, gps_time: np.ndarray,
              intensity: np.ndarray, tile_size: float, crs: pyproj.CRS | None) -> dict[str, int]:
    """One run folder of the survey: trajectory.csv and its tiles. Returns points per tile."""
    folder = survey_dir / run_id
    write_trajectory_csv(folder / "trajectory.csv", traj)
    counts = {}
    for name, idx in cut_tiles(xyz, tile_size):
        write_tile(folder / "tiles" / name,
                   PointTile(xyz[idx], gps_time[idx], intensity[idx], run_id=run_id, name=name), crs=crs)
        counts[name] = len(idx)
    return counts


def write_control_csv(path: str | os.PathLike, ids: list[str], xyz: np.ndarray, sd: np.ndarray) -> None:
    """control.csv as SPEC.md gives it: id,x,y,z,sd_x,sd_y,sd_z (metres)."""
    with atomic_write(path) as f:
        f.write(",".join(CONTROL_COLUMNS) + "\n")
        for i, p, s in zip(ids, np.atleast_2d(xyz), np.atleast_2d(sd), strict=True):
            f.write(f"{i},{p[0]:.4f},{p[1]:.4f},{p[2]:.4f},{s[0]:.4f},{s[1]:.4f},{s[2]:.4f}\n")


def write_truth_run(truth_dir: Path, run_id: str, traj: Trajectory, chainage: np.ndarray) -> None:
    """The true trajectory (SPEC format) and the chainage of each of its epochs."""
    write_trajectory_csv(truth_dir / "trajectories" / f"{run_id}.csv", traj)
    with atomic_write(truth_dir / "chainage" / f"{run_id}.csv") as f:
        f.write("time,chainage\n")
        np.savetxt(f, np.column_stack([traj.time, chainage]), fmt=["%.9f", "%.6f"], delimiter=",")


def write_params(truth_dir: Path, params: dict) -> None:
    """scenario.json: the scenario, seed, size and what was put in (drift peaks, counts)."""
    write_json(truth_dir / "scenario.json", params)
