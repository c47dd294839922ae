"""The end every voting matcher shares: peaks -> dense check -> alias test -> refine -> ties.

``pair_voting`` (all keypoint pairs) and ``mutual_nn`` (descriptor matches) differ only in
which pairs vote; what they do with the votes is here, so both refuse the same way.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from railtraj.data import Keypoints, PointTile, Ties, TileOffset
from railtraj.matching.consensus import (
    Checked,
    alias_covariance,
    alias_rivals,
    check_peaks,
    choose,
    consensus,
    failed,
    make_ties,
    search_peaks,
)
from railtraj.matching.intensity import Surroundings
from railtraj.matching.piecewise import (
    Piecewise,
    alias_ratio,
    edge_peak,
    edge_profile,
    piecewise_fit,
    reference_times,
    reference_tree,
    reversed_fit,
    track_axis,
    track_frame,
    window_ties,
    windows_with_times,
)
from railtraj.matching.refine import directions, sample
from railtraj.matching.spacing import profile_gap_ratio
from railtraj.matching.target import PlaneTarget, cached_filled_target, cached_target, with_surface
from railtraj.matching.threads import in_background
from railtraj.matching.voting import Votes, find_peaks, slices

#: keypoint pairs agreeing with the curve needed to use them as ties (else one tie per window)
MIN_KEYPOINT_TIES = 3
#: m; a curve moved to its edge profile's peak may change its across and up by this much at most
MAX_EDGE_MOVE_ACROSS = 0.02
#: m; a curve whose along-track offset rests on marks placed this far along from where its
#: windows were fitted is fitted again there
MARKS_REFIT_M = 0.2
#: run b's scan profiles this many times further apart than run a's (:func:`profile_gap_ratio`):
#: the windows fit run a's points onto run b's (the matchers' default ``reverse_gap_ratio``). A
#: sparse run's points place the edges along the track only to within its profile gap, and its
#: windows erred together: on a commensurate tunnel driven at 5 and 20 m/s (profiles 2 and 8 cm
#: apart) the pairs' along-track errors scattered 2.4 cm RMS, `ok` pairs up to 4.7 cm off claiming
#: 1.4 cm; fitted the other way, 0.7 cm RMS, the worst `ok` 1.8 cm; a bored tube at 5 and 20 m/s
#: was resolved along 89 % of its length instead of 75 %. At 10 and 12 m/s the gain was small
#: (worst tie 2.5 -> 1.5 cm), and a tube at 8 and 16 m/s lost a fifth of its resolved length
#: (83 -> 66 %): the sparse run's planes smooth the thin ring joints the dense run's points would
#: be placed by (docs/method.md, "Session 61")
REVERSE_GAP_RATIO = 2.5
#: a pair's along-track fitness profile rising by less than this over the search window shows no
#: alias of its own: its windows are placed by marks where they hold some (_no_alias_of_its_own)
FLAT_PROFILE = 0.02

Refiner = Callable[[PointTile, Keypoints, PointTile, Keypoints, TileOffset], TileOffset]


@dataclass(frozen=True)
class VoteSettings:
    inlier_radius: float = 0.1  # m; a pair agrees with a translation this closely
    n_peaks: int = 5  # distinct vote peaks checked densely
    min_inliers: int = 5  # votes the best peak needs to be ok
    min_check_votes: int = 2  # fewer than min_inliers but this many: checked densely, at best ambiguous
    check_points: int = 20_000  # raw points of tile b for the dense check
    profile_points: int = 2_000  # of those, slid along the weak axis to find aliases
    fitness_radius: float = 0.05
    surface_reach: float = 0.0  # m; beyond fitness_radius: points fit where a plane is (PlaneTarget.fits)
    min_fitness: float = 0.5  # below: no common geometry (no_overlap)
    # m; where no vote peak fits, the clouds are searched this far about the trajectories' offset
    # (search_peaks; piecewise only; 0: off)
    search_m: float = 0.5
    ambiguity_ratio: float = 0.8  # misfit best/rival at or above this: ambiguous
    max_sd: float = 0.03  # m; see builtins.icp
    target_voxel: float = 0.05
    tie_positions: str = "offset"
    window_length: float = 5.0  # m; > 0: refine as a curve of offsets along the track (piecewise)
    min_windows: int = 4  # windows the curve needs for ok (fewer: no curvature, degenerate)
    intensity: bool = True  # windows without edges placed by intensity marks (matching.intensity)
    objects: bool = True  # ... and by short objects, boxes and cabinets (matching.objects)
    reverse_gap_ratio: float = REVERSE_GAP_RATIO  # run b's profile gap over run a's from which the windows fit a onto b (0: never)


def peak_table(checked) -> list[list[float]]:
    """[dx, dy, dz, votes, fitness] per checked peak, for the report."""
    return [[*c.peak.d.tolist(), float(c.peak.count), c.fit.fitness] for c in checked]


def resolve(tile_a: PointTile, kp_a: Keypoints, tile_b: PointTile, kp_b: Keypoints, votes: Votes,
            s: VoteSettings, refiner: Refiner | None, info: dict) -> TileOffset:
    """Turn ``votes`` into a TileOffset, refusing (status) rather than guessing."""
    t0 = time.perf_counter()
    peaks = find_peaks(votes, s.inlier_radius, s.n_peaks)
    info.update(pairs=len(votes), background_votes=votes.background(s.inlier_radius))
    info["timings"]["peaks"] = time.perf_counter() - t0
    piecewise = refiner is not None and s.window_length > 0
    # a sparse detector (20-70 keypoints a tile) leaves a fifth of the pairs below min_inliers,
    # though their dense clouds fit: those are checked too, but their alias rests on the dense
    # profile and the chain along the track, never on their votes (at best ambiguous)
    few_votes = bool(peaks) and s.min_check_votes <= peaks[0].count < s.min_inliers and piecewise
    voted = bool(peaks) and (peaks[0].count >= s.min_inliers or few_votes)
    searched = piecewise and s.search_m > 0
    if not voted and not searched:
        return _unchecked(tile_a, tile_b, peaks, info)
    if voted:
        info["peak_ratio"] = peaks[1].count / peaks[0].count if len(peaks) > 1 else 0.0
        info["vote_slices"] = slices(votes, peaks[0].d, s.inlier_radius)
    if few_votes:
        info["few_votes"] = int(peaks[0].count)

    t1 = time.perf_counter()
    # run a's KD-tree for the window profiles, built on another core while its plane target is
    tree = in_background(reference_tree, tile_a.xyz) if piecewise else None
    target = reference_target(tile_a.xyz, s)
    moving = sample(tile_b.xyz, s.check_points, seed=1)
    chosen, refusal = None, "no_consensus" if few_votes or not voted else "no_overlap"
    if voted:
        chosen = _dense_check(target, moving, [p for p in peaks if p.count >= (s.min_check_votes if few_votes else
                                                                                s.min_inliers)], votes, s, info)
    if (chosen is None or chosen.fit.overlap < s.min_fitness) and searched:
        # the votes found nothing that fits: the clouds themselves are searched about the
        # trajectories' offset, and what they find is at best ambiguous, as a few votes' peak
        found = search_peaks(target, moving, votes.center, half=s.search_m, step=s.fitness_radius, n=s.n_peaks,
                             radius=s.fitness_radius)
        searched_info: dict = {}  # (the votes' check stays on record should the search find nothing)
        checked = _dense_check(target, moving, found, votes, s, searched_info) if found else None
        if checked is not None and checked.fit.overlap >= s.min_fitness:
            chosen, few_votes = checked, True
            info.update(searched_info, few_votes=0, searched_m=s.search_m)
    info["timings"]["dense_check"] = time.perf_counter() - t1
    if chosen is None:  # no peak with votes enough, and the search found nothing that fits
        return _unchecked(tile_a, tile_b, peaks, info)
    if chosen.fit.overlap < s.min_fitness:  # (a handful of votes fitting nowhere is no consensus)
        ramped = _ramped(tile_a, kp_a, tile_b, kp_b, votes, chosen, s, info, tree()) if piecewise else None
        return ramped if ramped is not None else failed(tile_a, tile_b, refusal, info, chosen.fit.d,
                                                        inliers=chosen.peak.count)
    if piecewise:
        return _piecewise_estimate(tile_a, kp_a, tile_b, kp_b, votes, chosen, s, info, tree(), few_votes)
    if info["rival_misfit_ratio"] >= s.ambiguity_ratio:
        return failed(tile_a, tile_b, "ambiguous", info, chosen.fit.d, alias_covariance(chosen.fit, votes.window),
                      inliers=chosen.peak.count)

    if refiner is not None:
        start = TileOffset(tile_a.run_id, tile_b.run_id, tile_a.name, tile_b.name, d=chosen.fit.d, status="ok")
        out = refiner(tile_a, kp_a, tile_b, kp_b, start)
        info["timings"].update({f"icp_{k}": v for k, v in out.info.pop("timings", {}).items()})
        out.info.update(info)
        return out
    return _vote_estimate(tile_a, kp_a, tile_b, kp_b, votes, chosen, s, info)


def _ramped(tile_a, kp_a, tile_b, kp_b, votes: Votes, chosen: Checked, s: VoteSettings, info: dict,
            tree: cKDTree) -> TileOffset | None:
    """The windows of a pair no one translation fits, fitted from the best candidate: where its
    offset changes within the tile, they fit where the tile as a whole cannot. At best
    ``ambiguous`` (the candidate's alias is the chain's to check); None (the pair is refused)
    unless ``min_windows`` windows fit.

    A GNSS multipath bias ramps in over the last tens of metres before a portal: on a held-out
    survey whose cuttings were 30 m, run a's error grew from 1 to 31 cm across one 25 m tile,
    which fitted run b's by 0.39 at best (0.5 needed) though each 5 m of it fitted by 0.75-0.92.
    That pair, and the same one against run c, were ``no_overlap``; no pair saw the bias, and
    run a kept it claiming 1.3 cm (4 % of its epochs beyond 3 sd, worst 26 sd).

    Windows that fit make the candidate nearest one of them fit at least that window's share of
    the tile: below it the clouds do not overlap, and fitting windows is not tried (a
    twin-track pair of the control survey fitted by 0.07: 8 s of windows that did not fit)."""
    if chosen.fit.overlap < s.min_fitness * _window_share(tile_b, chosen.fit.information, s.window_length):
        return None
    trial = dict(info, rigid_overlap=chosen.fit.overlap)
    out = _piecewise_estimate(tile_a, kp_a, tile_b, kp_b, votes, chosen, s, trial, tree, few_votes=True)
    return out if len(out.info.get("piecewise", {}).get("windows", [])) >= s.min_windows else None


def _window_share(tile: PointTile, information: np.ndarray, window_length: float) -> float:
    """The share of ``tile`` along the track (its central 99 %) one window of ``window_length``
    covers; 1 where the track direction is unknown (``information`` not finite)."""
    if not np.isfinite(information).all():
        return 1.0
    s = tile.xyz @ track_axis(information, tile.travel)
    extent = float(np.subtract(*np.quantile(s, [0.995, 0.005])))
    return min(1.0, window_length / extent) if extent > 0 else 1.0


def _unchecked(tile_a: PointTile, tile_b: PointTile, peaks: list, info: dict) -> TileOffset:
    """``no_consensus``: no vote peak had votes enough to be checked on the dense clouds."""
    info["vote_peaks"] = [[*p.d.tolist(), float(p.count), np.nan] for p in peaks]
    return failed(tile_a, tile_b, "no_consensus", info, peaks[0].d if peaks else None,
                  inliers=peaks[0].count if peaks else 0)


def _dense_check(target: PlaneTarget, moving: np.ndarray, candidates: list, votes: Votes, s: VoteSettings,
                 info: dict) -> Checked:
    """The candidate translation that fits ``moving`` best after a quick fit, among ``candidates``
    and the two best aliases along its weak axis; its alias profile and the peaks' table go to
    ``info``."""
    checked = check_peaks(target, moving, candidates, fitness_radius=s.fitness_radius)
    best = choose(checked, s.inlier_radius)[0]
    rivals, info["alias_profile"] = alias_rivals(target, moving, checked[best], votes.center, votes.window,
                                                 s.fitness_radius, 2 * s.inlier_radius, s.profile_points)
    checked += rivals
    best, rival = choose(checked, s.inlier_radius)
    info.update(vote_peaks=peak_table(checked), chosen_peak=best, rival_misfit_ratio=rival,
                check_fitness=checked[best].fit.fitness)
    return checked[best]


def _no_alias_of_its_own(info: dict) -> bool:
    """Whether a pair whose windows found edges shows no along-track alias of its own: its
    fitness profile rises by less than :data:`FLAT_PROFILE` over the search window (a tube's
    ring joints seen 9-10 cm apart rose it by 0.003-0.005 in 25 m; a ribbed tunnel's by tenths).
    Its windows' edges then sit on the joint nearest where they started, and a box among them
    (a mark) says which one it is. Asked of ambiguous ribbed pairs too, marks placed a held-out
    commensurate survey's pairs to centimetres where their ribs placed them to millimetres
    (0.015 -> 0.024 m inter-run) and tripled its matching time."""
    fitness = np.asarray(info.get("alias_profile", {}).get("fitness", []), float)
    return len(fitness) > 0 and bool(np.isfinite(fitness).all()) and float(np.ptp(fitness)) < FLAT_PROFILE


def reference_target(xyz: np.ndarray, s: VoteSettings, filled: bool = False) -> PlaneTarget:
    """Run a's plane target (``filled``: :func:`railtraj.matching.target.filled_target`, for the
    windows' across-and-up fits); where ``s.surface_reach`` exceeds the fitness radius, one
    that fits points on the filled planes that far from a voxel centroid
    (:meth:`railtraj.matching.target.PlaneTarget.fits`)."""
    target = (cached_filled_target if filled else cached_target)(xyz, s.target_voxel)
    if s.surface_reach <= s.fitness_radius:
        return target
    return with_surface(target, cached_filled_target(xyz, s.target_voxel), s.surface_reach)


def _beyond(tile: PointTile, left_out: np.ndarray | None) -> np.ndarray:
    """What lies around the points of ``tile`` that are kept: those ``left_out`` (a mask, or
    None: none) and its context."""
    parts = [tile.xyz[left_out] if left_out is not None else np.zeros((0, 3))]
    return np.vstack(parts + ([] if tile.context is None else [tile.context]))


def _piecewise_estimate(tile_a, kp_a, tile_b, kp_b, votes: Votes, chosen, s: VoteSettings, info,
                        tree: cKDTree, few_votes: bool = False) -> TileOffset:
    """Refine as a curve of offsets along the track (:mod:`railtraj.matching.piecewise`), then
    judge it: ``ambiguous`` if an along-track alias of the curve fits nearly as well,
    ``degenerate`` if the offset's sd exceeds ``max_sd`` in any direction or fewer than
    ``min_windows`` windows carry it (a short overlap: with 2-3 windows the curvature of the
    drift is not seen, and errors reached 13 mm on the thesis tunnel), else ``ok`` with ties
    whose offsets follow the curve. A pair with fewer votes than ``min_inliers`` is never
    ``ok`` here: its alias is left to the chain along the track."""
    t0 = time.perf_counter()
    target, across_target = reference_target(tile_a.xyz, s), reference_target(tile_a.xyz, s, filled=True)

    a_around = _beyond(tile_a, None) if s.objects else None  # (the same for every start)

    reverse = s.reverse_gap_ratio > 0 and profile_gap_ratio(tile_b, tile_a) >= s.reverse_gap_ratio
    if reverse:
        info["windows_reversed"] = True
        target_b, across_b = reference_target(tile_b.xyz, s), reference_target(tile_b.xyz, s, filled=True)
        b_around = _beyond(tile_b, None) if s.objects else None

    def windows_onto(ref: PointTile, mov: PointTile, ref_target: PlaneTarget, ref_across: PlaneTarget,
                     ref_around: np.ndarray | None, ref_tree: cKDTree, start: np.ndarray, center: np.ndarray,
                     marks_first: bool) -> tuple[Piecewise | None, np.ndarray]:
        """:func:`piecewise_fit` of ``mov``'s points onto ``ref``'s from ``start`` (run b onto run
        a, or the other way round), and which of ``mov``'s points it used."""
        inside = ref_target.inside(mov.xyz + start, 0.3)
        intensity = None if not s.intensity or ref.intensity is None or mov.intensity is None else \
            (ref.intensity, mov.intensity[inside])
        around = Surroundings(ref_around, _beyond(mov, ~inside),
                              lambda xyz: ref_target.inside(xyz, 0.0)) if s.objects else None
        fit = piecewise_fit(ref_target, ref.xyz, mov.xyz[inside], start, s.window_length,
                            chosen.fit.information, ref_tree, intensity, s.objects, min_windows=s.min_windows,
                            tau=s.fitness_radius, vote_window=(center, votes.window), around=around,
                            across_target=ref_across, marks_first=marks_first, travel=tile_a.travel)
        return fit, inside

    def fit_from(start: np.ndarray, center: np.ndarray = votes.center, marks_first: bool = False):
        if reverse:
            return fit_reversed(start, center, marks_first)
        fit, inside = windows_onto(tile_a, tile_b, target, across_target, a_around, tree, start, center, marks_first)
        if fit is None:
            return None, inside, 0.0, 0.0, {}
        return fit, inside, *alias_ratio(target, tile_b.xyz[inside], fit, votes.center, votes.window,
                                         s.fitness_radius, 2 * s.inlier_radius, 2 * s.profile_points)

    def fit_reversed(start: np.ndarray, center: np.ndarray, marks_first: bool):
        """fit_from with run a's points fitted onto run b's (``reverse_gap_ratio``), turned back."""
        inside = target.inside(tile_b.xyz + start, 0.3)
        rev, inside_a = windows_onto(tile_b, tile_a, target_b, across_b, b_around, reference_tree(tile_b.xyz),
                                     -start, -center, marks_first)
        if rev is None or not inside.any():
            return None, inside, 0.0, 0.0, {}
        fit = reversed_fit(rev, tile_b.xyz[inside])
        if not rev.on_marks:
            return fit, inside, *alias_ratio(target, tile_b.xyz[inside], fit, votes.center, votes.window,
                                             s.fitness_radius, 2 * s.inlier_radius, 2 * s.profile_points)
        # placed by marks alone: judged by them (alias_ratio), on the clouds they were found on
        rival, shift, profile = alias_ratio(target_b, tile_a.xyz[inside_a], rev, -votes.center, votes.window,
                                            s.fitness_radius, 2 * s.inlier_radius, 2 * s.profile_points)
        return fit, inside, rival, -shift, profile

    start = chosen.fit.d
    fit, inside, rival, shift, profile = fit_from(start)
    if fit is None:  # no window fitted: across and up unchecked (a rigid fit's formal sd, 0-1 mm, on
        # a corner tile of an open cutting drew two runs 5-11 cm apart at portal_trap 1's start)
        info["unusable"] = "no window of the overlap could be fitted"
        return failed(tile_a, tile_b, "degenerate", info, chosen.fit.d, inliers=chosen.peak.count)
    info["alias_profile"] = profile
    if rival * s.ambiguity_ratio >= 1.0:  # an alias fits clearly better: the votes chose wrong
        moved = fit_from(fit.d_ref + shift * fit.axis)
        if moved[0] is not None:
            info["moved_to_alias"] = (moved[0].d_ref - fit.d_ref).tolist()
            start = fit.d_ref + shift * fit.axis
            fit, inside, rival, _, info["alias_profile"] = moved
    if fit.on_marks and abs((fit.d_ref - start) @ fit.axis) > MARKS_REFIT_M:
        # marks placed run b metres from where its windows were fitted: on a curve, and along an
        # axis a degree off, their across and up lean there; fitted again where the marks put it
        # (and the marks searched about it: the votes' window may end just beyond)
        moved = fit_from(fit.d_ref, center=fit.d_ref)
        if moved[0] is not None and moved[0].on_marks:
            info["moved_to_marks"] = (moved[0].d_ref - fit.d_ref).tolist()
            fit, inside, rival, _, info["alias_profile"] = moved
    moved_to_edges = False
    if not (fit.windows[:, 5] > 0).any():  # no window found an along-track offset
        moved = _to_edges(fit, fit_from, target, tree, tile_b.xyz[inside], votes, s.fitness_radius)
        if moved is not None:
            info["moved_to_edges"] = (moved[0].d_ref - fit.d_ref).tolist()
            fit, inside, rival, _, info["alias_profile"] = moved
            moved_to_edges = True
    if (s.intensity or s.objects) and (fit.windows[:, 5] == 1).any() and _no_alias_of_its_own(info):
        moved = fit_from(fit.d_ref, marks_first=True)
        if moved[0] is not None and (moved[0].windows[:, 5] == 2).any():
            info["marks_over_edges"] = int((moved[0].windows[:, 5] == 2).sum())
            fit, inside, rival, _, info["alias_profile"] = moved
    info["timings"]["windows"] = time.perf_counter() - t0
    info["time_a"], info["time_b"] = reference_times(fit, tile_a.xyz, tile_a.gps_time, tile_b.xyz[inside],
                                                     tile_b.gps_time[inside])
    sd = np.sqrt(np.maximum(np.linalg.eigvalsh(fit.cov), 0.0))
    info.update(rival_misfit_ratio=rival, piecewise=fit.summary(), weak_sd=float(sd[-1]), fitness=chosen.fit.fitness,
                information=directions(np.linalg.inv(fit.cov)))
    ia, ib = consensus(votes, fit.at(kp_b.xyz[votes.ib]), s.inlier_radius)
    keep = fit.covers(kp_b.xyz[ib])  # ties only where the curve interpolates its windows
    ia, ib = ia[keep], ib[keep]
    degenerate = not (sd[-1] <= s.max_sd and fit.n_used >= s.min_windows)
    info["degenerate_fit"] = degenerate  # also when ambiguous: should the chain fix it, it is coarse
    # a curve moved to its edges' peak sits on one alias of many: the chain along the track chooses
    ambiguous = rival >= s.ambiguity_ratio or ((few_votes or moved_to_edges) and not degenerate)
    if (ambiguous or degenerate) and len(fit.windows) and (fit.windows[:, 5] == 1).any():
        # left to the chain along the track: it needs the aliases edges too thin for the
        # fitness profile repeat on (ring joints)
        info["edge_profile"] = edge_profile(target, tree, tile_b.xyz[inside], fit, votes.center, votes.window,
                                            s.fitness_radius)
    if ambiguous or degenerate:  # across and up still hold, window by window (a bias ramping in)
        info["weak_windows"] = windows_with_times(fit, tile_a.xyz, tile_a.gps_time, tile_b.xyz[inside],
                                                  tile_b.gps_time[inside])
    if ambiguous:
        cov = fit.cov + votes.window**2 * np.outer(fit.axis, fit.axis)
        return failed(tile_a, tile_b, "ambiguous", info, fit.d_ref, cov, inliers=len(ia))
    if degenerate:
        return failed(tile_a, tile_b, "degenerate", info, fit.d_ref, fit.cov, inliers=len(ia))
    if len(ia) >= MIN_KEYPOINT_TIES:
        ties = make_ties(tile_a, tile_b, kp_a, kp_b, ia, ib, fit.at(kp_b.xyz[ib]), s.tie_positions)
    else:  # too few keypoints agree with the curve: tie the windows themselves
        t_a, t_b, xyz_a, xyz_b = window_ties(fit, tile_a.xyz, tile_a.gps_time, tile_b.xyz[inside],
                                             tile_b.gps_time[inside])
        ties = Ties(tile_a.run_id, tile_b.run_id, t_a, t_b, xyz_a, xyz_b, np.full(len(t_a), 1.0 / max(len(t_a), 1)))
    return TileOffset(tile_a.run_id, tile_b.run_id, tile_a.name, tile_b.name, d=fit.d_ref, cov=fit.cov,
                      inliers=len(ia), status="ok", ties=ties, info=info)


def _to_edges(fit: Piecewise, fit_from: Callable, target, tree: cKDTree, moving: np.ndarray, votes: Votes,
              tau: float) -> tuple | None:
    """``fit_from``'s refit from the highest significant peak of ``fit``'s edge profile, for a
    curve none of whose windows found an along-track offset: a fast train's votes in a
    ring-jointed tube fall between the joints, whose 2.5 cm steps only the edge profile sees
    there. None unless the refit's windows find valleys, and its across and up stay within
    :data:`MAX_EDGE_MOVE_ACROSS` of ``fit``'s: the move is along the track only (on 24 moves
    in tubes they changed by at most 0.6 cm; two refits across two tracks in a ``mixed``
    tunnel, 4-5 cm up, found other surfaces and were 12 cm off)."""
    peak = edge_peak(edge_profile(target, tree, moving, fit, votes.center, votes.window, tau, across=True))
    moved = None if peak is None else fit_from(fit.d_ref + peak * fit.axis)
    if moved is None or moved[0] is None or not (moved[0].windows[:, 5] == 1).any():
        return None
    new = moved[0]
    change = track_frame(new.axis) @ (new.d_ref - fit.at((new.origin + new.s_ref * new.axis)[None])[0])
    return moved if np.abs(change[1:]).max() <= MAX_EDGE_MOVE_ACROSS else None


def _vote_estimate(tile_a, kp_a, tile_b, kp_b, votes, chosen, s: VoteSettings, info) -> TileOffset:
    """Without refinement: the vote peak (1-4 cm off in the prototype), its scatter as covariance."""
    d = chosen.peak.d
    ia, ib = consensus(votes, d, s.inlier_radius)
    spread = votes.d[votes.near(d, s.inlier_radius)]
    cov = np.cov(spread.T) / len(spread) if len(spread) > 3 else np.eye(3) * s.inlier_radius**2
    dirs = directions(chosen.fit.information)
    weak_sd = float(np.sqrt(np.linalg.eigvalsh(chosen.fit.cov)[-1]))
    info.update(information=dirs, weak_sd=weak_sd, fitness=chosen.fit.fitness)
    if not weak_sd <= s.max_sd:
        return failed(tile_a, tile_b, "degenerate", info, d, cov, inliers=len(ia))
    ties = make_ties(tile_a, tile_b, kp_a, kp_b, ia, ib, d, s.tie_positions)
    return TileOffset(tile_a.run_id, tile_b.run_id, tile_a.name, tile_b.name, d=d, cov=cov,
                      inliers=len(ia), status="ok", ties=ties, info=info)
