"""A tile pair's track direction taken from the trajectory, not from its noisy point-to-plane fit.

The matcher takes the track direction of a tile pair (``info["piecewise"]["axis"]``) as the
weakest direction of its point-to-plane information, levelled. With 2 cm range noise that
direction was 1.1-1.7 degrees off the direction of travel on every pair of a held-out survey
(0.1-0.7 degrees at 5 mm), and levelled it ignores the grade. Everything the along-track stage
and the adjustment do with a pair leans on that direction: a weak pair's covariance is opened
along it, an alias is a shift along it. A 3 m alias taken along a direction 1.5 degrees off puts
8 cm across the track, where the pair claims 2 mm, and a 2 % grade puts 6 cm in height. The run's
own trajectory gives the direction its cloud was georeferenced along, to a few hundredths of a
degree, grade included.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from railtraj.data import TileOffset, Trajectory

log = logging.getLogger(__name__)

#: half the time span (s) over which the direction of travel is taken
HALF_SPAN_S = 0.25
#: below this speed (m/s) the trajectory says nothing of the direction: the pair keeps its own
MIN_SPEED = 0.5


def travel_step(traj: Trajectory, t: float) -> tuple[np.ndarray, float]:
    """How far (3-D, m) ``traj`` moves over ``HALF_SPAN_S`` either side of ``t``, and in how many
    seconds (less at the ends of its span)."""
    lo, hi = np.clip([t - HALF_SPAN_S, t + HALF_SPAN_S], *traj.span)
    xyz = traj.position_at(np.array([lo, hi]))
    return xyz[1] - xyz[0], float(hi - lo)


def travel_direction(traj: Trajectory, t: float) -> np.ndarray | None:
    """Unit 3-D direction of travel of ``traj`` at time ``t`` (None when it barely moves)."""
    move, seconds = travel_step(traj, t)
    if seconds <= 0 or np.linalg.norm(move) < MIN_SPEED * seconds:
        return None
    return move / np.linalg.norm(move)


def rotation_between(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector ``u`` onto unit vector ``v`` (Rodrigues)."""
    k, c = np.cross(u, v), float(u @ v)
    if c <= -1.0 + 1e-12:
        raise ValueError("opposite directions: no unique smallest rotation")
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + K + K @ K / (1.0 + c)


def on_travel_direction(o: TileOffset, trajectories: dict[str, Trajectory]) -> TileOffset:
    """``o`` with its track direction set to run a's direction of travel at ``time_a``, and its
    covariances (the offset's and the curve's, ``fit_cov``) turned with it, so that what is
    unknown along the track is unknown along the track. The offset itself is as measured."""
    pw = o.info.get("piecewise")
    t = o.info.get("time_a", np.nan)
    if not pw or "axis" not in pw or not np.isfinite(t) or o.run_a not in trajectories:
        return o
    new = travel_direction(trajectories[o.run_a], float(t))
    if new is None:
        return o
    old = np.asarray(pw["axis"], float)
    new = new if new @ old >= 0 else -new
    R = rotation_between(old, new)
    cov = R @ np.asarray(o.cov, float) @ R.T if np.isfinite(o.cov).all() else o.cov
    info = dict(o.info, piecewise=dict(pw, axis=new.tolist(), fitted_axis=old.tolist()))
    if "fit_cov" in pw:
        info["piecewise"]["fit_cov"] = (R @ np.asarray(pw["fit_cov"], float) @ R.T).tolist()
    return replace(o, cov=cov, info=info)


def pair_travel(traj: Trajectory, lo: np.ndarray, hi: np.ndarray) -> np.ndarray | None:
    """The run's horizontal direction of travel where its trajectory crosses the plan box
    ``lo``-``hi`` (a tile pair's overlap), at its middle epoch inside (inside, should it pass
    twice); None where it never is or stands still there. Given to the matcher with the tiles
    (:attr:`railtraj.data.PointTile.travel`): a fit started far across the track has its weakest
    direction across, not along (a held-out pair whose tile held one wall of a tunnel the grid
    cut lengthwise)."""
    inside = np.flatnonzero(((traj.xyz[:, :2] >= np.asarray(lo)[:2]) & (traj.xyz[:, :2] <= np.asarray(hi)[:2]))
                            .all(axis=1))
    if not len(inside):
        return None
    move = travel_direction(traj, float(traj.time[inside[len(inside) // 2]]))
    level = 0.0 if move is None else float(np.hypot(move[0], move[1]))
    return np.array([move[0], move[1], 0.0]) / level if level > 1e-6 else None


def fitted_direction_note(offsets: list[TileOffset]) -> str | None:
    """A note (and a warning) when some pairs kept the matcher's fitted direction because their
    run a's trajectory did not give one there (the train stood still)."""
    kept = [o for o in offsets if "axis" in o.info.get("piecewise", {}) and "fitted_axis" not in o.info["piecewise"]
            and np.isfinite(o.info.get("time_a", np.nan))]
    if not kept:
        return None
    note = (f"{len(kept)} tile pair(s) keep the track direction of their point-to-plane fit (e.g. {kept[0].tile_a} "
            f"{kept[0].run_a}~{kept[0].run_b}): run a's trajectory shows no motion there; with noisy points that "
            "direction can be a degree or two off, so their along-track uncertainty leans across the track")
    log.warning(note)
    return note


__all__ = ["fitted_direction_note", "on_travel_direction", "pair_travel", "rotation_between", "travel_direction",
           "travel_step"]
