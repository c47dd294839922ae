"""Configuration schema of the ``railtraj`` Hydra application (the composition root's input).

The top-level options live in :class:`RunConfig`; each stage group (detector, descriptor,
matcher, optimizer, executor) gets its options from the dataclass its plugin registered, and
the pipeline group from :class:`PipelineConfig`. Everything is stored in Hydra's ConfigStore, so
the installed package runs with no YAML; ``conf/`` only holds presets.
Only this module and :mod:`railtraj.cli` import Hydra/OmegaConf.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING

from railtraj.alongtrack import AlongTrackOptions
from railtraj.errors import ConfigError
from railtraj.plugins import registry
from railtraj.portal import PortalOptions
from railtraj.same_track import SameTrackOptions
from railtraj.sd_check import SdCheckOptions


@dataclass
class PipelineConfig:
    """Which tiles and run pairs are matched, and what is written.

    ``local``: one tile area (``tile`` = a tile file name, or "x,y" in survey coordinates; when
    empty, every overlapping pair); ``global``: all tiles, every run matched to a reference run;
    ``multirun``: all tiles, every pair of runs, adjusted jointly.
    """

    name: str = "global"
    pairs: str = "reference"           # reference | all
    reference_run: str | None = None  # default: the first run in name order
    tile: str | None = None         # local only: tile name or "x,y"
    max_pairs: int = 0                 # 0: no limit (a cap for quick looks)
    min_overlap_m: float = 2.0         # overlap of tile bounding boxes in x and y
    pair_part_m: float = 25.0          # larger tiles are matched in parts this long, detected in squares of this grid (0: whole)
    max_misalignment_m: float = 3.0    # how far apart the same feature may be in two runs
    # where the along-track chains put two runs further apart than that, their tile pairs are
    # matched again within the distance they need, up to this (m; at most max_misalignment_m: never)
    max_widened_m: float = 6.0
    # three runs or more matched to a reference: where its chains resolve less of a run pair's track
    # than this share and another of its run pairs resolves this share or more, the other runs'
    # pairs are matched too (0: never)
    other_pairs_below: float = 0.5
    # ... and where the sd check finds the reference's GNSS biased, wherever one of its run pairs
    # resolves less than this share (1.0: is not resolved along its whole track; 0: never)
    other_pairs_below_biased: float = 1.0
    tile_cache_gb: float = 1.0         # GiB of whole tiles kept between detection and matching (shared by the workers)
    alongtrack: AlongTrackOptions = field(default_factory=AlongTrackOptions)  # joint alias resolution
    sd_check: SdCheckOptions = field(default_factory=SdCheckOptions)  # reported sd against the runs' disagreement
    same_track: SameTrackOptions = field(default_factory=SameTrackOptions)  # runs on one track compared where GNSS is good
    portal: PortalOptions = field(default_factory=PortalOptions)  # a portal's GNSS keeps an sd in the corrected sd


LOCAL = PipelineConfig(name="local", pairs="all", alongtrack=AlongTrackOptions(enabled=False))
GLOBAL = PipelineConfig(name="global", pairs="reference")
MULTIRUN = PipelineConfig(name="multirun", pairs="all")


@dataclass
class RunConfig:
    """Options of one railtraj job. ``survey_dir`` empty: the built-in synthetic demo survey."""

    survey_dir: str | None = None
    out_dir: str = "outputs/${now:%Y-%m-%d_%H-%M-%S_%f}"
    crs: str = "EPSG:27700"            # survey CRS of trajectories and tiles (heights ODN)
    sbet_crs: str | None = None       # frame of SBET and anchors; None: ETRS89 (BNG) / WGS 84
    proj_grid_dir: str | None = None  # folder of PROJ grids (railtraj installs OSTN15/OSGM15)
    anchors: str = "auto"              # auto: write anchors.csv when the grids are found; true; false
    write_tiles: bool = False          # write re-georeferenced tiles to OUT/tiles/<run>/
    truth_dir: str | None = None    # simulator truth, for scoring only (never used to correct)
    threads: int = 0                   # threads of the main process (KD-trees, window fits, Open3D); 0: every core it may use
    resume: bool = True                # reuse finished tiles/pairs of an earlier run in out_dir
    max_memory_gb: float = 0.0         # stop with an error above this resident memory (GiB, with workers); 0: off
    detector: Any = MISSING
    descriptor: Any = MISSING
    matcher: Any = MISSING
    optimizer: Any = MISSING
    executor: Any = MISSING
    pipeline: Any = MISSING


#: accepted spellings of ``anchors=`` (Hydra turns true/false into booleans) and what they mean
ANCHORS_MODES = {"auto": "auto", "true": "true", "yes": "true", "on": "true", "required": "true",
                 "false": "false", "no": "false", "off": "false"}


def anchors_mode(value: Any) -> str:
    """``auto``, ``true`` or ``false`` for an ``anchors=`` value; anything else is a ConfigError,
    because a typo must not silently behave like ``auto``."""
    mode = ANCHORS_MODES.get(str(value).strip().lower())
    if mode is None:
        raise ConfigError(f"anchors={value} is not an option: use anchors=auto (write anchors.csv "
                          "when the OS grids are found), anchors=true (fail without them) or "
                          "anchors=false (skip anchors.csv)")
    return mode


#: the defaults list: which option of each group a plain `railtraj` uses.
DEFAULTS: list[Any] = [
    "railtraj_schema",
    {"detector": "iss"},            # ISS keypoints (thesis' detector)
    {"descriptor": "none"},         # descriptors do not separate repetitive tunnel geometry
    {"matcher": "pair_voting"},     # translation voting + dense check + refinement
    {"optimizer": "spline"},        # continuous per-run corrections, one robust sparse solve
    {"executor": "process"},        # a worker per core (demo on 2 cores: 96 s serial, 73 s)
    {"pipeline": "global"},
    "_self_",
]

HYDRA_OVERRIDES: dict[str, Any] = {
    "run": {"dir": "${out_dir}"},
    "sweep": {"dir": "${out_dir}", "subdir": "${hydra.job.override_dirname}"},
    "job": {"config": {"override_dirname": {
        "exclude_keys": ["survey_dir", "out_dir", "proj_grid_dir", "truth_dir"]}}},
    # after a sweep: summary.csv, summary.md, summary.png in the sweep folder (railtraj.sweep)
    "callbacks": {"sweep_summary": {"_target_": "railtraj.cli.SweepSummary"}},
}


def register_configs(cs: ConfigStore | None = None) -> None:
    """Publish the schema, the pipeline presets and every plugin's stage options to Hydra."""
    cs = cs or ConfigStore.instance()
    cs.store(name="railtraj_schema", node=RunConfig)
    for preset in (LOCAL, GLOBAL, MULTIRUN):
        cs.store(group="pipeline", name=preset.name, node=preset)
    for spec in registry().specs():
        cs.store(group=spec.kind, name=spec.name, node=spec.config(name=spec.name))
    cs.store(name="railtraj", node={"defaults": DEFAULTS, "hydra": HYDRA_OVERRIDES})


__all__ = ["RunConfig", "PipelineConfig", "register_configs", "anchors_mode", "field"]
