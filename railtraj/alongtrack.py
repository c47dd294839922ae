"""Joint along-track ambiguity resolution: one alias per tile pair, chosen along the track.

Ribs, rings and sleepers repeat, so a tile pair's along-track offset is known only up to a
multiple of their periods; when two periods are commensurate (1.5 m ribs, 0.6 m sleepers) even
the combination repeats every 3.0 m and only sparse unique objects (niches, boxes) tell the
aliases apart. A single pair cannot always be sure; the chain of pairs along a run pair can:

* the offset between two runs is a smooth curve of chainage that never jumps by a period, and
  each pair's own curve of offsets measures its *rate* (mm per metre), so the offset at the next
  pair is predicted to centimetres;
* near the portals the trajectories' reported sd is small, which anchors the chain at zero.

Per run pair the pairs are ordered along run b's track. Each pair's candidates are the local
maxima of its along-track fitness profile (the matcher's ``alias_profile``: the share of run b's
points within 5 cm of run a's when its curve is shifted by t). A min-sum (Viterbi) pass over
the chain with

* an evidence cost per candidate from its misfit against the best one,
* a prior cost from the trajectories' sd, and
* a transition cost on the difference between a candidate and the offset predicted from the
  previous pair plus the measured rate,

gives the best sequence. A forward-backward pass gives every candidate's min-marginal cost. A
pair is *resolved* only when its best candidate beats the runner-up by ``min_margin`` (GNSS
ambiguity fixing's ratio test). Otherwise it stays ``ambiguous`` and is used across the track
and in height only. This applies to ``ok`` pairs too: a pair the matcher found sure but the chain
cannot confirm is demoted, never kept on a possible alias.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
from scipy.signal import find_peaks

from railtraj.data import Ties, TileOffset, Trajectory

log = logging.getLogger(__name__)


@dataclass
class AlongTrackOptions:
    """Settings of the joint resolution (``pipeline.alongtrack.*``)."""

    enabled: bool = True
    rate_sd: float = 0.003          # m/m: error of a pair's measured drift rate
    curvature_sd: float = 0.0004    # m/m^2: change of the drift rate along the track
    min_margin: float = 16.0        # cost (chi-square) by which the chosen candidate must win: 4 sigma
    max_excess: float = 25.0        # a pair whose best candidate adds more than this to the chain is inconsistent
    evidence_ratio: float = 1.25    # a misfit ratio worth 3 sigma of evidence against a candidate
    max_evidence: float = 9.0       # ... and no candidate is charged more than that (3 sigma)
    min_fitness: float = 0.5        # pairs whose profile never reaches this give no evidence
    min_prominence: float = 0.02    # a candidate's fitness stands this far above the dips beside it
    max_misfit_ratio: float = 2.5   # candidates misfitting more than this times the best are dropped
    max_candidates: int = 15


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


def resolve_along_track(offsets: list[TileOffset], trajectories: dict[str, Trajectory],
                        options: AlongTrackOptions) -> tuple[list[TileOffset], list[dict]]:
    """Offsets with each candidate pair resolved, moved to another alias or demoted, and one
    report row per candidate pair."""
    if not options.enabled:
        return list(offsets), []
    out, report = list(offsets), []
    chains: dict[tuple[str, str], list[Pair]] = {}
    travelled = {r: _travelled(t) for r, t in trajectories.items()}
    for k, o in enumerate(offsets):
        pair = _candidates(k, o, trajectories, travelled, options)
        if pair is not None:
            chains.setdefault((o.run_a, o.run_b), []).append(pair)
    for (run_a, run_b), chain in sorted(chains.items()):
        chain.sort(key=lambda p: p.s)
        for pair, (shift, margin, verdict) in zip(chain, _resolve_chain(chain, options), strict=True):
            resolved = verdict == "resolved"
            out[pair.index] = _apply(offsets[pair.index], shift, resolved, trajectories)
            report.append({"run_a": run_a, "run_b": run_b, "tile_a": offsets[pair.index].tile_a,
                           "tile_b": offsets[pair.index].tile_b, "status_before": offsets[pair.index].status,
                           "status": out[pair.index].status, "verdict": verdict, "shift_m": round(shift, 3),
                           "margin": round(min(margin, 1e6), 1), "candidates": len(pair.shift),
                           "candidate_shifts_m": np.round(pair.shift, 2).tolist()})
    moved = sum(abs(r["shift_m"]) > 0.1 and r["status"] == "ok" for r in report)
    log.info("along-track: %d tile pairs with candidates, %d resolved (%d moved to another alias), %d left weak",
             len(report), sum(r["status"] == "ok" for r in report), moved,
             sum(r["status"] != "ok" for r in report))
    return out, report


def _candidates(index: int, o: TileOffset, trajectories: dict[str, Trajectory],
                travelled: dict[str, np.ndarray], options: AlongTrackOptions) -> Pair | None:
    """The pair's alias candidates, or None if it has no along-track fit to choose from."""
    pw, prof = o.info.get("piecewise"), o.info.get("alias_profile")
    if o.status not in ("ok", "ambiguous") or not pw or not prof or "fit_cov" not in pw:
        return None
    times = (o.info.get("time_a", np.nan), o.info.get("time_b", np.nan))
    if not np.isfinite(times).all() or o.run_b not in trajectories or o.run_a not in trajectories:
        return None
    fitness = np.asarray(prof["fitness"], float)
    if not len(fitness) or fitness.max() < options.min_fitness:
        return None  # the pair's clouds hardly meet at any shift: no along-track evidence
    ts = prof["start"] + prof["step"] * np.arange(len(fitness))
    misfit = np.maximum(1.0 - fitness, 1e-3)
    # candidates are the prominent peaks only: a profile's noise is no alias
    peaks, _ = find_peaks(np.concatenate([[0.0], fitness, [0.0]]), prominence=options.min_prominence)
    peaks = peaks - 1
    peaks = peaks[misfit[peaks] <= options.max_misfit_ratio * misfit[peaks].min()] if len(peaks) else peaks
    if not len(peaks):
        return None  # no peak stands out: the pair says nothing along the track
    peaks = peaks[np.argsort(misfit[peaks])][: options.max_candidates]
    shift = ts[peaks] + _vertex(fitness, peaks) * prof["step"]
    shift = np.where(np.abs(shift) < 0.75 * prof["step"], 0.0, shift)  # the matcher's own fit
    m = misfit[peaks]
    axis = np.asarray(pw["axis"], float)
    traj_b = trajectories[o.run_b]
    direction = _direction(traj_b, times[1])
    sign = float(np.sign(axis @ direction)) or 1.0
    u = (o.d @ direction) + shift * (axis @ direction)
    cov = np.asarray(pw["fit_cov"], float)
    sd_a, sd_b = trajectories[o.run_a].sd_at(np.array([times[0]])), traj_b.sd_at(np.array([times[1]]))
    prior_var = float(((sd_a[0] ** 2 + sd_b[0] ** 2) @ direction**2)) if sd_a is not None and sd_b is not None else 1e4
    # the profile is measured about the matcher's curve, fitted at its own choice, so it favours
    # that choice; a misfit ratio is therefore worth at most ``max_evidence``
    evidence = np.minimum(9.0 * (np.log(m / m.min()) / np.log(options.evidence_ratio)) ** 2, options.max_evidence)
    return Pair(index, float(np.interp(times[1], traj_b.time, travelled[o.run_b])), u, shift, evidence,
                float(np.asarray(pw["gradient"], float) @ direction) * sign, float(np.sqrt(direction @ cov @ direction)),
                max(prior_var, 1e-6))


def _vertex(f: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Sub-sample position (in steps, within +-0.5) of the peak of ``f`` at each index ``k``:
    the vertex of the parabola through the sample and its neighbours (0 at the ends)."""
    inner = (k > 0) & (k < len(f) - 1)
    out = np.zeros(len(k))
    y0, y1, y2 = f[k[inner] - 1], f[k[inner]], f[k[inner] + 1]
    curv = y0 - 2 * y1 + y2
    out[inner] = np.where(curv < 0, 0.5 * (y0 - y2) / np.where(curv < 0, curv, -1.0), 0.0)
    return np.clip(out, -0.5, 0.5)


def _resolve_chain(chain: list[Pair], options: AlongTrackOptions) -> list[tuple[float, float, str]]:
    """Per pair: the chosen shift, its margin over the runner-up and a verdict (``resolved``,
    ``ambiguous``: the margin is too small, ``inconsistent``: none of its candidates fits the
    chain; such a pair is taken out, the worst first, and the rest solved again)."""
    active = list(range(len(chain)))
    verdicts: dict[int, tuple[float, float, str]] = {}
    while active:
        sub = [chain[i] for i in active]
        marginals, without = _min_marginals(sub, options)
        excess = np.array([m.min() - w for m, w in zip(marginals, without, strict=True)])
        worst = int(np.argmax(excess))
        if excess[worst] > options.max_excess:
            verdicts[active.pop(worst)] = (0.0, 0.0, "inconsistent")
            continue
        for i, cost in zip(active, marginals, strict=True):
            order = np.argsort(cost)
            margin = float(cost[order[1]] - cost[order[0]]) if len(cost) > 1 else np.inf
            verdicts[i] = (float(chain[i].shift[order[0]]), margin,
                           "resolved" if margin >= options.min_margin else "ambiguous")
        break
    return [verdicts[i] for i in range(len(chain))]


def _transition(p: Pair, q: Pair, options: AlongTrackOptions) -> np.ndarray:
    """(k_p, k_q) cost of going from each candidate of ``p`` to each of ``q``: the offset
    predicted from ``p`` with the measured rate, against ``q``'s candidates."""
    ds = q.s - p.s
    predicted = p.u[:, None] + 0.5 * (p.rate + q.rate) * ds
    var = (options.rate_sd * ds) ** 2 + (0.5 * options.curvature_sd * ds**2) ** 2 + p.sd**2 + q.sd**2
    return (q.u[None, :] - predicted) ** 2 / var


def _min_marginals(chain: list[Pair], options: AlongTrackOptions) -> tuple[list[np.ndarray], np.ndarray]:
    """Min-sum forward-backward over the chain: per pair, the least total cost of a sequence
    through each of its candidates, and the least cost of the chain without that pair."""
    unary = [p.evidence + p.u**2 / p.prior_var for p in chain]
    trans = [_transition(p, q, options) for p, q in zip(chain[:-1], chain[1:], strict=True)]
    fwd = [unary[0]]
    for k in range(1, len(chain)):
        fwd.append(unary[k] + (fwd[-1][:, None] + trans[k - 1]).min(axis=0))
    bwd = [np.zeros(len(chain[-1].u))]
    for k in range(len(chain) - 2, -1, -1):
        bwd.insert(0, (trans[k] + (unary[k + 1] + bwd[0])[None, :]).min(axis=1))
    n = len(chain)
    without = np.zeros(n)
    for k in range(n):  # a pair left out: its neighbours joined directly
        if n == 1:
            without[k] = 0.0
        elif k == 0:
            without[k] = float((unary[1] + bwd[1]).min())
        elif k == n - 1:
            without[k] = float(fwd[n - 2].min())
        else:
            skip = _transition(chain[k - 1], chain[k + 1], options)
            without[k] = float((fwd[k - 1][:, None] + skip + (unary[k + 1] + bwd[k + 1])[None, :]).min())
    return [f + b for f, b in zip(fwd, bwd, strict=True)], without


def _apply(o: TileOffset, shift: float, resolved: bool, trajectories: dict[str, Trajectory]) -> TileOffset:
    """The pair after resolution: on its chosen alias and ``ok``, or ``ambiguous``."""
    pw = o.info["piecewise"]
    axis, fit_cov = np.asarray(pw["axis"], float), np.asarray(pw["fit_cov"], float)
    info = dict(o.info, alongtrack={"shift_m": shift, "resolved": resolved})
    if not resolved:
        if o.status == "ok":
            info["demoted"] = "along-track alias not resolved jointly"
        window = float(o.info.get("search_window", 3.0))
        return replace(o, status="ambiguous", cov=fit_cov + window**2 * np.outer(axis, axis),
                       ties=Ties.empty(o.run_a, o.run_b), info=info)
    if abs(shift) < 1e-9 and o.status == "ok":
        return replace(o, info=info)
    d = o.d + shift * axis
    info["resolved"] = "joint" if o.status != "ok" else "moved"
    info["time_a"] = _time_after_shift(trajectories[o.run_a], o.info["time_a"], shift * axis)
    return replace(o, d=d, cov=fit_cov, status="ok", ties=Ties.empty(o.run_a, o.run_b), info=info)


def _direction(traj: Trajectory, t: float) -> np.ndarray:
    """Unit horizontal direction of travel at time ``t``."""
    xyz, _ = traj.interpolate(np.clip([t - 0.25, t + 0.25], *traj.span))
    v = xyz[1] - xyz[0]
    v[2] = 0.0
    n = np.linalg.norm(v)
    return v / n if n > 0 else np.array([1.0, 0.0, 0.0])


def _travelled(traj: Trajectory) -> np.ndarray:
    """Metres travelled (in plan) by the run at each epoch."""
    step = np.linalg.norm(np.diff(traj.xyz[:, :2], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(step)])


def _time_after_shift(traj: Trajectory, t: float, move: np.ndarray) -> float:
    """When the run passed the point ``move`` away (along the track) from where it was at ``t``."""
    xyz, _ = traj.interpolate(np.clip([t - 0.25, t + 0.25], *traj.span))
    v = (xyz[1] - xyz[0]) / 0.5
    speed2 = float(v[:2] @ v[:2])
    return float(np.clip(t + (move[:2] @ v[:2]) / speed2, *traj.span)) if speed2 > 0 else t
