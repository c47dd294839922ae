"""Point-to-plane Gauss-Newton refinement and what it says about the constrained directions.

Point-to-point ICP (kiss-icp) cannot recover an along-track offset in a tunnel: walls slide
along themselves. Point-to-plane only pulls across each surface, so ribs, boxes and sleeper
faces are what fix the along-track position, and the normal matrix ``H = sum w n n^T`` tells
how well: its weak eigenvector points along the tunnel axis (25-80x weaker in the prototype).
``cov = sigma^2 H^-1`` treats points as independent, so its *size* is optimistic (neighbouring
points share errors); its *shape* (which direction is weak) is the useful part.

Moving points are raw points (not voxel centroids) cropped to the interior of the reference,
so that no point near a tile end is pulled onto something that has no counterpart.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from railtraj.matching.target import PlaneTarget


@dataclass(frozen=True)
class Fit:
    """Result of :func:`point_to_plane`: p_ref = R (p - center) + center + d."""

    d: np.ndarray
    cov: np.ndarray
    information: np.ndarray  # 3x3 translation information (Schur complement when 6-DoF)
    sigma: float  # weighted RMS of the point-to-plane residuals (m)
    fitness: float  # share of moving points within ``fitness_radius`` of the reference
    n_used: int
    iterations: int
    converged: bool
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))


def sample(xyz: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """At most ``n`` points of ``xyz`` drawn without replacement (seeded, reproducible)."""
    if len(xyz) <= n:
        return xyz
    return xyz[np.random.default_rng(seed).choice(len(xyz), n, replace=False)]


def crop(target: PlaneTarget, moving: np.ndarray, d: np.ndarray, margin: float) -> np.ndarray:
    """Moving points that land at least ``margin`` inside the reference once moved by ``d``."""
    return moving[target.inside(moving + d, margin)]


def fitness(target: PlaneTarget, moved: np.ndarray, radius: float = 0.05) -> float:
    """Share of ``moved`` points with a reference voxel centroid within ``radius``."""
    if len(moved) == 0:
        return 0.0
    idx, _ = target.nearest(moved, radius)
    return float(np.mean(idx >= 0))


def point_to_plane(target: PlaneTarget, moving: np.ndarray, d0: np.ndarray, *,
                   translation_only: bool = True, iterations: int = 20, max_dist: float = 0.25,
                   kernel: float = 0.05, tol: float = 1e-4, fitness_radius: float = 0.05) -> Fit:
    """Move ``moving`` onto ``target`` starting from translation ``d0`` (Huber-weighted GN).

    ``max_dist`` bounds the correspondence search, ``kernel`` is the Huber threshold on the
    point-to-plane residual, ``tol`` the step size (m, rad) at which iteration stops.
    """
    moving = np.asarray(moving, float)
    center = moving.mean(axis=0) if len(moving) else np.zeros(3)
    rot, d = np.eye(3), np.asarray(d0, float).copy()
    npar = 3 if translation_only else 6
    H = np.zeros((npar, npar))
    sigma, n_used, converged, it = np.nan, 0, False, 0
    for it in range(1, iterations + 1):
        q = (moving - center) @ rot.T + center + d
        idx, _ = target.nearest(q, max_dist)
        ok = idx >= 0
        idx = idx[ok]
        w = target.weight[idx]
        n = target.normal[idx]
        r = np.einsum("ij,ij->i", n, q[ok] - target.anchor[idx])
        w = w * np.minimum(1.0, kernel / np.maximum(np.abs(r), 1e-12))
        J = n if translation_only else np.hstack([np.cross(q[ok] - center - d, n), n])
        H = (J * w[:, None]).T @ J
        n_used = int((w > 0).sum())
        if n_used < 2 * npar or np.linalg.cond(H) > 1e12:
            break
        step = -np.linalg.solve(H, (J * w[:, None]).T @ r)
        sigma = float(np.sqrt((w * r**2).sum() / max(w.sum() - npar, 1.0)))
        if translation_only:
            d = d + step
        else:
            rot = Rotation.from_rotvec(step[:3]).as_matrix() @ rot
            d = d + step[3:]
        if np.abs(step).max() < tol:
            converged = True
            break
    info3 = H if translation_only else H[3:, 3:] - H[3:, :3] @ np.linalg.pinv(H[:3, :3]) @ H[:3, 3:]
    try:
        cov = sigma**2 * np.linalg.inv(info3) if n_used >= 2 * npar else np.full((3, 3), np.inf)
    except np.linalg.LinAlgError:
        cov = np.full((3, 3), np.inf)
    moved = (moving - center) @ rot.T + center + d
    return Fit(d, cov, info3, sigma, fitness(target, moved, fitness_radius), n_used, it,
               converged, rot, center)


def directions(information: np.ndarray) -> dict:
    """Eigenvalues (ascending) and eigenvectors (columns) of a 3x3 information matrix, as lists."""
    if not np.isfinite(information).all():
        return {"eigenvalues": [float("nan")] * 3, "eigenvectors": np.full((3, 3), np.nan).tolist()}
    vals, vecs = np.linalg.eigh(information)
    return {"eigenvalues": vals.tolist(), "eigenvectors": vecs.tolist(),
            "weak_direction": vecs[:, 0].tolist(),
            "condition": float(vals[-1] / vals[0]) if vals[0] > 0 else float("inf")}
