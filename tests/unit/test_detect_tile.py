"""A large tile's keypoints are those of the 25 m squares its pairs are matched in
(railtraj.pipeline.detect_tile, railtraj.io.survey.grid_cells)."""

from __future__ import annotations

import types

import numpy as np
import pytest

from railtraj.io.las import read_tile, write_tile
from railtraj.io.survey import grid_cells
from railtraj.matching.synthetic import placed, tunnel_tile
from railtraj.pipeline import detect_tile
from railtraj.plugins import registry
from railtraj.resume import Cache


def test_grid_cells_cut_a_large_tile_on_the_survey_grid_and_leave_a_small_one_whole():
    rng = np.random.default_rng(0)
    xyz = rng.uniform([530010.0, 180000.0, 0.0], [530060.0, 180008.0, 5.0], (2000, 3))
    cells = grid_cells(xyz, 25.0)
    assert sorted(len(c) for c in cells) == sorted(np.bincount(np.floor(xyz[:, 0] / 25).astype(int))[-3:])
    assert np.array_equal(np.sort(np.concatenate(cells)), np.arange(len(xyz)))
    for c in cells:  # every part within one square of the grid
        assert np.ptp(np.floor(xyz[c, :2] / 25.0), axis=0).max() == 0
    for small in (xyz[xyz[:, 0] < 530035.0], xyz):
        part_m = 25.0 if len(small) < len(xyz) else 0.0
        assert len(grid_cells(small, part_m)) == 1


@pytest.fixture(scope="module")
def lining(tmp_path_factory):
    """A featureless lining 50 m long in the survey grid, written as one 50 m tile and as the
    squares of a 25 m grid."""
    folder = tmp_path_factory.mktemp("tiles")
    whole = folder / "whole.laz"
    write_tile(whole, placed(tunnel_tile(0, 50, density=300, features=False, seed=0)))
    tile = read_tile(whole)  # (as stored: the squares hold the very same coordinates)
    squares = []
    for k, idx in enumerate(grid_cells(tile.xyz, 25.0)):
        squares.append(folder / f"square{k}.laz")
        write_tile(squares[-1], tile.subset(idx))
    return whole, squares


def _keypoints(path, part_m):
    stages = types.SimpleNamespace(detector=registry().create("detector", "iss", {}),
                                   descriptor=registry().create("descriptor", "fpfh", {}))
    kp, _ = detect_tile(("A", path, (0.0, 1e9), stages, 1.0, part_m))
    return kp


def test_a_large_tile_gives_the_keypoints_of_its_25_m_squares(lining):
    """Where a square's edge cuts a plain lining the detector fires, at the same place in every
    run: the only keypoints of a featureless tube, and what gives its pairs' offset across and
    up. A 50 m tile detected whole has none in its middle (its pairs' parts there were refused)."""
    whole, squares = lining
    parts = [_keypoints(p, 25.0) for p in squares]
    want = np.vstack([k.xyz for k in parts])
    got = _keypoints(whole, 25.0)
    assert len(squares) >= 3 and len(want) > 0
    np.testing.assert_array_equal(got.xyz, want)
    np.testing.assert_array_equal(got.descriptors, np.vstack([k.descriptors for k in parts]))
    assert len(_keypoints(whole, 0.0)) < len(got)  # detected whole: no cuts inside


def test_the_detection_grid_is_part_of_a_tiles_cache_key(lining, tmp_path):
    """Another ``pipeline.pair_part_m`` detects a large tile in other squares: a resumed run
    must not reuse its keypoints."""
    whole, _ = lining
    cache = Cache(tmp_path, {"detector": {"name": "iss"}, "descriptor": {"name": "fpfh"}})
    keys = {cache.tile_key("A", whole, (0.0, 1e9), part_m) for part_m in (25.0, 25.0, 50.0, 0.0)}
    assert len(keys) == 3
