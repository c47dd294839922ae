"""The gap between scan profiles, measured from a cloud's points and times."""

from __future__ import annotations

import numpy as np
import pytest

from railtraj.data import PointTile, TileOffset
from railtraj.matching.spacing import (
    DESIGN_SPACING,
    point_spacing,
    profile_gap_ratio,
    profile_sampling,
    radius_scale,
    sparse_profiles_note,
)


def _profiles(gap: float, rate: float = 250.0, per_profile: int = 500, length: float = 25.0) -> PointTile:
    """A rotating profile scanner in a 3 m radius tube: one circle every ``gap`` metres."""
    n = int(length / gap)
    angle = np.tile(np.linspace(0, 2 * np.pi, per_profile, endpoint=False), n)
    k = np.repeat(np.arange(n), per_profile)
    xyz = np.column_stack([k * gap, 3 * np.cos(angle), 3 * np.sin(angle)])
    t = 1000.0 + k / rate + angle / (2 * np.pi * rate)
    return PointTile(xyz, t, np.full(len(t), 1000, np.uint16))


@pytest.mark.parametrize("gap", [0.04, 0.08, 0.16])
def test_profile_spacing_is_the_gap_between_profiles(gap):
    assert profile_sampling(_profiles(gap))[0] == pytest.approx(gap, rel=0.1)


def test_a_faster_runs_profiles_are_as_many_times_further_apart():
    slow, fast = _profiles(0.02, length=10.0), _profiles(0.08, length=10.0)
    assert profile_gap_ratio(fast, slow) == pytest.approx(4.0, rel=0.1)
    assert profile_gap_ratio(slow, fast) == pytest.approx(0.25, rel=0.1)
    few = PointTile(slow.xyz[:3], slow.gps_time[:3], slow.intensity[:3])  # nothing to measure: NaN
    assert np.isnan(profile_gap_ratio(fast, few)) and np.isnan(profile_gap_ratio(few, fast))


def test_radius_scale_grows_only_beyond_the_design_spacing():
    assert radius_scale(_profiles(0.04))[0] == 1.0
    scale, spacing = radius_scale(_profiles(0.04), _profiles(0.16))
    assert scale == pytest.approx(0.16 / DESIGN_SPACING, rel=0.1) and spacing == pytest.approx(0.16, rel=0.1)


@pytest.mark.parametrize("per_profile", [500, 100])
def test_profile_spacing_is_measured_when_a_profiles_points_lie_further_apart_than_the_profiles(per_profile):
    """100 points round a 3 m tube lie 19 cm apart, the profiles 4 cm: a point's nearest
    neighbour is in the next profile (the held-out surveys with 250-350 points per profile)."""
    gap, along = profile_sampling(_profiles(0.04, per_profile=per_profile))
    assert gap == pytest.approx(0.04, rel=0.1)
    assert along == pytest.approx(2 * np.pi * 3.0 / per_profile, rel=0.1)


def test_radius_scale_follows_the_area_each_point_of_a_sparse_profile_samples():
    scale, gap = radius_scale(_profiles(0.04, per_profile=100))
    assert scale == pytest.approx(np.sqrt(0.04 * 2 * np.pi * 3.0 / 100) / DESIGN_SPACING, rel=0.1)
    assert gap == pytest.approx(0.04, rel=0.1)  # the profile gap still places edges along the track


def _pair(status: str, tile: PointTile, other: PointTile) -> TileOffset:
    return TileOffset("a", "b", "t", "t", status=status, info={"point_spacing": point_spacing(tile, other)})


def test_a_survey_of_sparse_profiles_is_told_so_and_a_dense_one_is_not():
    sparse, dense = _profiles(0.04, per_profile=100), _profiles(0.04)  # points 0.19 and 0.04 m apart on each circle
    assert point_spacing(dense, sparse) == pytest.approx(2 * np.pi * 3.0 / 100, rel=0.1)  # the coarser tile's
    note = sparse_profiles_note([_pair("ok", sparse, sparse), _pair("ambiguous", sparse, sparse),
                                 _pair("no_overlap", sparse, dense)])
    assert "0.19 m apart along each profile" in note and "1 of 3" in note
    assert sparse_profiles_note([_pair("ok", dense, dense), _pair("ok", dense, dense), _pair("ok", sparse, dense)]) is None
    assert sparse_profiles_note([TileOffset("a", "b", "t", "t")]) is None  # nothing measured: nothing said


def test_too_few_points_say_nothing():
    tile = _profiles(0.04)
    assert np.isnan(profile_sampling(tile.subset(np.arange(10)))[0])


def test_a_tile_is_measured_once_while_its_points_are_alive():
    from railtraj.matching import spacing

    tile, other = _profiles(0.04), _profiles(0.08)
    before = spacing._samplings.builds
    assert spacing.tile_sampling(tile)[0] == profile_sampling(tile)[0]
    radius_scale(tile)
    radius_scale(tile, other)
    assert spacing._samplings.builds - before == 2  # tile once, other once
    assert radius_scale(tile, other)[1] == pytest.approx(0.08, rel=0.1)
