"""fpfh attaches one 33-bin histogram per keypoint, in the keypoints' order; none changes nothing."""

from __future__ import annotations

import numpy as np
import pytest

from railtraj.matching.synthetic import tunnel_tile
from railtraj.plugins import registry


@pytest.fixture(scope="module")
def tile_and_keypoints():
    tile = tunnel_tile(0, 8, density=600)
    kp = registry().create("detector", "harris3d", {}).detect(tile)
    return tile, kp


def test_fpfh_rows_follow_the_keypoints_not_sorted_indices(tile_and_keypoints):
    tile, kp = tile_and_keypoints
    fpfh = registry().create("descriptor", "fpfh", {})
    described = fpfh.describe(tile, kp)
    assert described.descriptors.shape == (len(kp), 33)
    assert np.isfinite(described.descriptors).all()
    # Open3D: 3 angle histograms of 100 % each, for the point and for its weighted neighbours
    np.testing.assert_allclose(described.descriptors.sum(axis=1), 600.0, rtol=1e-6)
    perm = np.random.default_rng(0).permutation(len(kp))
    again = fpfh.describe(tile, kp.subset(perm))
    np.testing.assert_allclose(again.descriptors, described.descriptors[perm])
    assert len(np.unique(described.descriptors.round(6), axis=0)) > len(kp) // 2  # not all alike


def test_fpfh_of_no_keypoints_is_empty(tile_and_keypoints):
    tile, kp = tile_and_keypoints
    out = registry().create("descriptor", "fpfh", {}).describe(tile, kp.subset(np.zeros(0, int)))
    assert out.descriptors.shape == (0, 33)


def test_none_returns_the_keypoints_unchanged(tile_and_keypoints):
    tile, kp = tile_and_keypoints
    assert registry().create("descriptor", "none", {}).describe(tile, kp) is kp
