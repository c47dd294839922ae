"""Attitude conventions of SPEC.md and the body <-> world transforms built on them.

Body frame: x forward, y right, z down. Attitude (roll, pitch, heading) in degrees, heading
clockwise from grid north. Body -> local NED is R = Rz(heading) Ry(pitch) Rx(roll); the survey
CRS is east-north-up, so a body vector p lands at ``world = origin + M @ R @ p`` with ``M`` the
NED -> ENU axis swap. Everything here is vectorized over epochs.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

#: NED -> ENU axis swap: (N, E, D) -> (E, N, -D). It is its own inverse.
NED_TO_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def attitude_to_rotation(rpy_deg: np.ndarray) -> Rotation:
    """Body -> NED rotations from (n, 3) roll, pitch, heading in degrees."""
    rpy = np.atleast_2d(np.asarray(rpy_deg, dtype=float))
    return Rotation.from_euler("ZYX", rpy[:, ::-1], degrees=True)


def rotation_to_attitude(rot: Rotation) -> np.ndarray:
    """Inverse of :func:`attitude_to_rotation`: (n, 3) roll, pitch, heading in degrees.

    Heading is wrapped to [0, 360) as surveyors expect.
    """
    hpr = np.atleast_2d(rot.as_euler("ZYX", degrees=True))
    rpy = hpr[:, ::-1].copy()
    rpy[:, 2] = np.mod(rpy[:, 2], 360.0)
    return rpy


def body_to_world_matrices(rpy_deg: np.ndarray) -> np.ndarray:
    """(n, 3, 3) matrices ``M @ R`` that take body vectors to ENU world vectors."""
    return NED_TO_ENU @ attitude_to_rotation(rpy_deg).as_matrix()


def attitude_from_direction(direction_enu: np.ndarray, roll_deg: np.ndarray | float = 0.0) -> np.ndarray:
    """Attitude (roll, pitch, heading in degrees) of a body whose x axis points along ``direction_enu``.

    Used by the simulator to derive heading from the track tangent and pitch from the grade.
    """
    d = np.atleast_2d(np.asarray(direction_enu, dtype=float))
    heading = np.degrees(np.arctan2(d[:, 0], d[:, 1]))
    pitch = np.degrees(np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1])))
    roll = np.broadcast_to(np.asarray(roll_deg, dtype=float), heading.shape)
    return np.column_stack([roll, pitch, np.mod(heading, 360.0)])


def track_frames(xyz: np.ndarray) -> np.ndarray:
    """(n, 3, 3): at each epoch of a path ``xyz`` (n, 3), rows along the track (horizontal),
    across it (left) and up. (:func:`railtraj.matching.piecewise.track_frame`: one axis's.)"""
    tangent = np.gradient(xyz[:, :2], axis=0) if len(xyz) > 1 else np.array([[1.0, 0.0]])
    norm = np.linalg.norm(tangent, axis=1)
    tangent = np.where(norm[:, None] > 0, tangent / np.maximum(norm, 1e-12)[:, None], [1.0, 0.0])
    frame = np.zeros((len(xyz), 3, 3))
    frame[:, 0, :2] = tangent
    frame[:, 1, :2] = np.column_stack([-tangent[:, 1], tangent[:, 0]])
    frame[:, 2, 2] = 1.0
    return frame
