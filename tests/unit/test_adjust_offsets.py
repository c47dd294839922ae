"""How a tile pair enters the adjustment window by window (railtraj.adjust.offsets)."""

from __future__ import annotations

import numpy as np

from railtraj.adjust.offsets import WEAK_ALONG_SD_M, offset_covariance, resolved_by_window
from railtraj.data import Ties, TileOffset


def _fixed_pair(status: str = "coarse", ties: Ties | None = None) -> TileOffset:
    """A pair the chain fixed, with three windows; its middle one did not find the offset along
    the track (x)."""
    windows = {"time_a": [10.0, 10.5, 11.0], "time_b": [20.0, 20.5, 21.0],
               "d": [[0.30, 0.01, 0.0], [0.0, 0.02, 0.0], [0.32, 0.03, 0.0]], "along": [True, False, True]}
    info = {"time_a": 10.5, "time_b": 20.5, "piecewise": {"axis": [1.0, 0.0, 0.0]}, "weak_windows": windows}
    return TileOffset("run_a", "run_b", "t", "t", np.array([0.31, 0.02, 0.0]), np.diag([0.02, 0.005, 0.005]) ** 2,
                      3, status, ties if ties is not None else Ties.empty("run_a", "run_b"), info)


def test_a_fixed_pair_without_ties_is_its_windows_along_the_track_only_where_they_found_it():
    pair = _fixed_pair()
    parts = resolved_by_window(pair)
    assert [p.info["time_a"] for p in parts] == [10.0, 10.5, 11.0]
    assert [p.info["time_b"] for p in parts] == [20.0, 20.5, 21.0]
    np.testing.assert_array_equal([p.d for p in parts], pair.info["weak_windows"]["d"])
    sd = np.sqrt([np.diag(offset_covariance(p)) for p in parts])
    np.testing.assert_allclose(sd[[0, 2]], np.sqrt(3) * np.sqrt(np.diag(pair.cov)) * np.ones((2, 3)))
    assert sd[1, 0] > WEAK_ALONG_SD_M / 2 and sd[1, 1] == sd[0, 1]  # across still, along not


def test_pairs_with_ties_unresolved_or_with_one_window_stay_whole():
    tie = Ties("run_a", "run_b", [10.0], [20.0], [[0.0, 0.0, 0.0]], [[0.0, 0.0, 0.0]], [1.0])
    one = _fixed_pair()
    one.info["weak_windows"] = {k: v[:1] for k, v in one.info["weak_windows"].items()}
    for pair in (_fixed_pair(ties=tie), _fixed_pair("ambiguous"), one):
        assert resolved_by_window(pair) == [pair]
