"""Known-answer tests for the ``spline`` optimizer: a drifting inter-run offset, realistic tie
weights, clustered alias outliers, weak offsets and control points."""

from __future__ import annotations

import numpy as np
import pytest

from railtraj.data import ControlObservations, Ties, TileOffset, Trajectory
from railtraj.plugins import registry

TUNNEL = (50.0, 350.0)  # chainage of the tunnel: GNSS outside, drift inside
LENGTH = 400.0


def _envelope(s: np.ndarray) -> np.ndarray:
    u = np.clip((s - TUNNEL[0]) / (TUNNEL[1] - TUNNEL[0]), 0, 1)
    return (4 * u * (1 - u)) ** 1.5


def _error(s: np.ndarray, direction, wiggle: float, phase: float) -> np.ndarray:
    """A smooth INS drift along chainage ``s`` with a faster component (changes of rate)."""
    env = _envelope(s)
    slow = env[:, None] * np.asarray(direction)
    fast = (env * wiggle * np.sin(2 * np.pi * (s - TUNNEL[0]) / 100.0 + phase))[:, None] * [1.0, 0.8, 0.1]
    return slow + fast


class Run:
    """A run along a straight track (x = chainage), its true and drifting trajectory."""

    def __init__(self, run_id: str, speed: float, t0: float, direction, wiggle: float, phase: float,
                 reverse: bool = False) -> None:
        self.run_id, self.speed, self.t0, self.reverse = run_id, speed, t0, reverse
        self.time = t0 + np.arange(0, LENGTH / speed, 0.05)
        self.s = self.chainage(self.time)
        self.err_args = (direction, wiggle, phase)
        true = np.column_stack([530000 + self.s, np.full_like(self.s, 180000.0), np.full_like(self.s, 10.0)])
        sd = 0.015 + 0.5 * np.outer(_envelope(self.s), [1.0, 1.0, 0.2])
        rpy = np.tile([0.0, 0.0, 270.0 if reverse else 90.0], (len(self.time), 1))
        self.true = Trajectory(self.time, true, rpy, sd, run_id=run_id)
        self.traj = Trajectory(self.time, true + self.error(self.s), rpy, sd, run_id=run_id)

    def chainage(self, t: np.ndarray) -> np.ndarray:
        s = (t - self.t0) * self.speed
        return LENGTH - s if self.reverse else s

    def time_at(self, s: np.ndarray) -> np.ndarray:
        return self.t0 + ((LENGTH - s) if self.reverse else s) / self.speed

    def error(self, s: np.ndarray) -> np.ndarray:
        return _error(s, *self.err_args)


def _pair_ties(a: Run, b: Run, rng: np.random.Generator, n_per_pair: int = 20, noise: float = 0.002):
    """Ties in 25 m tile pairs through the tunnel, weight 1/n per pair (as the matchers give)."""
    parts = []
    for s0 in np.arange(TUNNEL[0] + 5, TUNNEL[1] - 5, 25.0):
        s = np.sort(rng.uniform(s0, s0 + 25, n_per_pair))
        feature = np.column_stack([530000 + s, 180000 + rng.uniform(-3, 3, len(s)), 10 + rng.uniform(-1, 4, len(s))])
        xa = feature + a.error(s) + noise * rng.standard_normal(feature.shape)
        xb = feature + b.error(s) + noise * rng.standard_normal(feature.shape)
        parts.append(Ties(a.run_id, b.run_id, a.time_at(s), b.time_at(s), xa, xb, np.full(len(s), 1.0 / len(s))))
    return parts


def _runs(speed_a: float, speed_b: float) -> tuple[Run, Run]:
    a = Run("run_a", speed_a, 300000.0, (0.8, -0.7, 0.15), 0.03, 0.0)
    b = Run("run_b", speed_b, 300600.0, (-0.8, 0.8, -0.12), 0.05, 1.3, reverse=True)
    return a, b


def _inter_run_error(out: dict[str, Trajectory], a: Run, b: Run, s: np.ndarray) -> np.ndarray:
    """(n, 3) disagreement of the corrected runs at chainage ``s`` (zero when they agree)."""
    ea = out["run_a"].interpolate(a.time_at(s))[0] - a.true.interpolate(a.time_at(s))[0]
    eb = out["run_b"].interpolate(b.time_at(s))[0] - b.true.interpolate(b.time_at(s))[0]
    return ea - eb


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(x ** 2, axis=1))))


def _optimize(a: Run, b: Run, ties, offsets=(), control=None, **options):
    opt = registry().create("optimizer", "spline", options)
    out = opt.optimize({"run_a": a.traj, "run_b": b.traj}, Ties.concat(list(ties)), list(offsets), control=control)
    return out, opt.diagnostics


@pytest.mark.parametrize("speed", [10.0, 20.0])
def test_recovers_a_drifting_offset_to_millimetres(speed):
    a, b = _runs(speed, speed * 1.3)
    s = np.linspace(TUNNEL[0] + 10, TUNNEL[1] - 10, 2000)
    rate = np.linalg.norm(np.gradient(a.error(s) - b.error(s), s, axis=0), axis=1).max()
    assert rate > 0.015  # the offset between the runs changes by over 15 mm per metre
    out, diag = _optimize(a, b, _pair_ties(a, b, np.random.default_rng(1)))
    before = _rms(a.error(s) - b.error(s))
    after = _rms(_inter_run_error(out, a, b, s))
    assert before > 0.5
    assert after < 0.003, f"inter-run RMS {after * 1000:.1f} mm"
    assert diag["observations"]["tie"]["rejected"] == 0


def test_absolute_error_follows_the_sd_weighted_average_of_the_runs():
    a, b = _runs(10.0, 13.0)
    out, _ = _optimize(a, b, _pair_ties(a, b, np.random.default_rng(2)))
    s = np.linspace(TUNNEL[0] + 10, TUNNEL[1] - 10, 500)
    sa, sb = a.traj.sd_at(a.time_at(s)), b.traj.sd_at(b.time_at(s))
    wa, wb = 1 / sa ** 2, 1 / sb ** 2
    bound = (wa * a.error(s) + wb * b.error(s)) / (wa + wb)  # best absolute error relative ties allow
    got = out["run_a"].interpolate(a.time_at(s))[0] - a.true.interpolate(a.time_at(s))[0]
    assert np.sqrt(np.mean(np.sum((got - bound) ** 2, axis=1))) < 0.01
    # the posterior sd is honest: the runs' common error is within 3 sd almost everywhere
    sd = out["run_a"].sd_at(a.time_at(s))
    assert np.mean(np.abs(got) < 3 * sd + 0.005) > 0.95
    # ... and never above the input's (information only narrows it): GNSS-good ends keep theirs
    for run in (a, b):
        assert np.all(out[run.run_id].sd <= run.traj.sd + 1e-12)
        assert np.max(out[run.run_id].sd[run.s < TUNNEL[0] - 10]) <= 0.015 + 1e-12


def _with_wrong_ties(clean, rng, share: float = 0.3):
    """The same ties with ``share`` of them replaced by wrong matches: rib (1.5 m) and combined
    (3.0 m) aliases along the track and random mismatches, scattered over every tile pair."""
    bad = []
    for t in clean:
        xb = t.xyz_b.copy()
        wrong = rng.permutation(len(t))[: int(round(share * len(t)))]
        kind = np.arange(len(wrong)) % 3
        xb[wrong[kind == 0], 0] += 1.5
        xb[wrong[kind == 1], 0] -= 3.0
        xb[wrong[kind == 2]] += rng.normal(0, 0.3, ((kind == 2).sum(), 3)) + [0.2, 0.1, 0.0]
        bad.append(Ties(t.run_a, t.run_b, t.time_a, t.time_b, t.xyz_a, xb, t.weight))
    return bad


@pytest.mark.parametrize("speed", [10.0, 20.0])
def test_thirty_percent_wrong_ties_move_the_result_less_than_5_mm(speed):
    a, b = _runs(speed, speed * 1.3)
    rng = np.random.default_rng(3)
    clean = _pair_ties(a, b, rng)
    ref, _ = _optimize(a, b, clean)
    out, diag = _optimize(a, b, _with_wrong_ties(clean, rng))
    s = np.linspace(TUNNEL[0] + 10, TUNNEL[1] - 10, 2000)
    for r, run in (("run_a", a), ("run_b", b)):
        t = run.time_at(s)
        moved = out[r].interpolate(t)[0] - ref[r].interpolate(t)[0]
        assert np.abs(moved).max() < 0.005, f"{r} moved {np.abs(moved).max() * 1000:.1f} mm"
    n_wrong = sum(int(round(0.3 * len(t))) for t in clean)
    assert diag["observations"]["tie"]["rejected"] >= 0.95 * n_wrong
    assert diag["rejected"] and diag["rejected"][0]["kind"] == "tie"


def test_a_tile_pair_locked_on_an_alias_is_rejected_whole():
    a, b = _runs(10.0, 13.0)
    clean = _pair_ties(a, b, np.random.default_rng(5))
    bad = list(clean)
    k = len(bad) // 2
    t = bad[k]
    bad[k] = Ties(t.run_a, t.run_b, t.time_a, t.time_b, t.xyz_a, t.xyz_b + [3.0, 0.0, 0.0], t.weight)
    out, diag = _optimize(a, b, bad)
    assert diag["observations"]["tie"]["rejected"] == len(t)
    s = np.linspace(t.time_a.min(), t.time_a.max(), 50)
    s = (s - a.t0) * a.speed
    assert np.abs(_inter_run_error(out, a, b, s)).max() < 0.04  # bridged by its neighbours (25 m gap)


def test_weak_offsets_constrain_only_across_and_up():
    a, b = _runs(10.0, 10.0)
    offsets = []
    for s in np.arange(TUNNEL[0] + 10, TUNNEL[1] - 10, 25.0):
        d = a.error(np.array([s]))[0] - b.error(np.array([s]))[0]
        d_alias = d + [1.5, 0, 0]  # along-track (x) is off by a rib period
        cov = np.diag([2.0 ** 2, 0.004 ** 2, 0.004 ** 2])
        offsets.append(TileOffset("run_a", "run_b", f"t{s}", f"t{s}", d=d_alias, cov=cov, status="ambiguous",
                                  info={"time_a": float(a.time_at(np.array([s]))[0]),
                                        "time_b": float(b.time_at(np.array([s]))[0])}))
    out, diag = _optimize(a, b, [], offsets)
    s = np.linspace(TUNNEL[0] + 20, TUNNEL[1] - 20, 500)
    err = _inter_run_error(out, a, b, s)
    before = a.error(s) - b.error(s)
    assert np.sqrt(np.mean(err[:, 1:] ** 2)) < 0.02 < np.sqrt(np.mean(before[:, 1:] ** 2))
    assert np.abs(err[:, 0] - before[:, 0]).max() < 0.05  # along: the alias is not believed
    assert diag["observations"]["offset"]["used"] == len(offsets)


@pytest.mark.parametrize("use_drift_rates", [True, False])
def test_an_unresolved_pairs_drift_rate_carries_the_along_track_offset(use_drift_rates):
    """Weak pairs every 25 m, each on an unknown alias, each with its curve's change of offset
    over 20 m, 3 mm/m off (sd): from the portals, the rates alone carry the runs' along-track
    offset through the tunnel (1.6 m at most) to a quarter (a tenth with exact rates: the rest
    is their noise, summed); without them it is left as it was."""
    a, b = _runs(10.0, 10.0)
    rng = np.random.default_rng(3)
    offsets, half, sd = [], 10.0, 0.003 * 20.0
    for s in np.arange(TUNNEL[0] + 10, TUNNEL[1] - 10, 25.0):
        d = lambda x: a.error(np.array([x]))[0] - b.error(np.array([x]))[0]  # noqa: B023, E731
        change = d(s + half) - d(s - half) + [rng.normal(0.0, sd), 0.0, 0.0]
        rate = {"time_a": a.time_at(np.array([s - half, s + half])).tolist(),
                "time_b": b.time_at(np.array([s - half, s + half])).tolist(),
                "change": change.tolist(), "axis": [1.0, 0.0, 0.0], "sd_m": sd}
        offsets.append(TileOffset("run_a", "run_b", f"t{s}", f"t{s}", d=d(s) + [1.5, 0, 0],
                                  cov=np.diag([2.0 ** 2, 0.004 ** 2, 0.004 ** 2]), status="ambiguous",
                                  info={"time_a": float(a.time_at(np.array([s]))[0]),
                                        "time_b": float(b.time_at(np.array([s]))[0]), "drift_rate": rate}))
    out, diag = _optimize(a, b, [], offsets, use_drift_rates=use_drift_rates)
    s = np.linspace(TUNNEL[0] + 20, TUNNEL[1] - 20, 500)
    along, before = _inter_run_error(out, a, b, s)[:, 0], (a.error(s) - b.error(s))[:, 0]
    assert np.abs(before).max() > 1.0
    if use_drift_rates:
        assert np.sqrt(np.mean(along**2)) < 0.25 * np.sqrt(np.mean(before**2))
        assert diag["observations"]["drift_rate"]["used"] == len(offsets)
    else:
        assert np.sqrt(np.mean(along**2)) > 0.8 * np.sqrt(np.mean(before**2))
        assert "drift_rate" not in diag["observations"]

def test_a_pair_the_adjustment_rejects_is_reported_rejected():
    """Coarse pairs every 12.5 m, one of them 0.86 m off across the track with a 9 mm sd (a
    matcher's wrong peak the along-track chain kept, held-out mixed 5015): the adjustment leaves
    it out and offsets.csv must not call it coarse; the others keep their status."""
    from railtraj.adjust.offsets import REJECTED, with_rejections

    a, b = _runs(10.0, 12.0)
    offsets = []
    for k, s in enumerate(np.arange(TUNNEL[0] + 10, TUNNEL[1] - 10, 12.5)):
        d = a.error(np.array([s]))[0] - b.error(np.array([s]))[0] + ([0.0, 0.86, 0.0] if k == 10 else 0.0)
        offsets.append(TileOffset("run_a", "run_b", f"t{k}", f"t{k}", d=d, cov=np.diag([0.02, 0.009, 0.007]) ** 2,
                                  status="coarse", info={"time_a": float(a.time_at(np.array([s]))[0]),
                                                         "time_b": float(b.time_at(np.array([s]))[0])}))
    out, diag = _optimize(a, b, [], offsets)
    marked, note = with_rejections(offsets, diag)
    assert [o.status for o in marked] == ["coarse"] * 10 + [REJECTED] + ["coarse"] * (len(offsets) - 11)
    assert marked[10].info["rejected"]["status_before"] == "coarse" and "1 tile pair(s)" in note
    assert with_rejections(offsets, {}) == (offsets, "")


def test_control_points_pin_the_absolute_position():
    a, b = _runs(10.0, 13.0)
    rng = np.random.default_rng(4)
    ties = _pair_ties(a, b, rng)
    s_cp = np.arange(TUNNEL[0] + 25, TUNNEL[1], 50.0)  # a control point every 50 m
    ids, runs, times, seen, xyz = [], [], [], [], []
    for run in (a, b):
        t = run.time_at(s_cp)
        true = np.column_stack([530000 + s_cp, np.full_like(s_cp, 180002.0), np.full_like(s_cp, 11.5)])
        ids += [f"CP{k}" for k in range(len(s_cp))]
        runs += [run.run_id] * len(s_cp)
        times.append(t)
        seen.append(true + run.error(s_cp))
        xyz.append(true + rng.normal(0, 0.003, true.shape))
    n = len(ids)
    control = ControlObservations(ids, runs, np.concatenate(times), np.vstack(seen), np.vstack(xyz),
                                  np.full((n, 3), 0.003), np.full((n, 3), 0.005), ["picked"] * n)
    without, _ = _optimize(a, b, ties)
    out, diag = _optimize(a, b, ties, control=control)
    s = np.linspace(TUNNEL[0] + 10, TUNNEL[1] - 10, 1000)
    abs_without = _rms(without["run_a"].interpolate(a.time_at(s))[0] - a.true.interpolate(a.time_at(s))[0])
    abs_with = _rms(out["run_a"].interpolate(a.time_at(s))[0] - a.true.interpolate(a.time_at(s))[0])
    assert abs_with < 0.025 < abs_without
    assert diag["observations"]["control"] == {"used": n, "rejected": 0}


def test_no_observations_leaves_trajectories_unchanged_with_a_note():
    a, b = _runs(10.0, 10.0)
    out, diag = _optimize(a, b, [])
    assert out["run_a"] is a.traj and diag["notes"]


def test_a_wrong_weak_pair_where_gnss_is_good_does_not_pull_the_runs_apart():
    """At a portal both runs report 1.5 cm and agree. A wrong degenerate pair there says they are
    0.15 m apart across the track: weakened like the tunnel's drift (one error per 500 m), the
    GNSS priors let it pull the runs apart; counted per knot (``gnss_sd_m``) they hold."""
    a, b = _runs(10.0, 13.0)
    s_wrong = TUNNEL[0] - 30.0
    wrong = TileOffset("run_a", "run_b", "x", "y", d=np.array([0.0, 0.15, 0.0]),
                       cov=np.diag([50.0**2, 0.02**2, 0.02**2]), status="degenerate",
                       info={"time_a": float(a.time_at(np.array([s_wrong]))[0]),
                             "time_b": float(b.time_at(np.array([s_wrong]))[0]), "piecewise": {"axis": [1.0, 0.0, 0.0]}})
    ties = _pair_ties(a, b, np.random.default_rng(5))
    s = np.linspace(s_wrong - 10, s_wrong + 10, 50)
    apart = {}
    for label, options in (("as drift", {"gnss_sd_m": 0.0, "drift_sd_m": 0.0}), ("per knot", {})):
        out, _ = _optimize(a, b, ties, [wrong], **options)
        apart[label] = float(np.abs(_inter_run_error(out, a, b, s)[:, 1]).max())
    assert apart["per knot"] < 0.01 and apart["as drift"] > 2 * apart["per knot"], apart


def test_where_the_correction_refutes_the_claimed_sd_the_reported_sd_covers_it():
    """A run reports 0.2 m over its first 40 m (a widened claim), where nothing observes it; from
    80 m on it drifts 2 cm a metre against a GNSS-held run. The correction carries that rate back
    to the start, 0.74 m, where the input was right. Capped at the claim (information only
    narrows it) the reported sd says 0.2 m there: 3.7 sd. A correction beyond two claimed sd
    refutes the claim; the reported sd is then at least half the correction (or the posterior)."""
    time = 300000.0 + np.arange(0.0, LENGTH / 10.0, 0.05)
    s = (time - time[0]) * 10.0
    true = np.column_stack([530000 + s, np.full_like(s, 180000.0), np.full_like(s, 10.0)])
    rpy = np.tile([0.0, 0.0, 90.0], (len(s), 1))
    drift = np.column_stack([np.zeros_like(s), 0.02 * np.clip(s - 40.0, 0.0, None), np.zeros_like(s)])
    sd_a = np.where(s[:, None] < 40.0, 0.2, 0.015 + 0.02 * (s[:, None] - 40.0)) * [1.0, 1.0, 0.2]
    trajs = {"run_a": Trajectory(time, true + drift, rpy, sd_a, run_id="run_a"),
             "run_b": Trajectory(time + 600.0, true, rpy, np.full((len(s), 3), 0.015), run_id="run_b")}
    ties = []
    for s0 in np.arange(80.0, LENGTH - 25.0, 25.0):
        at = np.linspace(s0, s0 + 20.0, 10)
        i = np.searchsorted(s, at)
        ties.append(Ties("run_a", "run_b", time[i], time[i] + 600.0, true[i] + drift[i], true[i],
                         np.full(len(i), 0.1)))
    out, found = {}, {}
    for ratio in (0.0, 2.0):
        optimizer = registry().create("optimizer", "spline", {"refuted_claim_ratio": ratio})
        out[ratio] = optimizer.optimize(trajs, Ties.concat(ties), [])["run_a"]
        found[ratio] = optimizer.diagnostics.get("claim_refuted", {})
    start = s < 10.0
    error = np.abs(out[2.0].xyz[start, 1] - 180000.0)
    assert error.max() > 0.5 and np.allclose(out[0.0].xyz, out[2.0].xyz)
    z = {ratio: float((error / o.sd[start, 1]).max()) for ratio, o in out.items()}
    assert z[0.0] > 3.0 and z[2.0] < 3.0, z
    # where the correction stayed within the claim nothing changed
    refuted = np.any(np.abs(out[0.0].xyz - trajs["run_a"].xyz) > 2.0 * sd_a, axis=1)
    assert np.allclose(out[0.0].sd[~refuted], out[2.0].sd[~refuted]) and refuted.mean() < 0.3
    # ... and metrics.json says where the claim was refuted, and for which run
    assert not found[0.0] and set(found[2.0]) == {"run_a"} and found[2.0]["run_a"]["warned"]
    spans = np.array(found[2.0]["run_a"]["spans_s"]) - time[0]
    assert spans.min() < 1.0 and spans.max() * 10.0 < 80.0, spans  # seconds at 10 m/s: before the ties


def test_past_the_last_tie_a_gnss_bias_fades_back_to_the_runs_gnss():
    """Run b leaves a tunnel at 300 m drifting along the track (its smoother's bridge, back to zero
    at the portal); its GNSS is biased by 0.3 m from 285 m, converging from 320 m over 20 m, while
    it reports 1.5 cm. The last ties are at 315 m (nothing to match beyond); the sd check widened
    run b from 275 m to the end. As a drift that may bend twice as freely, the correction holds
    what the last ties saw; as a Gauss-Markov bias beside the drift it fades back towards the
    run's GNSS, which is right again, and the reported sd covers what is left either way."""
    time = 300000.0 + np.arange(0.0, LENGTH / 10.0, 0.05)
    s = (time - time[0]) * 10.0
    true = np.column_stack([530000 + s, np.full_like(s, 180000.0), np.full_like(s, 10.0)])
    rpy = np.tile([0.0, 0.0, 90.0], (len(s), 1))
    bridge = np.where((s > 100.0) & (s < 300.0), np.sin(np.pi * (s - 100.0) / 200.0), 0.0)
    bias = 0.3 * np.where(s < 320.0, np.interp(s, [285.0, 305.0], [0.0, 1.0]), np.exp(-(s - 320.0) / 20.0))
    error = np.outer(0.6 * bridge + bias, [1.0, 0.0, 0.0])
    trajs = {"run_a": Trajectory(time, true, rpy, np.full((len(s), 3), 0.015), run_id="run_a"),
             "run_b": Trajectory(time + 600.0, true + error, rpy, (0.015 + 0.4 * bridge)[:, None] * [1.0, 1.0, 0.2],
                                 run_id="run_b")}
    ties = []
    for s0 in np.arange(20.0, 301.0, 25.0):
        i = np.searchsorted(s, np.linspace(s0, s0 + 20.0, 10))
        ties.append(Ties("run_a", "run_b", time[i], time[i] + 600.0, true[i], true[i] + error[i], np.full(len(i), 0.1)))
    widened = np.zeros((len(s), 3, 3))
    widened[s > 275.0, 0, 0] = 0.3**2  # as the sd check would: the disagreement, to the end
    out = {}
    for label, correlation in (("freer drift", 0.0), ("bias state", 25.0)):
        optimizer = registry().create("optimizer", "spline", {"gnss_bias_correlation_m": correlation})
        out[label] = optimizer.optimize(trajs, Ties.concat(ties), [], widening={"run_b": widened})["run_b"]
    error = {k: np.abs(o.xyz[:, 0] - true[:, 0]) for k, o in out.items()}
    seen, past = s < 315.0, s > 315.0
    assert all(e[seen].max() < 0.025 for e in error.values()), {k: e[seen].max() for k, e in error.items()}
    # at the survey's end, 80 m past the last tie: what is left of the worst error past it
    left = {k: float(e[s > 395.0].max() / e[past].max()) for k, e in error.items()}
    assert left["bias state"] < 0.4 and left["freer drift"] > 0.45, left
    assert error["bias state"][past].max() < error["freer drift"][past].max()
    assert all((error[k][past] / out[k].sd[past, 0]).max() < 3.0 for k in out)
    # metrics.json says where the bias was: run b's, about 0.3 m along x, from the portal on
    found = optimizer.diagnostics["gnss_bias"]
    assert set(found) == {"run_b"}, found
    peak = found["run_b"]
    assert 0.15 < peak["largest_m"][0] < 0.45 and 285.0 < (peak["time_s"] - time[0] - 600.0) * 10.0 < 340.0, peak
    assert 20.0 < peak["metres_above_2cm"] < 125.0, peak
