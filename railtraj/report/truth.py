"""Errors against the simulator's truth along the chainage, for the report's truth section.

Only for simulated surveys (``truth_dir=``): the truth is never used to correct anything.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from railtraj.report.chainage import Chainage

#: at most this many epochs per run are plotted
MAX_POINTS = 3000


def errors_along_chainage(result, truth_dir: Path,
                          chainage: Chainage) -> dict[str, dict[str, np.ndarray]]:
    """Per run: chainage and horizontal / vertical error of the input and corrected trajectories."""
    from railtraj.sim import load_truth
    from railtraj.sim.score import position_error

    truth = load_truth(truth_dir)
    out = {}
    for run_id in sorted(set(truth.trajectories) & set(result.trajectories)):
        true = truth.trajectories[run_id]
        before, ok = position_error(true, result.trajectories[run_id])
        after, _ = position_error(true, result.corrected[run_id])
        s = chainage.of_trajectory(result.trajectories[run_id])[ok]
        order = np.argsort(s, kind="stable")[:: max(1, int(ok.sum()) // MAX_POINTS)]
        out[run_id] = {"chainage": s[order]}
        for name, err in (("before", before[order]), ("after", after[order])):
            out[run_id][f"{name}_h"] = np.linalg.norm(err[:, :2], axis=1)
            out[run_id][f"{name}_v"] = np.abs(err[:, 2])
    return out
