"""Point-to-plane refinement: known offsets, the weak direction, and the noise-corrected information."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from railtraj.matching.refine import crop, directions, point_to_plane, sample
from railtraj.matching.synthetic import placed, rotation_z, tunnel_tile
from railtraj.matching.target import build_target

SHIFT = np.array([0.5, 1.5, 0.1])  # tunnel frame: along, across, up


@pytest.fixture(scope="module")
def ribbed():
    a = placed(tunnel_tile(0, 10, density=600, seed=0))
    b = placed(tunnel_tile(0, 10, density=600, seed=5)).translated(rotation_z(30) @ SHIFT)
    return build_target(a.xyz), b, -rotation_z(30) @ SHIFT


def _fit(target, b, d0, **kw):
    moving = crop(target, sample(b.xyz, 60_000), d0, 0.3)
    return point_to_plane(target, moving, d0, **kw)


def test_recovers_a_known_offset_from_3_cm_off_to_millimetres(ribbed):
    target, b, truth = ribbed
    fit = _fit(target, b, truth + [0.03, -0.02, 0.02])
    assert np.abs(fit.d - truth).max() < 0.002, (fit.d - truth) * 1000
    assert fit.fitness > 0.9
    assert fit.converged


def test_weak_direction_is_the_tunnel_axis(ribbed):
    target, b, truth = ribbed
    fit = _fit(target, b, truth)
    dirs = directions(fit.information)
    axis = rotation_z(30) @ [1.0, 0.0, 0.0]
    assert abs(np.dot(dirs["weak_direction"], axis)) > 0.95
    assert dirs["eigenvalues"][0] < dirs["eigenvalues"][2] / 3
    sd = np.sqrt(np.linalg.eigvalsh(fit.cov))
    assert sd[-1] > sd[0] and np.isfinite(sd).all()


def test_featureless_tube_has_no_real_along_track_information():
    a = placed(tunnel_tile(0, 10, density=600, seed=0, features=False))
    b = placed(tunnel_tile(0, 10, density=600, seed=5, features=False))
    target = build_target(a.xyz)
    ribbed_target = build_target(placed(tunnel_tile(0, 10, density=600, seed=0)).xyz)
    ribbed_b = placed(tunnel_tile(0, 10, density=600, seed=5))
    plain = _fit(target, b, np.zeros(3))
    ribs = _fit(ribbed_target, ribbed_b, np.zeros(3))
    per_point = [directions(f.information)["eigenvalues"][0] / f.n_used for f in (plain, ribs)]
    assert per_point[0] < 0.02 < per_point[1], per_point


def test_six_dof_recovers_a_small_rotation(ribbed):
    target, b, truth = ribbed
    c = b.xyz.mean(axis=0)
    rot = Rotation.from_euler("z", 0.3, degrees=True).as_matrix()
    turned = (b.xyz - c) @ rot.T + c
    moving = crop(target, sample(turned, 60_000), truth, 0.3)
    fit = point_to_plane(target, moving, truth, translation_only=False)
    angle = Rotation.from_matrix(fit.rotation @ rot).magnitude()
    assert np.degrees(angle) < 0.03
    assert fit.fitness > 0.9


def test_evaluation_only_does_not_move():
    target = build_target(np.random.default_rng(0).uniform(0, 1, (5000, 3)))
    moving = np.random.default_rng(1).uniform(0, 1, (500, 3))
    fit = point_to_plane(target, moving, np.zeros(3), iterations=0)
    assert (fit.d == 0).all()
