"""Builds remembered per points array (railtraj.matching.memo): by identity, bounded, forgotten
with the array."""

from __future__ import annotations

import gc

import numpy as np

from railtraj.matching.memo import ArrayMemo
from railtraj.matching.target import build_target, cached_target


def test_the_same_array_is_built_once_an_equal_copy_again():
    memo = ArrayMemo(lambda xyz, k: xyz.sum() * k)
    a = np.arange(12.0).reshape(4, 3)
    assert memo(a, 2) == memo(a, 2) == 132.0
    assert memo.builds == 1
    memo(a.copy(), 2)  # same contents, another array: identity is the key
    memo(a, 3)  # other arguments
    assert memo.builds == 3


def test_only_the_most_recent_entries_are_kept():
    memo = ArrayMemo(lambda xyz: object(), size=2)
    a, b, c = (np.zeros((2, 3)) + k for k in range(3))
    first = memo(a)
    memo(b)
    assert memo(a) is first  # a is now the most recent, b the oldest
    memo(c)  # drops b
    assert memo(a) is first and memo.builds == 3
    memo(b)
    assert memo.builds == 4


def test_an_entry_goes_with_its_array():
    memo = ArrayMemo(lambda xyz: len(xyz))
    a = np.zeros((5, 3))
    memo(a)
    del a
    gc.collect()
    assert memo._entries == []


def test_cached_target_equals_a_fresh_build():
    xyz = np.random.default_rng(0).normal(size=(2000, 3)) * [2.0, 2.0, 0.01]
    first = cached_target(xyz, 0.1)
    assert cached_target(xyz, 0.1) is first
    fresh = build_target(xyz, 0.1)
    np.testing.assert_array_equal(first.normal, fresh.normal)
    np.testing.assert_array_equal(first.anchor, fresh.anchor)
