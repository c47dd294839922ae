"""Evaluating a survey folder against its truth: trajectories and clouds, before and after.

:func:`evaluate` answers the questions a benchmark asks of a correction: how far are the input
and corrected trajectories from the truth, and how well do the runs' clouds agree as delivered,
after correction, and at best (re-georeferenced with the true trajectories: the floor set by
scanner noise alone).
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Sequence

import numpy as np

from railtraj.data import PointTile, Trajectory
from railtraj.georef import regeoreference
from railtraj.io.las import read_tile
from railtraj.io.survey import open_survey
from railtraj.sim.score import c2c, score_trajectories
from railtraj.sim.truth import load_truth


def load_run_cloud(survey_dir: str | os.PathLike, run_id: str,
                   tiles: Sequence[str] | None = None) -> PointTile:
    """All points of one run (optionally only the tiles named in ``tiles``) as one PointTile."""
    info = open_survey(survey_dir).run(run_id)
    parts = [read_tile(h.path, run_id) for h in info.tiles if tiles is None or h.name in tiles]
    if not parts:
        return PointTile(np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.uint16), run_id, "")
    return PointTile(np.concatenate([p.xyz for p in parts]), np.concatenate([p.gps_time for p in parts]),
                     np.concatenate([p.intensity for p in parts]), run_id, "merged")


def cloud_consistency(clouds: dict[str, np.ndarray], max_dist: float = 1.0,
                      n_sample: int = 50_000) -> dict:
    """:func:`c2c` from each run's cloud to each later run's (``"a->b"``, a before b by name);
    the other direction measures the same misalignment and costs another k-d tree."""
    out = {}
    for a, b in itertools.combinations(sorted(clouds), 2):
        out[f"{a}->{b}"] = c2c(clouds[a], clouds[b], max_dist=max_dist, n_sample=n_sample)
    return out


def evaluate(survey_dir: str | os.PathLike, truth_dir: str | os.PathLike,
             corrected: dict[str, Trajectory] | None = None, tiles: Sequence[str] | None = None,
             max_dist: float = 1.0, n_sample: int = 50_000) -> dict:
    """Trajectory scores and cloud consistency for the input survey, the truth floor and,
    if given, the corrected trajectories. ``tiles`` limits the clouds to those tile names."""
    survey = open_survey(survey_dir)
    truth = load_truth(truth_dir)
    given = {r: survey.load_trajectory(r) for r in survey.runs}
    raw = {r: load_run_cloud(survey_dir, r, tiles) for r in survey.runs}
    result = {"trajectories": {"input": score_trajectories(truth.trajectories, given, truth.chainage)},
              "clouds": {"input": cloud_consistency({r: t.xyz for r, t in raw.items()}, max_dist, n_sample)}}
    variants = {"truth": truth.trajectories}
    if corrected is not None:
        result["trajectories"]["corrected"] = score_trajectories(truth.trajectories, corrected,
                                                                 truth.chainage)
        variants["corrected"] = corrected
    for name, trajs in variants.items():
        moved = {r: regeoreference(t, given[r], trajs[r]).xyz for r, t in raw.items() if r in trajs}
        result["clouds"][name] = cloud_consistency(moved, max_dist, n_sample)
    return result
