"""Joint along-track ambiguity resolution: one alias per tile pair, chosen along the track.

Ribs, rings and sleepers repeat, so a tile pair's along-track offset is known only up to a
multiple of their periods; when two periods are commensurate (1.5 m ribs, 0.6 m sleepers) even
the combination repeats every 3.0 m and only sparse unique objects (niches, boxes) tell the
aliases apart. A single pair cannot always be sure; the chain of pairs along a run pair can:

* the offset between two runs is a smooth curve of chainage that never jumps by a period, and
  each pair's own curve of offsets measures its *rate* (mm per metre), so the offset at the next
  pair is predicted to centimetres;
* near the portals the trajectories' reported sd is small, which anchors the chain at zero.

Per run pair the pairs are ordered along run b's track. Each pair's candidates are the prominent
local maxima of its along-track fitness profile (the matcher's ``alias_profile``: the share of run
b's points within 5 cm of run a's when its curve is shifted by t). Then, as in bootstrapped GNSS
ambiguity fixing (Teunissen 1998), a Kalman smoother predicts the offset at every pair from the
anchors (the trajectories' sd) and the pairs fixed so far, with the measured rates as input. A
pair is fixed on the candidate nearest the prediction only when that candidate clearly beats the
runner-up, and an alias one period away that its profile shows no peak for, by ``min_margin``
(the period: the spacing of the profile's peaks where they lie evenly, else ``min_period``). The fitness evidence between candidates counts at most 3 sigma, because
the profile is measured about the matcher's own choice. That holds for an alias the profile shows no
peak for too: a matcher's ``ok`` is no proof (on a sparse scanner an ``ok`` pair sat 3 m off), so
the nearest such alias, a multiple of that period away, competes at 3 sigma. Fixed pairs
anchor the next round. An anchor is no proof either: a pair none of whose aliases lies near the
prediction releases the trajectories' anchor there (GNSS multipath biases a run along the track
while it reports centimetres), and the pair is predicted again from the rest of the chain.

What cannot be fixed stays ``ambiguous`` and is used across the track and in height only, with
the drift rate its windows measure where they span enough (``info["drift_rate"]``). This
applies to ``ok`` pairs too: a pair the matcher found sure but the chain cannot confirm is
demoted, never kept on a possible alias. A pair the matcher checked with too few votes
(``few_votes``) is stricter still: used only once the chain fixes it, else ``no_consensus``.
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

from railtraj.data import Ties, TileOffset, Trajectory
from railtraj.track_direction import on_travel_direction, travel_step

log = logging.getLogger(__name__)


@dataclass
class AlongTrackOptions:
    """Settings of the joint resolution (``pipeline.alongtrack.*``)."""

    enabled: bool = True
    rate_sd: float = 0.003          # m/m: error of a pair's measured drift rate at least
    window_sd: float = 0.02         # m: along-track error of one window, which a rate from few or close windows inherits
    drift_rates: bool = True        # an unresolved pair's rate still observes how the runs' offset changes (info["drift_rate"])
    drift_rate_span: float = 10.0   # m: ... where its windows span this much at least, on an ambiguous (not degenerate) fit
    drift_rate_windows: int = 4     # ... and it used this many windows at least (fewer: one window on an alias goes unseen)
    rate_radius: float = 50.0       # m: pairs this close along the track vote on each other's rate (0: off)
    rate_walk: float = 0.001        # (m/m)/sqrt(m): how fast the drift rate wanders at least (its bend as white noise; measured per run pair)
    walk_radius: float = 75.0       # m: ... and measured again from the pairs this close to each step (0: per run pair only)
    unmeasured_gap: float = 150.0   # m: across a longer stretch without a measured rate, it wanders as the trajectories' sd allows
    rate_gate: float = 4.0          # a pair's rate this many sd off the chain's counts no more than that
    anchor_gate: float = 3.0        # a pair none of whose aliases lies within this many sd of the prediction releases its anchor
    released_walk: float = 2.0      # ... and the rate's wander on the steps either side of it is this many times more
    min_margin: float = 16.0        # cost (chi-square) by which the chosen candidate must win: 4 sigma
    min_period: float = 0.5         # shortest alias assumed where a pair shows only one candidate (m)
    prior_correlation: float = 100.0  # m over which the trajectories' error counts as one
    anchor_sd: float = 0.25         # m: the trajectories anchor the chain where their along-track sd is at most this
    cycle_radius: float = 15.0      # m: ok pairs of three runs this close are checked for closure
    evidence_ratio: float = 1.25    # a misfit ratio worth 3 sigma of evidence against a candidate
    max_evidence: float = 9.0       # ... and no candidate is charged more than that (3 sigma)
    min_fitness: float = 0.5        # pairs whose profile never reaches this give no evidence
    min_significance: float = 3.0   # a candidate's peak rises this many counting sd above its dips
    lattice_significance: float = 2.0  # ... or this many where the significant peaks' lattice puts an alias
    max_misfit_ratio: float = 2.5   # candidates misfitting more than this times the best are dropped
    misfit_floor: float = 0.02      # ... where misfits below this count as this (a true alias misfits up to 5 %)
    max_candidates: int = 40
    max_pair_sd: float = 0.02      # m: a vaguer pair is never fixed, nor anchors its neighbours
    max_ok_sd: float = 0.015       # m: a vaguer fixed pair anchors the chain but is not ok (5 cm is 3.3 sd)
    sampling_sd: float = 0.15      # along-track sd per metre of profile gap: where edges are seen (both runs)
    resolved_sd: float = 0.05      # m: a stretch counts as resolved where the chain predicts the offset this well (coverage report)
    rematch_sd: float = 0.1        # m: a pair none of whose candidates lies near a prediction this good is matched again about it (0: never)


@dataclass(frozen=True)
class Curve:
    """An ok pair's offset near its reference point, for the cycle check: ``sign`` -1 reads it
    the other way round (moving the first run onto the second)."""

    index: int
    ref: np.ndarray
    axis: np.ndarray
    gradient: np.ndarray
    d: np.ndarray
    sign: float

    def at(self, p: np.ndarray) -> np.ndarray:
        return self.sign * (self.d + self.gradient * ((p - self.ref) @ self.axis))


#: along-track sd (m) at least of a fixed pair resting on one or two windows placed by marks:
#: on 5 simulated surveys with marks, 16 such pairs on two windows were 2.7 cm off RMS (up to
#: 7.8 cm, 5.4 sd of the 1.5 cm they claimed); one window of a pair sat 12.6 cm off where the
#: other was right to 0.7 cm, and two windows cannot check each other
MARKS_PAIR_SD = 0.03
#: across and up sd (m) at least of a pair whose along-track offset rests on marks alone: on 53
#: simulated surveys, 97 such pairs fixed on one mark window were 7.3 mm off across or up RMS,
#: 29 mm at most, where their curves claimed 2-3 mm
MARKS_ACROSS_SD = 0.01
#: across and up sd (m) at least of any pair the chains keep: on 62 simulated surveys the 2128
#: ok and coarse pairs were 3-7 mm off across and up RMS where their curves claimed 2.1-2.4 mm
#: (median), and 8.8 % beyond 3 sd (worst 17 sd); at 5 mm at least, 0.4 %
PAIR_ACROSS_SD = 0.005
#: across and up sd (m) at least, per metre between the points along a profile (the pair's
#: ``point_spacing``): a sparse scan's windows agree with each other but not with the truth. On
#: 11 simulated surveys at 100-200 points per profile the 365 pairs used were 3.7-5.4 mm off
#: across and up RMS where their points lay up to 0.16 m apart, 8.8 mm at 0.16-0.20 m, 19-78 mm
#: beyond; all claimed 5-6 mm (median), and 1.0 % were beyond 5 sd (worst 20 sd: 10 cm claiming
#: 5 mm at 0.36 m). At a tenth of the spacing: 0.14 % (worst 5.3)
SAMPLING_ACROSS_SD = 0.1
#: how near a multiple of a profile's lattice (a fraction of its spacing) a peak lies on it
LATTICE_TOLERANCE = 0.1
#: a pair across a portal: one end of its windows where run b's sd is within OPEN_SKY_SD times the
#: run's least (GNSS), the other more than MAX_SD_CHANGE times that end's; its rates at both ends
#: count PORTAL_RATE_VARIANCE times their variance (:func:`_end_rates`)
OPEN_SKY_SD = 1.5
MAX_SD_CHANGE = 2.0
PORTAL_RATE_VARIANCE = 4.0
#: verdict of a pair whose along-track profile shows no peak: it cannot be ``ok``
NO_EVIDENCE = "no along-track evidence"
#: status of a pair fixed on its alias whose own along-track sd exceeds ``max_ok_sd``: the alias
#: is sure, its centimetres are not (a 1.7 cm pair sat 6.2 cm off), so it is not ``ok``; it enters
#: the adjustment with its covariance, no ties, and anchors its neighbours like a fixed pair
COARSE = "coarse"


@dataclass
class Pair:
    """One tile pair in a chain: its candidates and what predicts its neighbours."""

    index: int  # position in the pipeline's offsets
    s: float  # metres along run b's track
    u: np.ndarray  # (k,) along-track offset of each candidate (run b's direction of travel)
    shift: np.ndarray  # (k,) shift of each candidate along the pair's axis from its d_ref
    evidence: np.ndarray  # (k,) cost of each candidate's misfit
    rate: float  # d u / d s from the pair's curve
    sd: float  # along-track sd of the pair's own fit
    prior_var: float  # variance of the along offset from the trajectories' sd
    u0: float = 0.0  # along-track offset of the matcher's own choice (shift 0)
    along: float = 1.0  # d u / d shift: the pair's axis projected on run b's direction of travel
    # False for a pair with too few votes whose profile's peaks crowd (see _periodic): fitted from
    # wherever its handful of votes pointed, its curve's slope counts only once its alias is
    # fixed (one such pair's -1 mm/m among its neighbours' +2..+11 bent the chain by 0.2 m)
    # Nor does a curve with fewer than two windows that found an along-track offset: its slope
    # along the track is point-to-plane's, which means nothing there (a ring-jointed tube's pair
    # whose windows found none gave 0 mm/m among neighbours' +10..+16 and put the prediction
    # 0.3 m, 2-3 sd, off for 100 m)
    rate_trusted: bool = True
    # (k,) whether the chain may fix each candidate: the matcher's own fit, or a peak that stands
    # out within a period too (see _candidates); the others only compete
    movable: np.ndarray | None = None
    # m: how far the nearest alias the profile shows no peak for may lie (Peaks.period; None:
    # ``min_period``)
    period: float | None = None
    # (m/m)^2: variance of ``rate`` (:func:`_rate_variance`; None: ``rate_sd`` squared)
    rate_var: float | None = None
    # (k,) m: how wide each candidate's peak is at its top (Peaks.width; None: one step)
    width: np.ndarray | None = None
    # whether its along-track evidence is marks whose profile shows one peak (a box, a stain)
    lone_mark: bool = False
    # (2,) for a lone mark: the along-track offsets of its profile's two ends, past which lies
    # the nearest alias it cannot have shown (see _candidates)
    profile_ends: np.ndarray | None = None
    # m: spacings of the evenly spaced trains among its peaks (Peaks.trains)
    trains: tuple[float, ...] = ()
    # (s, rate, variance) at both ends of the windows a parabola was fitted to (_end_rates): the
    # chain observes these instead of ``rate`` where they are given
    end_rates: tuple[tuple[float, float, float], ...] = ()


class Peaks(NamedTuple):
    """The significant peaks of a pair's along-track profile (:func:`_profile_peaks`)."""

    shift: np.ndarray  # (k,) from the matcher's fit (0: that fit)
    movable: np.ndarray  # (k,) whether the chain may move the pair onto each
    misfit: np.ndarray  # (k,) 1 - fitness at each
    period: float  # m: the profile's own alias spacing, or ``min_period`` where it shows none
    width: np.ndarray  # (k,) m: how wide each peak's top is (:func:`_peak_top_width`), a step at least
    trains: tuple[float, ...] = ()  # m: spacings of the evenly spaced trains among them (:func:`_trains`)


def resolve_along_track(offsets: list[TileOffset], trajectories: dict[str, Trajectory],
                        options: AlongTrackOptions) -> tuple[list[TileOffset], list[dict]]:
    """Offsets with each candidate pair resolved, moved to another alias or demoted, and one
    report row per candidate pair."""
    if not options.enabled:
        return [_unresolved_use(o) for o in offsets], []
    offsets = [on_travel_direction(o, trajectories) for o in offsets]
    out, report = list(offsets), []
    chains: dict[tuple[str, str], list[Pair]] = {}
    travelled = {r: metres_travelled(t) for r, t in trajectories.items()}
    least_sd = {r: _least_horizontal_sd(t) for r, t in trajectories.items()}
    for k, o in enumerate(offsets):
        pair = _candidates(k, o, trajectories, travelled, least_sd, options)
        if isinstance(pair, Pair):
            chains.setdefault((o.run_a, o.run_b), []).append(pair)
        elif pair == NO_EVIDENCE:  # every shift fits alike: observed where the trajectories say
            out[k] = _at_prior(_apply(o, 0.0, False, trajectories), trajectories)
            if not o.ok:  # an ok pair's demotion is reported: its matcher's ok had no ground
                continue
            report.append(_report_row(k, o, out[k].status, NO_EVIDENCE))
    for (run_a, run_b), chain in sorted(chains.items()):
        chain.sort(key=lambda p: p.s)
        own_rate = {p.index: p.rate for p in chain}
        chain = _consensus_rates(chain, options)
        walks = _unmeasured_walks(chain, _rate_walks(chain, options), options)
        if walks.max() > options.rate_walk:
            log.info("along-track %s~%s: the drift rate wanders %.2f-%.2f mm/m per sqrt(m), measured from its "
                     "pairs and, where they measure no rate, from the trajectories' sd (rate_walk %.2f at least)",
                     run_a, run_b, walks.min() * 1e3, walks.max() * 1e3, options.rate_walk * 1e3)
        verdicts, mu, var = _resolve_chain(chain, options, walks)
        periods = _periods_near(chain, options)
        for pair, (shift, margin, verdict), m, v, near in zip(chain, verdicts, mu, var, periods, strict=True):
            o, resolved = offsets[pair.index], verdict == "resolved"
            extra = _placement_variance(o, shift, pair, options, near)
            coarse = resolved and (pair.sd**2 + extra > options.max_ok_sd**2 or _degenerate_fit(o))
            out[pair.index] = _apply(o, shift, resolved, trajectories, coarse=coarse, alias_var=extra)
            if not resolved:  # observed at its likeliest candidate, or at the prediction if none is near
                u_best = pair.u0 + shift * pair.along
                near = (u_best - m) ** 2 <= 4.0 * (v + pair.sd**2)
                out[pair.index] = _at_predicted(out[pair.index], pair.u0, pair.along, u_best if near else m, v,
                                                trajectories, on_candidate=near)
            out[pair.index] = _unresolved_use(out[pair.index])
            # (a rate its neighbours disagreed with, replaced by theirs, is no measurement of its own)
            if not resolved and pair.rate_trusted and pair.rate == own_rate[pair.index] and options.drift_rates:
                out[pair.index] = _with_drift_rate(out[pair.index], pair, trajectories, options)
            report.append(_report_row(pair.index, o, out[pair.index].status, verdict, shift, margin, pair.shift,
                                      predicted=(m, v)))
    for k in _cycle_breaks(out, options):  # three runs: d_ab + d_bc must equal d_ac
        demoted = _apply(out[k], 0.0, False, trajectories)
        out[k] = _unresolved_use(replace(demoted, info=dict(demoted.info, demoted="a triangle of runs does not close")))
        report.append(_report_row(k, out[k], out[k].status, "cycle not closed", before="ok"))
    out = [_within_reach(_unresolved_use(o), options) for o in out]  # (and those outside any chain)
    moved = sum(abs(r["shift_m"]) > 0.1 and r["status"] in ("ok", COARSE) for r in report)
    log.info("along-track: %d tile pairs with candidates, %d resolved (%d moved to another alias), %d left weak",
             len(report), sum(r["status"] == "ok" for r in report), moved,
             sum(r["status"] != "ok" for r in report))
    return out, report


def _report_row(index: int, o: TileOffset, status: str, verdict: str, shift: float = 0.0, margin: float = 0.0,
                candidate_shifts: np.ndarray | None = None, before: str | None = None,
                predicted: tuple[float, float] | None = None) -> dict:
    """One row of the along-track report (metrics.json ``adjustment.alongtrack``): the pair's row
    in offsets.csv (``pair``), its runs and tiles, its status before and after, the verdict and
    the chosen shift, its margin and the candidates' shifts; for a pair in a chain, the chain's
    along-track offset there (run b's direction of travel) and its sd (``predicted_m``,
    ``predicted_sd_m``)."""
    shifts = np.zeros(0) if candidate_shifts is None else candidate_shifts
    row = {"pair": index, "run_a": o.run_a, "run_b": o.run_b, "tile_a": o.tile_a, "tile_b": o.tile_b,
           "status_before": o.status if before is None else before, "status": status, "verdict": verdict,
           "shift_m": round(shift, 3), "margin": round(min(margin, 1e6), 1),
           "candidates": len(shifts), "candidate_shifts_m": np.round(shifts, 2).tolist()}
    if predicted is not None:
        row.update(predicted_m=round(float(predicted[0]), 3), predicted_sd_m=round(float(np.sqrt(predicted[1])), 3))
    return row


def used_along(o: TileOffset) -> bool:
    """Whether the chains used pair ``o`` along the track: ``ok``, or resolved (``coarse`` too)."""
    return o.status == "ok" or bool(o.info.get("resolved"))


class BeyondReach(NamedTuple):
    """Where a chain puts two runs further apart along the track than the matcher searched
    (:func:`beyond_reach`): the worst pair's report row, the window searched there, a window
    that would reach (``suggested``, m, rounded up to half a metre) and every run pair concerned."""

    worst: dict
    window: float
    suggested: float
    run_pairs: frozenset


def beyond_reach(report: list[dict], offsets: list[TileOffset], crop_margin: float) -> BeyondReach | None:
    """Whether a chain puts two runs further apart along the track (2 sd) than the matcher
    searched: its window (``matcher.max_misalignment``, in each pair's info) or the tiles' crop
    (``pipeline.max_misalignment_m``, ``crop_margin``). There no pair can have been matched at its
    true offset, only at an alias inside the window, and the chain leaves such pairs unresolved.
    On a simulated survey whose runs drifted 2.5 m (4 m apart), a run's pairs stayed unresolved
    over 200 m and the runs 1.26 m apart; 60 surveys of drifts up to 1.5 m reached 2.6 m at most.
    A pair the chain fixed (``ok``, or resolved: :func:`used_along`) was matched where the chain
    puts the runs."""
    rows = [r for r in report if "predicted_m" in r and r["status"] != "ok" and r["verdict"] != "resolved"]
    window = np.array([min(float(offsets[r["pair"]].info.get("window", np.inf)), crop_margin) for r in rows])
    # a prediction vaguer than the window says nothing of where the runs are (a chain with no
    # sure pair: "0.46 +- 1000 m apart" asked for a 2 km search window on a sparse scan)
    informative = np.array([r["predicted_sd_m"] for r in rows], float) <= window
    rows, window = [r for r, keep in zip(rows, informative, strict=True) if keep], window[informative]
    if not rows:
        return None
    reach = np.array([abs(r["predicted_m"]) + 2.0 * r["predicted_sd_m"] for r in rows])
    beyond = reach > window
    if not beyond.any():
        return None
    k = int(np.argmax(reach - window))
    run_pairs = frozenset((r["run_a"], r["run_b"]) for r, b in zip(rows, beyond, strict=True) if b)
    return BeyondReach(rows[k], float(window[k]), float(np.ceil(2.0 * (reach.max() + 0.5)) / 2.0), run_pairs)


def beyond_reach_note(found: BeyondReach | None) -> str | None:
    """A note (and a warning) where a chain puts two runs further apart along the track than the
    matcher searched (``found``, from :func:`beyond_reach`), with the options that would reach."""
    if found is None:
        return None
    worst, suggested = found.worst, found.suggested
    note = (f"along-track: runs {worst['run_a']} and {worst['run_b']} are {abs(worst['predicted_m']):.2f} +- "
            f"{worst['predicted_sd_m']:.2f} m apart along the track at tile {worst['tile_a']}, but tile pairs were "
            f"searched within {found.window:g} m: there they could not be matched at their true offset and stay "
            f"unresolved; run again with matcher.max_misalignment={suggested:g} "
            f"pipeline.max_misalignment_m={suggested:g}")
    log.warning(note)
    return note


def _cycle_breaks(offsets: list[TileOffset], options: AlongTrackOptions) -> list[int]:
    """Indices of ``ok`` pairs in a triangle of runs that does not close.

    At the same place, ``d_ab + d_bc = d_ac`` (each moves the second run onto the first). Three
    ``ok`` pairs whose reference points lie within ``cycle_radius`` of each other and whose sum
    misses by more than half ``min_period`` hold a wrong alias somewhere. Which one cannot be told
    from the triangle alone, so all three are demoted. A whole run shifted by one period passes
    every cycle: the anchors at the portals are what catch that.
    """
    by_pair: dict[tuple[str, str], list[Curve]] = {}
    for k, o in enumerate(offsets):
        pw = o.info.get("piecewise", {})
        if not (o.ok and "ref_point" in pw):
            continue
        ref, axis, grad = (np.asarray(pw[key], float) for key in ("ref_point", "axis", "gradient"))
        by_pair.setdefault((o.run_a, o.run_b), []).append(Curve(k, ref, axis, grad, np.asarray(o.d, float), 1.0))
        by_pair.setdefault((o.run_b, o.run_a), []).append(Curve(k, ref, axis, grad, np.asarray(o.d, float), -1.0))
    runs = sorted({r for pair in by_pair for r in pair})
    broken: set[int] = set()
    for a, b, c in ((a, b, c) for a in runs for b in runs for c in runs if a < b < c):
        for ab in by_pair.get((a, b), []):  # a few hundred pairs: small loops
            near_bc, near_ac = (_near(by_pair.get(key, []), ab.ref, options.cycle_radius) for key in ((b, c), (a, c)))
            for bc in near_bc:
                for ac in near_ac:  # each pair's offset taken at the same place (its drift rate)
                    if np.linalg.norm(ab.at(ab.ref) + bc.at(ab.ref) - ac.at(ab.ref)) > 0.5 * options.min_period:
                        broken |= {ab.index, bc.index, ac.index}
    if broken:
        log.warning("along-track: %d ok tile pairs in triangles of runs that do not close; demoted", len(broken))
    return sorted(broken)


def _near(curves: list[Curve], p: np.ndarray, radius: float) -> list[Curve]:
    return [q for q in curves if np.linalg.norm((q.ref - p)[:2]) <= radius]


def _candidates(index: int, o: TileOffset, trajectories: dict[str, Trajectory],
                travelled: dict[str, np.ndarray], least_sd: dict[str, float | None],
                options: AlongTrackOptions) -> Pair | str | None:
    """The pair's alias candidates; :data:`NO_EVIDENCE` if its profile shows no peak at all (it
    fits alike at every shift); None if it has no along-track fit to choose from."""
    pw, prof = o.info.get("piecewise"), o.info.get("alias_profile")
    if o.status not in ("ok", "ambiguous", "degenerate") or not pw or not prof or "fit_cov" not in pw:
        return None
    times = (o.info.get("time_a", np.nan), o.info.get("time_b", np.nan))
    if not np.isfinite(times).all() or o.run_b not in trajectories or o.run_a not in trajectories:
        return None
    found = _profile_peaks(prof, options)
    edges = _profile_peaks(o.info["edge_profile"], options) if "edge_profile" in o.info else None
    if edges is not None and len(edges[0]) >= 2 and _periodic(edges[0], options.min_period) and (
            found is None or len(found[0]) <= 1 or not _periodic(found[0], options.min_period)):
        # the edges' own profile shows aliases a period apart where the fitness profile shows
        # one peak at most, or peaks that crowd (its noise): edges too thin for the fitness repeat
        # there (a tube's ring joints, railtraj.matching.piecewise.edge_profile). The fitness's
        # one peak was the top of its slope, 3.7 m from the windows
        found = edges
    if found is None:
        return NO_EVIDENCE  # no peak stands out: the pair says nothing along the track
    if edges is not None and found is not edges:
        found = found._replace(shift=_on_edges(found, edges.shift, float(prof["step"])))
    shift, movable, m, period, width, trains = found
    lone_mark = found is not edges and prof.get("source") == "marks" and len(shift) == 1
    if _unchecked_fit(o):
        movable = np.zeros_like(movable)
    axis = np.asarray(pw["axis"], float)
    traj_b = trajectories[o.run_b]
    direction, prior_var = _along_frame(o, trajectories)
    sign = float(np.sign(axis @ direction)) or 1.0
    u = (o.d @ direction) + shift * (axis @ direction)
    cov = np.asarray(pw["fit_cov"], float)
    # the profile is measured about the matcher's curve, fitted at its own choice, so it favours
    # that choice; a misfit ratio is therefore worth at most ``max_evidence``
    evidence = np.minimum(9.0 * (np.log(m / m.min()) / np.log(options.evidence_ratio)) ** 2, options.max_evidence)
    # marks are no repeated structure: their profile shows every alias within its reach, so an
    # alias it shows no peak for lies past one of its ends
    ends = None
    if lone_mark:
        reach = prof["start"] + np.array([0.0, prof["step"] * (len(prof["fitness"]) - 1)])
        ends = o.d @ direction + reach * (axis @ direction)
    s = float(np.interp(times[1], traj_b.time, travelled[o.run_b]))
    rate = _rate(o, np.asarray(pw["gradient"], float), direction, sign, traj_b)
    return Pair(index, s, u, shift, evidence, rate, float(np.sqrt(direction @ cov @ direction)),
                max(prior_var, 1e-6), float(o.d @ direction), float(axis @ direction),
                rate_trusted=("few_votes" not in o.info or _periodic(shift, options.min_period))
                and ("windows" not in pw or _along_windows(pw["windows"]) >= 2), movable=movable, period=period,
                rate_var=_rate_variance(pw, options), width=width, lone_mark=lone_mark, profile_ends=ends,
                trains=() if lone_mark else trains,
                end_rates=() if _degenerate_fit(o) else _end_rates(pw, s, rate, sign, traj_b, travelled[o.run_b],
                                                                         least_sd[o.run_b], options))


def _on_edges(found: Peaks, edge_shift: np.ndarray, step: float) -> np.ndarray:
    """``found``'s shifts, each moved to the nearest peak of the edge profile (``edge_shift``)
    within half its top's width where that top is wider than a ``step``. A flat fitness top
    places an alias only to within its width (and the chain claims no better,
    :func:`_placement_variance`); the edges may say where in it. On held-out tube 510 a top
    25 cm wide put a pair 2.70 m on, 9.0 cm off; the edge profile's joint put it 2.2 cm off.
    The matcher's own fit (shift 0) is placed by its windows and stays."""
    shift = found.shift.copy()
    for k in np.flatnonzero((shift != 0.0) & (found.width > 1.5 * step)):  # a handful of candidates
        near = edge_shift[np.abs(edge_shift - shift[k]) <= 0.5 * found.width[k]]
        if len(near):
            shift[k] = near[np.argmin(np.abs(near - shift[k]))]
    return shift


def _profile_peaks(prof: dict, options: AlongTrackOptions) -> Peaks | None:
    """The significant peaks of an along-track profile (``info["alias_profile"]`` or
    ``info["edge_profile"]``) and the profile's alias period; None where no peak stands out."""
    # scipy.signal takes ~1 s to import: not at `railtraj --help`
    from scipy.signal import find_peaks, peak_prominences

    fitness = np.asarray(prof["fitness"], float)
    if not len(fitness) or not np.isfinite(fitness).all() or (
            fitness.max() < options.min_fitness and prof.get("source") != "marks"):
        return None  # the pair's clouds hardly meet at any shift
    ts = prof["start"] + prof["step"] * np.arange(len(fitness))
    misfit = np.maximum(1.0 - fitness, 1e-3)
    # candidates are the significant peaks only: a profile's noise is no alias. A peak stands
    # out when it rises above the higher dip beside it by min_significance counting sd (the
    # fitness is a share of the profile's points: binomial noise)
    peaks, props = find_peaks(fitness, prominence=0.0)  # (a peak on the window's edge is no peak)
    n_points = float(prof.get("points", 2000))
    measured = np.asarray(prof.get("noise", []), float)  # an edge profile's: its costs are no counts
    costs = len(measured) == len(fitness)

    def noise(prominence: np.ndarray) -> np.ndarray:
        if costs:  # the peak's and its dip's errors (about as large)
            return np.sqrt(2.0) * measured[peaks]
        return _counting_noise(fitness, peaks, prominence, n_points)

    peak_noise = noise(props["prominences"])
    significant = props["prominences"] >= options.min_significance * peak_noise
    # ... and another alias than the matcher's own fit is one to move to only if it also stands
    # out against the dips within min_period either side (aliases lie a period apart, so a
    # real one falls off within a period). Against the whole window, the top sample of a flat
    # profile rose over the falls at the window's ends, and the chain moved a ring-jointed
    # tube's pair 1.00 m onto it: 21 cm off, claiming 1.6 cm. Such a peak still competes (a
    # rival that keeps a pair from being fixed): dropped, it let the chain fix a demo pair 24 cm off
    within = 2 * int(np.ceil(options.min_period / prof["step"])) + 1
    with warnings.catch_warnings():  # "some peaks have a prominence of 0": a flat stretch, no alias
        warnings.simplefilter("ignore", RuntimeWarning)
        local = peak_prominences(fitness, peaks, wlen=within)[0]
    local_noise = noise(local)
    movable = local >= options.min_significance * local_noise
    shift = ts[peaks] + _vertex(fitness, peaks) * prof["step"]  # sub-sample, from the matcher's fit
    lattice = _lattice_period(shift[significant], options.min_period)
    if lattice:  # a peak where the significant ones' lattice puts an alias is tested there only
        on = _off_multiple(shift, lattice) <= LATTICE_TOLERANCE * lattice
        significant |= on & (props["prominences"] >= options.lattice_significance * peak_noise)
        movable |= on & (local >= options.lattice_significance * local_noise)
    peaks, movable, shift = peaks[significant], movable[significant], shift[significant]
    period, trains = _alias_period(shift, options.min_period), _trains(shift, options.min_period)
    if len(peaks):
        # the profile is measured about the curve fitted at the matcher's choice, its across and up
        # included; an alias 3 m away sees run a's drift moved them by 3 m times its rate, so the
        # truth there misfit 0.3-4.9 % of the points where the matcher's choice misfit 0-0.8 %
        # (session 57): a ratio of two such shares says nothing, and below misfit_floor they count
        # as that. (An edge profile's misfits are costs, no shares: there the joint the curve was
        # fitted on misfits far less than the others, and its ripple is no alias.)
        floor = 0.0 if costs else options.misfit_floor
        floored = np.maximum(misfit[peaks], floor)
        keep = floored <= options.max_misfit_ratio * floored.min()
        peaks, movable, shift = peaks[keep], movable[keep], shift[keep]
    if not len(peaks):
        return None
    order = np.argsort(misfit[peaks])[: options.max_candidates]
    peaks, movable, shift = peaks[order], movable[order], shift[order]
    # a peak closer to the matcher's own fit than a quarter period is that fit (its windows
    # place it better than the profile's 5 cm steps)
    shift = np.where(np.abs(shift) < 0.25 * options.min_period, 0.0, shift)
    shift, first = np.unique(shift, return_index=True)
    peaks, movable = peaks[first], movable[first] | (shift == 0.0)  # the matcher's own fit always is
    top_sd = measured[peaks] if costs else np.sqrt(misfit[peaks] / n_points)
    return Peaks(shift, movable, misfit[peaks], period, _peak_top_width(fitness, peaks, top_sd) * prof["step"], trains)


def _peak_top_width(fitness: np.ndarray, peaks: np.ndarray, top_sd: np.ndarray) -> np.ndarray:
    """How many samples wide each peak's top is: the run of samples around it within ``top_sd``
    (its sample's sd) of its value. A ring-jointed tube's fitness profile is flat: 1.0 from
    2.65 to 2.85 m on a held-out tube, where the chain moved a pair 2.70 m, 9 cm short of the
    joint its edge profile showed at 2.75-2.80 m."""
    out = np.ones(len(peaks))
    for k, (p, sd) in enumerate(zip(peaks, top_sd, strict=True)):  # a handful of candidates
        below = np.flatnonzero(fitness < fitness[p] - sd)
        out[k] = below[below > p].min(initial=len(fitness)) - below[below < p].max(initial=-1) - 1
    return out


def _alias_period(shift: np.ndarray, min_period: float) -> float:
    """How far apart a pair's aliases lie, from its profile's significant peaks (shifts from
    the matcher's fit, which counts as one): their spacing where three or more lie evenly (every
    gap within 15 % of the median gap, at least ``min_period``), else ``min_period``.

    The chain weighs an alias the profile shows no peak for at the nearest multiple of this. A
    ring-jointed tube's profile shows its joints every 1.5 m and nothing between; taken
    ``min_period`` (0.5 m) away instead, such an alias kept a prediction of 0.16-0.27 m sd below
    the margin at 10 of 18 pairs whose joint nearest the prediction was right to 1-3 cm. Peaks
    dropped for their misfit count here: commensurate ribs and sleepers show their 3.0 m
    combination strongest, and the sleepers' 0.6 m between, weaker, keep the period short."""
    gaps = _peak_gaps(shift, min_period)
    if len(gaps) < 2:
        return min_period
    median = float(np.median(gaps))
    even = median >= min_period and bool((np.abs(gaps - median) <= 0.15 * median).all())
    return median if even else min_period


def _with_fit(shift: np.ndarray, min_period: float) -> np.ndarray:
    """A profile's peaks in order, the matcher's fit (shift 0) among them; a peak within a
    quarter of ``min_period`` of that fit is that fit."""
    return np.unique(np.append(np.where(np.abs(shift) < 0.25 * min_period, 0.0, shift), 0.0))


def _peak_gaps(shift: np.ndarray, min_period: float) -> np.ndarray:
    """Gaps (m) between a profile's peaks in order (:func:`_with_fit`)."""
    return np.diff(_with_fit(shift, min_period))


def _trains(shift: np.ndarray, min_period: float) -> tuple[float, ...]:
    """Spacings (m) of the evenly spaced trains among a profile's peaks (the matcher's fit,
    shift 0, among them): each peak at least ``min_period`` from that fit whose distance has two
    or more non-zero multiples (itself one) on peaks, within ``LATTICE_TOLERANCE``; each spacing
    once, the mean of its members' distances over their multiples.

    Ribs and sleepers give two trains that interleave, so the gaps between the peaks are not
    even and :func:`_alias_period` sees no period. Held-out mixed 4602 (ribs 1.5 m, sleepers
    0.65 m): a pair's peaks lay -0.48, 0.81, 1.48, 2.10, 2.94, 3.41 and 4.51 m from its fit,
    which was a rib alias; the chain moved it 1.48 m onto the truth (1.1 cm off), but its
    neighbours showed only the sleepers' 0.65 m, so the move was taken for one off every period
    by 19 cm (:func:`_placement_variance`), its sd with it, and the runs stayed 9 cm apart along
    the track beside it."""
    s = _with_fit(shift, min_period)
    found: list[float] = []
    for base in np.abs(s[np.abs(s) >= min_period]):  # a handful of peaks
        n = np.round(s / base)
        on = (n != 0) & (_off_multiple(s, base) <= LATTICE_TOLERANCE * base)
        if len(np.unique(n[on])) >= 2:
            spacing = float(np.mean(np.abs(s[on] / n[on])))
            if not any(abs(spacing - f) <= LATTICE_TOLERANCE * f for f in found):
                found.append(spacing)
    return tuple(sorted(found))


def _lattice_period(shift: np.ndarray, min_period: float) -> float | None:
    """The spacing of which every gap between a profile's significant peaks (and the matcher's
    fit, shift 0) is a whole multiple, within ``LATTICE_TOLERANCE`` of it: the lattice its aliases
    lie on, where three or more peaks show one at least ``min_period`` long; else None.

    Sleepers in an open cutting give a train of peaks of one height that fades with the overlap.
    Searched for anywhere, a peak must rise 3 sd to be no noise; at a multiple of the train's
    spacing an alias is expected, and 2 sd say it is there. Portal_trap 1's pair at its multipath
    bump had its right alias 2.6 m on, 2.9 sd, beside significant peaks 0.65, 1.95 and 3.25 m on."""
    gaps = _peak_gaps(shift, min_period)
    if len(gaps) < 2:
        return None
    base = float(gaps.min())
    if base < min_period or (_off_multiple(gaps, base) > LATTICE_TOLERANCE * base).any():
        return None
    return float(np.mean(gaps / np.round(gaps / base)))


def _counting_noise(fitness: np.ndarray, peaks: np.ndarray, prominence: np.ndarray, n_points: float) -> np.ndarray:
    """sd of a peak's rise above its dip: the fitness is a share of the profile's points
    (binomial noise), counted at the peak and at the dip."""
    dip = np.maximum(1.0 - (fitness[peaks] - prominence), 0.0)
    return np.sqrt((np.maximum(1.0 - fitness[peaks], 1e-3) + dip) / n_points)


def _periodic(shift: np.ndarray, min_period: float) -> bool:
    """Whether a profile's peaks (and the matcher's own fit, shift 0) are all at least
    ``min_period`` apart, as aliases are. Peaks 0.13-0.17 m apart are the profile's noise: the
    pair's windows found nothing repeatable there either."""
    return bool((np.diff(np.unique(np.append(shift, 0.0))) >= min_period).all())


def _used_windows(pw: dict) -> np.ndarray:
    """Along-track positions of the windows a pair's curve was fitted on (all, in the older
    five-column records without the flag)."""
    return np.array([w[0] for w in pw.get("windows", []) if len(w) < 5 or w[4] > 0], float)


def _rate_variance(pw: dict, options: AlongTrackOptions) -> float:
    """Variance of a pair's drift rate: its curve's slope at the reference point, fitted to the
    windows it used (a parabola through 4 or more, a line through fewer), each known to
    ``window_sd`` along the track, plus ``rate_sd`` squared.

    On 1013 trusted pairs of 26 simulated surveys the rate's error against the truth grew with
    that geometry: 1.0 mm/m RMS on 5-6 windows spanning 20 m, 3.8 on three spanning 9 m, 15.6 on
    two (up to 46 mm/m). With ``rate_sd`` alone, 2.4 % were beyond 3 sd and 1.3 % beyond 4; with
    the geometry, 0.2 % and none.

    Windows scattered more than ``window_sd`` about the curve (``window_resid_sd_mm``) count with
    that scatter: on a sparse scan (120 points per profile) a pair's three windows found two ring
    aliases 1.2 m apart, and their slope of -119 mm/m (the truth: 0), taken to 4 mm/m at the
    chain's first pair, bent the prediction 1.3-2.5 m off. Two pairs were fixed there on ring
    aliases, claiming 2-3 cm."""
    if len(_used_windows(pw)) < 2:
        return options.rate_sd**2
    _, cov = _curve_cov(pw, options)
    return float(options.rate_sd**2 + cov[1, 1])


def _curve_cov(pw: dict, options: AlongTrackOptions) -> tuple[np.ndarray, np.ndarray]:
    """The windows a pair's along-track curve used, about its reference point (the median of run
    b's points, about the windows' median), and the covariance of the curve's coefficients (a
    parabola through 4 or more, a line through fewer), each window known to ``window_sd``, or to
    the windows' scatter about the curve where that is more (it lends the slope that scatter)."""
    x = _used_windows(pw)
    x = x - np.median(x)
    design = np.vander(x, 3 if len(x) >= 4 else 2, increasing=True)
    scatter = max(options.window_sd, float(pw.get("window_resid_sd_mm", [0.0])[0]) / 1000.0)
    return x, np.linalg.pinv(design.T @ design) * scatter**2


def _end_rates(pw: dict, s: float, rate: float, sign: float, traj_b: Trajectory, travelled_b: np.ndarray,
               least_sd_b: float | None, options: AlongTrackOptions) -> tuple[tuple[float, float, float], ...]:
    """The pair's drift rate at both ends of the windows its curve was fitted to, where that curve
    is a parabola (4 windows or more spanning ``drift_rate_span``): ``(s, rate, variance)`` per end,
    ``s`` in metres along run b's track (the pair is at ``s``, its axis ``sign`` along run b's
    travel), the variance that of the parabola's slope there (as :func:`_rate_variance`), plus
    ``rate_sd`` squared. Empty otherwise. A pair across a portal (:data:`PORTAL_RATE_VARIANCE`)
    counts them at twice their sd: where GNSS comes back the drift stops at a kink no parabola
    follows. At 1 sd, one such pair of held-out thesis 5623 gave -9 mm/m at its inner end where
    the truth was -36 (4.8 sd), the prediction at its neighbour moved 15 cm, the neighbour stayed
    unfixed, and the run pair went 0.033 / 0.062 -> 0.259 / 0.476 m (0.027 / 0.055 at 2 sd);
    dropped altogether, the portal pairs of 5612, right to 1.2 sd, were lost with them, and
    0.031 / 0.082 m went back to 0.107 / 0.198.

    One rate per pair, at its middle, samples the drift's rate every 25 m along a tunnel that runs
    along the tile grid; where the rate swings (+33 to -43 mm/m within 125 m, held-out thesis
    5612 at heading 0), a rate missing at its extreme put the prediction 0.4-0.8 m off over
    100 m, 2.4-4 of its sd. The parabola's slope at its ends samples it twice as densely. On 54
    held-out surveys the end rates were 3.3 mm/m RMS off the truth (the middle's 1.8), 0.3 % of
    them beyond 3 sd."""
    used = _used_windows(pw)
    if len(used) < 4 or np.ptp(used) < options.drift_rate_span or "curvature_mm_per_m2" not in pw:
        return ()
    x, cov = _curve_cov(pw, options)
    bend = 2.0 * float(pw["curvature_mm_per_m2"][0]) / 1000.0  # d rate / d x along the pair's axis
    ends_at = np.interp(s + sign * np.array([x.min(), x.max()]), travelled_b, traj_b.time)
    inflate = PORTAL_RATE_VARIANCE if _across_portal(traj_b, ends_at, least_sd_b) else 1.0
    ends = []
    for end in (x.min(), x.max()):
        slope = np.array([0.0, 1.0, 2.0 * end])  # the parabola's slope at ``end``
        ends.append((s + sign * end, rate + bend * end, inflate * (options.rate_sd**2 + float(slope @ cov @ slope))))
    return tuple(sorted(ends))


def _least_horizontal_sd(traj: Trajectory) -> float | None:
    """The run's least reported horizontal sd (where its GNSS is best); None where it reports none.
    Once per run: over a 1 h run at 200 Hz it takes 16 ms, and every pair with end rates asks."""
    return None if traj.sd is None else float(np.hypot(traj.sd[:, 0], traj.sd[:, 1]).min())


def _across_portal(traj: Trajectory, times: np.ndarray, least: float | None) -> bool:
    """Whether the run passes a portal between ``times``: at one its horizontal sd is within
    :data:`OPEN_SKY_SD` times its ``least`` (:func:`_least_horizontal_sd`; GNSS), at the other more
    than :data:`MAX_SD_CHANGE` times that (False where the run reports no sd)."""
    if traj.sd is None or least is None:
        return False
    horizontal = np.hypot(*traj.sd_at(times)[:, :2].T)
    return bool(horizontal.min() <= OPEN_SKY_SD * least and horizontal.max() > MAX_SD_CHANGE * horizontal.min())


def _with_drift_rate(o: TileOffset, pair: Pair, trajectories: dict[str, Trajectory],
                     options: AlongTrackOptions) -> TileOffset:
    """An unresolved pair with its curve's change of offset along the track, for the adjustment
    (``info["drift_rate"]``): the offset moves by ``gradient x L`` from ``half`` metres before its
    reference point to ``half`` after (``L = 2 half``, the span of its windows), whichever alias
    it sits on, to the rate's sd (``pair.rate_var``) times ``L`` along the track.

    Without it the adjustment has nothing along the track between fixed pairs and bridges the
    correction smoothly from one to the next. In a ring-jointed tube 280 m passed between two
    fixed pairs (offsets 0.07 and 0.26 m) while the runs' offset fell to -0.52 m between, so the
    bridge moved the runs further apart there (0.71 m) than the input had them (0.52 m); ten
    unresolved pairs there each measured the offset's rate.

    Not for a coarse pair (fixed, one offset known to centimetres): its rate, within its sd,
    moves the correction beside it by that sd times the distance to the next pair. Tried on
    held-out surveys: all-coarse commensurate_fast 1061 0.020 / 0.063 -> 0.016 / 0.055 m, but
    thesis 4606 0.012 / 0.031 -> 0.014 / 0.050 and commensurate 1053 0.015 / 0.042 -> 0.018 /
    0.046 (one rate 1 sd off bent the correction 4 cm, 20 m away)."""
    pw = o.info["piecewise"]
    s = _used_windows(pw)
    if (o.status != "ambiguous" or not np.isfinite(o.cov).all() or len(s) < max(2, options.drift_rate_windows)
            or np.ptp(s) < options.drift_rate_span):
        return o
    half = 0.5 * float(np.ptp(s))
    axis, gradient = np.asarray(pw["axis"], float), np.asarray(pw["gradient"], float)
    traj_a, traj_b = trajectories[o.run_a], trajectories[o.run_b]
    rate = {"time_a": [_time_after_shift(traj_a, o.info["time_a"], k * half * axis) for k in (-1.0, 1.0)],
            "time_b": [_time_after_shift(traj_b, o.info["time_b"], k * half * axis) for k in (-1.0, 1.0)],
            "change": (2.0 * half * gradient).tolist(), "axis": axis.tolist(),
            "sd_m": 2.0 * half * float(np.sqrt(pair.rate_var or options.rate_sd**2))}
    return replace(o, info=dict(o.info, drift_rate=rate))


def _rate(o: TileOffset, gradient: np.ndarray, direction: np.ndarray, sign: float, traj_b: Trajectory) -> float:
    """d u / d s: how fast the pair's along-track offset ``u = d . direction`` changes per metre
    of run b's travel.

    Two terms: the curve's own gradient, and, on a curved track, the turn of the direction
    itself, which moves the offset's across component into the along one at ``curvature x
    across`` per metre. On a 540 m radius with 1.5 m across, that is 2.9 mm/m: the chain's
    prediction through a curved station fell 0.3-0.4 m short without it, and no pair there
    could be fixed.
    """
    left = np.array([-direction[1], direction[0], 0.0])
    return float(gradient @ direction) * sign + _curvature(traj_b, float(o.info["time_b"])) * float(o.d @ left)


def _curvature(traj: Trajectory, t: float, half: float = 5.0) -> float:
    """Signed curvature (1/m, left turns positive) of the run's track in plan at ``t``: the turn
    of its direction of travel over ``half`` metres either side."""
    speed = float(np.linalg.norm(_velocity(traj, t)))
    if speed <= 0:
        return 0.0
    dt = half / speed
    lo, hi = max(t - dt, traj.span[0]), min(t + dt, traj.span[1])  # near a run's ends: what it covered
    a, b = _direction(traj, lo), _direction(traj, hi)
    travelled = speed * (hi - lo)
    return float(np.arctan2(a[0] * b[1] - a[1] * b[0], a @ b)) / max(travelled, 1e-6)


def _along_frame(o: TileOffset, trajectories: dict[str, Trajectory]) -> tuple[np.ndarray, float]:
    """Run b's unit direction of travel where the pair was observed, and the variance of the
    runs' along-track offset there from their trajectories' sd (1e4 where they report none)."""
    times = (o.info["time_a"], o.info["time_b"])
    traj_b = trajectories[o.run_b]
    direction = _direction(traj_b, times[1])
    sd_a, sd_b = trajectories[o.run_a].sd_at(np.array([times[0]])), traj_b.sd_at(np.array([times[1]]))
    prior_var = float((sd_a[0] ** 2 + sd_b[0] ** 2) @ direction**2) if sd_a is not None and sd_b is not None else 1e4
    return direction, prior_var


def _vertex(f: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Sub-sample position (in steps, within +-0.5) of the peak of ``f`` at each index ``k``:
    the vertex of the parabola through the sample and its neighbours (0 at the ends)."""
    inner = (k > 0) & (k < len(f) - 1)
    out = np.zeros(len(k))
    y0, y1, y2 = f[k[inner] - 1], f[k[inner]], f[k[inner] + 1]
    curv = y0 - 2 * y1 + y2
    out[inner] = np.where(curv < 0, 0.5 * (y0 - y2) / np.where(curv < 0, curv, -1.0), 0.0)
    return np.clip(out, -0.5, 0.5)


def _resolve_chain(chain: list[Pair], options: AlongTrackOptions, walks: np.ndarray
                   ) -> tuple[list[tuple[float, float, str]], np.ndarray, np.ndarray]:
    """Bootstrapped fixing along one run pair, as in GNSS integer ambiguity resolution.

    The along-track offset is predicted at every pair (mean and sd) by a Kalman smoother. It runs
    over the chain with the measured rates as input, anchored by the trajectories' sd and by the
    pairs fixed so far. A pair is fixed on the candidate nearest its prediction when

    * the pair's own along-track sd is at most ``max_pair_sd``,
    * that candidate is within ``3 sd`` of the prediction, and
    * the runner-up, or an alias a multiple of the pair's period (``Pair.period``) away that
      its profile shows no peak for,
      costs at least ``min_margin`` more (prediction misfit plus the capped fitness evidence),
    * and, for another alias than the matcher's, no other candidate lies within ``min_period``
      of it (two aliases are a period apart): a noisy profile's peaks crowd, and one of them
      15 cm off the truth (0.36 m from the next peak, in a ring-jointed tube) and one 8 cm off
      was fixed next to a precise prediction (a featureless tunnel near its portal). The
      matcher's own choice counts as such a peak: a profile's only peak 16 cm from the
      windows' fit is a disagreement, not an alias (it sat 11 cm off, in the demo's circular
      section),
    * and that alias stands out within a period of itself, not only against the whole window
      (``Pair.movable``; a flat profile's top sample is no alias).

    A pair resting on one mark (``Pair.lone_mark``: a box, a stain) is charged no alias within
    its profile, which spans the whole search window: the unseen alias lies just past the
    profile's end nearest the prediction (``Pair.profile_ends``), so the mark is fixed only where
    the search window covers the prediction (2.6 sd of it at least, for ``min_margin`` 16).
    Session 36 charged the nearer end whichever side it lay: a held-out feature-poor tunnel's
    boxes near tile edges, their profiles 0.9-1.7 m long on one side and 3 m on the other, the
    predictions 0.4-0.9 m off towards the long side (sd 0.3-0.4 m), stayed unfixed (inter-run
    0.597 m; fixed, 0.032 m). Session 30 fixed
    such a pair only where the chain predicted it to 0.167 m: fixed 350 m from other
    evidence, one box's correction, spread over the gaps, had moved the runs apart where the
    drift turned. The adjustment now follows the drift between such ties: on 53 simulated
    surveys, 29 lone marks predicted to 0.17-0.60 m were fixed, each within 3 cm of the truth
    (sd 3 cm at least); feature_poor 0 / 1 / 2 went from 0.168 / 0.414 / 0.660 m inter-run RMS
    to 0.035 / 0.264 / 0.136 m, a held-out one with 3 runs and a cabinet every 120 m from 0.700
    to 0.052 m, no epoch beyond 3 sd on any.

    Before any pair is fixed in a round, a pair that has no alias within ``anchor_gate`` sd of
    its prediction releases its anchor (:func:`_contradicted`), and the chain predicts again.
    The offset there holds one run's GNSS bias, which bends faster than an INS's drift: the
    rate's wander on the steps either side is ``released_walk`` times more (as the adjustment
    lets a run bend up to ``max_bend_widening`` times more where the sd check widened it). With
    the drift's wander, a held-out survey's pair at a multipath bias's peak, right to 7 mm, was
    predicted 3.7 sd off and left unfixed, and the adjustment kept its run 0.25 m off claiming
    4 cm (run b of mixed 6 with multipath at its first portal: 1.1 % of epochs beyond 3 sd).

    Fixed pairs then anchor the next round, until no pair can be fixed. ``walks`` is the drift
    rate's wander per step (:func:`_rate_walks`). Returns, per pair, the
    chosen shift, its margin and ``resolved`` or ``ambiguous``; and the last round's predicted
    along-track offset (mean, variance) at every pair.
    """
    n = len(chain)
    fixed = np.full(n, np.nan)  # along offset of the fixed candidate
    result: list[tuple[float, float, str]] = [(0.0, 0.0, "ambiguous")] * n
    anchored = anchor_var = _anchor_variance(chain, options)
    drift_walks = walks
    while True:
        mu, var = _smooth(chain, fixed, options, walks, anchor_var)
        released = np.isfinite(anchor_var) & _contradicted(chain, fixed, mu, var, options)
        if released.any():  # predicted again without them, before anything is fixed on them
            anchor_var = np.where(released, np.inf, anchor_var)
            # there the runs' offset holds a GNSS bias, which bends faster than an INS's drift
            beside = np.flatnonzero(np.isinf(anchor_var) & np.isfinite(anchored))
            walks = drift_walks.copy()
            walks[np.minimum(np.concatenate([beside, beside + 1]), n - 1)] *= options.released_walk
            continue
        newly = []
        for i, p in enumerate(chain):
            if np.isfinite(fixed[i]):
                continue
            total = var[i] + p.sd**2
            cost = (p.u - mu[i]) ** 2 / total + p.evidence
            order = np.argsort(cost)
            best = int(order[0])
            runner_up = cost[order[1]] if len(cost) > 1 else np.inf
            # an alias a multiple of the pair's period away may exist although the profile
            # showed no peak there; the one nearest the prediction competes (worth max_evidence)
            period = p.period or options.min_period
            k = np.round((p.u[best] - mu[i]) / period)
            k = k if k != 0 else np.sign(p.u[best] - mu[i]) or 1.0
            unseen = (p.u[best] - k * period - mu[i]) ** 2 / total + options.max_evidence
            if p.profile_ends is not None:  # a lone mark's: just past the profile's end nearest the prediction
                unseen = np.min((p.profile_ends - mu[i]) ** 2) / total + options.max_evidence
            margin = float(min(runner_up, unseen) - cost[best])
            near = (p.u[best] - mu[i]) ** 2 <= 9.0 * total and p.sd <= options.max_pair_sd
            # peaks closer than the shortest period cannot both be aliases: one is the
            # profile's noise, and where another alias sits is then known no better than that;
            # the matcher's own choice (shift 0) counts as such a peak whether the profile shows it or not
            others = np.append(np.delete(p.shift, best), 0.0)
            crowded = p.shift[best] != 0 and bool((np.abs(others - p.shift[best]) < options.min_period).any())
            result[i] = (float(p.shift[best]), margin, "ambiguous")
            movable = p.movable is None or bool(p.movable[best])
            if near and not crowded and movable and margin >= options.min_margin:
                newly.append((i, best, margin))
        if not newly:
            return result, mu, var
        for i, best, margin in newly:
            fixed[i] = chain[i].u[best]
            result[i] = (float(chain[i].shift[best]), margin, "resolved")


def _rate_walks(chain: list[Pair], options: AlongTrackOptions) -> np.ndarray:
    """How fast this run pair's drift rate wanders, per step of the chain (entry ``i``: from
    pair ``i - 1`` to ``i``), from its own pairs' rates, at least ``rate_walk``: two rates ``ds``
    apart differ by ``2 rate_sd^2 + walk^2 ds`` in the mean square.

    Over the whole chain it is measured over the distances the chain bridges (50-150 m); the
    median keeps stray rates out. But an INS's drift need not bend alike everywhere: where its
    velocity error wanders (simulated as an integrated random walk), the rate climbed from -10
    to -34 mm/m and back to +18 within 200 m, four times the chain's median wander, and the
    prediction across it sat 0.36 m (5 sd) off, so three ``ok`` pairs right to 1 cm could not be
    fixed. So near each step it is measured again, from the pairs 10-60 m apart whose midpoint
    lies within ``walk_radius``, and the larger of the two counts."""
    s_all = np.array([p.s for p in chain])
    walks = np.full(len(chain), options.rate_walk)
    rates = np.array([p.rate for p in chain if p.rate_trusted])
    s = s_all[[p.rate_trusted for p in chain]]
    ds = np.abs(s[None, :] - s[:, None])
    q = ((rates[None, :] - rates[:, None]) ** 2 - 2 * options.rate_sd**2) / np.maximum(ds, 1e-9)
    far = np.triu((ds >= 50.0) & (ds <= 150.0), 1)
    if far.sum() >= 5:
        walks[:] = max(options.rate_walk, np.sqrt(max(np.median(q[far]), 0.0)))
    near = np.triu((ds >= 10.0) & (ds <= 60.0), 1)
    if options.walk_radius <= 0 or near.sum() < 5:
        return walks
    mid, q_near = ((s[None, :] + s[:, None]) / 2)[near], q[near]
    step_mid = (s_all[1:] + s_all[:-1]) / 2
    around = np.abs(mid[None, :] - step_mid[:, None]) <= options.walk_radius  # (steps, rate pairs)
    counted = around.sum(axis=1) >= 5
    local = np.nanmedian(np.where(around, q_near[None, :], np.nan)[counted], axis=1)
    walks[1:][counted] = np.maximum(walks[1:][counted], np.sqrt(np.maximum(local, 0.0)))
    return walks


def _unmeasured_walks(chain: list[Pair], walks: np.ndarray, options: AlongTrackOptions) -> np.ndarray:
    """``walks`` where the chain measures how its drift rate wanders; across a stretch of more than
    ``unmeasured_gap`` metres without a trusted rate, at least the wander the trajectories' own
    sd implies (:func:`_walk_of_the_prior`).

    :func:`_rate_walks` measures the wander from rates at most 150 m apart, so across a longer
    stretch without one nothing measures it, and ``rate_walk`` alone made the chain sure of
    offsets its trajectories were not: in a held-out feature-poor tunnel (three runs, a cabinet
    every 200 m), run b drifted 1.8 m from run a mid-tunnel, where the trajectories' sd of their
    offset was 1.0 m, and the chain predicted 0.02 +- 0.46 m from the portals' rates. The
    cabinets' pairs, each right to 2 cm, lay 3.3-4 sd off that and stayed unfixed (run a~run b
    1.05 m inter-run RMS, 0.81 of the input's)."""
    s = np.array([p.s for p in chain])
    measured = np.concatenate([[-np.inf], s[[p.rate_trusted for p in chain]], [np.inf]])
    before = measured[np.searchsorted(measured, s[:-1], side="right") - 1]  # the last rate at or before each step
    after = measured[np.searchsorted(measured, s[1:], side="left")]  # the first at or after it
    unmeasured = np.append(False, after - before > options.unmeasured_gap)  # entry i: the step from pair i - 1
    if not unmeasured.any():
        return walks
    return np.where(unmeasured, np.maximum(walks, _walk_of_the_prior(chain, options)), walks)


def _walk_of_the_prior(chain: list[Pair], options: AlongTrackOptions) -> float:
    """How fast the drift rate must wander (m/m per sqrt(m)) for the offset between the anchors to
    be as uncertain as the trajectories' sd says (``Pair.prior_var``): the smoother's variance with
    the anchors alone grows as the walk squared, so the walk is the square root of the median,
    over the pairs the trajectories do not anchor, of their variance over the smoother's at a
    walk of 1. 0 where nothing anchors the chain or every pair is anchored."""
    anchor_var = _anchor_variance(chain, options)
    free = ~np.isfinite(anchor_var)
    if free.all() or not free.any():
        return 0.0
    bare = [replace(p, rate_trusted=False) for p in chain]
    _, unit = _smooth(bare, np.full(len(chain), np.nan), options, np.ones(len(chain)), anchor_var)
    prior_var = np.array([p.prior_var for p in chain])
    return float(np.sqrt(np.median(prior_var[free] / np.maximum(unit[free], 1e-12))))


def _consensus_rates(chain: list[Pair], options: AlongTrackOptions) -> list[Pair]:
    """The chain with each pair's drift rate replaced by what its neighbours agree on.

    A pair measures its rate from the slope of its own curve of 3-6 windows; most come within
    3 mm/m of the truth, but a curve bent by one stray window is 10-16 mm/m off (simulated
    18-20 m/s surveys). :func:`_smooth` holds such a rate at ``rate_gate`` sd, but only once the chain
    before it knows its rate; this check looks both ways, so a stray near a chain's start is
    caught too. The rate changes
    slowly along the track, so within ``rate_radius`` it is a straight line of chainage: fitted
    to the neighbours' rates with Tukey's biweight (rates more than ``4.685 * rate_sd`` off
    the line get no weight), its value at the pair replaces the pair's own when the two differ
    by more than 3 sd: of the pair's own rate (``Pair.rate_var``) and of how far a line may miss a
    rate that wanders at the chain's pace (:func:`_rate_walks`), over ``rate_radius`` (a bridge's
    sd at its middle: ``walk * sqrt(radius / 2)``). Where fewer than 4 neighbours, or fewer than
    half of them, agree on a line, the pair keeps its own rate.

    (Replacing every rate cost a 0.75 m-sleeper tunnel its chain: near the portals the rate bends
    by 10 mm/m within 30 m, and the line through a few neighbours pulled good rates 3-5 mm/m off.
    Replacing those more than ``3 * rate_sd`` off cost held-out surveys theirs where the drift
    wandered: on 50 m tiles (commensurate 5103) two pairs' rates, 12.6 and 18.2 mm/m, each within
    1 mm/m of the truth, were replaced by 1.9 and 5.4, the prediction sat 0.3 m (6 sd) off for 90 m
    and its pairs stayed unresolved: 0.085 / 0.242 m inter-run. On commensurate_fast 5102 four
    good rates were replaced, two of them 19 mm/m off: 0.168 / 0.401 m.)
    """
    if options.rate_radius <= 0 or len(chain) < 4:
        return chain
    s = np.array([p.s for p in chain])
    rate = np.array([p.rate for p in chain])
    trusted = np.array([p.rate_trusted for p in chain])
    scale = 4.685 * options.rate_sd  # Tukey's biweight at 95 % efficiency
    # a straight line through rates that wander at the chain's pace misses the rate at the pair by
    # about a bridge's sd over the radius (the median in the wander keeps stray rates out of it)
    walks = _rate_walks(chain, options)
    bend_var = np.maximum(walks, np.append(walks[1:], walks[-1])) ** 2 * options.rate_radius / 2.0
    out = []
    for i, p in enumerate(chain):  # a few dozen pairs per run pair: small loops
        if not p.rate_trusted:  # neither corrected nor used to correct
            out.append(p)
            continue
        near = np.flatnonzero((np.abs(s - p.s) <= options.rate_radius) & trusted)
        x = np.column_stack([np.ones(len(near)), s[near] - p.s])
        coef = np.array([np.median(rate[near]), 0.0])  # start from the median: robust to a stray half
        for _ in range(10):  # iteratively reweighted least squares
            r = (rate[near] - x @ coef) / scale
            w = np.where(np.abs(r) < 1.0, (1.0 - r**2) ** 2, 0.0)
            if len(near) < 4 or (w > 0).sum() < max(3, 0.5 * len(near)):
                coef = None  # too few neighbours agree: the pair keeps its own rate
                break
            new = np.linalg.lstsq(x * w[:, None], rate[near] * w, rcond=None)[0]
            if np.allclose(new, coef, atol=1e-6):
                break
            coef = new
        # only a rate its neighbours clearly disagree with is replaced: beyond 3 sd of its own
        # measurement and of the line's miss where the rate bends
        stray = coef is not None and abs(p.rate - coef[0]) > 3.0 * np.sqrt((p.rate_var or options.rate_sd**2) + bend_var[i])
        out.append(replace(p, rate=float(coef[0]), end_rates=()) if stray else p)
    return out


def _contradicted(chain: list[Pair], fixed: np.ndarray, mu: np.ndarray, var: np.ndarray,
                  options: AlongTrackOptions) -> np.ndarray:
    """Per pair, whether it is unfixed, precise (``max_pair_sd``) and has no alias within
    ``anchor_gate`` sd of the prediction: neither a candidate its profile shows nor one a
    multiple of its period from its best. Its along-track offset is one of its aliases, so where
    none is near the prediction is wrong, and near a portal that means the anchor: GNSS that
    claims the runs agree to centimetres while multipath biases one of them by decimetres. A bias
    across the track the sd check sees before the chains and widens; one along the track only the
    chain can see. On a held-out survey a run's GNSS sat 0.35 m off along the track at a portal:
    the chain, fixed to 7 mm from the tunnel's interior, was held there by its anchors, left the
    portal's three pairs unfixed (each pair's own candidate right to 1-2 cm, the nearest 4-8 sd
    from the prediction), and the adjustment kept the run on its bias claiming 1.4 cm (31 sd)."""
    out = np.zeros(len(chain), bool)
    for i, p in enumerate(chain):  # a few hundred pairs per run pair at most
        if np.isfinite(fixed[i]) or p.sd > options.max_pair_sd or p.lone_mark:
            continue
        best = p.u[np.argmin(np.abs(p.u - mu[i]))]
        period = p.period or options.min_period
        # the nearest alias is best itself or a multiple of the period from it
        out[i] = _off_multiple(mu[i] - best, period) ** 2 > options.anchor_gate**2 * (var[i] + p.sd**2)
    return out


def _anchor_variance(chain: list[Pair], options: AlongTrackOptions) -> np.ndarray:
    """Per pair, the variance with which the trajectories anchor its along-track offset at 0
    (``inf`` where they do not). The trajectories anchor the offset only where they are sure of
    it (GNSS: the portals, their sd at most ``anchor_sd``). Deeper in, their error is one drift
    seen at every pair, which no inflation counts once: in a 200 m tube whose offset rose to
    0.64 m (prior sd 0.23-0.44 m) it held the prediction 0.2 m, 2.4 sd, towards zero, and three
    pairs went unfixed. And the smoother's error is one error over ``prior_correlation``
    metres: where the pairs are closer than that, it counts once there."""
    s = np.array([p.s for p in chain])
    gaps = np.abs(np.diff(s))
    gap = np.minimum(np.append(gaps, np.inf), np.append(np.inf, gaps))
    inflate = np.where(np.isfinite(gap), np.maximum(1.0, options.prior_correlation / np.maximum(gap, 1.0)), 1.0)
    prior_var = np.array([p.prior_var for p in chain])
    return np.where(prior_var <= options.anchor_sd**2, prior_var * inflate, np.inf)


def _nodes(chain: list[Pair], fixed: np.ndarray, options: AlongTrackOptions) -> list[tuple[float, int, float, float, int]]:
    """Where :func:`_smooth` observes the chain, in order along run b's track: ``(s, pair, rate,
    rate variance, step)`` with ``pair`` the pair whose offset is observed there (-1 at the ends of
    its windows, where only their rates are: :attr:`Pair.end_rates`), ``rate`` NaN where none is
    measured (a pair whose rate is not trusted counts once its alias is fixed), and ``step`` the
    chain step whose wander applies on the way there (that of the pair it belongs to)."""
    nodes = []
    for i, p in enumerate(chain):
        if p.rate_trusted and p.end_rates:
            nodes += [(s, -1, rate, var, i) for s, rate, var in p.end_rates] + [(p.s, i, np.nan, np.nan, i)]
        else:
            rate = p.rate if p.rate_trusted or np.isfinite(fixed[i]) else np.nan
            nodes.append((p.s, i, rate, p.rate_var or options.rate_sd**2, i))
    return sorted(nodes, key=lambda node: node[0])


def _smooth(chain: list[Pair], fixed: np.ndarray, options: AlongTrackOptions,
            walks: np.ndarray, anchor_var: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and variance of the along-track offset at every pair (Rauch-Tung-Striebel smoother).

    The state is the offset and its rate (per metre of run b's travel); the rate wanders as a
    random walk of density ``walks`` per step (:func:`_rate_walks`: the drift's bend as white noise, as in the
    adjustment's smoothness), so the offset between two pairs follows the rate the pairs
    around them agree on, not just the mean of two. Observed (:func:`_nodes`): each pair's
    measured rate (``rate_sd``), at the ends of its windows where its curve is a parabola
    (:func:`_end_rates`), the offset as 0 +- the trajectories' sd where that is at most
    ``anchor_sd``, and its fixed candidate at fixed pairs.

    A rate more than ``rate_gate`` sd off what the chain expects is one stray window bending a
    pair's curve (16 mm/m against its neighbours' 1-5 mm/m, on a pair whose own fit was 24 cm
    off): its variance is raised until it sits at ``rate_gate`` sd, so it cannot drag the
    prediction onto its own candidate. (At 3 sd, a drift whose rate climbed from -4 to +23 mm/m
    within 60 m, all its pairs agreeing, was held back and its chain lost.)
    """
    nodes = _nodes(chain, fixed, options)
    n = len(nodes)
    xf, pf = np.zeros((n, 2)), np.zeros((n, 2, 2))  # filtered
    xp, pp = np.zeros((n, 2)), np.zeros((n, 2, 2))  # predicted
    q = np.asarray(walks, float) ** 2
    for k, (s, i, rate, rate_var, step) in enumerate(nodes):  # a few hundred per run pair at most
        if k == 0:
            xp[k], pp[k] = np.zeros(2), np.diag([1e6, 1.0])
        else:
            ds = s - nodes[k - 1][0]
            F = np.array([[1.0, ds], [0.0, 1.0]])
            xp[k] = F @ xf[k - 1]
            pp[k] = F @ pf[k - 1] @ F.T + q[step] * np.array([[ds**3 / 3, ds**2 / 2], [ds**2 / 2, ds]])
        x, P = xp[k].copy(), pp[k].copy()
        observed = [(1, rate, rate_var)]
        if i >= 0:
            observed += [(0, 0.0 if np.isfinite(anchor_var[i]) else np.nan, anchor_var[i]), (0, fixed[i], chain[i].sd**2)]
        for row, z, r in observed:
            if not np.isfinite(z):
                continue
            innovation_var = P[row, row] + r
            if row == 1:  # a stray rate is held at rate_gate sd
                innovation_var = max(innovation_var, (z - x[row]) ** 2 / options.rate_gate**2)
            gain = P[:, row] / innovation_var
            x, P = x + gain * (z - x[row]), P - np.outer(gain, P[row])
        xf[k], pf[k] = x, P
    xs, ps = xf.copy(), pf.copy()
    for k in range(n - 2, -1, -1):
        F = np.array([[1.0, nodes[k + 1][0] - nodes[k][0]], [0.0, 1.0]])
        g = pf[k] @ F.T @ np.linalg.inv(pp[k + 1])
        xs[k] = xf[k] + g @ (xs[k + 1] - xp[k + 1])
        ps[k] = pf[k] + g @ (ps[k + 1] - pp[k + 1]) @ g.T
    at_pairs = [k for k, node in enumerate(nodes) if node[1] >= 0]  # one node per pair, in chain order
    return xs[at_pairs, 0], ps[at_pairs, 0, 0]


def _placement_variance(o: TileOffset, shift: float, pair: Pair, options: AlongTrackOptions,
                        periods: np.ndarray) -> float:
    """Variance (m^2) to add along the track to a fixed pair's own fit, for what places it less
    well than that fit claims.

    * **Another alias.** The matcher's windows place its own choice to millimetres; another alias
      is placed by the fitness profile, sampled every ``step`` (5 cm, more on sparse scans) and
      often flat-topped there, so its peak is known to within its top's width (a step at least,
      :func:`_peak_top_width`): ``width^2 / 12``. On a 15 cm-gap scan a pair moved 3.06 m sat
      6.6 cm off while its fit claimed 5 mm; on a ring-jointed tube one moved onto a top 25 cm
      wide sat 9 cm off claiming 2.6 cm.
    * **Off every period.** Aliases lie a whole number of periods apart, so another alias
      sits a multiple of a period the structure there shows (``periods``: the pair's own and
      its neighbours', :func:`_periods_near`) from the matcher's choice. A peak that does not
      is placed no better than its distance from the nearest such multiple: in a held-out
      ring-jointed tube (1.3 times the speed, rings 1.25 m) a degenerate pair was moved 1.11 m,
      to an edge peak 14 cm short of the ring's multiple, and sat 12.9 cm off claiming 2.6 cm
      (now 14 cm: the runs' inter-run error there went from 0.037 / 0.141 to 0.018 / 0.065 m).
      Of 420 moved pairs on 36 simulated surveys, 340 lie within 2 cm of a multiple (1.0 cm
      RMS off the truth), 24 within 2-5 cm (2.1 cm RMS, 4.1 at most). The trains among the
      pair's own peaks (``Pair.trains``) count too: ribs and sleepers interleave, and its
      neighbours may show the sleepers' period only (held-out mixed 4602, :func:`_trains`).
    * **The profile gap.** Each run sees an edge only where a profile steps onto it, so it places
      the edge somewhere within one gap (speed over profile rate). Where ribs and sleepers repeat
      in step with the profiles (1.5 m is 30 gaps of 5 cm), every edge of a tile is sampled at
      the same phase and no number of windows averages that away: the whole pair is off
      together while its windows agree to millimetres, and its fit claims 7 mm. On 54 simulated
      surveys the ``ok`` pairs' along-track error was 0.5-0.6 cm RMS at 4-6.5 cm gaps, but
      1.1-2.1 cm at 6.5-11 cm gaps (one pair 4.0 cm off, 5.7 sd); 90 % of errors were within
      0.19 gap, 99 % within 0.3-0.4. So ``sampling_sd`` times the gap is added: 0.75 cm at
      5 cm, and past a gap of about 8.5 cm a pair is ``coarse``, not ``ok``.
    * **A degenerate fit** (too few windows for the drift's curvature, or too vague somewhere;
      :func:`_degenerate_fit`):
      the chain can fix its alias, but not its centimetres. Of 36 such pairs fixed on 12
      simulated surveys, 9 sat more than 2 cm off and one 5.3 cm off with a claimed 1.3 cm, so
      its sd is raised to ``max_pair_sd``, or to the spread of its windows (dropped ones
      included) about its curve when that is more: a pair whose windows spread 8.9 cm sat
      12 cm off (``mixed`` seed 2), 6 sd of ``max_pair_sd``. (Such pairs are ``coarse``.) The
      chain itself still fixes and predicts from the curve's own sd: using the spread there
      changed which pairs it fixed and doubled ``mixed`` seed 2's inter-run error.
    """
    sd, step = pair.sd, float(o.info.get("alias_profile", {}).get("step", 0.05))
    chosen = pair.shift == shift
    width = float(pair.width[chosen][0]) if pair.width is not None and chosen.any() else step
    extra = max(width, step) ** 2 / 12.0 if abs(shift) > 1e-9 else 0.0
    periods = np.concatenate([periods, pair.trains])
    if abs(shift) > 1e-9 and len(periods) and not pair.lone_mark:
        extra += float(np.min(_off_multiple(shift, periods))) ** 2
    extra += (options.sampling_sd * _profile_gap(o)) ** 2
    if _degenerate_fit(o):
        spread = float(o.info["piecewise"].get("window_spread_m", 0.0))
        extra += max(max(options.max_pair_sd, spread) ** 2 - sd**2, 0.0)
    if _on_few_marks(o):  # at least MARKS_PAIR_SD: such a window is now and then 6-13 cm off
        extra = max(extra, MARKS_PAIR_SD**2 - sd**2)
    return extra


def _off_multiple(x: float, period: float | np.ndarray) -> float | np.ndarray:
    """How far ``x`` (m) lies from the nearest whole multiple of ``period`` (m): where an alias a
    period apart would be."""
    return np.abs(x - period * np.round(x / period))


def _periods_near(chain: list[Pair], options: AlongTrackOptions) -> list[np.ndarray]:
    """Per pair, the alias periods (m) the structure shows around it: those its own profile and
    the profiles of the pairs within ``rate_radius`` spaced evenly (``Pair.period`` above
    ``min_period``; a lone mark's is the reach of its window, no period)."""
    s = np.array([p.s for p in chain])
    period = np.array([0.0 if p.lone_mark or not p.period else p.period for p in chain])
    shown = period > options.min_period
    return [period[shown & (np.abs(s - p.s) <= options.rate_radius)] for p in chain]


def _profile_gap(o: TileOffset) -> float:
    """The pair's profile gap (m) as the matcher measured it (the larger of its two tiles'); 0 where
    it could not tell (a slow, dense run: the gap is then centimetres at most)."""
    gap = float(o.info.get("profile_spacing", 0.0) or 0.0)
    return gap if np.isfinite(gap) else 0.0


def _degenerate_fit(o: TileOffset) -> bool:
    """Whether the pair's curve is degenerate (too few windows, or too vague somewhere), also
    when the matcher reported it ``ambiguous``, which it checks first. Such a pair fixed by the
    chain became ``ok``: in session 10's trial of a wider reference, 3 of 5 windows agreeing to
    1 cm, 10 cm from the other two (a featureless section), gave an ``ok`` pair 6.2 cm off."""
    return o.status == "degenerate" or bool(o.info.get("degenerate_fit", False))


def _unchecked_fit(o: TileOffset) -> bool:
    """Whether the pair's curve is degenerate and rests on 1-2 windows: a constant or a line
    through them fits them exactly, so nothing measures how far its along-track value may be
    off, and its sd (``max_pair_sd`` at least, :func:`_placement_variance`) is a guess. With
    2 cm range noise one such pair, fixed on its own fit, sat 11.8 cm off claiming 2.0 cm.
    The chain does not fix it: it is observed where the chain predicts, across and up only.

    Windows placed by marks alone (intensity, short objects) are another matter: the pair's
    offset is given at them (its reference point lies between them), and its alias profile, the
    marks' own, spans the whole search window."""
    windows = o.info["piecewise"].get("windows")
    if windows is None or not _degenerate_fit(o) or _along_windows(windows) > 2:
        return False
    return not _on_few_marks(o)


def _on_few_marks(o: TileOffset) -> bool:
    """Whether the pair's along-track offset rests on one or two windows, all placed by
    marks (intensity, short objects): nothing checks them against each other."""
    windows = o.info.get("piecewise", {}).get("windows") or []
    along = [w for w in windows if len(w) >= 6 and w[5] > 0]
    return 0 < len(along) <= 2 and all(w[5] == 2 for w in along)


def _unresolved_use(o: TileOffset) -> TileOffset:
    """How a pair the chain did not fix enters the adjustment: across and up only, as its
    ``ambiguous``/``degenerate`` status says, if its curve of offsets rests on two windows or more.

    * On a single window nothing checks that window, and its sd is a floor: of 26 such
      unresolved pairs on 48 simulated surveys, 4 were 3.2-8.7 cm off across or up while
      claiming 1 cm (up to 8.7 sd); with two windows or more, 4 of 536 were beyond 3 sd (5.5 at
      most). Such a pair keeps its status and is left unused (its covariance ``nan``).
    * A pair with too few votes (``few_votes``: the matcher checked it densely all the same) is
      the same: on two windows or more, 222 such pairs were 0.3 cm off across and up (median),
      2.8 cm at most, one beyond 3 sd, and in bored tubes, where most pairs have few votes,
      leaving them out left the runs up to 14 cm apart in height. On fewer (or none on record)
      it is ``no_consensus``, as before it was checked: fitted from a peak of 2-4 votes, such
      pairs in open cuttings sat up to 2.3 m off across and up (one pulled two runs 8.5 cm
      apart, 4 sd).

    ``ok`` and ``coarse`` pairs, fixed by the chain, are returned as they are."""
    if o.status in ("ok", COARSE):
        return o
    windows = _windows(o)
    if "few_votes" in o.info:
        if windows >= 2:
            return replace(o, info=dict(o.info, demoted="too few votes, and the along-track chain could not fix "
                                                       "its alias: across and up only"))
        info = dict(o.info, demoted="too few votes on a single window, and the along-track chain could not fix its "
                                    "alias")
        return replace(o, status="no_consensus", cov=np.full((3, 3), np.nan), ties=Ties.empty(o.run_a, o.run_b),
                       info=info)
    if o.status in ("ambiguous", "degenerate") and windows == 1:
        info = dict(o.info, unused="its curve rests on a single window: across and up unchecked")
        return replace(o, cov=np.full((3, 3), np.nan), info=info)
    return o


def _windows(o: TileOffset) -> int:
    """How many windows the pair's curve of offsets has, across and up (-1 if it has none on record)."""
    windows = o.info.get("piecewise", {}).get("windows")
    return -1 if windows is None else len(windows)


def _along_windows(windows: list) -> int:
    """How many of a curve's windows found an along-track offset (their profile had a valley:
    the sixth column, :class:`railtraj.matching.piecewise.Piecewise`)."""
    return sum(1 for w in windows if len(w) < 6 or w[5] > 0)


def _within_reach(o: TileOffset, options: AlongTrackOptions) -> TileOffset:
    """An ``ok`` pair with only the ties its curve places to ``max_ok_sd``.

    Ties carry the pair's curve of offsets to each keypoint: its offset at the reference point
    plus its gradient times the distance. The gradient comes from 3-6 windows that can share a
    bias (on a curve through a station, five windows of one pair drifted 6 mm/m off the truth
    while scattering 1 cm about their line), so a tie ``x`` metres away is known to
    ``sqrt(sd^2 + (rate_sd x)^2)`` only; at the tile's end that pair's tie was 8.3 cm off. Ties
    beyond ``max_ok_sd`` are dropped (the nearest one always stays), the others share the
    pair's weight of one.
    """
    pw = o.info.get("piecewise", {})
    if not (o.ok and o.ties is not None and len(o.ties) and "ref_point" in pw and "fit_cov" in pw):
        return o
    axis = np.asarray(pw["axis"], float)
    reach = (o.ties.xyz_b - np.asarray(pw["ref_point"], float)) @ axis
    var = float(axis @ np.asarray(pw["fit_cov"], float) @ axis) + (options.rate_sd * reach) ** 2
    keep = (var <= options.max_ok_sd**2) | (np.abs(reach) == np.abs(reach).min())
    if keep.all():
        return o
    t = o.ties
    ties = Ties(t.run_a, t.run_b, t.time_a[keep], t.time_b[keep], t.xyz_a[keep], t.xyz_b[keep],
                np.full(int(keep.sum()), 1.0 / keep.sum()))
    return replace(o, ties=ties, info=dict(o.info, ties_beyond_reach=int((~keep).sum())))


def _apply(o: TileOffset, shift: float, resolved: bool, trajectories: dict[str, Trajectory],
           coarse: bool = False, alias_var: float = 0.0) -> TileOffset:
    """The pair after resolution: on its chosen alias and ``ok`` (:data:`COARSE` if ``coarse``),
    or ``ambiguous``; ``alias_var`` widens it along the track (:func:`_placement_variance`).

    A pair moved by ``shift`` is observed at run a's time ``shift`` further along: where run a
    saw run b's structure. The shift is the spacing of run a's own structure (its alias
    profile moves run b's points over run a's), which run a's drift stretches and turns, so the
    moved offset is the true one there. Keeping the matcher's time instead (exact only for a
    shift of the true period along the true track) left 3.3 cm along and 4.2 cm across on
    portal_trap 304 (inter-run max 3.7 -> 6.6 cm); across and up kept there and along moved,
    7.0 cm.
    """
    pw = o.info["piecewise"]
    axis, fit_cov = np.asarray(pw["axis"], float), np.asarray(pw["fit_cov"], float)
    info = dict(o.info, alongtrack={"shift_m": shift, "resolved": resolved})
    if not resolved:
        if o.status == "ok":
            info["demoted"] = "along-track alias not resolved jointly"
        window = float(o.info.get("window", 3.0))
        return replace(o, status="ambiguous" if o.status == "ok" else o.status,
                       cov=_across_floor(o, fit_cov + window**2 * np.outer(axis, axis)),
                       ties=Ties.empty(o.run_a, o.run_b), info=info)
    if abs(shift) < 1e-9 and o.status == "ok" and not coarse:  # its ties as they are, its sd widened
        return replace(o, cov=_across_floor(o, o.cov + alias_var * np.outer(axis, axis)), info=info)
    d = o.d + shift * axis
    info["resolved"] = "joint" if o.status != "ok" else "moved"
    info["time_a"] = _time_after_shift(trajectories[o.run_a], o.info["time_a"], shift * axis)
    if shift and o.info.get("weak_windows"):  # its windows move with it (the adjustment may read them)
        info["weak_windows"] = _shifted_windows(o.info["weak_windows"], trajectories[o.run_a], shift * axis)
    return replace(o, d=d, cov=_across_floor(o, fit_cov + alias_var * np.outer(axis, axis)),
                   status=COARSE if coarse else "ok",
                   ties=Ties.empty(o.run_a, o.run_b), info=info)


def _shifted_windows(windows: dict, traj_a: Trajectory, move: np.ndarray) -> dict:
    """A pair's windows (``weak_windows``) on the alias ``move`` away, as :func:`_apply` moves
    the pair: each window's offset by ``move``, run a's time to where it passed the point ``move``
    further along."""
    return dict(windows, d=(np.asarray(windows["d"], float) + move).tolist(),
                time_a=[_time_after_shift(traj_a, t, move) for t in windows["time_a"]])


def _across_floor(o: TileOffset, cov: np.ndarray) -> np.ndarray:
    """``cov`` with its across and up sd raised to :data:`PAIR_ACROSS_SD`, and to
    :data:`MARKS_ACROSS_SD` where the pair's along-track offset rests on marks alone
    (:func:`_on_few_marks`): its curve's across and up come from windows fitted across a
    featureless wall, which claim millimetres but do not check each other along the track. On a
    sparse scan, to :data:`SAMPLING_ACROSS_SD` times the spacing of its points along a profile."""
    floor = max(MARKS_ACROSS_SD if _on_few_marks(o) else PAIR_ACROSS_SD,
                SAMPLING_ACROSS_SD * float(np.nan_to_num(o.info.get("point_spacing", 0.0))))
    axis = np.asarray(o.info["piecewise"]["axis"], float)
    up = np.array([0.0, 0.0, 1.0])
    across = np.cross(up, axis)
    for n in (across / np.linalg.norm(across), up):
        cov = cov + max(floor**2 - float(n @ cov @ n), 0.0) * np.outer(n, n)
    return cov


def _at_prior(o: TileOffset, trajectories: dict[str, Trajectory]) -> TileOffset:
    """A pair without along-track evidence (and so outside any chain) observed where the input
    trajectories put run a against run b (no along-track offset), with their sd: as
    :func:`_at_predicted`, for want of a prediction."""
    direction, prior_var = _along_frame(o, trajectories)
    axis = np.asarray(o.info["piecewise"]["axis"], float)
    return _at_predicted(o, float(o.d @ direction), float(axis @ direction), 0.0, prior_var, trajectories)


def _at_predicted(o: TileOffset, u0: float, along: float, mu: float, var: float,
                  trajectories: dict[str, Trajectory], on_candidate: bool = True) -> TileOffset:
    """An unresolved pair observed where the chain predicts, not on the matcher's alias.

    A weak pair still constrains across and up, at ``time_a``/``time_b``. The matcher took run a's
    time at the place its (possibly wrong) alias points to: 3 m off on a 3 m alias, where the
    runs' offset has moved by 3 m times its gradient (18 mm/m: 5 cm), and the adjustment, whose
    common mode of the runs is only loosely held without control, absorbed that as a shift of
    every run (commensurate_fast: 20 cm). So ``time_a`` is moved to the along-track offset
    ``mu``: the pair's candidate nearest the chain's prediction when it lies within 2 sd of it
    (a prediction across an unresolved section can be 0.3 m off where the matcher was right),
    else the prediction itself. What the prediction's variance ``var`` leaves unknown of where
    the offset applies widens its covariance along the pair's gradient. ``on_candidate`` False:
    ``mu`` is the prediction, no candidate of the pair's (:func:`rematch_centres` reads it).
    """
    if not np.isfinite(mu) or not np.isfinite(var) or abs(along) < 0.5:
        return o
    shift = (mu - u0) / along
    pw = o.info["piecewise"]
    axis, gradient = np.asarray(pw["axis"], float), np.asarray(pw["gradient"], float)
    info = dict(o.info, time_a=_time_after_shift(trajectories[o.run_a], o.info["time_a"], shift * axis),
                observed_at={"predicted_shift_m": round(float(shift), 3), "sd_m": round(float(np.sqrt(var)), 3),
                             "on_candidate": bool(on_candidate)})
    return replace(o, cov=o.cov + var / along**2 * np.outer(gradient, gradient), info=info)


def rematch_centres(offsets: list[TileOffset], options: AlongTrackOptions) -> dict[int, np.ndarray]:
    """Pairs to match again about the chains' prediction, each with that search centre (the
    offset ``d`` there): the unresolved pairs none of whose candidates lies within 2 sd of a
    prediction of sd ``rematch_sd`` at most (:func:`_at_predicted`), not matched again before
    (``info["rematched"]`` or ``info["rematch_tried"]``, :func:`railtraj.pipeline.run_pipeline`).

    The matcher searches about where the trajectories put the runs and keeps the alias its votes
    and dense check prefer; its alias profile is measured about the curve fitted there, so it
    favours that alias. On a held-out commensurate tunnel with a noisy scanner (15 mm range
    noise), 9 of 24 pairs sat on the 3.0 m alias (ribs 1.5 m, sleepers 0.6 m) as ``ok``, the truth
    3 m away fitting 23 % of the points where the alias fitted 99 %: the truth was no candidate,
    the chains predicted it to 4-12 cm and could only leave the pairs unresolved (50 % of the
    length resolved). Matched again about the prediction the pair is fitted there, its
    neighbouring aliases in its profile, and the chains choose among them as for any pair.
    """
    if options.rematch_sd <= 0:
        return {}
    out = {}
    for k, o in enumerate(offsets):
        at = o.info.get("observed_at")
        if at and not at.get("on_candidate", True) and at["sd_m"] <= options.rematch_sd and not (
                {"rematched", "rematch_tried"} & o.info.keys()):
            out[k] = np.asarray(o.d, float) + at["predicted_shift_m"] * np.asarray(o.info["piecewise"]["axis"], float)
    return out


def _velocity(traj: Trajectory, t: float) -> np.ndarray:
    """Horizontal velocity (m/s) at time ``t``, over the half second about it (less at the run's ends)."""
    move, seconds = travel_step(traj, t)
    v = move / seconds if seconds > 0 else np.zeros(3)
    v[2] = 0.0
    return v


def _direction(traj: Trajectory, t: float) -> np.ndarray:
    """Unit horizontal direction of travel at time ``t``."""
    v = _velocity(traj, t)
    n = np.linalg.norm(v)
    return v / n if n > 0 else np.array([1.0, 0.0, 0.0])


def metres_travelled(traj: Trajectory) -> np.ndarray:
    """Metres travelled (in plan) by the run at each epoch."""
    step = np.linalg.norm(np.diff(traj.xyz[:, :2], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(step)])


def _time_after_shift(traj: Trajectory, t: float, move: np.ndarray) -> float:
    """When the run passed the point ``move`` away (along the track) from where it was at ``t``."""
    v = _velocity(traj, t)
    speed2 = float(v @ v)
    return float(np.clip(t + (move[:2] @ v[:2]) / speed2, *traj.span)) if speed2 > 0 else t
