"""Voxel grids: centroids, membership, neighbour sums, block planes and keypoint times."""

from __future__ import annotations

import itertools

import numpy as np

from railtraj.matching.neighbours import smallest_eigen
from railtraj.matching.voxel import block_covariance, nearest_member, neighbour_sums, voxelize


def _cloud(n=5000, seed=0, offset=(530000.0, 180000.0, 20.0)):
    rng = np.random.default_rng(seed)
    return rng.uniform(0, 2, (n, 3)) + offset


def test_voxel_centroids_and_counts_match_a_direct_grouping():
    xyz = _cloud()
    g = voxelize(xyz, 0.25)
    ijk = np.floor((xyz - g.origin) / 0.25).astype(int)
    groups = {}
    for i, key in enumerate(map(tuple, ijk)):
        groups.setdefault(key, []).append(i)
    assert len(g) == len(groups)
    assert g.count.sum() == len(xyz)
    for members in list(groups.values())[:50]:
        v = g.inverse[members[0]]
        assert (g.inverse[members] == v).all()
        np.testing.assert_allclose(g.xyz[v], xyz[members].mean(axis=0), atol=1e-9)


def test_nearest_member_is_the_closest_raw_point_in_the_voxel():
    xyz = _cloud(seed=1)
    g = voxelize(xyz, 0.3)
    vox = np.array([0, 5, 5, 17, len(g) - 1])
    pos = g.xyz[vox] + 0.01
    raw = nearest_member(g, xyz, vox, pos)
    for v, p, r in zip(vox, pos, raw, strict=True):
        members = np.flatnonzero(g.inverse == v)
        assert r == members[np.argmin(((xyz[members] - p) ** 2).sum(axis=1))]


def test_neighbour_sums_equal_the_27_block_brute_force():
    xyz = _cloud(2000, seed=2)
    g = voxelize(xyz, 0.2)
    values = np.random.default_rng(3).normal(size=(len(g), 4))
    ijk = {tuple(k): i for i, k in enumerate(np.floor((g.xyz - g.origin) / 0.2).astype(int))}
    expect = np.zeros_like(values)
    for key, i in ijk.items():
        for off in itertools.product((-1, 0, 1), repeat=3):
            j = ijk.get((key[0] + off[0], key[1] + off[1], key[2] + off[2]))
            if j is not None:
                expect[i] += values[j]
    np.testing.assert_allclose(neighbour_sums(g, values), expect, atol=1e-12)


def test_block_planes_of_a_tilted_plane_far_from_the_origin():
    rng = np.random.default_rng(4)
    uv = rng.uniform(0, 3, (20000, 2))
    normal = np.array([0.3, -0.2, 0.93])
    normal /= np.linalg.norm(normal)
    e1 = np.cross(normal, [1, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    xyz = uv[:, :1] * e1 + uv[:, 1:] * e2 + np.array([530000.0, 180000.0, 20.0])
    g = voxelize(xyz, 0.05)
    n, mean, cov = block_covariance(xyz, g)
    vals, vec = smallest_eigen(cov)
    full = n > 50
    assert np.abs(np.abs(vec[full] @ normal) - 1).max() < 1e-6
    assert np.abs((mean[full] - xyz[0]) @ normal).max() < 1e-6  # block means lie on the plane
    assert vals[full, 0].max() < 1e-10


def test_smallest_eigen_agrees_with_eigh():
    rng = np.random.default_rng(5)
    X = rng.normal(size=(1000, 3, 3)) * [1.0, 0.5, 0.01]
    C = X @ X.transpose(0, 2, 1)
    vals, vec = smallest_eigen(C)
    ref_vals, ref_vecs = np.linalg.eigh(C)
    np.testing.assert_allclose(vals, ref_vals, atol=1e-9)
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", vec, ref_vecs[:, :, 0])), 1, atol=1e-6)
