"""End-to-end accuracy per scenario and seed, scored against the simulator's truth. Run:

    .venv/bin/python benchmarks/bench_alongtrack.py [--scenarios commensurate mixed] [--seeds 0 1 2]
        [--optimizer spline] [--size 1.0]

For each survey (generated once, cached under $RAILTRAJ_CACHE or ~/.cache/railtraj/bench) it runs
the default pipeline and prints one table row:

* inter-run horizontal RMS / max before -> after, vertical RMS after (all run pairs pooled);
* absolute horizontal RMS after, and its distance to the sd-weighted average of the runs' input
  errors (the best relative observations allow without control: ``bound``);
* the worst ``ok`` tile-pair offset, the number of ``coarse`` pairs and their worst, the worst tie,
  against the truth, and ties over 5 cm;
* the share of tile pairs whose along-track offset is used (``ok`` or resolved);
* honesty: the share of epochs whose corrected horizontal error exceeds 3 times the reported
  posterior horizontal sd, and the largest such ratio (a wrong answer reported as reliable).
"""

from __future__ import annotations

import argparse
import logging
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from railtraj.alongtrack import used_along
from railtraj.georef import PoseCache
from railtraj.pipeline import PipelineOptions, Stages, run_pipeline
from railtraj.plugins import registry
from railtraj.sim import generate, load_truth
from railtraj.sim.drift import Multipath
from railtraj.sim.scenarios import Scenario, get_scenario
from railtraj.sim.score import offset_errors, position_error, score_trajectories, tie_errors


def survey_for(scenario: str, seed: int, size: float, vary: tuple[str, ...] = ()) -> Path:
    cache = Path(os.environ.get("RAILTRAJ_CACHE", Path.home() / ".cache" / "railtraj"))
    name = f"{scenario}-{seed}" + ("" if size == 1.0 else f"-x{size}") + "".join(f"-{v}" for v in vary)
    root = cache / "bench" / name
    if not (root / "survey").is_dir():
        generate(varied(get_scenario(scenario), vary), root, seed=seed, size=size, overwrite=True)
    return root / "survey"


def varied(scn: Scenario, vary: tuple[str, ...]) -> Scenario:
    """The scenario with ``key=value`` changes: a field of its geometry, scanner or drift,
    ``tunnel_length`` (every section but the cuttings times the value), ``speed``
    (every run's speed times the value), ``tile_size`` (m), ``runs`` (that many passes, the
    catalogue's repeated in turn, 600 s apart) or ``multipath`` (``run_b`` or ``run_b@1``: that
    run gets portal_trap's GNSS multipath bias at its first, or n-th, portal), ``heading_deg``
    and ``origin`` (``x,y``: where the alignment starts; a tunnel along a grid axis with its
    centre on a tile edge is cut lengthwise), to try surveys the catalogue does not hold. The
    drift's direction is drawn in the map's frame: to change a heading alone, turn the drift as
    much (``azimuth_turn_deg``, a drift field: heading 0 instead of 60 with ``azimuth_turn_deg=-60``)."""
    for item in vary:
        key, value = item.split("=")
        if key == "speed":
            scn = replace(scn, runs=tuple(replace(r, speed=r.speed * float(value)) for r in scn.runs))
        elif key == "tile_size":
            scn = replace(scn, tile_size=float(value))
        elif key == "runs":
            base = scn.runs
            scn = replace(scn, runs=tuple(replace(base[k % len(base)], run_id=f"run_{chr(ord('a') + k)}",
                                                  start_time=base[0].start_time + 600.0 * k)
                                          for k in range(int(value))))
        elif key == "multipath":
            run, _, portal = value.partition("@")
            bias = Multipath(run, portal=int(portal or 0), bias=(0.3, -0.25, 0.1))
            scn = replace(scn, drift=replace(scn.drift, multipath=(*scn.drift.multipath, bias)))
        elif key in ("heading_deg", "origin"):  # the alignment: heading, or where it starts ("x,y")
            al = scn.geometry.alignment
            al = replace(al, heading_deg=float(value)) if key == "heading_deg" else \
                replace(al, origin=(*map(float, value.split(",")), al.origin[2]))
            scn = replace(scn, geometry=replace(scn.geometry, alignment=al))
        elif key == "tunnel_length":
            scn = replace(scn, geometry=replace(scn.geometry, sections=tuple(
                (k, n if k == "cutting" else n * float(value)) for k, n in scn.geometry.sections)))
        elif hasattr(scn.drift, key):
            scn = replace(scn, drift=replace(scn.drift, **{key: type(getattr(scn.drift, key))(value)}))
        elif hasattr(scn.geometry, key):
            scn = replace(scn, geometry=replace(scn.geometry, **{key: type(getattr(scn.geometry, key) or 0.0)(value)}))
        elif hasattr(scn.scanner, key):
            scn = replace(scn, scanner=replace(scn.scanner, **{key: type(getattr(scn.scanner, key))(value)}))
        else:
            raise SystemExit(f"--vary {item}: not a geometry, scanner or drift field, nor tunnel_length, speed, "
                             "tile_size, runs, multipath, heading_deg or origin")
    return scn


def averaging_bound_gap(truth, before, after, chainage) -> tuple[float, float]:
    """RMS (horizontal) of each run's corrected error minus the sd-weighted average of all runs'
    input errors at the same chainage: how far the absolute result is from what relative
    observations allow; and the RMS of that average's own error (the bound).

    The gap counts a result better than the average as a gap too: where a run's sd is too
    optimistic (GNSS multipath at a portal), the average follows that run's error and the
    adjustment, which weighs the runs by their agreement as well, may not."""
    runs = sorted(after)
    err_in, err_out, sd, ch = {}, {}, {}, {}
    for r in runs:
        e_in, ok = position_error(truth[r], before[r])
        e_out, _ = position_error(truth[r], after[r])
        ch[r] = np.interp(before[r].time[ok], truth[r].time, chainage[r])
        err_in[r], err_out[r] = e_in, e_out
        sd[r] = before[r].sd[ok] if before[r].sd is not None else np.ones_like(e_in)
    gaps, bounds = [], []
    for r in runs:
        sel = np.arange(0, len(ch[r]), max(1, len(ch[r]) // 3000))
        num, den = np.zeros((len(sel), 3)), np.zeros((len(sel), 3))
        for q in runs:
            order = np.argsort(ch[q])
            inside = (ch[r][sel] >= ch[q].min()) & (ch[r][sel] <= ch[q].max())
            e = np.column_stack([np.interp(ch[r][sel], ch[q][order], err_in[q][order, k]) for k in range(3)])
            s = np.column_stack([np.interp(ch[r][sel], ch[q][order], sd[q][order, k]) for k in range(3)])
            w = inside[:, None] / s**2
            num, den = num + w * e, den + w
        gaps.append((err_out[r][sel] - num / den)[:, :2])
        bounds.append((num / den)[:, :2])
    rms = lambda parts: float(np.sqrt(np.mean(np.sum(np.vstack(parts) ** 2, axis=1))))  # noqa: E731
    return rms(gaps), rms(bounds)


def score(survey_dir: Path, result) -> dict:
    truth = load_truth(survey_dir.parent / "truth")
    before = score_trajectories(truth.trajectories, result.trajectories, truth.chainage)
    after = score_trajectories(truth.trajectories, result.corrected, truth.chainage)
    pool = lambda s, k: float(np.sqrt(np.mean([v[k] ** 2 for v in s["consistency"].values()])))  # noqa: E731
    maxi = lambda s, k: float(max(v[k] for v in s["consistency"].values()))  # noqa: E731
    off = offset_errors(truth.trajectories, result.trajectories, result.offsets)
    coarse = offset_errors(truth.trajectories, result.trajectories,  # scored like ok pairs
                           [replace(o, status="ok" if o.status == "coarse" else "x") for o in result.offsets])
    poses = PoseCache()
    ties = [np.linalg.norm(tie_errors(truth.trajectories, result.trajectories, t, poses), axis=1) for t in result.ties]
    ties = np.concatenate(ties) if ties else np.zeros(0)
    used = sum(used_along(o) for o in result.offsets)
    coverage = result.adjustment.get("alongtrack_coverage") or {}
    length = sum(c["length_m"] for c in coverage.values())
    return {
        "h_before": pool(before, "rms_h"), "hmax_before": maxi(before, "max_h"),
        "h_after": pool(after, "rms_h"), "hmax_after": maxi(after, "max_h"), "v_after": pool(after, "rms_v"),
        "v_before": pool(before, "rms_v"), "abs_h_before": before["overall"]["rms_h"],
        "abs_h_after": after["overall"]["rms_h"], "abs_v_before": before["overall"]["rms_v"],
        "abs_v_after": after["overall"]["rms_v"],
        **dict(zip(("bound_gap", "bound_h"), averaging_bound_gap(truth.trajectories, result.trajectories,
                                                                 result.corrected, truth.chainage), strict=True)),
        "worst_ok": float(max((np.linalg.norm(e) for e in off.values()), default=0.0)),
        "worst_coarse": float(max((np.linalg.norm(e) for e in coarse.values()), default=0.0)), "coarse": len(coarse),
        "worst_tie": float(ties.max()) if len(ties) else 0.0, "ties_over_5cm": int((ties > 0.05).sum()),
        "ties": len(ties), "used_share": used / max(len(result.offsets), 1),
        "resolved_share": sum(c["resolved_m"] for c in coverage.values()) / length if length else 0.0,
        **honesty(truth.trajectories, result.corrected),
    }


def honesty(truth, corrected) -> dict:
    """How often, and by how much, the corrected trajectories' error exceeds their posterior sd
    (horizontal): ``beyond_3sd`` (share of epochs over 3 sd) and ``worst_z``."""
    ratios = []
    for r, traj in corrected.items():
        if traj.sd is None:
            continue
        err, ok = position_error(truth[r], traj)
        ratios.append(np.linalg.norm(err[:, :2], axis=1) / np.maximum(np.linalg.norm(traj.sd[ok][:, :2], axis=1), 1e-9))
    z = np.concatenate(ratios) if ratios else np.zeros(0)
    return {"beyond_3sd": float(np.mean(z > 3)) if len(z) else 0.0, "worst_z": float(z.max()) if len(z) else 0.0}


def print_pairs(survey_dir: Path, result) -> None:
    """One line per tile pair: status (and before resolution), alias shift, margin, true error."""
    truth = load_truth(survey_dir.parent / "truth")
    errors = offset_errors(truth.trajectories, result.trajectories, result.offsets)
    for k, o in enumerate(result.offsets):
        at = o.info.get("alongtrack", {})
        err = f"error {np.round(errors[k] * 1000).astype(int).tolist()} mm" if k in errors else ""
        print(f"    {o.run_b} {o.tile_a:<20} {o.status:<12} shift {at.get('shift_m', 0):+.2f} "
              f"{o.info.get('resolved', o.info.get('demoted', '')):<10} {err}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", nargs="+", default=["commensurate", "commensurate_fast", "mixed"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--optimizer", default="spline")
    ap.add_argument("--pipeline", default="global", choices=["global", "multirun"])
    ap.add_argument("--size", type=float, default=1.0)
    ap.add_argument("--vary", nargs="*", default=[], help="key=value: a geometry, scanner or drift field (e.g. roughness=1), tunnel_length (factor), speed (factor), tile_size (m), runs (count), multipath (run[@portal]), heading_deg or origin (x,y)")
    ap.add_argument("--pairs", action="store_true", help="also print every tile pair: status, alias shift, error")
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    print("| scenario | seed | inter-run h RMS / max before -> after (m) | v RMS before -> after | "
          "abs h / v RMS before -> after | abs h bound, gap | worst ok offset | coarse: n, worst | worst tie | ties > 5 cm | "
          "along used | length resolved | beyond 3 sd, worst | s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for scenario in args.scenarios:
        for seed in args.seeds:
            survey = survey_for(scenario, seed, args.size, tuple(args.vary))
            reg = registry()
            stages = Stages(reg.create("detector", "iss"), reg.create("descriptor", "none"),
                            reg.create("matcher", "pair_voting"), reg.create("optimizer", args.optimizer),
                            reg.create("executor", "process"))
            options = PipelineOptions(mode=args.pipeline, pairs="all" if args.pipeline == "multirun" else "reference")
            t0 = time.perf_counter()
            result = run_pipeline(survey, stages, options, progress=lambda *a: None)
            s = score(survey, result)
            if args.pairs:
                print_pairs(survey, result)
            print(f"| {scenario} | {seed} | {s['h_before']:.3f} / {s['hmax_before']:.2f} -> {s['h_after']:.3f} / "
                  f"{s['hmax_after']:.3f} | {s['v_before']:.3f} -> {s['v_after']:.3f} | {s['abs_h_before']:.2f} / "
                  f"{s['abs_v_before']:.2f} -> {s['abs_h_after']:.3f} / {s['abs_v_after']:.3f} | {s['bound_h']:.3f}, {s['bound_gap']:.3f} | "
                  f"{s['worst_ok']:.3f} | {s['coarse']}, {s['worst_coarse']:.3f} | {s['worst_tie']:.3f} | {s['ties_over_5cm']} of {s['ties']} | "
                  f"{s['used_share']:.0%} | {s['resolved_share']:.0%} | {s['beyond_3sd']:.1%}, {s['worst_z']:.1f} | {time.perf_counter() - t0:.0f} |",
                  flush=True)


if __name__ == "__main__":
    main()
