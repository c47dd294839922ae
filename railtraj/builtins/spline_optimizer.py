"""The ``spline`` optimizer: continuous per-run corrections from one sparse least-squares solve.

The thesis' g2o graph with fixed attitude, rebuilt so that it follows a drifting offset exactly:

1. **Model** (:mod:`railtraj.adjust.model`): each run's position correction is linear between
   knots every ``knot_spacing`` metres travelled (or seconds); observations attach at their own
   time through interpolation weights.
2. **Observations** (:mod:`railtraj.adjust.observations`): priors from the trajectory's reported
   sd, second-difference smoothness from an INS error model, ties, weak tile offsets in their
   constrained directions with their full covariance, control points as absolute observations;
   where the sd check found a run's GNSS biased, a Gauss-Markov bias state beside the drift
   (:mod:`railtraj.adjust.gnss_bias`).
3. **Solve** (:mod:`railtraj.adjust.solve`): the problem is linear, so one sparse banded solve
   per robust iteration (GNC with truncated least squares on whitened residuals), and the
   posterior sd from the band of the inverse.

``self.diagnostics`` holds counts, rejected observations, iterations and under-constrained spans
after :meth:`optimize`; the pipeline writes it to metrics.json and the report.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from railtraj.adjust import observations as obs
from railtraj.adjust.gnss_bias import (
    bias_map,
    bias_scale,
    estimated_bias,
    gauss_markov,
    gnss_share,
    on_bias,
    on_drift,
)
from railtraj.adjust.model import CorrectionModel
from railtraj.adjust.offsets import offset_covariance, resolved_by_window, usable_offset
from railtraj.adjust.recentre import recentre
from railtraj.adjust.solve import solve
from railtraj.adjust.stiffness import bend_density, stretches
from railtraj.data import ControlObservations, Ties, TileOffset, Trajectory
from railtraj.hookspecs import hookimpl
from railtraj.sd_check import covariance_at, format_spans, time_spans, widened_at, widened_sd

log = logging.getLogger(__name__)

#: at most this many rejected observations are listed individually in the diagnostics
MAX_LISTED = 200


@dataclass
class SplineConfig:
    name: str = "spline"
    knot_spacing: float = 5.0          # distance between correction knots (knot_unit)
    knot_unit: str = "m"               # m: metres travelled (default); s: seconds
    drift_curvature_sd: float = 0.0016  # drift model: white-noise density of its bend along the track, m/m^1.5
    bend_from_reported_sd: bool = True  # per outage, raise that density until the model's prior reaches the run's sd
    max_bend_widening: float = 2.0     # where the sd check widened a run's sd, its bend's sd (and a GNSS bias') grows up to this factor
    # where the widened run's sd is GNSS-like, the widening is a bias state beside the drift,
    # correlated over this many metres (0: freer drift there too, the treatment before session 55)
    gnss_bias_correlation_m: float = 25.0
    gnss_bias_sd_scale: float = 2.0    # the bias state's sd, in units of the sd check's widening
    recentre: bool = True              # without control: runs' common correction at their sd-weighted average
    tie_sigma_m: float = 0.01          # 1-sigma of one tie (a tile pair's ties weigh 1/n each), per axis
    offset_sd_floor_m: float = 0.005   # added in quadrature to a tile offset's sd
    max_weak_sd_m: float = 0.3         # directions of a weak tile offset with larger sd are not used
    use_weak_offsets: bool = True      # degenerate/ambiguous pairs constrain across and up
    use_drift_rates: bool = True       # ... and their curve's change of offset along the track (info["drift_rate"])
    windows_where_widened: bool = True  # resolved pairs without ties enter window by window where the sd check widened a run
    robust_confidence: float = 0.999   # chi-square level beyond which an observation is rejected
    default_sd_m: float = 1.0          # prior sd where the trajectory reports none
    prior_correlation: float = 500.0   # (knot_unit) length over which the reported sd is one independent error
    gnss_sd_m: float = 0.03            # reported horizontal sd up to which a position is GNSS-controlled: one error per knot
    drift_sd_m: float = 0.10           # ... from which it is the smoother's bridge: one error per prior_correlation
    min_sd_m: float = 0.005            # floor on the reported sd
    max_gap: float = 10.0              # knots without any observation before a stretch is reported
    weak_span_sd_m: float = 0.05       # ... when the trajectory's own sd there exceeds this
    # a correction beyond this many claimed sd refutes the claim: the sd is then >= |correction| / this (0: off)
    refuted_claim_ratio: float = 2.0


class SplineOptimizer:
    """Fits smooth per-run corrections to ties, weak offsets and control in one sparse solve."""

    def __init__(self, **options) -> None:
        self.config = SplineConfig(**options)
        self.diagnostics: dict = {}

    def optimize(self, trajectories: dict[str, Trajectory], ties: Sequence[Ties],
                 offsets: Sequence[TileOffset], control: ControlObservations | None = None,
                 widening: dict[str, np.ndarray] | None = None) -> dict[str, Trajectory]:
        """Corrected trajectories. ``widening``: per run, a covariance (n_epochs, 3, 3) to add to
        its reported sd where :mod:`railtraj.sd_check` found that sd understated."""
        cfg, t0 = self.config, time.perf_counter()
        widening = widening or {}
        model = CorrectionModel(trajectories, cfg.knot_spacing, cfg.knot_unit,
                                tuple(widening) if cfg.gnss_bias_correlation_m > 0 else ())
        self._bends: dict[str, list[dict]] = {}
        self._bias_scale: dict[str, np.ndarray] = {}
        blocks = [b for r in sorted(trajectories)
                  for b in self._model_blocks(model, r, trajectories[r], widening.get(r))]
        offsets, by_window = _by_window_where_widened(offsets, trajectories, widening, cfg.windows_where_widened)
        data = [self._ties(model, ties), self._offsets(model, offsets, trajectories),
                self._drift_rates(model, offsets, trajectories), self._control(model, control, trajectories)]
        data = [b for b in data if b is not None]
        if not any(len(b) for b in data):
            note = "optimizer spline: no ties, usable tile offsets or control; trajectories left unchanged"
            log.warning(note)
            self.diagnostics = {"optimizer": "spline", "notes": [note]}
            return dict(trajectories)
        sol = solve(blocks + data, model.n_unknowns, confidence=cfg.robust_confidence)
        cov_blocks = sol.banded.covariance_blocks()
        out, spans, claimed, refuted = {}, [], {}, {}
        for r in sorted(trajectories):
            traj = trajectories[r]
            corr, sd = _evaluate(model, r, traj.time, sol, cov_blocks)
            claimed[r] = np.full((len(traj.time), 3), cfg.default_sd_m) if traj.sd is None else traj.sd
            if r in widening:
                claimed[r] = widened_sd(claimed[r], widening[r])
            # the priors are weakened to count a correlated error once per prior_correlation, so
            # their posterior sd overstates it where the input was already good (portals: 3.4 cm
            # for GNSS at 1.5 cm); information only ever narrows it, so never report more than
            # the claim, unless the correction itself refutes the claim
            if traj.sd is not None:
                cap = self._claim_not_refuted(claimed[r], corr)
                sd, lifted = np.minimum(sd, cap), cap > claimed[r]
                if lifted.any():
                    refuted[r] = _refuted_claim(r, traj.time, corr, claimed[r], lifted)
            out[r] = traj.with_positions(traj.xyz + corr, np.maximum(sd, 1e-6))
            spans += self._weak_spans(model, r, traj, data)
        self.diagnostics = self._report(blocks + data, sol, model, spans, time.perf_counter() - t0)
        self.diagnostics["bend_raised"] = self._bends
        if self._bias_scale:  # metrics.json: adjustment.gnss_bias
            self.diagnostics["gnss_bias"] = {r: estimated_bias(model, r, S, sol.x)
                                             for r, S in self._bias_scale.items()}
            for r, found in self.diagnostics["gnss_bias"].items():
                log.info("run %s: GNSS bias found up to %s m (x, y, z) at %.1f s, above 2 cm over %.0f m "
                         "(a Gauss-Markov state beside the drift; adjustment.gnss_bias)", r,
                         ", ".join(f"{v:.3f}" for v in found["largest_m"]), found["time_s"], found["metres_above_2cm"])
        if by_window:
            self.diagnostics["by_window"] = by_window
        if refuted:  # metrics.json: adjustment.claim_refuted, and a note per run
            self.diagnostics["claim_refuted"] = refuted
            self.diagnostics["notes"] += [found["note"] for found in refuted.values() if found["warned"]]
        with_control = any(b.kind == "control" and len(b) for b in data)
        if cfg.recentre and not with_control:
            out, shift = recentre(trajectories, out, claimed)
            self.diagnostics["recentred_m"] = shift
        log.info("optimizer spline: %d runs, %d knots, %s; %d GNC iterations, %.2f s", len(trajectories),
                 model.n_knots, ", ".join(f"{b.kind} {len(b)}" for b in data), sol.iterations,
                 time.perf_counter() - t0)
        return out

    def _claim_not_refuted(self, claimed: np.ndarray, correction: np.ndarray) -> np.ndarray:
        """The claimed sd, raised per axis to |correction| / ``refuted_claim_ratio`` where the
        correction moved the run by more than that many claimed sd: such a claim was wrong there
        (or the correction is), so it cannot bound the posterior (a short portal survey's free
        start moved 1.05 m under a claimed 0.29 m)."""
        ratio = self.config.refuted_claim_ratio
        return claimed if ratio <= 0 else np.maximum(claimed, np.abs(correction) / ratio)

    def _model_blocks(self, model: CorrectionModel, run_id: str, traj: Trajectory,
                      widening: np.ndarray | None = None) -> list[obs.Block]:
        cfg = self.config
        times = model.runs[run_id].knot_time
        sd = traj.sd_at(times)
        sd = np.full((len(times), 3), cfg.default_sd_m) if sd is None else np.maximum(sd, cfg.min_sd_m)
        correlated = max(cfg.prior_correlation / cfg.knot_spacing, 1.0)
        share = _drift_share(sd, cfg.gnss_sd_m, cfg.drift_sd_m)
        prior_sd = sd * np.sqrt(correlated**share)[:, None]
        density = cfg.drift_curvature_sd
        if cfg.bend_from_reported_sd and model.runs[run_id].count >= 3:
            density, outages = bend_density(density, model.knot_metres(run_id), prior_sd, sd, cfg.gnss_sd_m)
            if outages:  # metrics.json: adjustment.bend_raised, per run the outages raised
                self._bends[run_id] = [{**o, "metres": [round(float(model.runs[run_id].knot_distance[o[k]]), 1)
                                                        for k in ("first_knot", "last_knot")]} for o in outages]
        if widening is None:
            return [obs.prior(model, run_id, prior_sd), obs.smoothness(model, run_id, density)]
        extra = covariance_at(times, traj.time, widening)
        biased = run_id in model.bias_first  # the model holds its bias knots (gnss_bias_correlation_m > 0)
        if biased:  # the widening's share that is a GNSS bias gets its own state; the rest is drift's
            gnss = gnss_share(1.0 - share, model.runs[run_id].knot_distance, cfg.gnss_bias_correlation_m,
                              np.trace(extra, axis1=1, axis2=2) > 0)
            gnss_bias, extra = gnss[:, None, None] * extra, share[:, None, None] * extra
        # where it is the drift's (its sd understated), the run's error is not the INS drift the
        # smoothness models either: it may bend more in the widened directions, as its sd grew
        # there but at most max_bend_widening times (a freer bend let a wrong weak pair at a
        # portal pull 0.8 m)
        relax = extra / np.mean(sd**2, axis=1)[:, None, None]
        room = (cfg.max_bend_widening**2 - 1.0) / np.maximum(np.trace(relax, axis1=1, axis2=2), 1e-12)
        relax = relax * np.minimum(1.0, room)[:, None, None]
        # a disagreement found by the sd check spans tens of metres: counted once per correlation length
        blocks = [obs.prior(model, run_id, prior_sd, extra * correlated),
                  obs.smoothness(model, run_id, density, relax)]
        if not biased:
            return blocks
        scale = self._bias_scale[run_id] = cfg.gnss_bias_sd_scale * bias_scale(gnss_bias)
        to_bias = bias_map(model, run_id, scale)
        bias_bend = obs.smoothness(model, run_id, density * cfg.max_bend_widening)
        return [on_drift(b, to_bias) for b in blocks] + [
            gauss_markov(model, run_id, cfg.gnss_bias_correlation_m), on_bias(bias_bend, to_bias)]

    def _ties(self, model: CorrectionModel, ties: Sequence[Ties]) -> obs.Block | None:
        parts = [t for t in ties if len(t) and t.run_a in model.runs and t.run_b in model.runs]
        if not parts:
            return None
        k, w = zip(*(obs.relative(model, t.run_a, t.time_a, t.run_b, t.time_b) for t in parts), strict=True)
        value = np.vstack([t.xyz_a - t.xyz_b for t in parts])
        weight = np.concatenate([t.weight for t in parts])
        labels = {"run_a": np.concatenate([[t.run_a] * len(t) for t in parts]),
                  "run_b": np.concatenate([[t.run_b] * len(t) for t in parts]),
                  "time_a": np.concatenate([t.time_a for t in parts]),
                  "time_b": np.concatenate([t.time_b for t in parts])}
        n = len(weight)
        return obs.assemble("tie", model.n_unknowns, np.vstack(k), np.vstack(w), value,
                            obs.isotropic(np.full(n, self.config.tie_sigma_m)), weight, labels=labels)

    def _offsets(self, model: CorrectionModel, offsets: Sequence[TileOffset],
                 trajectories: dict[str, Trajectory]) -> obs.Block | None:
        cfg = self.config
        use = [o for o in offsets if (cfg.use_weak_offsets or o.ok) and usable_offset(o, trajectories)]
        if not use:
            return None
        ka, wa, kb, wb = [], [], [], []
        for o in use:  # one pair each: a handful per tile pair, not per point
            k1, w1 = model.weights(o.run_a, np.array([o.info["time_a"]]))
            k2, w2 = model.weights(o.run_b, np.array([o.info["time_b"]]))
            ka.append(k1), wa.append(w1), kb.append(k2), wb.append(w2)
        knots = np.hstack([np.vstack(ka), np.vstack(kb)])
        w = np.hstack([-np.vstack(wa), np.vstack(wb)])
        cov = np.stack([offset_covariance(o) for o in use]) + cfg.offset_sd_floor_m ** 2 * np.eye(3)
        # ok pairs with ties enter through their ties; an ok pair without (resolved jointly along
        # the track) enters here in full, a weak pair in its constrained directions only
        return obs.assemble("offset", model.n_unknowns, knots, w, np.stack([o.d for o in use]),
                            obs.from_covariance(cov, cfg.max_weak_sd_m), labels=_pair_labels(use))

    def _drift_rates(self, model: CorrectionModel, offsets: Sequence[TileOffset],
                     trajectories: dict[str, Trajectory]) -> obs.Block | None:
        """``[c_b(t_b1) - c_a(t_a1)] - [c_b(t_b0) - c_a(t_a0)] = change`` along the track: how
        an unresolved pair's offset changes over its windows, whatever alias it sits on
        (:func:`railtraj.alongtrack._with_drift_rate`)."""
        if not (self.config.use_weak_offsets and self.config.use_drift_rates):
            return None
        use = [o for o in offsets if "drift_rate" in o.info and usable_offset(o, trajectories)]
        if not use:
            return None
        rates = [o.info["drift_rate"] for o in use]
        ends = [obs.relative(model, o.run_a, np.array(r["time_a"]), o.run_b, np.array(r["time_b"]))
                for o, r in zip(use, rates, strict=True)]
        knots = np.vstack([np.hstack([k[1], k[0]]) for k, _ in ends])  # the far end minus the near end
        w = np.vstack([np.hstack([w[1], -w[0]]) for _, w in ends])
        axis = np.array([r["axis"] for r in rates])
        sd = np.hypot([r["sd_m"] for r in rates], self.config.offset_sd_floor_m)
        whiten = np.zeros((len(use), 3, 3))
        whiten[:, 0, :] = axis / sd[:, None]  # the track direction only
        return obs.assemble("drift_rate", model.n_unknowns, knots, w, np.array([r["change"] for r in rates]),
                            whiten, labels=_pair_labels(use))

    def _control(self, model: CorrectionModel, control: ControlObservations | None,
                 trajectories: dict[str, Trajectory]) -> obs.Block | None:
        if control is None or not len(control):
            return None
        keep = np.isin(control.run_id, list(trajectories))
        c = control
        k = []
        for r in np.unique(c.run_id[keep]):
            m = keep & (c.run_id == r)
            kr, wr = model.weights(str(r), c.time[m])
            k.append((np.flatnonzero(m), kr, wr))
        order = np.concatenate([i for i, _, _ in k])
        knots, weights = np.vstack([kr for _, kr, _ in k]), np.vstack([wr for _, _, wr in k])
        labels = {"id": c.ids[order], "run_id": c.run_id[order], "time": c.time[order]}
        return obs.assemble("control", model.n_unknowns, knots, weights, (c.xyz - c.seen)[order],
                            obs.from_covariance(c.cov()[order]), labels=labels)

    def _weak_spans(self, model: CorrectionModel, run_id: str, traj: Trajectory, data: list[obs.Block]) -> list[dict]:
        """Stretches of a run longer than ``max_gap`` knots with no observation, where the
        trajectory's own sd is above ``weak_span_sd_m``: the correction rests on the prior there."""
        cfg = self.config
        rk = model.runs[run_id]
        times = [blk.labels[t][blk.labels[r] == run_id] for blk in data
                 for r, t in (("run_id", "time"), ("run_a", "time_a"), ("run_b", "time_b")) if r in blk.labels]
        seen = np.sort(rk.param_at(np.concatenate(times).astype(float))) if times else np.zeros(0)
        param = rk.epoch_param
        ends = np.concatenate([[param[0]], seen, [param[-1]]])
        gap = np.searchsorted(seen, param)
        lo, hi = ends[gap], ends[gap + 1]
        sd = traj.sd.max(axis=1) if traj.sd is not None else np.full(len(param), cfg.default_sd_m)
        weak = (hi - lo > cfg.max_gap * model.spacing) & (sd > cfg.weak_span_sd_m)
        spans = []
        for i0, last in stretches(weak):
            span = {"run_id": run_id, "time_from": float(traj.time[i0]), "time_to": float(traj.time[last]),
                    "length": float(param[last] - param[i0]), "max_input_sd_m": float(sd[i0:last + 1].max())}
            spans.append(span)
            log.warning("run %s, %.1f-%.1f s (%.0f %s): no tie, tile offset or control point; the correction "
                        "there is interpolated and rests on the trajectory's sd (up to %.2f m)", run_id,
                        span["time_from"], span["time_to"], span["length"], model.unit, span["max_input_sd_m"])
        return spans

    def _report(self, blocks: list[obs.Block], sol, model: CorrectionModel, spans: list[dict],
                seconds: float) -> dict:
        counts, rejected = {}, []
        for blk, g, r2 in zip(blocks, sol.gnc_weight, sol.chi2_per_obs, strict=True):
            if not blk.robust:
                continue
            bad = np.flatnonzero(g < 0.5)
            counts[blk.kind] = {"used": int(len(blk) - len(bad)), "rejected": int(len(bad))}
            for i in bad[:MAX_LISTED]:
                row = {k: (v[i].item() if hasattr(v[i], "item") else v[i]) for k, v in (blk.labels or {}).items()}
                rejected.append({"kind": blk.kind, **row, "whitened_residual": float(np.sqrt(r2[i]))})
        return {"optimizer": "spline", "config": asdict(self.config), "knots": model.n_knots,
                "observations": counts, "rejected": rejected, "gnc_iterations": sol.iterations,
                "bandwidth": sol.banded.bandwidth, "under_constrained": spans, "seconds": round(seconds, 3),
                "notes": []}


def _refuted_claim(run_id: str, time_s: np.ndarray, correction: np.ndarray, claimed: np.ndarray,
                   lifted: np.ndarray) -> dict:
    """Where a run's correction refuted its claimed sd (``lifted``: epochs, axes), for
    metrics.json, logged, and where it exceeded three claimed sd a warning and a note: the SBET's
    sd (or the sd check's widening) understates its error there, or the correction is wrong
    there; control would tell which."""
    ratio = np.where(lifted, np.abs(correction) / np.maximum(claimed, 1e-9), 0.0)
    i, k = np.unravel_index(np.argmax(ratio), ratio.shape)
    at = lifted.any(axis=1)
    found = {"epochs": int(at.sum()), "spans_s": time_spans(time_s, at),
             "worst_correction_m": float(abs(correction[i, k])), "claimed_sd_m": float(claimed[i, k]),
             "axis": "xyz"[k], "time_s": float(time_s[i])}
    found["note"] = (f"run {run_id}: the correction moved it {found['worst_correction_m']:.3f} m ({found['axis']}) "
                     f"at {found['time_s']:.1f} s, {ratio[i, k]:.1f} times the {found['claimed_sd_m']:.3f} m its "
                     f"sd claims; that claim is refuted at {format_spans(found['spans_s'])}, where its corrected "
                     "sd is at least half the correction (adjustment.claim_refuted)")
    # beyond 3 claimed sd no honest sd would have allowed it: a warning; between 2 and 3, information
    found["warned"] = bool(ratio[i, k] > 3.0)
    log.log(logging.WARNING if found["warned"] else logging.INFO, found["note"])
    return found


def _by_window_where_widened(offsets: Sequence[TileOffset], trajectories: dict[str, Trajectory],
                             widening: dict[str, np.ndarray], enabled: bool) -> tuple[list[TileOffset], dict]:
    """``offsets`` with each resolved pair without ties that lies where the sd check widened one
    of its runs read window by window (:func:`railtraj.adjust.offsets.resolved_by_window`), and
    how many pairs and windows were ({} when none).

    Only there: elsewhere the runs' GNSS and drift model hold the correction between pairs, and
    the windows' own scatter cost accuracy (docs/method.md, "Session 48")."""
    if not (enabled and widening):
        return list(offsets), {}
    out, pairs, windows = [], 0, 0
    for o in offsets:  # tile pairs: tens to hundreds, a handful of windows each
        parts = resolved_by_window(o)
        if len(parts) > 1 and _widened_at_any(parts, widening, trajectories):
            out += parts
            pairs, windows = pairs + 1, windows + len(parts)
        else:
            out.append(o)
    return out, ({"pairs": pairs, "windows": windows} if pairs else {})


def _widened_at_any(parts: list[TileOffset], widening: dict[str, np.ndarray],
                    trajectories: dict[str, Trajectory]) -> bool:
    """Whether either run of a pair's windows (``parts``) was widened where it measured any of them."""
    o, n = parts[0], len(parts)
    runs = np.array([o.run_a] * n + [o.run_b] * n)
    times = np.array([p.info["time_a"] for p in parts] + [p.info["time_b"] for p in parts], float)
    return bool(widened_at(widening, trajectories, runs, times).any())


def _pair_labels(offsets: Sequence[TileOffset]) -> dict[str, np.ndarray]:
    """Columns naming each tile pair's observation in the diagnostics: runs, tiles, times."""
    labels = {k: np.array([getattr(o, k) for o in offsets], dtype=object) for k in ("run_a", "run_b", "tile_a", "tile_b")}
    labels.update(time_a=np.array([o.info["time_a"] for o in offsets]), time_b=np.array([o.info["time_b"] for o in offsets]))
    return labels


def _drift_share(sd: np.ndarray, gnss_sd_m: float, drift_sd_m: float) -> np.ndarray:
    """Per knot, 0 where the reported horizontal sd is GNSS-like (<= ``gnss_sd_m``), 1 where it is
    the smoother's drift (>= ``drift_sd_m``), log-linear between.

    A smoother's error in a tunnel is one smooth bridge from portal to portal, so its prior counts
    once per ``prior_correlation``. Where GNSS is good its error is GNSS noise that decorrelates
    within metres: weakened like the bridge, the priors at a portal let a wrong weak tile pair
    there pull two runs 9 cm apart where their input agreed to 1 cm (simulated portal, survey
    start).
    """
    h = np.sqrt(np.mean(sd[:, :2] ** 2, axis=1))
    if not drift_sd_m > gnss_sd_m:
        return (h > gnss_sd_m).astype(float)
    return np.clip(np.log(np.maximum(h, 1e-9) / gnss_sd_m) / np.log(drift_sd_m / gnss_sd_m), 0.0, 1.0)


def _evaluate(model: CorrectionModel, run_id: str, times: np.ndarray, sol, cov_blocks) -> tuple[np.ndarray, np.ndarray]:
    """Correction (n, 3) and its posterior sd (n, 3) at ``times``."""
    k, w = model.weights(run_id, times)
    corr = np.zeros((len(times), 3))
    var = np.zeros((len(times), 3))
    for a in range(3):
        p, q = 3 * k[:, 0] + a, 3 * k[:, 1] + a
        corr[:, a] = w[:, 0] * sol.x[p] + w[:, 1] * sol.x[q]
        var[:, a] = (w[:, 0] ** 2 * sol.banded.covariance(p, p, cov_blocks)
                     + 2 * w[:, 0] * w[:, 1] * sol.banded.covariance(p, q, cov_blocks)
                     + w[:, 1] ** 2 * sol.banded.covariance(q, q, cov_blocks))
    return corr, np.sqrt(np.maximum(var, 0.0))


__all__ = ["SplineConfig", "SplineOptimizer"]


@hookimpl
def railtraj_register_stages(registry) -> None:
    registry.add("optimizer", "spline", SplineOptimizer, SplineConfig)
