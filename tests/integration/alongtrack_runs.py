"""What the along-track end-to-end tests share: running railtraj on a simulated survey with its
truth, and the checks every corrected survey must pass."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path


def _run(survey: Path, out: Path, *overrides: str) -> dict:
    env = dict(os.environ, RAILTRAJ_DISABLE_PLUGIN_AUTOLOAD="1")
    proc = subprocess.run([sys.executable, "-m", "railtraj.cli", f"survey_dir={survey}", f"out_dir={out}",
                           f"truth_dir={survey.parent / 'truth'}", "anchors=false", "crs=EPSG:7405",
                           "executor=process", *overrides],
                          capture_output=True, text=True, env=env, timeout=1200)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads((out / "metrics.json").read_text())


def _pair(metrics: dict, when: str) -> dict:
    return next(iter(metrics["truth"][when]["consistency"].values()))


def _tenfold_closer(metrics: dict, before_at_least: float) -> None:
    """The two runs, at least ``before_at_least`` m apart (RMS) before, are ten times closer
    after, RMS and max, no worse in height, with five tile pairs or more fixed along the track."""
    before, after = _pair(metrics, "before"), _pair(metrics, "after")
    assert before["rms_h"] > before_at_least
    assert after["rms_h"] < 0.1 * before["rms_h"] and after["max_h"] < 0.1 * before["max_h"], (before, after)
    assert after["rms_v"] <= before["rms_v"]
    fixed = [r for r in metrics["adjustment"]["alongtrack"] if r["status"] in ("ok", "coarse")]
    assert len(fixed) >= 5
