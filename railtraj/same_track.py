"""Runs on the same track, compared position by position where both report GNSS.

A train runs on its rails: two passes over the same track put their trajectories on the same
line across the track and up, whatever their clouds show, less a constant (the reference point's
lever arm across, mirrored when the train runs the other way; another vehicle). Where both runs
report GNSS-quality sd, their positions at the same place measure ``error_a - error_b`` across
and up to the rails' play and the GNSS noise, in open cuttings and at portals where tile pairs
fit badly or not at all, and where multipath biases one run's GNSS.

Held-out commensurate 4902: run c's GNSS sat 0.33 m off across at its exit portal while it
reported 1.3 cm; the one tile pair there that fitted was ambiguous, so nothing convicted run c.
Compared with runs a and b on the same track, it was convicted, and the adjustment, holding it to
them where its bias had faded, corrected it: 0.101 / 0.387 -> 0.034 / 0.112 m from run a.

Each observation is a weak tile offset (``ambiguous``: along the track it says nothing), named
``same track <n>`` after the ``segment_m`` of run a it lies in: :mod:`railtraj.sd_check` counts
each segment as its own tile pair, and the optimizer takes them across and up as it takes
ambiguous pairs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from railtraj.data import TileOffset, Trajectory, reports_gnss
from railtraj.geo import track_frames

#: the tile name of a same-track observation: ``same track <segment>``
PREFIX = "same track"


@dataclass
class SameTrackOptions:
    sd_m: float = 0.02          # sd of one comparison across and up (0: no comparison)
    # runs whose paths lie further apart across (median) are on other tracks; a place further
    # from that median, or where the runs' headings differ by more than max_turn_deg, is on
    # another track (a turnout) and is not compared
    max_apart_m: float = 0.5
    max_turn_deg: float = 2.0
    gnss_sd_m: float = 0.10     # both runs report at most this horizontal sd where they are compared
    spacing_m: float = 5.0      # one comparison every so many metres of run a
    segment_m: float = 25.0     # comparisons within so many metres of run a count as one tile pair


def same_track_offsets(trajectories: dict[str, Trajectory], options: SameTrackOptions,
                       trusted: dict[str, Trajectory] | None = None) -> list[TileOffset]:
    """Per pair of runs on the same track, where both report GNSS-quality sd: every
    ``spacing_m`` of run a, its position less run b's nearest, across the track and up, less the
    pair's median there. ``trusted``: the runs with their sd widened where their GNSS was found
    biased (:mod:`railtraj.sd_check`): the median is taken where neither run's is, and a pair
    with fewer than three such places is not compared (a run biased at both short portals
    shifted the median, and the adjustment held the others to its bias). Places where one run
    turns off the other's track (a turnout: more than ``max_apart_m`` across from the median, or
    headings more than ``max_turn_deg`` apart) are not compared."""
    if not options.sd_m > 0:
        return []
    out = []
    runs = sorted(trajectories)
    for i, a in enumerate(runs):
        for b in runs[i + 1:]:
            out += _compared(trajectories[a], trajectories[b], options,
                             None if trusted is None else (trusted[a], trusted[b]))
    return out


def _compared(run_a: Trajectory, run_b: Trajectory, options: SameTrackOptions,
              trusted: tuple[Trajectory, Trajectory] | None) -> list[TileOffset]:
    """The comparisons of two runs (none where they are on other tracks)."""
    if run_a.sd is None or run_b.sd is None or len(run_a.time) < 2 or len(run_b.time) < 2:
        return []
    travelled = run_a.travelled()
    gnss = reports_gnss(run_a.sd, options.gnss_sd_m)
    at = np.flatnonzero(gnss & (np.diff(np.floor(travelled / options.spacing_m), prepend=-1) > 0))
    if not len(at):
        return []
    distance, near = cKDTree(run_b.xyz[:, :2]).query(run_a.xyz[at, :2])
    keep = reports_gnss(run_b.sd, options.gnss_sd_m)[near] & (distance < options.spacing_m)
    at, near = at[keep], near[keep]
    if len(at) < 3:
        return []
    frame = track_frames(run_a.xyz)[at]
    local = np.einsum("nij,nj->ni", frame, run_a.xyz[at] - run_b.xyz[near])  # along, across, up
    sure = np.ones(len(at), bool)
    if trusted is not None:
        sure = reports_gnss(trusted[0].sd, options.gnss_sd_m)[at] & reports_gnss(trusted[1].sd, options.gnss_sd_m)[near]
    if sure.sum() < 3 or not abs(np.median(local[sure, 1])) <= options.max_apart_m:
        return []
    constant = np.median(local[sure, 1:], axis=0)
    local[:, 1:] -= constant
    local[:, 0] = 0.0
    turn = np.degrees(np.arccos(np.clip(np.abs(np.einsum("ni,ni->n", frame[:, 0], track_frames(run_b.xyz)[near, 0])),
                                        0.0, 1.0)))
    keep = (np.abs(local[:, 1]) <= options.max_apart_m) & (turn <= options.max_turn_deg)
    at, near, frame, local = at[keep], near[keep], frame[keep], local[keep]
    d = np.einsum("nji,nj->ni", frame, local)
    segment = np.floor(travelled[at] / options.segment_m).astype(np.int64)
    cov = options.sd_m**2 * np.eye(3)
    return [TileOffset(run_a.run_id, run_b.run_id, f"{PREFIX} {s}", f"{PREFIX} {s}", d[k], cov, 0, "ambiguous", None,
                       {"time_a": float(run_a.time[at[k]]), "time_b": float(run_b.time[near[k]]),
                        "piecewise": {"axis": frame[k, 0].tolist()}, "same_track": True,
                        "constant_m": constant.tolist()})
            for k, s in enumerate(segment)]


def summary(observations: list[TileOffset]) -> tuple[dict, str | None]:
    """metrics.json: per pair of runs compared, how many places and the constant taken out
    (across, up, m); and a note naming them (None: no runs were compared)."""
    pairs: dict[str, dict] = {}
    for o in observations:
        entry = pairs.setdefault(f"{o.run_a}~{o.run_b}", {"places": 0, "constant_across_up_m": o.info["constant_m"]})
        entry["places"] += 1
    if not pairs:
        return {"observations": 0, "run_pairs": {}}, None
    note = ("runs on the same track compared position by position where both report GNSS (across and up, "
            "pipeline.same_track; sd_m=0 turns it off): " + ", ".join(
                f"{k} at {v['places']} places, their constant {100 * v['constant_across_up_m'][0]:.1f} cm across, "
                f"{100 * v['constant_across_up_m'][1]:.1f} cm up" for k, v in sorted(pairs.items())))
    return {"observations": len(observations), "run_pairs": pairs}, note
