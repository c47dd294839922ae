"""The per-process tile cache gives exactly what reading the file gives (railtraj.io.tile_cache)."""

from __future__ import annotations

import numpy as np
import pytest

from railtraj.io.las import read_tile, write_tile
from railtraj.io.tile_cache import TileCache, tile_bytes


@pytest.fixture
def tiles(tmp_path, make_tile):
    paths = []
    for k in range(3):
        path = tmp_path / f"t{k}.laz"
        write_tile(path, make_tile(n=5000, seed=k, name=path.name))
        paths.append(path)
    return paths


def test_crops_equal_cropped_reads_point_for_point(tiles):
    cache = TileCache(1.0)
    full = read_tile(tiles[0], run_id="a")
    lo = full.xyz.min(axis=0) + [3.0, 5.0, -np.inf]
    hi = full.xyz.max(axis=0) - [7.0, 2.0, -np.inf]
    hi[2] = np.inf
    for _ in range(2):  # a miss, then a hit
        got = cache.read(tiles[0], run_id="a", bbox=(lo, hi))
        want = read_tile(tiles[0], run_id="a", bbox=(lo, hi))
        assert 0 < len(got) < len(full)
        for name in ("xyz", "gps_time", "intensity"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
        assert got.name == want.name and got.run_id == "a"
    assert (cache.reads, cache.hits) == (1, 1)


def test_a_box_holding_the_whole_tile_gives_the_cached_tile_itself(tiles):
    """So that what a matcher builds from a tile (its plane target, its KD-tree) serves every
    pair the tile is in (railtraj.matching.memo keys them by the array's identity)."""
    cache = TileCache(1.0)
    full = cache.read(tiles[0])
    box = (full.xyz.min(axis=0), full.xyz.max(axis=0))  # inclusive: every point is inside
    assert cache.read(tiles[0], bbox=box) is full
    part = cache.read(tiles[0], bbox=(box[0], box[1] - [1.0, 0.0, 0.0]))
    assert part is not full and 0 < len(part) < len(full)


def test_cached_tiles_are_read_only(tiles):
    tile = TileCache(1.0).read(tiles[0])
    with pytest.raises(ValueError):
        tile.xyz[0, 0] = 0.0


def test_least_recently_used_tile_goes_first_beyond_the_budget(tiles):
    size = tile_bytes(read_tile(tiles[0]))
    cache = TileCache(2.5 * size / 2**30)  # room for two tiles
    cache.read(tiles[0])
    cache.read(tiles[1])
    cache.read(tiles[0])  # hit: tile 1 is now the oldest
    cache.read(tiles[2])  # evicts tile 1
    cache.read(tiles[0])
    assert (cache.reads, cache.hits) == (3, 2)
    cache.read(tiles[1])
    assert cache.reads == 4


def test_a_rewritten_file_is_read_again(tiles, make_tile):
    cache = TileCache(1.0)
    first = cache.read(tiles[0])
    write_tile(tiles[0], make_tile(n=100, seed=9, name=tiles[0].name))
    assert len(cache.read(tiles[0])) == 100 != len(first)


def test_zero_budget_reads_every_time(tiles):
    cache = TileCache(0.0)
    cache.read(tiles[0])
    cache.read(tiles[0])
    assert (cache.reads, cache.hits) == (2, 0)


def test_a_missing_tile_is_an_input_error(tmp_path):
    from railtraj.errors import InputError

    with pytest.raises(InputError, match="gone.laz"):
        TileCache(1.0).read(tmp_path / "gone.laz")


def test_the_context_is_every_point_of_the_run_near_the_box_that_the_crop_does_not_hold(tmp_path, make_tile):
    """A pair's box reaches 3 m past its tile's edge, where the next tile's points lie: they are
    context, as are both tiles' points up to ``reach`` beyond the box; the crop's are not."""
    paths = []
    for k in range(3):
        path = tmp_path / f"t{k}.laz"
        write_tile(path, make_tile(n=5000, seed=k, origin=(25.0 * k, 0.0, 0.0), size=25.0, name=path.name))
        paths.append(path)
    everything = np.vstack([read_tile(p).xyz for p in paths])
    lo, hi = np.array([-3.0, -3.0, -np.inf]), np.array([28.0, 28.0, np.inf])
    tile = TileCache(1.0).read_with_context(paths[0], "a", tuple(paths[:2]), (lo, hi), 2.5)
    in_box = ((everything >= lo) & (everything <= hi)).all(axis=1)
    near = ((everything >= lo - [2.5, 2.5, 0]) & (everything <= hi + [2.5, 2.5, 0])).all(axis=1)
    own = np.isin(everything[:, 0], read_tile(paths[0]).xyz[:, 0])
    want = everything[near & ~(own & in_box)]
    got = tile.context
    assert len(tile) == (own & in_box).sum() and len(got) == len(want) > 0
    assert (got[:, 0] < 28.0).any()  # the next tile's points inside the box are there
    np.testing.assert_array_equal(np.sort(got[:, 0]), np.sort(want[:, 0]))
