"""Checks each run's reported sd against what the other runs show, and widens it where it lies.

The adjustment weighs the runs by their reported sd. Where GNSS is good an SBET claims 1-3 cm,
and near a portal multipath can bias it by decimetres while it still claims 2 cm (the thesis'
failure near a portal). Taken at its word, such a run pulls the runs that agree with each other
towards its bias, or keeps its own bias while the ties that show it are rejected as outliers,
and the result claims 2 cm either way.

The runs' ties measure ``error_a - error_b`` directly. Under the reported sd that difference has
covariance ``S_a + S_b + C_obs``; a tie or tile offset beyond ``max_z`` standard deviations says
one of the two sds is wrong, when another tile pair nearby says so too (one aliased pair convicts
nobody; a weak pair, across and up only, may be that other pair, never the only one). The run to
blame is the one at odds with most of the runs it meets near there: with
three or more runs the run whose GNSS is biased disagrees with all others while the others agree;
with two runs both are blamed. A blamed run's covariance is widened by the disagreement it shows,
in the track frame (along, across, up), over ``reach_m`` metres around it, so the adjustment
follows the runs that agree and the corrected run's posterior sd says how little its own GNSS
was worth there.

A disagreement far beyond both runs' reported sd that only weak pairs show convicts nobody (a
wrong weak pair in an open cutting would free a good run to follow it): the adjustment leaves
those pairs out and keeps the runs where their GNSS puts them, and the corrected sd of the run at
odds with the others there (with two runs, of both) covers the disagreement.

A vote of runs is no proof: runs through one portal minutes apart may share a multipath bias,
and then the run the others outvote is the right one. Nothing relative can tell, so where a vote
settled a disagreement every run's corrected sd keeps a share of it (``vote_share``), unless
control nearby settles it instead; the correction itself follows the majority.

The pipeline checks twice. Before the along-track chains, on the matcher's pairs, across the track
and up only (``along=False``: a pair may sit on an alias along it), so that the chains are not
anchored on a run's biased portal; a bias seen across is taken to be as large along. After the
chains, in every direction on the pairs they kept, with the first check's finding kept where this
one finds nothing (``earlier``).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field, fields, replace

import numpy as np

from railtraj.adjust.offsets import WEAK_STATUSES, by_window, offset_covariance, usable_offset
from railtraj.adjust.stiffness import stretches
from railtraj.data import TileOffset, Trajectory, reports_gnss
from railtraj.geo import track_frames

log = logging.getLogger(__name__)

#: variance (m^2) given to a direction an observation is not compared in
UNSEEN_VAR = 1e4


@dataclass
class SdCheckOptions:
    enabled: bool = True
    max_z: float = 5.0         # disagreement (in sd of the reported sds and the observation) that convicts
    # ... where both runs report GNSS-quality sd (horizontal <= gnss_sd_m): there the sd is a GNSS
    # solution's, not an INS drift model's (which may understate a tunnel's drift twofold), and a
    # multipath bias shows as a smaller multiple of it
    max_z_gnss: float = 3.5
    gnss_sd_m: float = 0.10
    reach_m: float = 25.0      # metres of the blamed run around a disagreement whose sd is raised
    fade_m: float = 25.0       # ... beyond which its corrected sd still fades out over this many metres
    tie_sd_m: float = 0.01     # sd of one tie, per axis (as the spline optimizer's tie_sigma_m)
    max_weak_sd_m: float = 0.3  # directions of an offset with larger sd are not compared (as the optimizer's)
    # False: across and up only, for tile pairs that may sit on an along-track alias (the matcher's,
    # before the chains); a bias seen across is then taken to be as large along the track
    along: bool = True
    # a sure pair this many times beyond the limit across the track and up convicts with no other pair
    lone_z: float = 2.0
    # where runs that agree outvoted a run, the share of its disagreement that every run's corrected
    # sd keeps there: the vote is no evidence against a bias the majority shares (see _vote_margin)
    vote_share: float = 0.5


@dataclass(frozen=True)
class _Observations:
    """Inter-run differences pooled from ties and tie-less tile offsets, one row each."""

    run_a: np.ndarray
    run_b: np.ndarray
    time_a: np.ndarray
    time_b: np.ndarray
    where: np.ndarray  # (n, 2) world position, to find observations near each other
    d: np.ndarray      # (n, 3) error_a - error_b
    cov: np.ndarray    # (n, 3, 3) of the observation itself
    pair: np.ndarray   # (n,) index of the tile pair it comes from
    weak: np.ndarray   # (n,) from a degenerate/ambiguous pair: across and up only, never convicts alone


@dataclass
class SdCheck:
    """What the check found. ``widening``: per blamed run, the covariance (n_epochs, 3, 3) to add to
    its reported sd at each epoch (zero outside the convicted spans), large in the directions the
    runs disagree in only; ``trajectories``: every run with its per-axis sd widened by it, for
    optimizers that take nothing but an sd per axis; ``summary``: for metrics.json."""

    trajectories: dict[str, Trajectory]
    widening: dict[str, np.ndarray]
    summary: dict
    #: per blamed run, the covariance (n_epochs, 3, 3) to add to its *corrected* sd beyond the
    #: widened spans, fading out over ``fade_m`` (see :func:`with_fading_margin`)
    margin: dict[str, np.ndarray] = field(default_factory=dict)
    #: per run, the covariance (n_epochs, 3, 3) to add to its *corrected* sd where a vote of runs
    #: settled a disagreement (see :func:`_vote_margin`)
    vote_margin: dict[str, np.ndarray] = field(default_factory=dict)
    #: indices (in the offsets checked) of the weak tile pairs whose disagreement is unsettled
    #: (:func:`_unsettled_margin`): left out of the adjustment, which keeps both runs where their
    #: GNSS puts them
    unsettled_pairs: frozenset[int] = frozenset()


def check_reported_sd(trajectories: dict[str, Trajectory], offsets: Sequence[TileOffset],
                      options: SdCheckOptions | None = None, earlier: SdCheck | None = None,
                      control_at: np.ndarray | None = None, widened: dict[str, np.ndarray] | None = None) -> SdCheck:
    """Find where the runs' ties and tile offsets convict a run's reported sd, and widen it there.

    ``earlier``: a check already made on other tile pairs, or in fewer directions (the matcher's
    pairs, before the along-track chains, across and up): where this one finds nothing, what that
    one found stands. ``control_at``: where the adjustment takes control points (n, 2): they
    settle a vote of runs near them, which then keeps no margin (:func:`_vote_margin`).
    ``widened``: per run, the widening (n_epochs, 3, 3) the earlier check gave it."""
    options = options or SdCheckOptions()
    if earlier is not None or control_at is not None:
        check = check_reported_sd(trajectories, offsets, options, widened=earlier.widening if earlier else None)
        return _settled(check if earlier is None else _where_silent(check, earlier), control_at, options)
    summary = {"enabled": options.enabled, "observations": 0, "disagreeing": 0, "runs": {}, "notes": []}
    obs = _pool(trajectories, offsets, options) if options.enabled and len(trajectories) > 1 else None
    if obs is None:
        return SdCheck(dict(trajectories), {}, summary)
    if not options.along:
        obs = _across_and_up(obs, trajectories, options.max_weak_sd_m)
    reported = [_reported_sd(trajectories, runs, times) for runs, times in ((obs.run_a, obs.time_a),
                                                                            (obs.run_b, obs.time_b))]
    z, d, obs_sd = _z(obs, reported, options.max_weak_sd_m)
    gnss = reports_gnss(reported[0], options.gnss_sd_m) & reports_gnss(reported[1], options.gnss_sd_m)
    limit = np.where(gnss, options.max_z_gnss, options.max_z)
    # a bias spans tens of metres, seen by neighbouring tile pairs (25 m): two reaches apart
    bad = _corroborated(obs, z > limit, 2 * options.reach_m)
    if options.along:  # across and up the disagreement is no larger than in every direction
        candidate = gnss & ~obs.weak & (z > options.lone_z * limit)
        bad[candidate] |= _lone_across(_subset(obs, candidate), trajectories, [sd[candidate] for sd in reported],
                                       limit[candidate], options)
    bad &= _near(obs.where, obs.where[bad & ~obs.weak], 2 * options.reach_m)  # weak pairs never convict alone
    summary.update(observations=int(len(z)), disagreeing=int(bad.sum()))
    runs = sorted(set(obs.run_a) | set(obs.run_b))
    # ... and so is a run's disagreement with several others: the global pipeline pairs every
    # run with the reference only, and a biased reference showed against run b in one tile pair
    # and against run c in another 26-50 m on; counted within one reach, run b was blamed too
    # and dragged 5-6 cm off with the reference (a held-out portal survey: max 9.2 -> 4.7 cm)
    at_odds = _runs_at_odds(runs, obs, bad, 2 * options.reach_m, np.linalg.norm(d, axis=1), limit * obs_sd)
    out, widening, margin = dict(trajectories), {}, {}
    blamed_by = {}
    for run in runs:
        traj = trajectories[run]
        blamed = blamed_by[run] = bad & _blamed(run, runs, obs, at_odds)
        # the widening is sized and placed by the sure pairs only: a wrong weak pair in an open
        # cutting (33 cm across on an alias 2.7 m off) widened a run 0.76 m and freed it to follow
        # such pairs (portal_trap 1: max 0.04 -> 0.89 m)
        sized = blamed & ~obs.weak
        if not sized.any() or traj.sd is None:
            continue
        times, seen = _of_run(obs, sized, run, d)
        extra, track_sd, margin[run] = _widening(traj, times, seen, options.reach_m, options.fade_m,
                                                 as_along=not options.along)
        widening[run] = extra
        out[run] = traj.with_positions(traj.xyz, widened_sd(traj.sd, extra))
        changed = np.any(track_sd > 0, axis=1)
        spans = time_spans(traj.time, changed)
        worst = float(np.linalg.norm(seen, axis=1).max())
        claimed = float(np.median(np.linalg.norm(traj.sd[changed][:, :2], axis=1)))
        others = sorted(set(np.where(obs.run_a == run, obs.run_b, obs.run_a)[blamed]))
        summary["runs"][run] = {"observations": int(sized.sum()), "spans_s": spans, "worst_disagreement_m": worst,
                                "reported_sd_m": claimed, "against": others,
                                "widened_sd_m": dict(zip(("along", "across", "up"), track_sd.max(axis=0).tolist(),
                                                         strict=True))}
        note = (f"run {run}: its reported sd understates its error at {format_spans(spans)}: run(s) {', '.join(others)} "
                f"disagree with it by up to {worst:.2f} m where it reports {claimed:.3f} m (horizontal sd); its sd was "
                f"widened there, so the adjustment follows the runs that agree")
        log.warning(note)
        summary["notes"].append(note)
    # settled by other runs: one run of the two blamed (outvoted), or both where a third run was
    # there to side with one of them (two against two: the unblamed allies of a blamed run decide)
    vote = bad & ~obs.weak & ((sum(blamed_by.values()) == 1) | (len(runs) > 2))
    vote_margin = {}
    if vote.any() and options.vote_share > 0:
        vote_margin = _vote_margin(trajectories, obs.where[vote], options.vote_share * d[vote], options)
        outvoted = [run for run in runs if (blamed_by[run] & vote).any()]
        summary["vote"] = _vote_summary(obs, vote, d, outvoted, vote_margin, options)
        log.warning(summary["vote"]["note"])
        summary["notes"].append(summary["vote"]["note"])
    freed = [widened_at(w, trajectories, obs.run_a, obs.time_a) | widened_at(w, trajectories, obs.run_b, obs.time_b)
             for w in (widening, widened or {})]
    # after the chains only: before them a portal's pairs are mostly weak, and the runs that agree
    # there do not show it (held-out 4902: the reference was blamed with the biased run)
    unsettled = options.along & obs.weak & ~bad & (z > options.lone_z * limit) & ~freed[0] & ~freed[1]
    if unsettled.any():
        odds = _runs_at_odds(runs, obs, unsettled, 2 * options.reach_m, np.linalg.norm(d, axis=1), limit * obs_sd)
        blamed = {run: unsettled & _blamed(run, runs, obs, odds) for run in runs}
        for run, extra in _unsettled_margin(trajectories, obs, d, blamed, options).items():
            vote_margin[run] = vote_margin.get(run, 0.0) + extra
        summary["unsettled"] = _unsettled_summary(blamed, d, obs.pair)
        log.warning(summary["unsettled"]["note"])
        summary["notes"].append(summary["unsettled"]["note"])
    return SdCheck(out, widening, summary, margin, vote_margin, frozenset(obs.pair[unsettled].tolist()))


def _lone_across(obs: _Observations, trajectories: dict[str, Trajectory], reported: list[np.ndarray],
                 limit: np.ndarray, options: SdCheckOptions) -> np.ndarray:
    """Sure observations whose disagreement across the track and up alone exceeds ``lone_z``
    times the limit: where both runs report GNSS-quality sd, they convict with no other tile pair.

    Corroboration guards against one wrong pair, and the wrong pairs seen are aliases, off along
    the track; across and up no alias moves a pair. A held-out twin-track survey's portal had one
    cutting tile pair: it showed a run's 0.39 m multipath bias at 18 sd, across the track too,
    and the pair next to it, in the tunnel where the runs report 10 cm, at 3.6 sd. Nobody was
    convicted and the run kept its bias claiming 9 mm (13 % of its epochs beyond 3 sd, worst 30).
    Only after the chains: before them the matcher's pairs at a portal are mostly ambiguous, so
    a lone pair has no sure pairs around it to say which run is at odds. On portal_trap 2 one
    `ok` pair, 20 m into the tunnel, blamed the biased run's partner (the biased run "agreed"
    with the third run 25 m further on, where both report 0.4 m): maximum 4.9 -> 6.9 cm."""
    across = _across_and_up(obs, trajectories, options.max_weak_sd_m)
    return (_z(across, reported, options.max_weak_sd_m)[0] > options.lone_z * limit) & ~obs.weak


def _subset(obs: _Observations, mask: np.ndarray) -> _Observations:
    """The observations where ``mask`` holds."""
    return _Observations(*(getattr(obs, f.name)[mask] for f in fields(_Observations)))


def _vote_margin(trajectories: dict[str, Trajectory], where: np.ndarray, share: np.ndarray,
                 options: SdCheckOptions) -> dict[str, np.ndarray]:
    """Per run passing within ``reach_m`` of the places ``where`` (n, 2) that a vote of runs
    settled, the covariance (n_epochs, 3, 3) that makes its corrected sd cover ``share`` (n, 3, a
    share of each disagreement there), over ``reach_m`` around them and fading out over ``fade_m``.

    Where runs that agree with each other disagree with one run, the adjustment follows them and
    each corrected run's posterior sd is theirs, 1-2 cm. But runs through one portal minutes apart
    see the same satellites off the same walls: a simulated portal biased two of three runs alike
    by 0.39 m, the third run was blamed, and all three ended 0.39 m off claiming 0.8-3 cm (10-15 %
    of their epochs beyond 3 sd, worst 34 sd). Relative observations cannot tell that from one
    biased run; so every run there keeps a share of the disagreement in its corrected sd, half by
    default, as two runs that disagree with no third to vote would (each is then half of it off).
    The correction itself is left to follow the majority."""
    from scipy.spatial import cKDTree

    out = {}
    for run, traj in trajectories.items():
        if traj.sd is None:
            continue
        dist, at = cKDTree(traj.xyz[:, :2]).query(where)
        near = dist <= options.reach_m
        if near.any():
            extra, _, fading = _widening(traj, traj.time[at[near]], share[near], options.reach_m, options.fade_m,
                                         as_along=not options.along)
            out[run] = extra + fading
    return out


def _of_run(obs: _Observations, mask: np.ndarray, run: str, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The times at which ``run`` made the observations in ``mask``, and their disagreements ``d``."""
    as_a, as_b = mask & (obs.run_a == run), mask & (obs.run_b == run)
    return np.concatenate([obs.time_a[as_a], obs.time_b[as_b]]), np.concatenate([d[as_a], d[as_b]])


def widened_at(widening: dict[str, np.ndarray], trajectories: dict[str, Trajectory], runs: np.ndarray,
               times: np.ndarray) -> np.ndarray:
    """Whether each observation's run (``runs``) is widened (``widening``, per run) at its time."""
    out = np.zeros(len(runs), bool)
    for run, extra in widening.items():
        m = runs == run
        if m.any():
            at = np.clip(np.searchsorted(trajectories[run].time, times[m]), 0, len(extra) - 1)
            out[m] = np.einsum("nii->n", extra[at]) > 0
    return out


def _unsettled_margin(trajectories: dict[str, Trajectory], obs: _Observations, d: np.ndarray,
                      blamed: dict[str, np.ndarray], options: SdCheckOptions) -> dict[str, np.ndarray]:
    """Per run, the covariance (n_epochs, 3, 3) that makes its corrected sd cover the whole
    disagreement ``d`` (along the track as well) of the unsettled observations ``blamed`` on it
    (weak, far beyond the runs' reported sd, convicting nobody, neither run widened there by this
    check or an earlier one), over ``reach_m`` and fading out over ``fade_m``.

    A weak pair's across and up are sure where the lining is the same along the track, but a wrong
    one in an open cutting was 33 cm off across (on an alias 2.7 m off), so it convicts nobody
    alone and the adjustment keeps both runs where their GNSS puts them. Held-out commensurate
    4902 (three runs, 220 points per profile): run c's GNSS sat 0.33 m off across at its exit
    portal claiming 1.3 cm; the one tile pair there that fitted at all was ambiguous and showed
    it at 11 sd; nothing convicted run c, which kept its bias at 28 sd (5 % of its epochs beyond
    3 sd). The run at odds with the runs it meets there is blamed (with two runs, both)."""
    out = {}
    for run, mine in blamed.items():
        traj = trajectories[run]
        if traj.sd is None or not mine.any():
            continue
        extra, _, fading = _widening(traj, *_of_run(obs, mine, run, d), options.reach_m, options.fade_m, as_along=True)
        out[run] = extra + fading
    return out


def _unsettled_summary(blamed: dict[str, np.ndarray], d: np.ndarray, pair: np.ndarray) -> dict:
    """The runs weak pairs alone show at odds far beyond their reported sd, and a note."""
    runs = sorted(run for run, mine in blamed.items() if mine.any())
    seen = np.any(list(blamed.values()), axis=0)
    pairs = sorted(set(pair[seen].tolist()))
    worst = float(np.linalg.norm(d[seen], axis=1).max())
    note = (f"run(s) {', '.join(runs)} at odds with the runs they meet by up to {worst:.2f} m where they report "
            f"centimetres, seen only by tile pairs whose along-track offset is unresolved ({len(pairs)}), so nobody's "
            f"GNSS was widened and those pairs were left out of the adjustment, which keeps the runs where their GNSS "
            f"puts them; the corrected sd there covers the disagreement. Control there would settle it")
    return {"observations": int(seen.sum()), "runs": runs, "worst_disagreement_m": worst, "pairs_left_out": len(pairs),
            "note": note}


def _vote_summary(obs: _Observations, vote: np.ndarray, d: np.ndarray, outvoted: list[str],
                  margin: dict[str, np.ndarray], options: SdCheckOptions) -> dict:
    """The runs outvoted and outvoting, the margin each run's corrected sd keeps, and a note."""
    worst = float(np.linalg.norm(d[vote], axis=1).max())
    majority = sorted((set(obs.run_a[vote]) | set(obs.run_b[vote])) - set(outvoted))
    kept = _largest_sd(margin)
    note = (f"run(s) {', '.join(outvoted)} disagree with run(s) {', '.join(majority) or 'among them'} by up to "
            f"{worst:.2f} m and the runs that agree decide the correction there, but should they share a GNSS bias "
            f"(multipath at one portal, minutes apart) it is off by as much and nothing relative shows it; so every "
            f"run's corrected sd there keeps {options.vote_share:.0%} of the disagreement (up to "
            f"{max(kept.values(), default=0.0):.2f} m). Control there would settle it")
    return {"observations": int(vote.sum()), "outvoted": outvoted, "majority": majority, "worst_disagreement_m": worst,
            "share": options.vote_share, "corrected_sd_margin_m": kept, "note": note}


def _settled(check: SdCheck, control_at: np.ndarray | None, options: SdCheckOptions) -> SdCheck:
    """``check`` without the vote margin of each stretch of a run that passes within two reaches of
    a control point: the adjustment follows the control there, not the majority of runs."""
    if control_at is None or not len(control_at) or not check.vote_margin:
        return check
    vote_margin, dropped = {}, 0
    for run, extra in check.vote_margin.items():
        near = _near(check.trajectories[run].xyz[:, :2], control_at, 2 * options.reach_m)
        keep = _stretches_apart(extra, near[:, None, None] * np.eye(3))
        dropped += int((np.einsum("nii->n", extra) > 0).sum() - keep.sum())
        if keep.any():
            vote_margin[run] = np.where(keep[:, None, None], extra, 0.0)
    if not dropped:
        return check
    note = "control points near where runs outvoted a run settle the vote: the corrected sd keeps no margin there"
    log.info(note)
    summary = dict(check.summary, notes=[*check.summary["notes"], note])
    if "vote" in summary:
        summary["vote"] = dict(summary["vote"], corrected_sd_margin_m=_largest_sd(vote_margin), settled_by_control=True)
    return replace(check, vote_margin=vote_margin, summary=summary)


def _where_silent(check: SdCheck, earlier: SdCheck) -> SdCheck:
    """``check``, with each stretch of a run that ``earlier`` widened (with its fading margin) kept
    where ``check`` widened nothing there. A check on sure pairs measures every direction, so where
    it saw the bias too its widening stands; but the along-track chains may have demoted the pairs
    that showed a bias, and weak pairs alone convict nobody."""
    widening, margin, out = dict(check.widening), dict(check.margin), dict(check.trajectories)
    notes = list(check.summary["notes"])
    for run, extra in earlier.widening.items():
        mine = widening.get(run, np.zeros_like(extra))
        keep = _stretches_apart(extra + earlier.margin.get(run, 0.0), mine)
        if not keep.any():
            continue
        kept = np.where(keep[:, None, None], extra, 0.0)
        widening[run] = mine + kept
        margin[run] = margin.get(run, 0.0) + np.where(keep[:, None, None], earlier.margin.get(run, 0.0), 0.0)
        traj = out[run]  # where ``check`` is silent, its sd is the reported one
        out[run] = traj.with_positions(traj.xyz, widened_sd(traj.sd, kept))
        notes += [n for n in earlier.summary["notes"] if n.startswith(f"run {run}:")]
    vote_margin = dict(check.vote_margin)
    for run, extra in earlier.vote_margin.items():
        keep = _stretches_apart(extra, vote_margin.get(run, np.zeros_like(extra)))
        if keep.any():
            vote_margin[run] = vote_margin.get(run, 0.0) + np.where(keep[:, None, None], extra, 0.0)
            if earlier.summary["vote"]["note"] not in notes:
                notes.append(earlier.summary["vote"]["note"])
    summary = dict(check.summary, earlier=earlier.summary, notes=notes)
    return SdCheck(out, widening, summary, margin, vote_margin, check.unsettled_pairs)


def _largest_sd(covariances: dict[str, np.ndarray]) -> dict[str, float]:
    """Per run, the largest sd (m, the root of the trace) of its covariances (n, 3, 3)."""
    return {run: float(np.sqrt(np.einsum("nii->n", c).max())) for run, c in sorted(covariances.items())}


def _stretches_apart(earlier: np.ndarray, later: np.ndarray) -> np.ndarray:
    """Epochs of the stretches where covariance ``earlier`` (n, 3, 3) is not zero that share no
    epoch with where ``later`` is not zero."""
    from scipy.ndimage import label

    stretch = label(np.einsum("nii->n", earlier) > 0)[0]
    return (stretch > 0) & ~np.isin(stretch, stretch[np.einsum("nii->n", later) > 0])


def widened_sd(sd: np.ndarray, widening: np.ndarray) -> np.ndarray:
    """Per-axis sd (n, 3) of a run whose covariance was widened by ``widening`` (n, 3, 3)."""
    return np.sqrt(sd**2 + np.einsum("nii->ni", widening))


def _pool(trajectories: dict[str, Trajectory], offsets: Sequence[TileOffset],
          options: SdCheckOptions) -> _Observations | None:
    """The ties of ``ok`` pairs and the offsets of tie-less ``ok`` and ``coarse`` pairs, as the
    optimizer uses them, and weak pairs (degenerate, ambiguous) across and up, flagged ``weak``.

    A wrong weak pair near a portal would convict a good run, so weak pairs only corroborate
    (and say which run is at odds) where an ``ok`` or ``coarse`` pair disagrees too. Left out
    altogether, a run whose GNSS sat 0.39 m off near its entry portal was seen there by one
    coarse pair (7.7 sd) and three ambiguous ones (20-65 sd across), was not convicted, and the
    adjustment rejected those four and kept the run where its GNSS put it, claiming 1.3 cm (a
    simulated survey drifted 2.5 m, matched within 4.5 m: 8 % of epochs beyond 3 sd).
    A weak pair counts window by window where the matcher gave its windows
    (:func:`railtraj.adjust.offsets.by_window`): a bias ramping in within its tile shows there.
    Same-track observations (:mod:`railtraj.same_track`) are sure, across and up; each segment
    of them counts as one tile pair."""
    rows, segments = [], {}
    for k, o in enumerate(offsets):
        if o.run_a not in trajectories or o.run_b not in trajectories:
            continue
        same_track = bool(o.info.get("same_track"))
        if same_track:  # (one tile pair per segment: one place alone convicts nobody)
            k = segments.setdefault((o.run_a, o.run_b, o.tile_a), len(offsets) + len(segments))
        t = o.ties
        if o.ok and t is not None and len(t):
            rows.append((np.full(len(t), o.run_a, object), np.full(len(t), o.run_b, object), t.time_a, t.time_b,
                         t.xyz_a[:, :2], t.xyz_a - t.xyz_b, np.broadcast_to(options.tie_sd_m**2 * np.eye(3), (len(t), 3, 3)),
                         np.full(len(t), k), np.zeros(len(t), bool)))
        else:
            for w in by_window(o):  # a weak pair window by window, where it has them (across and up)
                if not usable_offset(w, trajectories):
                    continue
                t_a = np.array([w.info["time_a"]])
                # like a tie's xyz_a - xyz_b (the optimizer's c_b - c_a = d): error_a - error_b
                rows.append((np.array([w.run_a], object), np.array([w.run_b], object), t_a,
                             np.array([w.info["time_b"]]), trajectories[w.run_a].position_at(t_a)[:, :2],
                             np.asarray(w.d, float)[None], offset_covariance(w)[None], np.array([k]),
                             np.array([w.status in WEAK_STATUSES and not same_track])))
    if not rows:
        return None
    return _Observations(*(np.concatenate(column) for column in zip(*rows, strict=True)))


def _across_and_up(obs: _Observations, trajectories: dict[str, Trajectory], max_weak_sd_m: float) -> _Observations:
    """The observations with the along-track direction (run a's, where it was observed) left out.

    One that leaves a direction out already (sd beyond ``max_weak_sd_m``: a weak pair, along its
    own track axis, fitted on the clouds) is kept as it is: a bias ramping in tilts the biased
    run's trajectory by its gradient (1.5 cm/m at a held-out portal), and a second unseen
    direction that far from the first gave the plane between them an across sd of 0.6-1.3 m, so
    the weak pairs there said nothing across the track either."""
    cov = obs.cov.copy()
    unseen = np.linalg.eigvalsh(obs.cov)[:, -1] > max_weak_sd_m**2
    for run, traj in trajectories.items():
        m = (obs.run_a == run) & ~unseen
        if m.any():
            along = track_frames(traj.xyz)[np.clip(np.searchsorted(traj.time, obs.time_a[m]), 0, len(traj.time) - 1), 0]
            cov[m] += UNSEEN_VAR * np.einsum("ni,nj->nij", along, along)
    return replace(obs, cov=cov)


def _z(obs: _Observations, reported: list[np.ndarray],
       max_weak_sd_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each observation's disagreement in sd of the two runs' reported sd (``reported``: run a's
    and run b's, (n, 3) each, from :func:`_reported_sd`) and its own covariance, and the
    disagreement itself, both in the directions the observation constrains; third, the largest
    sd of that covariance in those directions (how large a disagreement it could have missed)."""
    vals, vecs = np.linalg.eigh(obs.cov)
    keep = (np.sqrt(np.maximum(vals, 0.0)) <= max_weak_sd_m).astype(float)
    project = np.einsum("nik,nk,njk->nij", vecs, keep, vecs)
    d = np.einsum("nij,nj->ni", project, obs.d)
    var = obs.cov.copy()
    known = np.ones(len(d), bool)
    for sd in reported:
        given = np.isfinite(sd).all(axis=1)
        known &= given
        var[given] += np.einsum("ni,ij->nij", sd[given] ** 2, np.eye(3))
    var = np.einsum("nik,nkl,njl->nij", project, var, project)
    sd = np.sqrt(np.linalg.eigvalsh(var)[:, -1])
    z = np.sqrt(np.einsum("ni,ni->n", d, np.linalg.solve(var + (np.eye(3) - project), d[..., None])[..., 0]))
    return np.where(known, z, 0.0), d, np.where(known, sd, np.inf)


def _reported_sd(trajectories: dict[str, Trajectory], runs: np.ndarray, times: np.ndarray) -> np.ndarray:
    """The sd (n, 3) each observation's run reports at its time (infinite where it reports none)."""
    out = np.full((len(runs), 3), np.inf)
    for run, traj in trajectories.items():
        m = runs == run
        if m.any() and traj.sd is not None:
            out[m] = traj.sd_at(times[m])
    return out


def _blamed(run: str, runs: list[str], obs: _Observations, at_odds: dict[str, np.ndarray]) -> np.ndarray:
    """Observations of ``run`` whose disagreement is put on it: near each, ``run`` is at odds with
    the runs it meets (:func:`_runs_at_odds`) at least as much as the other run of the
    observation is. One run with biased GNSS disagrees with every run it meets there, and they
    with it alone; with two runs both are blamed."""
    involved = (obs.run_a == run) | (obs.run_b == run)
    other = np.where(obs.run_a == run, obs.run_b, obs.run_a)
    theirs = np.zeros(len(obs.d))
    for r in runs:
        theirs[other == r] = at_odds[r][other == r]
    return involved & (at_odds[run] >= theirs)


def _corroborated(obs: _Observations, bad: np.ndarray, reach_m: float) -> np.ndarray:
    """Disagreements that another tile pair (of the same runs or of others) shows within
    ``reach_m`` too: one wrong tile pair (an alias, a coarse fit) convicts nobody."""
    from scipy.spatial import cKDTree

    idx = np.flatnonzero(bad)
    if len(idx) < 2:
        return np.zeros_like(bad)
    tree = cKDTree(obs.where[idx])
    near = tree.sparse_distance_matrix(tree, reach_m, output_type="ndarray")
    rows, cols = near["i"], near["j"]
    other_pair = obs.pair[idx][cols] != obs.pair[idx][rows]
    keep = np.zeros(len(idx), bool)
    keep[rows[other_pair]] = True
    out = np.zeros_like(bad)
    out[idx[keep]] = True
    return out


def _near(where: np.ndarray, points: np.ndarray, reach_m: float) -> np.ndarray:
    """Whether each of ``where`` lies within ``reach_m`` of any of ``points``."""
    from scipy.spatial import cKDTree

    if not len(points):
        return np.zeros(len(where), bool)
    return cKDTree(points).query_ball_point(where, reach_m, return_length=True) > 0


def _runs_at_odds(runs: list[str], obs: _Observations, bad: np.ndarray, reach_m: float, size: np.ndarray,
                  missed: np.ndarray) -> dict[str, np.ndarray]:
    """Per run, at each observation's place: how many other runs it disagrees with within
    ``reach_m``, less how many it agrees with there (sure observations, none disagreeing).

    The agreement counts where some runs meet only one other: the global pipeline pairs every
    run with the reference only, so a run whose GNSS is biased disagrees with the reference
    alone, and the reference with it alone, while the reference agrees with the third run.
    Counting disagreements only blamed both (a held-out survey's run b, 0.33 m off along the
    track at a portal: the reference was widened as far, and the adjustment kept run b 0.25 m
    off claiming 5 cm).

    An observation agrees only with a disagreement (``size``, m) at least as large as the one it
    could have missed (``missed``: the limit times its largest sd). Where the runs report 0.4 m,
    a pair within the limit says nothing about a 0.3 m bias: on portal_trap 2 such a pair, 25 m
    from the biased run's portal, had it "agree" with the third run, and its partner was blamed."""
    from scipy.spatial import cKDTree

    count = {r: np.zeros(len(obs.d)) for r in runs}
    at = np.flatnonzero(bad)  # only where an observation disagrees does the count matter (blame is of those)
    at_tree = cKDTree(obs.where[at]) if len(at) else None
    for i, r in enumerate(runs):
        for q in runs[i + 1:]:
            of_pair = ((obs.run_a == r) & (obs.run_b == q)) | ((obs.run_a == q) & (obs.run_b == r))
            disagree = _near(obs.where, obs.where[bad & of_pair], reach_m)
            agreeing = np.flatnonzero(of_pair & ~bad & ~obs.weak)
            agree = np.zeros(len(obs.d), bool)
            if len(agreeing) and at_tree is not None:
                near = at_tree.sparse_distance_matrix(cKDTree(obs.where[agreeing]), reach_m, output_type="ndarray")
                sees = missed[agreeing][near["j"]] <= size[at][near["i"]]
                agree[at[near["i"][sees]]] = True
            agree &= ~disagree
            count[r] += disagree.astype(float) - agree
            count[q] += disagree.astype(float) - agree
    return count


def _widening(traj: Trajectory, times: np.ndarray, seen: np.ndarray, reach_m: float,
              fade_m: float, as_along: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The covariance (n_epochs, 3, 3) that makes the run's sd cover the disagreements ``seen`` at
    ``times``, within ``reach_m`` metres travelled, and its sd (n_epochs, 3) along the track, across
    it and up. Kept in the track frame so that a bias across the track does not free the run along
    it, where its reported sd may still be right. Third, the margin (n_epochs, 3, 3) by which that
    widening fades out linearly over the next ``fade_m`` metres (:func:`with_fading_margin`)."""
    from scipy.ndimage import maximum_filter1d

    frame = track_frames(traj.xyz)
    bins = np.floor(traj.travelled()).astype(np.int64)
    at = np.clip(np.searchsorted(traj.time, times), 0, len(traj.time) - 1)
    size = np.abs(np.einsum("nij,nj->ni", frame[at], seen))
    if as_along:  # not compared along the track: a GNSS bias is as likely along as across
        size[:, 0] = np.maximum(size[:, 0], size[:, 1])
    track_sd = np.zeros((bins[-1] + 1, 3))
    np.maximum.at(track_sd, bins[at], size)
    track_sd = maximum_filter1d(track_sd, size=2 * int(np.ceil(reach_m)) + 1, axis=0, mode="constant")
    faded = track_sd.copy()
    steps = int(np.ceil(fade_m))
    for j in range(1, min(steps, len(faded) - 1) + 1):  # metres of fade (tens), not epochs
        share = 1.0 - j / (steps + 1)
        faded[j:] = np.maximum(faded[j:], share * track_sd[:-j])
        faded[:-j] = np.maximum(faded[:-j], share * track_sd[j:])
    track_sd, faded = track_sd[bins], faded[bins]
    extra = np.einsum("nki,nk,nkj->nij", frame, track_sd**2, frame)
    margin = np.einsum("nki,nk,nkj->nij", frame, faded**2 - track_sd**2, frame)
    return extra, track_sd, margin


def covariance_at(times: np.ndarray, epochs: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Per-epoch covariances ``cov`` (n_epochs, 3, 3) at ``epochs``, linearly interpolated to
    ``times`` (component by component: still symmetric positive semi-definite)."""
    flat = cov.reshape(len(cov), 9)
    return np.column_stack([np.interp(times, epochs, c) for c in flat.T]).reshape(-1, 3, 3)


def with_fading_margin(corrected: dict[str, Trajectory], checked: SdCheck) -> dict[str, Trajectory]:
    """The corrected runs with their sd widened by the check's fading margin and its vote margin
    (:func:`_vote_margin`).

    A bias does not stop where the ties stop showing it: at a simulated portal, GNSS multipath
    grew over 40 m of open sky that only weak tile pairs saw, and 25 m from the last convicting
    tie the corrected run still sat 0.2 m off at 15 sd. Freeing the run over that stretch in the
    adjustment too let it drift from runs whose bias had ended (maximum inter-run error 4-5 ->
    6-17 cm on 13 portal surveys), so only its corrected sd says that its GNSS may still be
    biased there."""
    out = dict(corrected)
    for run in sorted(set(checked.margin) | set(checked.vote_margin)):
        traj, checked_time = corrected.get(run), checked.trajectories[run].time
        if traj is None or traj.sd is None:
            continue
        margin = checked.margin.get(run, 0.0) + checked.vote_margin.get(run, 0.0)
        out[run] = traj.with_positions(traj.xyz, widened_sd(traj.sd, covariance_at(traj.time, checked_time, margin)))
    return out


def time_spans(time: np.ndarray, flag: np.ndarray) -> list[list[float]]:
    """[first, last] time of each run of consecutive flagged epochs."""
    return [[float(time[a]), float(time[b])] for a, b in stretches(flag)]


def format_spans(spans: list[list[float]]) -> str:
    """Time spans for a log line: the first five, and how many more."""
    return ", ".join(f"{a:.1f}-{b:.1f} s" for a, b in spans[:5]) + (f" and {len(spans) - 5} more" if len(spans) > 5 else "")


__all__ = ["SdCheck", "SdCheckOptions", "check_reported_sd", "widened_sd"]
