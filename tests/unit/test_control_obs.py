"""Control points picked by hand (control_obs.csv): times, checks, residuals."""

from __future__ import annotations

import numpy as np
import pytest

from railtraj.control import abreast_time, control_residuals, observe_control
from railtraj.errors import RailtrajError
from railtraj.io.survey import Survey


def _survey(tmp_path, rows: list[str], obs_rows: list[str] | None) -> Survey:
    (tmp_path / "control.csv").write_text("id,x,y,z,sd_x,sd_y,sd_z\n" + "\n".join(rows) + "\n")
    if obs_rows is not None:
        (tmp_path / "control_obs.csv").write_text("id,run_id,x,y,z\n" + "\n".join(obs_rows) + "\n")
    return Survey(tmp_path, {}, control_path=tmp_path / "control.csv")


def test_abreast_time_is_when_the_point_lies_across_the_track(make_trajectory):
    traj = make_trajectory(n=2000, heading_deg=30.0, speed=10.0)
    t_true = traj.time[1234] + 0.0037
    pos = traj.interpolate(np.array([t_true]))[0][0]
    left = np.array([-np.cos(np.radians(30.0)), np.sin(np.radians(30.0)), 0.0])  # across the track
    assert abreast_time(traj, pos + 2.5 * left + [0, 0, 1.5])[0] == pytest.approx(t_true, abs=0.002)


def test_picked_observations_carry_time_and_surveyed_coordinates(tmp_path, make_trajectory):
    traj = make_trajectory(n=2000, run_id="run_a")
    seen = traj.interpolate(np.array([traj.time[500]]))[0][0] + [0.5, -0.3, 1.2]
    surveyed = ",".join(f"{v:.3f}" for v in seen + [0.2, 0.1, 0.0])
    picked = ",".join(f"{v:.3f}" for v in seen)
    survey = _survey(tmp_path, [f"CP1,{surveyed},0.003,0.003,0.004"], [f"CP1,run_a,{picked}"])
    obs, notes = observe_control(survey, {"run_a": traj})
    assert len(obs) == 1 and not notes and obs.source[0] == "picked"
    np.testing.assert_allclose(obs.xyz[0] - obs.seen[0], [0.2, 0.1, 0.0], atol=1e-6)
    assert abs(obs.time[0] - traj.time[500]) < 0.1
    res = control_residuals(obs, {"run_a": traj}, {"run_a": traj})
    assert res[0]["before_m"] == res[0]["after_m"] and res[0]["horizontal_before"] == pytest.approx(0.2236, abs=1e-3)
    moved = traj.with_positions(traj.xyz + [0.2, 0.1, 0.0])
    assert control_residuals(obs, {"run_a": traj}, {"run_a": moved})[0]["horizontal_after"] < 1e-3


@pytest.mark.parametrize("row, message", [
    ("CP9,run_a,1,2,3", "id CP9 is not in control.csv"),
    ("CP1,run_z,1,2,3", "run run_z is not a run"),
    ("CP1,run_a,one,2,3", "control observations file"),
])
def test_bad_control_obs_rows_are_refused_with_the_fix(tmp_path, make_trajectory, row, message):
    survey = _survey(tmp_path, ["CP1,530000,180000,20,0.003,0.003,0.004"], [row])
    with pytest.raises(RailtrajError, match=message):
        observe_control(survey, {"run_a": make_trajectory(run_id="run_a")})


def test_no_control_csv_gives_no_observations(tmp_path, make_trajectory):
    obs, notes = observe_control(Survey(tmp_path, {}), {"a": make_trajectory()})
    assert len(obs) == 0 and notes == []


def _wall_with_target(tmp_path, traj, spacing: float, phase: float) -> tuple[Survey, np.ndarray]:
    """A side wall 2.5 m right of a run heading north, scanned in rows of points ``spacing``
    apart up the wall (a profile every 4.5 cm along it), with a bright 0.2 m target centred
    ``phase`` m above a row: the survey folder, and the target's centre."""
    from railtraj.data import PointTile
    from railtraj.io.las import read_header, write_tile
    from railtraj.io.survey import RunInfo

    y0 = traj.xyz[0, 1]
    yy, zz = np.meshgrid(np.arange(90.0, 110.0, 0.045), np.arange(0.5, 3.0, spacing), indexing="ij")
    x = np.full(yy.size, traj.xyz[0, 0] + 2.5)
    xyz = np.column_stack([x, y0 + yy.ravel(), traj.xyz[0, 2] + zz.ravel()])
    centre = np.array([x[0], y0 + 100.0, traj.xyz[0, 2] + 0.5 + 6 * spacing + phase])
    on_target = (np.abs(xyz[:, 1] - centre[1]) <= 0.1) & (np.abs(xyz[:, 2] - centre[2]) <= 0.1)
    times = traj.time[0] + yy.ravel() / 10.0  # abreast of each point at 10 m/s
    order = np.argsort(times)
    tile = PointTile(xyz[order], times[order], np.where(on_target, 20_000, 1_000)[order].astype(np.uint16), "run_a")
    folder = tmp_path / "run_a"
    folder.mkdir(parents=True)
    write_tile(folder / "wall.laz", tile)
    (tmp_path / "control.csv").write_text("id,x,y,z,sd_x,sd_y,sd_z\nCP1," + ",".join(f"{v:.4f}" for v in centre)
                                          + ",0.003,0.003,0.004\n")
    run = RunInfo("run_a", folder, folder / "trajectory.csv", [read_header(folder / "wall.laz")])
    return Survey(tmp_path, {"run_a": run}, control_path=tmp_path / "control.csv"), centre


@pytest.mark.parametrize("spacing", [0.04, 0.18])
def test_a_located_targets_height_is_claimed_to_the_spacing_of_its_rows(tmp_path, make_trajectory, spacing):
    """A 0.2 m target on a wall scanned in rows 0.18 m apart is one row of points, anywhere within
    9 cm of its centre: its height is off by that much, not the 2 cm a dense scan gives. Given the
    scan's point spacing, the located height claims ``spacing / sqrt(12)`` at least and stays
    within 2 sd of the truth; without it, it claims 2 cm and is up to 3.8 sd off. At 0.04 m the
    2 cm stays."""
    traj = make_trajectory(n=3000, run_id="run_a", heading_deg=0.0, sd=False)
    worst = {}
    for k, phase in enumerate(np.array([-0.075, -0.04, 0.0, 0.035, 0.075]) * spacing / 0.18):
        survey, centre = _wall_with_target(tmp_path / str(k), traj, spacing, phase)
        for given in (float("nan"), spacing):
            obs, notes = observe_control(survey, {"run_a": traj}, point_spacing=given)
            assert len(obs) == 1 and not notes, notes
            z = abs(obs.seen[0, 2] - centre[2]) / obs.pick_sd[0, 2]
            worst[np.isfinite(given)] = max(worst.get(np.isfinite(given), 0.0), z)
            if np.isfinite(given):
                assert obs.pick_sd[0, 2] == pytest.approx(max(0.02, spacing / np.sqrt(12)))
    assert worst[True] <= 2.0, worst
    assert (worst[False] > 3.0) == (spacing > 0.1), worst
