"""From vote peaks to one trustworthy translation: dense check, alias test, ties.

Votes alone cannot tell a rib from the next one (the runner-up peak sat at +-1.5 m with 0.74-1.04
of the best count in the prototype, and once won). What does tell them apart is the whole
cloud: after two quick point-to-plane steps from each peak, the share of points within 5 cm of
the reference was 0.885-0.96 at the true offset and at most 0.81 at aliases. So every matcher
ends here: check the top peaks densely, pick the best, and refuse (``ambiguous``) when a
distinct alias misfits almost as little, or (``no_overlap``) when nothing fits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from railtraj.data import Keypoints, PointTile, Ties, TileOffset
from railtraj.matching.refine import Fit, crop, point_to_plane, sample
from railtraj.matching.target import PlaneTarget
from railtraj.matching.threads import map_threads
from railtraj.matching.voting import Peak, Votes


@dataclass(frozen=True)
class Checked:
    peak: Peak
    fit: Fit


def check_peaks(target: PlaneTarget, moving: np.ndarray, peaks: list[Peak], *, iterations: int = 2,
                margin: float = 0.3, fitness_radius: float = 0.05) -> list[Checked]:
    """Quick point-to-plane fit (``iterations`` steps) from every peak, with its dense fitness."""
    def check(k: int) -> Checked:  # a handful of peaks, each fully vectorized
        pts = crop(target, moving, peaks[k].d, margin)
        return Checked(peaks[k], point_to_plane(target, pts, peaks[k].d, iterations=iterations, max_dist=0.2,
                                                fitness_radius=fitness_radius))

    return map_threads(check, len(peaks))


def search_peaks(target: PlaneTarget, moving: np.ndarray, center: np.ndarray, half: float, step: float,
                 n: int, radius: float = 0.05, points: int = 500) -> list[Peak]:
    """The ``n`` translations that fit best among a grid ``step`` apart within ``half`` of
    ``center`` (a cube), each at least ``2 step`` from a better one: candidates where the votes
    put none that fits. They carry no votes (count 0).

    Keypoints need not repeat between runs: on a sparse scan (0.18 m between a profile's points)
    a portal's open cutting gave 120-180 keypoints a tile and vote peaks of 11-13 pairs over a
    background of 30 %, none near the truth, so its pairs were ``no_overlap``. Yet the clouds
    fitted there by 0.73 at the true offset, the grid's best; an alias 0.67 m along fitted by
    0.65. The points are those :func:`check_peaks` would fit at ``center``; their fitness at every
    shift from one pair search (:func:`grid_fitness`)."""
    g = np.arange(-half, half + step / 2, step)
    axes = [float(c) + g for c in center]
    shifts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    pts = sample(moving, points, seed=3)
    pts = pts[target.inside(pts + center, 0.3)]  # as check_peaks crops them
    if len(pts) == 0:
        return []
    fitness = grid_fitness(target, pts, axes, radius)
    chosen: list[np.ndarray] = []
    for k in np.argsort(-fitness, kind="stable"):
        if len(chosen) == n:
            break
        if all(np.abs(shifts[k] - c).max() >= 2 * step for c in chosen):
            chosen.append(shifts[k])
    return [Peak(d, 0) for d in chosen]


def grid_fitness(target: PlaneTarget, pts: np.ndarray, axes: list[np.ndarray], radius: float) -> np.ndarray:
    """Share of ``pts`` that fit ``target`` (a voxel centroid nearer than ``radius``) moved by each
    shift of a grid, its coordinates ``axes`` (three ascending, evenly spaced arrays; the shifts
    in ``meshgrid(*axes, indexing="ij")`` order): what a KD-tree query of every point at every
    shift gives, to the bit, from one pair search.

    Every centroid within the radius of a moved point lies within the radius plus the grid's
    half-diagonal of the point moved to the grid's centre; each such pair fits at the few shifts
    whose every coordinate lies within the radius of theirs, checked by the sum of squares the
    KD-tree compares. A 21^3 grid of 500 points on one core: 0.04-0.47 s instead of 1.1-2.7 s
    (4.6 M queries). Memory grows with the grid (a bool per point and shift: 4.6 MB here) and
    with the pairs (0.1-0.3 M here, within 0.92 m)."""
    n = [len(a) for a in axes]
    step = [(a[-1] - a[0]) / (len(a) - 1) if len(a) > 1 else radius for a in axes]
    centre = np.array([0.5 * (a[0] + a[-1]) for a in axes])
    reach = radius + 0.5 * float(np.sqrt(sum((a[-1] - a[0]) ** 2 for a in axes)))
    pairs = cKDTree(pts + centre).sparse_distance_matrix(target.tree, reach * (1 + 1e-9) + 1e-9,
                                                         output_type="ndarray")
    owner, c = pairs["i"], target.tree.data[pairs["j"]]
    p = pts[owner]
    # per axis the first candidate index: the grid's nearest shifts to the pair's within the radius
    first = [np.floor((c[:, k] - p[:, k] - axes[k][0]) / step[k] - radius / step[k]).astype(np.int64) - 1
             for k in range(3)]
    candidates = [int(np.floor(2 * radius / step[k])) + 3 for k in range(3)]

    def along(k: int, rows: np.ndarray, offset: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Grid index, coordinate difference and within-radius mask of ``rows`` along axis k."""
        idx = first[k][rows] + offset
        valid = (idx >= 0) & (idx < n[k])
        idx = np.clip(idx, 0, n[k] - 1)
        diff = (p[rows, k] + axes[k][idx]) - c[rows, k]
        return idx, diff, valid & (np.abs(diff) < radius)

    hit = np.zeros((len(pts), n[0] * n[1] * n[2]), bool)
    rows0 = np.arange(len(owner))
    for o0 in range(candidates[0]):
        i0, d0, ok0 = along(0, rows0, o0)
        rows1, i0, d0 = rows0[ok0], i0[ok0], d0[ok0]
        for o1 in range(candidates[1]):
            i1, d1, ok1 = along(1, rows1, o1)
            rows2, j0, e0, i1, d1 = rows1[ok1], i0[ok1], d0[ok1], i1[ok1], d1[ok1]
            for o2 in range(candidates[2]):
                i2, d2, ok2 = along(2, rows2, o2)
                ok2 &= e0 * e0 + d1 * d1 + d2 * d2 < radius * radius
                hit[owner[rows2[ok2]], (j0[ok2] * n[1] + i1[ok2]) * n[2] + i2[ok2]] = True
    return hit.mean(axis=0)


def alias_profile(target: PlaneTarget, moving: np.ndarray, d: np.ndarray, axis: np.ndarray,
                  ts: np.ndarray, radius: float = 0.05, margin: float = 0.3) -> np.ndarray:
    """Fitness of ``moving`` shifted to ``d + t axis`` for each t in ``ts``.

    Vote peaks only show aliases that keypoints voted for; a few descriptor matches may show
    none. Sliding the dense cloud along the weak axis (the tunnel) shows every rib and sleeper
    alias directly. Only points that stay inside the reference at every shift count, so the
    tile ends do not favour small shifts. One batched KD-tree query for all shifts, point by
    point: consecutive queries a step apart walk the same branches of the tree (a quarter faster
    than shift by shift; the counts are the same).
    """
    pts = moving[target.inside(moving + d + ts[0] * axis, margin)
                 & target.inside(moving + d + ts[-1] * axis, margin)]
    if len(pts) == 0:
        return np.zeros(len(ts))
    shifted = (pts[:, None, :] + d + ts[None, :, None] * axis).reshape(-1, 3)
    idx, _ = target.nearest(shifted, radius)
    return (idx >= 0).reshape(len(pts), len(ts)).mean(axis=0)


def window_chord(d: np.ndarray, axis: np.ndarray, center: np.ndarray, window: float) -> tuple[float, float]:
    """The range of t for which ``d + t axis`` stays within ``window`` of ``center``."""
    b = np.asarray(d, float) - center
    ab = float(axis @ b)
    disc = ab**2 - float(b @ b) + window**2
    if disc <= 0:
        return -window, window
    return -ab - np.sqrt(disc), -ab + np.sqrt(disc)


def profile_rivals(ts: np.ndarray, fit: np.ndarray, exclude: float, lo: float, hi: float,
                   n: int = 2) -> np.ndarray:
    """Shifts t in [lo, hi] of the ``n`` highest local maxima of a fitness profile, farther than
    ``exclude`` from zero."""
    inner = (fit[1:-1] >= fit[:-2]) & (fit[1:-1] >= fit[2:])
    t = ts[1:-1]
    peaks = np.flatnonzero(inner & (np.abs(t) > exclude) & (t >= lo) & (t <= hi)) + 1
    return ts[peaks[np.argsort(-fit[peaks])][:n]]


def alias_rivals(target: PlaneTarget, moving: np.ndarray, best: Checked, center: np.ndarray, window: float,
                 radius: float = 0.05, exclude: float = 0.2, points: int = 2_000) -> tuple[list[Checked], dict]:
    """The two best aliases along the weak axis of ``best``, quick-fitted like vote peaks.

    The profile spans the part of the weak axis that lies within ``window`` of ``center`` (one
    step beyond, so that an alias right at the edge is still a local maximum) and is returned
    for the report: ``{"axis", "start", "step", "fitness"}``.
    """
    info = best.fit.information
    axis = np.linalg.eigh(info)[1][:, 0] if np.isfinite(info).all() else np.array([1.0, 0.0, 0.0])
    lo, hi = window_chord(best.fit.d, axis, center, window)
    ts = np.arange(lo - radius, hi + 1.5 * radius, radius)
    fit = alias_profile(target, sample(moving, points, seed=2), best.fit.d, axis, ts, radius=radius)
    profile = {"axis": axis.tolist(), "start": float(ts[0]), "step": radius, "fitness": fit.tolist()}
    rivals = [Peak(best.fit.d + t * axis, 0) for t in profile_rivals(ts, fit, exclude, lo, hi)]
    return check_peaks(target, moving, rivals, fitness_radius=radius), profile


#: misfits (shares of points left out) are compared this much above themselves: two fits that
#: leave no point out are indistinguishable (ratio 1), not infinitely far apart. On a smooth
#: tube scanned on lines 2 cm apart every point lay within the fitness radius at every shift,
#: and 0 / 0 read as "no rival": a pair 2.5 m off on a ring-joint alias was reported ``ok``
MISFIT_FLOOR = 1e-4


def misfit_ratio(best: float, rival: float) -> float:
    """How close a rival's misfit comes to the best's: ``best / rival``, both above
    :data:`MISFIT_FLOOR` (1: indistinguishable, near 0: the rival fits far worse)."""
    return float((best + MISFIT_FLOOR) / (rival + MISFIT_FLOOR))


def choose(checked: list[Checked], distinct: float) -> tuple[int, float]:
    """Index of the best-fitting peak, and how close the best *distinct* rival comes to it.

    Closeness is the ratio of misfits (share of points farther than the fitness radius), best
    over rival: 1 means indistinguishable, a rib alias scored ~0.2 in a simulated tunnel (its
    fitness ratio, 0.93, said much less). Peaks whose quick fits converged to within
    ``distinct`` of the winner are the same answer and are not rivals.
    """
    misfit = np.array([1.0 - c.fit.fitness for c in checked])
    best = int(np.argmin(misfit))
    rival = 0.0
    for i, c in enumerate(checked):
        if i != best and np.abs(c.fit.d - checked[best].fit.d).max() > distinct:
            rival = max(rival, misfit_ratio(misfit[best], misfit[i]))
    return best, rival


def consensus(votes: Votes, d: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Keypoint pairs (ia, ib) that agree with ``d`` within ``radius``, each keypoint used once.

    ``d`` is one translation, or one per vote (a line of offsets along the track). A keypoint
    in several agreeing pairs keeps the pair closest to ``d``.
    """
    d = np.asarray(d, float)
    expected = np.broadcast_to(d, votes.d.shape)
    k = np.flatnonzero(((votes.d - expected) ** 2).sum(axis=1) <= radius**2)
    if len(k) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    err = ((votes.d[k] - expected[k]) ** 2).sum(axis=1)
    k = k[np.argsort(err, kind="stable")]
    k = k[np.unique(votes.ib[k], return_index=True)[1]]
    err = ((votes.d[k] - expected[k]) ** 2).sum(axis=1)
    k = k[np.argsort(err, kind="stable")]
    k = k[np.unique(votes.ia[k], return_index=True)[1]]
    return votes.ia[k], votes.ib[k]


def make_ties(tile_a: PointTile, tile_b: PointTile, kp_a: Keypoints, kp_b: Keypoints, ia: np.ndarray,
              ib: np.ndarray, d: np.ndarray, positions: str = "offset") -> Ties:
    """Ties of the consensus pairs; weights 1/n so that one tile pair weighs one in total.

    ``positions="offset"``: xyz_b is run b's keypoint and xyz_a = xyz_b + d (``d`` one offset or
    one per tie), so every tie agrees with the refined offset (keypoints of two runs are the same object only to a voxel or so;
    their raw difference scatters by centimetres). ``"keypoints"``: both runs' keypoint positions
    as detected (the thesis). Times are always the two keypoints' own gps_times.
    """
    n = len(ia)
    xyz_b = kp_b.xyz[ib]
    xyz_a = xyz_b + d if positions == "offset" else kp_a.xyz[ia]
    return Ties(tile_a.run_id, tile_b.run_id, kp_a.gps_time[ia], kp_b.gps_time[ib], xyz_a, xyz_b,
                np.full(n, 1.0 / max(n, 1)))


def boxes_overlap(tile_a: PointTile, tile_b: PointTile, d: np.ndarray, window: float) -> bool:
    """Whether the x-y boxes of tile a and tile b moved by ``d`` overlap within ``window``."""
    (alo, ahi), (blo, bhi) = tile_a.bounds, tile_b.bounds
    blo, bhi = blo + d, bhi + d
    return bool((alo[:2] <= bhi[:2] + window).all() and (blo[:2] <= ahi[:2] + window).all())


def failed(tile_a: PointTile, tile_b: PointTile, status: str, info: dict, d: np.ndarray | None = None,
           cov: np.ndarray | None = None, inliers: int = 0) -> TileOffset:
    """A TileOffset that says why there is no reliable match (``d`` is kept only as a diagnostic)."""
    return TileOffset(tile_a.run_id, tile_b.run_id, tile_a.name, tile_b.name,
                      d=np.full(3, np.nan) if d is None else np.asarray(d, float),
                      cov=np.full((3, 3), np.nan) if cov is None else np.asarray(cov, float),
                      inliers=inliers, status=status, ties=Ties.empty(tile_a.run_id, tile_b.run_id),
                      info=info)


def alias_covariance(fit: Fit, window: float) -> np.ndarray:
    """Covariance of an ``ambiguous`` estimate: the fit's own, plus the whole search window along
    its weakest direction (the tunnel axis, where the aliases lie). Across and up stay usable."""
    if not (np.isfinite(fit.information).all() and np.isfinite(fit.cov).all()):
        return np.full((3, 3), np.nan)
    axis = np.linalg.eigh(fit.information)[1][:, 0]
    return fit.cov + window**2 * np.outer(axis, axis)
