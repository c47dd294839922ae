"""The vote figure for the report: a PNG for matched and for refused tile pairs."""

from __future__ import annotations

import numpy as np

from railtraj.data import TileOffset
from railtraj.matching.synthetic import second_acquisition, tunnel_tile
from railtraj.plugins import registry
from railtraj.report.votes import plot_votes

PNG = b"\x89PNG\r\n\x1a\n"


def test_plot_of_a_matched_pair(tmp_path):
    a = tunnel_tile(0, 8, density=500)
    b = second_acquisition(a, (0.5, 1.5, 0.1))
    det = registry().create("detector", "harris3d", {})
    off = registry().create("matcher", "pair_voting", {"refine": False}).match(a, det.detect(a), b, det.detect(b))
    assert off.status == "ok"
    slices = off.info["vote_slices"]
    assert max(slices["x"]) > 0 and np.argmax(slices["y"]) == len(slices["y"]) // 2  # peak at the winner
    path = tmp_path / "votes.png"
    plot_votes(off, path)
    assert path.read_bytes()[:8] == PNG and path.stat().st_size > 5000


def test_plot_of_a_pair_without_votes(tmp_path):
    off = TileOffset("a", "b", "ta", "tb", status="few_keypoints", info={"timings": {}})
    plot_votes(off, tmp_path / "none.png")
    assert (tmp_path / "none.png").read_bytes()[:8] == PNG
