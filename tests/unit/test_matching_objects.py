"""Short objects (a box on a plain lining) place a window without edges along the track."""

import numpy as np
import pytest

from railtraj.data import Keypoints, PointTile
from railtraj.matching.intensity import IntensityMarks, Surroundings
from railtraj.matching.objects import short_objects
from railtraj.matching.synthetic import HALF_WIDTH, _box, tunnel_xyz
from railtraj.plugins import registry

LENGTH, RADIUS, DENSITY = 20.0, 3.0, 400.0
BOX = (8.0, 8.7, 2.55, 0.5, 1.2)  # along from, to; its front face's distance across; from, to up


def surface(rng, area: float) -> int:
    return rng.poisson(DENSITY * area)


def lining(rng, boxes=(BOX,), tray=None, shift=0.0):
    """The upper half of a smooth tube along x with boxes on its wall (front, top and bottom
    faces, the wall behind them unseen) and optionally a cable tray from ``tray`` to the end,
    sampled at random; x moved by ``-shift``. Returns the points and the mask of box points."""
    n = surface(rng, LENGTH * np.pi * RADIUS)
    x, phi = rng.uniform(0, LENGTH, n), rng.uniform(0, np.pi, n)
    pts = np.column_stack([x, RADIUS * np.cos(phi), RADIUS * np.sin(phi)])
    for x0, x1, front, z0, z1 in boxes:  # the wall behind the box is in its shadow
        pts = pts[~((pts[:, 0] > x0) & (pts[:, 0] < x1) & (pts[:, 1] > 0)
                    & (pts[:, 2] / pts[:, 1] > z0 / front) & (pts[:, 2] / pts[:, 1] < z1 / front))]
    parts, on_box = [pts], [np.zeros(len(pts), bool)]
    for x0, x1, front, z0, z1 in boxes:
        m = surface(rng, (x1 - x0) * (z1 - z0))
        face = np.column_stack([rng.uniform(x0, x1, m), np.full(m, front), rng.uniform(z0, z1, m)])
        faces = [face]
        for z in (z0, z1):
            m = surface(rng, (x1 - x0) * (RADIUS - front))
            faces.append(np.column_stack([rng.uniform(x0, x1, m), rng.uniform(front, np.sqrt(RADIUS**2 - z**2), m),
                                          np.full(m, z)]))
        box = np.vstack(faces)
        parts.append(box)
        on_box.append(np.ones(len(box), bool))
    if tray is not None:
        m = surface(rng, (LENGTH - tray) * 0.3)
        parts.append(np.column_stack([rng.uniform(tray, LENGTH, m), rng.uniform(-2.8, -2.5, m), np.full(m, 1.5)]))
        on_box.append(np.zeros(m, bool))
    xyz = np.vstack(parts)
    return xyz - [shift, 0.0, 0.0], np.concatenate(on_box)


def test_short_objects_are_the_box_not_the_lining_nor_a_cable_tray_that_ends():
    rng = np.random.default_rng(3)
    xyz, on_box = lining(rng, tray=12.0)
    found = short_objects(xyz, np.array([1.0, 0.0, 0.0]), 0.1)
    assert found[on_box].mean() > 0.6  # the box's points but those within reach of the wall (which runs on)
    assert found[~on_box].sum() < 0.01 * on_box.sum()  # not the tube, its cut ends or the tray's end


@pytest.mark.parametrize("shift", [0.43, -0.67])
def test_a_box_places_a_window_without_edges_and_a_plain_one_stays_unplaced(shift):
    rng = np.random.default_rng(1)
    a, _ = lining(rng)
    b, _ = lining(rng, shift=shift)
    marks = IntensityMarks.build(a, None, b, None, np.eye(3), np.zeros(3), radius=0.05, objects=True)
    s, t = marks.place(5.0, 10.0, np.zeros(3), -1.5, 1.5)
    assert abs(t - shift) < 0.02  # the box's ends, each placed to the points' spacing
    assert abs(s - (8.35 - shift)) < 0.3  # where the box is in run b
    assert np.isnan(marks.place(12.0, 17.0, np.zeros(3), -1.5, 1.5)[1])  # nothing there
    plain = IntensityMarks.build(a, None, b, None, np.eye(3), np.zeros(3), radius=0.05, objects=False)
    assert np.isnan(plain.place(5.0, 10.0, np.zeros(3), -1.5, 1.5)[1])  # no intensity: nothing marks


def test_boxes_a_metre_apart_repeat_and_place_nothing():
    boxes = tuple((x0, x0 + 0.5, 2.55, 0.5, 1.2) for x0 in np.arange(5.0, 11.0, 1.0))
    rng = np.random.default_rng(2)
    a, _ = lining(rng, boxes)
    b, _ = lining(rng, boxes, shift=0.3)
    marks = IntensityMarks.build(a, None, b, None, np.eye(3), np.zeros(3), radius=0.05, objects=True)
    assert np.isnan(marks.place(6.0, 10.0, np.zeros(3), -1.5, 1.5)[1])


def test_a_box_half_a_metre_from_the_tile_edge_is_found_and_a_cut_surface_is_not():
    rng = np.random.default_rng(4)
    box = (LENGTH - 1.1, LENGTH - 0.5, 2.55, 0.5, 1.2)
    xyz, on_box = lining(rng, boxes=(box,))
    found = short_objects(xyz, np.array([1.0, 0.0, 0.0]), 0.1)
    assert found[on_box].mean() > 0.6
    assert found[~on_box].sum() < 0.01 * on_box.sum()  # the lining cut by both ends is no object


def test_a_box_is_placed_among_many_chance_intensity_marks_of_one_run():
    """Run b views the lining from the other track: 5 % of its points are marked by chance
    (far beyond its intensity's sd) and agree with nothing in run a. Pooled with the box's
    points they keep its peak below the rise a mark needs; each kind is placed on its own."""
    rng = np.random.default_rng(8)
    a, _ = lining(rng)
    b, _ = lining(rng, shift=0.43)
    a_intensity = np.exp(rng.normal(6.0, 0.1, len(a)))
    b_intensity = np.exp(rng.normal(6.0, 0.1, len(b)) + np.where(rng.random(len(b)) < 0.05, 1.5, 0.0))
    marks = IntensityMarks.build(a, a_intensity, b, b_intensity, np.eye(3), np.zeros(3), radius=0.05, objects=True)
    s, t = marks.place(5.0, 10.0, np.zeros(3), -1.5, 1.5)
    assert abs(t - 0.43) < 0.02
    assert abs(s - (8.35 - 0.43)) < 0.3
    # the pair's along-track profile is the box's too: it peaks at the curve, most of it agreeing
    _, _, profile = marks.alias_ratio(lambda xyz: np.tile([0.43, 0.0, 0.0], (len(xyz), 1)), -1.5, 1.5)
    ts = profile["start"] + profile["step"] * np.arange(len(profile["fitness"]))
    assert abs(ts[np.argmax(profile["fitness"])]) < 0.06 and max(profile["fitness"]) > 0.8


@pytest.mark.parametrize(("disc_shift", "placed"), [(0.43, True), (0.9, False)])
def test_a_box_and_a_painted_mark_that_disagree_place_nothing(disc_shift, placed):
    """A bright disc on the lining is placed by the intensity, the box by its shape: where the
    two agree the window is placed, where they are 0.47 m apart neither is trusted."""
    rng = np.random.default_rng(8)
    a, _ = lining(rng)
    b, _ = lining(rng, shift=0.43)

    def painted(xyz, centre):
        disc = np.hypot(xyz[:, 0] - centre, xyz[:, 2] - 2.0) < 0.3
        return np.exp(rng.normal(6.0, 0.1, len(xyz)) + np.where(disc, 1.5, 0.0))

    marks = IntensityMarks.build(a, painted(a, 6.0), b, painted(b, 6.0 - disc_shift), np.eye(3), np.zeros(3),
                                 radius=0.05, objects=True)
    t = marks.place(5.0, 10.0, np.zeros(3), -1.5, 1.5)[1]
    assert (abs(t - 0.43) < 0.02) if placed else np.isnan(t)


def test_a_box_across_the_tile_edge_is_seen_whole_in_the_context():
    """Run a's tile ends across the box (run b's, 0.43 m further on, lies inside): alone, run a's
    cut box ends at the cloud's edge and is no object; with the points beyond the edge
    (``PointTile.context``) it is the box, and places run b's."""
    rng = np.random.default_rng(8)
    a_all, _ = lining(rng)
    b_all, _ = lining(rng, shift=0.43)
    edge = 8.4  # run a's box: 8.0-8.7 m
    a, b = a_all[a_all[:, 0] < edge], b_all[b_all[:, 0] < edge]
    around = (a_all[(a_all[:, 0] >= edge) & (a_all[:, 0] < edge + 2.5)],
              b_all[(b_all[:, 0] >= edge) & (b_all[:, 0] < edge + 2.5)])
    alone = IntensityMarks.build(a, None, b, None, np.eye(3), np.zeros(3), radius=0.05, objects=True)
    assert np.isnan(alone.place(3.0, edge, np.zeros(3), -1.5, 1.5)[1])
    seen = IntensityMarks.build(a, None, b, None, np.eye(3), np.zeros(3), radius=0.05, objects=True,
                                around=Surroundings(*around, lambda xyz: xyz[:, 0] < edge))
    assert abs(seen.place(3.0, edge, np.zeros(3), -1.5, 1.5)[1] - 0.43) < 0.02


def _cut(xyz, lo, hi, reach=2.5):
    """The points of ``xyz`` from ``lo`` to ``hi`` along x (a tile) and those within ``reach``
    beyond (its context)."""
    x = xyz[:, 0]
    return xyz[(x >= lo) & (x < hi)], xyz[((x >= lo - reach) & (x < lo)) | ((x >= hi) & (x < hi + reach))]


@pytest.mark.parametrize("edge", [7.8, 8.15, 8.5])
def test_a_box_across_the_tile_edge_is_placed_whole_by_the_tile_that_holds_run_as_view_of_it(edge):
    """Run b's box (7.57-8.27 m) and run a's (8.0-8.7 m, its centre at 8.35 m) are cut by the
    edge between two tiles: the pair whose run a's tile holds run a's box's centre places it,
    whole, with the parts beyond its edges, to the points' spacing; the other places nothing.
    A cut part alone against a whole box would fit anywhere along it."""
    rng = np.random.default_rng(9)
    a_all, _ = lining(rng)
    b_all, _ = lining(rng, shift=0.43)
    placed = []
    for lo, hi in ((0.0, edge), (edge, LENGTH)):
        (a, a_around), (b, b_around) = _cut(a_all, lo, hi), _cut(b_all, lo, hi)
        holds = lambda xyz, lo=lo, hi=hi: (xyz[:, 0] >= lo) & (xyz[:, 0] < hi)  # noqa: E731
        marks = IntensityMarks.build(a, None, b, None, np.eye(3), np.zeros(3), radius=0.05, objects=True,
                                     around=Surroundings(a_around, b_around, holds))
        placed.append(marks.place(lo, hi, np.zeros(3), -1.5, 1.5)[1])
    held = 0 if 8.35 < edge else 1
    assert abs(placed[held] - 0.43) < 0.02 and np.isnan(placed[1 - held])


def test_a_box_in_run_bs_next_tile_is_placed_by_the_pair_whose_run_a_tile_holds_it():
    """Run b is 1 m behind: its box (9.0-9.7 m) lies in its next tile, beyond its cloud's end
    (8.9 m), but run a's (8.0-8.7 m) lies in run a's tile. The last window places it; the pair
    of the next tile, which does not hold run a's box, does not."""
    rng = np.random.default_rng(10)
    a_all, _ = lining(rng)
    b_all, _ = lining(rng, shift=-1.0)
    (a, a_around), (b, b_around) = _cut(a_all, 0.0, 8.9), _cut(b_all, 0.0, 8.9)
    start = np.array([-1.0, 0.0, 0.0])
    marks = IntensityMarks.build(a, None, b, None, np.eye(3), np.zeros(3), radius=0.05, objects=True,
                                 around=Surroundings(a_around, b_around, lambda xyz: xyz[:, 0] < 8.9))
    s, t = marks.place(4.0, 8.9, start, -1.5, 1.5)
    assert abs(t) < 0.02 and abs(s - 9.35) < 0.3  # where the box is in run b, beyond the window
    (a, a_around), (b, b_around) = _cut(a_all, 8.9, LENGTH), _cut(b_all, 8.9, LENGTH)
    nxt = IntensityMarks.build(a, None, b, None, np.eye(3), np.zeros(3), radius=0.05, objects=True,
                               around=Surroundings(a_around, b_around, lambda xyz: xyz[:, 0] >= 8.9))
    assert np.isnan(nxt.place(8.9, 14.0, start, -1.5, 1.5)[1])


CURVE_RADIUS, LAG = 550.0, 0.3  # m: a curve of the demo's; run b 0.3 m behind along it


def _bend(xyz):
    """x along a circle of :data:`CURVE_RADIUS` (turning left), y across, z up."""
    r = CURVE_RADIUS - xyz[:, 1]
    return np.column_stack([r * np.sin(xyz[:, 0] / CURVE_RADIUS), CURVE_RADIUS - r * np.cos(xyz[:, 0] / CURVE_RADIUS),
                            xyz[:, 2]])


def _unbend(p):
    return np.column_stack([CURVE_RADIUS * np.arctan2(p[:, 0], CURVE_RADIUS - p[:, 1]),
                            CURVE_RADIUS - np.hypot(p[:, 0], CURVE_RADIUS - p[:, 1]), p[:, 2]])


def _curved_tube(seed, lag, run):
    """25 m of a featureless tube on the curve with one box on its wall, ``lag`` m behind."""
    rng = np.random.default_rng(seed)
    xyz = np.vstack([tunnel_xyz(-12.5, 12.5, density=300, seed=seed, features=False),
                     _box(rng, 300, (7.0, HALF_WIDTH - 0.3, 1.0), (7.6, HALF_WIDTH, 1.7))])
    t = 1000.0 + xyz[:, 0] / 10.0
    order = np.argsort(t)
    return PointTile(_bend(xyz[order] - [lag, 0.0, 0.0]) + rng.normal(0, 0.01, xyz.shape), t[order], run_id=run,
                     name=run)


@pytest.mark.parametrize("votes_off", [2.0, -2.5])
def test_a_curve_placed_by_a_box_far_from_its_start_is_fitted_again_there(votes_off):
    """The votes put run b metres along the curve from where it is; the box places the curve's
    along-track offset there. Its windows, fitted where the votes put run b, lean across the
    track on a curve (6 mm here; 4.6 cm on mixed 5, where the fitted axis was also 0.9 degrees
    off): the pair is fitted again where the box puts it, to a millimetre or two."""
    a, b = _curved_tube(0, 0.0, "A"), _curved_tube(1, LAG, "B")
    truth = lambda p: _bend(_unbend(p) + [LAG, 0.0, 0.0]) - p  # noqa: E731  (p_a = p_b + d)
    pick = np.random.default_rng(5).choice(len(a), 60, replace=False)  # keypoints voting for the wrong place
    wrong = truth(np.zeros((1, 3)))[0] + [votes_off, 0.0, 0.0]
    off = registry().create("matcher", "pair_voting", {"max_misalignment": 3.0}).match(
        a, Keypoints(a.xyz[pick], a.gps_time[pick]), b, Keypoints(a.xyz[pick] - wrong, a.gps_time[pick]), None)
    pw = off.info["piecewise"]
    err = off.d - truth(np.array([pw["ref_point"]]))[0]
    axis = np.asarray(pw["axis"])
    assert "moved_to_marks" in off.info and (np.asarray(pw["windows"])[:, 5] == 2).any()
    assert abs(err @ axis) < 0.01 and abs(err @ [-axis[1], axis[0], 0.0]) < 0.003 and abs(err[2]) < 0.003
