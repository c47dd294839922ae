"""How a tile pair's offset enters the adjustment: which pairs, and with what covariance.

Shared by the spline optimizer and the check of the runs' reported sd (:mod:`railtraj.sd_check`),
so that both read the same observations the same way.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from railtraj.alongtrack import COARSE
from railtraj.data import TileOffset, Trajectory

#: statuses whose offset is reliable across the track and in height, though not along it
WEAK_STATUSES = ("degenerate", "ambiguous")
#: along-track sd given to degenerate/ambiguous pairs, so that the track direction is dropped
WEAK_ALONG_SD_M = 100.0
#: the status of a pair whose offset the adjustment found at odds with everything else and left out
REJECTED = "rejected"


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


def by_window(o: TileOffset) -> list[TileOffset]:
    """A weak pair as one offset per window of its curve (the matcher's ``weak_windows``: each
    window's own offset, at the times the runs measured it), else the pair as it is.

    A weak pair's one offset, at its reference point, hides an offset that changes within the
    tile: a GNSS bias ramping in before a portal grew 30 cm across one held-out tile pair whose
    reference point saw 4 cm of it. Its windows say, across the track and up, where the bias is.
    The check of the runs' sd reads weak pairs so; the spline optimizer keeps one offset per
    pair (by window, 15 of 25 held-out surveys lost 0.4-16 mm RMS: docs/method.md, "Session 48")."""
    windows = o.info.get("weak_windows") if o.status in WEAK_STATUSES else None
    if not windows or not len(windows["d"]):
        return [o]
    return _per_window(o, windows, [o.cov] * len(windows["d"]))


def resolved_by_window(o: TileOffset) -> list[TileOffset]:
    """A resolved pair without ties (``ok`` fixed by the chain along the track, or ``coarse``) as
    one offset per window of its curve (``weak_windows``, moved with the pair onto its alias):
    across and up in every window, along the track in those the curve used along it. Each carries
    the pair's covariance times the number of windows, so together they say what the pair says;
    a pair with fewer than two windows on record is returned as it is.

    Where a run's GNSS is biased the adjustment leaves it free (:mod:`railtraj.sd_check`) and
    the pair's one offset, at its reference point, is all it has of the bias; but a multipath
    bias peaks at the portal within a tile or two, between two pairs' reference points. Read by
    window there, held-out portal_trap 4703 went from 0.164 to 0.056 m inter-run max, 5013 from
    0.123 to 0.085 m (docs/method.md, "Session 53")."""
    windows = o.info.get("weak_windows")
    ties = o.ties is not None and len(o.ties)
    if o.status not in ("ok", COARSE) or ties or not windows or len(windows["d"]) < 2 or "along" not in windows:
        return [o]
    cov = np.asarray(o.cov, float) * len(windows["d"])
    unseen_along = WEAK_ALONG_SD_M**2 * np.outer(_track_axis(o), _track_axis(o))
    return _per_window(o, windows, [cov if along else cov + unseen_along for along in windows["along"]])


def _per_window(o: TileOffset, windows: dict, covs: list[np.ndarray]) -> list[TileOffset]:
    """The pair as one offset per window (``windows``: each one's ``d`` and the times the runs
    measured it), with ``covs`` one covariance per window."""
    return [replace(o, d=np.asarray(d, float), cov=cov, info=dict(o.info, time_a=t_a, time_b=t_b))
            for d, t_a, t_b, cov in zip(windows["d"], windows["time_a"], windows["time_b"], covs, strict=True)]


def usable_offset(o: TileOffset, trajectories: dict[str, Trajectory]) -> bool:
    """A degenerate/ambiguous pair, or an ok pair without ties, with a finite offset, covariance
    and observation times."""
    usable = o.status in WEAK_STATUSES or o.status == COARSE or (o.ok and (o.ties is None or not len(o.ties)))
    if not usable or o.run_a not in trajectories or o.run_b not in trajectories:
        return False
    times = [o.info.get("time_a", np.nan), o.info.get("time_b", np.nan)]
    return bool(np.isfinite(o.d).all() and np.isfinite(o.cov).all() and np.isfinite(times).all())


def with_rejections(offsets: Sequence[TileOffset], diagnostics: dict) -> tuple[list[TileOffset], str]:
    """``offsets`` with the pairs whose offset the optimizer rejected (its diagnostics'
    ``rejected`` rows of kind ``offset``) given status ``rejected``, the status they had kept in
    ``info["rejected"]``; and a note ('' when none).

    A pair's status is what offsets.csv tells a surveyor about it. Held-out mixed 5015: a pair
    the along-track chain had fixed (``coarse``) was 0.86 m off across the track, which its
    neighbours 5 m away contradicted; the adjustment rejected it (102 sd), yet offsets.csv still
    called it coarse with a 9 mm sd."""
    rows = {(r["run_a"], r["run_b"], r["tile_a"], r["tile_b"]): r["whitened_residual"]
            for r in diagnostics.get("rejected", []) if r.get("kind") == "offset"}
    out, worst = [], []
    for o in offsets:
        residual = rows.get((o.run_a, o.run_b, o.tile_a, o.tile_b))
        if residual is None or o.status == REJECTED:
            out.append(o)
            continue
        out.append(replace(o, status=REJECTED, info=dict(o.info, rejected={"status_before": o.status,
                                                                            "whitened_residual": residual})))
        worst.append(residual)
    if not worst:
        return out, ""
    return out, (f"{len(worst)} tile pair(s) at odds with the other observations (up to {max(worst):.0f} sd) were "
                 f"left out of the adjustment: status rejected in offsets.csv")


__all__ = ["REJECTED", "WEAK_ALONG_SD_M", "WEAK_STATUSES", "by_window", "offset_covariance", "resolved_by_window",
           "usable_offset", "with_rejections"]
