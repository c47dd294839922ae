"""The synthetic tunnel survey generator: realistic multi-run surveys with ground truth.

Front door:

* :func:`generate` writes ``out_dir/survey`` (SPEC.md) and ``out_dir/truth`` for a catalogue
  scenario (:data:`CATALOGUE`) or a :class:`Scenario` of your own;
* :func:`demo_survey` returns the cached built-in demo (scenario ``mixed``);
* :func:`load_truth` reads a truth folder back; :func:`score_trajectories`, :func:`c2c` and
  :func:`evaluate` measure trajectories and clouds against it.

railtraj itself never reads the truth when correcting a survey.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

_EXPORTS = {
    "CATALOGUE": "scenarios", "DEMO": "scenarios", "Scenario": "scenarios", "get_scenario": "scenarios",
    "SimResult": "simulate", "generate": "simulate", "demo_survey": "demo", "evaluate": "evaluation",
    "c2c": "score", "score_trajectories": "score", "Truth": "truth", "load_truth": "truth",
}
__all__ = ["CATALOGUE", "DEMO", "Scenario", "SimResult", "Truth", "c2c", "demo_survey", "evaluate",
           "generate", "get_scenario", "load_truth", "score_trajectories"]

if TYPE_CHECKING:  # pragma: no cover
    from railtraj.sim.demo import demo_survey
    from railtraj.sim.evaluation import evaluate
    from railtraj.sim.scenarios import CATALOGUE, DEMO, Scenario, get_scenario
    from railtraj.sim.score import c2c, score_trajectories
    from railtraj.sim.simulate import SimResult, generate
    from railtraj.sim.truth import Truth, load_truth


def __getattr__(name: str):
    """Import on first use, so ``railtraj-sim --list`` or scoring does not load Open3D."""
    if name not in _EXPORTS:
        raise AttributeError(f"module 'railtraj.sim' has no attribute {name!r}")
    return getattr(importlib.import_module(f"railtraj.sim.{_EXPORTS[name]}"), name)
