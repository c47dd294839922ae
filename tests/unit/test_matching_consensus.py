"""The dense search for candidate translations where the votes found none."""

from __future__ import annotations

import numpy as np
import pytest

from railtraj.matching.consensus import search_peaks
from railtraj.matching.synthetic import placed, rotation_z, tunnel_tile
from railtraj.matching.target import build_target


@pytest.mark.parametrize("shift", [(0.3, 0.25, 0.1), (0.1, -0.4, -0.2)])
def test_the_search_finds_the_offset_within_its_cube_to_half_a_step(shift):
    """Two scans of a ribbed tunnel 0.3-0.5 m apart: the grid's best translation is the truth's
    nearest node, and the others are distinct candidates (two steps apart at least)."""
    a = placed(tunnel_tile(0, 10, density=600, seed=0))
    b = placed(tunnel_tile(0, 10, density=600, seed=5)).translated(rotation_z(30) @ np.array(shift))
    truth = -rotation_z(30) @ np.array(shift)
    peaks = search_peaks(build_target(a.xyz), b.xyz, np.zeros(3), half=0.5, step=0.05, n=3)
    assert len(peaks) == 3 and all(p.count == 0 for p in peaks)
    assert np.abs(peaks[0].d - truth).max() <= 0.025 + 1e-9, peaks[0].d - truth
    for i in range(3):
        for j in range(i):
            assert np.abs(peaks[i].d - peaks[j].d).max() >= 0.1 - 1e-9
