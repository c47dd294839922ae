"""The line of offsets along the track (matching.piecewise): known answers.

Run b is run a's tunnel stretched and bent as INS drift does it: its offset to run a changes by
millimetres per metre along the track. A single translation cannot describe that; the line
must, at every point of the overlap.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest

from railtraj.matching.piecewise import (
    Piecewise,
    alias_ratio,
    along_costs,
    along_profile,
    curve_through,
    edge_costs,
    edge_profile,
    fit_curve,
    piecewise_fit,
    pooled_variance,
    reference_position,
    reference_times,
    reference_tree,
    reversed_fit,
    surface_normals,
    track_axis,
    track_frame,
    valley_significance,
    window_ties,
)
from railtraj.matching.synthetic import placed, rotation_z, tunnel_tile, tunnel_xyz
from railtraj.matching.target import build_target

pytestmark = pytest.mark.slow  # most fit the windows of simulated tunnel tiles: 2-11 s each

AXIS = np.array([1.0, 0.0, 0.0])


def test_fit_curve_recovers_a_parabola_and_drops_a_window_on_an_alias():
    s = np.arange(-12.5, 12.6, 5.0)
    coefs = np.array([[0.3, -0.2, 0.05], [0.008, -0.004, 0.001], [1e-4, -2e-4, 0.0]])
    d = np.vander(s, 3, increasing=True) @ coefs
    d[2, 0] += 0.65  # one window locked onto the next sleeper
    got, cov, used, sd = fit_curve(np.column_stack([s, d]), AXIS, 0.0)
    assert used.tolist() == [True, True, False, True, True, True]
    np.testing.assert_allclose(got, coefs, atol=1e-9)
    # a perfect curve still reports the floor sd (1 cm along per window), never zero
    assert 0.004 < np.sqrt(cov[0, 0]) < 0.010 and sd[0] == pytest.approx(0.010)


def test_fit_curve_keeps_the_end_windows_of_a_bending_drift_and_drops_one_on_an_alias_there():
    """The windows of held-out mixed 306's pair where run b's GNSS came back at a portal (along
    m): the parabola through the first four, extrapolated, misses the last window by 3.2 cm,
    but that prediction alone scatters 3 window sd there. The same window on the next sleeper
    (0.6 m) is still dropped."""
    s = np.array([-12.51, -7.67, -2.49, 3.06, 7.58])
    along = np.array([-0.1387, -0.1814, -0.2046, -0.2031, -0.2136])
    windows = np.column_stack([s, along, np.zeros((5, 2))])
    _, cov, used, _ = fit_curve(windows, AXIS, 0.0)
    assert used.all() and np.sqrt(cov[0, 0]) < 0.02
    windows[4, 1] += 0.6
    assert fit_curve(windows, AXIS, 0.0)[2].tolist() == [True, True, True, True, False]


def test_fit_curve_takes_along_from_the_windows_that_found_it_and_across_and_up_from_all():
    s = np.arange(-12.5, 12.6, 5.0)
    coefs = np.array([[0.3, -0.2, 0.05], [0.008, -0.004, 0.001], [1e-4, -2e-4, 0.0]])
    d = np.vander(s, 3, increasing=True) @ coefs
    d[4:, 0] += np.array([0.07, -0.09])  # no valley: point-to-plane's along value, meaningless
    got, cov, used, sd = fit_curve(np.column_stack([s, d]), AXIS, 0.0, along=[True] * 4 + [False] * 2)
    assert used.tolist() == [True] * 4 + [False] * 2
    np.testing.assert_allclose(got, coefs, atol=1e-9)
    # along from 4 windows, across and up from 6: the intercept's variance follows
    G4, G6 = (np.vander(s[:n], 3, increasing=True) for n in (4, 6))
    np.testing.assert_allclose(np.diag(cov), sd**2 * [np.linalg.inv(G.T @ G)[0, 0] for G in (G4, G6, G6)])
    none = fit_curve(np.column_stack([s, d]), AXIS, 0.0, along=[False] * 6)
    assert not none[2].any() and none[1][0, 0] >= 1e4 and np.allclose(none[0][:, 1:], coefs[:, 1:])


def test_fit_curve_degree_follows_the_windows():
    got, cov, used, _ = fit_curve(np.array([[2.0, 0.1, 0.2, 0.3]]), AXIS, 2.0)
    np.testing.assert_allclose(got, [[0.1, 0.2, 0.3], [0, 0, 0], [0, 0, 0]])
    assert used.all() and np.isfinite(cov).all()
    two = np.array([[-2.5, 0.1, 0.0, 0.0], [2.5, 0.2, 0.0, 0.0]])
    got, *_ = fit_curve(two, AXIS, 0.0)
    np.testing.assert_allclose(got[:, 0], [0.15, 0.02, 0.0])


def test_across_and_up_that_bend_beyond_any_drift_are_a_line_with_its_scatter():
    """A held-out sparse scan of a station: two platform edges 0.45 m apart across the track each
    fitted some windows (across m). A parabola through them bends 5 mm/m^2 and leaves 2 cm,
    which made the pair 54 cm off across, claiming 1.9 cm. No drift bends so: a line, and half
    the windows' spread is the sd. A drift bending 1 mm/m^2 (more than any simulated) keeps its
    parabola."""
    s = np.array([-9.59, -4.98, 0.17, 5.33, 10.25])
    station = np.column_stack([s, np.zeros(5), [-1.68, -1.33, -1.37, -1.42, -1.84], np.full(5, 0.29)])
    coefs, cov, _, sd = fit_curve(station, AXIS, 0.0)
    # the outer windows were right (-1.77): the sd is half the windows' spread, not the line's 13 cm
    assert coefs[2, 1] == 0.0 and np.sqrt(cov[1, 1]) == pytest.approx(0.255) and sd[1] > 0.15
    assert np.sqrt(cov[2, 2]) < 0.003  # up agrees: untouched
    bending = station.copy()
    bending[:, 2] = -1.5 + 0.004 * s + 0.001 * s**2
    coefs, cov, _, sd = fit_curve(bending, AXIS, 0.0)
    assert coefs[2, 1] == pytest.approx(0.001) and sd[1] == pytest.approx(0.003)


def test_a_fitted_track_direction_across_the_track_is_overruled_by_the_direction_of_travel(stretched):
    """A fit started far across the track (votes that failed on a sparse scan, a tile holding one
    wall of a tunnel the grid cuts lengthwise) has no wall in reach: its weakest direction is
    across. Windows cut across the track then placed a held-out pair 13 cm off across,
    claiming 1 cm. The run's trajectory says which way the train went."""
    a, b, true_d = stretched
    heading = rotation_z(30)
    along, across = heading @ [1.0, 0, 0], heading @ [0, 1.0, 0]
    travel = -along  # (either way along the track)
    no_wall = 1e6 * np.eye(3) - (1e6 - 10.0) * np.outer(across, across)  # across the weakest
    assert abs(track_axis(no_wall) @ across) == pytest.approx(1.0)
    assert abs(track_axis(no_wall, travel) @ along) == pytest.approx(1.0)
    # a fitted direction within a few degrees of travel is the surfaces' own, and kept
    tilted = rotation_z(33) @ [1.0, 0, 0]
    slight = 1e6 * np.eye(3) - (1e6 - 10.0) * np.outer(tilted, tilted)
    np.testing.assert_allclose(abs(track_axis(slight, travel) @ tilted), 1.0, atol=1e-9)

    target = build_target(a.xyz)
    start = true_d.mean(axis=0)
    inside = target.inside(b.xyz + start, 0.3)
    fit = piecewise_fit(target, a.xyz, b.xyz[inside], start, 5.0, no_wall, travel=travel)
    assert fit is not None and fit.axis_from_travel and fit.summary()["axis_from_travel"]
    err = fit.at(b.xyz[inside]) - true_d[inside]
    assert np.abs(err @ track_frame(fit.axis)[1:].T).max() < 0.003  # across and up
    wrong = piecewise_fit(target, a.xyz, b.xyz[inside], start, 5.0, no_wall)  # as before: 5 cm off across
    assert not wrong.axis_from_travel and abs(wrong.axis @ across) == pytest.approx(1.0)
    assert np.abs((wrong.at(b.xyz[inside]) - true_d[inside]) @ across).max() > 0.02


@pytest.fixture(scope="module")
def stretched():
    """Run a (24 m of ribbed tunnel) and run b drifting along it: b = a - d(x), where d(x) goes
    from d0 - 12 g to d0 + 12 g (+-9.6 cm along, -+4.8 cm across, +-1.2 cm up)."""
    a = tunnel_tile(0, 24, density=800, noise=0.005, seed=0)
    d0, g = np.array([0.35, 0.10, -0.03]), np.array([0.008, -0.004, 0.001])
    x = a.xyz[:, 0] - 12.0
    local_d = d0 + x[:, None] * g
    rng = np.random.default_rng(5)
    b_xyz = a.xyz - local_d + rng.normal(0, 0.005, a.xyz.shape)
    b = type(a)(b_xyz, a.gps_time, run_id="B", name="B")
    R = rotation_z(30)
    return placed(a), placed(b), (local_d @ R.T)


def test_piecewise_fit_follows_a_stretched_run_to_millimetres(stretched):
    a, b, true_d = stretched
    target = build_target(a.xyz)
    start = true_d.mean(axis=0) + rotation_z(30) @ [0.04, 0.0, 0.0]  # 4 cm off along the track
    inside = target.inside(b.xyz + start, 0.3)
    fit = piecewise_fit(target, a.xyz, b.xyz[inside], start, length=5.0)
    assert fit is not None and fit.n_used >= 3
    err = fit.at(b.xyz[inside]) - true_d[inside]
    along, across, up = np.abs(err @ track_frame(fit.axis).T).max(axis=0)
    assert along < 0.005 and across < 0.003 and up < 0.003
    np.testing.assert_allclose(abs(fit.axis @ rotation_z(30) @ [1.0, 0, 0]), 1.0, atol=1e-4)
    # a rigid translation cannot: the true offset varies by 19 cm along this overlap
    assert np.ptp(true_d[inside] @ fit.axis) > 0.15


def test_window_ties_carry_the_true_offset_where_and_when_they_are(stretched):
    a, b, true_d = stretched
    target = build_target(a.xyz)
    inside = target.inside(b.xyz + true_d.mean(axis=0), 0.3)
    fit = piecewise_fit(target, a.xyz, b.xyz[inside], true_d.mean(axis=0), length=5.0)
    time_a, time_b, xyz_a, xyz_b = window_ties(fit, a.xyz, a.gps_time, b.xyz[inside], b.gps_time[inside])
    assert len(time_a) == fit.n_used >= 4
    k = np.array([np.flatnonzero(inside)[np.argmin(((b.xyz[inside] - p) ** 2).sum(axis=1))] for p in xyz_b])
    np.testing.assert_allclose(xyz_a - xyz_b, true_d[k], atol=0.005)
    # both runs pass each tie's place at the same time in this synthetic pair (5 m/s, 0.2 s per m)
    np.testing.assert_allclose(time_a, time_b, atol=0.1)


@pytest.mark.parametrize(("gap", "found"), [(1.7, True), (4.0, False)])
def test_a_reference_point_beyond_the_cloud_takes_the_time_at_the_trains_speed(stretched, gap, found):
    """A box seen whole in the context is placed where it lies, up to metres beyond run b's
    cloud: its time is the line through the cloud's last metres of times, up to TIME_REACH
    (3 m) beyond; farther, none."""
    a, b, true_d = stretched
    target = build_target(a.xyz)
    inside = target.inside(b.xyz + true_d.mean(axis=0), 0.3)
    fit = piecewise_fit(target, a.xyz, b.xyz[inside], true_d.mean(axis=0), length=5.0)
    whole = reference_times(fit, a.xyz, a.gps_time, b.xyz, b.gps_time)[1]
    short = ((b.xyz - fit.origin) @ fit.axis) < fit.s_ref - gap  # run b's cloud ends gap m before
    cut = reference_times(fit, a.xyz, a.gps_time, b.xyz[short], b.gps_time[short])[1]
    assert abs(cut - whole) < 0.02 if found else np.isnan(cut)  # 5 m/s: 0.02 s is 10 cm


@pytest.mark.parametrize("across", [False, True])
@pytest.mark.parametrize("seed", [0, 1])
def test_along_costs_equal_a_nearest_neighbour_query_per_shift(seed, across):
    """The capsule search finds every reference point that can be nearest within tau; across
    run a's surface, the costs are :func:`edge_costs`' (the distance along the nearest point's
    normal, a query per shift)."""
    rng = np.random.default_rng(seed)
    ref = tunnel_tile(seed=seed).xyz
    pts = ref[rng.choice(len(ref), 3000, replace=False)] + rng.normal(0, 0.01, (3000, 3))
    axis = np.array([np.cos(0.3), np.sin(0.3), 0.0])
    d, tau = np.array([0.02, -0.01, 0.005]), 0.05
    ts = np.arange(-0.1, 0.1 + 0.0025, 0.005)
    target, tree = build_target(ref), reference_tree(ref)
    got = along_profile(tree, pts, d, axis, ts, tau, normals=surface_normals(target) if across else None)
    cost = edge_costs(target, tree, pts + d, axis, ts, tau, across=across)
    spread = cost.std(axis=0)
    want = cost[:, spread >= np.median(spread)].mean(axis=1)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-15)
    assert np.ptp(want) > 1e-5  # the profile has a shape to get wrong


def test_reference_position_lies_between_the_windows_the_curve_uses():
    """The overlap's median lies beyond the curve's windows once the window at the tile's end,
    found on an alias, is dropped: the offset is reported at the nearest used window, not
    extrapolated to the median (nor between the windows *found*)."""
    s = np.array([-10.0, -5.0, 0.0, 5.0])
    windows = np.column_stack([s, 0.003 * s, np.zeros((4, 2)), np.ones(4)])
    windows[0, 1] += 0.65  # a sleeper alias
    _, _, used, _ = fit_curve(windows[:, :4], AXIS, 0.0)
    assert used.tolist() == [False, True, True, True]
    assert reference_position(-8.0, windows, used) == -5.0
    assert reference_position(1.0, windows, used) == 1.0
    one = np.array([False, True, False, False])  # one window from edges: nothing to move between
    assert reference_position(-8.0, windows, one) == -8.0
    windows[1, 4] = 2  # ... but from a mark, placed to centimetres
    assert reference_position(-8.0, windows, one) == -5.0


def test_a_reversed_fit_is_the_curve_of_run_b_where_run_as_windows_land():
    """Run a's windows fitted onto run b (a dense run a against a sparse run b) give run b's
    curve: each window where its points land on run b, with the opposite offset. Run b lags
    1.5 m along a drift of 1 cm/m: read at run a's positions instead, the curve would be 1.5 cm
    off along the track."""
    axis = rotation_z(30) @ [1.0, 0.0, 0.0]
    c0, c1 = np.array([1.5, 0.1, -0.02]), np.array([0.01, 0.002, -0.001])
    origin_b = np.array([530_010.0, 180_005.0, 20.0])
    u_b = np.linspace(-10.0, 10.0, 5)  # window centres on run b, along the track
    true = lambda u: c0[None] + u[:, None] * c1[None]  # noqa: E731 (moves b onto a)
    p_b = origin_b + u_b[:, None] * axis
    p_a = p_b + true(u_b)
    origin_a = origin_b + np.array([0.3, -0.2, 0.0])
    table = np.column_stack([(p_a - origin_a) @ axis, -true(u_b), np.ones(5), np.ones(5)])
    rev = Piecewise(np.zeros((3, 3)), axis, origin_a, 0.0, np.eye(3), table, (-12.0, 12.0), np.zeros(3))
    moving = origin_b + np.linspace(-12.0, 12.0, 241)[:, None] * axis  # run b's points, centred on origin_b
    fit = reversed_fit(rev, moving)
    np.testing.assert_allclose(fit.windows[:, 0], u_b, atol=1e-9)
    np.testing.assert_allclose(fit.at(p_b), true(u_b), atol=1e-9)
    assert fit.n_used == 5 and fit.marks is None


def test_a_fast_trains_windows_find_the_joints_where_the_plain_distance_ripples():
    """Scan lines 7.5 cm apart over 8 cm ring joints, run b 3 cm off along the track: the
    plain squared distance ripples as the runs' lines pass each other, and no window's valley
    stood out of that ripple (none found an along-track offset). Across run a's surface the
    lining is flat at every shift and each window's valley is the joints'."""
    a_xyz, b_true = _ring_jointed(0, 24, 0, lines=0.075), _ring_jointed(0, 24, 10, lines=0.075)
    d0 = np.array([0.4, 0.02, -0.01])
    fit = piecewise_fit(build_target(a_xyz), a_xyz, b_true - d0, d0 + 0.03 * AXIS, length=5.0, tau=0.075)
    found = fit.windows[:, 5] == 1
    assert found.sum() >= 4
    np.testing.assert_allclose(fit.windows[found, 1], d0[0], atol=0.012)
    assert abs(fit.d_ref[0] - d0[0]) < 0.008


def test_window_spread_counts_the_windows_the_curve_dropped():
    s = np.array([-10.0, -5.0, 0.0, 5.0, 10.0])
    coefs = np.array([[0.3, 0.1, 0.0], [0.002, 0.0, 0.0], [0.0, 0.0, 0.0]])
    d = np.vander(s, 3, increasing=True) @ coefs
    d[1, 0] += 0.10  # dropped: 10 cm along the track off the curve
    windows = np.column_stack([s, d, [1, 0, 1, 1, 1], np.ones(5)])
    fit = Piecewise(coefs, AXIS, np.zeros(3), 0.0, np.eye(3) * 1e-4, windows, (-10.0, 10.0), np.full(3, 0.01))
    assert fit.window_spread() == pytest.approx(0.10 / np.sqrt(5), rel=1e-9)
    assert fit.summary()["window_spread_m"] == fit.window_spread()


def test_windows_fitted_in_threads_equal_those_fitted_on_one_thread(stretched, monkeypatch):
    from railtraj.matching import threads

    a, b, true_d = stretched
    target = build_target(a.xyz)
    start = true_d.mean(axis=0)
    inside = target.inside(b.xyz + start, 0.3)
    fitted_on, map_threads = set(), threads.map_threads

    def recording(fn, n):  # notes which threads fit the windows
        def window(k):
            fitted_on.add(threading.get_ident())
            return fn(k)
        return map_threads(window, n)

    monkeypatch.setattr("railtraj.matching.piecewise.map_threads", recording)
    monkeypatch.setattr(threads, "available_cores", lambda: 2)
    fits = {}
    for n in (1, 0):  # threads=1, then every core
        fitted_on.clear()
        threads.set_threads(n)
        fits[n] = piecewise_fit(target, a.xyz, b.xyz[inside], start, length=5.0)
        assert (fitted_on == {threading.get_ident()}) == (n == 1)
    np.testing.assert_array_equal(fits[0].windows, fits[1].windows)
    np.testing.assert_array_equal(fits[0].cov, fits[1].cov)


def test_ties_are_kept_only_where_the_curve_interpolates_its_windows():
    """A parabola through four 1 cm windows is known to 0.7 cm between them but to 1.7 cm half
    a window past the last one (the held-out portal_trap 91 pair: a tie there 3.7 cm off). With
    the end window dropped, points past the last used window's centre are not covered."""
    s = np.arange(-12.5, 12.6, 5.0)
    coefs = np.array([[0.3, -0.2, 0.05], [0.02, -0.004, 0.001], [0.0, 0.0, 0.0]])
    d = np.vander(s, 3, increasing=True) @ coefs
    d[-1, 0] += 0.2  # the last window off the curve: dropped
    got, cov, used, sd = fit_curve(np.column_stack([s, d]), AXIS, 0.0)
    assert used.tolist() == [True, True, True, True, True, False]
    windows = np.column_stack([s, d, used, np.ones(len(s))])
    fit = Piecewise(got, AXIS, np.zeros(3), 0.0, cov, windows, (-15.0, 10.0), sd)
    along = np.array([-15.0, -12.5, 0.0, 7.5, 7.6, 10.0])
    covered = fit.covers(np.column_stack([along, np.zeros((6, 2))]))
    assert covered.tolist() == [False, True, True, True, False, False]
    # and the spread of a parabola's value grows past the windows it was fitted on
    G = np.vander(s[used], 3, increasing=True)
    M = np.linalg.inv(G.T @ G)
    var = [np.vander([x], 3, increasing=True)[0] @ M @ np.vander([x], 3, increasing=True)[0] for x in (0.0, 7.5, 10.0)]
    assert var[0] < var[1] < var[2] and var[2] > 1.8 * var[1]


def _scanned(x0: float, x1: float, seed: int, phase: float, features: bool = True, spacing: float = 0.05) -> np.ndarray:
    """Tunnel points on scan lines across the track every ``spacing`` metres from ``phase``:
    a profile scanner's sampling, whose lines two runs lay at different places."""
    xyz = tunnel_xyz(x0, x1, 1600, seed=seed, features=features)
    xyz[:, 0] = np.round((xyz[:, 0] - phase) / spacing) * spacing + phase
    return xyz + np.random.default_rng(seed).normal(0, 0.005, xyz.shape)


@pytest.mark.parametrize("phase", [0.011, 0.037])
def test_windows_without_edges_give_no_along_track_offset(phase):
    """Half the overlap ribbed, half a plain tube (a slab-track circular section), scanned on
    lines 5 cm apart: in the plain half the profile only ripples as the two runs' lines pass
    each other, its lowest sample 8-16 cm off the truth. Those windows give across and up but
    no along-track offset (on mixed 185 two of them put an ``ok`` pair 6.7 cm off)."""
    def run(seed: int, phase: float) -> np.ndarray:
        return np.concatenate([_scanned(0, 12, seed, phase), _scanned(12, 24, seed + 1, phase, features=False)])

    a_xyz, b_true = run(0, 0.0), run(10, phase)
    d0, g = np.array([0.05, 0.02, -0.01]), np.array([0.004, 0.0, 0.0])
    b_xyz = b_true - (d0 + (b_true[:, 0] - 12.0)[:, None] * g)
    fit = piecewise_fit(build_target(a_xyz), a_xyz, b_xyz, d0, length=3.0)
    x = fit.windows[:, 0] + fit.origin[0]
    found = fit.windows[:, 5] > 0
    assert found.sum() >= 4 and x[found].max() < 12.5 and x.max() > 20  # along in the ribbed half only
    assert fit.n_used == found.sum()
    # each edge is placed only to the scan-line spacing: within half of it
    np.testing.assert_allclose(fit.windows[found, 1], d0[0] + (x[found] - 12.0) * g[0], atol=0.025)
    # the plain half still places run b across and up
    np.testing.assert_allclose(fit.windows[~found, 2:4], np.tile(d0[1:], ((~found).sum(), 1)), atol=0.005)


def test_valley_significance_separates_edges_from_a_plain_tube():
    """A 5 m window of run b against run a's tile around it, each sampling the surfaces afresh."""
    ts = np.arange(-0.1, 0.1025, 0.005)
    for features, expect in ((True, lambda v: v > 10), (False, lambda v: v < 1)):
        a, b = tunnel_xyz(-1, 6, 800, seed=0, features=features), tunnel_xyz(0, 5, 800, seed=1, features=features)
        costs = along_costs(reference_tree(a), b[::10], np.zeros(3), AXIS, ts, 0.05)
        assert expect(valley_significance(ts, costs)), (features, valley_significance(ts, costs))


def test_windows_are_halved_where_only_part_of_the_overlap_has_edges():
    """A 24 m overlap whose first 9 m are ribbed and the rest a plain tube (a pair at the end of
    a featureless section): on 5 m windows only two find the along-track offset, too few for a
    curve that checks itself. Halving those two puts four windows on the edges, each placed as
    well as before, and the plain part keeps its across and up. The pair's offset is reported
    between those windows: at the overlap's middle it would be extrapolated."""
    def run(seed: int, phase: float) -> np.ndarray:
        return np.concatenate([_scanned(0, 9, seed, phase), _scanned(9, 24, seed + 1, phase, features=False)])

    a_xyz, b_true = run(0, 0.0), run(10, 0.023)
    d0, g = np.array([0.05, 0.02, -0.01]), np.array([0.003, 0.0, 0.0])
    b_xyz = b_true - (d0 + (b_true[:, 0] - 12.0)[:, None] * g)
    fit = piecewise_fit(build_target(a_xyz), a_xyz, b_xyz, d0, length=5.0)
    x = fit.windows[:, 0] + fit.origin[0]
    found = fit.windows[:, 5] > 0
    assert found.sum() >= 4 and x[found].max() < 9.5 and x.max() > 20
    assert np.all(np.diff(x) > 0)  # in order along the track
    np.testing.assert_allclose(fit.windows[found, 1], d0[0] + (x[found] - 12.0) * g[0], atol=0.025)
    np.testing.assert_allclose(fit.windows[~found, 2:4], np.tile(d0[1:], ((~found).sum(), 1)), atol=0.005)
    # the offset is reported where the edges place it, not extrapolated to the overlap's middle
    x_ref = fit.origin[0] + fit.s_ref * fit.axis[0]
    assert x[found].min() - 1e-3 <= x_ref <= x[found].max() + 1e-3
    assert abs(fit.d_ref[0] - (d0[0] + (x_ref - 12.0) * g[0])) < 0.025  # its windows' precision


def _marked(xyz: np.ndarray, marks: list[tuple[tuple[float, float, float], float]], seed: int) -> np.ndarray:
    """Intensity of an even grey surface (6 % noise), times each mark's gain within 0.35 m of it."""
    level = 20000.0 * (1 + 0.06 * np.random.default_rng(seed).standard_normal(len(xyz)))
    for centre, gain in marks:
        level[np.linalg.norm(xyz - np.asarray(centre), axis=1) <= 0.35] *= gain
    return level.astype(np.uint16)


def test_marks_in_the_intensity_place_the_windows_of_a_plain_tube():
    """A plain tube (no edges anywhere) with a stain or a painted patch every 6 m on its walls:
    the windows over a mark are placed along the track by it (found 2), to the precision of the
    scan lines, and the curve rests on them; without intensity none is placed. The pair's offset
    is given between those windows."""
    marks = [((3.0, -3.0, 1.5), 1.8), ((9.0, 3.0, 2.0), 0.5), ((15.0, -3.0, 1.0), 0.6), ((21.0, 3.0, 1.5), 1.7)]
    a_xyz, b_true = _scanned(0, 24, 0, 0.0, features=False), _scanned(0, 24, 10, 0.023, features=False)
    a_int, b_int = _marked(a_xyz, marks, 1), _marked(b_true, marks, 2)
    d0, g = np.array([0.3, 0.02, -0.01]), np.array([0.003, 0.0, 0.0])
    b_xyz = b_true - (d0 + (b_true[:, 0] - 12.0)[:, None] * g)
    start = d0 - np.array([0.25, 0.0, 0.0])  # 25 cm off along the track: the votes know nothing better
    target = build_target(a_xyz)
    plain = piecewise_fit(target, a_xyz, b_xyz, start, length=5.0)
    assert not (plain.windows[:, 5] > 0).any()
    fit = piecewise_fit(target, a_xyz, b_xyz, start, length=5.0, intensity=(a_int, b_int),
                        vote_window=(start, 1.0))
    x = fit.windows[:, 0] + fit.origin[0]
    placed_by_marks = fit.windows[:, 5] == 2
    assert placed_by_marks.sum() >= 3 and fit.on_marks
    np.testing.assert_allclose(fit.windows[placed_by_marks, 1], d0[0] + (x[placed_by_marks] - 12.0) * g[0], atol=0.02)
    x_ref = fit.origin[0] + fit.s_ref * fit.axis[0]
    assert abs(fit.d_ref[0] - (d0[0] + (x_ref - 12.0) * g[0])) < 0.02
    assert np.sqrt(fit.cov[0, 0]) >= 0.01  # a mark's window is known to centimetres, not millimetres


def _ring_jointed(x0: float, x1: float, seed: int, spacing: float = 1.25, lines: float = 0.02,
                  width: float = 0.08) -> np.ndarray:
    """A plain tube scanned on lines ``lines`` apart whose lining steps 2.5 cm inwards over a
    ``width`` ring joint every ``spacing`` metres (a segmental lining; floor left plain)."""
    xyz = _scanned(x0, x1, seed, 0.007 * seed, features=False, spacing=lines)
    joint = (xyz[:, 0] % spacing < width) & (xyz[:, 2] > 0.3)
    inward = np.column_stack([np.zeros(len(xyz)), -xyz[:, 1], np.full(len(xyz), 2.0) - xyz[:, 2]])
    xyz[joint] += 0.025 * inward[joint] / np.linalg.norm(inward[joint], axis=1, keepdims=True)
    return xyz


def test_the_edge_profile_shows_the_ring_joints_the_fitness_profile_misses():
    """Ring joints every 1.25 m and nothing else, the votes 1.25 m off (an alias): the windows
    find valleys there, the fitness profile (points within 5 cm) shows no alias, and the edge
    profile shows one every ring spacing, the truth among them, with its own noise."""
    from railtraj.alongtrack import AlongTrackOptions, _profile_peaks

    a_xyz, b_true = _ring_jointed(0, 24, 0), _ring_jointed(0, 24, 10)
    d0 = np.array([0.4, 0.02, -0.01])
    b_xyz = b_true - d0
    start = d0 + 1.25 * AXIS
    target = build_target(a_xyz)
    fit = piecewise_fit(target, a_xyz, b_xyz, start, length=5.0, tree=reference_tree(a_xyz))
    assert (fit.windows[:, 5] == 1).sum() >= 3 and abs(fit.d_ref[0] - start[0]) < 0.03  # on the alias
    options = AlongTrackOptions()
    _, _, fitness = alias_ratio(target, b_xyz, fit, start, 3.0)
    seen = _profile_peaks(fitness, options)
    assert seen is None or len(seen[0]) <= 1
    edges = edge_profile(target, reference_tree(a_xyz), b_xyz, fit, start, 3.0, tau=0.05)
    assert len(edges["noise"]) == len(edges["fitness"]) and edges["source"] == "edges"
    shift, movable = (peaks := _profile_peaks(edges, options)).shift, peaks.movable
    lattice = -1.25 * np.round(-shift / 1.25)
    assert len(shift) >= 3 and movable.all()
    np.testing.assert_allclose(shift, lattice, atol=0.05)  # every peak is a ring joint away
    assert np.isin([-1.25, 0.0, 1.25], np.round(lattice, 2)).all()  # the truth (-1.25) among them


def test_pooled_variance_is_never_negative_where_it_is_zero_beside_larger_values():
    """A running mean of zeros after larger values leaves tiny negatives (their sqrt is NaN)."""
    variance = np.r_[np.random.default_rng(0).random(50) * 1e-3 + 1e-2, np.zeros(50)]
    pooled = pooled_variance(variance, 5)
    assert np.isfinite(np.sqrt(pooled)).all()
    np.testing.assert_allclose(pooled[10:40], variance[10:40], atol=1e-3)  # a mean of its neighbours


@pytest.mark.parametrize("across", [True, False])
def test_a_fast_trains_edge_profile_shows_the_joints_and_no_ripple(across):
    """Scan lines 6.5 cm apart (a fast train) over 8 cm ring joints: the plain squared distance
    ripples as the runs' lines pass each other, nearly as deep as a joint's 2.5 cm step, and
    some of that ripple stands out as peaks between the joints (candidates that are no alias).
    Across run a's surface only, every significant peak is a joint."""
    from railtraj.alongtrack import AlongTrackOptions, _profile_peaks

    a_xyz, b_true = _ring_jointed(0, 24, 0, lines=0.065), _ring_jointed(0, 24, 10, lines=0.065)
    d0 = np.array([0.4, 0.02, -0.01])
    b_xyz = b_true - d0
    target, tree = build_target(a_xyz), reference_tree(a_xyz)
    fit = piecewise_fit(target, a_xyz, b_xyz, d0, length=5.0, tree=tree)
    edges = edge_profile(target, tree, b_xyz, fit, d0, 3.0, tau=0.065, across=across)
    shift = _profile_peaks(edges, AlongTrackOptions()).shift
    off_lattice = np.abs(shift - 1.25 * np.round(shift / 1.25)) > 0.05
    assert len(shift) >= 3
    assert (not off_lattice.any()) == across, shift


def _resolved_between_joints(lines: float) -> tuple:
    """The matcher's end on a ring-jointed tube scanned on lines ``lines`` apart whose 40
    keypoint pairs all vote 0.6 m off the truth (between two joints): the pair's offset and
    the truth."""
    from railtraj.data import Keypoints, PointTile
    from railtraj.matching.resolve import VoteSettings, resolve
    from railtraj.matching.voting import pair_translations

    a_xyz, b_true = _ring_jointed(0, 24, 0, lines=lines), _ring_jointed(0, 24, 10, lines=lines)
    d0 = np.array([0.4, 0.02, -0.01])
    b_xyz = b_true - d0
    wrong = d0 + 0.6 * AXIS
    kp_b = b_xyz[np.random.default_rng(3).choice(len(b_xyz), 40, replace=False)]
    kp_a, kp_b = Keypoints(kp_b + wrong, np.zeros(40)), Keypoints(kp_b, np.zeros(40))
    tile_a = PointTile(a_xyz, np.zeros(len(a_xyz)), run_id="a", name="t")
    tile_b = PointTile(b_xyz, np.zeros(len(b_xyz)), run_id="b", name="t")
    votes = pair_translations(kp_a.xyz, kp_b.xyz, wrong, 3.0)
    off = resolve(tile_a, kp_a, tile_b, kp_b, votes, VoteSettings(fitness_radius=max(0.05, lines)),
                  lambda *args: None, {"timings": {}})
    return off, d0


def test_votes_between_the_joints_end_on_a_joint_and_are_left_to_the_chain():
    """Scan lines 4 cm apart: the votes (and the dense check's rival) fall between the joints.
    The pair ends on a joint (its windows' valleys, or the edge profile's peak the matcher
    moves a curve without valleys to), one alias of many, so it is ambiguous and the chain
    along the track chooses; nowhere between the joints."""
    off, d0 = _resolved_between_joints(0.04)
    assert off.status == "ambiguous", off.status
    along = (off.d - d0) @ AXIS
    assert abs(along - 1.25 * round(along / 1.25)) < 0.03, along  # on a joint
    assert np.abs(off.d[1:] - d0[1:]).max() < 0.005
    assert off.info["piecewise"]["windows_used"] >= 1


def test_a_pair_whose_every_shift_fits_every_point_is_never_ok():
    """Scan lines 2 cm apart on a smooth tube: every point lies within the fitness radius at
    every shift, so the curve and its aliases all misfit 0. That ratio is 1 (indistinguishable),
    not 0 / 0 read as "no rival": the pair, on a joint 2.5 m from the truth, was reported ok."""
    off, d0 = _resolved_between_joints(0.02)
    along = (off.d - d0) @ AXIS
    assert abs(along) > 1.0  # the dense check took a rival on a joint alias ...
    assert off.status == "ambiguous" and off.info["rival_misfit_ratio"] >= 0.8  # ... and says so


def test_a_window_placed_by_marks_that_the_curve_drops_leaves_the_others_their_floor():
    """Five windows placed by edges agree to 3 mm; a box's window (placed by marks) sits 1.8 m
    from them. The curve drops it, and its along-track sd is the edges' own, not the marks'."""
    rng = np.random.default_rng(5)
    s = np.array([-10.0, -5.0, 0.0, 5.0, 10.0])
    edges = np.column_stack([s, 1.7 + 0.003 * rng.standard_normal(5), np.full(5, 0.8), np.full(5, 0.01), np.ones(5)])
    box = np.array([[-8.0, -0.1, 0.8, 0.01, 2.0]])
    _, cov, used, _ = curve_through(np.vstack([box, edges]), AXIS, 0.0)
    _, alone, _, _ = curve_through(edges, AXIS, 0.0)
    assert not used[0] and used[1:].all()
    assert np.sqrt(cov[0, 0]) == pytest.approx(np.sqrt(alone[0, 0]))  # 2 cm floor: twice that
    _, cov, used, _ = curve_through(np.vstack([box, edges[:3] * [1, 0, 1, 1, 0]]), AXIS, 0.0)
    assert used[0] and np.sqrt(cov[0, 0]) >= 0.02 / np.sqrt(2)  # kept: along to centimetres only


def test_edge_windows_on_another_alias_than_a_mark_count_across_and_up_only():
    """Ribs for 7 m, then a plain tube with a stain on its wall (the end of a ribbed section).
    The votes chose the alias one rib (1.5 m) on: the one or two edge windows find that alias,
    the window over the stain finds the truth. They are further apart than any drift moves the
    runs in 10 m, so the edges are on an alias: the curve rests on the stain, and the edge
    windows place run b across and up only. Through both, its slope was metres per 10 m."""
    def run(seed: int, phase: float) -> np.ndarray:
        return np.concatenate([_scanned(0, 7, seed, phase), _scanned(7, 24, seed + 1, phase, features=False)])

    marks = [((19.0, -3.0, 1.5), 1.8)]
    a_xyz, b_true = run(0, 0.0), run(10, 0.023)
    a_int, b_int = _marked(a_xyz, marks, 1), _marked(b_true, marks, 2)
    d0, g = np.array([0.3, 0.02, -0.01]), np.array([0.003, 0.0, 0.0])
    b_xyz = b_true - (d0 + (b_true[:, 0] - 12.0)[:, None] * g)
    start = d0 + np.array([1.5, 0.0, 0.0])
    fit = piecewise_fit(build_target(a_xyz), a_xyz, b_xyz, start, length=5.0, intensity=(a_int, b_int),
                        vote_window=(start, 3.0))
    x = fit.windows[:, 0] + fit.origin[0]
    truth = d0[0] + (x - 12.0) * g[0]
    assert (fit.windows[:, 5] == 2).any() and fit.on_marks
    assert fit.summary()["windows_off_marks"] >= 1  # reported with the pair
    assert np.all(np.abs(fit.windows[fit.windows[:, 5] > 0, 1] - truth[fit.windows[:, 5] > 0]) < 0.05)
    x_ref = fit.origin[0] + fit.s_ref * fit.axis[0]
    assert abs(fit.d_ref[0] - (d0[0] + (x_ref - 12.0) * g[0])) < 0.05
    assert abs(fit.gradient[0]) < 0.05
    np.testing.assert_allclose(fit.windows[x < 7, 2:4], np.tile(d0[1:], ((x < 7).sum(), 1)), atol=0.01)


@pytest.mark.parametrize(("edges_at", "mark_at", "dropped"), [
    ([(5.0, 2.1)], (9.0, -0.15), 1),  # mixed 817's pair: one edge window 2.3 m from the mark, 4 m away
    ([(-6.0, 2.2), (5.7, 2.3)], (-8.5, -0.5), 2),  # portal_trap 1's: two
    ([(-5.0, 0.2), (-1.0, 0.22), (3.0, 0.2)], (7.0, -1.2), 0),  # three agree: the curve decides
    ([(5.0, 0.2)], (6.0, 0.05), 0),  # 15 cm in 1 m: no alias, the same offset
    ([(0.0, 0.2)], (10.0, 0.75), 0),  # 55 cm in 10 m: a drift could do that
])
def test_edge_windows_a_mark_contradicts_are_dropped_only_where_too_few_to_check_each_other(edges_at, mark_at, dropped):
    """Windows (s, along-track offset) placed by edges and one placed by a mark, along the x axis."""
    from railtraj.matching.piecewise import _off_the_marks

    rows = [[s, u, 0.1, 0.0, 1.0] for s, u in edges_at] + [[mark_at[0], mark_at[1], 0.1, 0.0, 2.0]]
    off = _off_the_marks(np.array(rows), AXIS)
    assert off.sum() == dropped and not off[-1]


def _bent(xyz: np.ndarray, radius: float, x_mid: float = 12.0) -> np.ndarray:
    """``xyz`` of a straight tunnel along x bent to the left on a curve of ``radius`` about x_mid."""
    theta = (xyz[:, 0] - x_mid) / radius
    return np.column_stack([x_mid + (radius - xyz[:, 1]) * np.sin(theta),
                            radius * (1 - np.cos(theta)) + xyz[:, 1] * np.cos(theta), xyz[:, 2]])


def test_a_mark_metres_from_the_start_on_a_curve_places_the_pair_across_where_it_sits():
    """A plain tube on a 150 m curve, one stain 3 m from the overlap's middle, run b a metre
    along the track from where the votes start it. A window fitted across at the start lies a
    metre along a wall that turns: its across is off by that metre times the wall's turn there
    (2 cm at the stain, 8 cm at the overlap's ends). The stain places its window along the
    track; across and up are fitted again there, and so are the other windows' at the stain's
    along-track offset: every window within 5 mm of the truth across and up, and the curve too."""
    marks = [((15.0, -3.0, 1.5), 1.8)]
    a_flat, b_flat = _scanned(0, 24, 0, 0.0, features=False), _scanned(0, 24, 10, 0.023, features=False)
    a_int, b_int = _marked(a_flat, marks, 1), _marked(b_flat, marks, 2)
    a_xyz, d = _bent(a_flat, 150.0), np.array([1.0, 0.02, -0.01])
    b_xyz = _bent(b_flat, 150.0) - d
    start = d - np.array([1.0, 0.0, 0.0])
    fit = piecewise_fit(build_target(a_xyz), a_xyz, b_xyz, start, length=5.0, intensity=(a_int, b_int))
    by_mark = fit.windows[:, 5] == 2
    assert by_mark.sum() == 1 and fit.on_marks and len(fit.windows) >= 4
    np.testing.assert_allclose(fit.windows[by_mark, 1], d[0], atol=0.03)  # to the scan lines
    np.testing.assert_allclose(fit.windows[:, 2:4], np.tile(d[1:], (len(fit.windows), 1)), atol=0.005)
    np.testing.assert_allclose(fit.d_ref[1:], d[1:], atol=0.005)


@pytest.mark.parametrize("marks_first", [False, True])
def test_a_mark_among_repeating_edges_places_the_pair_when_asked_first(marks_first):
    """Ring joints every 1.25 m and one stain on the lining; the votes an alias (1.25 m) off.
    The windows' valleys sit on the joint nearest where they start: the alias. Asked first (as
    the matcher does where a pair's profile shows no alias of its own), the stain's window is
    placed by it and the joints count across and up only: the pair sits on the truth."""
    a_xyz, b_true = _ring_jointed(0, 24, 0, lines=0.05), _ring_jointed(0, 24, 10, lines=0.05)
    marks = [((13.6, -3.0, 1.5), 1.8)]
    a_int, b_int = _marked(a_xyz, marks, 1), _marked(b_true, marks, 2)
    d0 = np.array([0.4, 0.02, -0.01])
    b_xyz = b_true - d0
    start = d0 + 1.25 * AXIS
    fit = piecewise_fit(build_target(a_xyz), a_xyz, b_xyz, start, length=5.0, tree=reference_tree(a_xyz),
                        intensity=(a_int, b_int), vote_window=(start, 3.0), marks_first=marks_first)
    by_marks = fit.windows[:, 5] == 2
    if not marks_first:
        assert not by_marks.any() and abs(fit.d_ref[0] - start[0]) < 0.03  # on the alias
        return
    assert by_marks.sum() == 1 and not (fit.windows[:, 5] == 1).any() and fit.on_marks
    assert abs(fit.d_ref[0] - d0[0]) < 0.03 and np.abs(fit.d_ref[1:] - d0[1:]).max() < 0.005
