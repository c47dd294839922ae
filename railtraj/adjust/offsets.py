"""How a tile pair's offset enters the adjustment: which pairs, and with what covariance.

Shared by the spline optimizer and the check of the runs' reported sd (:mod:`railtraj.sd_check`),
so that both read the same observations the same way.
"""

from __future__ import annotations

import numpy as np

from railtraj.alongtrack import COARSE
from railtraj.data import TileOffset, Trajectory

#: statuses whose offset is reliable across the track and in height, though not along it
WEAK_STATUSES = ("degenerate", "ambiguous")
#: along-track sd given to degenerate/ambiguous pairs, so that the track direction is dropped
WEAK_ALONG_SD_M = 100.0


def offset_covariance(o: TileOffset) -> np.ndarray:
    """A tile offset's covariance as an observation: a weak pair says nothing along the track,
    whatever its sd there."""
    if o.status not in WEAK_STATUSES:
        return np.asarray(o.cov, float)
    axis = _track_axis(o)
    return o.cov + WEAK_ALONG_SD_M**2 * np.outer(axis, axis)


def _track_axis(o: TileOffset) -> np.ndarray:
    """The pair's track direction: from its curve of offsets, else its least constrained direction."""
    axis = o.info.get("piecewise", {}).get("axis")
    if axis is not None:
        return np.asarray(axis, float)
    return np.linalg.eigh(o.cov)[1][:, -1]


def usable_offset(o: TileOffset, trajectories: dict[str, Trajectory]) -> bool:
    """A degenerate/ambiguous pair, or an ok pair without ties, with a finite offset, covariance
    and observation times."""
    usable = o.status in WEAK_STATUSES or o.status == COARSE or (o.ok and (o.ties is None or not len(o.ties)))
    if not usable or o.run_a not in trajectories or o.run_b not in trajectories:
        return False
    times = [o.info.get("time_a", np.nan), o.info.get("time_b", np.nan)]
    return bool(np.isfinite(o.d).all() and np.isfinite(o.cov).all() and np.isfinite(times).all())


__all__ = ["WEAK_ALONG_SD_M", "WEAK_STATUSES", "offset_covariance", "usable_offset"]
