"""Translation voting and mutual nearest neighbours against brute force and planted answers."""

from __future__ import annotations

import time

import numpy as np

from railtraj.builtins.mutual_nn import mutual_pairs
from railtraj.matching.consensus import consensus
from railtraj.matching.voting import counts, find_peaks, pair_translations


def _keypoints(n=700, seed=0, shift=(0.4, -1.2, 0.05), inliers=0.5, noise=0.01):
    """Scattered keypoints a, and b = a share of them moved by -shift plus clutter (p_a = p_b + d)."""
    rng = np.random.default_rng(seed)
    a = rng.uniform([0, -3, 0], [25, 3, 5], (n, 3))
    k = int(n * inliers)
    b = np.vstack([a[:k] - shift + rng.normal(0, noise, (k, 3)), rng.uniform([0, -3, 0], [25, 3, 5], (n - k, 3))])
    return a, b, np.asarray(shift)


def test_pair_translations_are_exactly_the_pairs_inside_the_window():
    a, b, _ = _keypoints(60, seed=1)
    center = np.array([0.5, 0.0, 0.0])
    votes = pair_translations(a, b, center, 2.0)
    brute = {(i, j) for i in range(len(a)) for j in range(len(b))
             if np.linalg.norm(a[i] - b[j] - center) <= 2.0}
    assert set(zip(votes.ia.tolist(), votes.ib.tolist(), strict=True)) == brute
    np.testing.assert_allclose(votes.d, a[votes.ia] - b[votes.ib])


def test_counts_are_the_thesis_inlier_counts():
    a, b, _ = _keypoints(40, seed=2)
    votes = pair_translations(a, b, None, 3.0)
    c = counts(votes, 0.1)
    brute = [(np.linalg.norm(votes.d - t, axis=1) <= 0.1).sum() for t in votes.d]
    np.testing.assert_array_equal(c, brute)


def test_peak_recovers_the_planted_translation_fast_for_700_keypoints():
    a, b, shift = _keypoints()
    t = time.perf_counter()
    votes = pair_translations(a, b, None, 3.0)
    peaks = find_peaks(votes, 0.1, 5)
    elapsed = time.perf_counter() - t
    assert np.abs(peaks[0].d - shift).max() < 0.005
    assert peaks[0].count >= 300
    assert peaks[1].count < peaks[0].count / 5
    assert elapsed < 1.0, f"700 x 700 voting took {elapsed:.2f} s"


def test_consensus_uses_each_keypoint_once_and_only_agreeing_pairs():
    a, b, shift = _keypoints(200, seed=3)
    b = np.vstack([b, b[:20] + 0.03])  # near-duplicates of true matches
    votes = pair_translations(a, b, None, 3.0)
    ia, ib = consensus(votes, shift, 0.1)
    assert len(np.unique(ia)) == len(ia) and len(np.unique(ib)) == len(ib)
    assert np.linalg.norm(a[ia] - b[ib] - shift, axis=1).max() <= 0.1
    assert len(ia) >= 95


def test_mutual_pairs_match_the_nested_loops_of_algorithm_1():
    rng = np.random.default_rng(4)
    da, db = rng.random((50, 33)), rng.random((60, 33))
    ia, ib = mutual_pairs(da, db)
    dist = np.linalg.norm(da[:, None] - db[None], axis=2)
    ab, ba = dist.argmin(axis=1), dist.argmin(axis=0)
    expect = [(i, ab[i]) for i in range(50) if ba[ab[i]] == i]
    assert list(zip(ia.tolist(), ib.tolist(), strict=True)) == expect
