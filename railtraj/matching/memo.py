"""What a matcher builds from a tile's points, remembered while that points array is alive.

A tile is the reference (run a) of one to three tile pairs, and the tile cache
(:mod:`railtraj.io.tile_cache`) hands every pair whose crop box holds the whole tile the same
read-only array. Its plane target and KD-tree are therefore built once and serve all those pairs
(and the several fits of one pair) instead of once per pair: on the demo survey 45 builds of each
instead of 88. Entries are keyed by the array's identity, not its contents (hashing 200 k
points would cost more than some builds), and hold only a weak reference to it, so a finished
tile's entries go with its array.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable
from typing import Any

import numpy as np


class ArrayMemo:
    """``build(xyz, *args)`` for the ``size`` most recently used (array, args), by identity."""

    def __init__(self, build: Callable[..., Any], size: int = 2) -> None:
        self.build, self.size = build, size
        self._entries: list[tuple[weakref.ref, tuple, Any]] = []
        self.builds = 0

    def __call__(self, xyz: np.ndarray, *args, **inputs) -> Any:
        """``inputs`` go to ``build`` but are neither part of the key nor kept: what follows from
        ``xyz`` itself (the tile that holds it)."""
        for k, (ref, key, value) in enumerate(self._entries):
            if ref() is xyz and key == args:
                self._entries.insert(0, self._entries.pop(k))
                return value
        value = self.build(xyz, *args, **inputs)
        self.builds += 1
        ref = weakref.ref(xyz)
        self._entries.insert(0, (ref, args, value))
        del self._entries[self.size:]
        weakref.finalize(xyz, self._forget, ref)
        return value

    def _forget(self, ref: weakref.ref) -> None:
        self._entries[:] = [entry for entry in self._entries if entry[0] is not ref]
