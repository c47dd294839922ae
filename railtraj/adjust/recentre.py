"""Put the runs' common correction where relative observations place it: their sd-weighted average.

Ties and tile offsets see only differences between runs; what the runs share is seen by their
priors alone, and the sd-weighted average of the runs at each place is the best estimate of it
(the bound of issue #9). The spline's smoothness term pulls that common part towards the
*unweighted* average bend of the runs, and with priors weakened for correlation it wins: on a
2-run survey whose runs' sd differ by a fifth, the common correction missed the weighted average
by 6 cm RMS. This step shifts every run, at each chainage, by the same vector so that the
sd-weighted mean of the corrections there is zero (averaged over ``SMOOTH_M`` of chainage). Being the same for every run at a chainage, it
leaves all relative geometry (ties, inter-run agreement) as it was.

Chainage (:mod:`railtraj.chainage`, as in the report) is the distance along a reference run (the
one with the longest track), onto which every run's epochs are projected: runs on parallel tracks
share it. It is taken on the *corrected* runs, which agree where they were observed: on their
inputs a run on the neighbouring track that sat 2.3 m off across (4 m + 2.3 m from the reference)
fell outside ``MAX_LATERAL_M`` for 170 m, kept the shift from where it left, and ended 38 cm off
across from the other runs, which its tile pairs measured to 3 mm (``mixed``, seed 61). Where fewer
than two runs pass, the shift is carried over from the nearest place where two do.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import uniform_filter1d

from railtraj.chainage import Chainage
from railtraj.data import Trajectory

#: runs further than this from the reference run's track are not at its chainage: a neighbouring
#: track (3.5-4.5 m) plus the runs' misalignment, not the other bore of a twin-bore tunnel
MAX_LATERAL_M = 6.0
#: a gap longer than this in a run's chainage breaks its coverage
MAX_GAP_M = 5.0
#: the shift is averaged over this many metres of chainage: the runs' common error is drift and
#: changes no faster, but their weights can step (a run's widened sd ends). Such a step shifted
#: every run by 12 cm within 1 m, and the runs, still 0.8 m apart along the track, took it at
#: different places: a 12 cm spike between them (portal_trap, ribs 1.2 m, ch 98)
SMOOTH_M = 21.0


def recentre(inputs: dict[str, Trajectory], corrected: dict[str, Trajectory],
             sd: dict[str, np.ndarray]) -> tuple[dict[str, Trajectory], float]:
    """``corrected`` shifted so that the ``sd``-weighted mean correction is zero at each chainage,
    and the largest shift applied (m)."""
    if len(inputs) < 2:
        return dict(corrected), 0.0
    along = Chainage(corrected[max(sorted(inputs), key=lambda r: _length(inputs[r].xyz))])
    grid = np.arange(0.0, along.length + 1.0, 1.0)
    num, den, runs = np.zeros((len(grid), 3)), np.zeros((len(grid), 3)), np.zeros(len(grid))
    chainage = {}
    for r in sorted(inputs):
        ch = chainage[r] = along.of_trajectory(corrected[r], MAX_LATERAL_M)
        ok = np.isfinite(ch)
        if ok.sum() < 2:
            continue
        order = np.argsort(ch[ok], kind="stable")
        x = ch[ok][order]
        c = (corrected[r].xyz - inputs[r].xyz)[ok][order]
        w = 1.0 / np.maximum(sd[r][ok][order], 1e-3) ** 2
        covered = _covered(grid, x)
        for k in range(3):
            num[covered, k] += np.interp(grid[covered], x, w[:, k] * c[:, k])
            den[covered, k] += np.interp(grid[covered], x, w[:, k])
        runs += covered
    shared = runs >= 2
    if not shared.any():
        return dict(corrected), 0.0
    shift = np.column_stack([np.interp(grid, grid[shared], num[shared, k] / den[shared, k]) for k in range(3)])
    shift = uniform_filter1d(shift, size=int(SMOOTH_M), axis=0, mode="nearest")  # (1 m grid)
    out, largest = {}, 0.0
    for r in sorted(corrected):
        ch = chainage[r]
        ok = np.isfinite(ch)
        delta = np.zeros((len(ch), 3))
        if ok.any():
            delta[ok] = np.column_stack([np.interp(ch[ok], grid, shift[:, k]) for k in range(3)])
            # epochs away from the reference track keep the shift of the nearest epoch that has one
            idx = np.flatnonzero(ok)
            nearest = idx[np.clip(np.searchsorted(idx, np.arange(len(ch))), 0, len(idx) - 1)]
            delta[~ok] = delta[nearest[~ok]]
        largest = max(largest, float(np.abs(delta).max()))
        out[r] = corrected[r].with_positions(corrected[r].xyz - delta, corrected[r].sd)
    return out, largest


def _length(xyz: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(xyz[:, :2], axis=0), axis=1).sum())


def _covered(grid: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Grid points inside the run's chainage span and not inside a gap of more than MAX_GAP_M."""
    inside = (grid >= x[0]) & (grid <= x[-1])
    i = np.clip(np.searchsorted(x, grid), 1, len(x) - 1)
    return inside & (x[i] - x[i - 1] <= MAX_GAP_M)


__all__ = ["recentre"]
