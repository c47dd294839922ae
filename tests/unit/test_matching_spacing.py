"""The gap between scan profiles, measured from a cloud's points and times."""

from __future__ import annotations

import numpy as np
import pytest

from railtraj.data import PointTile
from railtraj.matching.spacing import DESIGN_SPACING, profile_spacing, radius_scale


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
    assert profile_spacing(_profiles(gap)) == pytest.approx(gap, rel=0.1)


def test_radius_scale_grows_only_beyond_the_design_spacing():
    assert radius_scale(_profiles(0.04))[0] == 1.0
    scale, spacing = radius_scale(_profiles(0.04), _profiles(0.16))
    assert scale == pytest.approx(0.16 / DESIGN_SPACING, rel=0.1) and spacing == pytest.approx(0.16, rel=0.1)


def test_too_few_points_say_nothing():
    tile = _profiles(0.04)
    assert np.isnan(profile_spacing(tile.subset(np.arange(10))))


def test_a_tile_is_measured_once_while_its_points_are_alive():
    from railtraj.matching import spacing

    tile, other = _profiles(0.04), _profiles(0.08)
    before = spacing._spacings.builds
    assert spacing.tile_spacing(tile) == profile_spacing(tile)
    radius_scale(tile)
    radius_scale(tile, other)
    assert spacing._spacings.builds - before == 2  # tile once, other once
    assert radius_scale(tile, other)[1] == pytest.approx(0.08, rel=0.1)
