"""Points on short objects: the signal boxes, cabinets and doors of a featureless lining.

A slab-track circular section has nothing in its shape that repeats, and nothing that says where
along the track a point is, except the objects fixed to its walls every few tens of metres. A
window's along-track profile (:func:`railtraj.matching.piecewise.along_costs`) does not see
them: it measures distance across run a's surface, which a box's front face slides along, and its
8 000 sampled points hold a few of a box's points at best (session 9: 0.1 % of a tile).

Here every point of a cloud is asked whether the surface through it *ends* along the track
within :data:`MAX_LENGTH` on both sides: moved along the track in :data:`STEP` steps, it finds no
point of its own cloud within ``radius`` (twice the matcher's fitness radius, which follows the
scan's profile spacing). Lining, floor, rails and cable trays run on; a box's faces end at the
box. Such points are *marks* of their own (:mod:`railtraj.matching.intensity`): a box gives one
peak where its two runs' points overlap, as wide as the box.

An end found outside the cloud's footprint is the tile's edge, not an object's (a surface cut by
the tile's edge ends there, in one run and not the other); a box 0.5 m from the edge is still
one. A box across the edge is seen whole in the points the pipeline reads :data:`CONTEXT_M`
beyond the pair's box (``PointTile.context``), and is placed by the one pair whose run a's tile
holds the centre of run a's view of it (:func:`railtraj.matching.intensity.held_objects`).
Periodic parts shorter than MAX_LENGTH (sleepers, ribs) end too; their windows have edges and
never ask, and where a profile of marks has a peak per period it is refused like repeated marks
(:func:`railtraj.matching.intensity.profile_peak`).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

#: longest object (m along the track) taken: boxes and cabinets are 0.4-1.2 m, doors about 1 m;
#: a niche's back wall (2-3 m) has edges the windows see
MAX_LENGTH = 2.0
#: shortest (m): a lone point or a scan line's noise ends at once
MIN_LENGTH = 0.2
#: step (m) of the moves along the track
STEP = 0.1
#: how far (m) beyond a tile pair's box its runs' points are read as context
#: (``PointTile.context``): a box cut by the tile's edge is seen whole, and to end
CONTEXT_M = MAX_LENGTH + 0.5


def short_objects(xyz: np.ndarray, axis: np.ndarray, radius: float) -> np.ndarray:
    """Mask of the points of ``xyz`` (n, 3) on surfaces that end along ``axis`` (unit,
    horizontal) within :data:`MAX_LENGTH` on both sides, at least :data:`MIN_LENGTH` long.

    Most points run on, one way or both, for the whole length (near the tile's edge only the
    other way); only those that find nothing ``MAX_LENGTH`` away either way are followed step
    by step (a box 2 m from another surface along the track is lost)."""
    out = np.zeros(len(xyz), bool)
    if len(xyz) < 2:
        return out
    tree = cKDTree(xyz)
    lo, hi = xyz[:, :2].min(axis=0) + radius, xyz[:, :2].max(axis=0) - radius

    def found(p: np.ndarray) -> np.ndarray:
        return tree.query(p, distance_upper_bound=radius, workers=-1)[0] <= radius

    def within(p: np.ndarray) -> np.ndarray:
        return np.all((p[:, :2] > lo) & (p[:, :2] < hi), axis=1)

    reach = MAX_LENGTH * axis
    idx = np.flatnonzero(~found(xyz + reach))
    idx = idx[~found(xyz[idx] - reach)]
    p = xyz[idx]
    ahead, behind = np.zeros(len(idx)), np.zeros(len(idx))  # how far each way the surface runs on
    going_ahead, going_behind = np.ones(len(idx), bool), np.ones(len(idx), bool)
    for d in np.arange(STEP, MAX_LENGTH + STEP / 2, STEP):  # 20 moves of the few points left
        going_ahead[going_ahead] = found(p[going_ahead] + d * axis)
        going_behind[going_behind] = found(p[going_behind] - d * axis)
        ahead += STEP * going_ahead
        behind += STEP * going_behind
    length = ahead + behind
    # each way's first miss must lie inside the footprint: beyond it the surface ran off the tile
    on_tile = within(p + (ahead + STEP)[:, None] * axis) & within(p - (behind + STEP)[:, None] * axis)
    out[idx[(length + STEP < MAX_LENGTH) & (length >= MIN_LENGTH) & on_tile]] = True
    return out
