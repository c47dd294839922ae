"""Along-track offset from marks in the intensity, where the geometry has no edges.

A slab-track circular section is a smooth tube: nothing in its shape says where along the
track a point is (:func:`railtraj.matching.piecewise.valley_significance` finds no valley), and
a pair there is used across the track and in height only. Its lining is not one even grey,
though: water stains, soot, repairs and painted markers return more or less light than the
concrete around them, and every tile carries intensity.

Each run's intensity is compared with its own surroundings first: the log-intensity of a point
minus the median of its cross-section cell (``CELL`` metres across and up, over the whole tile).
Range, incidence and surface class are alike along a uniform section, so they leave the cell's
median and only what changes along the track stays; the residual is scaled by its robust sd. A
point of run b is *marked* where its residual exceeds :data:`MARK_SD`; it *agrees* with run a at
a shift ``t`` where run a's nearest point within ``radius`` of it, moved ``t`` along the track,
has a residual of the same sign beyond :data:`AGREE_SD`. The share of marked points that agree,
over the shifts, is a profile like the geometric fitness profile: a mark gives one peak (its
discs overlap most at the true shift), chance agreement a floor, and a repeated pattern (ring
joints, sleepers) one peak per period, which the rival test refuses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

#: cross-section cell (m, across and up) within which intensities are compared
CELL = 0.1
#: points a cell needs for its median; fewer, its points count as unmarked
MIN_CELL_POINTS = 5
#: ... and how much of the track (m, in bins of ALONG_BIN m) its points must cover
MIN_ALONG, ALONG_BIN = 3.0, 0.5
#: a point of run b is on a mark where its residual is beyond this many sd
MARK_SD = 4.0
#: ... and run a agrees there where its residual is within this many sd of run b's (a mark darkens
#: or brightens its surface alike for every run) and beyond half of MARK_SD
AGREE_SD = 2.5
#: marked points a window needs before its profile means anything
MIN_MARKED = 30
#: the share of marked points that agree must rise this far above the profile's floor (chance)
MIN_RISE = 0.25
#: the best rival peak may rise at most this fraction of the main peak's rise
MAX_RIVAL = 0.5
#: ... and the floor be at most this fraction of it: a high floor is a step (a change of surface
#: along the track), which agrees over a range of shifts, not a mark
MAX_FLOOR = 0.5
#: widest peak (m, at half its rise) taken for a mark: a disc of radius r gives about 1.6 r, and a
#: change of surface along the track a ramp metres wide whose centre moves with each run's view
MAX_WIDTH = 1.0
#: step (m) of the shifts searched
STEP = 0.02


def residuals(coords: np.ndarray, intensity: np.ndarray) -> tuple[np.ndarray, float]:
    """Log-intensity minus the median of its cross-section cell (0 in cells with fewer than
    :data:`MIN_CELL_POINTS` points), and the residuals' robust sd. ``coords``: (n, 3) along,
    across, up."""
    if not len(coords):
        return np.zeros(0), 0.0
    level = np.log(np.maximum(np.asarray(intensity, float), 1.0))
    cells = np.floor(coords[:, 1:] / CELL).astype(np.int64)
    _, cell = np.unique(cells, axis=0, return_inverse=True)
    cell = cell.ravel()
    order = np.lexsort((level, cell))
    counts = np.bincount(cell)
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    median = level[order][starts + counts // 2]
    # a cell must run along the track (lining, floor): an object's faces fill a cell over a metre
    # or so, and which of them a run sees depends on its direction of travel. (Not the whole
    # tile: on a 550 m curve a 10 cm cell of a straight frame holds the wall for 4 m or more.)
    bins = np.floor((coords[:, 0] - coords[:, 0].min()) / ALONG_BIN).astype(np.int64)
    n_bins = int(bins.max()) + 1
    covered = np.bincount(np.unique(cell * n_bins + bins) // n_bins, minlength=len(counts))
    keep = (counts >= MIN_CELL_POINTS) & (covered * ALONG_BIN >= MIN_ALONG)
    r = np.where(keep[cell], level - median[cell], 0.0)
    return r, (1.4826 * float(np.median(np.abs(r[r != 0]))) if (r != 0).any() else 0.0)


@dataclass
class IntensityMarks:
    """Run a's intensity residuals and run b's, in one track frame, to slide run b along."""

    tree: cKDTree  # run a's points (along, across, up)
    a_resid: np.ndarray  # log-intensity residuals (:func:`residuals`)
    a_sd: float
    b_coords: np.ndarray  # run b's points (along, across, up), before any offset
    b_resid: np.ndarray
    b_sd: float
    radius: float  # m: how close run a's point must be

    @classmethod
    def build(cls, a_xyz: np.ndarray, a_intensity: np.ndarray, b_xyz: np.ndarray, b_intensity: np.ndarray,
              frame: np.ndarray, origin: np.ndarray, radius: float) -> IntensityMarks:
        """``frame``: rows along, across, up (each run's residuals are its own: its cells need
        not coincide with the other's)."""
        a, b = (a_xyz - origin) @ frame.T, (b_xyz - origin) @ frame.T
        return cls(cKDTree(a), *residuals(a, a_intensity), b, *residuals(b, b_intensity), radius)

    def agreement(self, inside: np.ndarray, offset: np.ndarray, ts: np.ndarray) -> np.ndarray:
        """(len(ts), m) whether each of the m marked points of run b among ``inside``, moved by
        ``offset`` (track frame: one (3,), or one per point of run b (n, 3)) and then ``t`` along
        the track, agrees with run a."""
        marked = inside & (np.abs(self.b_resid) > MARK_SD * self.b_sd) if self.b_sd > 0 else inside & False
        offset = np.asarray(offset, float)
        pts = self.b_coords[marked] + (offset if offset.ndim == 1 else offset[marked])
        level = self.b_resid[marked]
        out = np.zeros((len(ts), len(pts)), bool)
        if not len(pts) or not self.a_sd > 0:
            return out
        lookup = np.append(self.a_resid, 0.0)  # a missing neighbour (index n) agrees with nothing
        tolerance = AGREE_SD * np.hypot(self.a_sd, self.b_sd)
        for k, t in enumerate(ts):  # a few dozen shifts, each one query of all marked points
            _, idx = self.tree.query(pts + np.array([t, 0.0, 0.0]), distance_upper_bound=self.radius)
            a_level = lookup[idx]
            out[k] = (np.abs(a_level - level) <= tolerance) & (np.abs(a_level) > MARK_SD * self.a_sd / 2)
        return out

    def shift(self, inside: np.ndarray, offset: np.ndarray, lo: float, hi: float) -> float:
        """Along-track shift (m) of the marks among ``inside`` from ``offset`` onto run a's,
        searched from ``lo`` to ``hi``; NaN when the profile has no single clear peak
        (:func:`profile_peak`)."""
        ts = np.arange(lo, hi + STEP / 2, STEP)
        agree = self.agreement(inside, offset, ts)
        if agree.shape[1] < MIN_MARKED:
            return float("nan")
        return profile_peak(ts, agree.mean(axis=1))


    def alias_ratio(self, offsets: np.ndarray, lo: float, hi: float) -> tuple[float, float, dict]:
        """How close the best alias along the track comes to the curve that moves run b's points
        by ``offsets`` (n, 3, track frame), by the marks: like the geometric
        :func:`railtraj.matching.piecewise.alias_ratio`, the misfit (share of marked points that
        do not agree) at the curve over that of the best shift beyond the curve's peak, the
        shift to it, and the profile (``points``: the marked points, ``source`` "marks")."""
        ts = STEP * np.arange(np.floor(lo / STEP), np.ceil(hi / STEP) + 1)
        agree = self.agreement(np.ones(len(self.b_coords), bool), offsets, ts)
        share = agree.mean(axis=1) if agree.shape[1] else np.zeros(len(ts))
        profile = {"start": float(ts[0]), "step": STEP, "fitness": share.tolist(), "points": agree.shape[1],
                   "source": "marks"}
        k0 = int(np.argmin(np.abs(ts)))
        floor = float(np.median(share))
        foot = _extent(share - floor, k0, 0.1 * (share[k0] - floor))[0] if share[k0] > floor else ts == ts[k0]
        if foot.all():
            return 0.0, 0.0, profile
        k = int(np.flatnonzero(~foot)[np.argmax(share[~foot])])
        return float((1.0 - share[k0]) / max(1.0 - share[k], 1e-12)), float(ts[k]), profile


def profile_peak(ts: np.ndarray, share: np.ndarray) -> float:
    """Centre of the single clear peak of an agreement profile, NaN if there is none.

    The floor is the profile's median (chance agreement, at most :data:`MAX_FLOOR` of the rise);
    the peak must rise :data:`MIN_RISE` above it, be at most :data:`MAX_WIDTH` wide and lie inside the range with its feet (where it falls to a tenth of its rise), and
    nothing beyond its feet rise more than :data:`MAX_RIVAL` of it. Its centre is the centroid of
    the part above half its rise, which a disc's overlap (a tent, symmetric about the true shift)
    places without bias."""
    floor = float(np.median(share))
    k = int(np.argmax(share))
    rise = share[k] - floor
    if not (rise >= MIN_RISE and floor <= MAX_FLOOR * rise):
        return float("nan")
    half, lo_half, hi_half = _extent(share - floor, k, 0.5 * rise)
    foot, lo, hi = _extent(share - floor, k, 0.1 * rise)
    if lo == 0 or hi == len(ts) - 1:
        return float("nan")  # the peak runs off the range: its centre is not seen
    if (hi_half - lo_half) * (ts[1] - ts[0]) > MAX_WIDTH:
        return float("nan")  # a step or a streak along the track: each run's view moves its centre
    if (~foot).any() and share[~foot].max() - floor > MAX_RIVAL * rise:
        return float("nan")
    w = share[lo_half:hi_half + 1] - floor - 0.5 * rise
    return float((ts[lo_half:hi_half + 1] * w).sum() / w.sum())


def _extent(y: np.ndarray, k: int, level: float) -> tuple[np.ndarray, int, int]:
    """The run of samples around ``k`` where ``y`` stays above ``level``: mask, first, last."""
    below = np.flatnonzero(y <= level)
    lo = int(below[below < k].max()) + 1 if (below < k).any() else 0
    hi = int(below[below > k].min()) - 1 if (below > k).any() else len(y) - 1
    mask = np.zeros(len(y), bool)
    mask[lo:hi + 1] = True
    return mask, lo, hi
