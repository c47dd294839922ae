"""The railtraj method, step by step: pair tiles, detect, describe, match, optimize, report.

:func:`run_pipeline` reads like the method section of the thesis (chapter 3): for every pair of
overlapping tiles of two runs it detects keypoints, describes them, matches them into a
translation with its uncertainty and a set of tie features; the optimizer then corrects every
run's trajectory so the ties agree; the corrected trajectories, anchor observations for
GNSS/INS re-processing, QC figures and (optionally) re-georeferenced tiles are written.
Stages arrive already built (see :mod:`railtraj.cli`): nothing here knows about configuration.
"""

from __future__ import annotations

import inspect
import logging
import os
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from railtraj.adjust.offsets import with_rejections
from railtraj.alongtrack import (
    COARSE,
    AlongTrackOptions,
    BeyondReach,
    beyond_reach,
    beyond_reach_note,
    rematch_centres,
    resolve_along_track,
    used_along,
)
from railtraj.alongtrack_coverage import along_track_coverage
from railtraj.consistency import check_survey
from railtraj.control import observe_control
from railtraj.data import (
    ControlObservations,
    Keypoints,
    PointTile,
    Ties,
    TileOffset,
    Trajectory,
    check_span,
)
from railtraj.errors import ConfigError
from railtraj.georef import Regeoreferencer
from railtraj.io.survey import (
    Survey,
    TilePair,
    find_overlaps,
    grid_cells,
    in_parts,
    open_survey,
    require_overlaps,
    unparsed_crs_note,
    with_context,
)
from railtraj.io.tile_cache import DEFAULT_BUDGET_GB, tile_cache
from railtraj.matching.objects import CONTEXT_M
from railtraj.matching.spacing import median_point_spacing, sparse_profiles_note
from railtraj.matching.threads import blas_one_thread
from railtraj.portal import PortalOptions, with_portal_sd
from railtraj.qc import PairClouds, distance_stats, pair_clouds, tie_residuals
from railtraj.resume import Cache, cached_map
from railtraj.same_track import SameTrackOptions, same_track_offsets
from railtraj.same_track import summary as same_track_summary
from railtraj.sd_check import SdCheck, SdCheckOptions, check_reported_sd, with_fading_margin
from railtraj.track_direction import fitted_direction_note, pair_travel

log = logging.getLogger(__name__)

#: points per tile pair kept to measure cloud-to-cloud distances before and after correction
C2C_SAMPLE = 20_000
#: statuses of a matched pair (the others are refusals: a pair refused alone may be matched again)
MATCHED = ("ok", "ambiguous", "degenerate")


@dataclass
class Stages:
    """The built stage objects one job uses."""

    detector: Any
    descriptor: Any
    matcher: Any
    optimizer: Any
    executor: Any


@dataclass
class PipelineOptions:
    """Plain options of one job (built from the Hydra config by the CLI)."""

    mode: str = "global"                 # local | global | multirun
    pairs: str = "reference"             # reference | all
    reference_run: str | None = None
    tile: str | None = None
    max_pairs: int = 0
    min_overlap_m: float = 2.0
    pair_part_m: float = 25.0
    max_misalignment_m: float = 3.0
    max_widened_m: float = 6.0
    other_pairs_below: float = 0.5
    other_pairs_below_biased: float = 1.0
    crs: str = "EPSG:27700"
    grid_dir: str | None = None
    sbet_crs: str | None = None          # SBET and anchors frame; None: railtraj.crs default
    tile_cache_gb: float = DEFAULT_BUDGET_GB  # whole tiles kept between detect and match, shared by the workers
    alongtrack: AlongTrackOptions = field(default_factory=AlongTrackOptions)
    sd_check: SdCheckOptions = field(default_factory=SdCheckOptions)
    same_track: SameTrackOptions = field(default_factory=SameTrackOptions)
    portal: PortalOptions = field(default_factory=PortalOptions)


@dataclass
class PairResult:
    """What matching one tile pair produced, plus a point sample for C2C."""

    offset: TileOffset
    sample_a: PointTile
    sample_b: PointTile
    seconds: dict[str, float] = field(default_factory=dict)


@dataclass
class PipelineResult:
    survey: Survey
    options: PipelineOptions
    trajectories: dict[str, Trajectory]
    corrected: dict[str, Trajectory]
    pairs: list[PairResult]
    ties: list[Ties]
    seconds: dict[str, float]
    control: ControlObservations = field(default_factory=ControlObservations.empty)
    adjustment: dict[str, Any] = field(default_factory=dict)  # the optimizer's diagnostics
    notes: list[str] = field(default_factory=list)  # warnings a surveyor must see in metrics/report
    resume: dict[str, int] = field(default_factory=dict)  # tiles/pairs reused from an earlier run

    @property
    def offsets(self) -> list[TileOffset]:
        return [p.offset for p in self.pairs]


def run_pipeline(survey_dir: Path, stages: Stages, options: PipelineOptions,
                 progress=None, cache: Cache | None = None) -> PipelineResult:
    """Run the whole method on a survey folder and return everything the writers need.

    With a ``cache`` (:mod:`railtraj.resume`), tiles and pairs finished by an earlier run are
    reused and every newly finished one is stored at once.
    """
    clock: dict[str, float] = {}
    t0 = time.perf_counter()
    survey = open_survey(survey_dir)
    trajectories = {r: survey.load_trajectory(r, crs=options.crs, grid_dir=options.grid_dir,
                                              sbet_crs=options.sbet_crs)
                    for r in survey.runs}
    check_survey(survey, trajectories, options.crs)
    survey_notes = [n for n in [unparsed_crs_note(survey, options.crs)] if n]
    for note in survey_notes:
        log.warning(note)
    pairs = select_pairs(survey, options)
    clock["load"] = time.perf_counter() - t0
    log.info("survey %s: %d runs, %d tiles, %d tile pairs to match", survey.root, len(survey.runs),
             sum(len(r.tiles) for r in survey.runs.values()), len(pairs))

    t0 = time.perf_counter()
    # each worker process keeps its own tile cache: their budgets share the one given
    per_process = replace(options, tile_cache_gb=options.tile_cache_gb / max(1, int(getattr(stages.executor, "workers", 1))))
    keypoints, tile_key, tiles_reused = _detect(pairs, {}, {}, trajectories, stages, per_process, cache, progress)
    clock["detect"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    matched, pairs_reused = _match(pairs, keypoints, tile_key, trajectories, stages, per_process, cache, progress)
    clock["match"] = time.perf_counter() - t0
    log.info("%d of %d tile pairs matched reliably", sum(r.offset.ok for r in matched), len(matched))

    t0 = time.perf_counter()
    results, before_chains, alongtrack = _along_track(matched, trajectories, options)
    clock["alongtrack"] = time.perf_counter() - t0
    along_notes, searched, coverage = [], options.max_misalignment_m, None
    resolved = [r.offset for r in results]
    if options.alongtrack.enabled:
        reach = beyond_reach(alongtrack, resolved, searched)
        if reach is not None and _can_widen(stages.matcher, options, reach):
            t0 = time.perf_counter()
            matched, searched, note, more = _widened(reach, pairs, matched, results, keypoints, tile_key, trajectories,
                                                     stages, per_process, cache, progress, survey)
            results, before_chains, alongtrack = _along_track(matched, trajectories, options)
            resolved = [r.offset for r in results]
            reach = beyond_reach(alongtrack, resolved, searched)  # what even the second pass did not reach
            pairs_reused += more
            along_notes.append(note)
            clock["widened"] = time.perf_counter() - t0
        t0, rematched = time.perf_counter(), []
        # a pair fixed again lets the chains predict its neighbours better (a matcher that cannot
        # be widened, matcher=icp, cannot search about a prediction either)
        for _ in range(REMATCH_PASSES if callable(getattr(stages.matcher, "widened", None)) else 0):
            centres = rematch_centres(resolved, options.alongtrack)
            if not centres:
                break
            matched, results, before_chains, alongtrack, kept, more = _rematched(
                centres, pairs, matched, keypoints, tile_key, trajectories, stages, per_process, cache, progress, survey)
            resolved = [r.offset for r in results]
            pairs_reused += more
            rematched.append((len(centres), kept))
        if rematched:
            clock["rematched"] = time.perf_counter() - t0
            along_notes.append(_rematched_note(rematched, options))
        coverage, coverage_note = along_track_coverage(resolved, alongtrack, trajectories,
                                                       options.alongtrack.resolved_sd)
        unresolved, why = _reference_unresolved(coverage, before_chains, survey, options)
        if unresolved:
            t0 = time.perf_counter()
            ref = _reference(survey, options)
            others = [p for p in select_pairs(survey, replace(options, pairs="all")) if ref not in (p.run_a, p.run_b)]
            keypoints, tile_key, more_tiles = _detect(others, keypoints, tile_key, trajectories, stages, per_process,
                                                      cache, progress)
            others_matched, more = _match(others, keypoints, tile_key, trajectories, stages, per_process, cache,
                                          progress)
            pairs, matched = pairs + others, matched + others_matched
            results, before_chains, alongtrack = _along_track(matched, trajectories, options)
            resolved = [r.offset for r in results]
            coverage, coverage_note = along_track_coverage(resolved, alongtrack, trajectories,
                                                           options.alongtrack.resolved_sd)
            tiles_reused, pairs_reused = tiles_reused + more_tiles, pairs_reused + more
            along_notes.append(_other_pairs_note(unresolved, why, len(others)))
            clock["other_pairs"] = time.perf_counter() - t0
        along_notes += [fitted_direction_note(resolved), beyond_reach_note(reach), coverage_note]
    if cache:  # (after every pass: a resumed run looks up the widened and the other pairs last)
        cache.prune()
    ok = [o for o in resolved if o.ok]

    t0 = time.perf_counter()
    control, notes = observe_control(survey, trajectories, point_spacing=median_point_spacing(resolved)[0])
    notes = survey_notes + notes + [n for n in [*along_notes, sparse_profiles_note(resolved),
                                                 joined_tiles_note(resolved)] if n]
    clock["control"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    ties = Ties.concat([o.ties for o in ok if o.ties is not None])
    offsets = [r.offset for r in results]
    # the optimizer weighs the runs by their sd: widen it first where the runs show it lies
    control_at = control.xyz[:, :2] if len(control) and _takes(stages.optimizer, "control") else None
    # runs on the same track compared where both report GNSS: the check sees a portal's bias
    # there, the adjustment holds the runs together where neither's GNSS is found biased
    same_track = same_track_offsets(trajectories, options.same_track)
    checked = check_reported_sd(trajectories, offsets + same_track, options.sd_check, earlier=before_chains,
                                control_at=control_at)
    notes += checked.summary["notes"]
    same_track = same_track_offsets(trajectories, options.same_track, trusted=checked.trajectories)
    same_track_metrics, same_track_note = same_track_summary(same_track)
    notes += [same_track_note] if same_track_note else []
    adjusted = [o for k, o in enumerate(offsets) if k not in checked.unsettled_pairs] + same_track
    corrected, adjustment = optimize(stages.optimizer, trajectories, ties, adjusted, control, notes, checked)
    # a pair the adjustment left out says so in offsets.csv
    marked, rejected_note = with_rejections([p.offset for p in results], adjustment)
    results = [replace(p, offset=o) for p, o in zip(results, marked, strict=True)]
    # a portal's GNSS may be biased alike in every run: only the corrected sd can say so
    corrected, portal_metrics, portal_note = with_portal_sd(corrected, trajectories, options.portal, control_at)
    for note, level in ((rejected_note, logging.WARNING), (portal_note, logging.INFO)):
        if note:
            log.log(level, note)
            notes.append(note)
    clock["optimize"] = time.perf_counter() - t0
    adjustment["alongtrack"] = alongtrack
    if coverage is not None:
        adjustment["alongtrack_coverage"] = coverage
    adjustment["sd_check"] = checked.summary
    adjustment["same_track"] = same_track_metrics
    adjustment["portal"] = portal_metrics
    log.info("stage times: %s", ", ".join(f"{k} {v:.1f} s" for k, v in clock.items()))
    return PipelineResult(survey, options, trajectories, corrected, results, ties, clock, control, adjustment, notes,
                          resume={"tiles_reused": tiles_reused, "pairs_reused": pairs_reused})


def _detect(pairs: list[TilePair], keypoints: dict, tile_key: dict, trajectories: dict[str, Trajectory],
            stages: Stages, options: PipelineOptions, cache: Cache | None, progress) -> tuple[dict, dict, int]:
    """``keypoints`` and ``tile_key`` (by (run, tile path)) with the tiles of ``pairs`` not yet
    in them detected (finished ones from ``cache``), in :func:`visit_order`; and how many came
    from the cache."""
    order = visit_order(pairs)
    tiles = [t for t in dict.fromkeys(t for k in order for t in ((pairs[k].run_a, pairs[k].tile_a.path),
                                                                 (pairs[k].run_b, pairs[k].tile_b.path)))
             if t not in keypoints]
    keys = [cache.tile_key(run, path, trajectories[run].span, options.pair_part_m) if cache else ""
            for run, path in tiles]
    with blas_one_thread():  # (railtraj.matching.threads: faster here, same results)
        detected, reused = cached_map(
            stages.executor, detect_tile,
            [(run, path, trajectories[run].span, stages, options.tile_cache_gb, options.pair_part_m)
             for run, path in tiles],
            keys, cache, "tiles", progress=progress or _log_progress("detected keypoints in", "tiles"))
    return ({**keypoints, **dict(zip(tiles, detected, strict=True))}, {**tile_key, **dict(zip(tiles, keys, strict=True))},
            reused)


def _reference(survey: Survey, options: PipelineOptions) -> str:
    """The run every other run is matched to where ``pairs`` is ``reference``."""
    return options.reference_run or sorted(survey.runs)[0]


def _reference_unresolved(coverage: dict[str, dict] | None, checked: SdCheck | None, survey: Survey,
                          options: PipelineOptions) -> tuple[dict, str]:
    """In a survey of three runs or more matched to a reference, the reference's run pairs
    (``"run_a~run_b"``: share) whose offset the chains resolved along less of the track than
    ``pipeline.other_pairs_below_biased`` (1.0) where the check before the chains widened the
    reference's reported sd (GNSS biased), or than ``pipeline.other_pairs_below`` (0.5) where
    another of its run pairs resolved that share or more: there the other runs' tile pairs are
    to be matched too. And why (``{}, ""`` where not).

    Where the reference is biased, any run pair it leaves partly unresolved: a held-out portal
    survey along a grid row (5955) resolved a~b over 47 % of its track, below 0.5, and b~c, matched
    too, placed run b (0.011 / 0.037 m); matched against run a's neighbouring tiles too
    (:func:`_misfit_for_its_tile`), a~b resolved 70 %, b~c went unmatched and the runs came out
    0.029 / 0.112 m apart. With b~c: 0.011 / 0.037 m again.

    The chains are anchored where the runs report a small sd, at the portals. Where multipath
    biases the reference run at its portals and the check widens its sd there, none of its
    chains is anchored, though the other runs, good at theirs, are: a held-out portal survey
    (sleepers 0.6 m, 1.3 times the speed, run a biased at both portals) resolved its run pairs
    over 67 and 69 of 296 m and left the runs 0.31 / 0.52, 0.24 / 0.41 and 0.34 / 0.59 m apart;
    with run b~c matched too, b~c resolved over 201 m, 0.017 / 0.050 m.

    Where another run is placed along the track and this one is not, run b~c carries c's
    placement over to b (``d_ab = d_ac - d_bc``, and the chains resolve every run pair jointly):
    held-out thesis at heading 0, sleepers 0.6 m, three runs, run a~b resolved 26 % and a~c
    100 %; with b~c matched, 0.233 / 0.425 -> 0.015 / 0.070 m inter-run. Not where every one of
    the reference's run pairs resolves little for want of features (the reference's sd stands):
    on held-out feature_poor 1056 (a~b 13 %, a~c 18 %) and 1057 the other pairs, unresolved too,
    moved run pairs by -2 to +4 cm RMS, as many apart as together."""
    if coverage is None or options.pairs != "reference" or len(survey.runs) < 3:
        return {}, ""
    ref = _reference(survey, options)
    shares = {key: c["share"] for key, c in coverage.items() if ref in key.split("~")}
    biased = checked is not None and ref in checked.widening
    name = "other_pairs_below_biased" if biased else "other_pairs_below"
    below = getattr(options, name)
    low = {key: share for key, share in shares.items() if share < below}
    placed = sorted(key for key, share in shares.items() if share >= below)
    if not low or not (biased or placed):
        return {}, ""
    because = ("the reference run's GNSS disagrees with the other runs' where it anchors the chains" if biased
               else f"{', '.join(placed)} resolved more: the other runs matched to each other carry it over")
    return low, f"less than {below:.0%} (pipeline.{name}), and {because}"


def _other_pairs_note(unresolved: dict[str, float], why: str, n_pairs: int) -> str:
    """The warning that the other runs' tile pairs were matched, and why."""
    shares = ", ".join(f"{key} {share:.0%}" for key, share in sorted(unresolved.items()))
    note = (f"along-track: the reference run's chains resolved {shares} of the track, {why}; the {n_pairs} tile pairs "
            "between the other runs were matched too, and every run pair resolved jointly "
            "(pipeline=multirun always does)")
    log.warning(note)
    return note


def _match(pairs: list[TilePair], keypoints: dict, tile_key: dict, trajectories: dict[str, Trajectory],
           stages: Stages, options: PipelineOptions, cache: Cache | None, progress,
           centres: list[np.ndarray] | None = None) -> tuple[list[PairResult], int]:
    """Match ``pairs`` on the executor (finished pairs from ``cache``), in the order of ``pairs``;
    and how many came from the cache. Each pair's job carries its runs' directions of travel
    (:func:`railtraj.track_direction.pair_travel`; not part of the cache key: they overrule only
    a fitted track direction more than 10 degrees off, and a reprocessed trajectory moves them
    by hundredths of a degree). ``centres``: per pair, where the matcher searches about (the
    offset; default: where the trajectories put the runs)."""
    centres = centres or [None] * len(pairs)
    order = visit_order(pairs)
    backwards = order[::-1]  # the tiles detected last are still in the tile cache: match them first
    pair_keys = [cache.pair_key(pairs[k], tile_key[(pairs[k].run_a, pairs[k].tile_a.path)],
                                tile_key[(pairs[k].run_b, pairs[k].tile_b.path)],
                                _match_key(options, centres[k]))
                 if cache else "" for k in backwards]
    jobs = [(pairs[k], keypoints[(pairs[k].run_a, pairs[k].tile_a.path)],
             keypoints[(pairs[k].run_b, pairs[k].tile_b.path)], stages, options,
             tuple(pair_travel(trajectories[run], pairs[k].overlap_min, pairs[k].overlap_max)
                   for run in (pairs[k].run_a, pairs[k].run_b)), centres[k]) for k in backwards]
    with blas_one_thread():
        matched, reused = cached_map(stages.executor, match_pair, jobs, pair_keys, cache, "pairs",
                                     progress=progress or _log_progress("matched", "tile pairs"))
    results: list[PairResult] = [None] * len(pairs)  # type: ignore[list-item]
    for k, r in zip(backwards, matched, strict=True):
        results[k] = r
    return results, reused


def _along_track(results: list[PairResult], trajectories: dict[str, Trajectory],
                 options: PipelineOptions) -> tuple[list[PairResult], SdCheck | None, list[dict]]:
    """The matched pairs with their along-track aliases resolved jointly (:mod:`railtraj.alongtrack`),
    the check of reported sd made before the chains (across and up), and the along-track report."""
    # the chains are anchored where the runs report a small sd (portals): where the matcher's
    # pairs show a run's GNSS biased there, that anchor is as loose as the check widens it
    matched = [r.offset for r in results]
    before_chains = None
    if options.alongtrack.enabled:
        before_chains = check_reported_sd(trajectories, matched, replace(options.sd_check, along=False))
    anchors = trajectories if before_chains is None else before_chains.trajectories
    resolved, report = resolve_along_track(matched, anchors, options.alongtrack)
    return [replace(r, offset=o) for r, o in zip(results, resolved, strict=True)], before_chains, report


def _can_widen(matcher, options: PipelineOptions, reach: BeyondReach) -> bool:
    """Whether the pairs a chain puts beyond the matcher's reach can be matched again further out:
    ``pipeline.max_widened_m`` is beyond the window searched, and the matcher can be widened
    (it has a ``widened(window)`` method, as the built-in voting matchers)."""
    return options.max_widened_m > reach.window and callable(getattr(matcher, "widened", None))


def _widened(reach: BeyondReach, pairs: list[TilePair], matched: list[PairResult], resolved: list[PairResult],
             keypoints: dict, tile_key: dict, trajectories: dict[str, Trajectory], stages: Stages,
             options: PipelineOptions, cache: Cache | None, progress,
             survey: Survey) -> tuple[list[PairResult], float, str | None, int]:
    """The matcher's results ``matched`` with the tile pairs of the run pairs ``reach`` names
    matched again within a wider window (the suggested one, at most ``pipeline.max_widened_m``),
    but for those the chains had already used along the track (``resolved``: ``ok``, or
    resolved); that window, a note saying so, and the count of pairs reused from the cache.

    The matcher searches within ``matcher.max_misalignment`` (3 m) of where the trajectories put
    the runs; where the chains put two runs further apart (2 sd), no pair there can be matched at
    its truth, only at an alias inside the window, and the chains leave them unresolved. A held-out
    sparse portal survey (140 points per profile) had one run 2.6 m off the reference: 0.42 / 0.87 m
    inter-run, the chains saying "1.64 +- 0.69 m apart"; matched again within 4 m, 0.021 / 0.068 m.
    Only those run pairs' tiles are matched again, and their keypoints are reused. A pair the
    chains used is kept as it was: a wider window holds more aliases of the ribs (1.5 m) and
    sleepers, and a held-out portal survey whose runs drifted 3.4 m apart, all of whose run
    pair's tile pairs were matched again within 4.5 m, used 1 of them along the track instead of
    14, and ended 0.144 / 0.270 m inter-run instead of 0.019 / 0.069."""
    window = min(reach.suggested, options.max_widened_m)
    again = [k for k, p in enumerate(pairs) if ((p.run_a, p.run_b) in reach.run_pairs
                                                 or (p.run_b, p.run_a) in reach.run_pairs)
             and not used_along(resolved[k].offset)]
    if not again:
        return matched, reach.window, None, 0
    runs = ", ".join(f"{a}~{b}" for a, b in sorted(reach.run_pairs))
    worst = reach.worst
    note = (f"along-track: the chains put runs {worst['run_a']} and {worst['run_b']} {abs(worst['predicted_m']):.2f} "
            f"+- {worst['predicted_sd_m']:.2f} m apart at tile {worst['tile_a']}, beyond the {reach.window:g} m the "
            f"matcher searched; the {len(again)} tile pairs of {runs} they had not used along the track were matched "
            f"again within {window:g} m (pipeline.max_widened_m={options.max_widened_m:g}; 0: never)")
    log.warning(note)
    again_matched, more = _match_within([pairs[k] for k in again], window, window, keypoints, tile_key, trajectories,
                                        stages, options, cache, progress, survey)
    out = list(matched)
    for k, r in zip(again, again_matched, strict=True):
        out[k] = r
    return out, window, note, more


def _match_within(again: list[TilePair], window: float, reach: float, keypoints: dict, tile_key: dict,
                  trajectories: dict[str, Trajectory], stages: Stages, options: PipelineOptions, cache: Cache | None,
                  progress, survey: Survey, centres: list[np.ndarray] | None = None) -> tuple[list[PairResult], int]:
    """The tile pairs ``again`` matched again by the matcher searching within ``window`` m (about
    ``centres``, or where the trajectories put the runs), each with its runs' tiles within
    ``reach`` m as context (:func:`_widened`, :func:`_rematched`); and how many came from the cache."""
    searching = replace(stages, matcher=stages.matcher.widened(window))
    redo = with_context(again, survey, reach + CONTEXT_M)
    return _match(redo, keypoints, tile_key, trajectories, searching, replace(options, max_misalignment_m=window),
                  cache, progress, centres=centres)


#: m: the search window (each way) of a pair matched again about the chains' prediction: its
#: neighbouring aliases (sleepers 0.6 m, ribs 1.0-1.5 m) inside, the alias it was on (3.0 m) not
REMATCH_WINDOW_M = 1.0
#: rounds of matching again: each may fix pairs that predict their neighbours to ``rematch_sd``
REMATCH_PASSES = 3


def _rematched(centres: dict[int, np.ndarray], pairs: list[TilePair], matched: list[PairResult], keypoints: dict,
               tile_key: dict, trajectories: dict[str, Trajectory], stages: Stages, options: PipelineOptions,
               cache: Cache | None, progress,
               survey: Survey) -> tuple[list[PairResult], list[PairResult], SdCheck | None, list[dict], int, int]:
    """The pairs ``centres`` names matched again within :data:`REMATCH_WINDOW_M` of their
    centre (the offset the chains predict, :func:`railtraj.alongtrack.rematch_centres`) and the
    chains run again: a pair they then resolve keeps its new match (``info["rematched"]``), any
    other its first (``info["rematch_tried"]``: not tried again). The matcher's results, the
    along-track results, the check of reported sd before the chains and the along-track report
    (as :func:`_along_track`), how many pairs kept their new match, how many came from the cache.

    Only a resolved pair is kept: a new match the chains cannot fix either is no better placed,
    and in a bored tube searched within 1 m of the prediction a pair's profile could be flat,
    showing no alias at all, where its first match's windows had measured the drift's rate."""
    again = sorted(centres)
    reach = max(float(np.linalg.norm(centres[k])) for k in again) + REMATCH_WINDOW_M
    redone, more = _match_within([pairs[k] for k in again], REMATCH_WINDOW_M, reach, keypoints, tile_key,
                                 trajectories, stages, options, cache, progress, survey,
                                 centres=[centres[k] for k in again])
    trial = list(matched)
    for k, r in zip(again, redone, strict=True):
        if r.offset.status in MATCHED:
            info = dict(r.offset.info, rematched={"centre": np.round(centres[k], 3).tolist(),
                                                  "first_status": matched[k].offset.status})
            trial[k] = replace(r, offset=replace(r.offset, info=info))
    results, before_chains, report = _along_track(trial, trajectories, options)
    kept = {k for k in again if "rematched" in trial[k].offset.info and results[k].offset.status in ("ok", COARSE)}
    out = list(matched)
    for k in again:
        first = matched[k].offset
        out[k] = trial[k] if k in kept else replace(matched[k], offset=replace(first, info=dict(
            first.info, rematch_tried=np.round(centres[k], 3).tolist())))
    if len(kept) < len(again):
        results, before_chains, report = _along_track(out, trajectories, options)
    return out, results, before_chains, report, len(kept), more


def _rematched_note(passes: list[tuple[int, int]], options: PipelineOptions) -> str:
    """A note on the pairs matched again about the chains' prediction: how many, in how many
    passes, and how many the chains then resolved (kept)."""
    tried, kept = sum(n for n, _ in passes), sum(k for _, k in passes)
    note = (f"along-track: {tried} tile pair(s) none of whose aliases lay where the chains put them (to "
            f"pipeline.alongtrack.rematch_sd={options.alongtrack.rematch_sd:g} m or better) matched again within "
            f"{REMATCH_WINDOW_M:g} m of that, in {len(passes)} pass(es): {kept} then resolved along the track and kept "
            "that match, the others keep their first")
    log.info(note)
    return note


def optimize(optimizer, trajectories: dict[str, Trajectory], ties: list[Ties], offsets: list[TileOffset],
             control: ControlObservations, notes: list[str],
             checked: SdCheck | None = None) -> tuple[dict[str, Trajectory], dict[str, Any]]:
    """Run the optimizer; control goes to optimizers that take it, or a warning says it was not used.
    Where the sd check widened a run's sd, an optimizer that takes ``widening`` gets it with the
    reported trajectories; any other gets trajectories whose per-axis sd is widened. Either way the
    corrected runs' sd then fades out past the widened spans (:func:`with_fading_margin`)."""
    kwargs = {}
    if checked is not None and checked.widening:
        if _takes(optimizer, "widening"):
            kwargs["widening"] = checked.widening
        else:
            trajectories = checked.trajectories
    if len(control):
        if _takes(optimizer, "control"):
            kwargs["control"] = control
        else:
            note = (f"{len(control)} control observations were not used: optimizer "
                    f"{type(optimizer).__name__} does not take control points (use optimizer=spline)")
            log.warning(note)
            notes.append(note)
    corrected = optimizer.optimize(trajectories, ties, offsets, **kwargs)
    if checked is not None:
        corrected = with_fading_margin(corrected, checked)
    adjustment = dict(getattr(optimizer, "diagnostics", None) or {})
    notes += adjustment.get("notes", [])
    if all(np.array_equal(corrected[r].xyz, trajectories[r].xyz) for r in trajectories):
        note = "the optimizer left every trajectory unchanged"
        if note not in " ".join(notes):
            log.warning(note)
            notes.append(note)
    return corrected, adjustment


def _takes(optimizer, argument: str) -> bool:
    """Whether the optimizer's ``optimize`` takes ``argument`` (``widening``, ``control``)."""
    return argument in inspect.signature(optimizer.optimize).parameters


def select_pairs(survey: Survey, options: PipelineOptions) -> list[TilePair]:
    """Overlapping tile pairs to match, per the pipeline mode."""
    pairs = in_parts(require_overlaps(find_overlaps(survey, min_overlap_m=options.min_overlap_m), survey),
                     options.pair_part_m)
    if options.pairs == "reference":
        ref = _reference(survey, options)
        if ref not in survey.runs:
            raise ConfigError(f"reference_run {ref!r} is not a run of the survey; runs: {', '.join(sorted(survey.runs))}")
        pairs = [p for p in pairs if ref in (p.run_a, p.run_b)]
    if options.tile:
        pairs = [p for p in pairs if _pair_at(p, options.tile)]
        if not pairs:
            raise ConfigError(f"no overlapping tile pair at tile={options.tile!r}; give a tile file name "
                              "(e.g. 530000_180025.laz) or 'x,y' inside a tile of two runs")
    if options.max_pairs > 0:
        pairs = pairs[: options.max_pairs]
    return with_context(pairs, survey, options.max_misalignment_m + CONTEXT_M)


def visit_order(pairs: list[TilePair]) -> list[int]:
    """Indices of ``pairs`` grouped by the tile of run a (then run b and its tile): the order in
    which detection visits the tiles, so that the pairs sharing a tile are neighbours and, walked
    backwards, find their tiles still in the per-process tile cache (:mod:`railtraj.io.tile_cache`).
    Only the order of work changes: results are put back in the order of ``pairs``."""
    return sorted(range(len(pairs)), key=lambda k: (pairs[k].run_a, str(pairs[k].tile_a.path), pairs[k].run_b,
                                                      str(pairs[k].tile_b.path)))


def _pair_at(pair: TilePair, tile: str) -> bool:
    names = {pair.tile_a.path.name, pair.tile_b.path.name, pair.tile_a.path.stem, pair.tile_b.path.stem}
    if tile in names:
        return True
    try:
        x, y = (float(v) for v in tile.split(","))
    except ValueError:
        return False
    return bool(pair.overlap_min[0] <= x <= pair.overlap_max[0] and pair.overlap_min[1] <= y <= pair.overlap_max[1])


def detect_tile(job: tuple) -> tuple[Keypoints, dict[str, float]]:
    """Read one tile, check its run's trajectory span covers it, detect and describe its keypoints
    (a tile longer than 1.2 ``part_m`` in the squares of that grid: :func:`grid_cells`).

    The job carries the trajectory's span, not the trajectory: workers need nothing more. The tile
    stays in this process's tile cache for the pairs matched next (``cache_gb``)."""
    run_id, path, span, stages, cache_gb, part_m = job
    t = time.perf_counter()
    tile = tile_cache(cache_gb).read(path, run_id=run_id)
    check_span(run_id, span, tile.gps_time, f"points of {run_id}/{path.name}")
    seconds = {"read": time.perf_counter() - t, "detect": 0.0, "describe": 0.0}
    found = []
    for square in grid_cells(tile.xyz, part_m):  # a large tile in the squares its pairs are matched in
        part = tile if len(square) == len(tile) else tile.subset(square)
        t = time.perf_counter()
        kp = stages.detector.detect(part)
        seconds["detect"] += time.perf_counter() - t
        t = time.perf_counter()
        found.append(stages.descriptor.describe(part, kp))
        seconds["describe"] += time.perf_counter() - t
    kp = found[0] if len(found) == 1 else Keypoints.concatenate(found)
    log.debug("%s/%s: %d points, %d keypoints", run_id, path.name, len(tile), len(kp))
    return kp, seconds


def _match_key(options: PipelineOptions, centre: np.ndarray | None) -> dict:
    """What of the job's options a matched pair depends on (its cache key)."""
    key = {"max_misalignment_m": options.max_misalignment_m, "c2c_sample": C2C_SAMPLE}
    if centre is not None:
        key["centre"] = np.round(centre, 4).tolist()
    return key


def match_pair(job: tuple) -> PairResult:
    """Match one tile pair from its keypoints (runs in a worker for parallel executors).

    Both tiles are cropped to their overlap grown by the largest expected misalignment, and so
    are the keypoints, so that partly overlapping tiles compare like with like. The tiles come
    from this process's tile cache when detection or an earlier pair has just read them, each
    with its run's direction of travel there (:attr:`railtraj.data.PointTile.travel`).
    """
    pair, (kp_a, sec_a), (kp_b, sec_b), stages, options, (travel_a, travel_b), centre = job
    initial = None
    margin = options.max_misalignment_m
    if centre is not None:  # searched about it: the crop reaches as far
        initial = TileOffset(pair.run_a, pair.run_b, pair.tile_a.path.name, pair.tile_b.path.name, d=centre)
        margin += float(np.linalg.norm(centre))
    lo = np.asarray(pair.overlap_min, dtype=float) - margin
    hi = np.asarray(pair.overlap_max, dtype=float) + margin
    lo[2], hi[2] = -np.inf, np.inf
    seconds = {k: sec_a[k] + sec_b[k] for k in sec_a}

    t = time.perf_counter()
    tiles = tile_cache(options.tile_cache_gb)
    tile_a = replace(tiles.read_with_context(pair.tile_a.path, pair.run_a, pair.context_a, (lo, hi), CONTEXT_M),
                     travel=travel_a)
    tile_b = replace(tiles.read_with_context(pair.tile_b.path, pair.run_b, pair.context_b, (lo, hi), CONTEXT_M),
                     travel=travel_b)
    kp_a, kp_b = (kp.subset(np.flatnonzero(((kp.xyz >= lo) & (kp.xyz <= hi)).all(axis=1))) for kp in (kp_a, kp_b))
    seconds["read"] += time.perf_counter() - t

    t = time.perf_counter()
    offset = stages.matcher.match(tile_a, kp_a, tile_b, kp_b, initial)
    if _misfit_for_its_tile(offset, pair):
        joined = replace(tiles.read_joined(pair.tile_a.path, pair.run_a, pair.context_a, (lo, hi), CONTEXT_M),
                         travel=travel_a)
        again = stages.matcher.match(joined, kp_a, tile_b, kp_b, initial)
        if again.status in MATCHED:  # else the first refusal stands
            tile_a, offset = joined, again
        offset = replace(offset, info=dict(offset.info, joined_tiles=len(pair.context_a), joined_status=again.status))
    seconds["match"] = time.perf_counter() - t

    names = dict(run_a=pair.run_a, run_b=pair.run_b, tile_a=pair.tile_a.path.name, tile_b=pair.tile_b.path.name)
    ties = offset.ties
    if ties is not None:
        ties = Ties(pair.run_a, pair.run_b, ties.time_a, ties.time_b, ties.xyz_a, ties.xyz_b, ties.weight)
    times = _overlap_times(pair, tile_a, tile_b)  # unless the matcher says where it observed the offset
    times.update({k: offset.info[k] for k in times if np.isfinite(offset.info.get(k, np.nan))})
    info = dict(offset.info, keypoints_a=len(kp_a), keypoints_b=len(kp_b), points_a=len(tile_a),
                points_b=len(tile_b), seconds=seconds, **times)
    offset = TileOffset(**names, d=offset.d, cov=offset.cov, inliers=offset.inliers, status=offset.status,
                        ties=ties, info=info)
    rng = np.random.default_rng(0)
    sample = [t_.subset(rng.permutation(len(t_))[:C2C_SAMPLE]) for t_ in (tile_a, tile_b)]
    log.debug("%s/%s vs %s/%s: %s d=%s", *names.values(), offset.status, np.round(offset.d, 4))
    return PairResult(offset, sample[0], sample[1], seconds)


def _misfit_for_its_tile(offset: TileOffset, pair: TilePair) -> bool:
    """Whether a pair refused as ``no_overlap`` after its dense check is to be matched again
    against run a's whole cloud about the pair's box, its neighbouring tiles' points included.

    Each run's tiles are cut on the same grid, each run where its own drift puts it. Where a grid
    line cuts the tunnel lengthwise and the runs are far apart across, run b's tile holds a strip
    run a's has in the next tile: a held-out tunnel along a grid row, its axis on a tile edge,
    runs 1.7-2.3 m apart across, had 7 of 25 pairs below the fitness needed at every vote
    peak (run b's points 0.10-0.27 on run a's surface) and resolved 43 % of its length."""
    return offset.status == "no_overlap" and "vote_peaks" in offset.info and len(pair.context_a) > 1


def joined_tiles_note(offsets: list[TileOffset]) -> str | None:
    """A note (and a warning) when pairs were matched again against run a's neighbouring tiles
    too (:func:`_misfit_for_its_tile`): how many, and how many then matched."""
    tried = [o for o in offsets if "joined_tiles" in o.info]
    if not tried:
        return None
    matched = [o for o in tried if o.info["joined_status"] in MATCHED]
    note = (f"{len(tried)} tile pair(s) found no fit against run a's tile (no_overlap; e.g. {tried[0].tile_a} "
            f"{tried[0].run_a}~{tried[0].run_b}) and were matched again against run a's points in its neighbouring "
            f"tiles too, {len(matched)} of them then matched: the tile grid cuts the tunnel lengthwise there and the "
            "runs are far apart across")
    log.warning(note)
    return note


def _overlap_times(pair: TilePair, tile_a: PointTile, tile_b: PointTile) -> dict[str, float]:
    """Median gps_time of each run's points in the pair's overlap: when the offset was observed."""
    out = {}
    for key, tile in (("time_a", tile_a), ("time_b", tile_b)):
        inside = ((tile.xyz[:, :2] >= pair.overlap_min[:2]) & (tile.xyz[:, :2] <= pair.overlap_max[:2])).all(axis=1)
        times = tile.gps_time[inside] if inside.any() else tile.gps_time
        out[key] = float(np.median(times)) if len(times) else float("nan")
    return out


def qc_figures(result: PipelineResult, clouds: list[PairClouds] | None = None,
               move: Regeoreferencer | None = None) -> dict[str, Any]:
    """Tie residuals and C2C distances before and after correction, overall and per pair
    (``clouds``: :func:`railtraj.qc.pair_clouds` of ``result``, and ``move``, its trajectories'
    :class:`~railtraj.georef.Regeoreferencer`: built here if not given)."""
    before, after = [], []
    move = move or Regeoreferencer(result.trajectories, result.corrected)  # one interpolator per run
    for ties in result.ties:
        before.append(tie_residuals(ties))
        after.append(tie_residuals(ties, move))
    clouds = pair_clouds(result, move) if clouds is None else clouds
    per_pair = []
    for c in clouds:
        o = result.pairs[c.index].offset
        per_pair.append({"tile_a": o.tile_a, "tile_b": o.tile_b, "run_a": o.run_a, "run_b": o.run_b,
                         "c2c_median_before": c.median_before, "c2c_median_after": c.median_after})
    return {
        "tie_residual_before_m": distance_stats(_concat(before)),
        "tie_residual_after_m": distance_stats(_concat(after)),
        "c2c_before_m": distance_stats(_concat([c.c2c_before for c in clouds])),
        "c2c_after_m": distance_stats(_concat([c.c2c_after for c in clouds])),
        "c2c_per_pair": per_pair,
    }


def _concat(parts: list[np.ndarray]) -> np.ndarray:
    return np.concatenate(parts) if parts else np.zeros(0)


def _log_progress(what: str, unit: str):
    """The default progress callback of a long stage: a bar with counts, rate and ETA on stderr
    when it is a terminal and not in CI (env ``CI`` set), else a log line every few seconds. The
    last call logs the count and the stage's time either way, so the log keeps the timings."""
    state: dict[str, Any] = {"start": time.perf_counter(), "last": 0.0, "bar": None}
    interactive = sys.stderr.isatty() and not os.environ.get("CI")

    def report(done: int, total: int) -> None:
        now = time.perf_counter()
        if interactive:
            if state["bar"] is None:
                from tqdm import tqdm
                from tqdm.contrib.logging import logging_redirect_tqdm

                state["redirect"] = logging_redirect_tqdm()  # log lines print above the bar
                state["redirect"].__enter__()
                state["bar"] = tqdm(total=total, desc=what, unit=f" {unit}", dynamic_ncols=True)
            state["bar"].update(done - state["bar"].n)
            if done == total:
                state["bar"].close()
                state["redirect"].__exit__(None, None, None)
        elif done < total and now - state["last"] > 5.0:
            state["last"] = now
            log.info("%s %d/%d %s", what, done, total, unit)
        if done == total:
            log.info("%s %d/%d %s in %.1f s", what, done, total, unit, now - state["start"])
    return report
