"""trajectory.csv (SPEC.md): read and write one run's trajectory, plus the CSV helpers the other
readers share.

Columns are found by header name (case-insensitive, any order, extra columns ignored), so files
exported by other tools load as long as they use SPEC's names. Numbers are parsed by numpy in C;
only when that fails is the file scanned line by line to name the offending line and column.
"""

from __future__ import annotations

import csv
import os
import warnings
from pathlib import Path

import numpy as np

from railtraj.data import Trajectory
from railtraj.errors import FormatError, InputError, TrajectoryError
from railtraj.io.atomic import atomic_write

REQUIRED = ("time", "x", "y", "z", "roll", "pitch", "heading")
OPTIONAL_SD = ("sd_x", "sd_y", "sd_z")
#: printf formats for writing: time to 1 ns, positions and sd to 1 micrometre, angles to 1e-9 deg.
FORMATS = {"time": "%.9f", "x": "%.6f", "y": "%.6f", "z": "%.6f", "roll": "%.9f",
           "pitch": "%.9f", "heading": "%.9f", "sd_x": "%.6f", "sd_y": "%.6f", "sd_z": "%.6f"}


def require_file(path: str | os.PathLike, what: str) -> Path:
    """Return ``path`` as a Path, or raise :class:`InputError` if it is not an existing file."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{what} {p} does not exist or is not a file: check the path")
    return p


def not_text_error(path: Path, what: str) -> FormatError:
    """The error for a file that is not UTF-8 text (a binary file, or another encoding)."""
    return FormatError(f"{what} {path} is not UTF-8 text (it has bytes that are not UTF-8): "
                       "save it as a plain-text UTF-8 (or ASCII) CSV")


def read_header(path: Path, required: tuple[str, ...], what: str) -> list[str]:
    """Lower-cased, stripped column names of a CSV's first line; raise if a required one is missing."""
    try:
        with open(path, encoding="utf-8-sig") as f:
            first = f.readline()
    except UnicodeDecodeError:
        raise not_text_error(path, what) from None
    names = [c.strip().strip('"').lower() for c in first.rstrip("\r\n").split(",")]
    missing = [c for c in required if c not in names]
    if not first.strip() or missing:
        raise FormatError(
            f"{what} {path} lacks column(s) {', '.join(missing or required)} in its header line "
            f"(found: {first.strip() or 'an empty file'}); the first line must name the columns "
            f"{','.join(required)}")
    return names


def _locate_bad_cell(path: Path, cols: dict[str, int], what: str) -> FormatError:
    """The error for a file numpy could not parse: its first bad cell, or not being text."""
    try:
        return _scan_for_bad_cell(path, cols, what)
    except UnicodeDecodeError:
        return not_text_error(path, what)


def _scan_for_bad_cell(path: Path, cols: dict[str, int], what: str) -> FormatError:
    """Find the first line whose used cells are not numbers (error path only, so a plain scan)."""
    with open(path, encoding="utf-8-sig") as f:
        for lineno, line in enumerate(f, start=1):
            if lineno == 1 or not line.strip() or line.lstrip().startswith("#"):
                continue
            cells = line.rstrip("\r\n").split(",")
            for name, k in cols.items():
                if k >= len(cells):
                    return FormatError(f"{what} {path} line {lineno} has {len(cells)} cells but "
                                       f"column {name!r} is number {k + 1}: fix or remove that line")
                try:
                    float(cells[k])
                except ValueError:
                    return FormatError(f"{what} {path} line {lineno}, column {name!r}: "
                                       f"{cells[k].strip()!r} is not a number; fix or remove that line")
    return FormatError(f"{what} {path} could not be parsed as comma-separated numbers: "
                       "check the delimiter is ',' and the file is plain text")


def read_numeric_columns(path: str | os.PathLike, required: tuple[str, ...],
                         optional: tuple[str, ...] = (), what: str = "CSV file") -> dict[str, np.ndarray]:
    """Float64 columns by header name: all of ``required`` and those of ``optional`` present.

    Blank lines and lines starting with ``#`` are skipped. Raises :class:`FormatError` naming the
    file, line and column of the first cell that is not a number.
    """
    p = require_file(path, what)
    names = read_header(p, required, what)
    wanted = [c for c in (*required, *optional) if c in names]
    cols = {c: names.index(c) for c in wanted}
    try:
        with warnings.catch_warnings():  # "input contained no data" is reported by the caller
            warnings.simplefilter("ignore", UserWarning)
            table = np.loadtxt(p, delimiter=",", skiprows=1, usecols=list(cols.values()),
                               ndmin=2, dtype=np.float64, encoding="utf-8-sig", comments="#")
    except ValueError:
        raise _locate_bad_cell(p, cols, what) from None
    return {c: table[:, i] for i, c in enumerate(wanted)}


def read_text_columns(path: str | os.PathLike, required: tuple[str, ...],
                      what: str = "CSV file") -> dict[str, np.ndarray]:
    """String columns by header name, for small tables with text cells (control, outputs).

    Uses the csv module, so quoted cells (a tile name with a comma) read back intact.
    """
    p = require_file(path, what)
    names = read_header(p, required, what)
    with open(p, encoding="utf-8-sig", newline="") as f:
        reader = csv.reader(f)
        rows = []
        try:
            next(reader, None)
            for row in reader:
                if not row or row[0].lstrip().startswith("#"):
                    continue
                if len(row) != len(names):
                    raise FormatError(f"{what} {p} line {reader.line_num} has {len(row)} cells but "
                                      f"the header has {len(names)}: fix or remove that line")
                rows.append(row)
        except UnicodeDecodeError:
            raise not_text_error(p, what) from None
        except csv.Error as err:
            raise FormatError(f"{what} {p} line {reader.line_num} is not valid CSV ({err}): "
                              "check its quotes (\") are paired, or fix that line") from None
    table = np.array(rows, dtype=str).reshape(len(rows), len(names))
    return {c: np.char.strip(table[:, names.index(c)]) for c in required}


def to_float(col: np.ndarray, name: str, path: str | os.PathLike, what: str) -> np.ndarray:
    """Convert a string column from :func:`read_text_columns` to float64, naming a bad cell."""
    try:
        return col.astype(np.float64)
    except ValueError:
        bad = next(i for i, v in enumerate(col) if not _is_float(v))
        raise FormatError(f"{what} {path}, data row {bad + 1}, column {name!r}: "
                          f"{str(col[bad])!r} is not a number; fix or remove that row") from None


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def read_trajectory_csv(path: str | os.PathLike, run_id: str = "") -> Trajectory:
    """Read a SPEC trajectory.csv: time,x,y,z,roll,pitch,heading and optional sd_x,sd_y,sd_z.

    sd columns are used only when all three are present. Non-finite values, sd that are not
    positive and unsorted times are reported with the file and row, so the surveyor can fix the
    export (a negative sd would otherwise weigh that epoch wrongly without a word).
    """
    what = "trajectory"
    cols = read_numeric_columns(path, REQUIRED, OPTIONAL_SD, what)
    have_sd = all(c in cols for c in OPTIONAL_SD)
    for name, col in cols.items():
        bad = ~np.isfinite(col)
        if bad.any():
            row = int(np.argmax(bad))
            raise TrajectoryError(
                f"{what} {path}: column {name!r} is {float(col[row])} at data row {row + 1} "
                f"(time {float(cols['time'][row])}); remove or fill that epoch")
    if have_sd:
        _check_sd(np.column_stack([cols[c] for c in OPTIONAL_SD]), cols["time"], path, what)
    try:
        return Trajectory(
            time=cols["time"],
            xyz=np.column_stack([cols["x"], cols["y"], cols["z"]]),
            rpy=np.column_stack([cols["roll"], cols["pitch"], cols["heading"]]),
            sd=np.column_stack([cols[c] for c in OPTIONAL_SD]) if have_sd else None,
            run_id=run_id)
    except TrajectoryError as err:
        raise TrajectoryError(f"{path}: {err}") from None


def _check_sd(sd: np.ndarray, time: np.ndarray, path, what: str) -> None:
    """Raise if an sd is zero or negative: a 1-sigma must be positive to weigh its epoch."""
    bad = ~(sd > 0)
    if bad.any():
        row, k = (int(v) for v in np.argwhere(bad)[0])
        n_bad = int(bad.any(axis=1).sum())
        raise TrajectoryError(
            f"{what} {path}: column {OPTIONAL_SD[k]!r} is {float(sd[row, k])} at data row "
            f"{row + 1} (time {float(time[row])}) and {n_bad} row(s) in all; sd_x, sd_y, sd_z "
            "must be positive 1-sigma in metres: fix the export, or remove the three sd columns")


def write_trajectory_csv(path: str | os.PathLike, traj: Trajectory) -> None:
    """Write ``traj`` as a SPEC trajectory.csv, atomically, at round-trip precision.

    Times get 9 decimals (1 ns), positions and sd 6 (1 micrometre), angles 9 (1e-9 degree):
    far below any survey tolerance, so read -> write -> read changes nothing that matters.
    """
    names = list(REQUIRED)
    columns = [traj.time[:, None], traj.xyz, traj.rpy]
    if traj.sd is not None:
        names += OPTIONAL_SD
        columns.append(traj.sd)
    table = np.hstack(columns)
    with atomic_write(path) as f:
        np.savetxt(f, table, fmt=[FORMATS[c] for c in names], delimiter=",",
                   header=",".join(names), comments="")
