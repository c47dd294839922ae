"""railtraj.crs: accurate BNG/ODN <-> ETRS89 with the OS grids, a clear CRSError without them."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyproj
import pytest

from railtraj import crs
from railtraj.errors import CRSError

GRID_DIR = Path("/work/shared/data/proj")
HAVE_GRIDS = all((GRID_DIR / g).is_file() for g in crs.OS_GRIDS)
needs_grids = pytest.mark.skipif(
    not HAVE_GRIDS, reason=f"Ordnance Survey grids {crs.OS_GRIDS} not found in {GRID_DIR}")

#: BNG easting, northing, ODN height across England (London, Norfolk, Cornwall, Cumbria).
ENGLAND = np.array([[530000.0, 180000.0, 10.0], [620000.0, 300000.0, 30.0],
                    [170000.0, 50000.0, 100.0], [330000.0, 520000.0, 250.0]])


@needs_grids
def test_bng_points_round_trip_below_1_mm():
    lat, lon, h = crs.to_etrs89(ENGLAND, "EPSG:27700", GRID_DIR)
    back = crs.from_geographic(lat, lon, h, "EPSG:27700", GRID_DIR)
    assert np.abs(back - ENGLAND).max() < 1e-3


@needs_grids
def test_known_point_and_geoid_separation_in_england():
    lat, lon, h = crs.to_etrs89(ENGLAND, "EPSG:27700", GRID_DIR)
    # 530000, 180000 is by Trafalgar Square, London.
    assert abs(lat[0] - 51.504) < 2e-3 and abs(lon[0] - (-0.128)) < 2e-3
    separation = h - ENGLAND[:, 2]
    assert ((separation > 44.0) & (separation < 54.0)).all(), separation


@needs_grids
def test_2d_bng_is_promoted_to_bng_plus_odn():
    assert crs.survey_crs("EPSG:27700").to_epsg() == 7405
    a = np.column_stack(crs.to_etrs89(ENGLAND, "EPSG:27700", GRID_DIR))
    b = np.column_stack(crs.to_etrs89(ENGLAND, "EPSG:7405", GRID_DIR))
    np.testing.assert_array_equal(a, b)
    tr = crs.etrs89_transformer("EPSG:27700", GRID_DIR)
    assert "OSGB36 to ETRS89" in tr.description and "ODN height" in tr.description


@needs_grids
def test_point_outside_the_grid_is_a_crs_error():
    with pytest.raises(CRSError, match="outside"):
        crs.to_etrs89([[-3.0e6, 180000.0, 10.0]], "EPSG:27700", GRID_DIR)


def test_missing_grids_raise_crs_error_in_a_fresh_process(tmp_path):
    """append_data_dir is process-wide, so the no-grid case runs in its own interpreter."""
    env = {k: v for k, v in os.environ.items() if k not in ("PROJ_DATA", "PROJ_LIB")}
    env.update(PROJ_NETWORK="OFF", PROJ_USER_WRITABLE_DIRECTORY=str(tmp_path))
    code = ("from railtraj import crs\n"
            "from railtraj.errors import CRSError\n"
            "try:\n    crs.etrs89_transformer('EPSG:27700')\n"
            "except CRSError as e:\n    print('CRSError:', e)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                         timeout=120, check=True).stdout
    assert out.startswith("CRSError: cannot transform EPSG:7405 to ETRS89 accurately"), out
    assert "uk_os_OSTN15_NTv2_OSGBtoETRS.tif" in out and "proj_grid_dir=" in out


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
