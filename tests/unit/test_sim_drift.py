"""The GNSS/INS error model: zero at portals, growing inside, hazards the sd does not show."""

from __future__ import annotations

import numpy as np
import pytest

from railtraj.data import Trajectory
from railtraj.sim.drift import DriftSpec, Multipath, drift, envelope, outages


def _straight(n: int = 6001, rate: float = 100.0, run_id: str = "r") -> tuple[Trajectory, np.ndarray, np.ndarray]:
    """10 m/s east for 60 s; sky for the first and last 100 m (a 400 m tunnel between)."""
    t = 300000.0 + np.arange(n) / rate
    s = 10.0 * (t - t[0])
    xyz = np.column_stack([530000.0 + s, np.full(n, 180000.0), np.full(n, 10.0)])
    rpy = np.column_stack([np.zeros(n), np.zeros(n), np.full(n, 90.0)])
    return Trajectory(t, xyz, rpy, run_id=run_id), s, (s < 100.0) | (s > 500.0)


def test_outages_and_envelope():
    assert outages(np.array([1, 1, 0, 0, 1, 0], bool)) == [(2, 4), (5, 6)]
    assert outages(np.ones(4, bool)) == []
    env = envelope(101)
    assert env[0] < 0.01 and env[-1] < 0.01 and env.max() == pytest.approx(1.0, abs=1e-3)
    assert np.argmax(env) == 50
    grow = envelope(50, open_start=True, open_end=False)
    assert (np.diff(grow) > 0).all()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_drift_is_zero_outside_and_peaks_inside(seed):
    true, s, sky = _straight()
    spec = DriftSpec(max_horizontal=1.5, max_vertical=0.2)
    est, info = drift(true, s, sky, spec, np.random.default_rng(seed))
    err = est.xyz - true.xyz
    h = np.linalg.norm(err[:, :2], axis=1)
    assert h[sky].max() < 0.05 and np.abs(err[sky, 2]).max() < 0.06    # small noise only
    assert spec.min_fraction * 1.5 - 1e-9 <= h.max() <= 1.5 + 1e-9
    assert spec.min_fraction * 0.2 - 1e-9 <= np.abs(err[:, 2]).max() <= 0.2 + 1e-9
    peak = np.argmax(h)
    assert 150.0 < s[peak] < 450.0                                      # near the middle
    # drift is smooth: no jumps between 100 Hz epochs inside the tunnel
    assert np.abs(np.diff(err[~sky], axis=0)).max() < 0.01
    # reported sd: small outside, growing to sd_scale * max in the middle
    assert est.sd[sky].max() <= max(spec.sd_open) + 1e-9
    assert est.sd[:, 0].max() == pytest.approx(spec.sd_scale * 1.5 + spec.sd_open[0], rel=0.01)
    assert est.sd[np.argmin(np.abs(s - 300)), 0] > 10 * est.sd[0, 0]
    assert len(info["outages"]) == 1 and info["max_error_horizontal"] == pytest.approx(h.max())
    np.testing.assert_array_equal(est.rpy, true.rpy)


def test_same_seed_same_drift_other_seed_other_drift():
    true, s, sky = _straight()
    a = drift(true, s, sky, DriftSpec(), np.random.default_rng(3))[0]
    b = drift(true, s, sky, DriftSpec(), np.random.default_rng(3))[0]
    c = drift(true, s, sky, DriftSpec(), np.random.default_rng(4))[0]
    np.testing.assert_array_equal(a.xyz, b.xyz)
    assert np.abs(a.xyz - c.xyz).max() > 0.1


def test_multipath_bias_is_not_in_the_reported_sd():
    true, s, sky = _straight()
    bias = (0.3, -0.2, 0.1)
    spec = DriftSpec(multipath=(Multipath("r", portal=0, bias=bias, ramp=40.0),))
    plain, _ = drift(true, s, sky, DriftSpec(), np.random.default_rng(7))
    trap, info = drift(true, s, sky, spec, np.random.default_rng(7))
    extra = trap.xyz - plain.xyz
    at_portal = np.argmin(np.abs(s - 100.0))
    np.testing.assert_allclose(extra[at_portal], bias, atol=0.01)
    assert np.abs(extra[s < 55.0]).max() < 1e-12                        # before the ramp
    assert np.abs(extra[s > 499.0]).max() < 0.01                         # faded at the far portal
    np.testing.assert_array_equal(trap.sd, plain.sd)                     # the sd shows nothing
    assert info["multipath"]["applied"] and info["multipath"]["kind"] == "entry"
    other = drift(true, s, sky, DriftSpec(multipath=(Multipath("someone_else"),)),
                  np.random.default_rng(7))[0]
    np.testing.assert_array_equal(other.xyz, plain.xyz)


def test_heading_bias_only_for_listed_runs():
    true, s, sky = _straight()
    spec = DriftSpec(heading_bias_deg=0.05, heading_bias_runs=("r",))
    est, info = drift(true, s, sky, spec, np.random.default_rng(0))
    np.testing.assert_allclose(est.rpy[:, 2], 90.05)
    assert info["heading_bias_deg"] == 0.05
    spec = DriftSpec(heading_bias_deg=0.05, heading_bias_runs=("x",))
    np.testing.assert_allclose(drift(true, s, sky, spec, np.random.default_rng(0))[0].rpy[:, 2], 90.0)


def test_a_rough_drift_bends_more_and_still_meets_the_portals():
    """``roughness`` adds an integrated random walk (white acceleration): the drift's rate
    changes everywhere along the outage, not only on the envelope's scale, while the error stays
    zero at the portals and within the configured maximum."""
    true, s, sky = _straight()
    bends = {}
    for roughness in (0.0, 1.0):
        spec = DriftSpec(roughness=roughness)
        bends[roughness] = []
        for seed in range(6):
            est, _ = drift(true, s, sky, spec, np.random.default_rng(seed))
            err = (est.xyz - true.xyz)[:, :2]
            h = np.linalg.norm(err, axis=1)
            assert h[sky].max() < 0.05 and h.max() <= spec.max_horizontal + 1e-9
            every_10m = err[1500:4500:100]  # inside, away from the open-sky noise
            bends[roughness].append(np.abs(np.diff(every_10m, 2, axis=0)).max() / h.max())
    assert np.median(bends[1.0]) > 1.5 * np.median(bends[0.0])
