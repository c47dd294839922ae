"""Reading back the truth folder a simulation wrote (for scoring, tests and benchmarks)."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from railtraj.data import Trajectory
from railtraj.errors import InputError
from railtraj.io.survey import read_control
from railtraj.io.trajectory_csv import read_numeric_columns, read_trajectory_csv


@dataclass(frozen=True)
class Truth:
    """True trajectories and chainage per run, true control positions, scenario parameters."""

    trajectories: dict[str, Trajectory]
    chainage: dict[str, np.ndarray]
    params: dict
    control: dict[str, np.ndarray]

    @property
    def run_ids(self) -> list[str]:
        return sorted(self.trajectories)


def load_truth(truth_dir: str | os.PathLike) -> Truth:
    """Load a truth folder written by :func:`railtraj.sim.generate`."""
    root = Path(truth_dir)
    params_path = root / "scenario.json"
    if not params_path.is_file():
        raise InputError(f"{root} is not a simulation truth folder (no scenario.json): pass the "
                         "'truth' folder next to the generated 'survey'")
    params = json.loads(params_path.read_text(encoding="utf-8"))
    trajectories, chainage = {}, {}
    for path in sorted((root / "trajectories").glob("*.csv")):
        run_id = path.stem
        trajectories[run_id] = read_trajectory_csv(path, run_id)
        chainage[run_id] = read_numeric_columns(root / "chainage" / f"{run_id}.csv",
                                                ("time", "chainage"), what="chainage file")["chainage"]
    control = {}
    if (root / "control.csv").is_file():
        cp = read_control(root / "control.csv")
        control = {str(i): p for i, p in zip(cp.ids, cp.xyz, strict=True)}
    return Truth(trajectories, chainage, params, control)
