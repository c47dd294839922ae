"""The dense search for candidate translations where the votes found none."""

from __future__ import annotations

import numpy as np
import pytest

from railtraj.matching.consensus import grid_fitness, search_peaks
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


@pytest.mark.parametrize(("half", "step", "radius"), [(0.5, 0.05, 0.05), (0.3, 0.04, 0.07), (0.2, 0.1, 0.03)])
def test_grid_fitness_is_a_kd_tree_query_of_every_point_at_every_shift(half, step, radius):
    """From one pair search, the same share at each of the grid's shifts as querying the target's
    KD-tree for every point moved by it (the search's fitness before session 60): equal to the bit."""
    a = placed(tunnel_tile(0, 10, density=300, seed=0))
    b = placed(tunnel_tile(0, 10, density=300, seed=5)).translated(rotation_z(30) @ np.array([0.2, 0.1, 0.05]))
    target = build_target(a.xyz)
    pts = b.xyz[np.random.default_rng(1).choice(len(b.xyz), 300, replace=False)]
    centre = np.array([-0.1, -0.15, -0.03])  # the truth: -0.12, -0.19, -0.05
    g = np.arange(-half, half + step / 2, step)
    axes = [centre[k] + g for k in range(3)]
    shifts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    idx, _ = target.nearest((pts[:, None, :] + shifts[None]).reshape(-1, 3), radius)
    want = (idx >= 0).reshape(len(pts), -1).mean(axis=0)
    assert want.max() - want.min() > 0.2  # the grid reaches from misfit to (near) fit
    np.testing.assert_array_equal(grid_fitness(target, pts, axes, radius), want)
