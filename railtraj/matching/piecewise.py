"""A tile pair's offset as a smooth curve along the track: window by window, then one fit.

Two runs' tiles are not one translation apart. INS drift changes along the track: in the
simulated tunnels by up to 18 mm per metre, so over a 25 m tile run b's cloud is stretched and
bent against run a's by several centimetres (within-tile sd of the true offset 1-13 cm). A
rigid fit averages that away and, worse, blurs the rib edges the along-track estimate depends
on. So the overlap is cut into windows of ``length`` metres along the track; each window gets

- across and up from point-to-plane (walls and floor fix them to millimetres), and
- along from its *edges*: a profile scanner turning across the track never sees the faces of
  ribs and sleepers, only where each profile steps onto or off them, so point-to-plane has
  no along-track information left once the normal noise is taken out (its weakest eigenvalue
  was below zero on every simulated pair). Sliding the window's points along the track and
  measuring their distance to run a's raw points does see the edges: the along-track shift
  is the minimum of that profile (truncated squared distance across run a's surface, the
  informative half of the points, parabola through the three lowest samples). A window
  without edges has no valley (:func:`valley_significance`): it gives across and up, but no
  along-track offset.

A curve ``d(s) = c0 + c1 u + c2 u^2`` (``u = s - s_ref``; a parabola from 4 windows, a line
from 2) through the window estimates is the result, ``c0`` the offset at the reference point
(the median along-track position of run b's points in the overlap, moved between the windows
that found an along-track offset where three or more did and all lie to one side of it). Its
scatter gives an honest covariance (each edge is placed only to a profile spacing, so a
window's along estimate scatters by about a centimetre; across and up by millimetres), and
windows far off the curve (a window on a sleeper alias) are dropped. On the simulated thesis
tunnel the offset at the reference point came within 4.8 / 1.7 / 3.4 mm RMS (along / across /
up) of the truth on pairs a rigid fit refused as degenerate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import uniform_filter1d
from scipy.spatial import cKDTree

from railtraj.matching.consensus import alias_profile, misfit_ratio, profile_rivals, window_chord
from railtraj.matching.intensity import LazyMarks, Surroundings
from railtraj.matching.memo import ArrayMemo
from railtraj.matching.refine import Fit, point_to_plane, sample
from railtraj.matching.target import PlaneTarget
from railtraj.matching.threads import map_threads

#: per-window sd floors (m) along, across, up: what a window estimate scatters by at best
WINDOW_SD_FLOOR = np.array([0.010, 0.003, 0.003])
#: along-track sd floor (m) of a curve resting on a window placed by intensity marks
#: (:mod:`railtraj.matching.intensity`): such windows scattered by 0.1-6 cm on simulated marks
MARKS_SD_FLOOR = 0.02
#: how far (m) marks are searched either side of a window's offset where no vote window says
MARKS_SEARCH = 1.5
#: a window's along-track profile (across run a's surface) must rise from its valley by this
#: many times its noise (:func:`valley_significance`); flatter, the window has no edges and
#: gives no offset. On 1 704 windows of 12 simulated surveys started 0-3 cm off the truth, 6
#: kept 1 408, 63 of them more than 3 cm off; the plain distance's 3 kept 1 471, 127 off
MIN_VALLEY = 6.0
#: how far (m) beyond a cloud's end a time is extrapolated at the train's speed (:func:`reference_times`)
TIME_REACH = 3.0
#: variance (m^2) of the along-track offset of a curve none of whose windows found one
UNKNOWN_VAR = 1e4
#: along-track windows a curve needs before anything checks it: a line through two fits them
#: exactly. With fewer, the windows that found an offset are halved (:func:`window_offsets`)
CHECKED_WINDOWS = 3
#: m/m: the fastest the runs' along-track offset may change between two windows of a pair (the
#: drift reaches ~18 mm/m, a GNSS bump at a portal ~15 mm/m), and m: how far two windows that
#: agree may still differ. An edge window further than that from every window placed by marks
#: found another alias (:func:`_off_the_marks`)
MAX_DRIFT_RATE = 0.05
WINDOW_AGREEMENT = 0.1
#: an edge profile's peak a curve without valleys is moved to must rise this many sd above the
#: higher dip beside it (:func:`edge_peak`); tube 515's joints rose 8-38, its noise 3-4
MIN_EDGE_PEAK = 5.0
#: degrees: a fitted track direction further than this from the direction of travel is not the
#: track's (noise turns it 0.1-1.7 degrees; a fit with no wall in reach, 90)
MAX_AXIS_TURN_DEG = 10.0
#: 1/m: no drift bends the runs' offset across or up faster than this within a tile pair (a
#: curvature of 3 mm/m^2 is a 19 cm bow over 25 m). Windows whose across or up values a parabola
#: fits only so bent disagree: of 3 108 pairs with windows on 112 simulated surveys, 99.9 % of
#: the ok and coarse ones bent less than 1.9 mm/m^2 and 5 more than 3: two ambiguous, one portal
#: pair 1.6 cm off, and two 14.5 and 34-54 cm off across claiming 1-2 cm (one of them a station's
#: two platform edges, each fitting some windows of a sparse scan)
MAX_CURVATURE = 0.003


@dataclass(frozen=True)
class Piecewise:
    """``d(p) = sum_j coefs[j] u^j``, ``u = (p - origin) @ axis - s_ref``: offset moving b onto a."""

    coefs: np.ndarray  # (3, 3) world-frame coefficients of u^0 (the offset at s_ref), u^1, u^2
    axis: np.ndarray  # (3,) unit horizontal track direction
    origin: np.ndarray  # (3,) where s = 0
    s_ref: float  # along-track position of the reference point (where: piecewise_fit)
    cov: np.ndarray  # (3, 3) covariance of d_ref
    windows: np.ndarray  # (k, 6): s, dx, dy, dz, used along (1/0), along found (1: its profile has a valley, 2: marks placed it, 0: neither)
    span: tuple[float, float]  # along-track range of the windows the curve was fitted on
    resid_sd: np.ndarray  # (3,) scatter of the used windows about the curve, along/across/up
    marks: LazyMarks | None = None  # the clouds' intensity marks and short objects, where looked for
    off_marks: int = 0  # edge windows a mark showed on another alias: across and up only (_off_the_marks)
    axis_from_travel: bool = False  # the direction of travel overruled the fitted track direction (track_axis)

    @property
    def on_marks(self) -> bool:
        """Whether the curve's along-track offset rests on windows placed by marks alone."""
        used = self.windows[self.windows[:, 4] > 0, 5] if len(self.windows) else np.zeros(0)
        return bool(len(used)) and bool((used == 2).all())

    @property
    def d_ref(self) -> np.ndarray:
        """The offset at the reference point."""
        return self.coefs[0]

    @property
    def gradient(self) -> np.ndarray:
        """Change of the offset per metre along ``axis`` at the reference point."""
        return self.coefs[1]

    def at(self, xyz: np.ndarray) -> np.ndarray:
        """The offset at each of the points ``xyz`` (n, 3); beyond :attr:`span` the offset at
        its nearer end (a parabola must not be extrapolated)."""
        return self._along(np.clip((np.asarray(xyz, float) - self.origin) @ self.axis, *self.span))

    def _along(self, s: np.ndarray) -> np.ndarray:
        """The offset at along-track positions ``s`` (from :attr:`origin`), not clipped to the span."""
        return np.vander(np.asarray(s, float) - self.s_ref, 3, increasing=True) @ self.coefs

    def covers(self, xyz: np.ndarray) -> np.ndarray:
        """Mask of the points ``xyz`` between the centres of the outermost used windows along
        the track: where the curve interpolates what it was fitted on. Beyond them it
        extrapolates, and a parabola's sd grows fast there (2.5x its sd at the reference point
        half a window past the last centre). On held-out portal_trap 91 a tie 2.4 m past the
        last used window was 3.7 cm off where its pair claimed 0.7 cm."""
        s = (np.asarray(xyz, float) - self.origin) @ self.axis
        centres = self.windows[self.windows[:, 4] > 0, 0]
        if not len(centres):
            return np.zeros(len(s), bool)
        return (s >= centres.min()) & (s <= centres.max())

    @property
    def n_used(self) -> int:
        return int(self.windows[:, 4].sum()) if len(self.windows) else 0

    def window_spread(self) -> float:
        """RMS along-track distance (m) of every window with an along-track offset, used or
        dropped, from the curve: how far apart the windows were before the curve dropped the worst."""
        found = self.windows[self.windows[:, 5] > 0] if len(self.windows) else self.windows
        if not len(found):
            return 0.0
        off = (found[:, 1:4] - self._along(found[:, 0])) @ self.axis
        return float(np.sqrt(np.mean(off**2)))

    def summary(self) -> dict:
        """JSON-ready diagnostics for a tile pair's ``info``."""
        frame = track_frame(self.axis)
        return {"window_spread_m": self.window_spread(),
                "gradient_mm_per_m": (frame @ self.gradient * 1000).round(3).tolist(),
                "curvature_mm_per_m2": (frame @ self.coefs[2] * 1000).round(4).tolist(),
                "window_resid_sd_mm": (self.resid_sd * 1000).round(2).tolist(),
                "windows": np.round(self.windows, 4).tolist(), "windows_used": self.n_used,
                "axis": self.axis.tolist(), "ref_point": (self.origin + self.s_ref * self.axis).tolist(),
                "gradient": self.gradient.tolist(), "fit_cov": self.cov.tolist(),
                **({"windows_off_marks": self.off_marks} if self.off_marks else {}),
                **({"axis_from_travel": True} if self.axis_from_travel else {})}


def track_axis(information: np.ndarray, travel: np.ndarray | None = None) -> np.ndarray:
    """Unit horizontal track direction: the weakest direction of a point-to-plane information
    matrix (walls and floor constrain everything but the track), levelled; or ``travel`` (the
    run's horizontal direction of travel, :attr:`railtraj.data.PointTile.travel`) where the two
    differ by more than :data:`MAX_AXIS_TURN_DEG`.

    Not the principal axis of the points: a tunnel crossing a square tile diagonally is cut
    unevenly at the corners, and that axis was 1.7 degrees off in the thesis tunnel, enough
    to put a 4.5 m rib alias 14 cm across and hide it from the alias check. Not the direction
    of travel either where the two agree: the windows are cut along the surfaces, and the
    pipeline turns the pair's covariance onto the trajectory's direction afterwards
    (:mod:`railtraj.track_direction`). But a fit started far across the track (a sparse scan
    whose votes failed, a tile that holds one wall of a twin-track tunnel the grid cuts
    lengthwise) has no wall in reach, and its weakest direction is across: a held-out survey's
    pair was then cut into windows across the track, placed "along" on the profile spacing
    and came out 13 cm off across, claiming 1 cm.
    """
    v = np.linalg.eigh(information)[1][:, 0]
    v = np.array([v[0], v[1], 0.0])
    norm = np.linalg.norm(v)
    if not np.isfinite(norm) or norm < 1e-6:
        return np.array([1.0, 0.0, 0.0]) if travel is None else _canonical(travel)
    v /= norm
    if travel is not None and abs(v @ travel) < np.cos(np.radians(MAX_AXIS_TURN_DEG)):
        v = travel
    return _canonical(v)


def _canonical(v: np.ndarray) -> np.ndarray:
    """``v`` or ``-v``, whichever points east (or north, if it points neither east nor west)."""
    return v if v[0] > 0 or (v[0] == 0 and v[1] > 0) else -v


def track_frame(axis: np.ndarray) -> np.ndarray:
    """Rows along, across (left) and up for a horizontal unit ``axis``."""
    up = np.array([0.0, 0.0, 1.0])
    return np.vstack([axis, np.cross(up, axis), up])


def _pair_search_tree(xyz: np.ndarray, leafsize: int) -> cKDTree:
    """A KD-tree for :func:`along_profile`'s pair search (``sparse_distance_matrix``): the pairs
    found do not depend on the tree, and an unbalanced tree with 32-point leaves on run a's side,
    4-point leaves on the window's, is searched 13 % faster (and built twice as fast) than the
    defaults."""
    return cKDTree(xyz, leafsize=leafsize, balanced_tree=False, compact_nodes=False)


_trees = ArrayMemo(_pair_search_tree)


def reference_tree(xyz: np.ndarray) -> cKDTree:
    """KD-tree of run a's raw points for :func:`along_profile`, built once per tile while its
    array is alive (:mod:`railtraj.matching.memo`)."""
    return _trees(xyz, 32)


def along_coordinates(tree: cKDTree, axis: np.ndarray) -> np.ndarray:
    """Along-track coordinate of each of the tree's points, about its first point: projected
    once per fit for :func:`along_profile`, not once per pair of points it finds."""
    return (tree.data - tree.data[0]) @ axis


def along_profile(tree: cKDTree, pts: np.ndarray, d: np.ndarray, axis: np.ndarray, ts: np.ndarray,
                  tau: float, tree_along: np.ndarray | None = None, normals: np.ndarray | None = None) -> np.ndarray:
    """Mean truncated squared distance to the reference points of ``pts + d + t axis`` per t:
    the mean over its informative points of :func:`along_costs`."""
    return along_costs(tree, pts, d, axis, ts, tau, tree_along, normals).mean(axis=1)


def surface_normals(target: PlaneTarget) -> np.ndarray:
    """(n, 3) normal of the plane block of each of the reference's raw points (``target`` built
    on them, in their order); zero where the block is not planar."""
    block = target.grid.inverse
    return np.where((target.weight[block] > 0)[:, None], target.normal[block], 0.0)


def along_costs(tree: cKDTree, pts: np.ndarray, d: np.ndarray, axis: np.ndarray, ts: np.ndarray,
                tau: float, tree_along: np.ndarray | None = None, normals: np.ndarray | None = None) -> np.ndarray:
    """Truncated squared distance to the reference points of ``pts + d + t axis``, (len(ts), m)
    for the m informative points; with ``normals`` (:func:`surface_normals`) only its part
    across run a's surface, the nearest point's normal (:func:`edge_costs`, the same costs).

    Only the half of the points whose distance changes most over ``ts`` count: points on plain
    walls change little (they slide along themselves) and only add noise.

    Every reference point within ``tau`` of a shifted point lies in the cylinder of radius
    ``tau`` around the segment the point slides along, so those neighbours are found once (one
    pair search, then the cylinder) and each shift's distances follow from their along-track
    and squared distances; the same costs as a nearest-neighbour query per shift (to 1e-17 m^2),
    at a third of the time (a quarter of the demo's matching was these queries). The squared
    distances are the pair search's own, and the along-track ones differences of
    ``tree_along`` (:func:`along_coordinates`): gathering each pair's two points took as long
    as the search itself (15 M pairs on a thesis-density tile pair).
    """
    moved = pts + d
    reach = tau + float(np.abs(ts).max())
    pairs = _pair_search_tree(moved, 4).sparse_distance_matrix(tree, reach, output_type="ndarray")
    tree_along = along_coordinates(tree, axis) if tree_along is None else tree_along
    owner, ref = pairs["i"], pairs["j"]
    along = tree_along[ref] - ((moved - tree.data[0]) @ axis)[owner]
    nn2 = pairs["v"] ** 2
    near = nn2 - along**2 <= tau * tau  # inside the cylinder: within tau of some shifted position
    owner, ref, along, nn2 = owner[near], ref[near], along[near], nn2[near]
    # a stable sort of 16-bit owners is a radix sort (a window holds a few thousand points)
    order = np.argsort(owner.astype(np.int16) if len(pts) < 2**15 else owner, kind="stable")
    owner, ref, along, nn2 = owner[order], ref[order], along[order], nn2[order]
    cost = np.full((len(ts), len(pts)), tau * tau)
    if not len(owner):
        return _informative_half(cost)
    starts = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]])
    if normals is None:
        for k, t in enumerate(ts):  # a few dozen shifts, each vectorised over all neighbours
            cost[k, owner[starts]] = np.minimum(np.minimum.reduceat(nn2 - 2.0 * t * along + t * t, starts), tau * tau)
        return _informative_half(cost)
    # across the surface: each neighbour's distance along its normal, linear in the shift, kept
    # for the nearest neighbour (the smallest of it among the neighbours as near as the nearest)
    normal = normals[ref]
    across = np.einsum("ij,ij->i", normal, tree.data[ref] - moved[owner])
    slope, planar = normal @ axis, normal.any(axis=1)
    counts = np.diff(np.r_[starts, len(owner)])
    for k, t in enumerate(ts):
        dist2 = nn2 - 2.0 * t * along + t * t
        nearest = np.minimum.reduceat(dist2, starts)
        value = np.where(dist2 <= np.repeat(nearest, counts), np.where(planar, (across - t * slope) ** 2, dist2), np.inf)
        cost[k, owner[starts]] = np.where(nearest <= tau * tau, np.minimum.reduceat(value, starts), tau * tau)
    return _informative_half(cost)


def _informative_half(cost: np.ndarray) -> np.ndarray:
    """The columns (points) of a (shifts, points) cost table whose cost changes most over the
    shifts, the upper half by sd: points on plain walls slide along themselves and add noise."""
    if not cost.shape[1]:
        return cost
    spread = cost.std(axis=0)
    return cost[:, spread >= np.median(spread)]


def _subset_means(cost: np.ndarray, groups: int) -> np.ndarray:
    """(shifts, groups) mean cost of ``groups`` interleaved subsets of the points (columns):
    how much a profile owes to which points happened to be sampled."""
    members = np.arange(cost.shape[1]) % groups
    return np.column_stack([cost[:, members == g].mean(axis=1) for g in range(groups)])


def valley_significance(ts: np.ndarray, costs: np.ndarray, groups: int = 8) -> float:
    """How surely the profile of ``costs`` (:func:`along_costs`) rises from a valley over ``ts``:
    its rise at the ends of the range (of the parabola fitted to the whole profile, from the
    centre) over the larger of two noises the rise must stand out of:

    * the scan lines' ripple: two runs' profiles pass each other every profile spacing, so
      the mean profile ripples; its sample-to-sample scatter (RMS step / sqrt 2);
    * the points' own sampling: the standard error of the rise over ``groups`` interleaved
      subsets of the points. Where nothing has edges, where points fall makes the profile
      undulate slowly, differently in each subset (on a randomly sampled plain tube the
      ripple alone made such an undulation 10 times its scatter).

    A window with edges (ribs, sleepers, brackets) scores tens. A window with none (a
    slab-track circular section, a platform wall) has no valley: its lowest sample is anywhere
    in the range (mixed 185: two such windows put an ``ok`` pair 6.7 cm off). On 462 windows of
    simulated mixed, commensurate and tube surveys, a score of 3 on the plain distance left
    out 62 of the 69 windows more than 3 cm off the truth, and 8 right to 2 cm. The windows
    now measure across run a's surface (:func:`along_costs`), whose lining is flat at every
    shift, and whose threshold was set on their own scores (:data:`MIN_VALLEY`).
    """
    G = np.vander(ts - ts.mean(), 3, increasing=True)
    half = 0.5 * np.ptp(ts)
    means = np.column_stack([costs.mean(axis=1), _subset_means(costs, groups)])
    rises = np.linalg.lstsq(G, means, rcond=None)[0][2] * half**2
    profile = means[:, 0]
    ripple = np.sqrt(np.mean(np.diff(profile) ** 2) / 2)
    sampling = rises[1:].std(ddof=1) / np.sqrt(groups)
    noise = max(ripple, sampling)
    return float(rises[0] / noise) if noise > 0 else (np.inf if rises[0] > 0 else 0.0)


def profile_minimum(ts: np.ndarray, cost: np.ndarray) -> float:
    """Shift at the minimum of a sampled profile (parabola through the lowest three samples);
    NaN when the minimum lies on the edge of the range (the window found no valley)."""
    k = int(np.argmin(cost))
    if k == 0 or k == len(ts) - 1:
        return float("nan")
    y0, y1, y2 = cost[k - 1:k + 2]
    curvature = y0 - 2 * y1 + y2
    step = ts[1] - ts[0]
    return float(ts[k] + (0.5 * (y0 - y2) / curvature * step if curvature > 0 else 0.0))


def window_offsets(target: PlaneTarget, tree: cKDTree, moving: np.ndarray, d_start: np.ndarray,
                   axis: np.ndarray, s: np.ndarray, length: float, *, points: int = 8_000,
                   search: float = 0.1, step: float = 0.005, tau: float = 0.05,
                   min_points: int = 1_500, min_windows: int = 4, min_length: float = 2.0,
                   marks: LazyMarks | None = None, vote_window: tuple[np.ndarray, float] | None = None,
                   across_target: PlaneTarget | None = None, marks_first: bool = False) -> tuple[np.ndarray, int]:
    """Offset of every window of about ``length`` metres of ``moving`` (at along-track positions
    ``s``): rows ``s_mean, dx, dy, dz, along``, in order along the track; windows without enough
    points are left out. Also how many edge windows a mark overrode (:func:`_off_the_marks`).
    Each window's profile is its points' distance across run a's surface (:func:`along_costs`
    with :func:`surface_normals`): the plain distance of a point on a plain lining follows where
    run a's scan lines lie, and on fast trains (lines 6-8 cm apart) its valley was that ripple's,
    3-4 cm off the joints (on 1 704 windows of 12 surveys, 447 more than 1.5 cm off the truth
    against 259; on held-out fast tube 515, 66 against 18). Points whose shifts cross run a's
    tile edge are left out (:func:`stays_on_tile`). A
    window whose profile has no valley (``along`` 0: no edges, :func:`valley_significance`)
    keeps its across and up; its along-track value is point-to-plane's, which means nothing,
    unless ``marks`` (intensity, :mod:`railtraj.matching.intensity`) place it (``along`` 2),
    searched along the chord of ``vote_window`` (the votes' centre and radius) through the
    window's offset. A short overlap gets shorter windows (down to ``min_length``) to reach ``min_windows``.
    Where only one or two windows find an along-track offset (:data:`CHECKED_WINDOWS`: a pair at
    the end of a featureless section, edges in part of it only), each of those is halved and its
    halves tested again, while halves of ``min_length`` or more find more offsets: on the mixed
    tunnels' pairs at the start of the slab-track section 2 of 5 windows became 4 of 7, and the
    curve through them checks itself. Halving where three found one (a line that checks itself
    already) gained three pairs and lost three on ten held-out surveys (shorter windows are
    noisier: one pair was moved onto a 1 m ring alias), so it is not done.

    The windows cover the central 99 % of the points along the track instead of all of them when
    that fills more windows with ``min_points``: a few stray points metres beyond a partial
    overlap (a diagonal tile corner) must not spread the grid so that most windows fall where
    there is nothing to fit (always trimming cost a dense survey a pair it had).
    ``tau`` is the matcher's fitness radius, which follows the scan's profile spacing; each
    window's overlap (:attr:`railtraj.matching.refine.Fit.overlap`, at least 0.5) is counted
    within it too (at a fixed 5 cm, a 16 cm profile gap left every window of a fast run below
    0.5 and its pair ``degenerate``). ``across_target``
    (:func:`railtraj.matching.target.filled_target`: sparse far walls with planes) fits each
    window's across and up again from there, its along-track offset held (in it, tilted coarse
    planes drew a window's along-track offset onto a rib 1.5 m away).

    With ``marks_first`` a window with edges is placed by marks too where it holds some, and
    where any is, the edges count across and up only: edges that repeat (a tube's ring joints)
    place a window on the alias nearest its start, a box on its own (asked by
    :mod:`railtraj.matching.resolve` where a pair's profile shows no alias of its own).

    A window placed by marks is moved along the track from its start, metres at times, and is
    fitted across and up again there (the wall turns on a curve). Where marks alone place the
    pair along the track, the windows without an along-track offset are fitted across and up
    again at the marks' (interpolated along the track): each had kept the start's, and on a
    curve its across is then off by that distance times the wall's turn. In a held-out bored
    tube a box 4.1 m from the votes' start sat 2.4 cm off across, claiming 2 mm; its pair's
    across came out 2.4 cm off."""
    edges = _window_edges(s, length, min_windows, min_length)
    if len(s):  # stray points may stretch the grid: the core's grid if it fills more windows
        core = _window_edges(s[(s >= np.quantile(s, 0.005)) & (s <= np.quantile(s, 0.995))], length,
                             min_windows, min_length)
        if _filled(s, core, min_points) > _filled(s, edges, min_points):
            edges = core
    ts = np.arange(-search, search + step / 2, step)
    tree_along, normals = along_coordinates(tree, axis), surface_normals(target)
    frame = track_frame(axis)

    def marked(lo: float, hi: float, d: np.ndarray) -> tuple[float, float]:
        """Where marks in the window lie along the track and their shift from ``d`` (NaN: none)."""
        if marks is None:
            return float("nan"), float("nan")
        t_lo, t_hi = window_chord(d, axis, *vote_window) if vote_window is not None else (-MARKS_SEARCH, MARKS_SEARCH)
        return marks().place(lo, hi, frame @ d, t_lo, t_hi)

    def fit_across(plane_target: PlaneTarget, pts: np.ndarray, d: np.ndarray) -> Fit:
        """The window's points fitted across and up from ``d``, along the track held."""
        return point_to_plane(plane_target, pts, d, iterations=10, max_dist=max(0.2, 2 * tau), fitness_radius=tau,
                              fixed=axis)

    def across_at(pts: np.ndarray, d: np.ndarray) -> np.ndarray | None:
        """The window's offset ``d`` with its across and up fitted again there (None where the
        window's points do not fit there): a mark moves a window metres along a curving wall,
        whose across at the start no longer holds (a box 3.5 m from the window's start sat
        2.4 cm off across in a bored tube)."""
        refit = fit_across(target if across_target is None else across_target, pts, d)
        return refit.d if refit.overlap >= 0.5 and np.isfinite(refit.d).all() else None

    def window_points(bounds: tuple[float, float, int]) -> tuple[np.ndarray | None, float]:
        """The window's sample of points (None: too few) and their mean along-track position."""
        lo, hi, seed = bounds
        inside = (s >= lo) & (s <= hi)
        if inside.sum() < min_points:
            return None, float("nan")
        return sample(moving[inside], points, seed=seed), float(s[inside].mean())

    def window(bounds: tuple[float, float, int]) -> list[float] | None:
        lo, hi, _ = bounds
        pts, s_mean = window_points(bounds)
        if pts is None:
            return None
        fit = point_to_plane(target, pts, d_start, iterations=10, max_dist=max(0.2, 2 * tau), fitness_radius=tau)
        if across_target is not None and across_target is not target and np.isfinite(fit.d).all():  # sparse walls too
            fit = fit_across(across_target, pts, fit.d)
        if not (fit.overlap >= 0.5 and np.isfinite(fit.d).all()):
            return None
        kept = pts[stays_on_tile(target, pts + fit.d, axis, ts, tau)]
        costs = along_costs(tree, kept, fit.d, axis, ts, tau, tree_along, normals)
        if not valley_significance(ts, costs) >= MIN_VALLEY:  # no edges: across and up only, unless marks
            s_mark, t = marked(lo, hi, fit.d)
            placed = across_at(pts, fit.d + t * axis) if np.isfinite(t) else None
            if placed is not None:  # placed where its marks are
                return [s_mark, *placed, 2.0]
            return [s_mean, *fit.d, 0.0]
        t = profile_minimum(ts, costs.mean(axis=1))
        if marks_first and np.isfinite(t):
            s_mark, t_mark = marked(lo, hi, fit.d)
            placed = across_at(pts, fit.d + t_mark * axis) if np.isfinite(t_mark) else None
            if placed is not None:
                return [s_mark, *placed, 2.0]
        return [s_mean, *(fit.d + t * axis), 1.0] if np.isfinite(t) else None

    def fitted(bounds: list[tuple[float, float, int]]) -> list:
        return map_threads(lambda k: window(bounds[k]), len(bounds))

    bounds = [(edges[k], edges[k + 1], k) for k in range(len(edges) - 1)]
    rows = fitted(bounds)
    while 0 < _found(rows) < min(min_windows, CHECKED_WINDOWS):
        # edges in part of the overlap only (the end of a featureless section): look closer there,
        # each half of a window that found an offset tested again
        split = [k for k, row in enumerate(rows)
                 if row is not None and row[4] > 0 and (bounds[k][1] - bounds[k][0]) / 2 >= min_length]
        if not split:
            break
        halves = [half for lo, hi, seed in (bounds[k] for k in split)
                  for half in ((lo, 0.5 * (lo + hi), 2 * seed + 1000), (0.5 * (lo + hi), hi, 2 * seed + 1001))]
        sub = fitted(halves)
        if _found(sub) <= len(split):  # the halves found no more than their windows did
            break
        keep = [k for k in range(len(bounds)) if k not in split]
        bounds, rows = [bounds[k] for k in keep] + halves, [rows[k] for k in keep] + sub
    kept = sorted((row, b) for row, b in zip(rows, bounds, strict=True) if row is not None)
    windows = np.array([row for row, _ in kept], float).reshape(-1, 5)
    off_marks = _off_the_marks(windows, axis)
    windows[off_marks, 4] = 0  # on another alias than the marks: across and up only
    if marks_first and (windows[:, 4] == 2).any():  # repeating edges: the marks alone place the pair along
        windows[windows[:, 4] == 1, 4] = 0
    plain = np.flatnonzero(windows[:, 4] == 0)
    if (windows[:, 4] == 2).any() and not (windows[:, 4] == 1).any() and len(plain):
        # along the track the pair rests on marks, often metres from where the other windows
        # kept the start's: those are fitted across and up again at the marks' along-track offset
        by_marks = windows[windows[:, 4] == 2]
        along = np.interp(windows[plain, 0], by_marks[:, 0], by_marks[:, 1:4] @ axis)

        def at_marks(i: int) -> np.ndarray | None:
            d = windows[plain[i], 1:4]
            return across_at(window_points(kept[plain[i]][1])[0], d + (along[i] - d @ axis) * axis)

        refitted = map_threads(at_marks, len(plain))
        for k, d in zip(plain, refitted, strict=True):
            windows[k, 1:4] = np.nan if d is None else d
        windows = windows[np.isfinite(windows).all(axis=1)]  # its points fit nowhere there
    return windows, int(off_marks.sum())


def stays_on_tile(target: PlaneTarget, pts: np.ndarray, axis: np.ndarray, ts: np.ndarray, reach: float) -> np.ndarray:
    """Mask of the points whose neighbourhood (``reach``) stays on one side of run a's tile
    edges (``target``'s bounding box) at every shift of ``ts`` along ``axis``. A point shifted
    off the tile loses its neighbours there and its cost ramps up: across the surface that
    ramp rose 6-11 noise sd at a plain tube's tile end, a valley where there are no edges.
    Points beside the box at every shift (a wall along the tile's side edge) keep their cost."""
    return target.inside(pts + (ts[0] - reach) * axis, 0.0) == target.inside(pts + (ts[-1] + reach) * axis, 0.0)


def _found(rows: list) -> int:
    """How many window rows found an along-track offset."""
    return sum(1 for row in rows if row is not None and row[4] > 0)


def _window_edges(s: np.ndarray, length: float, min_windows: int, min_length: float) -> np.ndarray:
    """Edges of windows of about ``length`` over the range of ``s`` (at least ``min_windows`` of
    ``min_length`` or more where the range allows)."""
    if not len(s):
        return np.zeros(1)
    span = float(np.ptp(s))
    n_win = max(1, round(span / length), min(min_windows, int(span // min_length)))
    return np.linspace(s.min(), s.max(), n_win + 1)


def _filled(s: np.ndarray, edges: np.ndarray, min_points: int) -> int:
    """How many windows between ``edges`` hold at least ``min_points`` of ``s``."""
    return int((np.histogram(s, edges)[0] >= min_points).sum()) if len(edges) > 1 else 0


def fit_curve(windows: np.ndarray, axis: np.ndarray, s_ref: float, reject: float = 0.03,
              along: np.ndarray | None = None, sd_floor: np.ndarray = WINDOW_SD_FLOOR) -> tuple:
    """Smooth curve through window offsets: (coefs (3, 3), cov of the offset at ``s_ref``, used
    mask, resid sd along/across/up). Coefficients are world-frame, of ``(s - s_ref)^0, ^1, ^2``.

    The degree follows the windows kept: a parabola from 4 (drift bends within a tile: on the
    thesis tunnel a straight line left 14.9 / 4.7 / 4.4 mm RMS at the reference point, a
    parabola 4.8 / 1.7 / 3.4 mm), a line from 2, a constant from 1; across and up a line where
    a parabola through 3 windows or more bends more than :data:`MAX_CURVATURE` (the windows
    disagree: the offset's sd there is at least half their spread). A window whose along-track
    offset is more than ``reject`` (3 window sd) off the curve through the others, in that
    difference's own sd (:func:`_deleted_residual`), is dropped, the worst first, while 3 or
    more remain (a tile pair left with 3 is not ``ok``: windows that disagree that much say the
    pair is unreliable). The sd per axis is the residual scatter, never below ``sd_floor``.

    ``along``: which windows found an along-track offset (default all); the others count across
    and up only. ``used`` marks the windows the along-track curve rests on.
    """
    frame = track_frame(axis)
    s, d = windows[:, 0] - s_ref, windows[:, 1:4] @ frame.T  # track frame
    along = np.ones(len(s), bool) if along is None else np.asarray(along, bool)
    used = along.copy()
    while used.sum() > 3:
        idx = np.flatnonzero(used)
        loo = np.array([_deleted_residual(s[idx], d[idx, 0], k) for k in range(len(idx))])
        if loo.max() <= reject:
            break
        used[idx[int(np.argmax(loo))]] = False
    coef, sd, var_scale = np.zeros((3, 3)), np.zeros(3), np.zeros(3)
    disagree = np.zeros(3)  # half the spread of windows that no drift explains (across, up)
    # along from the windows that found it; across and up also from those that found none
    for axes, rows in ((range(0, 1), used), (range(1, 3), used | ~along)):
        if not rows.any():  # no window found the along-track offset: it is unknown
            coef[0, axes] = d[:, axes].mean(axis=0)
            var_scale[axes] = np.inf
            continue
        for k in axes:
            c, G = _poly(s[rows], d[rows, k:k + 1])
            if k > 0 and abs(_bend(s[rows], d[rows, k])) > MAX_CURVATURE:  # no drift bends so: they disagree
                c, G = _poly(s[rows], d[rows, k:k + 1], max_degree=1)
                disagree[k] = np.ptp(d[rows, k]) / 2
            coef[:, k] = c[:, 0]
            sd[k] = _scatter(d[rows, k:k + 1] - np.vander(s[rows], 3, increasing=True) @ c, G)[0]
            var_scale[k] = float(np.linalg.inv(G.T @ G)[0, 0])  # s is relative to s_ref: the intercept
    sd = np.maximum(sd, sd_floor)
    # windows that disagree may each sit on one of two alignments (a station's platform edges):
    # the truth can be the outermost, so the sd is at least half their spread, not the line's
    cov_track = np.diag(np.minimum(np.maximum(sd**2 * var_scale, disagree**2), UNKNOWN_VAR))
    return coef @ frame, frame.T @ cov_track @ frame, used, sd


def _deleted_residual(s: np.ndarray, y: np.ndarray, k: int) -> float:
    """How far ``y[k]`` lies from the curve through the other windows (degree as in
    :func:`_poly`), in units of that difference's own sd over a window's: divided by
    ``sqrt(1 + h)``, ``h`` the leverage of predicting ``s[k]`` from the others.

    A curve through the others is known less well where it extrapolates: at the end window of
    4-6 evenly spaced ones ``h`` is 2.3-7.8, so the difference there scatters 1.8-3.0 window
    sd. Taken as is, the 3.2 cm at the end of a pair whose drift bent where a run's GNSS came
    back at a portal dropped two end windows (held-out mixed 306). Left with 3, the pair was
    ``degenerate`` (1.1 cm off the truth), its ties went, and the adjustment followed the
    run's biased GNSS there: 17 cm off, claiming 5 cm."""
    others = np.arange(len(s)) != k
    coef, G = _poly(s[others], y[others, None])
    g = np.vander(s[k:k + 1], G.shape[1], increasing=True)[0]
    leverage = float(g @ np.linalg.pinv(G.T @ G) @ g)
    return abs(float(y[k] - g @ coef[: G.shape[1], 0])) / np.sqrt(1.0 + leverage)


def reference_times(fit: Piecewise, a_xyz: np.ndarray, a_time: np.ndarray, b_xyz: np.ndarray,
                    b_time: np.ndarray, half: float = 1.0) -> tuple[float, float]:
    """When each run measured the reference point of ``fit``: median gps_time of its points
    within ``half`` metres along the track of it (run a's points taken back by ``d_ref``).

    The optimizer observes a tile pair's offset at these times, so they must belong to the
    same place as ``d_ref``: with drift changing by centimetres per metre, the overlap's
    median time can sit metres away from it on a partial overlap.
    """
    s = np.array([fit.s_ref])
    return (float(_times_near(fit, a_xyz - fit.d_ref, a_time, s, half)[0]),
            float(_times_near(fit, b_xyz, b_time, s, half)[0]))


def window_ties(fit: Piecewise, a_xyz: np.ndarray, a_time: np.ndarray, b_xyz: np.ndarray,
                b_time: np.ndarray, half: float = 0.5) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One tie per used window, for pairs whose keypoints agree too little to give ties:
    ``(time_a, time_b, xyz_a, xyz_b)`` at run b's point nearest each window's median, with the
    curve's offset there and both runs' median times within ``half`` metres along the track."""
    s_w = fit.windows[fit.windows[:, 4] > 0, 0]
    s_b = (b_xyz - fit.origin) @ fit.axis
    xyz_b = np.array([b_xyz[int(np.argmin(np.abs(s_b - s)))] for s in s_w]).reshape(-1, 3)  # a few windows
    time_a, time_b, ok = _window_times(fit, a_xyz, a_time, b_xyz, b_time, s_w, half)
    return time_a[ok], time_b[ok], xyz_b[ok] + fit.at(xyz_b[ok]), xyz_b[ok]


def windows_with_times(fit: Piecewise, a_xyz: np.ndarray, a_time: np.ndarray, b_xyz: np.ndarray,
                       b_time: np.ndarray, half: float = 0.5) -> dict[str, list]:
    """Every window's own offset (``d``, used by the curve or not), when each run measured it
    (``time_a``, ``time_b``: median times within ``half`` metres along the track), and whether the
    curve used it along the track (``along``: its profile found the offset there), for JSON.

    What an ``ambiguous`` or ``degenerate`` pair still says across the track and up, window by
    window: its one offset, at its reference point, hides an offset that changes within the
    tile (a GNSS bias ramping in at a portal, :func:`railtraj.matching.resolve._ramped`)."""
    time_a, time_b, ok = _window_times(fit, a_xyz, a_time, b_xyz, b_time, fit.windows[:, 0], half)
    return {"time_a": time_a[ok].tolist(), "time_b": time_b[ok].tolist(), "d": fit.windows[ok, 1:4].tolist(),
            "along": (fit.windows[ok, 4] > 0).tolist()}


def _window_times(fit: Piecewise, a_xyz: np.ndarray, a_time: np.ndarray, b_xyz: np.ndarray, b_time: np.ndarray,
                  s_w: np.ndarray, half: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """When each run measured the along-track positions ``s_w`` (run a's points taken back by
    the curve), and where both times are known."""
    time_a = _times_near(fit, a_xyz - fit.at(a_xyz), a_time, s_w, half)
    time_b = _times_near(fit, b_xyz, b_time, s_w, half)
    return time_a, time_b, np.isfinite(time_a) & np.isfinite(time_b)


def _times_near(fit: Piecewise, xyz: np.ndarray, times: np.ndarray, s_values: np.ndarray,
                half: float) -> np.ndarray:
    """Median time of the points within ``half`` metres along the track of each of ``s_values``.

    A position beyond the cloud (a box across the tile's edge, seen whole in its context and
    placed where it lies) takes the time of the line through the times of the last
    :data:`TIME_REACH` metres of the cloud, up to that far beyond its end (else NaN): the
    overlap's median time, the fallback, lay 12 m away, 4.1 cm of drift off on mixed 72."""
    s = (xyz - fit.origin) @ fit.axis
    out = np.full(len(s_values), np.nan)
    for k, sv in enumerate(s_values):  # a handful of positions
        near = np.abs(s - sv) <= half
        if near.any():
            out[k] = np.median(times[near])
            continue
        nearest_end = float(np.clip(sv, s.min(), s.max())) if len(s) else np.nan
        if abs(sv - nearest_end) <= TIME_REACH:
            end = np.abs(s - nearest_end) <= TIME_REACH
            if np.ptp(s[end]) > half:  # the train's speed from the run's own times there
                slope, intercept = np.polyfit(s[end], times[end], 1)
                out[k] = intercept + slope * sv
    return out


def _poly(s: np.ndarray, d: np.ndarray, max_degree: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares coefficients (3, k) of ``d`` (n, k) over ``s^0, s^1, s^2`` (the degree the number
    of windows allows, at most ``max_degree``, higher ones zero) and the design matrix."""
    degree = min(max_degree, 2 if len(s) >= 4 else min(len(s) - 1, 1))
    G = np.vander(s, degree + 1, increasing=True)
    coef = np.zeros((3, d.shape[1]))
    coef[: degree + 1] = np.linalg.lstsq(G, d, rcond=None)[0]
    return coef, G


def _bend(s: np.ndarray, y: np.ndarray) -> float:
    """Curvature (the coefficient of ``s^2``) of the least-squares parabola through ``y`` at ``s``:
    exact through 3 windows, 0 through fewer."""
    if len(s) < 3:
        return 0.0
    return float(np.linalg.lstsq(np.vander(s, 3, increasing=True), y, rcond=None)[0][2])


def _scatter(resid: np.ndarray, G: np.ndarray) -> np.ndarray:
    """Residual sd per axis (zero without degrees of freedom)."""
    dof = len(resid) - G.shape[1]
    return np.sqrt((resid**2).sum(axis=0) / dof) if dof > 0 else np.zeros(resid.shape[1])


def piecewise_fit(target: PlaneTarget, ref_xyz: np.ndarray, moving: np.ndarray, d_start: np.ndarray,
                  length: float = 5.0, information: np.ndarray | None = None, tree: cKDTree | None = None,
                  intensity: tuple[np.ndarray, np.ndarray] | None = None, objects: bool = False,
                  around: Surroundings | None = None, travel: np.ndarray | None = None,
                  **window_options) -> Piecewise | None:
    """Fit the curve of offsets moving ``moving`` (run b, inside the overlap) onto ``ref_xyz``.

    ``target`` is the plane target of ``ref_xyz``; ``information`` a point-to-plane information
    matrix near ``d_start`` (for the track direction; fitted here if None); ``tree`` a KD-tree
    on ``ref_xyz`` (built if None); ``intensity`` the two clouds' intensities, which place
    windows without edges where marks are (:func:`window_offsets`), as do short ``objects``
    (:mod:`railtraj.matching.objects`), told apart from a surface cut by the tile's edge by the
    runs' points ``around`` ``ref_xyz`` and ``moving``; ``travel`` run a's direction of travel
    (:attr:`railtraj.data.PointTile.travel`), which overrules a fitted direction far from it.
    Returns None when no window could be placed.
    """
    if information is None or not np.isfinite(information).all():
        information = point_to_plane(target, sample(moving, 20_000), d_start, iterations=3).information
    if not np.isfinite(information).all():
        return None
    axis = track_axis(information, travel)
    from_travel = not np.array_equal(axis, track_axis(information))  # travel overruled the fit
    origin = moving.mean(axis=0)
    s = (moving - origin) @ axis
    tree = reference_tree(ref_xyz) if tree is None else tree
    a_intensity, b_intensity = (None, None) if intensity is None else intensity
    marks = None if intensity is None and not objects else LazyMarks(
        ref_xyz, a_intensity, moving, b_intensity, track_frame(axis), origin, window_options.get("tau", 0.05), objects,
        around)
    windows, off_marks = window_offsets(target, tree, moving, d_start, axis, s, length, marks=marks, **window_options)
    if len(windows) == 0:
        return None
    return _curve(windows, off_marks, axis, origin, s, marks, from_travel)


def reversed_fit(rev: Piecewise, moving: np.ndarray) -> Piecewise:
    """The curve moving ``moving`` (run b's points) onto run a, from ``rev``: run a's points
    fitted onto run b's (:func:`piecewise_fit` with the roles swapped). Each window of ``rev``
    sits where its points land on run b, with the opposite offset; the curve is fitted through
    them as :func:`piecewise_fit` would. The intensity marks stay with ``rev``, whose clouds
    they were found on: the curve has none."""
    rows = rev.windows
    landed = rev.origin + rows[:, :1] * rev.axis + rows[:, 1:4]
    origin = moving.mean(axis=0)
    windows = np.column_stack([(landed - origin) @ rev.axis, -rows[:, 1:4], rows[:, 5]])
    windows = windows[np.argsort(windows[:, 0], kind="stable")]
    return _curve(windows, rev.off_marks, rev.axis, origin, (moving - origin) @ rev.axis, None, rev.axis_from_travel)


def _curve(windows: np.ndarray, off_marks: int, axis: np.ndarray, origin: np.ndarray, s: np.ndarray,
           marks: LazyMarks | None, from_travel: bool) -> Piecewise:
    """The :class:`Piecewise` through the rows of :func:`window_offsets` for the moving points
    at along-track positions ``s`` (from ``origin`` along ``axis``)."""
    s_ref = float(np.median(s))
    coefs, cov, used, sd = curve_through(windows, axis, s_ref)
    between = reference_position(s_ref, windows, used)
    if between != s_ref:  # which windows the curve keeps does not depend on s_ref
        s_ref = between
        coefs, cov, used, sd = curve_through(windows, axis, s_ref)
    table = np.column_stack([windows[:, :4], used, windows[:, 4]]).astype(float)
    centres = windows[used, 0] if used.any() else windows[:, 0]  # no along-track offset anywhere: all
    half = 0.5 * np.ptp(s) / len(windows)  # half a window
    span = (max(float(s.min()), centres.min() - half), min(float(s.max()), centres.max() + half))
    return Piecewise(coefs, axis, origin, s_ref, cov, table, span, sd, marks, off_marks, from_travel)


def curve_through(windows: np.ndarray, axis: np.ndarray, s_ref: float) -> tuple:
    """:func:`fit_curve` through the rows of :func:`window_offsets`, along the track through those
    that found an offset there, with the windows' sd floor: along the track
    :data:`MARKS_SD_FLOOR` where the curve keeps a window placed by marks (to centimetres only),
    else :data:`WINDOW_SD_FLOOR`. A window placed by marks that the curve drops leaves the
    others their floor: on a portal survey a box's window sat 1.8 m from where the sleepers'
    edges had put four windows (on an alias the chain then left), and the pair's along-track sd
    doubled."""
    along, by_marks = windows[:, 4] > 0, windows[:, 4] == 2
    if not by_marks.any():
        return fit_curve(windows[:, :4], axis, s_ref, along=along, sd_floor=WINDOW_SD_FLOOR)
    floor = WINDOW_SD_FLOOR.copy()
    floor[0] = MARKS_SD_FLOOR
    fit = fit_curve(windows[:, :4], axis, s_ref, along=along, sd_floor=floor)
    if not by_marks[fit[2]].any():  # the curve dropped them: the others keep their own floor
        fit = fit_curve(windows[:, :4], axis, s_ref, along=along, sd_floor=WINDOW_SD_FLOOR)
    return fit


def _off_the_marks(windows: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Which windows placed by edges (rows of :func:`window_offsets`) lie along the track further
    from every window placed by marks than the drift could move the runs' offset between them.

    Sleepers and ribs repeat: an edge window finds the alias nearest where it starts, the vote's
    choice. A mark (a stain, a box) does not. Where they disagree by more than the drift allows
    the edges are on another alias: they count across and up only, as windows that found no
    along-track offset. Only one or two such edge windows, though: a line through them and the
    mark fits them all, however wrong its slope. Five simulated pairs had such windows: the
    mark was right (2-19 cm off the truth), the edges 0.7-3.0 m off, the curve's slope
    0.2-0.7 m/m, and its along-track profile, smeared by that slope, showed no peak. Three edge
    windows or more check each other, and the curve drops what disagrees (:func:`fit_curve`):
    on commensurate 2 the mark was the one on an alias, 1.37 m off, its three edges right to
    2-12 cm; on six others four or five edges shared an alias and the chain moved the pair."""
    by_edges, by_marks = windows[:, 4] == 1, windows[:, 4] == 2
    if not by_marks.any() or not by_edges.any():
        return np.zeros(len(windows), bool)
    along = windows[:, 1:4] @ track_frame(axis)[0]
    apart = np.abs(windows[by_edges, 0][:, None] - windows[by_marks, 0][None, :])
    differ = np.abs(along[by_edges][:, None] - along[by_marks][None, :])
    out = np.zeros(len(windows), bool)
    out[by_edges] = (differ > WINDOW_AGREEMENT + MAX_DRIFT_RATE * apart).all(axis=1)
    if out.sum() >= CHECKED_WINDOWS:  # enough to check each other: the curve drops what disagrees
        out[:] = False
    return out


def reference_position(s_median: float, windows: np.ndarray, used: np.ndarray) -> float:
    """Where along the track a curve reports its offset: the overlap's median ``s_median``,
    moved between the windows the curve rests on (``used``, rows of :func:`window_offsets`) so
    its along-track offset is interpolated, not extrapolated. Between the windows *used*: one
    found and then dropped at a tile's end moved a ribbed pair's reference 3 m beyond its
    curve (a 50 m-tile survey, session 26's windows across the surface: 0.013 -> 0.193 m
    RMS). With one or two windows, only where marks placed them: a mark is where it is to
    centimetres (a window's edges, at the end of a featureless section, were not:
    :data:`CHECKED_WINDOWS`)."""
    if used.sum() >= CHECKED_WINDOWS or (used.any() and (windows[used, 4] == 2).all()):
        return float(np.clip(s_median, windows[used, 0].min(), windows[used, 0].max()))
    return s_median


def alias_ratio(target: PlaneTarget, moving: np.ndarray, fit: Piecewise, center: np.ndarray, window: float,
                radius: float = 0.05, exclude: float = 0.2, points: int = 4_000) -> tuple[float, float, dict]:
    """How close the best alias along the track comes to the fitted curve of offsets.

    Like :func:`railtraj.matching.consensus.alias_rivals`, but every point is first moved by its
    own offset on the curve, so a stretched run b no longer blurs the true alignment: the misfit
    (share of points farther than ``radius`` from run a) of the best distinct local maximum of
    the along-track fitness profile, against that of the curve itself, each the best within 3 cm.
    Returns the ratio (1: indistinguishable, above 1: the alias fits better), the along-track
    shift to that alias, and the coarse profile for the report.

    A curve whose along-track offset rests on intensity marks alone is judged by them
    (:meth:`railtraj.matching.intensity.IntensityMarks.alias_ratio`): its geometry fits alike
    at every shift.
    """
    if fit.on_marks and fit.marks is not None and len(fit.marks().b_coords) == len(moving):
        lo, hi = window_chord(fit.d_ref, fit.axis, center, window)
        ratio, shift, profile = fit.marks().alias_ratio(fit.at, lo, hi)
        return ratio, shift, {"axis": fit.axis.tolist(), **profile}
    pts = sample(moving, points, seed=2)
    moved = pts + fit.at(pts)
    lo, hi = window_chord(fit.d_ref, fit.axis, center, window)
    ts = radius * np.arange(np.floor(lo / radius) - 1, np.ceil(hi / radius) + 2)
    coarse = alias_profile(target, moved, np.zeros(3), fit.axis, ts, radius=radius)
    profile = {"axis": fit.axis.tolist(), "start": float(ts[0]), "step": radius, "fitness": coarse.tolist(),
               "points": len(pts)}
    rivals = profile_rivals(ts, coarse, exclude, lo, hi)
    if len(rivals) == 0:
        return 0.0, 0.0, profile
    fine = np.arange(-0.03, 0.0301, 0.01)
    centres = np.concatenate([[0.0], rivals])
    # the coarse ends first and last: alias_profile keeps the points inside at both, so the fine
    # fitnesses count the same points as the coarse profile
    ts_fine = np.concatenate([[ts[0]], (centres[:, None] + fine).ravel(), [ts[-1]]])
    fitness = alias_profile(target, moved, np.zeros(3), fit.axis, ts_fine, radius=radius)
    table = fitness[1:-1].reshape(len(centres), len(fine))
    misfit = 1.0 - table.max(axis=1)
    k = 1 + int(np.argmin(misfit[1:]))
    shift = float(centres[k] + fine[int(np.argmax(table[k]))])
    return misfit_ratio(misfit[0], misfit[k]), shift, profile


def edge_profile(target: PlaneTarget, tree: cKDTree, moving: np.ndarray, fit: Piecewise, center: np.ndarray,
                 window: float, tau: float, step: float = 0.05, points: int = 8_000, groups: int = 8,
                 across: bool = False) -> dict:
    """The along-track profile of the curve's edges: 1 minus the mean truncated cost (over
    ``tau^2``, :func:`edge_costs`; ``across`` run a's surface only) of ``moving`` moved by its
    curve and shifted along the track against run a's points, over the chord of the vote
    window, for the informative half of the points. ``tree`` and ``target`` are both built on
    run a's points (the same array).

    The chain weighs its candidates by the plain distance's profile: across the surface, the
    joint the curve was fitted on misfits so much less than the others (a joint that fits
    leaves only the range noise) that the others fell beyond ``max_misfit_ratio``, the truth
    among them (tube 303: 59 % of the length used along the track -> 50 %). Across the
    surface it finds where to move a curve without valleys (:func:`edge_peak`).

    :func:`alias_ratio`'s fitness counts points within ``radius``; a ring joint's 2.5 cm step
    lies within it, so a ring-jointed tube's fitness profile is flat (0.98-0.999 over 6 m) and
    shows none of the aliases its windows' valleys sit on. This profile shows them, one a ring
    spacing from the next. ``noise`` is each sample's standard error, from ``groups``
    interleaved subsets of the points (the costs are no counts), ``across`` pooled with its
    neighbours' (:func:`edge_costs` says what ``across`` is for): with 2 000 points the
    joints' valleys rose 1-2 times the noise's highest peaks, with 8 000 (0.4-1.1 s a pair)
    5-30 sd against at most 5.
    """
    pts = sample(moving, points, seed=3)
    moved = pts + fit.at(pts)
    lo, hi = window_chord(fit.d_ref, fit.axis, center, window)
    ts = step * np.arange(np.floor(lo / step) - 1, np.ceil(hi / step) + 2)
    kept = moved[target.inside(moved + ts[0] * fit.axis, 0.3) & target.inside(moved + ts[-1] * fit.axis, 0.3)]
    cost = _informative_half(edge_costs(target, tree, kept, fit.axis, ts, tau, across) / tau**2)
    profile = {"axis": fit.axis.tolist(), "start": float(ts[0]), "step": step, "points": cost.shape[1], "source": "edges"}
    if cost.shape[1] < 2 * groups:
        return {**profile, "fitness": [], "noise": []}
    variance = _subset_means(cost, groups).var(axis=1, ddof=1) / groups
    if across:  # pooled over 5 neighbouring shifts: one sample's 7 degrees of freedom let a
        # tenth of its noise estimates fall below half the truth, and a slow undulation of the
        # lining between joints then rose 3.4 sd (2.3 pooled; the joints 10-13)
        variance = pooled_variance(variance, 5)
    return {**profile, "fitness": (1.0 - cost.mean(axis=1)).tolist(), "noise": np.sqrt(variance).tolist()}


def pooled_variance(variance: np.ndarray, width: int) -> np.ndarray:
    """The running mean of ``variance`` over ``width`` neighbouring samples, never below 0: a
    running mean subtracts sums, and where the variance is 0 beside larger values it left
    -2e-18, whose square root (the noise) was NaN, so a peak there was never significant."""
    return np.maximum(uniform_filter1d(variance, width, mode="nearest"), 0.0)


def edge_costs(target: PlaneTarget, tree: cKDTree, pts: np.ndarray, axis: np.ndarray, ts: np.ndarray,
               tau: float, across: bool = True) -> np.ndarray:
    """(len(ts), len(pts)) cost of ``pts`` shifted by each of ``ts`` along ``axis``: the squared
    distance to the nearest of run a's points (``tree``), with ``across`` only its part across
    run a's surface there (the normal of ``target``'s block); ``tau^2`` beyond ``tau``.

    A point on a plain lining slides along it, and the plain squared distance then follows
    where run a's scan lines happen to lie, a ripple as deep as a ring joint's 2.5 cm step
    once the lines are 5-7 cm apart (a fast train): on held-out tube 515 (1.3x speed) the
    joints rose 5-20 sd over it and noise peaks 4-6. Across the surface only, the lining is
    flat at every shift and the joints stand out alone: 8-44 sd, noise at most 3 (a tenth of
    the distance along the surface added back brought the ripple back on 6.5 cm lines: 12-15
    sd between a synthetic tube's joints). Blocks without a plane keep the plain distance.
    """
    # point by point, all its shifts in a row: consecutive queries walk the same branches of the
    # tree (twice as fast as shift by shift, the same answers). (along_costs' cylinder search is
    # built for the windows' +-10 cm; over metres a query per shift is cheaper)
    shifted = (pts[:, None, :] + ts[None, :, None] * axis).reshape(-1, 3)
    dist, idx = tree.query(shifted, distance_upper_bound=tau)
    cost = np.full(len(shifted), tau * tau)
    found = np.isfinite(dist)
    cost[found] = dist[found] ** 2
    if across:
        found = np.flatnonzero(found)
        normal = surface_normals(target)[idx[found]]
        planar, normal = found[normal.any(axis=1)], normal[normal.any(axis=1)]
        cost[planar] = np.einsum("ij,ij->i", normal, tree.data[idx[planar]] - shifted[planar]) ** 2
    return np.ascontiguousarray(cost.reshape(len(pts), len(ts)).T)


def edge_peak(profile: dict, min_sd: float = MIN_EDGE_PEAK) -> float | None:
    """Shift (m) of the highest peak of an :func:`edge_profile` whose prominence (its rise above
    the higher dip beside it) is ``min_sd`` times its sample's standard error, times sqrt 2 (the
    dip's as large); None where none is."""
    from scipy.signal import find_peaks  # ~1 s to import: not at `railtraj --help`

    fitness, noise = np.asarray(profile["fitness"], float), np.asarray(profile["noise"], float)
    if not len(fitness):
        return None
    peaks, props = find_peaks(fitness, prominence=0.0)
    peaks = peaks[props["prominences"] >= min_sd * np.sqrt(2.0) * noise[peaks]]
    if not len(peaks):
        return None
    return float(profile["start"] + profile["step"] * peaks[np.argmax(fitness[peaks])])
