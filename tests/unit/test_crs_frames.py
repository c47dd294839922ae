"""Any survey frame: an SBET in WGS 84 against a UTM survey, anchors back in the SBET's frame,
the British default (ETRS89) unchanged, and a bad ``sbet_crs`` refused in one line."""

from __future__ import annotations

import logging
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pyproj
import pytest

from railtraj import crs
from railtraj.errors import ConfigError, CRSError
from railtraj.export import _write_anchors, anchors_crs
from railtraj.io.outputs import read_anchors_csv
from railtraj.io.sbet import read_sbet, sbet_to_trajectory, trajectory_to_sbet
from railtraj.pipeline import PipelineOptions

#: PDAL's real SBET: 2 epochs at 32.545 N, 116.98 W (California), i.e. in UTM zone 11N
SBET = Path(__file__).resolve().parents[1] / "data" / "pdal_sbet_smrmsg" / "2-points.sbet"
UTM11 = "EPSG:32611"


def _pyproj_utm(records: np.ndarray) -> np.ndarray:
    """E, N, h_ell of the SBET positions in WGS 84 / UTM 11N, straight from pyproj."""
    tr = pyproj.Transformer.from_crs("EPSG:4979", UTM11, always_xy=True)
    e, n = tr.transform(np.degrees(records["lon"]), np.degrees(records["lat"]))
    return np.column_stack([e, n, records["z"]])


@pytest.mark.parametrize("sbet_crs", ["EPSG:4979", None])
def test_wgs84_sbet_on_a_utm_survey_matches_pyproj_to_1_mm(sbet_crs):
    records = read_sbet(SBET)
    traj = sbet_to_trajectory(records, crs=UTM11, sbet_crs=sbet_crs)
    expected = _pyproj_utm(records)
    assert np.abs(traj.xyz - expected).max() < 1e-3
    assert 500_000 < expected[0, 0] < 503_000 and 3_600_000 < expected[0, 1] < 3_602_000
    lat, lon = np.degrees(records["lat"]), np.degrees(records["lon"])
    conv = pyproj.Proj(UTM11).get_factors(lon, lat).meridian_convergence
    np.testing.assert_allclose(traj.rpy[:, 2], np.mod(np.degrees(records["heading"]) - conv, 360),
                               atol=1e-9)


def test_utm_survey_back_to_the_wgs84_sbet_frame():
    records = read_sbet(SBET)
    traj = sbet_to_trajectory(records, crs=UTM11, sbet_crs="EPSG:4979")
    back = trajectory_to_sbet(traj, crs=UTM11, sbet_crs="EPSG:4979", template=records)
    # 1e-10 rad is 0.6 mm on the ground
    np.testing.assert_allclose(back["lat"], records["lat"], rtol=0, atol=1e-10)
    np.testing.assert_allclose(back["lon"], records["lon"], rtol=0, atol=1e-10)
    np.testing.assert_allclose(back["z"], records["z"], rtol=0, atol=1e-3)
    np.testing.assert_allclose(back["heading"], records["heading"], rtol=0, atol=1e-9)


def test_2d_projected_survey_is_promoted_with_ellipsoidal_heights(caplog):
    crs._promoted.cache_clear()
    with caplog.at_level(logging.INFO, logger="railtraj.crs"):
        c = crs.survey_crs_3d(UTM11)
    assert c.is_projected and len(c.axis_info) == 3 and "UTM zone 11N" in c.name
    assert "taken as 3-D with ellipsoidal heights on its own datum (WGS 84)" in caplog.text
    assert crs.survey_crs_3d("EPSG:27700").to_epsg() == 7405  # BNG still gets ODN heights
    compound = pyproj.CRS("EPSG:32611+5703")
    assert crs.survey_crs_3d(compound) == compound  # a vertical datum is kept: geoid grids needed


def test_anchors_are_written_in_the_sbet_frame_and_read_back(tmp_path):
    records = read_sbet(SBET)
    traj = sbet_to_trajectory(records, crs=UTM11, run_id="a")
    t = records["time"]
    ties = SimpleNamespace(run_a="a", run_b="b", time_a=np.array([t[0], t[1]]), time_b=t.copy())
    result = SimpleNamespace(corrected={"a": traj}, ties=[ties], offsets=[],
                             options=PipelineOptions(crs=UTM11, sbet_crs="EPSG:4979"))
    # the 2 epochs are 5 ms apart, so anchors (one per 0.5 s) keep the first
    assert _write_anchors(result, tmp_path, "true", notes := []) == 1 and not notes
    rows = read_anchors_csv(tmp_path / "anchors.csv")
    records = records[:1]
    assert anchors_crs(result) == "EPSG:4979"
    # lat, lon, h_ell are the SBET's own WGS 84 values (anchors.csv keeps 1e-9 degree, 0.1 mm)
    np.testing.assert_allclose(rows["lat"], np.degrees(records["lat"]), rtol=0, atol=2e-9)
    np.testing.assert_allclose(rows["lon"], np.degrees(records["lon"]), rtol=0, atol=2e-9)
    np.testing.assert_allclose(rows["h_ell"], records["z"], rtol=0, atol=1e-3)
    xyz = crs.from_geographic(rows["lat"], rows["lon"], rows["h_ell"], UTM11, sbet_crs="EPSG:4979")
    assert np.abs(xyz - np.column_stack([rows["x"], rows["y"], rows["z"]])).max() < 1e-3


def test_british_default_is_etrs89_and_unchanged():
    assert crs.default_sbet_crs("EPSG:27700") == crs.ETRS89_3D
    assert crs.default_sbet_crs("EPSG:7405") == crs.ETRS89_3D
    assert crs.default_sbet_crs(UTM11) == crs.WGS84_3D
    assert anchors_crs(SimpleNamespace(options=PipelineOptions())) == "EPSG:4937"
    lat, lon, h = np.array([51.5]), np.array([-0.13]), np.array([60.0])
    np.testing.assert_array_equal(crs.from_geographic(lat, lon, h, "EPSG:27700"),
                                  crs.from_geographic(lat, lon, h, "EPSG:27700", sbet_crs="EPSG:4937"))


def test_default_frame_is_logged_for_a_non_british_survey(caplog):
    with caplog.at_level(logging.INFO, logger="railtraj.crs"):
        assert crs.resolve_sbet_crs(None, UTM11) == "EPSG:4979"
        assert crs.resolve_sbet_crs("EPSG:7912", UTM11) == "EPSG:7912"
        assert crs.resolve_sbet_crs(None, "EPSG:27700") == "EPSG:4937"
    assert len(caplog.records) == 1 and "WGS 84 (EPSG:4979)" in caplog.text


@pytest.mark.parametrize(("value", "fix"), [
    ("EPSG:4326", "sbet_crs=EPSG:4979"),     # 2-D: its 3-D version
    ("EPSG:32611", "sbet_crs=EPSG:4979"),    # projected: its geographic 3-D frame
    ("EPSG:4978", "EPSG:4979 (WGS 84)"),     # geocentric: the examples
    ("EPSG:5703", "EPSG:4979 (WGS 84)"),     # vertical
    ("not-a-crs", "EPSG:4979 (WGS 84)"),
])
def test_bad_sbet_crs_is_a_one_line_config_error(value, fix):
    with pytest.raises(ConfigError) as err:
        crs.sbet_frame(value, UTM11)
    msg = str(err.value)
    assert msg.startswith(f"sbet_crs={value} ") and fix in msg and "\n" not in msg


def test_cli_refuses_a_bad_sbet_crs_with_exit_2(tmp_path):
    run = subprocess.run([sys.executable, "-m", "railtraj.cli", f"survey_dir={tmp_path / 'none'}",
                          f"out_dir={tmp_path / 'out'}", "crs=EPSG:32611", "sbet_crs=EPSG:4326"],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 2
    lines = [ln for ln in run.stderr.splitlines() if ln.startswith("railtraj: error:")]
    assert len(lines) == 1 and "sbet_crs=EPSG:4979" in lines[0], run.stderr


def test_a_coarse_datum_change_is_a_warning_naming_the_survey_frame(caplog):
    """ITRF2014 to the WGS 84 ensemble is a 2 m transformation: PROJ moves the positions."""
    crs._warn_if_coarse.cache_clear()
    lat, lon, h = [32.545], [-116.98], [107.7]
    with caplog.at_level(logging.WARNING, logger="railtraj.crs"):
        crs.from_geographic(lat, lon, h, UTM11, sbet_crs="EPSG:4979")
        assert not caplog.records
        crs.from_geographic(lat, lon, h, UTM11, sbet_crs="EPSG:7912")
    assert "accurate to 2.00 m only" in caplog.text and "sbet_crs=EPSG:4979" in caplog.text


def test_compound_us_survey_still_needs_its_geoid_grid():
    """UTM 11N + NAVD88: orthometric heights need the NOAA geoid grid, ellipsoidal ones do not."""
    try:
        crs.from_geographic([32.545], [-116.98], [107.7], "EPSG:32611+5703", sbet_crs="EPSG:4979")
    except CRSError as err:
        assert "proj_grid_dir=" in str(err) and "\n" not in str(err)
    else:
        pytest.skip("a NAVD88 geoid grid is installed (or PROJ's network is on)")
