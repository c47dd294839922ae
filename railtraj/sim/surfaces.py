"""Surface classes of the simulated scene and the LiDAR intensity each returns.

Every triangle of the scene carries one class; the scanner looks the class up for each hit to
give the point a plausible intensity (retro-reflective targets bright, steel rails bright,
wet ballast dark), so that intensity-based methods and the QC report see realistic contrast.
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np


class Surface(IntEnum):
    """What a triangle is made of (stored per triangle as uint8)."""

    LINING = 0          # concrete tunnel lining
    BED = 1             # track bed: ballast or slab
    RAIL = 2
    SLEEPER = 3
    RIB = 4             # steel arch rib
    PLATFORM = 5
    PLATFORM_EDGE = 6   # painted edge and coping
    WALL = 7            # station wall tiles
    CEILING = 8
    PILLAR = 9
    NICHE = 10
    DOOR = 11           # emergency exit door at the back of a niche
    METAL = 12          # signal boxes, cabinets
    CABLE_TRAY = 13
    EARTH = 14          # cutting slopes
    RETAINING = 15      # cutting retaining walls and portal headwalls
    MAST = 16           # overhead line masts
    TARGET = 17         # retro-reflective survey target (control point)


#: Mean intensity (uint16 scale) at normal incidence and 5 m range, per class.
REFLECTANCE = np.array([
    18000, 9000, 42000, 20000, 26000, 22000, 38000, 30000, 20000, 24000,
    17000, 33000, 28000, 25000, 12000, 19000, 27000, 62000,
], dtype=float)

assert len(REFLECTANCE) == len(Surface)


def intensity(cls: np.ndarray, cos_incidence: np.ndarray, rng_m: np.ndarray,
              rng: np.random.Generator, noise: float = 0.06, gain: np.ndarray | None = None) -> np.ndarray:
    """Intensity per hit: class reflectance, Lambert-like incidence, mild range fall-off, noise.

    The model is deliberately simple: ``R * g * (0.3 + 0.7 cos) * (5 / max(r, 1)) ** 0.5 * (1 + noise)``,
    clipped to uint16; ``g`` is ``gain`` per hit (marks on the lining, :mod:`railtraj.sim.marks`), else 1.
    """
    base = REFLECTANCE[cls] * (0.3 + 0.7 * np.abs(cos_incidence))
    if gain is not None:
        base *= gain
    base *= np.sqrt(5.0 / np.maximum(rng_m, 1.0))
    base *= 1.0 + noise * rng.standard_normal(len(base))
    return np.clip(base, 0, 65535).astype(np.uint16)
