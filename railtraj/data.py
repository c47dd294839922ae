"""The data model the stages exchange: numpy-backed dataclasses that check their own shapes.

Nothing here reads or writes files (that is :mod:`railtraj.io`) and nothing here is an algorithm
beyond what a type needs to be useful (interpolating a trajectory, transforming points).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from railtraj.errors import TrajectoryError
from railtraj.geo import NED_TO_ENU, attitude_to_rotation, rotation_to_attitude


def extent(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Minimum and maximum corner of an (n, 3) array of points, column by column: numpy's
    ``min(axis=0)`` walks an (n, 3) array row by row, 15 times slower (85 ms on a tile of
    2.65 M points, read three times per tile pair)."""
    columns = range(xyz.shape[1])
    return np.array([xyz[:, k].min() for k in columns]), np.array([xyz[:, k].max() for k in columns])


def _as_array(name: str, value, shape_tail: tuple[int, ...], dtype=np.float64) -> np.ndarray:
    """Return ``value`` as a C-contiguous array of ``dtype`` with shape (n, *shape_tail), or raise."""
    arr = np.ascontiguousarray(value, dtype=dtype)
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        want = "(n" + "".join(f", {s}" for s in shape_tail) + ")"
        raise ValueError(f"{name} must have shape {want}, got {arr.shape}")
    return arr


@dataclass(frozen=True)
class Trajectory:
    """One run's trajectory: body (IMU) origin and attitude per epoch.

    ``xyz`` is easting, northing, height in the survey CRS; ``rpy`` is roll, pitch, heading in
    degrees (SPEC.md convention); ``sd`` the optional 1-sigma position uncertainty per axis.
    """

    time: np.ndarray
    xyz: np.ndarray
    rpy: np.ndarray
    sd: np.ndarray | None = None
    run_id: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "time", _as_array("time", self.time, ()))
        n = len(self.time)
        object.__setattr__(self, "xyz", _as_array("xyz", self.xyz, (3,)))
        object.__setattr__(self, "rpy", _as_array("rpy", self.rpy, (3,)))
        if self.sd is not None:
            object.__setattr__(self, "sd", _as_array("sd", self.sd, (3,)))
        for name in ("xyz", "rpy", "sd"):
            arr = getattr(self, name)
            if arr is not None and len(arr) != n:
                raise TrajectoryError(f"trajectory {self.run_id!r}: {name} has {len(arr)} rows but time has {n}")
        if n < 2:
            raise TrajectoryError(f"trajectory {self.run_id!r} has {n} epochs; at least 2 are needed")
        for name in ("time", "xyz", "rpy", "sd"):
            arr = getattr(self, name)
            if arr is not None and not np.isfinite(arr).all():
                row = int(np.flatnonzero((~np.isfinite(arr.reshape(n, -1))).any(axis=1))[0])
                raise TrajectoryError(
                    f"trajectory {self.run_id!r} has a NaN or infinite {name} at epoch {row} "
                    f"(time {float(self.time[row])}); remove or fill that epoch")
        steps = np.diff(self.time)
        if (steps <= 0).any():
            k = int(np.argmax(steps <= 0))
            raise TrajectoryError(
                f"trajectory {self.run_id!r} times are not strictly increasing at epoch {k + 1} "
                f"({float(self.time[k])} then {float(self.time[k + 1])}); sort it and drop duplicate epochs")

    def __len__(self) -> int:
        return len(self.time)

    @property
    def span(self) -> tuple[float, float]:
        """First and last epoch time."""
        return float(self.time[0]), float(self.time[-1])

    def covers(self, times: np.ndarray) -> np.ndarray:
        """Boolean mask of ``times`` that lie within the trajectory's time span."""
        t = np.asarray(times, dtype=float)
        return (t >= self.time[0]) & (t <= self.time[-1])

    def check_covers(self, times: np.ndarray, what: str = "points") -> None:
        """Raise :class:`TrajectoryError` unless every time in ``times`` is within the span."""
        check_span(self.run_id, self.span, times, what)

    def rotations(self) -> Rotation:
        """Body -> NED rotation per epoch."""
        return attitude_to_rotation(self.rpy)

    def travelled(self) -> np.ndarray:
        """Distance travelled (m, 3-D) from the first epoch to each epoch."""
        return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(self.xyz, axis=0), axis=1))])

    def position_at(self, times: np.ndarray) -> np.ndarray:
        """Position (linear) at arbitrary ``times`` within the span: no attitude, so no rotation
        of every epoch (25 ms on a 10 min run) is built."""
        t = np.asarray(times, dtype=float)
        self.check_covers(t, "requested times")
        return np.column_stack([np.interp(t, self.time, self.xyz[:, k]) for k in range(3)])

    def interpolate(self, times: np.ndarray) -> tuple[np.ndarray, Rotation]:
        """Position (linear) and body -> NED rotation (slerp) at arbitrary ``times`` within the span."""
        t = np.asarray(times, dtype=float)
        return self.position_at(t), Slerp(self.time, self.rotations())(t)

    def pose_at(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Position (n, 3) and body -> world (ENU) matrices (n, 3, 3) at ``times``."""
        xyz, rot = self.interpolate(times)
        return xyz, NED_TO_ENU @ rot.as_matrix()

    def body_to_world(self, times: np.ndarray, p_body: np.ndarray) -> np.ndarray:
        """World coordinates of body-frame vectors ``p_body`` measured at ``times``."""
        xyz, rot = self.interpolate(times)
        return xyz + rot.apply(np.asarray(p_body, dtype=float)) @ NED_TO_ENU.T

    def world_to_body(self, times: np.ndarray, p_world: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`body_to_world`."""
        xyz, rot = self.interpolate(times)
        return rot.inv().apply((np.asarray(p_world, dtype=float) - xyz) @ NED_TO_ENU.T)

    def sd_at(self, times: np.ndarray) -> np.ndarray | None:
        """Reported 1-sigma position uncertainty interpolated at ``times`` (None if not reported)."""
        if self.sd is None:
            return None
        t = np.asarray(times, dtype=float)
        return np.column_stack([np.interp(t, self.time, self.sd[:, k]) for k in range(3)])

    def with_positions(self, xyz: np.ndarray, sd: np.ndarray | None = None) -> Trajectory:
        """A copy with new positions (and uncertainties); epochs and attitude unchanged."""
        return replace(self, xyz=xyz, sd=self.sd if sd is None else sd)

    def with_attitude_from(self, rot: Rotation) -> Trajectory:
        """A copy with attitude taken from body -> NED rotations ``rot``."""
        return replace(self, rpy=rotation_to_attitude(rot))


def reports_gnss(sd: np.ndarray, gnss_sd_m: float) -> np.ndarray:
    """Where a reported sd (n, 3) is of GNSS quality: its horizontal sd at most ``gnss_sd_m``.
    The one test the sd check, the same-track comparison and the portals share."""
    return np.linalg.norm(np.asarray(sd)[:, :2], axis=1) <= gnss_sd_m


def check_span(run_id: str, span: tuple[float, float], times: np.ndarray, what: str = "points") -> None:
    """Raise :class:`TrajectoryError` unless every time in ``times`` lies within ``span``, the
    (first, last) epoch time of run ``run_id``'s trajectory. Takes the span rather than the
    trajectory so that a worker checking one tile needs two numbers, not the whole run."""
    t = np.asarray(times, dtype=float)
    inside = (t >= span[0]) & (t <= span[1])
    if len(t) and not inside.all():
        outside = int((~inside).sum())
        raise TrajectoryError(
            f"trajectory {run_id!r} ({span[0]:.3f}-{span[1]:.3f} s) does not cover "
            f"{outside} of {len(t)} {what} ({t.min():.3f}-{t.max():.3f} s); "
            "supply the trajectory for the whole run or check the time base (GPS week seconds vs adjusted standard time)")


@dataclass(frozen=True)
class PointTile:
    """One LAS/LAZ tile of one run: georeferenced points with their GPS times."""

    xyz: np.ndarray
    gps_time: np.ndarray
    intensity: np.ndarray | None = None
    run_id: str = ""
    name: str = ""
    # (m, 3) the run's points just beyond the tile (its neighbouring tiles): what a test of a
    # surface's shape may look at past the tile's edge (railtraj.matching.objects); never matched
    context: np.ndarray | None = None
    # (3,) the run's horizontal direction of travel over the tile, from its trajectory, where the
    # pipeline gives it (railtraj.track_direction.pair_travel): a matcher's check of the track
    # direction it fits; None: not known
    travel: np.ndarray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "xyz", _as_array("xyz", self.xyz, (3,)))
        object.__setattr__(self, "gps_time", _as_array("gps_time", self.gps_time, ()))
        if self.context is not None:
            object.__setattr__(self, "context", _as_array("context", self.context, (3,)))
        if len(self.gps_time) != len(self.xyz):
            raise ValueError(f"tile {self.name!r}: {len(self.xyz)} points but {len(self.gps_time)} gps_time values")
        if self.intensity is not None:
            object.__setattr__(self, "intensity", _as_array("intensity", self.intensity, (), np.uint16))
            if len(self.intensity) != len(self.xyz):
                raise ValueError(f"tile {self.name!r}: intensity length differs from point count")

    def __len__(self) -> int:
        return len(self.xyz)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned minimum and maximum corner."""
        if len(self) == 0:
            return np.full(3, np.nan), np.full(3, np.nan)
        return extent(self.xyz)

    def subset(self, mask: np.ndarray) -> PointTile:
        """The points selected by a boolean mask or index array (without the context: what
        lies around a part of the tile is not what lies around the tile)."""
        return replace(self, xyz=self.xyz[mask], gps_time=self.gps_time[mask],
                       intensity=None if self.intensity is None else self.intensity[mask], context=None)

    def translated(self, d: np.ndarray) -> PointTile:
        """A copy with every point moved by the vector ``d``."""
        d = np.asarray(d, dtype=float)
        return replace(self, xyz=self.xyz + d, context=None if self.context is None else self.context + d)


@dataclass(frozen=True)
class Keypoints:
    """Keypoints of one tile: positions, the GPS time of the point each stands for, a saliency,
    and optional descriptors (one row per keypoint)."""

    xyz: np.ndarray
    gps_time: np.ndarray
    score: np.ndarray | None = None
    descriptors: np.ndarray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "xyz", _as_array("xyz", self.xyz, (3,)))
        object.__setattr__(self, "gps_time", _as_array("gps_time", self.gps_time, ()))
        n = len(self.xyz)
        if self.score is None:
            object.__setattr__(self, "score", np.ones(n))
        object.__setattr__(self, "score", _as_array("score", self.score, ()))
        if self.descriptors is not None:
            object.__setattr__(self, "descriptors", np.ascontiguousarray(self.descriptors, dtype=np.float64))
        for name in ("gps_time", "score", "descriptors"):
            arr = getattr(self, name)
            if arr is not None and len(arr) != n:
                raise ValueError(f"keypoints: {name} has {len(arr)} rows, xyz has {n}")

    def __len__(self) -> int:
        return len(self.xyz)

    def with_descriptors(self, descriptors: np.ndarray) -> Keypoints:
        return replace(self, descriptors=descriptors)

    def subset(self, idx: np.ndarray) -> Keypoints:
        return Keypoints(self.xyz[idx], self.gps_time[idx], self.score[idx],
                         None if self.descriptors is None else self.descriptors[idx])

    @staticmethod
    def concatenate(parts: list[Keypoints]) -> Keypoints:
        """The keypoints of ``parts`` in order (descriptors where every part has them)."""
        described = all(p.descriptors is not None for p in parts)
        return Keypoints(np.vstack([p.xyz for p in parts]), np.concatenate([p.gps_time for p in parts]),
                         np.concatenate([p.score for p in parts]),
                         np.vstack([p.descriptors for p in parts]) if described else None)


@dataclass(frozen=True)
class Ties:
    """Matched features between two runs (rows of OUT/ties.csv).

    Row i says: the feature seen at ``xyz_a[i]`` by ``run_a`` at ``time_a[i]`` is the same object
    as the one seen at ``xyz_b[i]`` by ``run_b`` at ``time_b[i]``; ``weight`` is its relative weight.
    """

    run_a: str
    run_b: str
    time_a: np.ndarray
    time_b: np.ndarray
    xyz_a: np.ndarray
    xyz_b: np.ndarray
    weight: np.ndarray

    def __post_init__(self) -> None:
        for name, tail in (("time_a", ()), ("time_b", ()), ("xyz_a", (3,)), ("xyz_b", (3,)), ("weight", ())):
            object.__setattr__(self, name, _as_array(name, getattr(self, name), tail))
        n = len(self.time_a)
        if any(len(getattr(self, k)) != n for k in ("time_b", "xyz_a", "xyz_b", "weight")):
            raise ValueError("ties: all columns must have the same length")

    def __len__(self) -> int:
        return len(self.time_a)

    @classmethod
    def empty(cls, run_a: str = "", run_b: str = "") -> Ties:
        z = np.zeros(0)
        return cls(run_a, run_b, z, z, np.zeros((0, 3)), np.zeros((0, 3)), z)

    @classmethod
    def concat(cls, parts: list[Ties]) -> list[Ties]:
        """Merge ties per ordered run pair, dropping empty parts."""
        by_pair: dict[tuple[str, str], list[Ties]] = {}
        for p in parts:
            if len(p):
                by_pair.setdefault((p.run_a, p.run_b), []).append(p)
        return [cls(a, b, *(np.concatenate([getattr(p, k) for p in ps])
                            for k in ("time_a", "time_b", "xyz_a", "xyz_b", "weight")))
                for (a, b), ps in by_pair.items()]


@dataclass(frozen=True)
class TileOffset:
    """Result of matching one tile pair: the translation that moves run_b's points onto run_a's.

    ``d`` follows SPEC.md (p_a = p_b + d); ``cov`` is its 3x3 covariance, whose large eigenvalues
    show the directions the pair does not constrain (along a featureless tunnel). ``status`` is
    ``"ok"`` or one word saying why there is no reliable match.
    """

    run_a: str
    run_b: str
    tile_a: str
    tile_b: str
    d: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    cov: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))
    inliers: int = 0
    status: str = "unmatched"
    ties: Ties | None = None
    info: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def sd(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.cov), 0, None))


@dataclass(frozen=True)
class ControlObservations:
    """Control points seen in the runs' clouds: absolute observations for the optimizer.

    Row i says: run ``run_id[i]`` saw control point ``ids[i]`` at ``seen[i]`` (survey CRS, as
    georeferenced by that run's input trajectory) at gps_time ``time[i]``; the point was surveyed
    at ``xyz[i]`` with 1-sigma ``sd[i]``. ``pick_sd`` is how well the point was found in the cloud
    (hand pick or automatic location), per axis; ``source`` is ``picked`` (control_obs.csv) or
    ``located`` (found automatically). After correction ``seen + c_run(time)`` should equal ``xyz``.
    """

    ids: np.ndarray
    run_id: np.ndarray
    time: np.ndarray
    seen: np.ndarray
    xyz: np.ndarray
    sd: np.ndarray
    pick_sd: np.ndarray
    source: np.ndarray

    def __post_init__(self) -> None:
        for name in ("ids", "run_id", "source"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=object).reshape(-1))
        object.__setattr__(self, "time", _as_array("time", self.time, ()))
        for name in ("seen", "xyz", "sd", "pick_sd"):
            object.__setattr__(self, name, _as_array(name, getattr(self, name), (3,)))
        n = len(self.time)
        if any(len(getattr(self, k)) != n for k in ("ids", "run_id", "seen", "xyz", "sd", "pick_sd", "source")):
            raise ValueError("control observations: all columns must have the same length")

    def __len__(self) -> int:
        return len(self.time)

    @classmethod
    def empty(cls) -> ControlObservations:
        z3 = np.zeros((0, 3))
        return cls([], [], np.zeros(0), z3, z3, z3, z3, [])

    def cov(self) -> np.ndarray:
        """(n, 3, 3) covariance of ``xyz - seen``: survey sd and pick sd, per axis."""
        var = self.sd ** 2 + self.pick_sd ** 2
        return np.einsum("ni,ij->nij", var, np.eye(3))
