"""Speed and memory of whole jobs (issue #12). Run:

    .venv/bin/python benchmarks/bench_speed.py [--cases replica,demo,sizes,generate,thesis] [--sizes 0.2,0.5,1.0]
        [--executors serial,process,dask] [--scenario mixed] [--work /tmp/railtraj-bench-speed]

* ``replica``: the thesis replica tile pair (bench_local's ~2.3 M point simulated tile with a
  cabinet and a niche, and its second acquisition moved 0.5 / 1.5 / 0.10 m with 2 cm noise),
  written as LAZ once, then read, detected and matched in this process, twice: seconds per
  stage, first with the imports of Open3D and SciPy's modules (~1 s), then with them loaded.
* ``demo``: the main job on the built-in demo survey (``railtraj`` with no survey_dir; generated
  and cached first, not timed), once per executor. An executor may carry overrides after ``+``:
  ``serial+threads=1`` is a serial job held to one core (by default its main process threads
  KD-tree queries, window fits and Open3D over every core).
* ``sizes``: ``railtraj-sim <scenario> --size S`` surveys (generated once into ``--work``), the
  main job once per size and executor.
* ``generate``: the demo survey simulated at full size into ``--work`` (3 runs, ~600 m of
  tunnel, 5-15 M points per run): seconds, MB on disk and points per run. Target: 60 s on 2
  cores, under 150 MB (moved here from the test suite: speed targets are benchmarks).
* ``thesis``: a thesis-size survey (``mixed`` 1.33 times as long with 3500 points per profile: 3
  runs, 207 tiles of ~1 M points, 123 tile pairs; generated once, ~4 min), the main job once per
  executor (``--cases thesis --executors process``: ~4-5 min on 2 cores).

Each job runs as its own ``railtraj`` process with ``resume=false``; the table shows its wall
time, the stage seconds from metrics.json, its peak memory (metrics.json ``memory``: the largest
sampled total of the job and its workers) and the 1-minute load average when it started (the
machine may be shared: repeat a row when the load is above the core count). Targets on 2 cores:
replica 5 s, demo 90 s, thesis-size survey 10 min within 4 GiB.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
STAGES = ("load", "detect", "match", "alongtrack", "optimize", "write")


def replica(work: Path) -> None:
    """Read, detect and match the thesis replica pair; print the seconds of each stage."""
    import numpy as np

    sys.path.insert(0, str(HERE))
    from bench_local import SHIFT, frame, sim_tile

    from railtraj.io.las import read_tile, write_tile
    from railtraj.matching.synthetic import second_acquisition
    from railtraj.plugins import registry

    paths = [work / "replica" / "a.laz", work / "replica" / "b.laz"]
    if not all(p.exists() for p in paths):
        paths[0].parent.mkdir(parents=True, exist_ok=True)
        a, axis = sim_tile(2_300_000, featured=True)
        shift = frame(axis).T @ SHIFT
        b = second_acquisition(a, shift, noise=0.02, seed=1)
        np.save(work / "replica" / "truth.npy", -shift)
        for path, tile in zip(paths, (a, b), strict=True):
            write_tile(path, tile)
    truth = np.load(work / "replica" / "truth.npy")
    reg = registry()
    detector, matcher = reg.create("detector", "iss"), reg.create("matcher", "pair_voting")
    for label in ("first, importing Open3D and SciPy", "again, libraries loaded (as in a job's workers)"):
        load = os.getloadavg()[0]  # each pass reads the tiles anew: nothing the first built is reused
        t0 = time.perf_counter()
        a, b = (read_tile(p, run_id=r) for p, r in zip(paths, "ab", strict=True))
        t1 = time.perf_counter()
        ka, kb = detector.detect(a), detector.detect(b)
        t2 = time.perf_counter()
        off = matcher.match(a, ka, b, kb)
        t3 = time.perf_counter()
        err = np.abs(off.d - truth).max() * 1000
        print(f"replica ({len(a):,} / {len(b):,} points), {label}: read {t1 - t0:.1f} s, detect {t2 - t1:.1f} s, "
              f"match {t3 - t2:.1f} s, END TO END {t3 - t0:.1f} s; {off.status}, max error {err:.1f} mm; "
              f"load {load:.1f}")
        del a, b, ka, kb, off


def generation(work: Path) -> None:
    """Simulate the demo survey at full size; print its seconds, size on disk and points per run."""
    from railtraj.sim import generate

    load = os.getloadavg()[0]
    t = time.perf_counter()
    res = generate("mixed", work / "generate", seed=0, overwrite=True)
    wall = time.perf_counter() - t
    size_mb = sum(p.stat().st_size for p in res.survey_dir.rglob("*") if p.is_file()) / 1e6
    points = ", ".join(f"{r} {n / 1e6:.1f} M" for r, n in sorted(res.points.items()))
    print(f"generate mixed seed 0: {wall:.1f} s (target 60), {size_mb:.0f} MB (target < 150), points {points}; "
          f"load {load:.1f}")


def job(survey: Path | None, out: Path, executor: str) -> dict:
    """Run one railtraj job; its wall time, stage seconds, peak memory and the load at its start."""
    name, *overrides = executor.split("+")  # e.g. serial+threads=1: one core
    args = [f"out_dir={out}", f"executor={name}", *overrides, "resume=false", "anchors=false"]
    if survey is not None:
        args.insert(0, f"survey_dir={survey}")
    load = os.getloadavg()[0]
    t = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "railtraj.cli", *args], capture_output=True, text=True)
    wall = time.perf_counter() - t
    if res.returncode != 0:
        raise SystemExit(f"railtraj failed ({executor}, {survey}): {res.stderr[-2000:]}")
    metrics = json.loads((out / "metrics.json").read_text())
    return {"wall": wall, "load": load, "seconds": metrics["seconds"], "memory": metrics.get("memory", {}),
            "pairs": metrics["counts"]["tile_pairs"], "tiles": metrics["counts"]["tiles"]}


def row(label: str, executor: str, r: dict) -> str:
    stages = " / ".join(f"{r['seconds'].get(s, float('nan')):.1f}" for s in STAGES)
    return (f"| {label:<22} | {executor:<16} | {r['tiles']:5d} | {r['pairs']:5d} | {r['wall']:7.1f} | {stages} | "
            f"{r['memory'].get('peak_sampled_gb', float('nan')):5.2f} | {r['load']:4.1f} |")


def simulated(scenario: str, size: float, work: Path) -> Path:
    """A simulated survey of ``scenario`` at ``size`` (generated once into ``work``)."""
    from railtraj.sim import generate

    root = work / f"{scenario}-{size:g}"
    if not (root / "survey").is_dir():
        generate(scenario, root, seed=0, size=size)
    return root / "survey"


#: the thesis-size survey: the demo's tunnel 1.33 times as long, scanned with 3500 points per
#: profile (x sqrt(1.33) = ~4000): 3 runs, 207 tiles of ~1 M points (median), 123 tile pairs
THESIS_SIZE = {"size": 1.33, "points_per_profile": 3500}


def thesis_size(work: Path) -> Path:
    """The thesis-size survey (generated once into ``work``: ~4 min and 0.7 GB on 2 cores)."""
    from dataclasses import replace

    from railtraj.sim import generate
    from railtraj.sim.scenarios import get_scenario

    root = work / "thesis-size"
    if not (root / "survey").is_dir():
        scn = get_scenario("mixed")
        scn = replace(scn, scanner=replace(scn.scanner, points_per_profile=THESIS_SIZE["points_per_profile"]))
        generate(scn, root, seed=0, size=THESIS_SIZE["size"])
    return root / "survey"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="replica,demo,sizes")
    ap.add_argument("--sizes", default="0.2,0.5,1.0")
    ap.add_argument("--executors", default="serial,process,dask")
    ap.add_argument("--scenario", default="mixed")
    ap.add_argument("--work", type=Path, default=Path("/tmp/railtraj-bench-speed"))
    args = ap.parse_args()
    cases, executors = args.cases.split(","), args.executors.split(",")
    args.work.mkdir(parents=True, exist_ok=True)
    print(f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}")
    if "replica" in cases:
        replica(args.work)
    if "generate" in cases:
        generation(args.work)
    jobs: list[tuple[str, Path | None]] = []
    if "demo" in cases:
        from railtraj.sim import demo_survey

        demo_survey()  # generated and cached before timing
        jobs.append(("demo (cached)", None))
    if "thesis" in cases:
        jobs.append(("thesis-size", thesis_size(args.work)))
    if "sizes" in cases:
        jobs += [(f"{args.scenario} --size {s}", simulated(args.scenario, float(s), args.work))
                 for s in args.sizes.split(",")]
    if not jobs:
        return
    print(f"| survey | executor | tiles | pairs | wall s | stage s: {' / '.join(STAGES)} | peak GiB | load |")
    print("|---|---|---|---|---|---|---|---|")
    for label, survey in jobs:
        for executor in executors:
            folder = re.sub(r"[^\w.-]+", "_", label).strip("_")  # "demo (cached)": no ( ) in a Hydra override
            out = args.work / "out" / f"{folder}-{executor.replace('+', '_').replace('=', '')}"
            print(row(label, executor, job(survey, out, executor)), flush=True)


if __name__ == "__main__":
    main()
