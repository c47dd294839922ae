"""Re-georeference every input tile with the corrected trajectories (OUT/tiles/<run_id>/).

Each point keeps its body-frame measurement: it is taken back to the body frame with the input
trajectory at its gps_time and out again with the corrected one. Scales and offsets of the input
tile are kept so the output is as precise as the input.
"""

from __future__ import annotations

import logging
from pathlib import Path

from railtraj.georef import regeoreference
from railtraj.io.las import read_tile, write_tile

log = logging.getLogger(__name__)


def _retile(job: tuple) -> str:
    header, run_id, before, after, out_path = job
    tile = read_tile(header.path, run_id=run_id)
    before.check_covers(tile.gps_time, f"points of {header.path.name}")
    tile = regeoreference(tile, before, after)
    write_tile(out_path, tile, scales=tuple(header.scales), offsets=tuple(header.offsets), crs=header.crs)
    return str(out_path)


def write_corrected_tiles(result, tiles_dir: Path, executor=None) -> list[str]:
    """Write every tile of every run, re-georeferenced; returns the written paths."""
    jobs = [(h, run_id, result.trajectories[run_id], result.corrected[run_id],
             tiles_dir / run_id / (h.path.stem + ".laz"))
            for run_id, run in sorted(result.survey.runs.items()) for h in run.tiles]
    log.info("writing %d re-georeferenced tiles to %s", len(jobs), tiles_dir)
    if executor is None:
        return [_retile(j) for j in jobs]
    return executor.map(_retile, jobs)
