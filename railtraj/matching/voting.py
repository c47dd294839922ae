"""Translation voting: the thesis' exhaustive-pair outlier removal, done in translation space.

Thesis Algorithm 2 takes the translation proposed by each keypoint pair and counts how many
pairs it aligns (inliers), hypothesis by hypothesis: O(N^4) for N keypoints per side, over an
hour for 700. Every pair whose translation lies within ``radius`` of a hypothesis is exactly
one of its inliers, so the same counts come from a KD-tree over the pair translations, and
only pairs inside the search window (the maximum expected misalignment) need to exist at all:
700 x 700 keypoints take about 0.1 s.

Tunnels repeat: ribs every 1.5 m and sleepers every 0.65 m make competing peaks, so we return
the few best *distinct* peaks (not just the best) for a dense check to choose among.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from railtraj.matching.neighbours import ball_members
from railtraj.matching.threads import query_workers


@dataclass(frozen=True)
class Votes:
    """All pair translations inside the window: ``d[k] = a[ia[k]] - b[ib[k]]``."""

    d: np.ndarray
    ia: np.ndarray
    ib: np.ndarray
    center: np.ndarray
    window: float

    def __len__(self) -> int:
        return len(self.d)

    def near(self, t: np.ndarray, radius: float) -> np.ndarray:
        """Indices of the pairs whose translation is within ``radius`` of ``t``."""
        return np.flatnonzero(((self.d - t) ** 2).sum(axis=1) <= radius**2)

    def background(self, radius: float) -> float:
        """Votes a hypothesis would get by chance if translations filled the window uniformly."""
        return len(self) * (radius / self.window) ** 3


@dataclass(frozen=True)
class Peak:
    d: np.ndarray  # mean translation of its inliers (mean shift converged)
    count: int  # inlier pairs within the radius


def pair_translations(a: np.ndarray, b: np.ndarray, center: np.ndarray | None = None,
                      window: float = 3.0) -> Votes:
    """Translations a_i - b_j of every keypoint pair within ``window`` of ``center`` (a sphere)."""
    center = np.zeros(3) if center is None else np.asarray(center, float)
    if len(a) == 0 or len(b) == 0:
        z = np.zeros(0, np.int64)
        return Votes(np.zeros((0, 3)), z, z, center, window)
    ib, ia = ball_members(cKDTree(a), b + center, window)
    return Votes(a[ia] - b[ib], ia, ib, center, window)


def counts(votes: Votes, radius: float) -> np.ndarray:
    """Inlier count of every pair's own translation as a hypothesis (thesis Algorithm 2)."""
    if len(votes) == 0:
        return np.zeros(0, np.int64)
    tree = cKDTree(votes.d)
    return tree.query_ball_point(votes.d, radius, return_length=True, workers=query_workers(len(votes.d)))


def mean_shift(votes: Votes, t: np.ndarray, radius: float, steps: int = 5) -> Peak:
    """Move ``t`` to the mean of its inliers until it settles; the peak and its inlier count."""
    members = votes.near(t, radius)
    for _ in range(steps):
        if len(members) == 0:
            break
        t_new = votes.d[members].mean(axis=0)
        moved = np.abs(t_new - t).max()
        t, members = t_new, votes.near(t_new, radius)
        if moved < 1e-4:
            break
    return Peak(np.asarray(t, float), len(members))


def find_peaks(votes: Votes, radius: float, n_peaks: int = 5,
               separation: float | None = None) -> list[Peak]:
    """The ``n_peaks`` best distinct vote peaks, best first.

    Greedy: take the hypothesis with most inliers, refine it by mean shift, drop every
    hypothesis within ``separation`` (default 2.5 radius) of it, repeat.
    """
    if len(votes) == 0:
        return []
    separation = 2.5 * radius if separation is None else separation
    score = counts(votes, radius).astype(float)
    alive = np.ones(len(votes), bool)
    peaks: list[Peak] = []
    while len(peaks) < n_peaks and alive.any():
        k = int(np.argmax(np.where(alive, score, -1)))
        peak = mean_shift(votes, votes.d[k], radius)
        alive[((votes.d - peak.d) ** 2).sum(axis=1) <= separation**2] = False
        alive[k] = False
        if all(np.abs(peak.d - p.d).max() > radius for p in peaks):
            peaks.append(peak)
    peaks.sort(key=lambda p: -p.count)
    return peaks


def slices(votes: Votes, t: np.ndarray, radius: float, bin_size: float = 0.05) -> dict:
    """Histograms through ``t`` along x, y and z of the translations within ``radius`` of it in
    the other two axes: the peaks at the rib and sleeper spacing show up along the track."""
    edges = np.arange(-votes.window, votes.window + bin_size / 2, bin_size)
    out = {"start": float(-votes.window), "bin": bin_size}
    for k, axis in enumerate("xyz"):
        other = [j for j in range(3) if j != k]
        sel = (np.abs(votes.d[:, other] - t[other]) <= radius).all(axis=1)
        out[axis] = np.histogram(votes.d[sel, k] - t[k], edges)[0].tolist()
    return out
