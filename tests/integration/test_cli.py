"""End to end: the `railtraj` command on small simulated surveys (bad input: test_bad_inputs.py)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from evo.tools.file_interface import read_tum_trajectory_file

from railtraj.io.outputs import write_trajectory_tum
from railtraj.io.trajectory_csv import read_trajectory_csv

pytestmark = pytest.mark.slow


def railtraj(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "railtraj.cli", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=900, env=dict(os.environ, **(env or {})))


@pytest.fixture(scope="module")
def survey(tmp_path_factory) -> Path:
    from railtraj.sim import generate

    root = tmp_path_factory.mktemp("sim")
    res = generate("thesis", root, seed=3, size=0.3)
    return Path(res.survey_dir)


def test_job_writes_every_spec_output(survey, tmp_path, evo_ape):
    out = tmp_path / "out"
    truth_dir = survey.parent / "truth"
    res = railtraj(f"survey_dir={survey}", f"out_dir={out}", f"truth_dir={truth_dir}")
    assert res.returncode == 0, res.stderr[-3000:]
    runs = sorted(p.name for p in survey.iterdir() if p.is_dir())
    for run in runs:
        corrected = read_trajectory_csv(out / "trajectories" / f"{run}.csv", run)
        original = read_trajectory_csv(survey / run / "trajectory.csv", run)
        np.testing.assert_array_equal(corrected.time, original.time)   # same epochs
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["counts"]["runs"] == len(runs)
    assert metrics["counts"]["tile_pairs"] > 0
    assert "truth" in metrics and "c2c_before_m" in metrics["qc"]
    memory = metrics["memory"]  # peak resident memory, GiB; no limit by default
    assert memory["peak_self_gb"] > 0.05 and memory["peak_sampled_gb"] > 0.05 and memory["max_memory_gb"] == 0
    header = (out / "offsets.csv").read_text().splitlines()[0]
    assert header == "run_a,run_b,tile_a,tile_b,dx,dy,dz,sd_x,sd_y,sd_z,inliers,status"
    assert (out / "ties.csv").read_text().startswith("run_a,run_b,time_a,time_b,xa,ya,za,xb,yb,zb,weight")
    assert (out / "config.yaml").exists() and (out / "report.html").stat().st_size > 1000
    # anchors with the packaged OS grids; the simulated survey lies in London (E 530000 N 180000)
    from railtraj.io.outputs import read_anchors_csv

    assert metrics["counts"]["anchors"] > 0
    assert metrics["anchors_crs"] == "EPSG:4937"   # British survey: anchors in ETRS89, as before
    assert (out / "anchors.csv").read_text().startswith("run_id,time,x,y,z,lat,lon,h_ell,sd_x,sd_y,sd_z")
    anchors = read_anchors_csv(out / "anchors.csv")
    assert np.all(np.abs(np.asarray(anchors["lat"], float) - 51.5) < 0.1)
    assert np.all(np.abs(np.asarray(anchors["lon"], float) + 0.13) < 0.1)
    h_minus_height = np.asarray(anchors["h_ell"], float) - np.asarray(anchors["z"], float)
    assert np.all((44 < h_minus_height) & (h_minus_height < 48))   # OSGM15 geoid in London
    for run in runs:   # evo-compatible trajectories next to the CSV, one line per epoch ...
        tum = out / "trajectories" / f"{run}.tum"
        csv = read_trajectory_csv(out / "trajectories" / f"{run}.csv", run)
        np.testing.assert_allclose(read_tum_trajectory_file(str(tum)).positions_xyz, csv.xyz, rtol=0, atol=1e-6)
        # ... and evo's APE against the simulator's truth is metrics.json's
        write_trajectory_tum(tmp_path / f"truth_{run}.tum", read_trajectory_csv(
            truth_dir / "trajectories" / f"{run}.csv", run))
        rmse, worst, n = evo_ape(tmp_path / f"truth_{run}.tum", tum)
        ours = metrics["truth"]["after"]["runs"][run]
        assert n == ours["n"]
        assert abs(rmse - ours["rms_3d"]) < 1e-3 and abs(worst - ours["max_3d"]) < 1e-3
    assert not list(out.rglob("*.part")), "temporary files left behind"


def test_example_plugin_runs_end_to_end(survey, tmp_path):
    out = tmp_path / "plug"
    res = railtraj(f"survey_dir={survey}", f"out_dir={out}", "detector=voxel_corner", "pipeline=local",
                   "pipeline.max_pairs=1", "anchors=false")
    assert res.returncode == 0, res.stderr[-3000:]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["config"]["detector"]["name"] == "voxel_corner"
    assert metrics["counts"]["tile_pairs"] == 1


def test_comparative_sweep_runs_all_four_combinations(survey, tmp_path):
    out = tmp_path / "sweep"
    res = railtraj("-m", "detector=iss,harris3d", "descriptor=none,fpfh", "pipeline=local", "pipeline.max_pairs=1",
                   "matcher=pair_voting", "anchors=false", f"survey_dir={survey}", f"out_dir={out}")
    assert res.returncode == 0, res.stderr[-3000:]
    jobs = sorted(p.parent.name for p in out.glob("*/metrics.json"))   # named by the overrides
    combos = {(m.group(1), m.group(2)) for m in (re.search(r"descriptor=(\w+),detector=(\w+)", j) for j in jobs)}
    assert combos == {("fpfh", "harris3d"), ("fpfh", "iss"), ("none", "harris3d"), ("none", "iss")}
    for job in jobs:
        m = json.loads((out / job / "metrics.json").read_text())
        assert f"detector={m['config']['detector']['name']}" in job
        assert m["counts"]["tile_pairs"] == 1






def test_write_tiles_regeoreferences_every_tile(survey, tmp_path):
    from railtraj.io.las import read_tile

    out = tmp_path / "tiles"
    res = railtraj(f"survey_dir={survey}", f"out_dir={out}", "write_tiles=true", "optimizer=identity",
                   "pipeline.max_pairs=1", "anchors=false")
    assert res.returncode == 0, res.stderr[-3000:]
    for run in sorted(p for p in survey.iterdir() if p.is_dir()):
        inputs = sorted((run / "tiles").glob("*.la[sz]"))
        written = sorted((out / "tiles" / run.name).glob("*.laz"))
        assert [p.stem for p in written] == [p.stem for p in inputs]
        a, b = read_tile(inputs[0]), read_tile(written[0])      # identity: the same cloud back
        np.testing.assert_array_equal(a.gps_time, b.gps_time)
        assert np.abs(a.xyz - b.xyz).max() <= 0.0011


def test_help_lists_every_registered_stage_and_the_defaults():
    """``railtraj --help`` answers without composing through Hydra: it must still name every
    stage the registry holds (third-party plugins included) and mark the defaults."""
    from railtraj.plugins import registry

    out = railtraj("--help")
    assert out.returncode == 0, out.stderr
    lines = {line.split()[0]: line for line in out.stdout.splitlines() if line.startswith("  ") and line.split()}
    for spec in registry().specs():
        assert re.search(rf"[\s,\[]{re.escape(spec.name)}[\],]|[\s,\[]{re.escape(spec.name)}$", lines[spec.kind]), spec
    assert "[iss]" in lines["detector"] and "[spline]" in lines["optimizer"] and "[global]" in lines["pipeline"]
    assert "survey_dir" in lines and "max_memory_gb" in lines
