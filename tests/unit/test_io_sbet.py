"""SBET/SMRMSG: PDAL's reference fixtures, byte-identical round trips, conversion to SPEC."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyproj
import pytest

from railtraj.crs import PACKAGED_GRID_DIR, grid_convergence
from railtraj.errors import FormatError, TrajectoryError
from railtraj.io.sbet import (
    SBET_DTYPE,
    SMRMSG_DTYPE,
    read_sbet,
    read_smrmsg,
    sbet_to_trajectory,
    smrmsg_sd_at,
    trajectory_to_sbet,
    write_sbet,
    write_smrmsg,
)

PDAL = Path(__file__).resolve().parents[1] / "data" / "pdal_sbet_smrmsg"
GRID_DIR = PACKAGED_GRID_DIR

# PDAL test/unit/io/SbetReaderTest.cpp, radians.
RECORD0 = [1.516310028360710e+05, 5.680211852972264e-01, -2.041654392303940e+00,
           1.077152953296560e+02, -2.332420866600025e+00, -3.335067504871401e-01,
           -3.093961631767838e-02, -2.813407149321339e-02, -2.429905393889139e-02,
           3.046773230278662e+00, -2.198414736922658e-02, 7.859639737752390e-01,
           7.849084719295495e-01, -2.978807916450262e-01, 6.226807982589819e-05,
           9.312162756440178e-03, 7.217812320996525e-02]
RECORD1 = [1.516310078318641e+05, 5.680211834722869e-01, -2.041654392034053e+00,
           1.077151424357507e+02, -2.336228229691271e+00, -3.324663118952635e-01,
           -3.022948961008987e-02, -2.813856631423094e-02, -2.425215669392169e-02,
           3.047131105236811e+00, -2.198416007932108e-02, 8.397590491636475e-01,
           3.252165276637165e-01, -1.558883225990844e-01, 8.379685112283802e-04,
           7.372886784718076e-03, 7.179027672314571e-02]
SMRMSG0 = [536258, 0.056279, 0.057791, 0.070774, 0.006642, 0.008034, 0.008131, 0.236985,
           0.239420, 3.010802]


def test_pdal_sbet_records_are_reproduced():
    rec = read_sbet(PDAL / "2-points.sbet")
    assert rec.dtype == SBET_DTYPE and len(rec) == 2 and SBET_DTYPE.itemsize == 136
    np.testing.assert_allclose(list(rec[0]), RECORD0, rtol=1e-15, atol=0)
    np.testing.assert_allclose(list(rec[1]), RECORD1, rtol=1e-15, atol=0)


def test_pdal_smrmsg_count_and_first_record():
    rec = read_smrmsg(PDAL / "smrmsg.smrmsg")
    assert rec.dtype == SMRMSG_DTYPE and len(rec) == 21902 and SMRMSG_DTYPE.itemsize == 80
    np.testing.assert_allclose(list(rec[0]), SMRMSG0, rtol=0, atol=5e-7)


def test_pdal_smrmsg_matches_its_text_dump():
    """Spot rows of PDAL's smrmsg.txt (6 decimals), through to the last record."""
    expected = np.loadtxt(PDAL / "smrmsg_expected.csv", delimiter=",", comments="#", skiprows=3)
    rec = read_smrmsg(PDAL / "smrmsg.smrmsg")
    rows = expected[:, 0].astype(int)
    assert rows[-1] == len(rec) - 1 and len(rows) > 20
    got = np.array([list(r) for r in rec[rows]])
    np.testing.assert_allclose(got, expected[:, 1:], rtol=0, atol=5e-7)


@pytest.mark.parametrize(("name", "reader", "writer"), [
    ("2-points.sbet", read_sbet, write_sbet), ("smrmsg.smrmsg", read_smrmsg, write_smrmsg)])
def test_write_back_is_byte_identical(tmp_path, name, reader, writer):
    out = tmp_path / name
    writer(out, reader(PDAL / name))
    assert out.read_bytes() == (PDAL / name).read_bytes()


def test_pdal_badfile_is_rejected():
    with pytest.raises(FormatError, match=r"is 271 bytes, not a multiple of the 136-byte SBET "
                                          r"record: the file is truncated or not an SBET"):
        read_sbet(PDAL / "badfile.sbet")


def test_empty_and_garbage_files(tmp_path):
    (tmp_path / "e.sbet").write_bytes(b"")
    with pytest.raises(FormatError, match="is 0 bytes"):
        read_sbet(tmp_path / "e.sbet")
    junk = np.full(17, 1e6)  # latitude of 1e6 rad
    (tmp_path / "j.sbet").write_bytes(junk.tobytes())
    with pytest.raises(FormatError, match="not an SBET"):
        read_sbet(tmp_path / "j.sbet")


def test_smrmsg_from_another_run_is_refused():
    sbet, smr = read_sbet(PDAL / "2-points.sbet"), read_smrmsg(PDAL / "smrmsg.smrmsg")
    with pytest.raises(TrajectoryError, match="same POSPac run"):
        smrmsg_sd_at(smr, sbet["time"])


def test_smrmsg_sd_is_east_north_down_interpolated():
    smr = np.zeros(3, dtype=SMRMSG_DTYPE)
    smr["time"] = [10.0, 11.0, 12.0]
    smr["north_rms"], smr["east_rms"], smr["down_rms"] = [1, 2, 3], [10, 20, 30], [5, 5, 7]
    sd = smrmsg_sd_at(smr, np.array([10.5, 11.75]))
    np.testing.assert_allclose(sd, [[15, 1.5, 5], [27.5, 2.75, 6.5]])


def test_trajectory_sbet_round_trip(make_trajectory):
    # 150 km west of the central meridian (-2 deg): convergence is about -1.76 degrees here.
    traj = make_trajectory(n=100, seed=3, origin=(250000.0, 300000.0, 50.0), heading_deg=30.0)
    rec = trajectory_to_sbet(traj, "EPSG:27700", GRID_DIR)
    back = sbet_to_trajectory(rec, "EPSG:27700", GRID_DIR, run_id="r")
    assert back.run_id == "r"
    np.testing.assert_array_equal(back.time, traj.time)
    assert np.abs(back.xyz - traj.xyz).max() < 1e-3
    assert np.abs(back.rpy - traj.rpy).max() < 1e-9
    conv = grid_convergence(np.degrees(rec["lat"]), np.degrees(rec["lon"]))
    assert -2.0 < conv.mean() < -1.5
    np.testing.assert_allclose(np.degrees(rec["heading"]), traj.rpy[:, 2] + conv, atol=1e-9)


def test_sbet_heading_is_the_true_azimuth_of_motion(make_trajectory):
    """Independent check of the convergence sign: a run moving along grid bearing 30 degrees
    moves along the true azimuth that the SBET heading states (geodesic between epochs)."""
    traj = make_trajectory(n=200, seed=4, origin=(250000.0, 300000.0, 50.0), heading_deg=30.0)
    rec = trajectory_to_sbet(traj, "EPSG:27700", GRID_DIR)
    lat, lon = np.degrees(rec["lat"]), np.degrees(rec["lon"])
    az, _, _ = pyproj.Geod(ellps="GRS80").inv(lon[0], lat[0], lon[-1], lat[-1])
    true_heading_of_course = np.degrees(rec["heading"]) - (traj.rpy[:, 2] - 30.0)
    assert abs(az - true_heading_of_course.mean()) < 0.02
    assert abs(az - 30.0) > 0.5  # grid and true bearings really differ here


def test_velocities_without_template_are_north_west_up(make_trajectory):
    traj = make_trajectory(n=50, seed=5, heading_deg=90.0, speed=10.0)
    rec = trajectory_to_sbet(traj, "EPSG:27700", GRID_DIR)
    assert abs(np.median(rec["vy"]) + 10.0) < 0.1 and abs(np.median(rec["vx"])) < 0.1
    assert abs(np.median(rec["vz"]) - 0.1) < 0.05
    assert (rec["wander"] == 0).all() and (rec["ax"] == 0).all()


def test_template_keeps_other_fields_and_sd_from_smrmsg(make_trajectory):
    traj = make_trajectory(n=20, seed=6)
    template = np.zeros(len(traj), dtype=SBET_DTYPE)
    template["time"] = traj.time
    template["wx"] = 0.25
    rec = trajectory_to_sbet(traj, "EPSG:27700", GRID_DIR, template=template)
    assert (rec["wx"] == 0.25).all()
    smr = np.zeros(2, dtype=SMRMSG_DTYPE)
    smr["time"] = [traj.time[0] - 1, traj.time[-1] + 1]
    smr["east_rms"], smr["north_rms"], smr["down_rms"] = 0.01, 0.02, 0.03
    back = sbet_to_trajectory(rec, "EPSG:27700", GRID_DIR, smrmsg=smr)
    np.testing.assert_allclose(back.sd, np.tile([0.01, 0.02, 0.03], (len(traj), 1)))
    with pytest.raises(TrajectoryError, match="template"):
        trajectory_to_sbet(traj, "EPSG:27700", GRID_DIR, template=template[:5])
