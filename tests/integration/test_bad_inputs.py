"""Catalogue of bad inputs: each gets one line ``railtraj: error: <what and how to fix>``, exit 2.

A tiny simulated survey (with control.csv) is generated once; every case corrupts a copy of it
and runs the ``railtraj`` command. Besides the message, each case checks that no traceback is
printed and that what an earlier run left in out_dir is neither lost nor joined by half-written
files. Most cases fail while the survey is opened, before any tile is read.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import laspy
import numpy as np
import pytest

from railtraj.data import PointTile
from railtraj.io.las import read_tile, write_tile

pytestmark = pytest.mark.slow
PREVIOUS = {"metrics.json": '{"previous": "run"}\n', "config.yaml": "previous: run\n"}


def railtraj(*args: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    return subprocess.run([sys.executable, "-m", "railtraj.cli", *args], capture_output=True,
                          text=True, timeout=300, env=env)


@pytest.fixture(scope="module")
def tiny_survey(tmp_path_factory) -> Path:
    """Two runs over ~50 m of tunnel, 5-6 tiles each, and control.csv (about 2 s to generate)."""
    from railtraj.sim import generate

    return Path(generate("control", tmp_path_factory.mktemp("tiny"), seed=0, size=0.1).survey_dir)


# --- helpers that corrupt a copy of the survey --------------------------------------------------

def _edit_lines(path: Path, edit: Callable[[list[str]], list[str]]) -> None:
    path.write_text("\n".join(edit(path.read_text().splitlines())) + "\n")


def _set_cell(path: Path, row: int, column: str, value: str) -> None:
    """Set one cell of a CSV (row 1 = first data row)."""
    def edit(lines: list[str]) -> list[str]:
        k = lines[0].split(",").index(column)
        cells = lines[row].split(",")
        cells[k] = value
        lines[row] = ",".join(cells)
        return lines
    _edit_lines(path, edit)


def _drop_column(path: Path, column: str) -> None:
    def edit(lines: list[str]) -> list[str]:
        k = lines[0].split(",").index(column)
        return [",".join(c for i, c in enumerate(ln.split(",")) if i != k) for ln in lines]
    _edit_lines(path, edit)


def _remove(*paths: Path) -> None:
    for p in paths:
        shutil.rmtree(p) if p.is_dir() else p.unlink()


def _traj(s: Path, run: str = "run_a") -> Path:
    return s / run / "trajectory.csv"


def _tiles(s: Path, run: str = "run_a") -> list[Path]:
    return sorted((s / run / "tiles").glob("*.la[sz]"))


def _empty_tile(s: Path) -> None:
    empty = PointTile(xyz=np.zeros((0, 3)), gps_time=np.zeros(0), intensity=np.zeros(0, np.uint16))
    write_tile(_tiles(s)[0].with_name("zz_empty.laz"), empty)


def _tile_without_gps_time(s: Path) -> None:
    hdr = laspy.LasHeader(point_format=2, version="1.2")
    tile = read_tile(_tiles(s)[0])
    hdr.offsets, hdr.scales = np.floor(tile.xyz.min(axis=0)), [0.001] * 3
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = tile.xyz[:100].T
    las.write(_tiles(s)[0].with_name("zz_no_time.las"))


def _truncate(path: Path, keep: float = 0.5) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


def _shift_trajectory(s: Path, column: str, by: float) -> None:
    def edit(lines: list[str]) -> list[str]:
        k = lines[0].split(",").index(column)
        out = [lines[0]]
        for ln in lines[1:]:
            cells = ln.split(",")
            cells[k] = f"{float(cells[k]) + by:.6f}"
            out.append(",".join(cells))
        return out
    _edit_lines(_traj(s), edit)


def _swap_rows(path: Path, a: int, b: int) -> None:
    def edit(lines: list[str]) -> list[str]:
        lines[a], lines[b] = lines[b], lines[a]
        return lines
    _edit_lines(path, edit)


def _duplicate_row(path: Path, row: int) -> None:
    _edit_lines(path, lambda lines: lines[: row + 1] + [lines[row]] + lines[row + 1:])


def _sbet_instead(s: Path, size: int) -> None:
    _traj(s).unlink()
    (s / "run_a" / "trajectory.sbet").write_bytes(b"\x01" * size)


def _out_dir_is_file(s: Path, tmp: Path) -> list[str]:
    (tmp / "out_file").write_text("keep me\n")
    return [f"out_dir={tmp / 'out_file'}"]


def _out_dir_under_file(s: Path, tmp: Path) -> list[str]:
    (tmp / "out_file").write_text("keep me\n")
    return [f"out_dir={tmp / 'out_file' / 'sub'}"]


# Each case: id, corruption (survey copy, tmp folder) -> extra command-line arguments, and the
# lower-case fragments the error line must contain (what is wrong, and the fix).
Case = tuple[str, Callable[[Path, Path], "list[str] | None"], tuple[str, ...]]
CASES: list[Case] = [
    # the survey folder
    ("survey_missing", lambda s, t: [f"survey_dir={s / 'nope'}"], ("does not exist", "survey_dir=")),
    ("survey_is_a_file", lambda s, t: [f"survey_dir={s / 'control.csv'}"], ("is a file", "survey_dir=")),
    ("one_run_only", lambda s, t: shutil.rmtree(s / "run_b"), ("found 1 run (run_a)", "2 or more")),
    ("no_runs", lambda s, t: _remove(s / "run_a", s / "run_b"),
     ("found 0 runs", "2 or more run folders")),
    ("run_without_trajectory", lambda s, t: _traj(s).unlink(),
     ("has no trajectory.csv or trajectory.sbet", "add the run's trajectory")),
    ("tiles_folder_missing", lambda s, t: shutil.rmtree(s / "run_a" / "tiles"),
     ("has no tiles/*.laz", "put the run's lidar tiles in a tiles/ folder")),
    ("tiles_folder_empty", lambda s, t: _remove(*_tiles(s)),
     ("has no tiles/*.laz", "tiles/ folder")),
    ("csv_and_sbet_both", lambda s, t: (s / "run_a" / "trajectory.sbet").write_bytes(b"\0" * 136),
     ("both trajectory.csv and trajectory.sbet", "remove the other")),
    ("bad_run_name", lambda s, t: (s / "run_a").rename(s / "run a"), ("may contain only", "rename the folder")),
    # tiles
    ("truncated_laz", lambda s, t: _truncate(_tiles(s)[1]), ("truncated or corrupt", "re-export")),
    ("zero_byte_tile", lambda s, t: _tiles(s)[1].write_bytes(b""), ("cannot be read", "re-export")),
    ("not_a_las_file", lambda s, t: _tiles(s)[1].write_text("x,y,z\n1,2,3\n"),
     ("cannot be read", "remove it from tiles/")),
    ("empty_tile", lambda s, t: _empty_tile(s), ("zz_empty.laz is empty (0 points)", "remove it from tiles/")),
    ("tile_without_gps_time", lambda s, t: _tile_without_gps_time(s),
     ("point format 2 has no gps_time", "export the tiles with a point format that carries gps_time")),
    ("tiles_in_another_crs", lambda s, t: ["crs=EPSG:32630"], ("british national grid", "set crs=")),
    ("trajectory_far_from_tiles", lambda s, t: _shift_trajectory(s, "x", 5000.0),
     ("lies more than 200 m from run 'run_a'", "same crs")),
    ("trajectory_misses_point_times", lambda s, t: _shift_trajectory(s, "time", 1000.0),
     ("does not cover", "supply the trajectory for the whole run")),
    # trajectory.csv
    ("trajectory_text_cell", lambda s, t: _set_cell(_traj(s), 5, "y", "abc"),
     ("line 6, column 'y': 'abc' is not a number", "fix or remove that line")),
    ("trajectory_missing_column", lambda s, t: _drop_column(_traj(s), "heading"),
     ("lacks column(s) heading", "the first line must name the columns")),
    ("trajectory_nan", lambda s, t: _set_cell(_traj(s), 7, "z", "nan"),
     ("column 'z' is nan at data row 7", "remove or fill that epoch")),
    ("trajectory_duplicate_epoch", lambda s, t: _duplicate_row(_traj(s), 9),
     ("not strictly increasing", "drop duplicate epochs")),
    ("trajectory_unsorted", lambda s, t: _swap_rows(_traj(s), 3, 4),
     ("not strictly increasing", "sort it")),
    ("trajectory_negative_sd", lambda s, t: _set_cell(_traj(s), 4, "sd_y", "-0.02"),
     ("column 'sd_y' is -0.02 at data row 4", "must be positive", "remove the three sd columns")),
    ("trajectory_zero_sd", lambda s, t: _set_cell(_traj(s), 2, "sd_z", "0"),
     ("column 'sd_z' is 0.0 at data row 2", "must be positive")),
    ("trajectory_short_row", lambda s, t: _edit_lines(_traj(s), lambda ln: ln[:3] + ["300000.1,1,2"] + ln[3:]),
     ("line 4 has 3 cells", "fix or remove that line")),
    ("trajectory_header_only", lambda s, t: _edit_lines(_traj(s), lambda ln: ln[:1]),
     ("has 0 epochs", "at least 2")),
    ("trajectory_empty_file", lambda s, t: _traj(s).write_text(""), ("an empty file", "first line must name")),
    ("sbet_truncated", lambda s, t: _sbet_instead(s, 1000),
     ("not a multiple of the 136-byte sbet record", "truncated")),
    # control.csv
    ("control_text_coordinate", lambda s, t: _set_cell(s / "control.csv", 2, "x", "abc"),
     ("control file", "column 'x': 'abc' is not a number", "fix or remove that row")),
    ("control_missing_column", lambda s, t: _drop_column(s / "control.csv", "sd_z"),
     ("lacks column(s) sd_z", "id,x,y,z,sd_x,sd_y,sd_z")),
    ("control_duplicate_id", lambda s, t: _set_cell(s / "control.csv", 2, "id", "CP001"),
     ("id(s) cp001 appear more than once", "unique id")),
    ("control_empty_id", lambda s, t: _set_cell(s / "control.csv", 3, "id", ""),
     ("data row 3: the id is empty", "give every control point an id")),
    ("control_negative_sd", lambda s, t: _set_cell(s / "control.csv", 1, "sd_x", "-0.003"),
     ("sd_x of control point cp001 (data row 1) is -0.003", "positive number")),
    ("control_nan_coordinate", lambda s, t: _set_cell(s / "control.csv", 4, "z", "nan"),
     ("nan or infinite coordinate for control point cp004", "fix or remove")),
    ("control_header_only", lambda s, t: _edit_lines(s / "control.csv", lambda ln: ln[:1]),
     ("no control points", "remove the file")),
    ("control_ragged_row", lambda s, t: _edit_lines(s / "control.csv", lambda ln: ln + ["CP9,1,2"]),
     ("has 3 cells but the header has 7", "fix or remove that line")),
    # options
    ("out_dir_is_a_file", _out_dir_is_file, ("out_file is an existing file", "out_dir=")),
    ("out_dir_under_a_file", _out_dir_under_file, ("out_file is a file", "out_dir=")),
    ("unknown_anchors_value", lambda s, t: ["anchors=maybe"],
     ("anchors=maybe is not an option", "anchors=auto", "anchors=true", "anchors=false")),
    ("anchors_required_bad_grid_dir", lambda s, t: ["anchors=true", f"proj_grid_dir={s / 'control.csv'}"],
     ("proj_grid_dir=", "is not a folder", "pass the folder that holds the proj grid files")),
    ("unknown_option", lambda s, t: ["detector.no_such_option=1"], ("no_such_option", "railtraj --help")),
    ("unknown_key", lambda s, t: ["foo=1"], ("could not override 'foo'", "railtraj --help")),
    ("unknown_stage", lambda s, t: ["detector=nope"],
     ("could not find 'detector/nope'", "available options in 'detector':", "iss")),
    ("bad_value_type", lambda s, t: ["threads=many"], ("threads=many", "could not be converted to integer")),
    ("unknown_reference_run", lambda s, t: ["pipeline.reference_run=run_z"],
     ("reference_run 'run_z' is not a run of the survey", "runs: run_a, run_b")),
    ("no_tile_at_local_tile", lambda s, t: ["pipeline=local", "pipeline.tile=nowhere.laz"],
     ("no overlapping tile pair at tile='nowhere.laz'", "give a tile file name")),
    ("no_overlap", lambda s, t: ["pipeline.min_overlap_m=1000"],
     ("share no overlapping tiles", "same crs")),
    ("negative_max_memory", lambda s, t: ["max_memory_gb=-1"], ("max_memory_gb=-1", "0 for no limit")),
    # python, numpy and scipy alone take more than 50 MiB: stopped during detection, nothing written
    ("max_memory_exceeded", lambda s, t: ["max_memory_gb=0.05"],
     ("above max_memory_gb=0.05", "stopped before the machine swaps", "executor.workers=1")),
]


@pytest.mark.parametrize(("corrupt", "expected"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_is_one_line_exit_2(tiny_survey, tmp_path, corrupt, expected):
    survey = tmp_path / "survey"
    shutil.copytree(tiny_survey, survey)
    out = tmp_path / "out"
    out.mkdir()
    for name, text in PREVIOUS.items():  # what an earlier run left behind
        (out / name).write_text(text)
    extra = corrupt(survey, tmp_path)
    extra = extra if isinstance(extra, list) else []  # most corruptions return nothing
    keys = {a.split("=", 1)[0] for a in extra}
    defaults = {"survey_dir": survey, "out_dir": out, "anchors": "false"}
    res = railtraj(*(f"{k}={v}" for k, v in defaults.items() if k not in keys), *extra)
    assert res.returncode == 2, res.stderr[-3000:]
    assert "Traceback" not in res.stderr + res.stdout and "HYDRA_FULL_ERROR" not in res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("railtraj: error: "), res.stderr[-3000:]
    message = lines[0].lower()
    for fragment in expected:
        assert fragment in message, f"{fragment!r} not in {lines[0]!r}"
    assert "np.float64" not in message and "np.str_" not in message
    for name, text in PREVIOUS.items():
        assert (out / name).read_text() == text, f"{name} of the earlier run was changed"
    assert not list(out.rglob("*.part")) and not (out / "trajectories").exists()
    if (tmp_path / "out_file").exists():
        assert (tmp_path / "out_file").read_text() == "keep me\n"


def test_catalogue_is_large_enough():
    assert len(CASES) >= 30 and len({c[0] for c in CASES}) == len(CASES)


def test_unparsable_tile_crs_and_idle_optimizer_are_notes(tiny_survey, tmp_path):
    """Fallbacks that still give a result say so: a warning in the log and a note in metrics.json."""
    survey = tmp_path / "survey"
    shutil.copytree(tiny_survey, survey)
    tile = _tiles(survey)[0]
    las = laspy.read(tile)
    las.header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr("NOT A CRS"))
    las.header.global_encoding.wkt = True
    las.write(tile)
    out = tmp_path / "out"
    res = railtraj(f"survey_dir={survey}", f"out_dir={out}", "optimizer=identity", "pipeline.max_pairs=1",
                   "anchors=false")
    assert res.returncode == 0, res.stderr[-3000:]
    notes = json.loads((out / "metrics.json").read_text())["notes"]
    crs_notes = [n for n in notes if "cannot be parsed" in n]
    assert len(crs_notes) == 1 and tile.name in crs_notes[0] and "1 tile(s)" in crs_notes[0]
    assert "WARNING" in res.stdout and "cannot be parsed" in res.stdout
    assert "the optimizer left every trajectory unchanged" in notes
