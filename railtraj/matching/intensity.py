"""Along-track offset from marks in the intensity, where the geometry has no edges.

A slab-track circular section is a smooth tube: nothing in its shape says where along the
track a point is (:func:`railtraj.matching.piecewise.valley_significance` finds no valley), and
a pair there is used across the track and in height only. Its lining is not one even grey,
though: water stains, soot, repairs and painted markers return more or less light than the
concrete around them, and every tile carries intensity.

Each run's intensity is compared with its own surroundings first: the log-intensity of a point
minus the median of its cross-section cell (:data:`CELL` metres across and up, over the tile).
Range, incidence and surface class are alike along a uniform section, so they stay in the
cell's median and only what changes along the track is left. Cells that do not run along the
track for :data:`MIN_ALONG` metres (the faces of a box, seen from one side or the other
depending on the direction of travel) are left out. A point of run b is *marked* where its
residual is beyond :data:`MARK_SD` sd; it *agrees* with run a at a shift ``t`` where, moved
``t`` along the track, it has a point of run a on a mark within ``radius`` whose residual is
within :data:`AGREE_SD` sd of its own (a stain darkens its surface alike for every run).

Points on short objects (boxes, cabinets, doors: :mod:`railtraj.matching.objects`) are marks
too, whatever their intensity: such a point of run b agrees with run a where, moved, it has a
point of run a's objects within ``radius``. The two kinds are placed and judged each on their
own: one run's chance intensity marks agree with nothing and would flatten a box's profile.

The share of marked points that agree, over the shifts, is a profile like the geometric fitness
profile: a mark gives one narrow peak (its two discs overlap most at the true shift), chance
agreement a low floor. :func:`profile_peak` takes its centre only where nothing else rises
near it: a repeated pattern (ring bolts) gives a peak per period, and a change of surface along
the track (a section's end) a ramp as wide as a run's view of it; both are refused.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from railtraj.matching.consensus import misfit_ratio
from railtraj.matching.objects import MAX_LENGTH, short_objects

#: cross-section cell (m, across and up) within which intensities are compared
CELL = 0.1
#: points a cell needs for its median; fewer, its points count as unmarked
MIN_CELL_POINTS = 5
#: ... and how much of the track (m, in bins of ALONG_BIN m) its points must cover
MIN_ALONG, ALONG_BIN = 3.0, 0.5
#: a point of run b is on a mark where its residual is beyond this many sd
MARK_SD = 4.0
#: ... and run a agrees there where its nearest point beyond AGREE_LEVEL of that (within the
#: radius) has a residual within AGREE_SD sd of run b's: a mark darkens or brightens its surface
#: alike for every run
AGREE_SD, AGREE_LEVEL = 2.5, 0.5
#: marked points a window needs before its profile means anything
MIN_MARKED = 30
#: the share of marked points that agree must rise this far above the profile's floor (chance)
MIN_RISE = 0.25
#: the best rival peak may rise at most this fraction of the main peak's rise
MAX_RIVAL = 0.5
#: ... and the floor be at most this fraction of it: a high floor is a step (a change of surface
#: along the track), which agrees over a range of shifts, not a mark
MAX_FLOOR = 0.5
#: the intensity's and the objects' shifts in one window may differ by this many sd of their
#: difference (a step at least): else they are no one mark's and nothing is placed
CONFLICT_SD = 3.0
#: widest peak (m, at half its rise) taken for a mark: a disc of radius r gives about 1.6 r, and a
#: change of surface along the track a ramp metres wide whose centre moves with each run's view
MAX_WIDTH = 1.0
#: largest sd (m) of a mark's shift (:func:`peak_sd`) taken: MARKS_SD_FLOOR in railtraj.matching.piecewise
MAX_SD = 0.02
#: how far (m) beyond a window's ends its marks are taken whole (the largest mark's radius and more)
REACH = 0.75
#: points of run b's short objects closer than this (m) are one object (:func:`held_objects`)
OBJECT_GAP = 0.3
#: step (m) of the shifts searched in a window, and in a pair's alias profile (which places
#: nothing: the chain only tells its peaks apart, like the geometric profile's 5 cm steps)
STEP, ALIAS_STEP = 0.02, 0.05


def residuals(coords: np.ndarray, intensity: np.ndarray) -> tuple[np.ndarray, float]:
    """Log-intensity minus the median of its cross-section cell (0 in cells with fewer than
    :data:`MIN_CELL_POINTS` points or along less than :data:`MIN_ALONG` of the track), and the
    residuals' robust sd (0 where the tile has no intensity). ``coords``: (n, 3) along, across,
    up."""
    if not len(coords):
        return np.zeros(0), 0.0
    level = np.log(np.maximum(np.asarray(intensity, float), 1.0))
    ij = np.floor(coords[:, 1:] / CELL).astype(np.int64)
    ij -= ij.min(axis=0)
    _, cell = np.unique(ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1], return_inverse=True)
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


@dataclass(frozen=True)
class Surroundings:
    """What lies around a tile pair's clouds: where a short object cut by a tile's edge is seen
    whole (:func:`held_objects`)."""

    a: np.ndarray  # (k, 3) run a's points around its tile (``PointTile.context``)
    b: np.ndarray  # (m, 3) run b's points around its cloud: the rest of its tile, and its context
    a_holds: Callable[[np.ndarray], np.ndarray]  # mask: world points in run a's tile


@dataclass
class IntensityMarks:
    """Run a's intensity residuals and run b's, and each run's short objects, in one track
    frame, to slide run b along."""

    tree: cKDTree  # run a's points (along, across, up) that may agree (beyond AGREE_LEVEL of a mark)
    a_resid: np.ndarray  # their log-intensity residuals (:func:`residuals`)
    a_sd: float
    b_coords: np.ndarray  # run b's points (along, across, up), before any offset
    b_resid: np.ndarray
    b_sd: float
    radius: float  # m: how close run a's point must be
    frame: np.ndarray  # rows along, across, up (world directions)
    origin: np.ndarray  # world point of the frame's origin
    a_objects: cKDTree | None = None  # run a's points on the short objects its tile holds (:func:`held_objects`)
    b_objects: np.ndarray | None = None  # (m, 3) run b's points on short objects, whole (:func:`held_objects`)
    b_object_at: np.ndarray | None = None  # (m,) along-track centre of each one's object

    @classmethod
    def build(cls, a_xyz: np.ndarray, a_intensity: np.ndarray | None, b_xyz: np.ndarray,
              b_intensity: np.ndarray | None, frame: np.ndarray, origin: np.ndarray, radius: float,
              objects: bool = False, around: Surroundings | None = None) -> IntensityMarks:
        """``frame``: rows along, across, up (each run's residuals are its own: its cells need
        not coincide with the other's). Without intensities (None) only ``objects`` mark, seen
        whole with what lies ``around`` the clouds (:func:`held_objects`)."""
        a, b = (a_xyz - origin) @ frame.T, (b_xyz - origin) @ frame.T
        a_resid, a_sd = residuals(a, a_intensity) if a_intensity is not None else (np.zeros(len(a)), 0.0)
        b_resid, b_sd = residuals(b, b_intensity) if b_intensity is not None else (np.zeros(len(b)), 0.0)
        keep = np.abs(a_resid) > AGREE_LEVEL * MARK_SD * a_sd  # only these can agree: a small tree
        out = cls(cKDTree(a[keep]), a_resid[keep], a_sd, b, b_resid, b_sd, radius, frame, origin)
        if objects:  # continuity along the track is looked for within twice the fitness radius
            a_all, b_all = (a_xyz, b_xyz) if around is None else (np.vstack([a_xyz, around.a]), np.vstack([b_xyz, around.b]))
            holds = around.a_holds if around is not None else lambda xyz: np.ones(len(xyz), bool)
            a_on, b_on = (xyz[short_objects(xyz, frame[0], 2 * radius)] for xyz in (a_all, b_all))
            out.a_objects = cKDTree(held_objects((a_on - origin) @ frame.T, lambda c: holds(c @ frame + origin))[0])
            out.b_objects, out.b_object_at = held_objects((b_on - origin) @ frame.T, lambda c: np.ones(len(c), bool))
        return out

    def marked(self, inside: np.ndarray) -> np.ndarray:
        """Mask of run b's points among ``inside`` that lie on an intensity mark (beyond
        :data:`MARK_SD`)."""
        return inside & (np.abs(self.b_resid) > MARK_SD * self.b_sd) if self.b_sd > 0 else np.zeros_like(inside)

    def agreement(self, marked: np.ndarray, offset: np.ndarray, ts: np.ndarray) -> np.ndarray:
        """(len(ts), m) whether each of the m points of run b in ``marked`` (:meth:`marked`),
        moved by ``offset`` (track frame: one (3,), or one per marked point (m, 3)) and then
        ``t`` along the track, has a point of run a on a mark within the radius whose residual
        is within :data:`AGREE_SD` sd of its own."""
        level = self.b_resid[marked]
        lookup = np.append(self.a_resid, np.inf)  # a missing neighbour (index n) agrees with nothing
        tolerance = AGREE_SD * np.hypot(self.a_sd, self.b_sd)

        def agrees(moved: np.ndarray) -> np.ndarray:
            return np.abs(lookup[self.tree.query(moved, distance_upper_bound=self.radius)[1]] - level) <= tolerance

        return _profile(self.b_coords[marked] + offset, ts, agrees if self.a_sd > 0 else None)

    def object_agreement(self, mine: np.ndarray, offset: np.ndarray, ts: np.ndarray) -> np.ndarray:
        """(len(ts), m) whether each of the m points of run b's objects in ``mine`` (a mask of
        :attr:`b_objects`), moved by ``offset`` (as in :meth:`agreement`) and ``t``, has a point
        of run a's objects within the radius."""
        def agrees(moved: np.ndarray) -> np.ndarray:
            return self.a_objects.query(moved, distance_upper_bound=self.radius)[0] <= self.radius

        return _profile(self.b_objects[mine] + offset, ts, agrees if self.a_objects.n else None)

    def place(self, lo: float, hi: float, offset: np.ndarray, t_lo: float, t_hi: float) -> tuple[float, float]:
        """Where the marks of the window ``[lo, hi]`` (along-track, as :attr:`b_coords`) lie and
        their shift (m) from ``offset`` onto run a's, searched from ``t_lo`` to ``t_hi``:
        ``(s, t)``, NaN when the profile has no single clear peak (:func:`profile_peak`).

        Marks are whole: the window reaches :data:`REACH` beyond its ends (a disc cut in half by
        the window's end is matched against a whole one, and its peak leans), and takes the
        objects whose centre it holds (the first and last window those beyond run b's cloud: a
        box in run b's next tile whose view in run a lies in run a's), all of their points.
        ``s`` is the median position of the marked points that agree at the peak, for drift
        changes the offset along the window (18 mm/m is 4.5 cm at its end); an intensity mark
        there that lies beyond the window is left to the next one.

        Intensity marks and short objects are placed each on their own (:func:`_placed`), and
        the one placed more precisely is taken; where both are placed more than
        :data:`CONFLICT_SD` apart, nothing is. Pooled, a run's chance marks dilute the other
        kind's peak: run c of the demo, on the other track, marked 350 points of a window's
        lining by chance, and a box its 99 object points agreed on to 95 % rose only 0.23
        above the floor (:data:`MIN_RISE` 0.25)."""
        s = self.b_coords[:, 0]
        ts = np.arange(t_lo, t_hi + STEP / 2, STEP)
        marked = self.marked((s >= lo - REACH) & (s <= hi + REACH))
        kinds = [(self.agreement(marked, offset, ts), s[marked], MAX_WIDTH)]
        if self.b_objects is not None and len(s):  # (a box's overlap: a tent as wide at half its rise as the box is long)
            at = np.clip(self.b_object_at, s.min(), s.max())  # (the end windows take those held beyond)
            mine = (at >= lo) & (at <= hi)
            kinds.append((self.object_agreement(mine, offset, ts), self.b_objects[mine, 0], MAX_LENGTH))
        found = [(*peak, k) for k, (agree, along, width) in enumerate(kinds)
                 if (peak := _placed(ts, agree, along, width)) is not None]
        if not found:
            return float("nan"), float("nan")
        if len(found) == 2 and abs(found[0][0] - found[1][0]) > CONFLICT_SD * max(np.hypot(found[0][1], found[1][1]), STEP):
            return float("nan"), float("nan")
        t, _, s_mark, kind = min(found, key=lambda peak: peak[1])
        # an intensity mark beyond the window is the next window's; an object is this one's, where it lies
        return (s_mark, t) if kind == 1 or lo <= s_mark <= hi else (float("nan"), float("nan"))

    def alias_ratio(self, curve, lo: float, hi: float) -> tuple[float, float, dict]:
        """How close the best alias along the track comes to the curve of offsets ``curve``
        (world points (k, 3) to the offsets (k, 3) that move run b's points there onto run
        a's), by the marks: like the geometric :func:`railtraj.matching.piecewise.alias_ratio`,
        the misfit (share of marked points that do not agree) at the curve over that of the
        best shift beyond the curve's peak, the shift to it, and the profile (``points``: the
        marked points, ``source`` "marks"). Of intensity marks and short objects, the kind whose
        share rises most above its median at the curve is taken (as :meth:`place` places each
        kind on its own: run c's view from the other track marked 350 points of the lining by
        chance, which flattened a box's profile)."""
        ts = ALIAS_STEP * np.arange(np.floor(lo / ALIAS_STEP), np.ceil(hi / ALIAS_STEP) + 1)
        marked = self.marked(np.ones(len(self.b_coords), bool))
        kinds = [self.agreement(marked, self._curve_at(curve, self.b_coords[marked]), ts)]
        if self.b_objects is not None:
            kinds.append(self.object_agreement(np.ones(len(self.b_objects), bool),
                                               self._curve_at(curve, self.b_objects), ts))
        k0 = int(np.argmin(np.abs(ts)))
        # each kind on its own, as in place(): the one that rises most at the curve
        kinds = [agree for agree in kinds if agree.shape[1] >= MIN_MARKED] or [np.hstack(kinds)]
        shares = [agree.mean(axis=1) if agree.shape[1] else np.zeros(len(ts)) for agree in kinds]
        best = max(range(len(kinds)), key=lambda i: shares[i][k0] - np.median(shares[i]))
        share = shares[best]
        profile = {"start": float(ts[0]), "step": ALIAS_STEP, "fitness": share.tolist(),
                   "points": int(kinds[best].shape[1]), "source": "marks"}
        floor = float(np.median(share))
        foot = _extent(share - floor, k0, 0.1 * (share[k0] - floor))[0] if share[k0] > floor else ts == ts[k0]
        if foot.all():
            return 0.0, 0.0, profile
        k = int(np.flatnonzero(~foot)[np.argmax(share[~foot])])
        return misfit_ratio(1.0 - share[k0], 1.0 - share[k]), float(ts[k]), profile

    def _curve_at(self, curve, coords: np.ndarray) -> np.ndarray:
        """``curve``'s offsets (track frame) at run b's points ``coords`` (track frame)."""
        return curve(coords @ self.frame + self.origin) @ self.frame.T if len(coords) else np.zeros((0, 3))


def held_objects(coords: np.ndarray, holds) -> tuple[np.ndarray, np.ndarray]:
    """The points of the short objects a tile holds, whole, and each one's object's along-track
    centre. ``coords``: (m, 3) a run's points on short objects (track frame), those around its
    tile included; ``holds``: whether the tile holds track-frame points (mask).

    Points closer than :data:`OBJECT_GAP` are one object, held where its centre (mean point) is.
    Run a's objects are those its tile holds, each whole: a box across the tile's edge is matched
    by the one pair whose run a's tile holds its centre, whichever of run b's tiles and wherever
    its start puts run b's view of it. (Holding run b's by where its start put them, two
    neighbouring pairs started on different aliases of a featureless section both left a box
    out; and a cut part of a box alone against a whole one fits wherever it lies on it: a
    plateau as long as the box, whose centre is not the box's, that moved a pair 18.7 cm.)"""
    if not len(coords):
        return coords, np.zeros(0)
    pairs = cKDTree(coords).query_pairs(OBJECT_GAP, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(coords),) * 2)
    n, label = connected_components(graph, directed=False)
    count = np.bincount(label, minlength=n)
    centre = np.column_stack([np.bincount(label, weights=coords[:, k], minlength=n) for k in range(3)]) / count[:, None]
    lo, hi = np.full(n, np.inf), np.full(n, -np.inf)
    np.minimum.at(lo, label, coords[:, 0])
    np.maximum.at(hi, label, coords[:, 0])
    keep = np.asarray(holds(centre), bool)[label]
    return coords[keep], 0.5 * (lo + hi)[label[keep]]


def _profile(pts: np.ndarray, ts: np.ndarray, agrees) -> np.ndarray:
    """(len(ts), len(pts)) ``agrees(pts moved t along the track)`` for each ``t`` (all False
    where ``agrees`` is None: the other run has nothing to agree with)."""
    out = np.zeros((len(ts), len(pts)), bool)
    if agrees is None or not len(pts):
        return out
    for k, t in enumerate(ts):  # up to 300 shifts, each one query of the marked points
        out[k] = agrees(pts + np.array([t, 0.0, 0.0]))
    return out


class LazyMarks:
    """:meth:`IntensityMarks.build` on first use, once, also when windows on several threads
    ask at the same time: most pairs have edges in every window and never need it."""

    def __init__(self, *args) -> None:
        self._args, self._marks, self._lock = args, None, threading.Lock()

    def __call__(self) -> IntensityMarks:
        with self._lock:
            if self._marks is None:
                self._marks = IntensityMarks.build(*self._args)
            return self._marks


def _placed(ts: np.ndarray, agree: np.ndarray, along: np.ndarray, max_width: float) -> tuple[float, float, float] | None:
    """One kind of marks' shift, its sd and where they lie along the track (the median of the
    points that agree at the shift), from their agreement (shifts, points); None where they are
    fewer than :data:`MIN_MARKED` or show no single clear peak that places them to :data:`MAX_SD`."""
    if agree.shape[1] < MIN_MARKED:
        return None
    t = profile_peak(ts, agree.mean(axis=1), max_width)
    sd = peak_sd(ts, agree) if np.isfinite(t) else np.inf
    if not sd <= MAX_SD:
        return None
    at = agree[int(np.argmin(np.abs(ts - t)))]
    return (t, sd, float(np.median(along[at]))) if at.any() else None


def profile_peak(ts: np.ndarray, share: np.ndarray, max_width: float = MAX_WIDTH) -> float:
    """Centre of the single clear peak of an agreement profile, NaN if there is none.

    The floor is the profile's median (chance agreement, at most :data:`MAX_FLOOR` of the rise);
    the peak must rise :data:`MIN_RISE` above it, be at most :data:`MAX_WIDTH` wide at half its
    rise (``max_width``), lie inside the range with its feet (where it falls to a tenth of its rise), and nothing
    beyond its feet rise more than :data:`MAX_RIVAL` of it. Its centre is the centroid of
    the part above half its rise, which a disc's overlap (a tent, symmetric about the true shift)
    places without bias."""
    floor, k, rise, lo_half, hi_half = _half_peak(share)
    if not (rise >= MIN_RISE and floor <= MAX_FLOOR * rise):
        return float("nan")
    foot, lo, hi = _extent(share - floor, k, 0.1 * rise)
    if lo == 0 or hi == len(ts) - 1:
        return float("nan")  # the peak runs off the range: its centre is not seen
    if (hi_half - lo_half) * (ts[1] - ts[0]) > max_width:
        return float("nan")  # a step or a streak along the track: each run's view moves its centre
    if (~foot).any() and share[~foot].max() - floor > MAX_RIVAL * rise:
        return float("nan")
    return _centroid(ts[lo_half:hi_half + 1], share[lo_half:hi_half + 1], floor + 0.5 * rise)


def peak_sd(ts: np.ndarray, agree: np.ndarray, groups: int = 8) -> float:
    """sd (m) of :func:`profile_peak`'s centre from the scatter of the centres of ``groups``
    interleaved subsets of the marked points (columns of ``agree``), each over the full
    profile's peak, times 1.5: the subsets share run a's points, and on simulated discs the
    unscaled sd fell short of the errors by 1.4 (RMS of their ratio, 18 discs)."""
    floor, _, rise, lo, hi = _half_peak(agree.mean(axis=1))
    members = np.arange(agree.shape[1]) % groups
    subsets = [agree[lo:hi + 1, members == g].mean(axis=1) for g in range(groups)]
    centres = [c for c in (_centroid(ts[lo:hi + 1], y, floor + 0.5 * rise) for y in subsets) if np.isfinite(c)]
    return 1.5 * float(np.std(centres, ddof=1)) / np.sqrt(len(centres)) if len(centres) > 2 else np.inf


def _half_peak(share: np.ndarray) -> tuple[float, int, float, int, int]:
    """A profile's floor (its median), highest sample, rise above the floor, and the first and
    last sample of the run around it above half that rise."""
    floor = float(np.median(share))
    k = int(np.argmax(share))
    rise = float(share[k]) - floor
    _, lo, hi = _extent(share - floor, k, 0.5 * rise)
    return floor, k, rise, lo, hi


def _centroid(ts: np.ndarray, y: np.ndarray, level: float) -> float:
    """Centroid of ``ts`` weighted by how far ``y`` rises above ``level`` (NaN if nowhere)."""
    w = np.maximum(y - level, 0.0)
    return float((ts * w).sum() / w.sum()) if w.sum() > 0 else float("nan")


def _extent(y: np.ndarray, k: int, level: float) -> tuple[np.ndarray, int, int]:
    """The run of samples around ``k`` where ``y`` stays above ``level``: mask, first, last."""
    below = np.flatnonzero(y <= level)
    lo = int(below[below < k].max()) + 1 if (below < k).any() else 0
    hi = int(below[below > k].min()) - 1 if (below > k).any() else len(y) - 1
    mask = np.zeros(len(y), bool)
    mask[lo:hi + 1] = True
    return mask, lo, hi
