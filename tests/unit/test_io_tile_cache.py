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
