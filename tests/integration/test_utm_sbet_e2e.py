"""End to end: a UTM survey whose runs come as WGS 84 SBETs, as a surveyor receives them.

The simulated "thesis" survey is placed in UTM zone 11N (EPSG:32611, ellipsoidal heights) near
32.5 degrees N, where the meridian convergence is about -0.1 degree. Each run's trajectory.csv is
replaced by an SBET (and SMRMSG) written here independently of railtraj's own writer: pyproj
projects the UTM positions to WGS 84 (EPSG:4979) and the grid heading becomes true heading with
the projection's meridian convergence. railtraj must read them back to the same positions, run
with ``crs=EPSG:32611 sbet_crs=EPSG:4979`` and write anchors in WGS 84.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyproj
import pytest

from railtraj.io.outputs import read_anchors_csv
from railtraj.io.sbet import SBET_DTYPE, SMRMSG_DTYPE
from railtraj.io.survey import open_survey
from railtraj.io.trajectory_csv import read_trajectory_csv

pytestmark = pytest.mark.slow

UTM = "EPSG:32611"
WGS84 = "EPSG:4979"
ORIGIN = (480000.0, 3600000.0, 100.0)   # UTM 11N, about 32.5 N 117.2 W, h_ell 100 m
SIZE = 0.5   # at 0.3 the "thesis" runs match in 0-1 tile pairs and give no ties; here 9 pairs


def _utm_to_wgs84() -> pyproj.Transformer:
    return pyproj.Transformer.from_crs(pyproj.CRS(UTM).to_3d(), WGS84, always_xy=True)


def _write_sbet(run_dir: Path, traj) -> np.ndarray:
    """Replace ``run_dir/trajectory.csv`` by an SBET and SMRMSG in WGS 84; the SBET records."""
    lon, lat, h = _utm_to_wgs84().transform(*traj.xyz.T)
    convergence = pyproj.Proj(UTM).get_factors(lon, lat).meridian_convergence
    sbet = np.zeros(len(traj), dtype=SBET_DTYPE)
    sbet["time"] = traj.time
    sbet["lat"], sbet["lon"], sbet["z"] = np.radians(lat), np.radians(lon), h
    sbet["roll"], sbet["pitch"] = np.radians(traj.rpy[:, 0]), np.radians(traj.rpy[:, 1])
    sbet["heading"] = np.radians(np.mod(traj.rpy[:, 2] + convergence, 360.0))  # true heading
    sbet.tofile(run_dir / "trajectory.sbet")
    smrmsg = np.zeros(len(traj), dtype=SMRMSG_DTYPE)
    smrmsg["time"] = traj.time
    smrmsg["east_rms"], smrmsg["north_rms"], smrmsg["down_rms"] = traj.sd.T
    smrmsg["vnorth_rms"] = smrmsg["veast_rms"] = smrmsg["vdown_rms"] = 0.01
    smrmsg["roll_rms"] = smrmsg["pitch_rms"] = smrmsg["heading_rms"] = 1.0
    smrmsg.tofile(run_dir / "trajectory.smrmsg")
    (run_dir / "trajectory.csv").unlink()
    return sbet


@pytest.fixture(scope="module")
def utm_survey(tmp_path_factory) -> tuple[Path, dict]:
    """The simulated survey in UTM 11N with SBET trajectories, and its original CSV trajectories."""
    from railtraj.sim import generate
    from railtraj.sim.scenarios import get_scenario

    base = get_scenario("thesis")
    geometry = dataclasses.replace(
        base.geometry, alignment=dataclasses.replace(base.geometry.alignment, origin=ORIGIN))
    scenario = dataclasses.replace(base, crs=UTM, geometry=geometry)
    root = tmp_path_factory.mktemp("utm")
    survey = Path(generate(scenario, root, seed=3, size=SIZE).survey_dir)
    originals = {}
    for run_dir in sorted(p for p in survey.iterdir() if p.is_dir()):
        originals[run_dir.name] = read_trajectory_csv(run_dir / "trajectory.csv", run_dir.name)
        assert originals[run_dir.name].sd is not None
        _write_sbet(run_dir, originals[run_dir.name])
    return survey, originals


def test_sbet_reads_back_to_the_utm_trajectory(utm_survey):
    survey, originals = utm_survey
    opened = open_survey(survey)
    assert sorted(opened.runs) == sorted(originals)
    for run, original in originals.items():
        assert opened.run(run).trajectory_path.suffix == ".sbet"
        traj = opened.load_trajectory(run, crs=UTM, sbet_crs=WGS84)
        np.testing.assert_array_equal(traj.time, original.time)
        assert np.abs(traj.xyz - original.xyz).max() < 1e-3
        dh = np.mod(traj.rpy - original.rpy + 180.0, 360.0) - 180.0
        assert np.abs(dh).max() < 1e-8          # grid heading back; roll, pitch untouched
        np.testing.assert_allclose(traj.sd, original.sd, rtol=0, atol=1e-12)
    # the heading conversion is not a no-op here: true - grid is the convergence, about -0.1 deg
    records = np.fromfile(survey / "run_a" / "trajectory.sbet", dtype=SBET_DTYPE)
    diff = np.mod(np.degrees(records["heading"]) - originals["run_a"].rpy[:, 2] + 180, 360) - 180
    assert np.all((-0.2 < diff) & (diff < -0.05))


def test_utm_sbet_survey_runs_end_to_end(utm_survey, tmp_path):
    survey, originals = utm_survey
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "railtraj.cli", f"survey_dir={survey}", f"out_dir={out}",
           f"truth_dir={survey.parent / 'truth'}", f"crs={UTM}", f"sbet_crs={WGS84}"]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]

    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["anchors_crs"] == WGS84
    before, after = metrics["truth"]["before"], metrics["truth"]["after"]
    for run in originals:      # corrected trajectories (same epochs) closer to the truth
        corrected = read_trajectory_csv(out / "trajectories" / f"{run}.csv", run)
        np.testing.assert_array_equal(corrected.time, originals[run].time)
    assert after["overall"]["rms_3d"] < before["overall"]["rms_3d"], metrics["truth"]
    pair = "run_a~run_b"   # the runs agree with each other far better (0.31 m -> 0.02 m)
    assert after["consistency"][pair]["rms_3d"] < 0.5 * before["consistency"][pair]["rms_3d"]

    assert metrics["counts"]["anchors"] > 0
    anchors = read_anchors_csv(out / "anchors.csv")
    x, y, z = (np.asarray(anchors[k], float) for k in ("x", "y", "z"))
    lon, lat, h = _utm_to_wgs84().transform(x, y, z)
    # 1e-8 degree is 1.1 mm at most; the file has 9 decimals (0.1 mm)
    assert np.abs(np.asarray(anchors["lat"], float) - lat).max() < 1e-8
    assert np.abs(np.asarray(anchors["lon"], float) - lon).max() < 1e-8
    assert np.abs(np.asarray(anchors["h_ell"], float) - h).max() < 1e-3
    assert np.all(np.abs(lat - 32.5) < 0.1) and np.all(np.abs(lon + 117.2) < 0.1)
