"""Cross-sections: the 2-D outline (u, v) of each kind of structure, with a surface class per edge.

Kinds: ``rect`` (vertical walls, shallow arched roof: carries ribs, niches, boxes), ``circular``
(a smooth bored tunnel, feature-poor), ``station`` (platforms either side, flat ceiling) and
``cutting`` (open: floor, retaining walls, earth slopes, no roof). Dimensions follow from the
number of tracks. Outlines are polylines in the track frame; a closed outline repeats its first
vertex at the end. ``outline`` is a dense closed polygon used for the end walls between sections.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from railtraj.sim.surfaces import Surface

FLOOR = -0.35        #: track bed level below top of rail
NICHE_TOP = 2.2      #: niches reach from the floor to this height
WALL_TOP = 3.5       #: rect tunnel: springing line of the roof arch
CROWN = 4.6          #: rect tunnel: height of the roof crown
RIB_DROP = 1.0       #: ribs continue this far down the walls
KINDS = ("cutting", "rect", "circular", "station")


@dataclass(frozen=True)
class Profile:
    """One cross-section outline: vertices (k, 2), class per edge (k-1,), dense closed outline."""

    kind: str
    uv: np.ndarray
    cls: np.ndarray
    outline: np.ndarray
    centre: tuple[float, float]

    def wall_u(self, v: float, side: int) -> float:
        """|u| of the outline at height ``v`` on the given side (+1 right, -1 left)."""
        a, b = self.uv[:-1], self.uv[1:]
        lo, hi = np.minimum(a[:, 1], b[:, 1]), np.maximum(a[:, 1], b[:, 1])
        hit = (lo <= v) & (v <= hi) & (hi > lo)
        f = (v - a[hit, 1]) / (b[hit, 1] - a[hit, 1])
        u = a[hit, 0] + f * (b[hit, 0] - a[hit, 0])
        return float(np.max(side * u))


def arc(cu: float, cv: float, r: float, a0: float, a1: float, step: float = 0.3) -> np.ndarray:
    """Points on a circular arc from angle ``a0`` to ``a1`` (radians, from +u towards +v)."""
    n = max(2, int(np.ceil(abs(a1 - a0) * r / step)) + 1)
    a = np.linspace(a0, a1, n)
    return np.column_stack([cu + r * np.cos(a), cv + r * np.sin(a)])


def densify(poly: np.ndarray, step: float = 0.25) -> np.ndarray:
    """Insert points so that no edge of the polyline is longer than ``step``."""
    out = [poly[:1]]
    for a, b in zip(poly[:-1], poly[1:], strict=True):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        out.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return np.concatenate(out)


def _profile(kind: str, pieces: list[tuple[np.ndarray, Surface]], centre: tuple[float, float],
             closed: bool = True, top: float | None = None) -> Profile:
    """Join polyline pieces (each starting where the previous ended) into a Profile."""
    pts, cls = [pieces[0][0][:1]], []
    for poly, c in pieces:
        pts.append(poly[1:])
        cls.extend([int(c)] * (len(poly) - 1))
    uv = np.concatenate(pts)
    outline = uv if closed else np.vstack([[uv[0, 0], top], uv, [uv[-1, 0], top], [uv[0, 0], top]])
    return Profile(kind, uv, np.array(cls, dtype=np.uint8), densify(outline), centre)


def rect(half_width: float) -> Profile:
    """Vertical walls with a shallow circular roof arch from WALL_TOP to CROWN."""
    w, rise = half_width, CROWN - WALL_TOP
    r = (w * w + rise * rise) / (2 * rise)
    cv = CROWN - r
    a = np.arctan2(WALL_TOP - cv, w)
    wall_v = [FLOOR, NICHE_TOP, WALL_TOP - RIB_DROP, WALL_TOP]
    right = np.array([[w, v] for v in wall_v])
    left = np.array([[-w, v] for v in wall_v[::-1]])
    return _profile("rect", [
        (np.array([[-w, FLOOR], [w, FLOOR]]), Surface.BED),
        (right, Surface.LINING),
        (arc(0.0, cv, r, a, np.pi - a), Surface.LINING),
        (left, Surface.LINING),
    ], centre=(0.0, 2.0))


def rib_outlines(half_width: float, depth: float) -> tuple[np.ndarray, np.ndarray]:
    """Outer and inner polylines of an arch rib: up one wall from WALL_TOP - RIB_DROP, over the
    roof and down the other wall, ``depth`` thick (same vertex count, for banding)."""
    w, rise = half_width, CROWN - WALL_TOP
    r = (w * w + rise * rise) / (2 * rise)
    cv = CROWN - r
    n = max(8, int(np.ceil((np.pi - 2 * np.arccos(w / r)) * r / 0.3)) + 1)
    lo = WALL_TOP - RIB_DROP

    def line(ww: float, rr: float) -> np.ndarray:
        a = np.arctan2(np.sqrt(rr * rr - ww * ww), ww)      # where the wall meets the arch
        arc_a = np.linspace(a, np.pi - a, n)
        top = np.column_stack([rr * np.cos(arc_a), cv + rr * np.sin(arc_a)])
        return np.vstack([[ww, lo], top, [-ww, lo]])

    return line(w, r), line(w - depth, r - depth)


def circular(radius: float, centre_v: float) -> Profile:
    """A bored tunnel: one circle, cut by the track bed at FLOOR."""
    half = np.sqrt(radius ** 2 - (FLOOR - centre_v) ** 2)
    a = np.arctan2(FLOOR - centre_v, half)
    return _profile("circular", [
        (np.array([[-half, FLOOR], [half, FLOOR]]), Surface.BED),
        (arc(0.0, centre_v, radius, a, np.pi - a), Surface.LINING),
    ], centre=(0.0, centre_v))


def station(edge: float, back: float, platform: float = 0.95, ceiling: float = 5.5) -> Profile:
    """Side platforms from ``edge`` to ``back`` (|u|), walls at ``back``, flat ceiling."""
    return _profile("station", [
        (np.array([[-edge, FLOOR], [edge, FLOOR]]), Surface.BED),
        (np.array([[edge, FLOOR], [edge, platform]]), Surface.PLATFORM_EDGE),
        (np.array([[edge, platform], [back, platform]]), Surface.PLATFORM),
        (np.array([[back, platform], [back, ceiling]]), Surface.WALL),
        (np.array([[back, ceiling], [-back, ceiling]]), Surface.CEILING),
        (np.array([[-back, ceiling], [-back, platform]]), Surface.WALL),
        (np.array([[-back, platform], [-edge, platform]]), Surface.PLATFORM),
        (np.array([[-edge, platform], [-edge, FLOOR]]), Surface.PLATFORM_EDGE),
    ], centre=(0.0, 2.5))


def cutting(half_width: float, wall: float = 2.5, slope_top: float = 5.0, top: float = CROWN + 1.0) -> Profile:
    """Open cutting: floor, retaining walls to ``wall``, then earth slopes; no roof.

    ``top`` closes the outline (for the portal headwall) but is not a surface.
    """
    w, out = half_width, half_width + 2.0 * (slope_top - wall)
    return _profile("cutting", [
        (np.array([[-out, slope_top], [-w, wall]]), Surface.EARTH),
        (np.array([[-w, wall], [-w, FLOOR]]), Surface.RETAINING),
        (np.array([[-w, FLOOR], [w, FLOOR]]), Surface.BED),
        (np.array([[w, FLOOR], [w, wall]]), Surface.RETAINING),
        (np.array([[w, wall], [out, slope_top]]), Surface.EARTH),
    ], centre=(0.0, 2.0), closed=False, top=top)


@dataclass(frozen=True)
class SectionSet:
    """The four profiles for a given track layout."""

    tracks: tuple[float, ...]
    profiles: dict[str, Profile]
    rect_half_width: float

    @classmethod
    def for_tracks(cls, n_tracks: int, spacing: float = 4.0) -> SectionSet:
        """Profiles sized for one track on the axis or two tracks ``spacing`` apart."""
        tracks = (0.0,) if n_tracks == 1 else (-spacing / 2, spacing / 2)
        outer = max(abs(t) for t in tracks)
        hw = outer + 2.9
        edge = outer + 1.6
        profiles = {
            "rect": rect(hw),
            "circular": circular(hw + 0.35, 1.5 if n_tracks == 1 else 1.2),
            "station": station(edge, edge + 4.5),
            "cutting": cutting(hw + 0.6),
        }
        return cls(tracks, profiles, hw)
