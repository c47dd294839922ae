"""Short objects (a box on a plain lining) place a window without edges along the track."""

import numpy as np
import pytest

from railtraj.matching.intensity import IntensityMarks
from railtraj.matching.objects import short_objects

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
    _, _, profile = marks.alias_ratio(np.tile([0.43, 0.0, 0.0], (len(b), 1)), -1.5, 1.5)
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
