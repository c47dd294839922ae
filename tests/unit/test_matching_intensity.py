"""Intensity marks place a featureless window along the track, and refuse where they cannot."""

import numpy as np
import pytest

from railtraj.matching.intensity import IntensityMarks, profile_peak

LENGTH, RADIUS, DENSITY = 20.0, 3.0, 400.0


def tube(rng, shift=0.0):
    """The upper half of a smooth tube along x (no edges anywhere), sampled at random; x moved
    by ``-shift`` (so ``shift`` moves it back)."""
    n = rng.poisson(DENSITY * LENGTH * np.pi * RADIUS)
    x, phi = rng.uniform(0, LENGTH, n), rng.uniform(0, np.pi, n)
    return np.column_stack([x - shift, RADIUS * np.cos(phi), RADIUS * np.sin(phi)]), x, phi


def intensity(rng, x, phi, marks):
    """A smooth angle-dependent level, 6 % noise, and each mark's gain inside its disc."""
    level = 20000 * (0.6 + 0.4 * np.sin(phi)) * (1 + 0.06 * rng.standard_normal(len(x)))
    for xm, phim, r, gain in marks:
        inside = (x - xm) ** 2 + (RADIUS * (phi - phim)) ** 2 <= r**2
        level[inside] *= gain
    return level.astype(np.uint16)


def pair(marks, shift, seed=0):
    rng = np.random.default_rng(seed)
    a, xa, pa = tube(rng)
    b, xb, pb = tube(rng, shift)
    return IntensityMarks.build(a, intensity(rng, xa, pa, marks), b, intensity(rng, xb, pb, marks),
                                np.eye(3), np.zeros(3), radius=0.05)


@pytest.mark.parametrize("shift", [0.37, -0.81])
def test_a_mark_places_a_window_without_edges(shift):
    marks = pair([(8.0, 1.2, 0.35, 1.7), (13.0, 2.0, 0.3, 0.6)], shift)
    s, t = marks.place(5.0, 10.0, np.zeros(3), -1.5, 1.5)
    assert abs(t - shift) < 0.02  # MARKS_SD_FLOOR: one disc of ~150 points places a window to 1-2 cm
    assert abs(s - (8.0 - shift)) < 0.1  # where the mark is in run b
    s, t = marks.place(5.0, 15.0, np.zeros(3), -1.5, 1.5)
    assert abs(t - shift) < 0.02 and 8.0 - shift < s < 13.0 - shift


def test_a_mark_cut_by_the_window_end_is_taken_whole_and_left_to_the_window_it_lies_in():
    marks = pair([(8.0, 1.2, 0.5, 1.7)], 0.3)  # in run b at 7.7, 0.5 m across
    s, t = marks.place(2.7, 7.5, np.zeros(3), -1.5, 1.5)
    assert np.isnan(t)  # the next window's mark
    s, t = marks.place(7.5, 12.3, np.zeros(3), -1.5, 1.5)
    assert abs(t - 0.3) < 0.03 and abs(s - 7.7) < 0.1  # 1.5 MAX_SD: 500 points on this disc


def test_no_mark_no_shift():
    marks = pair([(8.0, 1.2, 0.35, 1.7)], 0.4)
    assert np.isnan(marks.place(11.0, 16.0, np.zeros(3), -1.5, 1.5)[1])


def test_repeated_marks_are_refused_as_aliases():
    """Marks every 1.0 m (ring bolts) fit every metre alike: no single peak."""
    marks = pair([(x, 1.5, 0.2, 1.8) for x in np.arange(2.0, 19.0, 1.0)], 0.3)
    assert np.isnan(marks.place(5.0, 10.0, np.zeros(3), -1.5, 1.5)[1])


def test_alias_ratio_is_low_on_the_true_shift_and_high_one_mark_off():
    marks = pair([(8.0, 1.2, 0.35, 1.7), (9.5, 1.2, 0.35, 1.7)], 0.5)
    right, _, profile = marks.alias_ratio(lambda xyz: np.tile([0.5, 0.0, 0.0], (len(xyz), 1)), -1.2, 1.2)
    assert right < 0.8 and profile["source"] == "marks" and profile["points"] > 0
    # one mark spacing off, the other mark fits: an alias as good as the curve
    wrong, shift, _ = marks.alias_ratio(lambda xyz: np.tile([0.5 - 1.5, 0.0, 0.0], (len(xyz), 1)), -2.0, 2.0)
    assert wrong > 0.8 and abs(shift - 1.5) < 0.1


def test_profile_peak_is_the_centre_of_a_tent_and_refuses_two():
    ts = np.arange(-1.0, 1.0001, 0.02)
    tent = np.maximum(0.05, 0.8 - 2.5 * np.abs(ts - 0.23))
    assert abs(profile_peak(ts, tent) - 0.23) < 0.005
    two = np.maximum(tent, np.maximum(0.05, 0.7 - np.abs(ts + 0.6) * 3))
    assert np.isnan(profile_peak(ts, two))
    wide = np.arange(-3.0, 3.0001, 0.02)  # 1.5 m wide at half its rise: a step, no mark
    assert np.isnan(profile_peak(wide, np.maximum(0.05, 0.8 - 0.5 * np.abs(wide - 0.23))))
    assert np.isnan(profile_peak(ts, np.full(len(ts), 0.05) + 0.01 * np.sin(ts * 9)))
