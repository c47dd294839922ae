"""Applanix SBET trajectories and SMRMSG accuracy files (POSPac output), read and written as-is.

Both are headerless arrays of little-endian float64 records, so numpy structured dtypes read and
write them byte for byte. Angles in the files are radians; latitude/longitude/ellipsoidal height
are in the frame of the GNSS processing, ``sbet_crs`` (a geographic 3-D CRS): by default ETRS89
(EPSG:4937), what a UK post-processing run referenced to OS Net delivers, for a British survey
CRS, and WGS 84 (EPSG:4979) for any other (:func:`railtraj.crs.default_sbet_crs`).

Converting to a :class:`Trajectory` projects positions to the survey CRS and turns SBET's *true*
heading into the *grid* heading SPEC.md asks for, using the projection's meridian convergence
(``grid = true - convergence``: 0 on the central meridian, about -1.8 degrees in Wales and
several degrees in the Hebrides). Roll and pitch are unchanged by that rotation about the
vertical.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from pyproj.exceptions import ProjError

from railtraj.crs import from_geographic, grid_convergence, to_geographic
from railtraj.data import Trajectory
from railtraj.errors import CRSError, FormatError, TrajectoryError
from railtraj.io.atomic import atomic_write
from railtraj.io.trajectory_csv import require_file

SBET_FIELDS = ("time", "lat", "lon", "z", "vx", "vy", "vz", "roll", "pitch", "heading",
               "wander", "ax", "ay", "az", "wx", "wy", "wz")
SMRMSG_FIELDS = ("time", "north_rms", "east_rms", "down_rms", "vnorth_rms", "veast_rms",
                 "vdown_rms", "roll_rms", "pitch_rms", "heading_rms")
#: 17 float64 per record (136 bytes): GPS time, lat, lon (rad), ellipsoidal height, velocities in
#: the wander-angle frame, roll, pitch, true heading, wander angle (rad), body accelerations and
#: angular rates.
SBET_DTYPE = np.dtype([(f, "<f8") for f in SBET_FIELDS])
#: 10 float64 per record (80 bytes): GPS time, N/E/D position RMS (m), N/E/D velocity RMS (m/s),
#: roll/pitch/heading RMS (Applanix: arc-minutes).
SMRMSG_DTYPE = np.dtype([(f, "<f8") for f in SMRMSG_FIELDS])


def _read_records(path: str | os.PathLike, dtype: np.dtype, kind: str) -> np.ndarray:
    p = require_file(path, f"{kind} file")
    size = p.stat().st_size
    if size == 0 or size % dtype.itemsize:
        raise FormatError(
            f"{kind} file {p} is {size} bytes, not a multiple of the {dtype.itemsize}-byte {kind} "
            f"record: the file is {'empty' if size == 0 else 'truncated'} or not an {kind}")
    records = np.fromfile(p, dtype=dtype)
    if not np.isfinite(records["time"]).all() or (np.diff(records["time"]) < 0).any():
        raise FormatError(f"{kind} file {p} has non-finite or decreasing times: it is corrupt or "
                          f"not an {kind}; re-export it from POSPac")
    return records


def _write_records(path: str | os.PathLike, records: np.ndarray, dtype: np.dtype) -> None:
    data = np.ascontiguousarray(records, dtype=dtype)
    with atomic_write(path, "wb") as f:
        f.write(data.tobytes())


def read_sbet(path: str | os.PathLike) -> np.ndarray:
    """All records of an SBET file as a structured array with fields :data:`SBET_FIELDS`."""
    records = _read_records(path, SBET_DTYPE, "SBET")
    used = ("lat", "lon", "z", "roll", "pitch", "heading")
    bad = ~np.isfinite(np.column_stack([records[f] for f in used]))
    if bad.any():
        k, j = (int(v) for v in np.argwhere(bad)[0])
        raise FormatError(f"SBET file {path}: {used[j]} is {float(records[used[j]][k])} at record "
                          f"{k + 1} (time {float(records['time'][k])}): it is corrupt or not an "
                          "SBET; re-export it from POSPac")
    if (np.abs(records["lat"]) > np.pi / 2).any() or (np.abs(records["lon"]) > 2 * np.pi).any():
        raise FormatError(f"SBET file {path} has latitudes or longitudes beyond +-90/360 degrees "
                          "in radians: it is corrupt or not an SBET")
    return records


def write_sbet(path: str | os.PathLike, records: np.ndarray) -> None:
    """Write SBET records atomically; what :func:`read_sbet` returns writes back byte-identical."""
    _write_records(path, records, SBET_DTYPE)


def read_smrmsg(path: str | os.PathLike) -> np.ndarray:
    """All records of an SMRMSG file as a structured array with fields :data:`SMRMSG_FIELDS`.

    Position RMS must be positive and the others not negative: they become the trajectory's sd,
    which weighs every epoch in the adjustment.
    """
    records = _read_records(path, SMRMSG_DTYPE, "SMRMSG")
    for name in SMRMSG_FIELDS[1:]:
        col = records[name]
        bad = ~(col > 0) if name in ("north_rms", "east_rms", "down_rms") else ~(col >= 0)
        if bad.any():
            k = int(np.argmax(bad))
            raise FormatError(
                f"SMRMSG file {path}: {name} is {float(col[k])} at record {k + 1} (time "
                f"{float(records['time'][k])}) and {int(bad.sum())} record(s) in all; RMS values "
                "must be positive: it is corrupt or not an SMRMSG, re-export it from POSPac")
    return records


def write_smrmsg(path: str | os.PathLike, records: np.ndarray) -> None:
    """Write SMRMSG records atomically (byte-identical round trip)."""
    _write_records(path, records, SMRMSG_DTYPE)


def smrmsg_sd_at(smrmsg: np.ndarray, times: np.ndarray) -> np.ndarray:
    """(n, 3) position sd (east, north, down RMS) interpolated linearly at ``times``.

    SMRMSG is usually 1 Hz against a 200 Hz SBET, so the ends are held constant for up to two
    SMRMSG intervals; times further outside mean the files are from different processing runs.
    """
    t = smrmsg["time"]
    step = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    if times.min() < t[0] - 2 * step or times.max() > t[-1] + 2 * step:
        raise TrajectoryError(
            f"SMRMSG covers {t[0]:.3f}-{t[-1]:.3f} s but the SBET {times.min():.3f}-"
            f"{times.max():.3f} s: use the SMRMSG file from the same POSPac run as the SBET")
    cols = ("east_rms", "north_rms", "down_rms")
    return np.column_stack([np.interp(times, t, smrmsg[c]) for c in cols])


def sbet_to_trajectory(records: np.ndarray, crs: str = "EPSG:27700",
                       grid_dir: str | os.PathLike | None = None,
                       smrmsg: np.ndarray | None = None, run_id: str = "",
                       sbet_crs: str | None = None) -> Trajectory:
    """A SPEC trajectory from SBET records: survey-CRS positions, degrees, grid heading.

    Positions go from ``sbet_crs`` (lat, lon, h_ell; None: the survey's default frame) to ``crs``
    through :mod:`railtraj.crs` (which refuses inaccurate transforms). Heading: ``grid = true - meridian convergence``, wrapped to
    [0, 360). sd comes from ``smrmsg`` (east, north, down RMS) when given.
    """
    lat, lon = np.degrees(records["lat"]), np.degrees(records["lon"])
    xyz = from_geographic(lat, lon, records["z"], crs, grid_dir, sbet_crs)
    try:
        convergence = grid_convergence(lat, lon, crs)
    except ProjError:
        raise CRSError(f"SBET positions (latitude {lat.min():.3f} to {lat.max():.3f}, longitude "
                       f"{lon.min():.3f} to {lon.max():.3f} degrees) are outside the area where "
                       f"{crs} is defined: check crs= (and sbet_crs=) fit the survey") from None
    heading = np.mod(np.degrees(records["heading"]) - convergence, 360.0)
    rpy = np.column_stack([np.degrees(records["roll"]), np.degrees(records["pitch"]), heading])
    sd = None if smrmsg is None else smrmsg_sd_at(smrmsg, records["time"])
    return Trajectory(time=records["time"], xyz=xyz, rpy=rpy, sd=sd, run_id=run_id)


def trajectory_to_sbet(traj: Trajectory, crs: str = "EPSG:27700",
                       grid_dir: str | os.PathLike | None = None,
                       template: np.ndarray | None = None,
                       sbet_crs: str | None = None) -> np.ndarray:
    """SBET records for ``traj`` in the frame ``sbet_crs`` (the inverse of
    :func:`sbet_to_trajectory`).

    Time, position and attitude come from ``traj``. The other fields are copied from
    ``template`` (records with the same epochs) when given; otherwise the wander angle,
    accelerations and angular rates are zero and the velocities are finite differences of the
    positions in the wander frame with wander 0: vx north, vy west, vz up (the axes PDAL's
    reference SBET shows when its velocities are compared with its positions).
    """
    lat, lon, h = to_geographic(traj.xyz, crs, grid_dir, sbet_crs)
    if template is not None:
        if len(template) != len(traj) or not np.array_equal(template["time"], traj.time):
            raise TrajectoryError(f"SBET template has {len(template)} records that do not match "
                                  f"the {len(traj)} epochs of trajectory {traj.run_id!r}: pass "
                                  "the SBET the trajectory was read from, or no template")
        out = np.array(template, dtype=SBET_DTYPE, copy=True)
    else:
        out = np.zeros(len(traj), dtype=SBET_DTYPE)
        v_enu = np.gradient(traj.xyz, traj.time, axis=0)
        out["vx"], out["vy"], out["vz"] = v_enu[:, 1], -v_enu[:, 0], v_enu[:, 2]
    true_heading = traj.rpy[:, 2] + grid_convergence(lat, lon, crs)
    out["time"] = traj.time
    out["lat"], out["lon"], out["z"] = np.radians(lat), np.radians(lon), h
    out["roll"], out["pitch"] = np.radians(traj.rpy[:, 0]), np.radians(traj.rpy[:, 1])
    out["heading"] = np.radians(np.mod(true_heading, 360.0))
    return out


def find_smrmsg(sbet_path: str | os.PathLike) -> Path | None:
    """The SMRMSG file beside an SBET: same stem with suffix .smrmsg, else the folder's only one."""
    p = Path(sbet_path)
    beside = p.with_suffix(".smrmsg")
    if beside.is_file():
        return beside
    found = sorted(p.parent.glob("*.smrmsg"))
    return found[0] if len(found) == 1 else None
