"""Point-to-plane Gauss-Newton refinement and what it says about the constrained directions.

Point-to-point ICP (kiss-icp) cannot recover an along-track offset in a tunnel: walls slide
along themselves. Point-to-plane only pulls across each surface, so ribs, boxes and sleeper
faces are what fix the along-track position, and the normal matrix ``H = sum w n n^T`` tells
how well: its weak eigenvector points along the tunnel axis (25-80x weaker in the prototype).
Noisy normals on plain walls fake some along-track information, so ``H`` is corrected for the
expected normal tilt (:func:`translation_information`); ``cov = sigma^2 H^-1`` with the sd of
unconstrained directions capped at the search window. It treats points as independent, so on
well-constrained axes it is optimistic; on the simulated tunnels the along-track sd (7-13 mm on
ray-cast tiles) matched the scatter of the estimates.

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
    information: np.ndarray  # 3x3 translation information, corrected for normal noise
    sigma: float  # weighted RMS of the point-to-plane residuals (m)
    fitness: float  # share of moving points within ``fitness_radius`` of the reference
    n_used: int
    iterations: int
    converged: bool
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    # share of moving points on the reference's surface (PlaneTarget.fits): ``fitness`` or more
    # on a target with planes beyond the fitness radius. It decides whether the clouds overlap;
    # ``fitness`` is what alias tests compare (their thresholds were set on it)
    overlap: float = float("nan")


def sample(xyz: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """At most ``n`` points of ``xyz`` drawn without replacement (seeded, reproducible)."""
    if len(xyz) <= n:
        return xyz
    return xyz[np.random.default_rng(seed).choice(len(xyz), n, replace=False)]


def crop(target: PlaneTarget, moving: np.ndarray, d: np.ndarray, margin: float) -> np.ndarray:
    """Moving points that land at least ``margin`` inside the reference once moved by ``d``."""
    return moving[target.inside(moving + d, margin)]


def _linearize(target: PlaneTarget, q: np.ndarray, nearest, kernel: float):
    """Reference planes of the points ``q`` that found one: (mask, index, normals, residuals,
    weights) and every point's distance to the nearest reference voxel (``nearest(q)``: inf
    beyond its ``max_dist``)."""
    idx, dist = nearest(q)
    ok = idx >= 0
    idx = idx[ok]
    n = target.normal[idx]
    r = np.einsum("ij,ij->i", n, q[ok] - target.anchor[idx])
    w = target.weight[idx] * np.minimum(1.0, kernel / np.maximum(np.abs(r), 1e-12))
    return ok, idx, n, r, w, dist


def translation_information(target: PlaneTarget, idx: np.ndarray, n: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``sum w n n^T`` minus what noisy normals add by themselves.

    A fitted normal tilts randomly by ``normal_var`` (rad^2) in-plane, so E[n n^T] of a plain
    wall has ``normal_var`` along the track although nothing there is constrained (a ribbed and a
    plain simulated tunnel got similar weak eigenvalues before this correction). Subtracting
    ``normal_var (I - n n^T)`` leaves the information the geometry really carries.
    """
    H = (n * w[:, None]).T @ n
    v = w * target.normal_var[idx]
    return H - v.sum() * np.eye(3) + (n * v[:, None]).T @ n


def _covariance(info: np.ndarray, sigma: float, max_sd: float) -> np.ndarray:
    """``sigma^2 info^-1`` with every direction's sd capped at ``max_sd`` (the search window)."""
    if not (np.isfinite(info).all() and np.isfinite(sigma)):
        return np.eye(3) * max_sd**2
    vals, vecs = np.linalg.eigh(info)
    var = sigma**2 / np.maximum(vals, sigma**2 / max_sd**2)
    return (vecs * var) @ vecs.T


def point_to_plane(target: PlaneTarget, moving: np.ndarray, d0: np.ndarray, *,
                   translation_only: bool = True, iterations: int = 20, max_dist: float = 0.25,
                   kernel: float = 0.05, tol: float = 1e-4, fitness_radius: float = 0.05,
                   max_sd: float = 3.0, fixed: np.ndarray | None = None) -> Fit:
    """Move ``moving`` onto ``target`` starting from translation ``d0`` (Huber-weighted GN).

    ``max_dist`` bounds the correspondence search, ``kernel`` is the Huber threshold on the
    point-to-plane residual, ``tol`` the step size (m, rad) at which iteration stops, ``max_sd``
    caps the reported sd of unconstrained directions. ``iterations=0`` only evaluates at ``d0``.
    ``fixed`` (a unit vector, translation only): the fit does not move along it.
    With rotation (``translation_only=False``) the covariance is that of the translation with
    the rotation held at its estimate.
    """
    moving = np.asarray(moving, float)
    center = moving.mean(axis=0) if len(moving) else np.zeros(3)
    rot, d = np.eye(3), np.asarray(d0, float).copy()
    npar = 3 if translation_only else 6
    sigma, n_used, converged, it, prev = np.nan, 0, False, 0, None
    info, dist = np.full((3, 3), np.nan), np.full(len(moving), np.inf)
    nearest = target.tracker(max(max_dist, fitness_radius, target.surface_reach))
    # the directions the fit moves in: all, or those across ``fixed``
    free = np.eye(npar) if fixed is None else np.linalg.svd(np.eye(3) - np.outer(fixed, fixed))[0][:, :2]
    for it in range(iterations + 1):
        q = (moving - center) @ rot.T + center + d
        ok, idx, n, r, w, dist = _linearize(target, q, nearest, kernel)
        n_used = int((w > 0).sum())
        if n_used < 2 * npar:
            break
        sigma = float(np.sqrt((w * r**2).sum() / max(w.sum() - npar, 1.0)))
        info = translation_information(target, idx, n, w)
        J = n if translation_only else np.hstack([np.cross(q[ok] - center - d, n), n])
        Jw = (J * w[:, None]).T
        H = free.T @ (Jw @ J) @ free  # (the small matrices last: nothing per point twice)
        if it == iterations or converged or np.linalg.cond(H) > 1e12:
            break  # the last pass only linearizes at the final estimate (info, sigma, fitness)
        step = -free @ np.linalg.solve(H, free.T @ (Jw @ r))
        if prev is not None and step @ prev < 0:
            step = 0.5 * step  # correspondences flip between neighbouring voxels: damp the cycle
        prev = step
        if translation_only:
            d = d + step
        else:
            rot = Rotation.from_rotvec(step[:3]).as_matrix() @ rot
            d = d + step[3:]
        converged = bool(np.abs(step).max() < tol)
    share = float(np.mean(dist <= fitness_radius)) if len(moving) else 0.0
    overlap = share
    if len(moving) and target.surface is not None:  # on the last linearization's points (q, ok, idx)
        nearest_idx = np.full(len(moving), -1)
        nearest_idx[ok] = idx
        overlap = float(np.mean(target.fits(q, nearest_idx, dist, fitness_radius)))
    return Fit(d, _covariance(info, sigma, max_sd), info, sigma, share, n_used, it, converged, rot, center, overlap)


def directions(information: np.ndarray) -> dict:
    """Eigenvalues (ascending) and eigenvectors (columns) of a 3x3 information matrix, as lists."""
    if not np.isfinite(information).all():
        return {"eigenvalues": [float("nan")] * 3, "eigenvectors": np.full((3, 3), np.nan).tolist()}
    vals, vecs = np.linalg.eigh(information)
    return {"eigenvalues": vals.tolist(), "eigenvectors": vecs.tolist(),
            "weak_direction": vecs[:, 0].tolist(),
            "condition": float(vals[-1] / vals[0]) if vals[0] > 0 else float("inf")}

