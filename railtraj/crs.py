"""Accurate transforms between the survey CRS and ETRS89 (EPSG:4937), or a clear refusal.

Anchors for GNSS/INS post-processing are given in ETRS89 latitude, longitude and ellipsoidal
height; SBET trajectories arrive in it. For British National Grid with ODN heights (EPSG:7405)
this needs the Ordnance Survey grids OSTN15 and OSGM15. Without them PROJ silently falls back to
a Helmert shift and a "ballpark" vertical step: metres wrong horizontally and 44-53 m wrong in
height, with only a warning. So every transformer here is built with ``only_best=True`` and
``allow_ballpark=False``, which makes PROJ raise instead, and that becomes a :class:`CRSError`
telling the user where to get the grids. Results are checked to be finite (``errcheck=True``).

The two grids ship with railtraj (``railtraj/grids/``, BSD-2 from PROJ-data ``uk_os/``) and are
put last on PROJ's search path, so BNG works out of the box while ``PROJ_DATA``, PROJ's user
folder and an explicit ``grid_dir`` still win.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

import numpy as np
import pyproj
from pyproj.exceptions import CRSError as ProjCRSError
from pyproj.exceptions import ProjError

from railtraj.errors import CRSError

ETRS89_3D = "EPSG:4937"
OS_GRIDS = ("uk_os_OSTN15_NTv2_OSGBtoETRS.tif", "uk_os_OSGM15_GB.tif")
#: the OS grids shipped as package data; searched after every other PROJ data folder
PACKAGED_GRID_DIR = Path(__file__).resolve().with_name("grids")
_OS_HINT = ("the Ordnance Survey grids {} and {} were not found (railtraj ships them in "
            "railtraj/grids/: reinstall railtraj, or download them from PROJ-data (uk_os/) and "
            "pass their folder as proj_grid_dir=...)").format(*OS_GRIDS)


def survey_crs(crs: str | pyproj.CRS) -> pyproj.CRS:
    """The 3-D CRS to use for survey coordinates: 2-D EPSG:27700 becomes EPSG:7405 (BNG + ODN)."""
    try:
        c = pyproj.CRS.from_user_input(crs)
    except ProjCRSError as err:
        raise CRSError(f"{crs!r} is not a CRS pyproj understands ({err}); give an EPSG code "
                       "such as EPSG:27700 or a WKT/PROJ string") from None
    return pyproj.CRS.from_epsg(7405) if c.to_epsg() == 27700 else c


def use_grid_dir(grid_dir: str | os.PathLike | None) -> None:
    """Put ``grid_dir`` (if given) and then the packaged grids on PROJ's data search path.

    The path is process-wide in pyproj and PROJ takes the first file of a name it finds, so a
    user's folder goes before the packaged one, which always stays last.
    """
    dirs = pyproj.datadir.get_data_dir().split(os.pathsep)
    packaged = str(PACKAGED_GRID_DIR)
    if packaged not in dirs and PACKAGED_GRID_DIR.is_dir():
        dirs.append(packaged)
    if grid_dir is not None:
        folder = Path(grid_dir).resolve()
        if not folder.is_dir():
            raise CRSError(f"proj_grid_dir={grid_dir} is not a folder: pass the folder that holds "
                           f"the PROJ grid files (for BNG: {OS_GRIDS[0]} and {OS_GRIDS[1]})")
        if str(folder) not in dirs:
            dirs.insert(dirs.index(packaged) if packaged in dirs else len(dirs), str(folder))
    if os.pathsep.join(dirs) != pyproj.datadir.get_data_dir():
        pyproj.datadir.set_data_dir(os.pathsep.join(dirs))


def _label(crs: pyproj.CRS) -> str:
    code = crs.to_authority()
    return ":".join(code) if code else crs.name


@functools.lru_cache(maxsize=16)
def _build(src_wkt: str, dst_wkt: str) -> pyproj.Transformer:
    return pyproj.Transformer.from_crs(pyproj.CRS(src_wkt), pyproj.CRS(dst_wkt), always_xy=True,
                                       only_best=True, allow_ballpark=False)


def _transformer(src: pyproj.CRS, dst: pyproj.CRS, grid_dir) -> pyproj.Transformer:
    use_grid_dir(grid_dir)
    try:
        return _build(src.to_wkt(), dst.to_wkt())
    except ProjError as err:
        survey = dst if src == pyproj.CRS(ETRS89_3D) else src
        head = f"cannot transform {_label(src)} to {_label(dst)} accurately: "
        if survey.to_epsg() == 7405 or "uk_os_" in str(err):
            head = f"cannot transform {_label(survey)} to ETRS89 accurately: "
            raise CRSError(head + _OS_HINT) from None
        raise CRSError(head + f"{err}; install the PROJ grids this CRS needs and pass their folder "
                       "as proj_grid_dir=..., or give a 3-D (compound) survey CRS") from None


def etrs89_transformer(src_crs: str | pyproj.CRS = "EPSG:27700",
                       grid_dir: str | os.PathLike | None = None) -> pyproj.Transformer:
    """Transformer survey CRS -> ETRS89 (EPSG:4937), ``always_xy``: (E, N, H) -> (lon, lat, h_ell).

    Raises :class:`CRSError` if PROJ has no accurate (non-ballpark) path, e.g. missing grids.
    """
    return _transformer(survey_crs(src_crs), pyproj.CRS(ETRS89_3D), grid_dir)


def geographic_transformer(dst_crs: str | pyproj.CRS = "EPSG:27700",
                           grid_dir: str | os.PathLike | None = None) -> pyproj.Transformer:
    """Inverse of :func:`etrs89_transformer`: (lon, lat, h_ell) -> (E, N, H) in ``dst_crs``."""
    return _transformer(pyproj.CRS(ETRS89_3D), survey_crs(dst_crs), grid_dir)


def _run(tr: pyproj.Transformer, a, b, c, what: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    try:
        out = tr.transform(np.asarray(a, float), np.asarray(b, float), np.asarray(c, float),
                           errcheck=True)
    except ProjError as err:
        raise CRSError(f"{what} failed ({err}): the coordinates are outside the area the "
                       "transformation grids cover; check the survey CRS (crs=...)") from None
    out = tuple(np.atleast_1d(np.asarray(v, dtype=np.float64)) for v in out)
    if not all(np.isfinite(v).all() for v in out):
        raise CRSError(f"{what} gave non-finite results: a grid is missing or the coordinates are "
                       "outside it; check the survey CRS and proj_grid_dir=...")
    return out


def to_etrs89(xyz: np.ndarray, src_crs: str | pyproj.CRS = "EPSG:27700",
              grid_dir: str | os.PathLike | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ETRS89 latitude, longitude (degrees) and ellipsoidal height (m) of (n, 3) survey points."""
    p = np.atleast_2d(np.asarray(xyz, dtype=np.float64))
    lon, lat, h = _run(etrs89_transformer(src_crs, grid_dir), p[:, 0], p[:, 1], p[:, 2],
                       f"transforming {len(p)} points from {src_crs} to ETRS89")
    return lat, lon, h


def from_geographic(lat_deg: np.ndarray, lon_deg: np.ndarray, h_ell: np.ndarray,
                    dst_crs: str | pyproj.CRS = "EPSG:27700",
                    grid_dir: str | os.PathLike | None = None) -> np.ndarray:
    """(n, 3) survey-CRS coordinates of ETRS89 latitude, longitude (degrees), h_ell (m)."""
    x, y, z = _run(geographic_transformer(dst_crs, grid_dir), lon_deg, lat_deg, h_ell,
                   f"transforming ETRS89 positions to {dst_crs}")
    return np.column_stack([x, y, z])


def grid_convergence(lat_deg: np.ndarray, lon_deg: np.ndarray,
                     crs: str | pyproj.CRS = "EPSG:27700") -> np.ndarray:
    """Meridian convergence (degrees) of ``crs``'s map projection at the given points.

    pyproj's sign convention (checked against finite differences of the projection): it is the
    true azimuth of grid north, so ``grid_heading = true_heading - convergence``. Zero for a
    geographic CRS. Latitude/longitude may be ETRS89: the datum shift changes it by < 1e-6 deg.
    """
    c = survey_crs(crs)
    horizontal = c.sub_crs_list[0] if c.is_compound else c
    lat = np.atleast_1d(np.asarray(lat_deg, dtype=np.float64))
    lon = np.atleast_1d(np.asarray(lon_deg, dtype=np.float64))
    if not horizontal.is_projected:
        return np.zeros(np.broadcast(lat, lon).shape)
    factors = pyproj.Proj(horizontal).get_factors(lon, lat, errcheck=True)
    return np.asarray(factors.meridian_convergence, dtype=np.float64)
