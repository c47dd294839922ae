"""How far apart a cloud's scan profiles are, so that radii follow the scanner and not the defaults.

A profile scanner samples densely across the track (centimetres along each profile) and sparsely
along it: the gap between consecutive profiles is the train's speed over the profile rate, 4 cm at
10 m/s and 250 profiles/s, 16 cm at 20 m/s and 125 profiles/s. Along-track matching works at
that resolution. A 5 cm fitness radius that suits the first leaves most points of the second
unmatched, so every pair reads as ``no_overlap``.

:func:`profile_spacing` measures the gap from the data: among a point's nearest neighbours, the
ones scanned in the same profile are microseconds apart, the ones of the next profile a whole
rotation apart. The profile gap is the median distance to the nearest neighbour of another
profile. :func:`radius_scale` turns it into the factor by which the defaults' radii grow.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from railtraj.data import PointTile
from railtraj.matching.memo import ArrayMemo

#: the profile gap the matchers' and detectors' default radii were set for (the simulator's
#: demo and thesis surveys: 4.4-5.2 cm)
DESIGN_SPACING = 0.06


def profile_spacing(tile: PointTile, slice_s: float = 0.4, queries: int = 500, k: int = 24,
                    seed: int = 0) -> float:
    """Median distance (m) from a point to the nearest point of another scan profile.

    Works on the points scanned within ``slice_s`` seconds of the tile's median time (a few
    metres of track at full density). NaN when the tile is too small to tell.
    """
    if len(tile) < 2 * k:
        return float("nan")
    t_mid = float(np.median(tile.gps_time))
    near = np.abs(tile.gps_time - t_mid) <= slice_s / 2
    if near.sum() < 2 * k:
        return float("nan")
    xyz, t = tile.xyz[near], tile.gps_time[near]
    rng = np.random.default_rng(seed)
    q = rng.choice(len(xyz), min(queries, len(xyz)), replace=False)
    dist, idx = cKDTree(xyz).query(xyz[q], k=k + 1)
    dist, dt = dist[:, 1:], np.abs(t[idx[:, 1:]] - t[q][:, None])
    same = np.median(dt[:, 0])  # the nearest neighbour is (nearly always) in the same profile
    other = dt > 20 * max(same, 1e-7)  # a rotation is hundreds of in-profile steps
    if not other.any(axis=1).mean() > 0.5:
        return float("nan")
    first = np.where(other, dist, np.inf).min(axis=1)
    return float(np.median(first[np.isfinite(first)]))


_spacings = ArrayMemo(lambda xyz, tile: profile_spacing(tile), size=8)


def tile_spacing(tile: PointTile) -> float:
    """:func:`profile_spacing` of a tile, measured once while its points array is alive: the
    detector and the matcher of every pair the tile is in ask for it (0.1-0.15 s each on a tile
    of 2.65 M points)."""
    return _spacings(tile.xyz, tile=tile)


def radius_scale(*tiles: PointTile) -> tuple[float, float]:
    """(scale, spacing): the factor (at least 1) by which density-dependent radii grow for these
    tiles, from the largest profile spacing among them."""
    spacing = np.nanmax([tile_spacing(t) for t in tiles] + [0.0])
    return max(1.0, float(spacing) / DESIGN_SPACING), float(spacing)
