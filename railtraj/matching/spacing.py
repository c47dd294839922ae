"""How far apart a cloud's scan profiles are, so that radii follow the scanner and not the defaults.

A profile scanner samples densely across the track (centimetres along each profile) and sparsely
along it: the gap between consecutive profiles is the train's speed over the profile rate, 4 cm at
10 m/s and 250 profiles/s, 16 cm at 20 m/s and 125 profiles/s. Along-track matching works at
that resolution. A 5 cm fitness radius that suits the first leaves most points of the second
unmatched, so every pair reads as ``no_overlap``.

:func:`profile_sampling` measures the gap from the data: among a point's nearest neighbours, the
ones scanned in the same profile are microseconds apart, the ones of the next profile a whole
rotation apart. The profile gap is the median distance to the nearest neighbour of another
profile; the spacing along a profile, to the nearest of its own. A scanner with few points per
profile samples a surface coarsely along each profile whatever the gap. :func:`radius_scale`
turns the coarser sampling into the factor by which the defaults' radii grow.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from railtraj.data import PointTile
from railtraj.matching.memo import ArrayMemo

#: the sampling the matchers' and detectors' default radii were set for (the simulator's demo
#: and thesis surveys: profiles 4.4-5.2 cm apart, their points 3.3-4.1 cm apart in the tunnels)
DESIGN_SPACING = 0.06
#: m: a survey whose points lie further apart than this along each profile (the median over its
#: tile pairs) aligns fewer tile pairs (:func:`sparse_profiles_note`)
SPARSE_POINT_SPACING = 0.13


def profile_sampling(tile: PointTile, slice_s: float = 0.4, queries: int = 500, k: int = 24,
                     seed: int = 0) -> tuple[float, float]:
    """(gap, along): the median distance (m) from a point to the nearest point of another scan
    profile, and to the nearest point of its own profile.

    Works on the points scanned within ``slice_s`` seconds of the tile's median time (a few
    metres of track at full density). Two points of one profile are a few scan steps apart in
    time (the median step between consecutive points), two of different profiles a rotation
    (hundreds of steps). NaN where the tile is too small to tell. A sparse profile's nearest
    neighbour lies in the next profile: taking the nearest neighbour's time for the scan step
    told nothing on 250-350 points per profile (4-5 cm gaps, 6-17 cm along a profile), and the
    radii stayed at the defaults while the pairs' fitness fell to 0.26 (``no_overlap``).
    """
    if len(tile) < 2 * k:
        return float("nan"), float("nan")
    t_mid = float(np.median(tile.gps_time))
    near = np.abs(tile.gps_time - t_mid) <= slice_s / 2
    if near.sum() < 2 * k:
        return float("nan"), float("nan")
    xyz, t = tile.xyz[near], tile.gps_time[near]
    step = float(np.median(np.diff(np.sort(t))))  # between consecutive points of one profile
    rng = np.random.default_rng(seed)
    q = rng.choice(len(xyz), min(queries, len(xyz)), replace=False)
    dist, idx = cKDTree(xyz).query(xyz[q], k=k + 1)
    dist, dt = dist[:, 1:], np.abs(t[idx[:, 1:]] - t[q][:, None])
    other = dt > 20 * max(step, 1e-9)  # a rotation is hundreds of scan steps
    nearest = [np.where(mask, dist, np.inf).min(axis=1) for mask in (other, ~other)]
    return tuple(float(np.median(d[np.isfinite(d)])) if np.isfinite(d).mean() > 0.5 else float("nan")
                 for d in nearest)


_samplings = ArrayMemo(lambda xyz, tile: profile_sampling(tile), size=8)


def tile_sampling(tile: PointTile) -> tuple[float, float]:
    """:func:`profile_sampling` of a tile, measured once while its points array is alive: the
    detector and the matcher of every pair the tile is in ask for it (0.1-0.15 s each on a tile
    of 2.65 M points)."""
    return _samplings(tile.xyz, tile=tile)


def profile_gap_ratio(tile: PointTile, other: PointTile) -> float:
    """How many times further apart ``tile``'s scan profiles lie than ``other``'s (NaN where
    either gap is not measured): a run driven faster, or scanned slower, samples the track
    more sparsely."""
    gap, other_gap = tile_sampling(tile)[0], tile_sampling(other)[0]
    return gap / other_gap if other_gap > 0 else float("nan")


def point_spacing(*tiles: PointTile) -> float:
    """The largest spacing (m) of the points along a profile among ``tiles`` (NaN where none tells)."""
    along = np.array([tile_sampling(t)[1] for t in tiles], float)
    return float(np.nanmax(along)) if np.isfinite(along).any() else float("nan")


def median_point_spacing(offsets: list) -> tuple[float, int]:
    """The median over the tile pairs of the points' spacing along a profile (``point_spacing``
    in each pair's info; NaN where none has it), and how many pairs have it."""
    spacing = np.array([o.info.get("point_spacing", np.nan) for o in offsets], float)
    spacing = spacing[np.isfinite(spacing)]
    return (float(np.median(spacing)) if len(spacing) else float("nan")), len(spacing)


def sparse_profiles_note(offsets: list) -> str | None:
    """A warning when the scanner samples each profile too coarsely for the matcher: the median
    over the tile pairs of the points' spacing along a profile (``point_spacing`` in each pair's
    info) beyond :data:`SPARSE_POINT_SPACING`; None otherwise.

    A wall scanned every 0.13 m or more along each profile is rows of points along the track:
    the plane target sees lines, not walls, and the two runs' rows interleave. Points between
    the rows are counted on the walls' planes (:meth:`railtraj.matching.target.PlaneTarget.fits`),
    but fewer pairs pass the alias tests. Five simulated surveys at 100-170 points per profile
    (median spacings 0.136-0.21 m) aligned 10-57 % of their tile pairs along the track and left
    their runs 0.016-0.42 m apart (RMS; 0.59-1.35 m in the input), with the sd saying so; at
    0.124-0.127 m (150-160 points) 1.1-1.3 cm. Session 40 mended two that reported wrong answers
    as reliable (a tube's pairs on ring aliases, a portal's GNSS bias kept), but a twin-track
    tunnel at 130 points per profile still kept 6 cm of a run's portal bias claiming 1.5 cm (3 m
    of its track beyond 3 sd), and control targets are located only to a few centimetres in
    height (up to 8 cm off: rows of points 0.18 m apart on the wall; they claim a third of the
    spacing). The note changes nothing.
    """
    spacing, n = median_point_spacing(offsets)
    if not n or spacing <= SPARSE_POINT_SPACING:
        return None
    aligned = sum(o.status in ("ok", "coarse") for o in offsets)
    return (f"the scan is sparse: its points lie {spacing:.2f} m apart along each profile (median over "
            f"{n} tile pairs; the matcher is checked down to {SPARSE_POINT_SPACING:.2f} m), so walls show "
            f"as rows of points and fewer tile pairs align ({aligned} of {len(offsets)} along the track). Treat the "
            "correction as unverified: at such spacings simulated surveys were left up to 0.4 m apart where few pairs "
            "aligned (the corrected sd says where), part of a run's GNSS bias at a portal was kept with a small sd, and "
            "control targets were located up to 8 cm off in height (they claim a third of the spacing). Scan with more "
            "points per profile for a full correction")


def radius_scale(*tiles: PointTile) -> tuple[float, float]:
    """(scale, gap): the factor (at least 1) by which density-dependent radii grow for these
    tiles, and the largest profile gap among them (what places an edge along the track).

    The scale follows the coarsest sampling among the tiles: the profile gap, or where a
    profile's points lie further apart than that, the side of the area each point samples
    (the geometric mean of the two). Radii grown with the points' spacing along a sparse profile
    itself fitted a smooth circular lining at every shift (the fitness profile flat at 1.0) and
    lost its chain there (a held-out twin-track tunnel at 350 points per profile: 0.012 -> 0.067 m
    inter-run); not grown at all, 250 points per profile matched 40 % of the length (0.114 m).
    """
    sampled = np.array([tile_sampling(t) for t in tiles] + [(0.0, 0.0)])
    gap, along = sampled[:, 0], sampled[:, 1]
    areal = np.sqrt(gap * np.where(np.isfinite(along), along, 0.0))
    coarsest = np.nanmax(np.concatenate([gap, areal]))
    return max(1.0, float(coarsest) / DESIGN_SPACING), float(np.nanmax(gap))
