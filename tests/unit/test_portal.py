"""A portal's GNSS, which runs may share a bias in, keeps an sd in the corrected sd."""

from __future__ import annotations

import numpy as np

from railtraj.data import Trajectory
from railtraj.portal import PortalOptions, portal_weight, with_portal_sd
from railtraj.sim.drift import DriftSpec, Multipath, drift

ENTRY, EXIT = 150.0, 450.0  # the tunnel, in metres along the runs


def _runs_biased_alike() -> tuple[dict[str, Trajectory], dict[str, Trajectory]]:
    """Two runs 10 m/s east through a 300 m tunnel, ten minutes apart, both with the simulator's
    multipath bias (0.3, -0.25, 0.1) m at the entry portal: the truth and what they report."""
    truth, reported = {}, {}
    for k, run in enumerate(("run_a", "run_b")):
        t = 300000.0 + 600.0 * k + np.arange(6001) / 100.0
        s = 10.0 * (t - t[0])
        xyz = np.column_stack([530000.0 + s, np.full(len(t), 180000.0), np.full(len(t), 10.0)])
        rpy = np.column_stack([np.zeros(len(t)), np.zeros(len(t)), np.full(len(t), 90.0)])
        truth[run] = Trajectory(t, xyz, rpy, run_id=run)
        spec = DriftSpec(multipath=(Multipath(run, portal=0, bias=(0.3, -0.25, 0.1)),))
        reported[run], _ = drift(truth[run], s, (s < ENTRY) | (s > EXIT), spec, np.random.default_rng(k))
    return truth, reported


def _worst_z(truth: Trajectory, traj: Trajectory) -> float:
    """The largest horizontal error in horizontal sd."""
    return float((np.linalg.norm((traj.xyz - truth.xyz)[:, :2], axis=1) / np.linalg.norm(traj.sd[:, :2], axis=1)).max())


def test_a_bias_the_runs_share_at_a_portal_stays_within_three_corrected_sd():
    """Nothing relative shows a bias both runs share: where they agree the correction keeps it, so
    only the sd can say it. Without the portal sd both are over 10 sd off at the entry; with it,
    within 3 sd, and far from the portals their sd is as reported."""
    truth, reported = _runs_biased_alike()
    assert min(_worst_z(truth[r], reported[r]) for r in reported) > 10
    out, metrics, note = with_portal_sd(reported, reported, PortalOptions())
    options = PortalOptions()
    for run in reported:
        assert _worst_z(truth[run], out[run]) < 3
        s = reported[run].xyz[:, 0] - 530000.0
        far = np.minimum(np.abs(s - ENTRY), np.abs(s - EXIT)) > options.reach_m + options.fade_m + 15
        np.testing.assert_array_equal(out[run].sd[far], reported[run].sd[far])
        near = np.abs(s - ENTRY) < options.reach_m - 15
        assert (out[run].sd[near] >= options.sd_m).all()
        np.testing.assert_array_equal(out[run].xyz, reported[run].xyz)
        assert metrics["runs"][run]["portals"] == 2
    assert "2 crossings of 2 run(s)" not in note and "4 crossings of 2 run(s)" in note


def test_control_at_a_portal_settles_it_and_sd_m_0_turns_it_off():
    truth, reported = _runs_biased_alike()
    traj, options = reported["run_a"], PortalOptions()
    s = traj.xyz[:, 0] - 530000.0
    weight = portal_weight(traj, options, control_at=np.array([[530000.0 + ENTRY, 180000.0]]))
    assert (weight[np.abs(s - ENTRY) < options.reach_m] == 0).all()
    assert (weight[np.abs(s - EXIT) < options.reach_m - 15] == 1).all()
    out, metrics, note = with_portal_sd(reported, reported, PortalOptions(sd_m=0.0))
    assert out is reported and note == "" and metrics == {"sd_m": 0.0}
