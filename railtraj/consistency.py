"""Checks that a survey's pieces belong together before any heavy work.

Two mistakes that otherwise produce silent nonsense: tiles in another CRS than the survey's, and
a trajectory in other coordinates (or of another run) than its tiles.
"""

from __future__ import annotations

import numpy as np
import pyproj

from railtraj.crs import survey_crs
from railtraj.data import Trajectory
from railtraj.errors import CRSError, SurveyError
from railtraj.io.survey import Survey

#: how far (m) a run's tiles may lie outside its trajectory's bounding box (scanner range)
MAX_TILE_DISTANCE_M = 200.0


def _horizontal(crs: pyproj.CRS) -> pyproj.CRS:
    return crs.sub_crs_list[0] if crs.is_compound else crs


def check_survey(survey: Survey, trajectories: dict[str, Trajectory], crs: str) -> None:
    """Raise a one-line error if a tile's CRS differs from ``crs`` or a run's tiles lie away from
    its trajectory."""
    want = _horizontal(survey_crs(crs))
    for run_id, run in sorted(survey.runs.items()):
        for header in run.tiles:
            if header.crs is not None and not _horizontal(header.crs).equals(want, ignore_axis_order=True):
                raise CRSError(f"tile {header.path} is in {_horizontal(header.crs).name!r} but the survey CRS is "
                               f"{want.name!r}; reproject the tiles or set crs=<their CRS>")
        lo = trajectories[run_id].xyz.min(axis=0)[:2] - MAX_TILE_DISTANCE_M
        hi = trajectories[run_id].xyz.max(axis=0)[:2] + MAX_TILE_DISTANCE_M
        for header in run.tiles:
            if (np.asarray(header.maxs)[:2] < lo).any() or (np.asarray(header.mins)[:2] > hi).any():
                raise SurveyError(
                    f"tile {header.path} lies more than {MAX_TILE_DISTANCE_M:.0f} m from run {run_id!r}'s trajectory "
                    f"(trajectory x {lo[0] + MAX_TILE_DISTANCE_M:.1f}.., tile x {header.mins[0]:.1f}..); "
                    "trajectory and tiles must be in the same CRS and belong to the same run")
