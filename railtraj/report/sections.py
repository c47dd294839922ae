"""Verdicts: what a surveyor may rely on, per tile pair and per stretch of tunnel.

Each matched tile pair gets one of four verdicts from its final status (after the joint
along-track resolution):

* ``aligned``: a unique translation in all three directions (status ``ok``);
* ``weak along-track``: across-track and height are fixed, along the track the pair says too
  little (``degenerate``) or only to 1.5-2 cm on a surely fixed alias (``coarse``); the
  adjustment's along-track position there comes from neighbours (or the coarse offset);
* ``unresolved``: an alias one rib or sleeper spacing away fits almost as well, and resolving the
  chain of pairs along the track did not decide it (``ambiguous``); across and height are used;
* ``refused``: no reliable match at all (``no_consensus``, ``no_overlap``, ``few_keypoints``...).

A *section* is a stretch of consecutive tile pairs of one pair of runs, ordered by chainage
along the reference run, that share a verdict.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from railtraj.adjust.offsets import REJECTED
from railtraj.report.chainage import Chainage

ALIGNED, WEAK, UNRESOLVED, REFUSED = "aligned", "weak along-track", "unresolved", "refused"
VERDICTS = (ALIGNED, WEAK, UNRESOLVED, REFUSED)
#: colours of the verdicts in every plot and table of the report
COLOURS = {ALIGNED: "#2ca02c", WEAK: "#ffbf00", UNRESOLVED: "#ff7f0e", REFUSED: "#d62728"}

#: why a pair with this status gave no (or only a partial) constraint, in a surveyor's words
REASONS = {
    "degenerate": "offset found across and up, not to 1 cm along the track (no distinct features)",
    "coarse": "alias fixed jointly along the track, but the pair places it only to 1.5-2 cm",
    "ambiguous": "an alias one rib or sleeper spacing away fits almost as well",
    "no_consensus": "too few keypoint pairs agree on any translation",
    "no_overlap": "the two clouds share too little surface at any offset",
    "few_keypoints": "too few keypoints in one of the tiles",
    "unmatched": "the pair was not matched",
    REJECTED: "its offset contradicts the other observations: the adjustment left it out",
}


def verdict(status: str) -> str:
    """The verdict of a tile pair with final matcher status ``status``."""
    return {"ok": ALIGNED, "degenerate": WEAK, "coarse": WEAK, "ambiguous": UNRESOLVED}.get(status, REFUSED)


@dataclass
class PairPlace:
    """Where one tile pair lies and what came of it."""

    index: int          # position in result.pairs / offsets.csv
    runs: str           # "run_a / run_b"
    tile_a: str
    tile_b: str
    xy: np.ndarray      # plan position where the offset was observed
    chainage: float     # along the reference run, m
    status: str
    verdict: str


@dataclass
class Section:
    """Consecutive tile pairs of one pair of runs with the same verdict."""

    runs: str
    start: float        # chainage of the first pair, m
    end: float          # chainage of the last pair, m
    pairs: list[int]    # indices into result.pairs
    verdict: str


def place_pairs(result, chainage: Chainage) -> list[PairPlace]:
    """Every tile pair with its plan position, chainage and verdict."""
    places = []
    for k, pr in enumerate(result.pairs):
        o = pr.offset
        xy = _observed_xy(result, pr)
        places.append(PairPlace(k, f"{o.run_a} / {o.run_b}", o.tile_a, o.tile_b, xy,
                                float(chainage.at(xy)[0]), o.status, verdict(o.status)))
    return places


def _observed_xy(result, pr) -> np.ndarray:
    """Run a's position when it saw the overlap, else the middle of the point sample."""
    t = pr.offset.info.get("time_a", np.nan)
    traj = result.trajectories.get(pr.offset.run_a)
    if traj is not None and np.isfinite(t) and traj.time[0] <= t <= traj.time[-1]:
        return traj.position_at(np.array([t]))[0, :2]
    if len(pr.sample_a):
        return np.median(pr.sample_a.xyz[:, :2], axis=0)
    return np.zeros(2)


def sections(places: list[PairPlace]) -> list[Section]:
    """Stretches of consecutive pairs (per pair of runs, by chainage) sharing a verdict."""
    out: list[Section] = []
    for runs in sorted({p.runs for p in places}):
        chain = sorted((p for p in places if p.runs == runs), key=lambda p: p.chainage)
        for p in chain:
            if out and out[-1].runs == runs and out[-1].verdict == p.verdict:
                out[-1].end = p.chainage
                out[-1].pairs.append(p.index)
            else:
                out.append(Section(runs, p.chainage, p.chainage, [p.index], p.verdict))
    return out


def pair_reason(offset, alongtrack: dict | None) -> str:
    """One line on why a pair is not aligned: the status' meaning plus the evidence."""
    info = offset.info or {}
    parts = [REASONS.get(offset.status, offset.status)]
    if offset.status == "ambiguous" and info.get("rival_misfit_ratio") is not None:
        parts.append(f"rival misfit ratio {info['rival_misfit_ratio']:.2f}")
    if info.get("rigid_overlap") is not None:  # (matching.resolve._ramped)
        parts.append(f"no one offset fits the tile (overlap {float(info['rigid_overlap']):.2f}), its windows do: "
                     f"the offset changes within it")
    if offset.status in ("no_overlap", "no_consensus") and info.get("fitness") is not None:
        parts.append(f"best fitness {float(info['fitness']):.2f}")
    if "keypoints_a" in info:
        parts.append(f"keypoints {info['keypoints_a']} / {info.get('keypoints_b', '?')}")
    if alongtrack:
        parts.append(f"along-track: {alongtrack['verdict']} (margin {alongtrack['margin']}, "
                     f"{alongtrack['candidates']} candidates)")
    if info.get("demoted"):
        parts.append(str(info["demoted"]))
    return "; ".join(parts)
