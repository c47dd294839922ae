"""End to end: generate small surveys, read them back the way railtraj does, score them."""

from __future__ import annotations

import re

import numpy as np
import pytest

import railtraj.sim.demo as demo_mod
from railtraj.errors import InputError
from railtraj.georef import regeoreference
from railtraj.io.las import read_tile
from railtraj.io.survey import open_survey, read_control
from railtraj.sim import cli, evaluate, generate, load_truth, score_trajectories
from railtraj.sim.scenarios import CATALOGUE

SIZE = 0.15


@pytest.fixture(scope="module")
def mixed(tmp_path_factory):
    return generate("mixed", tmp_path_factory.mktemp("mixed"), seed=0, size=SIZE)


def test_survey_follows_the_spec(mixed):
    survey = open_survey(mixed.survey_dir)
    assert sorted(survey.runs) == ["run_a", "run_b", "run_c"] and survey.control_path is None
    for run_id, info in survey.runs.items():
        traj = survey.load_trajectory(run_id)
        assert traj.sd is not None and (traj.sd > 0).all()
        assert len(info.tiles) == mixed.tiles[run_id]
        total = 0
        for head in info.tiles:
            m = re.fullmatch(r"(\d+)_(\d+)\.laz", head.name)
            assert m, head.name
            e, n = int(m[1]), int(m[2])
            assert e % 25 == 0 and n % 25 == 0
            assert head.crs is not None and head.has_gps_time
            tile = read_tile(head.path, run_id)
            assert (tile.xyz[:, 0] >= e - 1e-3).all() and (tile.xyz[:, 0] <= e + 25 + 1e-3).all()
            assert (tile.xyz[:, 1] >= n - 1e-3).all() and (tile.xyz[:, 1] <= n + 25 + 1e-3).all()
            traj.check_covers(tile.gps_time, f"points of {head.name}")
            assert (np.diff(tile.gps_time) >= 0).all()
            total += len(tile)
        assert total == mixed.points[run_id]


def test_truth_folder(mixed):
    truth = load_truth(mixed.truth_dir)
    survey = open_survey(mixed.survey_dir)
    assert truth.run_ids == sorted(survey.runs)
    for run_id, true in truth.trajectories.items():
        given = survey.load_trajectory(run_id)
        np.testing.assert_array_equal(true.time, given.time)
        assert len(truth.chainage[run_id]) == len(true)
        assert true.sd is None
    assert truth.params["seed"] == 0 and truth.params["scenario"]["name"] == "mixed"
    assert truth.params["portals"] and truth.params["runs"]["run_c"]["track"] == 1


def test_truth_georeferenced_runs_agree_and_drifted_runs_do_not(mixed):
    result = evaluate(mixed.survey_dir, mixed.truth_dir, n_sample=20000)
    floor, given = result["clouds"]["truth"], result["clouds"]["input"]
    for pair, c in floor.items():
        assert c["median"] <= 0.02, pair
        assert c["overlap"] > 0.95, pair
    assert max(c["p95"] for c in given.values()) > 0.2
    assert np.median([c["median"] for c in given.values()]) > 3 * np.median([c["median"] for c in floor.values()])


def test_drift_shows_the_configured_misalignment(mixed):
    truth = load_truth(mixed.truth_dir)
    survey = open_survey(mixed.survey_dir)
    given = {r: survey.load_trajectory(r) for r in survey.runs}
    spec = CATALOGUE["mixed"].drift
    score = score_trajectories(truth.trajectories, given, truth.chainage)
    for run_id, s in score["runs"].items():
        assert spec.min_fraction * spec.max_horizontal - 0.05 <= s["max_h"] <= spec.max_horizontal + 0.05, run_id
        assert s["max_v"] <= spec.max_vertical + 0.05
    portals = truth.params["portals"]
    for run_id, true in truth.trajectories.items():                  # GNSS in the cuttings
        ch = truth.chainage[run_id]
        sky = (ch < portals[0]) | (ch > portals[-1])
        assert np.linalg.norm(given[run_id].xyz[sky] - true.xyz[sky], axis=1).max() < 0.06
    assert max(c["max_h"] for c in score["consistency"].values()) > spec.max_horizontal * spec.min_fraction
    perfect = score_trajectories(truth.trajectories, truth.trajectories, truth.chainage)
    assert perfect["overall"]["max_3d"] < 1e-9


def _contents(root):
    out = {}
    for p in sorted(root.rglob("*")):
        if p.suffix == ".laz":
            t = read_tile(p)
            out[p.relative_to(root)] = (t.xyz.tobytes(), t.gps_time.tobytes(), t.intensity.tobytes())
        elif p.is_file():
            out[p.relative_to(root)] = p.read_bytes()
    return out


def test_same_seed_same_survey(tmp_path):
    a = generate("thesis", tmp_path / "a", seed=3, size=0.1)
    b = generate("thesis", tmp_path / "b", seed=3, size=0.1)
    c = generate("thesis", tmp_path / "c", seed=4, size=0.1)
    assert _contents(a.survey_dir) == _contents(b.survey_dir)
    ta, tb = _contents(a.truth_dir), _contents(b.truth_dir)
    ta.pop(next(k for k in ta if k.name == "scenario.json"))            # holds timings
    tb.pop(next(k for k in tb if k.name == "scenario.json"))
    assert ta == tb
    traj = "run_a/trajectory.csv"
    assert (a.survey_dir / traj).read_bytes() != (c.survey_dir / traj).read_bytes()


def test_existing_output_needs_overwrite(tmp_path):
    generate("thesis", tmp_path, seed=0, size=0.1)
    with pytest.raises(InputError, match="overwrite"):
        generate("thesis", tmp_path, seed=0, size=0.1)
    again = generate("thesis", tmp_path, seed=1, size=0.1, overwrite=True)
    assert again.survey_dir.is_dir()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]   # no leftovers


def test_control_scenario_writes_control_points(tmp_path):
    res = generate("control", tmp_path, seed=0, size=0.3)
    survey = open_survey(res.survey_dir)
    cp = read_control(survey.control_path)
    truth = load_truth(res.truth_dir)
    assert len(cp) >= 3 and sorted(truth.control) == sorted(cp.ids.tolist())
    true_xyz = np.array([truth.control[i] for i in cp.ids])
    assert (np.abs(cp.xyz - true_xyz) < 5 * cp.sd + 1e-3).all()
    # the targets are in the clouds: bright points right at the true control positions
    bright = []
    for run_id, info in survey.runs.items():
        given = survey.load_trajectory(run_id)
        for h in info.tiles:
            tile = regeoreference(read_tile(h.path, run_id), given, truth.trajectories[run_id])
            bright.append(tile.xyz[tile.intensity > 50000])
    bright = np.concatenate(bright)
    nearest = [np.linalg.norm(bright - p, axis=1).min() for p in true_xyz]
    assert max(nearest) < 0.1


def test_portal_trap_has_a_bias_the_sd_does_not_show(tmp_path):
    res = generate("portal_trap", tmp_path, seed=0, size=0.3)
    truth = load_truth(res.truth_dir)
    survey = open_survey(res.survey_dir)
    given = survey.load_trajectory("run_a")
    info = truth.params["runs"]["run_a"]["drift"]["multipath"]
    k = np.argmin(np.abs(truth.chainage["run_a"] - info["portal_chainage"]))
    err = given.xyz[k] - truth.trajectories["run_a"].xyz[k]
    np.testing.assert_allclose(err, info["bias"], atol=0.05)
    assert given.sd[k].max() < 0.05


def test_cli(tmp_path, capsys):
    assert cli.main(["--list"]) == 0
    assert "mixed (demo)" in capsys.readouterr().out
    assert cli.main(["feature_poor", str(tmp_path), "--size", "0.1", "--seed", "2"]) == 0
    out = capsys.readouterr().out
    assert "run_a" in out and "survey:" in out and "done in" in out
    assert cli.main(["feature_poor", str(tmp_path), "--size", "0.1"]) == 1
    assert "overwrite" in capsys.readouterr().err
    assert cli.main(["nope", str(tmp_path / "x")]) == 1
    assert cli.main([]) == 2


def test_demo_survey_is_generated_once_and_atomically(tmp_path, monkeypatch):
    calls = []

    def small(scenario, out_dir, seed=0):
        calls.append(out_dir)
        return generate(scenario, out_dir, seed=seed, size=0.1)

    monkeypatch.setattr(demo_mod, "generate", small)
    (tmp_path / f".demo-{demo_mod.demo_key()}.half").mkdir()            # a killed earlier attempt
    path = demo_mod.demo_survey(tmp_path)
    assert path == demo_mod.demo_dir(tmp_path) / "survey" and len(calls) == 1
    assert len(open_survey(path).runs) == 3 and (path.parent / "truth" / "scenario.json").is_file()
    assert demo_mod.demo_survey(tmp_path) == path and len(calls) == 1
    assert re.fullmatch(r"demo-[\d.]+-[0-9a-f]{12}", path.parent.name)
