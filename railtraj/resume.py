"""Resume: finished per-tile and per-pair results kept in the out folder and reused by a rerun.

Each result is one pickle file in ``OUT/.railtraj-cache/{tiles,pairs}/<key>.pkl``, written
atomically by the worker as soon as that tile or pair is done, so a run that is killed keeps the
work it finished. The key is a hash of everything the result depends on:

- a tile's keypoints: the tile file (path, size, mtime_ns), the time span of its run's
  trajectory (detection checks that it covers the tile's points) and the detector and descriptor
  options;
- a pair's match: both tiles' keys, the pair's overlap box, the matcher options and the
  pipeline options matching uses (``max_misalignment_m``);
- the source code that computes them (:func:`source_digest`): the stages' modules, the
  pipeline's detect or match step and what they import from railtraj. Editing the matcher's code
  re-matches, editing the report or the optimizer does not. Imports inside functions are not
  followed: after editing such code, run with ``resume=false``.

So a changed matcher option re-matches every pair but reuses the keypoints, and a changed tile
re-detects that tile and re-matches only its pairs. The lookup happens in the parent before any
job is dispatched: reused work costs one file read. With ``reuse=False`` (``resume=false``)
nothing is read and every result is computed and stored again. Once matching is done, the
entries this run did not use (other inputs or options) and temporary files left by a killed run
are deleted, so the cache holds one result per tile and pair of the last run.

The jobs of a sweep (``railtraj -m ...``) share one cache, ``SWEEP/.railtraj-cache``: jobs that
differ only in what comes after matching (the optimizer, along-track or sd-check options) reuse
the first job's keypoints and matches, and a job with another detector reuses nothing it should
not (the keys differ). Each job records what it used (``used-<job>.txt``) instead of pruning, and
after the sweep's last job :func:`prune_sweep` deletes what no job used.
"""

from __future__ import annotations

import hashlib
import inspect
import logging
import os
import pickle
import sys
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from railtraj.io.atomic import atomic_write

log = logging.getLogger(__name__)

#: bump when a cached result's type or meaning changes, so old caches are not read
CACHE_VERSION = 1
CACHE_DIR = ".railtraj-cache"


def file_identity(path: str | os.PathLike) -> tuple[str, int, int]:
    """(absolute path, size, mtime_ns): changes whenever the file is rewritten or replaced."""
    p = Path(path).resolve()
    st = p.stat()
    return str(p), st.st_size, st.st_mtime_ns


def digest(*parts: Any) -> str:
    """A stable hash of ``repr`` of the parts (configs are plain dicts, lists and numbers)."""
    return hashlib.sha256(repr((CACHE_VERSION, *parts)).encode()).hexdigest()[:32]


def _imported_modules(roots: Iterable[str]) -> list[ModuleType]:
    """The loaded modules ``roots`` name and, transitively, the modules of their package (or of
    railtraj) whose names they import."""
    seen: dict[str, ModuleType] = {}
    todo = list(roots)
    while todo:
        name = todo.pop()
        module = sys.modules.get(name)
        if name in seen or module is None:
            continue
        seen[name] = module
        own = ("railtraj", name.split(".")[0])
        for value in vars(module).values():
            dep = _module_of(value)
            if dep and dep.split(".")[0] in own:
                todo.append(dep)
    return [seen[n] for n in sorted(seen)]


def _module_of(value: Any) -> str | None:
    name = value.__name__ if inspect.ismodule(value) else getattr(value, "__module__", None)
    return name if isinstance(name, str) else None


def source_digest(stages: Iterable[Any], functions: Iterable[Callable] = ()) -> str:
    """Hash of the code that computes cached results: the modules defining the ``stages``'
    classes, the source of ``functions`` (and of the functions of their module they call), and
    what all of these import from railtraj or their own package, transitively."""
    roots = [type(stage).__module__ for stage in stages]
    h = hashlib.sha256()
    todo, done = list(functions), set()
    while todo:
        fn = todo.pop()
        if fn in done:
            continue
        done.add(fn)
        h.update(inspect.getsource(fn).encode())
        if not inspect.isfunction(fn):  # a class of the functions' module: its source is enough
            continue
        for name in fn.__code__.co_names:
            value = fn.__globals__.get(name)
            if (inspect.isfunction(value) or inspect.isclass(value)) and value.__module__ == fn.__module__:
                todo.append(value)
            elif value is not None and (_module_of(value) or "").startswith("railtraj"):
                roots.append(_module_of(value))
    for module in _imported_modules(roots):
        path = getattr(module, "__file__", None)
        if path and path.endswith(".py"):
            h.update(module.__name__.encode() + b"\0" + Path(path).read_bytes())
    return h.hexdigest()


class Cache:
    """Finished results of one out folder, by kind (``tiles``, ``pairs``) and key.

    ``configs`` holds the options of the stages whose results are cached (``detector``,
    ``descriptor``, ``matcher``) as plain dicts; ``code`` the :func:`source_digest` of the code
    that computes each kind (``tiles``, ``pairs``).
    """

    def __init__(self, folder: str | os.PathLike, configs: dict[str, Any],
                 code: dict[str, str] | None = None, reuse: bool = True, job: str | None = None) -> None:
        self.folder = Path(folder)
        self.configs = configs
        self.code = code or {}
        self.reuse = reuse
        self.job = job  # the job's name in a sweep's shared cache; None: the cache of one out folder
        self.used: set[Path] = set()

    def tile_key(self, run_id: str, tile_path: Path, trajectory_span: tuple[float, float], part_m: float) -> str:
        """``part_m``: the grid whose squares a large tile is detected in (``pipeline.pair_part_m``)."""
        return digest("tile", self.code.get("tiles"), run_id, file_identity(tile_path), trajectory_span, part_m,
                      self.configs.get("detector"), self.configs.get("descriptor"))

    def pair_key(self, pair, key_a: str, key_b: str, match_options: Any) -> str:
        """``pair``: a :class:`railtraj.io.survey.TilePair`; ``key_a``/``key_b``: its tiles' keys."""
        box = np.concatenate([pair.overlap_min, pair.overlap_max]).tolist()
        return digest("pair", self.code.get("pairs"), pair.run_a, pair.run_b, key_a, key_b, box,
                      self.configs.get("matcher"), match_options)

    def path(self, kind: str, key: str) -> Path:
        return self.folder / kind / f"{key}.pkl"

    def load(self, kind: str, key: str) -> Any | None:
        """The stored result, or None when absent, disabled or unreadable (then it is recomputed)."""
        path = self.path(kind, key)
        self.used.add(path)
        if not self.reuse or not path.exists():
            return None
        try:
            with open(path, "rb") as f:
                return pickle.load(f)
        except Exception as exc:  # noqa: BLE001 - a damaged entry is recomputed, never fatal
            log.warning("ignoring unreadable cache entry %s: %s", path, exc)
            return None

    def prune(self) -> None:
        """Delete the entries this run did not look up and temporary files of killed runs; in a
        sweep's cache, record what this job looked up instead (:func:`prune_sweep`)."""
        if self.job is not None:
            with atomic_write(self.folder / f"{USED}{self.job}.txt") as fh:
                fh.write("".join(f"{p.relative_to(self.folder)}\n" for p in sorted(self.used)))
            return
        for path in _entries_and_parts(self.folder):
            if path not in self.used:
                path.unlink(missing_ok=True)


def _entries_and_parts(folder: Path) -> list[Path]:
    """A cache folder's entries and the temporary files of killed runs."""
    return [*folder.glob("*/*.pkl"), *folder.glob("*/.*.part")]


#: prefix of a sweep job's list of the cache entries it used (Cache.prune, prune_sweep)
USED = "used-"


def prune_sweep(folder: str | os.PathLike, jobs: int) -> int | None:
    """After the last of a sweep's ``jobs``: delete the entries of its shared cache ``folder``
    that no job listed as used, temporary files of killed jobs, and the lists. Returns how many
    entries were deleted; None, deleting only the lists, when a job did not list what it used
    (it failed before matching ended): a sweep whose every job failed on a bad input must not
    empty the cache of the last good one. A sweep killed before its end keeps everything."""
    folder = Path(folder)
    lists = sorted(folder.glob(f"{USED}*.txt"))
    complete = len(lists) >= jobs
    used = {folder / line for path in lists for line in path.read_text().splitlines() if line}
    gone = [p for p in _entries_and_parts(folder) if p not in used] if complete else []
    for path in [*gone, *lists]:
        path.unlink(missing_ok=True)
    return sum(p.suffix == ".pkl" for p in gone) if complete else None


#: the job process an executor's worker computes for (None in the job's own process)
_job_pid: int | None = None


def serve_job(pid: int) -> None:
    """In an executor's worker: store results for the job process ``pid`` only while it lives.

    A job killed with SIGKILL left its workers finishing their chunks and storing results it
    never counted (a resumed run found one pair more in its cache than the killed one had)."""
    global _job_pid
    _job_pid = pid


def job_gone() -> bool:
    """Whether the job this worker computes for has died (a zombie counts as dead)."""
    if _job_pid is None:
        return False
    try:
        os.kill(_job_pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False
    try:  # killed but not yet reaped by its parent
        return Path(f"/proc/{_job_pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except (OSError, IndexError):
        return False


def _store(path: Path, value: Any) -> None:
    with atomic_write(path, "wb") as f:
        pickle.dump(value, f, protocol=pickle.HIGHEST_PROTOCOL)
        if job_gone():  # checked last, before the file takes its name: the next run prunes the part
            os._exit(1)


def _compute_and_store(task: tuple) -> Any:
    """Worker side of :func:`cached_map`: run one job and store its result as soon as it is done."""
    fn, path, job = task
    result = fn(job)
    _store(path, result)
    return result


def cached_map(executor, fn: Callable, jobs: Sequence, keys: Sequence[str], cache: Cache | None,
               kind: str, progress: Callable[[int, int], Any] | None = None) -> tuple[list, int]:
    """``executor.map(fn, jobs)``, reusing stored results; returns the results and how many
    were reused. Jobs are dispatched only for results the cache does not hold."""
    if cache is None:
        return executor.map(fn, jobs, progress=progress), 0
    results = [cache.load(kind, key) for key in keys]
    todo = [k for k, r in enumerate(results) if r is None]
    if len(todo) < len(jobs):
        log.info("resume: reusing %d of %d %s from %s", len(jobs) - len(todo), len(jobs), kind,
                 cache.folder)
    if todo:
        tasks = [(fn, cache.path(kind, keys[k]), jobs[k]) for k in todo]
        for k, result in zip(todo, executor.map(_compute_and_store, tasks, progress=progress),
                             strict=True):
            results[k] = result
            if not cache.path(kind, keys[k]).exists():  # stored by a worker on another machine
                _store(cache.path(kind, keys[k]), result)
    return results, len(jobs) - len(todo)
