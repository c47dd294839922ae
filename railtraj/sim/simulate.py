"""Generating a survey: scene -> runs -> drift -> scan -> georeference -> files (:func:`generate`).

The scanner measures in the body frame with the TRUE pose; the points are written georeferenced
with the DRIFTED pose (``world = drifted(t) * body``), exactly as a real system would produce
them from a drifting GNSS/INS solution. Everything is written into a hidden folder inside
``out_dir`` and renamed into ``survey/`` and ``truth/`` only once complete.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
import time
import zlib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyproj

from railtraj import __version__
from railtraj.errors import InputError
from railtraj.georef import PoseInterpolator
from railtraj.sim import writer
from railtraj.sim.drift import drift
from railtraj.sim.geometry import Scene, build_scene
from railtraj.sim.runs import drive
from railtraj.sim.scanner import scan
from railtraj.sim.scenarios import Scenario, get_scenario

log = logging.getLogger(__name__)
CONTROL_SD = (0.003, 0.003, 0.004)   #: 1-sigma of the surveyed control coordinates, metres


@dataclass(frozen=True)
class SimResult:
    """Where a simulation was written, and what it cost."""

    survey_dir: Path
    truth_dir: Path
    scenario: str
    seed: int
    size: float
    timings: dict[str, float] = field(default_factory=dict)
    points: dict[str, int] = field(default_factory=dict)
    tiles: dict[str, int] = field(default_factory=dict)
    drift: dict[str, dict] = field(default_factory=dict)

    def summary(self) -> list[str]:
        """Human-readable lines for the command line."""
        lines = [f"scenario {self.scenario} (seed {self.seed}, size {self.size:g})",
                 f"survey: {self.survey_dir}", f"truth:  {self.truth_dir}"]
        for run, n in self.points.items():
            d = self.drift.get(run, {})
            lines.append(f"  {run}: {n:,} points in {self.tiles[run]} tiles; max drift "
                         f"{d.get('max_error_horizontal', 0):.2f} m horizontal, "
                         f"{d.get('max_error_vertical', 0):.2f} m vertical")
        lines.append("time: " + ", ".join(f"{k} {v:.1f} s" for k, v in self.timings.items()))
        return lines


def generate(scenario: str | Scenario, out_dir: str | os.PathLike, seed: int = 0, size: float = 1.0,
             overwrite: bool = False, progress: Callable[[str], None] | None = None) -> SimResult:
    """Simulate ``scenario`` and write ``out_dir/survey`` (SPEC.md) and ``out_dir/truth``.

    The same scenario, seed and size give identical files. An existing ``survey`` or ``truth``
    in ``out_dir`` is an error unless ``overwrite`` is set.
    """
    scn = get_scenario(scenario, size)
    out = Path(out_dir)
    targets = {"survey": out / "survey", "truth": out / "truth"}
    existing = [str(p) for p in targets.values() if p.exists()]
    if existing and not overwrite:
        raise InputError(f"{', '.join(existing)} already exist(s): choose an empty out_dir or "
                         "pass overwrite=True (--overwrite)")
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    tmp = Path(tempfile.mkdtemp(prefix=".railtraj-sim-", dir=out))
    try:
        result = _simulate(scn, tmp / "survey", tmp / "truth", seed, progress or (lambda _m: None))
        for name, target in targets.items():
            if target.exists():
                shutil.rmtree(target)
            os.replace(tmp / name, target)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    timings = {**result.timings, "total": time.perf_counter() - start}
    log.info("scenario %s written to %s in %.1f s", scn.name, out, timings["total"])
    return SimResult(targets["survey"], targets["truth"], result.scenario, seed, scn.size,
                     timings, result.points, result.tiles, result.drift)


def _simulate(scn: Scenario, survey: Path, truth: Path, seed: int,
              say: Callable[[str], None]) -> SimResult:
    """Do the work of :func:`generate` into ``survey`` and ``truth``."""
    timings: dict[str, float] = {}
    t = time.perf_counter()
    scene = build_scene(scn.geometry)
    timings["scene"] = time.perf_counter() - t
    say(f"scene: {len(scene.triangles):,} triangles, {scene.centreline.length:.0f} m, "
        f"portals at {', '.join(f'{p:.0f}' for p in scene.portals())} m")
    log.info("scene of %d triangles built in %.2f s", len(scene.triangles), timings["scene"])
    crs = pyproj.CRS.from_user_input(scn.crs) if scn.crs else None
    points, tiles, drift_info, runs_info = {}, {}, {}, {}
    tag = zlib.crc32(scn.name.encode())   # scenarios draw different errors for the same seed

    def write(spec, true, drifted, returns, info, t_scan):
        xyz = PoseInterpolator(drifted).body_to_world(returns.gps_time, returns.p_body)
        counts = writer.write_run(survey, spec.run_id, drifted, xyz, returns.gps_time,
                                  returns.intensity, scn.tile_size, crs)
        writer.write_truth_run(truth, spec.run_id, true.trajectory, true.chainage)
        timings[f"write {spec.run_id}"] = time.perf_counter() - t_scan
        points[spec.run_id], tiles[spec.run_id], drift_info[spec.run_id] = len(returns), len(counts), info
        runs_info[spec.run_id] = {"track": spec.track, "direction": spec.direction, "points": len(returns),
                                  "tiles": counts, "scan_span": true.scan_span, "drift": info}
        say(f"{spec.run_id}: {len(returns):,} points, {len(counts)} tiles, max drift "
            f"{info['max_error_horizontal']:.2f} m ({timings[f'scan {spec.run_id}']:.1f} s scan, "
            f"{timings[f'write {spec.run_id}']:.1f} s write)")

    # writing run k (georeference, LAZ) overlaps scanning run k + 1 (ray casting)
    with ThreadPoolExecutor(max_workers=1) as pool:
        pending = []
        for k, spec in enumerate(scn.runs):
            t = time.perf_counter()
            rngs = [np.random.default_rng([seed, k, stream, tag]) for stream in range(3)]
            true = drive(spec, scene, scn.rate_hz, rngs[0])
            drifted, info = drift(true.trajectory, true.chainage, scene.open_sky(true.chainage),
                                  scn.drift, rngs[1])
            returns = scan(scene, PoseInterpolator(true.trajectory), *true.scan_span, scn.scanner, rngs[2])
            timings[f"scan {spec.run_id}"] = time.perf_counter() - t
            for f in pending:
                f.result()
            pending = [pool.submit(write, spec, true, drifted, returns, info, time.perf_counter())]
            del returns
        for f in pending:
            f.result()
    control = _write_control(scene, survey, truth, seed)
    writer.write_params(truth, {
        "railtraj_version": __version__, "seed": seed, "scenario": scn.to_dict(),
        "origin": scn.geometry.alignment.origin, "length": scene.centreline.length,
        "sections": scene.spans, "portals": scene.portals(), "tracks": scene.sections.tracks,
        "runs": runs_info, "control": control, "timings": timings})
    return SimResult(survey, truth, scn.name, seed, scn.size, timings, points, tiles, drift_info)


def _write_control(scene: Scene, survey: Path, truth: Path, seed: int) -> list[str]:
    """control.csv (surveyed, with noise) in the survey and the exact positions in the truth."""
    if not scene.control:
        return []
    ids = list(scene.control)
    true_xyz = np.array([scene.control[i] for i in ids])
    rng = np.random.default_rng([seed, 1_000_003])
    sd = np.broadcast_to(CONTROL_SD, true_xyz.shape)
    writer.write_control_csv(survey / "control.csv", ids, true_xyz + rng.standard_normal(true_xyz.shape) * sd, sd)
    writer.write_control_csv(truth / "control.csv", ids, true_xyz, np.full(true_xyz.shape, 1e-4))
    return ids
