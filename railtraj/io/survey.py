"""The survey folder of SPEC.md: discover runs, load their trajectories, find overlapping tiles.

Discovery reads only tile headers, so opening a survey of thousands of tiles is quick and a
bad layout is reported before any heavy work starts. Overlaps come from the headers' bounding
boxes (railtraj never trusts tile names or sizes).
"""

from __future__ import annotations

import itertools
import os
import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from railtraj.data import Trajectory
from railtraj.errors import NoOverlapError, SurveyError
from railtraj.io.las import TileHeader, empty_tile_error, missing_gps_time_error, read_header
from railtraj.io.sbet import find_smrmsg, read_sbet, read_smrmsg, sbet_to_trajectory
from railtraj.io.trajectory_csv import read_text_columns, read_trajectory_csv, to_float

RUN_NAME = re.compile(r"^[A-Za-z0-9_-]+$")
TRAJECTORY_NAMES = ("trajectory.csv", "trajectory.sbet")
TILE_SUFFIXES = (".laz", ".las")


@dataclass(frozen=True)
class RunInfo:
    """One run folder: its trajectory file (and SMRMSG beside an SBET) and its tiles' headers."""

    run_id: str
    folder: Path
    trajectory_path: Path
    tiles: list[TileHeader]
    smrmsg_path: Path | None = None


@dataclass(frozen=True)
class Survey:
    """A survey folder: its runs by id (sorted) and the optional control.csv."""

    root: Path
    runs: dict[str, RunInfo]
    control_path: Path | None = None

    def run(self, run_id: str) -> RunInfo:
        """The run called ``run_id``, or a :class:`SurveyError` listing the valid ids."""
        if run_id not in self.runs:
            raise SurveyError(f"survey {self.root} has no run {run_id!r}; "
                              f"its runs are: {', '.join(self.runs)}")
        return self.runs[run_id]

    def load_trajectory(self, run_id: str, crs: str = "EPSG:27700",
                        grid_dir: str | os.PathLike | None = None,
                        sbet_crs: str | None = None) -> Trajectory:
        """Read a run's trajectory.csv, or its trajectory.sbet (in the frame ``sbet_crs``)
        converted to ``crs``."""
        info = self.run(run_id)
        if info.trajectory_path.suffix == ".csv":
            return read_trajectory_csv(info.trajectory_path, run_id=run_id)
        smrmsg = None if info.smrmsg_path is None else read_smrmsg(info.smrmsg_path)
        return sbet_to_trajectory(read_sbet(info.trajectory_path), crs=crs, grid_dir=grid_dir,
                                  smrmsg=smrmsg, run_id=run_id, sbet_crs=sbet_crs)


def _open_run(folder: Path) -> RunInfo:
    trajs = [folder / n for n in TRAJECTORY_NAMES if (folder / n).is_file()]
    if not trajs:
        raise SurveyError(f"run folder {folder} has no trajectory.csv or trajectory.sbet: "
                          "add the run's trajectory or move the folder out of the survey")
    if len(trajs) > 1:
        raise SurveyError(f"run folder {folder} has both trajectory.csv and trajectory.sbet: "
                          "keep the one to use and remove the other")
    tile_dir = folder / "tiles"
    paths = sorted(p for p in tile_dir.glob("*") if p.suffix.lower() in TILE_SUFFIXES
                   and p.is_file()) if tile_dir.is_dir() else []
    if not paths:
        raise SurveyError(f"run folder {folder} has no tiles/*.laz or tiles/*.las: "
                          "put the run's LiDAR tiles in a tiles/ folder inside it")
    if not RUN_NAME.match(folder.name):
        raise SurveyError(f"run folder name {folder.name!r} in {folder.parent} may contain only "
                          "letters, digits, '-' and '_': rename the folder")
    tiles = [read_header(p) for p in paths]
    no_time = [t for t in tiles if not t.has_gps_time]
    if no_time:
        raise missing_gps_time_error(no_time[0].path, no_time[0].point_format)
    empty = [t for t in tiles if t.point_count == 0]
    if empty:
        raise empty_tile_error(empty[0].path)
    smrmsg = find_smrmsg(trajs[0]) if trajs[0].suffix == ".sbet" else None
    return RunInfo(folder.name, folder, trajs[0], tiles, smrmsg)


def _looks_like_run(folder: Path) -> bool:
    """A sub-folder is taken for a run if it has a trajectory file or a tiles/ folder."""
    return any((folder / n).is_file() for n in TRAJECTORY_NAMES) or (folder / "tiles").is_dir()


def open_survey(path: str | os.PathLike) -> Survey:
    """Discover the runs of a survey folder and read their tile headers.

    A sub-folder with a trajectory file or a tiles/ folder is a run and must have both; other
    sub-folders and hidden ones are ignored. A survey needs two or more runs. control.csv, when
    present, is read here too, so a malformed one fails before any heavy work.
    """
    root = Path(path)
    if not root.exists():
        raise SurveyError(f"survey folder {root} does not exist: check survey_dir=...")
    if not root.is_dir():
        raise SurveyError(f"survey path {root} is a file, not a folder: pass the folder that "
                          "holds the run folders as survey_dir=...")
    folders = sorted(p for p in root.iterdir()
                     if p.is_dir() and not p.name.startswith(".") and _looks_like_run(p))
    runs = {f.name: _open_run(f) for f in folders}
    if len(runs) < 2:
        found = f"{len(runs)} run{'s' if len(runs) != 1 else ''}"
        names = f" ({', '.join(runs)})" if runs else ""
        raise SurveyError(f"survey folder {root}: found {found}{names}; a survey needs 2 or more "
                          "run folders each with trajectory.csv and tiles/*.laz")
    control = root / "control.csv"
    if control.is_file():
        read_control(control)
    return Survey(root, runs, control if control.is_file() else None)


def unparsed_crs_note(survey: Survey, crs: str) -> str | None:
    """A note naming the tiles whose CRS record could not be parsed (they are taken to be in
    ``crs``, unchecked), or None when every tile's CRS was read or absent."""
    bad = [t for run in survey.runs.values() for t in run.tiles if t.crs_error]
    if not bad:
        return None
    return (f"{len(bad)} tile(s) have a CRS record that cannot be parsed, so they were assumed to be "
            f"in the survey CRS {crs} without a check (first: {bad[0].path}: {bad[0].crs_error}); "
            "rewrite their CRS, or check they are in that CRS")


@dataclass(frozen=True)
class TilePair:
    """Two tiles of different runs whose bounding boxes overlap in plan.

    ``overlap_min``/``overlap_max`` bound the common XY area (boxes grown by the margin) and the
    union of both tiles' heights: pass them to ``read_tile(bbox=...)`` to read only that column.
    """

    run_a: str
    run_b: str
    tile_a: TileHeader
    tile_b: TileHeader
    overlap_min: np.ndarray
    overlap_max: np.ndarray
    # each run's tiles that hold points near the pair's box (its own included): where the points
    # just beyond the box are read (:func:`with_context`)
    context_a: tuple[Path, ...] = ()
    context_b: tuple[Path, ...] = ()


def _bounds(tiles: list[TileHeader]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    mins = np.array([t.mins for t in tiles]).reshape(-1, 3)
    maxs = np.array([t.maxs for t in tiles]).reshape(-1, 3)
    return mins, maxs, np.array([t.point_count > 0 for t in tiles], dtype=bool)


def find_overlaps(survey: Survey, margin: float = 0.0, min_overlap_m: float = 1.0) -> list[TilePair]:
    """Tile pairs of different runs (run_a < run_b) whose XY boxes overlap by >= ``min_overlap_m``
    in both x and y after growing each box by ``margin``; empty tiles are skipped."""
    pairs: list[TilePair] = []
    for ra, rb in itertools.combinations(sorted(survey.runs), 2):
        ta, tb = survey.runs[ra].tiles, survey.runs[rb].tiles
        (min_a, max_a, ok_a), (min_b, max_b, ok_b) = _bounds(ta), _bounds(tb)
        lo = np.maximum(min_a[:, None, :2], min_b[None, :, :2]) - margin
        hi = np.minimum(max_a[:, None, :2], max_b[None, :, :2]) + margin
        hit = ((hi - lo) >= min_overlap_m).all(axis=2) & ok_a[:, None] & ok_b[None, :]
        for i, j in np.argwhere(hit):
            z_lo = min(min_a[i, 2], min_b[j, 2])
            z_hi = max(max_a[i, 2], max_b[j, 2])
            pairs.append(TilePair(ra, rb, ta[i], tb[j], np.append(lo[i, j], z_lo),
                                  np.append(hi[i, j], z_hi)))
    return pairs


#: a tile (pair) longer than this many ``pipeline.pair_part_m`` in x or y is matched in parts
#: (:func:`in_parts`) and detected in the squares of that grid (:func:`grid_cells`)
LARGE_TILE = 1.2


def in_parts(pairs: list[TilePair], part_m: float) -> list[TilePair]:
    """``pairs`` with every overlap longer than :data:`LARGE_TILE` x ``part_m`` in x or y cut into
    equal parts of at most ``part_m`` (the same tiles, a smaller overlap box each); ``part_m`` 0:
    unchanged.

    A tile pair's offset is fitted as one smooth curve over 5 m windows, and its along-track alias
    is chosen against the pairs around it. Tiles of 50 m hold up to 70 m of track, over which the
    drift bends more than a parabola follows, and their pairs lie too far apart for the chain along
    the track to predict one from the next: on a simulated tunnel of 50 m tiles 18 % of the pairs
    were used and the runs came out 1.41 m apart (1.44 before). Matched in 25 m parts, a large
    tile behaves like the 25 m tiles the matcher was built on (SPEC: tiles may have any size).
    """
    if part_m <= 0:
        return pairs
    out: list[TilePair] = []
    for p in pairs:  # a few hundred pairs, not points
        lo, hi = p.overlap_min[:2], p.overlap_max[:2]
        n = np.where(hi - lo > LARGE_TILE * part_m, np.ceil((hi - lo) / part_m), 1).astype(int)
        if (n == 1).all():
            out.append(p)
            continue
        ex, ey = (np.linspace(lo[k], hi[k], n[k] + 1) for k in range(2))
        out += [replace(p, overlap_min=np.array([ex[i], ey[j], p.overlap_min[2]]),
                        overlap_max=np.array([ex[i + 1], ey[j + 1], p.overlap_max[2]]))
                for i in range(n[0]) for j in range(n[1])]
    return out


def grid_cells(xyz: np.ndarray, part_m: float) -> list[np.ndarray]:
    """Indices of the points ``xyz`` (n, 3) in each square of a ``part_m`` grid in plan (the
    survey grid's multiples of ``part_m``), for a tile longer than ``1.2 part_m`` in x or y; one
    part of every point otherwise (or where ``part_m`` is 0).

    A tile's keypoints are detected in these squares (:func:`railtraj.pipeline.detect_tile`).
    The detector fires where a square's edge cuts the lining, at the same place in every run:
    such keypoints give the runs' offset across and up at that section (along the track they
    say nothing; the windows and the chain along the track do). A featureless lining has no
    other keypoints: a held-out tube in 25 m tiles came out 0.014 / 0.037 m inter-run, the same
    survey in 50 m tiles 0.90 / 1.29 m, its pairs' parts without a tile edge refused for too
    few keypoints. Detected in the squares :func:`in_parts` matches, a large tile gives the
    keypoints of the 25 m tiles the matcher was built on (SPEC: tiles may have any size)."""
    if part_m <= 0 or not len(xyz) or (np.ptp(xyz[:, :2], axis=0) <= LARGE_TILE * part_m).all():
        return [np.arange(len(xyz))]
    _, square = np.unique(np.floor(xyz[:, :2] / part_m).astype(np.int64), axis=0, return_inverse=True)
    order = np.argsort(square.ravel(), kind="stable")
    return np.split(order, np.flatnonzero(np.diff(square.ravel()[order])) + 1)


def with_context(pairs: list[TilePair], survey: Survey, reach: float) -> list[TilePair]:
    """``pairs`` with, per run, the tiles whose boxes come within ``reach`` (m, in plan) of the
    pair's overlap box: a surface cut by a tile's edge is whole there (a box across run a's tile
    boundary, :mod:`railtraj.matching.objects`)."""
    bounds = {r: _bounds(info.tiles) for r, info in survey.runs.items()}

    def near(run: str, lo: np.ndarray, hi: np.ndarray) -> tuple[Path, ...]:
        mins, maxs, nonempty = bounds[run]
        hit = nonempty & np.all((mins[:, :2] <= hi + reach) & (maxs[:, :2] >= lo - reach), axis=1)
        return tuple(survey.runs[run].tiles[k].path for k in np.flatnonzero(hit))

    return [replace(p, context_a=near(p.run_a, p.overlap_min[:2], p.overlap_max[:2]),
                    context_b=near(p.run_b, p.overlap_min[:2], p.overlap_max[:2])) for p in pairs]


def require_overlaps(pairs: list[TilePair], survey: Survey) -> list[TilePair]:
    """Return ``pairs`` unless they are empty, in which case raise :class:`NoOverlapError`."""
    if not pairs:
        ids = ", ".join(survey.runs)
        raise NoOverlapError(
            f"runs {ids} share no overlapping tiles (bounding boxes of their tiles do not "
            "intersect): check that all runs are in the same CRS and cover the same stretch of track")
    return pairs


@dataclass(frozen=True)
class ControlPoints:
    """Ground control from control.csv: ids, (n, 3) coordinates and (n, 3) 1-sigma."""

    ids: np.ndarray
    xyz: np.ndarray
    sd: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)


def read_control(path: str | os.PathLike) -> ControlPoints:
    """Read control.csv (id,x,y,z,sd_x,sd_y,sd_z; header names, any order).

    Every id must be present and unique: observations refer to control points by id.
    """
    what = "control file"
    names = ("id", "x", "y", "z", "sd_x", "sd_y", "sd_z")
    cols = read_text_columns(path, names, what)
    ids = cols["id"]
    if not len(ids):
        raise SurveyError(f"{what} {path} has a header but no control points: add them (one per "
                          "line: id,x,y,z,sd_x,sd_y,sd_z) or remove the file")
    if (ids == "").any():
        row = int(np.argmax(ids == ""))
        raise SurveyError(f"{what} {path}, data row {row + 1}: the id is empty; give every "
                          "control point an id")
    uniq, counts = np.unique(ids, return_counts=True)
    if (counts > 1).any():
        dup = uniq[counts > 1]
        raise SurveyError(f"{what} {path}: id(s) {', '.join(map(str, dup[:5]))} appear more than "
                          "once; give every control point a unique id (or remove the repeated rows)")
    num = {c: to_float(cols[c], c, path, what) for c in names[1:]}
    xyz = np.column_stack([num["x"], num["y"], num["z"]])
    sd = np.column_stack([num["sd_x"], num["sd_y"], num["sd_z"]])
    if not np.isfinite(xyz).all():
        row = int(np.argmax(~np.isfinite(xyz).all(axis=1)))
        raise SurveyError(f"{what} {path} has a NaN or infinite coordinate for control point "
                          f"{ids[row]} (data row {row + 1}): fix or remove that control point")
    bad = ~(np.isfinite(sd) & (sd > 0))
    if bad.any():
        row, k = (int(v) for v in np.argwhere(bad)[0])
        raise SurveyError(f"{what} {path}: {names[4 + k]} of control point {ids[row]} (data row "
                          f"{row + 1}) is {float(sd[row, k])}; every sd_x, sd_y, sd_z must be a "
                          "positive number (the point's 1-sigma in metres): fix those cells")
    return ControlPoints(cols["id"], xyz, sd)
