"""End to end on surveys whose repeated structure aliases along the track, against the truth.

``commensurate``: ribs every 1.5 m and sleepers every 0.6 m repeat together every 3.0 m, so only
niches and boxes 20-40 m apart tell the aliases apart (in 25 m and in 50 m tiles). The corrected
runs must agree better than the input and no ``ok`` offset may sit on an alias (none more than
5 cm off). The demo's tunnel with these ribs and sleepers is in
test_alongtrack_featureless_e2e.py, the plain and ring-jointed tubes in
test_alongtrack_tubes_e2e.py, control in test_alongtrack_control_e2e.py (one module each, so
that the test runners on several cores take them in parallel).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
from alongtrack_runs import _pair, _run

from railtraj.sim import generate
from railtraj.sim.scenarios import get_scenario

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def commensurate(tmp_path_factory) -> Path:
    """At 0.7 size (210 m of ribbed tunnel): 0.94 / 1.58 -> 0.014 / 0.033 m searched within 1 m
    then 2.5 m (:func:`commensurate_out`; 0.015 / 0.046 m with the default window), 12 ok pairs,
    the worst 1.5 cm off; generated and corrected in 136 s on one core."""
    return generate("commensurate", tmp_path_factory.mktemp("commensurate"), seed=1, size=0.7).survey_dir


@pytest.fixture(scope="module")
def commensurate_out(commensurate, tmp_path_factory) -> dict:
    """The run on it whose matcher searched within 1 m (``matcher.max_misalignment=1.0``): its
    tile pairs are matched as with the default window where the runs are less than 1 m apart,
    and again within 2.5 m where they are further apart. Its metrics.json. (One run for both
    tests below: a default run besides took 112 s of a CI worker; the default window is run
    end to end on the commensurate ribs and sleepers in test_alongtrack_featureless_e2e.py.)"""
    out = tmp_path_factory.mktemp("commensurate_out") / "out"
    return _run(commensurate, out, "matcher.max_misalignment=1.0", "pipeline.max_misalignment_m=1.0")


def test_commensurate_tunnel_is_corrected_without_accepting_an_alias(commensurate_out):
    metrics = commensurate_out
    before, after = _pair(metrics, "before"), _pair(metrics, "after")
    assert before["rms_h"] > 0.3
    assert after["rms_h"] < 0.25 * before["rms_h"] and after["max_h"] < before["max_h"]
    assert after["rms_v"] <= before["rms_v"]
    score = metrics["truth"]["tile_offsets"]
    assert score["ok_pairs"] >= 5
    assert max(score["max_abs_m"]) <= 0.05, score  # no ok pair on a 0.6, 1.5 or 3.0 m alias
    resolved = metrics["adjustment"]["alongtrack"]
    assert resolved and all(r["status"] in ("ok", "coarse", "ambiguous", "degenerate") for r in resolved)
    absolute_before = metrics["truth"]["before"]["overall"]["rms_h"]
    assert metrics["truth"]["after"]["overall"]["rms_h"] < absolute_before
    assert not [n for n in metrics["notes"] if "the scan is sparse" in n]  # 420 points per profile
    assert {r["portals"] for r in metrics["adjustment"]["portal"]["runs"].values()} == {2}  # into the tunnel, out


def test_runs_further_apart_than_the_matcher_searched_are_matched_again_further_out(commensurate_out):
    """The runs drift up to 1.6 m apart; searched within 1 m, the pairs where they are further
    apart can only be matched on an alias inside the window. The chains put the runs 1.44 +- 0.09 m
    apart there, so that run pair's tile pairs are matched again within 2.5 m, and the survey is
    corrected as with the default window: 0.94 / 1.58 -> 0.014 / 0.033 m. Without it
    (``pipeline.max_widened_m=0``, before session 41) a note asked the user to run again."""
    metrics = commensurate_out
    widened = [n for n in metrics["notes"] if "were matched again within" in n]
    assert len(widened) == 1 and "beyond the 1 m the matcher searched" in widened[0], metrics["notes"]
    assert not [n for n in metrics["notes"] if "run again with" in n]
    before, after = _pair(metrics, "before"), _pair(metrics, "after")
    assert before["max_h"] > 1.2  # the runs were further apart than the 1 m searched
    assert after["rms_h"] < 0.1 * before["rms_h"] and after["max_h"] < 0.1 * before["max_h"], (before, after)
    score = metrics["truth"]["tile_offsets"]
    assert score["ok_pairs"] >= 5 and max(score["max_abs_m"]) <= 0.05, score
    assert "widened" in metrics["seconds"]


def test_a_tube_in_50_m_tiles_is_matched_in_parts_detected_in_squares_and_corrected(tmp_path):
    """Tiles may have any size (SPEC). Matched whole, 50 m tiles gave pairs 50 m apart whose
    curves could not follow the drift (commensurate: 1.44 -> 1.41 m); matched in 25 m parts
    (``pipeline.pair_part_m``) they were corrected like 25 m tiles (0.013 / 0.040 m), but for a
    featureless tube. There the only keypoints are where a tile's edge cuts the lining (in every
    run at the same place: they give the offset across and up), and a 50 m tile's middle has
    none: its parts were refused or left to the chain, 0.84 / 1.26 m, one ``coarse`` pair 1.26 m
    off. Detected in the squares of the 25 m grid (:func:`railtraj.io.survey.grid_cells`):
    0.086 / 0.243 m, the worst resolved pair 3 cm off. At 0.4 size (a 120 m tube) about a minute."""
    scn = replace(get_scenario("tube"), tile_size=50.0)
    survey = generate(scn, tmp_path / "survey", seed=5124, size=0.4).survey_dir
    metrics = _run(survey, tmp_path / "out")
    before, after = _pair(metrics, "before"), _pair(metrics, "after")
    assert after["rms_h"] < 0.1 * before["rms_h"] and after["max_h"] < 0.15 * before["max_h"], (before, after)
    score = metrics["truth"]["tile_offsets"]
    assert score["ok_pairs"] == 0 or max(score["max_abs_m"]) <= 0.05, score


def test_a_sparse_scan_is_corrected_and_told_it_is_sparse(tmp_path):
    """At 71 points per profile (0.16 m apart along each, median) the walls are rows of points
    and the two runs' rows interleave. Counted by the distance to run a's points, a pair's
    fitness at the right offset was below half and none of 11 pairs was aligned along the
    track: 0.78 / 1.36 -> 0.48 / 0.93 m. Counted on run a's planes
    (railtraj.matching.target.PlaneTarget.fits), 7 are aligned: 0.028 / 0.058 m. The run still
    says the scan is sparse (railtraj.matching.spacing.sparse_profiles_note). At 0.5 size (a
    150 m tunnel) 30 s."""
    scn = get_scenario("commensurate")
    scn = replace(scn, scanner=replace(scn.scanner, points_per_profile=100))  # x sqrt(0.5): 71
    survey = generate(scn, tmp_path / "survey", seed=5, size=0.5).survey_dir
    metrics = _run(survey, tmp_path / "out")
    notes = [n for n in metrics["notes"] if "the scan is sparse" in n]
    assert len(notes) == 1 and "apart along each profile" in notes[0], metrics["notes"]
    before, after = _pair(metrics, "before"), _pair(metrics, "after")
    assert after["rms_h"] < 0.1 * before["rms_h"] and after["max_h"] < 0.1 * before["max_h"], (before, after)
    score = metrics["truth"]["tile_offsets"]
    assert score.get("ok_pairs", 0) == 0 or max(score["max_abs_m"]) <= 0.05, score
