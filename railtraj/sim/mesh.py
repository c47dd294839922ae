"""Building the scene's triangle mesh in the track frame, then bending it onto the alignment.

Every primitive is made in ``(s, u, v)`` coordinates (see :mod:`railtraj.sim.track`) with a
surface class per triangle. Long pieces are cut at most ``max_step`` metres apart along the
chainage so that, once each vertex is mapped through the curved centreline, the surfaces follow
the curve. Triangle orientation does not matter: ray casting hits both sides.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from railtraj.sim.track import Centreline

#: (s0, s1, u0, u1, v0, v1): a box in the track frame; sweep quads centred in it are left out.
Hole = tuple[float, float, float, float, float, float]
_FACES = {  # corner index bits: s = 1, u = 2, v = 4
    "s0": (0, 2, 6, 4), "s1": (1, 5, 7, 3), "u0": (0, 4, 5, 1),
    "u1": (2, 3, 7, 6), "v0": (0, 1, 3, 2), "v1": (4, 6, 7, 5),
}


def chainage_breaks(s0: float, s1: float, max_step: float, extra: Sequence[float] = ()) -> np.ndarray:
    """Sorted chainages from ``s0`` to ``s1`` no more than ``max_step`` apart, including ``extra``."""
    n = max(1, int(np.ceil((s1 - s0) / max_step)))
    s = np.concatenate([np.linspace(s0, s1, n + 1), [x for x in extra if s0 < x < s1]])
    return np.unique(s)


class MeshBuilder:
    """Collects triangles (in track-frame vertices) with a surface class each."""

    def __init__(self) -> None:
        self._verts: list[np.ndarray] = []
        self._tris: list[np.ndarray] = []
        self._cls: list[np.ndarray] = []
        self._n = 0

    def add(self, suv: np.ndarray, tris: np.ndarray, cls: int | np.ndarray) -> None:
        """Add vertices (k, 3) and triangles (m, 3) indexing them, with class(es)."""
        tris = np.asarray(tris, dtype=np.int64).reshape(-1, 3)
        self._verts.append(np.asarray(suv, dtype=float).reshape(-1, 3))
        self._tris.append(tris + self._n)
        self._cls.append(np.broadcast_to(np.asarray(cls, dtype=np.uint8), (len(tris),)).copy())
        self._n += len(self._verts[-1])

    def quads(self, corners: np.ndarray, cls: int | np.ndarray) -> None:
        """Add quads given as (m, 4, 3) corner arrays (in order around the quad)."""
        m = len(corners)
        base = 4 * np.arange(m)[:, None]
        tris = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]])
        self.add(corners.reshape(-1, 3), tris, np.concatenate([np.broadcast_to(cls, (m,))] * 2))

    def sweep(self, uv: np.ndarray, cls: np.ndarray | int, s: np.ndarray,
              holes: Sequence[Hole] = ()) -> None:
        """Sweep a polyline ``uv`` (k, 2) along chainages ``s`` (a grid of quads).

        ``cls`` is one class per polyline edge (or one for all). Quads whose centre lies inside a
        hole box are left out (niches cut into walls).
        """
        uv = np.asarray(uv, dtype=float)
        k, m = len(uv), len(s)
        grid = np.empty((m, k, 3))
        grid[..., 0] = np.asarray(s)[:, None]
        grid[..., 1:] = uv[None]
        c = np.broadcast_to(np.asarray(cls, dtype=np.uint8), (k - 1,))
        corners = np.stack([grid[:-1, :-1], grid[1:, :-1], grid[1:, 1:], grid[:-1, 1:]], axis=2)
        corners = corners.reshape(-1, 4, 3)
        qcls = np.broadcast_to(c, (m - 1, k - 1)).reshape(-1)
        keep = np.ones(len(corners), dtype=bool)
        centre = corners.mean(axis=1)
        for s0, s1, u0, u1, v0, v1 in holes:
            keep &= ~((centre[:, 0] > s0) & (centre[:, 0] < s1) & (centre[:, 1] > u0)
                      & (centre[:, 1] < u1) & (centre[:, 2] > v0) & (centre[:, 2] < v1))
        self.quads(corners[keep], qcls[keep])

    def boxes(self, params: np.ndarray, cls: int, faces: Sequence[str] = tuple(_FACES)) -> None:
        """Axis-aligned boxes in the track frame, one row (s0, s1, u0, u1, v0, v1) each;
        ``faces`` picks which of their six sides to add."""
        p = np.atleast_2d(np.asarray(params, dtype=float))
        if not len(p):
            return
        bits = np.arange(8)
        corners = np.stack([np.where(bits & 1, p[:, [1]], p[:, [0]]),
                            np.where(bits & 2, p[:, [3]], p[:, [2]]),
                            np.where(bits & 4, p[:, [5]], p[:, [4]])], axis=-1)   # (n, 8, 3)
        idx = np.array([_FACES[f] for f in faces])                                # (f, 4)
        self.quads(corners[:, idx].reshape(-1, 4, 3), cls)

    def prism(self, uv: np.ndarray, s: np.ndarray, cls: int) -> None:
        """A convex closed polygon ``uv`` (first vertex not repeated) swept along ``s``, capped."""
        uv = np.asarray(uv, dtype=float)
        self.sweep(np.vstack([uv, uv[:1]]), cls, s)
        for sc in (s[0], s[-1]):
            verts = np.column_stack([np.full(len(uv), sc), uv])
            fan = np.column_stack([np.zeros(len(uv) - 2), np.arange(1, len(uv) - 1), np.arange(2, len(uv))])
            self.add(verts, fan, cls)

    def band(self, outer: np.ndarray, inner: np.ndarray, s0: float, s1: float, cls: int) -> None:
        """A thick strip along a wall (an arch rib): inner face, two side faces, two end caps."""
        self.sweep(inner, cls, np.array([s0, s1]))
        for sc in (s0, s1):
            o = np.column_stack([np.full(len(outer), sc), outer])
            i = np.column_stack([np.full(len(inner), sc), inner])
            self.quads(np.stack([o[:-1], o[1:], i[1:], i[:-1]], axis=1), cls)
        for j in (0, -1):
            self.quads(np.array([[[s0, *outer[j]], [s1, *outer[j]], [s1, *inner[j]], [s0, *inner[j]]]]), cls)

    def ring(self, outline: np.ndarray, centre: tuple[float, float],
             bounds: tuple[float, float, float, float], s: float, cls: int) -> None:
        """The plane at chainage ``s`` outside a closed ``outline`` and inside ``bounds``
        (u0, u1, v0, v1): an end wall between two sections. The outline must be star-shaped
        around ``centre``; its vertices are projected radially onto the bounding rectangle."""
        c = np.asarray(centre, dtype=float)
        d = np.asarray(outline, dtype=float) - c
        lo, hi = np.array(bounds[0::2]) - c, np.array(bounds[1::2]) - c
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(d > 0, hi / d, np.where(d < 0, lo / d, np.inf))
        axis = np.argmin(t, axis=1)                  # 0: hits a vertical side, 1: horizontal
        q = c + d * t.min(axis=1)[:, None]
        p2 = np.column_stack([np.full(len(d), s), outline])
        q2 = np.column_stack([np.full(len(d), s), q])
        self.quads(np.stack([p2[:-1], p2[1:], q2[1:], q2[:-1]], axis=1), cls)
        turn = np.nonzero(axis[:-1] != axis[1:])[0]  # fill the rectangle corner between them
        corner = np.where((axis[turn] == 0)[:, None], np.column_stack([q[turn, 0], q[turn + 1, 1]]),
                          np.column_stack([q[turn + 1, 0], q[turn, 1]]))
        tri = np.stack([q2[turn], np.column_stack([np.full(len(turn), s), corner]), q2[turn + 1]], 1)
        if len(tri):
            self.add(tri.reshape(-1, 3), np.arange(3 * len(tri)).reshape(-1, 3), cls)

    def build(self, centreline: Centreline) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Vertices in local ENU (n, 3), triangles (m, 3) int32 and classes (m,) uint8."""
        suv = np.concatenate(self._verts)
        return (centreline.to_local(suv), np.concatenate(self._tris).astype(np.int32),
                np.concatenate(self._cls))
