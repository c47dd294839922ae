"""Control points seen in the runs' clouds: absolute observations for the global adjustment.

A control point (control.csv) is a surveyed feature visible in the clouds: the centre of a
retro-reflective target, the corner of a niche. Each run saw it where that run's trajectory error
put it. That position, with the time the run passed it, observes the run's correction:
``c_run(t) = X - seen``.

* **Picked by hand** (``control_obs.csv``: id,run_id,x,y,z in that run's cloud): the time is when
  the run was abreast of the picked point. That is the epoch whose scan plane, across the track,
  holds it.
* **Located automatically** (no control_obs.csv): within the run's expected error of the surveyed
  coordinates, where ``r = 3 sd + 0.3 m``, the largest compact cluster of bright returns.
  Retro-reflective targets are the brightest surfaces in a tunnel. Its centroid is ``seen``, the
  median gps_time of its points the time.
  - The centroid mixes the target's face with its lit sides. On the simulator's 0.2 m targets,
    3 cm deep, that biases it by under a centimetre towards the track; ``locate_sd_m`` (1 cm)
    covers it.
  - A point not found, or found twice (two clusters of similar size), gives no observation and a
    note.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from railtraj.data import ControlObservations, Trajectory
from railtraj.errors import SurveyError
from railtraj.georef import regeoreference_points
from railtraj.io.las import read_tile
from railtraj.io.survey import ControlPoints, Survey, read_control
from railtraj.io.trajectory_csv import read_text_columns, to_float

log = logging.getLogger(__name__)

CONTROL_OBS = "control_obs.csv"


@dataclass(frozen=True)
class LocateOptions:
    pick_sd_m: float = 0.01  # how well a hand pick hits the point
    locate_sd_m: tuple[float, float, float] = (0.01, 0.01, 0.02)  # how well the cluster's centroid does (E, N, U)
    search_sigmas: float = 3.0
    min_search_m: float = 0.3
    max_search_m: float = 3.0
    link_m: float = 0.1  # bright points this close belong to one cluster
    max_extent_m: float = 0.5  # a target is smaller than this
    min_points: int = 4


def observe_control(survey: Survey, trajectories: dict[str, Trajectory], options: LocateOptions = LocateOptions(),
                    point_spacing: float = float("nan")) -> tuple[ControlObservations, list[str]]:
    """Control observations of every run, and notes on the points that could not be used.

    ``point_spacing`` (m): how far apart the scan's points lie along a profile. On a side wall a
    profile runs up the wall, and a 0.2 m target is one or two rows of points, anywhere within
    half that spacing of its centre: a located target's height has an sd of ``spacing /
    sqrt(12)`` at least. Where the points lay 0.18 m apart, located targets were up to 8.4 cm
    off in height (3 of 10), claiming 2 cm, and a run was pulled 8 cm off in height around them;
    at 0.05 m, 2 cm at most (the 2 cm stays)."""
    if survey.control_path is None:
        return ControlObservations.empty(), []
    control = read_control(survey.control_path)
    picked = survey.root / CONTROL_OBS
    if picked.is_file():
        return _picked(picked, control, trajectories, options), []
    rows, notes = [], []
    for run_id, traj in sorted(trajectories.items()):
        for i, cid in enumerate(control.ids):  # a control point every ~100 m: a handful per run
            found, note = _locate(survey, run_id, traj, control.xyz[i], str(cid), options)
            if found is not None:
                rows.append((cid, run_id, *found, control.xyz[i], control.sd[i]))
            elif note:
                notes.append(note)
    for note in notes:
        log.warning(note)
    log.info("control: %d observations of %d points in %d runs", len(rows), len(control), len(trajectories))
    if not rows:
        return ControlObservations.empty(), notes
    ids, runs, times, seen, xyz, sd = zip(*rows, strict=True)
    n = len(rows)
    locate_sd = np.tile(options.locate_sd_m, (n, 1))
    if np.isfinite(point_spacing):  # rows of points up the wall, the target's centre anywhere between two
        locate_sd[:, 2] = np.maximum(locate_sd[:, 2], point_spacing / np.sqrt(12.0))
    return ControlObservations(ids, runs, times, np.array(seen), np.array(xyz), np.array(sd),
                               locate_sd, ["located"] * n), notes


def abreast_time(traj: Trajectory, xyz: np.ndarray) -> np.ndarray:
    """Time at which the run was abreast of each point: the nearest epoch in plan, refined to where
    the point lies in the plane across the direction of travel."""
    xyz = np.atleast_2d(np.asarray(xyz, float))
    k = cKDTree(traj.xyz[:, :2]).query(xyz[:, :2])[1]
    k0, k1 = np.clip(k - 1, 0, len(traj) - 1), np.clip(k + 1, 0, len(traj) - 1)
    v = (traj.xyz[k1, :2] - traj.xyz[k0, :2]) / np.maximum(traj.time[k1] - traj.time[k0], 1e-9)[:, None]
    speed2 = np.maximum((v**2).sum(axis=1), 1e-12)
    dt = ((xyz[:, :2] - traj.xyz[k, :2]) * v).sum(axis=1) / speed2
    return np.clip(traj.time[k] + dt, *traj.span)


def control_residuals(obs: ControlObservations, before: dict[str, Trajectory],
                      after: dict[str, Trajectory]) -> list[dict]:
    """Per observation, surveyed minus seen before and after correction (east, north, up, m)."""
    out = []
    for r in np.unique(obs.run_id) if len(obs) else []:
        m = obs.run_id == r
        if r not in before or r not in after:
            continue
        moved = regeoreference_points(obs.seen[m], obs.time[m], before[r], after[r])
        for i, res_b, res_a in zip(np.flatnonzero(m), obs.xyz[m] - obs.seen[m], obs.xyz[m] - moved, strict=True):
            out.append({"id": str(obs.ids[i]), "run_id": str(r), "source": str(obs.source[i]),
                        "time": float(obs.time[i]), "before_m": [round(float(x), 4) for x in res_b],
                        "after_m": [round(float(x), 4) for x in res_a],
                        "horizontal_before": round(float(np.hypot(*res_b[:2])), 4),
                        "horizontal_after": round(float(np.hypot(*res_a[:2])), 4),
                        "vertical_before": round(float(res_b[2]), 4), "vertical_after": round(float(res_a[2]), 4)})
    return out


def _picked(path: Path, control: ControlPoints, trajectories: dict[str, Trajectory],
            options: LocateOptions) -> ControlObservations:
    what = "control observations file"
    cols = read_text_columns(path, ("id", "run_id", "x", "y", "z"), what)
    seen = np.column_stack([to_float(cols[c], c, path, what) for c in ("x", "y", "z")])
    if not np.isfinite(seen).all():
        raise SurveyError(f"{what} {path} has a NaN or infinite coordinate: fix or remove that row")
    index = {str(c): k for k, c in enumerate(control.ids)}
    for row, (cid, run) in enumerate(zip(cols["id"], cols["run_id"], strict=True)):
        if str(cid) not in index:
            raise SurveyError(f"{what} {path}, row {row + 2}: id {cid} is not in control.csv; "
                              "fix the id or add the point to control.csv")
        if str(run) not in trajectories:
            raise SurveyError(f"{what} {path}, row {row + 2}: run {run} is not a run of the survey; "
                              f"runs: {', '.join(sorted(trajectories))}")
    k = np.array([index[str(c)] for c in cols["id"]], dtype=np.int64)
    runs = np.asarray(cols["run_id"], dtype=object)
    times = np.zeros(len(k))
    for r in np.unique(runs):
        m = runs == r
        times[m] = abreast_time(trajectories[str(r)], seen[m])
    n = len(k)
    return ControlObservations(np.asarray(cols["id"], dtype=object), runs, times, seen, control.xyz[k],
                               control.sd[k], np.full((n, 3), options.pick_sd_m), ["picked"] * n)


def _locate(survey: Survey, run_id: str, traj: Trajectory, xyz: np.ndarray, cid: str,
            options: LocateOptions) -> tuple[tuple | None, str | None]:
    """((time, seen), None) for the bright cluster near ``xyz`` in ``run_id``'s tiles, or
    (None, note). A point the run never passed gives (None, None)."""
    t = float(abreast_time(traj, xyz)[0])
    pos = traj.position_at(np.array([t]))
    if np.linalg.norm(pos[0, :2] - xyz[:2]) > 30.0:
        return None, None  # the run does not pass this point
    sd = traj.sd_at(np.array([t]))
    sd_h = float(np.hypot(*sd[0, :2])) if sd is not None else 1.0
    r = float(np.clip(options.search_sigmas * sd_h + 0.3, options.min_search_m, options.max_search_m))
    lo, hi = xyz - r, xyz + r
    parts = [read_tile(h.path, run_id=run_id, bbox=(lo, hi)) for h in survey.run(run_id).tiles
             if (h.mins <= hi).all() and (h.maxs >= lo).all()]
    pts = np.vstack([p.xyz for p in parts]) if parts else np.zeros((0, 3))
    if not len(pts) or any(p.intensity is None for p in parts):
        return None, f"control point {cid} not found in {run_id}: no points with intensity within {r:.2f} m"
    inten = np.concatenate([p.intensity for p in parts]).astype(float)
    times = np.concatenate([p.gps_time for p in parts])
    inside = np.linalg.norm(pts - xyz, axis=1) <= r
    pts, inten, times = pts[inside], inten[inside], times[inside]
    if len(pts) < options.min_points:
        return None, f"control point {cid} not found in {run_id}: no points within {r:.2f} m"
    bright = inten >= max(0.8 * np.percentile(inten, 99.9), 3.0 * np.median(inten))
    labels, sizes = _clusters(pts[bright], options.link_m)
    if not len(sizes) or sizes.max() < options.min_points:
        return None, f"control point {cid} not found in {run_id}: no bright target within {r:.2f} m"
    order = np.argsort(sizes)[::-1]
    if len(sizes) > 1 and sizes[order[1]] >= 0.5 * sizes[order[0]]:
        return None, f"control point {cid} ambiguous in {run_id}: two bright targets within {r:.2f} m"
    member = labels == order[0]
    cluster, when = pts[bright][member], times[bright][member]
    if np.ptp(cluster, axis=0).max() > options.max_extent_m:
        return None, f"control point {cid} not found in {run_id}: the bright patch is larger than a target"
    return (float(np.median(when)), cluster.mean(axis=0)), None


def _clusters(pts: np.ndarray, link: float) -> tuple[np.ndarray, np.ndarray]:
    """Connected components of points closer than ``link``: labels and sizes."""
    if not len(pts):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pairs = cKDTree(pts).query_pairs(link, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(pts), len(pts)))
    _, labels = connected_components(graph, directed=False)
    return labels, np.bincount(labels)
