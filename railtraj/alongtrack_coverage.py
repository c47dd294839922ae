"""Where along the track each run pair's offset is resolved, and where it is not.

The chains (:mod:`railtraj.alongtrack`) fix a tile pair's along-track alias, or predict the runs'
offset there from the pairs fixed either side, with an sd (``predicted_sd_m`` in their report).
Elsewhere (a featureless lining, a tube whose joints a sparse scan does not show, a chain too
vague to choose between aliases) the runs are placed across the track and in height only, and
along the track where the trajectories and drift rates put them: decimetres apart after the
correction where they were a metre apart before. Nothing in the corrected clouds shows which
stretch is which, so a surveyor needs to be told.

A run pair's tile pairs are ordered along run b's track (their median time in the overlap); each
owns the stretch half way to its neighbours. Its stretch is *resolved* where the chain used the
pair along the track (``ok``, or fixed: ``coarse`` too) or predicted the offset there within
``resolved_sd``, or where the two runs' own reported sd (horizontal, the larger axis, combined)
is within it: in the open, GNSS resolves what a pair in a cutting, with little to match, does
not need to. Every other tile pair of the run pair counts as not resolved, also one between
two fixed pairs that the chain does not predict at (no along-track evidence of its own): the
share is a lower bound. Consecutive unresolved stretches merge into one, reported as run b's
time span (metrics.json ``adjustment.alongtrack_coverage``, and a note).
"""

from __future__ import annotations

import logging

import numpy as np

from railtraj.adjust.stiffness import stretches
from railtraj.alongtrack import metres_travelled, used_along
from railtraj.data import TileOffset, Trajectory

log = logging.getLogger(__name__)

#: unresolved stretches named in the note (the longest), per run pair
NOTED_STRETCHES = 3


def along_track_coverage(offsets: list[TileOffset], report: list[dict], trajectories: dict[str, Trajectory],
                         resolved_sd: float) -> tuple[dict[str, dict], str | None]:
    """Per run pair (``"run_a~run_b"``): the length of run b's track its tile pairs cover, how
    much of it is resolved along the track, and the unresolved stretches (run b's time span,
    length, the chain's largest sd there where it predicted one); and a note naming the longest
    unresolved stretches (None where every stretch is resolved)."""
    predicted_sd = {r["pair"]: r["predicted_sd_m"] for r in report if "predicted_sd_m" in r}
    by_run_pair: dict[tuple[str, str], list[int]] = {}
    for k, o in enumerate(offsets):
        if o.run_b in trajectories and np.isfinite(o.info.get("time_b", np.nan)):
            by_run_pair.setdefault((o.run_a, o.run_b), []).append(k)
    coverage, noted = {}, []
    for (run_a, run_b), pairs in sorted(by_run_pair.items()):
        traj = trajectories[run_b]
        travelled = metres_travelled(traj)
        times = np.array([offsets[k].info["time_b"] for k in pairs], float)
        s = np.interp(times, traj.time, travelled)
        order = np.argsort(s)
        pairs, s = [pairs[k] for k in order], s[order]
        sd = np.array([predicted_sd.get(k, np.nan) for k in pairs], float)
        own = np.hypot(*(_reported_sd(trajectories.get(run), [offsets[k].info.get(f"time_{ab}", np.nan) for k in pairs])
                         for run, ab in ((run_a, "a"), (run_b, "b"))))
        resolved = np.array([used_along(offsets[k]) for k in pairs]) | (sd <= resolved_sd) | (own <= resolved_sd)
        lo, hi = _owned(s, resolved)
        gaps = [_unresolved(traj, travelled, lo[a:b + 1], hi[a:b + 1], sd[a:b + 1]) for a, b in stretches(~resolved)]
        length = float((hi - lo).sum())
        done = float((hi - lo)[resolved].sum())
        key = f"{run_a}~{run_b}"
        coverage[key] = {"length_m": round(length, 1), "resolved_m": round(done, 1),
                         "share": round(done / length, 3) if length > 0 else 1.0, "unresolved": gaps}
        if gaps:
            longest = sorted(gaps, key=lambda r: -r["length_m"])[:NOTED_STRETCHES]
            where = ", ".join(f"{r['time_b'][0]:.1f}-{r['time_b'][1]:.1f} s ({r['length_m']:.0f} m)" for r in longest)
            more = f" and {len(gaps) - len(longest)} more" if len(gaps) > len(longest) else ""
            noted.append(f"{key} over {done:.0f} of {length:.0f} m; not at {run_b} {where}{more}")
    if not noted:
        return coverage, None
    note = ("along-track: the runs' offset is resolved " + "; ".join(noted) + ". There the runs are placed across "
            "the track and in height only, along it where their trajectories put them (their corrected sd says how "
            f"far off; metrics.json adjustment.alongtrack_coverage; resolved: fixed, predicted or reported within "
            f"{resolved_sd:g} m)")
    log.warning(note)
    return coverage, note


def _reported_sd(traj: Trajectory | None, times: list[float]) -> np.ndarray:
    """The run's reported horizontal sd (the larger of x and y) at ``times``; inf where it
    reports none."""
    t = np.asarray(times, float)
    sd = traj.sd_at(np.nan_to_num(t)) if traj is not None else None
    if sd is None:
        return np.full(len(t), np.inf)
    return np.where(np.isfinite(t), sd[:, :2].max(axis=1), np.inf)


def _owned(s: np.ndarray, resolved: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The stretch of track each of the sorted positions ``s`` owns: half way to its neighbours,
    and at either end as far beyond as half the gap to its one neighbour (a lone pair: none);
    but between a resolved and an unresolved pair the unresolved one owns the whole gap. The
    drift grows away from a fixed pair: on three held-out surveys the runs were up to 6-10 cm
    apart along the track half way to an unresolved neighbour, within 4 cm at the fixed pairs."""
    bounds = np.concatenate([[s[0]], 0.5 * (s[1:] + s[:-1]), [s[-1]]])
    if len(s) > 1:
        bounds[0], bounds[-1] = s[0] - (bounds[1] - s[0]), s[-1] + (s[-1] - bounds[-2])
        bounds[1:-1] = np.where(resolved[:-1] & ~resolved[1:], s[:-1], bounds[1:-1])
        bounds[1:-1] = np.where(~resolved[:-1] & resolved[1:], s[1:], bounds[1:-1])
    return bounds[:-1], bounds[1:]


def _unresolved(traj: Trajectory, travelled: np.ndarray, lo: np.ndarray, hi: np.ndarray, sd: np.ndarray) -> dict:
    """One unresolved stretch: run b's time span over it, its length, the chain's largest sd in
    it (None where the chain predicted none of its pairs)."""
    span = np.interp([lo[0], hi[-1]], travelled, traj.time)
    if span[0] > span[1]:
        span = span[::-1]
    worst = float(np.nanmax(sd)) if np.isfinite(sd).any() else None
    return {"time_b": [round(float(span[0]), 2), round(float(span[1]), 2)], "length_m": round(float(hi[-1] - lo[0]), 1),
            "worst_sd_m": None if worst is None else round(worst, 3)}
