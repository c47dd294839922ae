"""The output files of SPEC.md (offsets.csv, ties.csv, anchors.csv, metrics.json and the TUM
copy of each trajectory), written atomically, and readers for the CSVs so tests and tools can
check what was written.

Tables are formatted column by column with numpy (no per-row Python formatting). Missing values
(a tile pair with no reliable match) are written as ``nan``. Text cells are quoted only if they
contain a comma or a quote, as the csv module would.
"""

from __future__ import annotations

import json
import math
import os
from functools import reduce
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from railtraj.data import Ties, TileOffset, Trajectory
from railtraj.geo import body_to_world_matrices
from railtraj.io.atomic import atomic_write
from railtraj.io.trajectory_csv import read_text_columns, to_float

OFFSET_COLUMNS = ("run_a", "run_b", "tile_a", "tile_b", "dx", "dy", "dz", "sd_x", "sd_y", "sd_z",
                  "inliers", "status")
TIE_COLUMNS = ("run_a", "run_b", "time_a", "time_b", "xa", "ya", "za", "xb", "yb", "zb", "weight")
ANCHOR_COLUMNS = ("run_id", "time", "x", "y", "z", "lat", "lon", "h_ell", "sd_x", "sd_y", "sd_z")
TUM_COLUMNS = ("time", "x", "y", "z", "qx", "qy", "qz", "qw")
#: printf format per numeric column; text columns are absent. Metres to 1 micrometre, times to
#: 1 ns, latitude/longitude to 1e-9 degree (0.1 mm).
_FMT = {"dx": "%.6f", "dy": "%.6f", "dz": "%.6f", "sd_x": "%.6f", "sd_y": "%.6f", "sd_z": "%.6f",
        "inliers": "%d", "time": "%.9f", "time_a": "%.9f", "time_b": "%.9f", "weight": "%.9g",
        "lat": "%.9f", "lon": "%.9f", "h_ell": "%.6f",
        **{c: "%.6f" for c in ("x", "y", "z", "xa", "ya", "za", "xb", "yb", "zb")}}


def _quote(values: np.ndarray) -> np.ndarray:
    """CSV-quote the text cells that need it (those containing a comma or a double quote)."""
    v = np.asarray(values, dtype=str)
    if v.size == 0:
        return v
    needs = (np.char.find(v, ",") >= 0) | (np.char.find(v, '"') >= 0)
    quoted = np.char.add(np.char.add('"', np.char.replace(v, '"', '""')), '"')
    return np.where(needs, quoted, v)


def _write_table(path: str | os.PathLike, columns: dict[str, np.ndarray]) -> None:
    """Write equal-length columns as CSV, numeric ones with :data:`_FMT`, atomically."""
    cells = [np.char.mod(_FMT[name], np.asarray(col)) if name in _FMT else _quote(col)
             for name, col in columns.items()]
    n = len(cells[0])
    lines = reduce(lambda a, b: np.char.add(np.char.add(a, ","), b), cells) if n else []
    with atomic_write(path) as f:
        f.write(",".join(columns) + "\n")
        if n:
            f.write("\n".join(lines.tolist()) + "\n")


def write_offsets_csv(path: str | os.PathLike, offsets: list[TileOffset]) -> None:
    """OUT/offsets.csv: one row per matched tile pair; d moves run_b onto run_a (p_a = p_b + d)."""
    d = np.array([o.d for o in offsets], dtype=np.float64).reshape(-1, 3)
    sd = np.array([o.sd for o in offsets], dtype=np.float64).reshape(-1, 3)
    text = {c: np.array([getattr(o, c) for o in offsets], dtype=str)
            for c in ("run_a", "run_b", "tile_a", "tile_b", "status")}
    _write_table(path, {
        **{c: text[c] for c in ("run_a", "run_b", "tile_a", "tile_b")},
        "dx": d[:, 0], "dy": d[:, 1], "dz": d[:, 2],
        "sd_x": sd[:, 0], "sd_y": sd[:, 1], "sd_z": sd[:, 2],
        "inliers": np.array([o.inliers for o in offsets], dtype=np.int64),
        "status": text["status"]})


def write_ties_csv(path: str | os.PathLike, ties_list: list[Ties]) -> None:
    """OUT/ties.csv: every matched feature of every run pair, one row each."""
    def cat(key: str, width: int | None = None) -> np.ndarray:
        parts = [getattr(t, key) for t in ties_list]
        empty = np.zeros((0, width) if width else 0)
        return np.concatenate(parts) if parts else empty

    xa, xb = cat("xyz_a", 3), cat("xyz_b", 3)
    _write_table(path, {
        "run_a": np.concatenate([np.full(len(t), t.run_a) for t in ties_list] or [[]]),
        "run_b": np.concatenate([np.full(len(t), t.run_b) for t in ties_list] or [[]]),
        "time_a": cat("time_a"), "time_b": cat("time_b"),
        "xa": xa[:, 0], "ya": xa[:, 1], "za": xa[:, 2],
        "xb": xb[:, 0], "yb": xb[:, 1], "zb": xb[:, 2], "weight": cat("weight")})


def write_anchors_csv(path: str | os.PathLike, rows: dict[str, np.ndarray]) -> None:
    """OUT/anchors.csv from a dict of equal-length columns named as :data:`ANCHOR_COLUMNS`.

    x, y, z are in the survey CRS; lat, lon (degrees) and h_ell (m) in the SBET's frame
    (``sbet_crs``: ETRS89 for a British survey, else WGS 84, unless given), which metrics.json
    records as ``anchors_crs``, so POSPac takes them back in the frame it produced."""
    missing = [c for c in ANCHOR_COLUMNS if c not in rows]
    if missing:
        raise ValueError(f"anchors: missing column(s) {', '.join(missing)}")
    lengths = {len(np.atleast_1d(rows[c])) for c in ANCHOR_COLUMNS}
    if len(lengths) > 1:
        raise ValueError(f"anchors: columns have different lengths {sorted(lengths)}")
    _write_table(path, {c: np.atleast_1d(rows[c]) for c in ANCHOR_COLUMNS})


def body_to_map_quaternions(rpy_deg: np.ndarray) -> np.ndarray:
    """(n, 4) unit quaternions (qx, qy, qz, qw), qw >= 0, rotating body vectors (x forward,
    y right, z down) into the map frame (east, north, up): the same M @ R as georeferencing."""
    return Rotation.from_matrix(body_to_world_matrices(rpy_deg)).as_quat(canonical=True)


def write_trajectory_tum(path: str | os.PathLike, traj: Trajectory) -> None:
    """OUT/trajectories/<run_id>.tum: ``time x y z qx qy qz qw`` per epoch, space-separated, for
    evo and other SLAM tools; positions in the survey CRS, orientation body -> map."""
    table = np.column_stack([traj.time, traj.xyz, body_to_map_quaternions(traj.rpy)])
    fmt = ["%.9f"] + ["%.6f"] * 3 + ["%.9f"] * 4
    with atomic_write(path) as f:
        np.savetxt(f, table, fmt=fmt, delimiter=" ", header=" ".join(TUM_COLUMNS), comments="# ")


def _plain(obj):
    """``obj`` with numpy types, paths and tuples made JSON-native and NaN/inf turned to None."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, np.generic):
        return _plain(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def write_json(path: str | os.PathLike, obj) -> None:
    """Write ``obj`` as indented JSON atomically; numpy values converted, NaN/inf -> null."""
    text = json.dumps(_plain(obj), indent=2, allow_nan=False)
    with atomic_write(path) as f:
        f.write(text + "\n")


def _read_table(path: str | os.PathLike, names: tuple[str, ...], what: str) -> dict[str, np.ndarray]:
    cols = read_text_columns(path, names, what)
    out = {}
    for c in names:
        if c not in _FMT:
            out[c] = cols[c]
        elif c == "inliers":
            out[c] = to_float(cols[c], c, path, what).astype(np.int64)
        else:
            out[c] = to_float(cols[c], c, path, what)
    return out


def read_offsets_csv(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Columns of an offsets.csv (text columns as str arrays, numbers as float64/int64)."""
    return _read_table(path, OFFSET_COLUMNS, "offsets file")


def read_ties_csv(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Columns of a ties.csv."""
    return _read_table(path, TIE_COLUMNS, "ties file")


def read_anchors_csv(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Columns of an anchors.csv."""
    return _read_table(path, ANCHOR_COLUMNS, "anchors file")
