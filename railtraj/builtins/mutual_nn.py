"""The ``mutual_nn`` matcher: the thesis' descriptor matching (Algorithm 1) and ranking (Algorithm 2).

Algorithm 1 keeps a pair (a_i, b_j) when each is the other's nearest neighbour in descriptor
space; here two KD-tree queries replace the nested loops. Algorithm 2 ranks every matched pair
by how many other pairs its translation aligns (inliers within ``inlier_radius``); here a
KD-tree over the pair translations counts them all at once. The ``top_n`` ranked pairs are
reported in ``info["ranking"]`` as in the thesis; the estimate then goes through the same dense
check, alias test and refinement as ``pair_voting`` (:mod:`railtraj.matching.resolve`), because
in tunnels only about half of the descriptor matches were right in the thesis and repeated
geometry makes confident wrong peaks.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from railtraj.builtins.pair_voting import VotingMatcher, VotingOptions
from railtraj.data import Keypoints, PointTile, TileOffset
from railtraj.errors import ConfigError
from railtraj.hookspecs import hookimpl
from railtraj.matching.voting import Votes, counts


@dataclass
class MutualNnConfig(VotingOptions):
    name: str = "mutual_nn"
    top_n: int = 10  # best-ranked pairs reported (thesis: top 10)
    min_inliers: int = 3  # agreeing pairs the best translation needs; fewer: no_consensus


def mutual_pairs(desc_a: np.ndarray, desc_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Thesis Algorithm 1: indices (ia, ib) of mutual nearest neighbours in descriptor space."""
    if len(desc_a) == 0 or len(desc_b) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    _, ab = cKDTree(desc_b).query(desc_a, workers=-1)
    _, ba = cKDTree(desc_a).query(desc_b, workers=-1)
    ia = np.flatnonzero(ba[ab] == np.arange(len(desc_a)))
    return ia, ab[ia]


class MutualNnMatcher(VotingMatcher):
    """Descriptor mutual-NN matching, translation ranking, dense check (see module docstring)."""

    kind = "mutual_nn"

    def __init__(self, top_n: int = 10, min_inliers: int = 3, **options) -> None:
        super().__init__(min_inliers=min_inliers, **options)
        self.top_n = top_n

    def match(self, tile_a: PointTile, kp_a: Keypoints, tile_b: PointTile, kp_b: Keypoints,
              initial: TileOffset | None = None) -> TileOffset:
        if kp_a.descriptors is None or kp_b.descriptors is None:
            raise ConfigError("matcher=mutual_nn needs descriptors: use descriptor=fpfh")
        t0 = time.perf_counter()
        center, info, refusal = self.open(tile_a, kp_a, tile_b, kp_b, initial)
        if refusal is not None:
            return refusal
        ia, ib = mutual_pairs(kp_a.descriptors, kp_b.descriptors)
        d = kp_a.xyz[ia] - kp_b.xyz[ib]
        inside = ((d - center) ** 2).sum(axis=1) <= self.window**2
        votes = Votes(d[inside], ia[inside], ib[inside], center, self.window)
        ranked = counts(votes, self.settings.inlier_radius)
        top = np.argsort(-ranked, kind="stable")[: self.top_n]
        info.update(mutual_pairs=len(ia), ranking=np.c_[votes.d[top], ranked[top]].tolist())
        info["timings"]["match_descriptors"] = time.perf_counter() - t0
        return self.finish(tile_a, kp_a, tile_b, kp_b, votes, info, t0)


@hookimpl
def railtraj_register_stages(registry) -> None:
    registry.add("matcher", "mutual_nn", MutualNnMatcher, MutualNnConfig)
