"""Cross-sections of the tile pairs' point samples (:class:`railtraj.qc.PairClouds`), and which
pairs to show: the worst and a typical one."""

from __future__ import annotations

import numpy as np

from railtraj.qc import PairClouds


def cross_section(points: np.ndarray, centre: np.ndarray, direction: np.ndarray,
                  half_width: float) -> np.ndarray:
    """Points within ``half_width`` of the vertical plane across the track through ``centre``,
    as (across-track offset to the right, height) pairs."""
    d = np.asarray(direction, float)[:2]
    right = np.array([d[1], -d[0]])
    rel = points[:, :2] - np.asarray(centre, float)[:2]
    keep = np.abs(rel @ d) <= half_width
    return np.column_stack([rel[keep] @ right, points[keep, 2]])


def slab_width(points: np.ndarray, centre: np.ndarray, direction: np.ndarray,
               want: int = 800, widths=(0.1, 0.2, 0.4, 0.8, 1.6)) -> float:
    """The thinnest slab half-width from ``widths`` holding ``want`` points (else the widest)."""
    rel = points[:, :2] - np.asarray(centre, float)[:2]
    along = np.abs(rel @ np.asarray(direction, float)[:2])
    for w in widths:
        if np.count_nonzero(along <= w) >= want:
            return w
    return widths[-1]


def pick_pairs(clouds: list[PairClouds]) -> list[tuple[str, PairClouds]]:
    """The worst pair (largest C2C median after correction) and a typical one (the median)."""
    usable = [c for c in clouds if np.isfinite(c.median_after)]
    if not usable:
        return []
    ranked = sorted(usable, key=lambda c: c.median_after)
    worst, typical = ranked[-1], ranked[len(ranked) // 2]
    picks = [("worst", worst)]
    if typical is not worst:
        picks.append(("typical", typical))
    return picks
