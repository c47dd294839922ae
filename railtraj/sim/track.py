"""The track alignment: a centreline in plan (straights and circular curves) and a vertical
profile (gentle grades), placed in survey coordinates.

Everything in the simulated scene is positioned in the track frame ``(s, u, v)``: chainage ``s``
along the tunnel axis, ``u`` horizontal offset to the right of the axis (looking towards
increasing chainage) and ``v`` height above the axis' top-of-rail level. :class:`Centreline`
maps that frame to local east-north-up coordinates (metres from :attr:`Alignment.origin`).
Cross-sections stay vertical on a grade, as walls of real structures do.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Spacing of the lookup tables; linear interpolation between them is exact to ~1e-6 m on R >= 200 m.
TABLE_STEP = 0.1


@dataclass(frozen=True)
class Alignment:
    """Plan and vertical geometry of the tunnel axis.

    ``curves``: consecutive (length m, radius m) pieces; radius 0 means straight, positive turns
    right (clockwise), negative left. ``grades``: consecutive (length m, grade) pieces, grade as a
    ratio (0.005 = 0.5 %); grade changes are smoothed over ``vertical_curve`` metres. Both lists
    are extended with their last piece if the section list is longer.
    """

    origin: tuple[float, float, float] = (530000.0, 180000.0, 10.0)
    heading_deg: float = 60.0
    curves: tuple[tuple[float, float], ...] = ((1e9, 0.0),)
    grades: tuple[tuple[float, float], ...] = ((1e9, 0.0),)
    vertical_curve: float = 40.0

    def scaled(self, factor: float) -> Alignment:
        """The same alignment with every piece's length multiplied by ``factor``."""
        return Alignment(self.origin, self.heading_deg,
                         tuple((length * factor, r) for length, r in self.curves),
                         tuple((length * factor, g) for length, g in self.grades),
                         self.vertical_curve * factor)


def _piecewise(pieces: tuple[tuple[float, float], ...], s: np.ndarray) -> np.ndarray:
    """Value of the piece each chainage falls in (the last piece continues forever)."""
    ends = np.cumsum([length for length, _ in pieces])
    k = np.minimum(np.searchsorted(ends, s, side="right"), len(pieces) - 1)
    return np.array([value for _, value in pieces], dtype=float)[k]


class Centreline:
    """Tabulated tunnel axis over chainage ``[0, length]``: position, tangent and grade."""

    def __init__(self, alignment: Alignment, length: float) -> None:
        self.alignment = alignment
        self.length = float(length)
        s = np.arange(0.0, self.length + 2 * TABLE_STEP, TABLE_STEP)
        radius = _piecewise(alignment.curves, s[:-1] + TABLE_STEP / 2)
        curvature = np.divide(1.0, radius, out=np.zeros_like(radius), where=radius != 0)
        heading = np.radians(alignment.heading_deg) + np.concatenate(
            [[0.0], np.cumsum(curvature * TABLE_STEP)])
        # exact integration of a constant-curvature piece: chord of length 2 sin(k h / 2) / k
        dh = curvature * TABLE_STEP
        chord = TABLE_STEP * np.sinc(dh / (2 * np.pi))
        mid = heading[:-1] + dh / 2
        east = np.concatenate([[0.0], np.cumsum(chord * np.sin(mid))])
        north = np.concatenate([[0.0], np.cumsum(chord * np.cos(mid))])
        grade = _piecewise(alignment.grades, s)
        win = max(1, int(round(alignment.vertical_curve / TABLE_STEP)))
        if win > 1:  # moving average of the grade: parabolic vertical curves
            pad = np.pad(grade, (win // 2, win - 1 - win // 2), mode="edge")
            grade = np.convolve(pad, np.ones(win) / win, mode="valid")
        height = np.concatenate([[0.0], np.cumsum((grade[:-1] + grade[1:]) / 2 * TABLE_STEP)])
        self._s, self._heading, self._grade = s, heading, grade
        self._east, self._north, self._height = east, north, height

    def point(self, s: np.ndarray) -> np.ndarray:
        """Local ENU position (n, 3) of the axis at top-of-rail level."""
        s = np.asarray(s, dtype=float)
        return np.stack([np.interp(s, self._s, a) for a in (self._east, self._north, self._height)], -1)

    def heading(self, s: np.ndarray) -> np.ndarray:
        """Heading of the axis in radians, clockwise from grid north (unwrapped)."""
        return np.interp(np.asarray(s, dtype=float), self._s, self._heading)

    def grade(self, s: np.ndarray) -> np.ndarray:
        """Grade (rise over run) at ``s``."""
        return np.interp(np.asarray(s, dtype=float), self._s, self._grade)

    def tangent(self, s: np.ndarray) -> np.ndarray:
        """Unit 3-D tangent (n, 3) towards increasing chainage, including the grade."""
        h, g = self.heading(s), self.grade(s)
        t = np.stack([np.sin(h), np.cos(h), g], -1)
        return t / np.linalg.norm(t, axis=-1, keepdims=True)

    def right(self, s: np.ndarray) -> np.ndarray:
        """Horizontal unit vector (n, 3) to the right of the axis."""
        h = self.heading(s)
        return np.stack([np.cos(h), -np.sin(h), np.zeros_like(h)], -1)

    def to_local(self, suv: np.ndarray) -> np.ndarray:
        """Map track-frame points (n, 3) of (s, u, v) to local ENU coordinates (n, 3)."""
        suv = np.asarray(suv, dtype=float)
        s, u, v = suv[:, 0], suv[:, 1], suv[:, 2]
        p = self.point(s) + u[:, None] * self.right(s)
        p[:, 2] += v
        return p

    def to_world(self, local: np.ndarray) -> np.ndarray:
        """Local ENU (metres from the origin) to survey coordinates."""
        return np.asarray(local, dtype=float) + np.asarray(self.alignment.origin)
