"""The drift's bend density is raised per outage until the model's prior reaches the run's own
sd, so that relative observations never claim an absolute precision nobody measured."""

from __future__ import annotations

import numpy as np
import pytest

from railtraj.adjust.stiffness import _prior_marginal_sd, bend_density
from railtraj.data import Ties, Trajectory
from railtraj.plugins import registry

PEAK_SD = 0.76  # per horizontal axis at the outage's middle, as a smoother reports after ~100 m
GNSS_SD = 0.015


def _reported(length: float, tunnel: float, spacing: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """Chainage and reported sd (n, 3) of a run with GNSS ``(length - tunnel) / 2`` m either side."""
    s = np.arange(0.0, length + 1e-9, spacing)
    u = np.clip((s - (length - tunnel) / 2) / tunnel, 0.0, 1.0)
    env = (4 * u * (1 - u)) ** 1.5
    return s, GNSS_SD + np.outer(env, [PEAK_SD, PEAK_SD, 0.3 * PEAK_SD])


@pytest.mark.parametrize("tunnel", [120.0, 200.0])
def test_a_short_outage_bends_until_the_prior_reaches_the_reported_sd(tunnel):
    s, sd = _reported(tunnel + 60.0, tunnel)
    prior = sd * np.where(sd[:, :1] > 0.1, 10.0, 1.0)  # the priors weakened for correlation
    base = 0.0016
    metres = np.diff(s)
    span = (0.5 * (metres[:-1] + metres[1:])) ** 1.5
    peak = int(np.argmax(sd[:, 0]))
    before = _prior_marginal_sd(np.full(len(s) - 2, base) * span, prior[:, 0])[peak]
    assert before < 0.8 * PEAK_SD  # the default bend claims more than the run reports
    density, outages = bend_density(base, metres, prior, sd, gnss_sd_m=0.03)
    after = _prior_marginal_sd(density[:, 0] * span, prior[:, 0])[peak]
    assert PEAK_SD / 1.03 <= after <= 1.5 * PEAK_SD
    assert len(outages) == 1 and outages[0]["factor"][0] > 1.2
    assert np.all(density >= base)  # never stiffer than the default
    gnss = sd[1:-1, 0] < 0.03
    assert np.all(density[gnss] == base)  # outside the outage the default stands


def test_a_long_outage_keeps_the_default_bend():
    s, sd = _reported(800.0, 600.0)
    prior = sd * np.where(sd[:, :1] > 0.1, 10.0, 1.0)
    density, outages = bend_density(0.0016, np.diff(s), prior, sd, gnss_sd_m=0.03)
    assert outages == [] and np.all(density == 0.0016)


def _run(run_id: str, amplitude: float, tunnel: float, t0: float) -> tuple[Trajectory, Trajectory]:
    """True and drifting trajectory along x at 10 m/s; the drift is ``amplitude`` x the envelope
    of the reported sd (a drift as large as the run says it may be)."""
    length = tunnel + 60.0
    time = t0 + np.arange(0.0, length / 10.0, 0.05)
    s = (time - t0) * 10.0
    u = np.clip((s - 30.0) / tunnel, 0.0, 1.0)
    env = (4 * u * (1 - u)) ** 1.5
    sd = GNSS_SD + np.outer(env, [PEAK_SD, PEAK_SD, 0.3 * PEAK_SD])
    true = np.column_stack([530000 + s, np.full_like(s, 180000.0), np.full_like(s, 10.0)])
    drift = np.outer(env, [amplitude * PEAK_SD, -amplitude * PEAK_SD, 0.0])
    rpy = np.tile([0.0, 0.0, 90.0], (len(time), 1))
    return Trajectory(time, true, rpy, sd, run_id=run_id), Trajectory(time, true + drift, rpy, sd, run_id=run_id)


def test_relative_ties_do_not_claim_an_absolute_precision_below_the_averaging_bound():
    """Two runs drifting the same way by 1.2 reported sd over a 150 m outage, tied perfectly
    every 2 m. Relative ties cannot see the common error: the best absolute answer is the runs'
    average, 1.2 sd off with sd 1/sqrt(2) of each. The corrected sd must cover that error."""
    tunnel = 150.0
    (ta, a), (tb, b) = _run("run_a", 1.2, tunnel, 1000.0), _run("run_b", 1.2, tunnel, 2000.0)
    s = np.arange(32.0, 30.0 + tunnel - 2, 2.0)
    ties = Ties("run_a", "run_b", 1000.0 + s / 10, 2000.0 + s / 10, a.interpolate(1000.0 + s / 10)[0],
                b.interpolate(2000.0 + s / 10)[0], np.ones(len(s)))
    for raise_bend, honest in ((True, True), (False, False)):
        opt = registry().create("optimizer", "spline", {"bend_from_reported_sd": raise_bend})
        out = opt.optimize({"run_a": a, "run_b": b}, [ties], [])
        z = []
        for run, truth in (("run_a", ta), ("run_b", tb)):
            err = np.linalg.norm(out[run].xyz[:, :2] - truth.xyz[:, :2], axis=1)
            z.append(err / np.linalg.norm(out[run].sd[:, :2], axis=1))
        assert (np.max(z) < 3.0) == honest, f"bend_from_reported_sd={raise_bend}: worst z {np.max(z):.2f}"
        raised = opt.diagnostics["bend_raised"]
        assert sorted(raised) == (["run_a", "run_b"] if raise_bend else [])
