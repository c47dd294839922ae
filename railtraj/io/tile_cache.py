"""Tiles read once per process: a bounded cache of whole tiles, keyed by file.

A tile is read in full to detect its keypoints and read again, cropped to the overlap, for every
tile pair it is in: decoding LAZ is most of a tile's I/O (about 80 ms per 330 k points on 2
cores), and a survey's tiles sit in one or two pairs each. :class:`TileCache` keeps the most
recently used whole tiles up to a byte budget and cuts crops out of them with the same inclusive
box test as :func:`railtraj.io.las.read_tile`, so a crop holds the same points in the same order
as a cropped read. Each process (the parent, or each executor worker) has its own cache
(:func:`tile_cache`); entries are keyed by the file's path, size and mtime, so a rewritten tile is
read again. Cached arrays are read-only: a stage that tried to change a tile in place would
otherwise change it for every later pair.
"""

from __future__ import annotations

import os
from collections import OrderedDict
from dataclasses import replace

import numpy as np

from railtraj.data import PointTile
from railtraj.io.las import read_tile
from railtraj.io.trajectory_csv import require_file

#: default budget of the per-process cache (``pipeline.tile_cache_gb``)
DEFAULT_BUDGET_GB = 1.0


def tile_bytes(tile: PointTile) -> int:
    """Memory held by a tile's arrays."""
    return int(tile.xyz.nbytes + tile.gps_time.nbytes + (0 if tile.intensity is None else tile.intensity.nbytes))


def crop(tile: PointTile, lo: np.ndarray, hi: np.ndarray) -> PointTile:
    """The points of ``tile`` inside the inclusive box ``lo``-``hi`` (as ``read_tile(bbox=)``);
    ``tile`` itself when the box holds all of them (so what a matcher builds from a tile's
    arrays, :mod:`railtraj.matching.memo`, serves every pair it is in)."""
    inside = ((tile.xyz >= lo) & (tile.xyz <= hi)).all(axis=1)
    return tile if inside.all() else tile.subset(inside)


class TileCache:
    """Whole tiles by file, least recently used dropped first beyond ``budget_gb`` (0: off)."""

    def __init__(self, budget_gb: float = DEFAULT_BUDGET_GB) -> None:
        self.budget = int(budget_gb * 2**30)
        self._tiles: OrderedDict[tuple, PointTile] = OrderedDict()
        self._bytes = 0
        self.reads = self.hits = 0

    def read(self, path: str | os.PathLike, run_id: str = "",
             bbox: tuple[np.ndarray, np.ndarray] | None = None) -> PointTile:
        """The tile at ``path`` (only inside ``bbox`` when given), from memory when cached."""
        p = require_file(path, "LAS/LAZ file")  # a missing tile: read_tile's one-line error
        st = p.stat()
        key = (str(p.resolve()), st.st_size, st.st_mtime_ns, run_id)
        tile = self._tiles.get(key)
        if tile is not None:
            self.hits += 1
            self._tiles.move_to_end(key)
        else:
            self.reads += 1
            tile = read_tile(path, run_id=run_id)
            self._store(key, tile)
        if bbox is None:
            return tile
        return crop(tile, np.asarray(bbox[0], float), np.asarray(bbox[1], float))

    def read_with_context(self, path: str | os.PathLike, run_id: str, around: tuple[os.PathLike, ...],
                          bbox: tuple[np.ndarray, np.ndarray], reach: float) -> PointTile:
        """The tile at ``path`` inside ``bbox``, with its context (``PointTile.context``): the
        run's points within ``reach`` (m, in plan) of the box that the crop does not hold, read
        from the tiles ``around`` (its own among them, beyond the box). The box reaches past the
        tile's edge, and the next tile's points there are context too."""
        tile = self.read(path, run_id=run_id, bbox=bbox)
        parts = [near.xyz[~inside] if os.fspath(other) == os.fspath(path) else near.xyz
                 for other, near, inside in self._near(run_id, around, bbox, reach)]
        return replace(tile, context=np.vstack(parts) if parts else np.zeros((0, 3)))

    def read_joined(self, path: str | os.PathLike, run_id: str, around: tuple[os.PathLike, ...],
                    bbox: tuple[np.ndarray, np.ndarray], reach: float) -> PointTile:
        """As :meth:`read_with_context`, but the points inside ``bbox`` of every tile ``around``
        are the tile's own (named as the tile at ``path``): the run's whole cloud in the box,
        whichever tile holds it, and its context beyond the box."""
        parts, context = [self.read(path, run_id=run_id, bbox=bbox)], []
        for other, near, inside in self._near(run_id, around, bbox, reach):
            context.append(near.xyz[~inside])
            if os.fspath(other) != os.fspath(path):
                parts.append(near.subset(inside))
        intensity = None if any(t.intensity is None for t in parts) else np.concatenate([t.intensity for t in parts])
        return replace(parts[0], xyz=np.vstack([t.xyz for t in parts]),
                       gps_time=np.concatenate([t.gps_time for t in parts]), intensity=intensity,
                       context=np.vstack(context) if context else np.zeros((0, 3)))

    def _near(self, run_id: str, around: tuple[os.PathLike, ...], bbox: tuple[np.ndarray, np.ndarray],
              reach: float):
        """Each tile of ``around`` read within ``reach`` (m, in plan) of ``bbox``, and which of
        those points lie inside the box: ``(path, tile, inside)``."""
        lo, hi = (np.asarray(corner, float) for corner in bbox)
        grow = np.array([reach, reach, 0.0])
        for other in around:
            near = self.read(other, run_id=run_id, bbox=(lo - grow, hi + grow))
            yield other, near, ((near.xyz >= lo) & (near.xyz <= hi)).all(axis=1)

    def _store(self, key: tuple, tile: PointTile) -> None:
        size = tile_bytes(tile)
        if size > self.budget:
            return
        for array in (tile.xyz, tile.gps_time, tile.intensity):
            if array is not None:
                array.flags.writeable = False
        self._tiles[key] = tile
        self._bytes += size
        self._evict()

    def resize(self, budget_gb: float) -> None:
        """Change the budget, dropping the oldest tiles beyond it."""
        self.budget = int(budget_gb * 2**30)
        self._evict()

    def _evict(self) -> None:
        """Drop the least recently used tiles until the cache fits its budget."""
        while self._tiles and self._bytes > self.budget:
            _, old = self._tiles.popitem(last=False)
            self._bytes -= tile_bytes(old)


_cache: TileCache | None = None


def tile_cache(budget_gb: float = DEFAULT_BUDGET_GB) -> TileCache:
    """This process's tile cache, with the budget ``budget_gb``."""
    global _cache
    if _cache is None:
        _cache = TileCache(budget_gb)
    elif _cache.budget != int(budget_gb * 2**30):
        _cache.resize(budget_gb)
    return _cache
