"""Write a finished pipeline's results to the out folder (SPEC.md "Output").

Every file is written atomically by :mod:`railtraj.io`; a failure part-way leaves earlier files
complete and never a half-written one.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from railtraj.control import control_residuals
from railtraj.data import Trajectory
from railtraj.errors import CRSError
from railtraj.georef import Regeoreferencer
from railtraj.io.outputs import (
    write_anchors_csv,
    write_json,
    write_offsets_csv,
    write_ties_csv,
    write_trajectory_tum,
)
from railtraj.io.trajectory_csv import write_trajectory_csv
from railtraj.pipeline import PipelineResult, qc_figures
from railtraj.qc import PairClouds, pair_clouds

log = logging.getLogger(__name__)

#: anchors are thinned to at most one per run and this many seconds
ANCHOR_INTERVAL_S = 0.5


def anchors_crs(result: PipelineResult) -> str:
    """The frame of anchors.csv's lat, lon, h_ell: the SBET's (``sbet_crs``, or its default)."""
    from railtraj.crs import default_sbet_crs

    return result.options.sbet_crs or default_sbet_crs(result.options.crs)


def anchor_rows(result: PipelineResult) -> dict[str, np.ndarray]:
    """Anchor observations: corrected positions (with posterior sd) of each run at the times
    where it was tied to another run, by a tie feature or a tile-pair offset."""
    observed = _observation_times(result)
    cols: dict[str, list] = {k: [] for k in ("run_id", "time", "x", "y", "z", "sd_x", "sd_y", "sd_z")}
    for run_id, traj in sorted(result.corrected.items()):
        times = observed.get(run_id, [])
        if not times:
            continue
        t = np.concatenate(times)
        _, first = np.unique(np.floor(t / ANCHOR_INTERVAL_S), return_index=True)
        t = np.sort(t[first])
        xyz = traj.position_at(t)
        sd = traj.sd_at(t)
        sd = np.full((len(t), 3), np.nan) if sd is None else sd
        cols["run_id"] += [run_id] * len(t)
        cols["time"].append(t)
        for k, axis in enumerate("xyz"):
            cols[axis].append(xyz[:, k])
            cols[f"sd_{axis}"].append(sd[:, k])
    out = {k: (np.asarray(v, dtype=object) if k == "run_id" else (np.concatenate(v) if v else np.zeros(0)))
           for k, v in cols.items()}
    return out


def _observation_times(result: PipelineResult) -> dict[str, list[np.ndarray]]:
    """Per run, the gps_times of its ties and of the tile-pair offsets that gave usable constraints."""
    out: dict[str, list[np.ndarray]] = {}
    for t in result.ties:
        out.setdefault(t.run_a, []).append(t.time_a)
        out.setdefault(t.run_b, []).append(t.time_b)
    for o in result.offsets:
        if o.status in ("ok", "coarse", "degenerate", "ambiguous") and np.isfinite(o.cov).all():
            for run, key in ((o.run_a, "time_a"), (o.run_b, "time_b")):
                if np.isfinite(o.info.get(key, np.nan)):
                    out.setdefault(run, []).append(np.array([o.info[key]]))
    return out


def write_outputs(result: PipelineResult, out_dir: Path, anchors: str = "auto", write_tiles: bool = False,
                  executor=None, truth_dir: Path | None = None, config: dict | None = None,
                  memory: Callable[[], dict[str, float]] | None = None) -> dict[str, Any]:
    """Write trajectories, offsets, ties, anchors, metrics.json, report.html (and tiles).

    ``memory`` (e.g. :meth:`railtraj.memory.MemoryMonitor.report`) gives the job's peak memory
    for metrics.json, measured just before it is written."""
    t0 = time.perf_counter()
    for run_id, traj in result.corrected.items():
        write_trajectory_csv(out_dir / "trajectories" / f"{run_id}.csv", traj)
        write_trajectory_tum(out_dir / "trajectories" / f"{run_id}.tum", traj)
    write_offsets_csv(out_dir / "offsets.csv", result.offsets)
    write_ties_csv(out_dir / "ties.csv", result.ties)
    notes: list[str] = list(result.notes)
    anchor_count = _write_anchors(result, out_dir, anchors, notes)
    if write_tiles:
        from railtraj.retile import write_corrected_tiles
        write_corrected_tiles(result, out_dir / "tiles", executor)
    seconds = dict(result.seconds, write=time.perf_counter() - t0)
    move = Regeoreferencer(result.trajectories, result.corrected)  # one interpolator per run, for all QC
    clouds = pair_clouds(result, move)  # once, for metrics.json's C2C figures and the report's plots
    metrics = build_metrics(result, seconds, anchor_count, notes, truth_dir, clouds, move)
    if memory is not None:
        metrics["memory"] = memory()
    if config is not None:
        metrics["config"] = {k: config.get(k) for k in ("detector", "descriptor", "matcher", "optimizer", "pipeline")}
    write_json(out_dir / "metrics.json", metrics)
    from railtraj.report.html import write_report
    write_report(out_dir / "report.html", result, metrics, truth_dir=truth_dir, clouds=clouds)
    return metrics


def _write_anchors(result: PipelineResult, out_dir: Path, mode: str, notes: list[str]) -> int:
    if mode.lower() in ("false", "no", "off"):
        return 0
    rows = anchor_rows(result)
    if len(rows["time"]) == 0:
        notes.append("anchors.csv not written: no tile pair was matched, so no anchor observations")
        return 0
    from railtraj.crs import to_geographic
    try:
        lat, lon, h = to_geographic(np.column_stack([rows["x"], rows["y"], rows["z"]]),
                                    result.options.crs, result.options.grid_dir, anchors_crs(result))
    except CRSError as exc:
        if mode.lower() in ("true", "yes", "on", "required"):
            raise
        notes.append(f"anchors.csv not written: {exc}")
        log.warning("anchors.csv not written: %s", exc)
        return 0
    rows.update(lat=lat, lon=lon, h_ell=h)
    write_anchors_csv(out_dir / "anchors.csv", rows)
    return len(lat)


def build_metrics(result: PipelineResult, seconds: dict[str, float], anchor_count: int, notes: list[str],
                  truth_dir: Path | None, clouds: list[PairClouds] | None = None,
                  move: Regeoreferencer | None = None) -> dict[str, Any]:
    """Counts, timings per stage and QC figures before and after correction."""
    statuses: dict[str, int] = {}
    stage_seconds: dict[str, float] = {}
    for pr in result.pairs:
        statuses[pr.offset.status] = statuses.get(pr.offset.status, 0) + 1
        for k, v in pr.seconds.items():
            stage_seconds[k] = stage_seconds.get(k, 0.0) + v
    metrics: dict[str, Any] = {
        "survey": str(result.survey.root),
        "pipeline": result.options.mode,
        "anchors_crs": anchors_crs(result),  # lat, lon, h_ell of anchors.csv (= the SBET frame)
        "counts": {
            "runs": len(result.survey.runs),
            "tiles": sum(len(r.tiles) for r in result.survey.runs.values()),
            "tile_pairs": len(result.pairs),
            "tile_pairs_by_status": statuses,
            # pairs whose windows fitted run a's points onto run b's, the sparser along the track
            # (railtraj.matching.resolve.REVERSE_GAP_RATIO)
            "tile_pairs_reversed": sum(bool(pr.offset.info.get("windows_reversed")) for pr in result.pairs),
            # pairs matched again about the along-track chains' prediction (railtraj.alongtrack.rematch_centres)
            "tile_pairs_rematched": sum("rematched" in pr.offset.info for pr in result.pairs),
            "ties": int(sum(len(t) for t in result.ties)),
            "anchors": anchor_count,
        },
        "seconds": {**{k: round(v, 3) for k, v in seconds.items()},
                    "per_stage_total": {k: round(v, 3) for k, v in stage_seconds.items()}},
        "qc": qc_figures(result, clouds, move),
        "adjustment": result.adjustment,
        "control": control_residuals(result.control, result.trajectories, result.corrected),
        "notes": notes,
        "resume": result.resume,
    }
    if truth_dir is not None and truth_dir.exists():
        metrics["truth"] = score_against_truth(result.trajectories, result.corrected, truth_dir, result.offsets)
    from railtraj.plugins import plugin_manager
    extra = {}
    for part in plugin_manager().hook.railtraj_metrics(result=result):
        if part:
            extra.update(part)
    if extra:
        metrics["plugins"] = extra
    return metrics


def score_against_truth(before: dict[str, Trajectory], after: dict[str, Trajectory], truth_dir: Path,
                        offsets: list | None = None) -> dict:
    """Absolute errors of the input and corrected trajectories against the simulator's truth,
    and of the ok tile-pair offsets (at their ties) against the true offsets."""
    from railtraj.sim import load_truth
    from railtraj.sim.score import score_offsets, score_trajectories

    truth = load_truth(truth_dir)
    scores = {"before": score_trajectories(truth.trajectories, before, truth.chainage),
              "after": score_trajectories(truth.trajectories, after, truth.chainage)}
    if offsets is not None:
        scores["tile_offsets"] = score_offsets(truth.trajectories, before, offsets)
    return scores
