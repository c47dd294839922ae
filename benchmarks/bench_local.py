"""Speed and accuracy of the local stages on the thesis replica. Run:

    .venv/bin/python benchmarks/bench_local.py [--source sim|synthetic] [--points 2000000]

Tile A is a ~2 M point, 25 m tunnel tile in the British National Grid: ray-cast by
railtraj.sim (thesis scenario, straight ribbed tunnel) when it is importable, else the numpy
tunnel of railtraj.matching.synthetic. Tile B is the thesis' synthetic second acquisition: A
moved 0.5 m along the track, 1.5 m across and 0.10 m up, with 2 cm Gaussian noise per axis.
Prints per-stage seconds and the error per axis (mm, along / across / up) for each detector
with pair_voting, the 700 x 700 keypoint vote alone, and icp started 0.8 m off along the track.
With the simulator it runs two tiles: one with a cabinet and a niche (must match) and one with
nothing but ribs (1.5 m) and sleepers (0.65 m): their phase still fixes the offset (measured
ok, +2.9 mm along); with 0.6 m sleepers it repeats every 3 m and the matcher refuses (ambiguous).

Targets on 2 cores: tile pair end to end <= 10 s (thesis ~188 s: ISS 74 s, FPFH 139 s,
matching 44-60 s with ~200 keypoints); 700 keypoints per side matched <= 1 s (thesis > 1 h).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from railtraj.data import PointTile, TileOffset
from railtraj.matching.synthetic import placed, rotation_z, second_acquisition, tunnel_tile
from railtraj.matching.voting import find_peaks, pair_translations
from railtraj.plugins import registry

SHIFT = np.array([0.5, 1.5, 0.10])  # along, across, up (tunnel frame)


def sim_tile(points: int, featured: bool = True, seed: int = 0) -> tuple[PointTile, np.ndarray]:
    """A 25 m x 25 m tile of a ray-cast tunnel and its unit track direction.

    ``featured``: centred between a wall cabinet and an emergency niche (the thesis scenario has
    one every 70-150 m); otherwise in the middle of the tunnel, with only ribs (1.5 m) and
    sleepers (0.65 m, so the pattern repeats only every 19.5 m) to tell one place from another.
    """
    from railtraj.georef import PoseInterpolator
    from railtraj.sim.geometry import build_scene
    from railtraj.sim.runs import drive
    from railtraj.sim.scanner import ScannerSpec, scan
    from railtraj.sim.scenarios import get_scenario
    from railtraj.sim.surfaces import Surface

    scn = get_scenario("thesis")
    scene = build_scene(scn.geometry)
    run = drive(scn.runs[0], scene, scn.rate_hz, np.random.default_rng(seed))
    traj = run.trajectory
    if featured:
        objects = np.isin(scene.surface, [Surface.METAL, Surface.NICHE])
        local = scene.vertices[scene.triangles[objects]].mean(axis=1)
        world = scene.centreline.to_world(local)
        near = world[np.abs(local[:, 0] - 170.0) < 15.0].mean(axis=0)  # cabinet ~160 m, niche ~180 m
        mid = int(np.argmin(((traj.xyz[:, :2] - near[:2]) ** 2).sum(axis=1)))
    else:
        mid = int(np.argmin(np.abs(run.chainage - scene.centreline.length / 2)))
    centre = traj.xyz[mid]
    speed = np.linalg.norm(traj.xyz[mid + 1] - traj.xyz[mid]) * scn.rate_hz
    per_profile = int(points / (25.0 / speed * scn.scanner.profile_rate))
    half = 20.0 / speed  # scan 40 m of track, keep the 25 m square around the middle
    returns = scan(scene, PoseInterpolator(traj), traj.time[mid] - half, traj.time[mid] + half,
                   ScannerSpec(points_per_profile=per_profile), np.random.default_rng(seed + 1))
    xyz = PoseInterpolator(traj).body_to_world(returns.gps_time, returns.p_body)
    keep = (np.abs(xyz[:, :2] - centre[:2]) <= 12.5).all(axis=1)
    axis = traj.xyz[mid + 1] - traj.xyz[mid]
    axis[2] = 0.0
    tile = PointTile(xyz[keep], returns.gps_time[keep], run_id="A", name="sim_A")
    return tile, axis / np.linalg.norm(axis)


def synthetic_tile(points: int, seed: int = 0) -> tuple[PointTile, np.ndarray]:
    density = points / 25.0 / 26.0  # ~26 m^2 of surface per metre of tunnel
    return placed(tunnel_tile(0, 25, density=density, seed=seed), heading_deg=30.0), rotation_z(30) @ [1, 0, 0]


def frame(axis: np.ndarray) -> np.ndarray:
    """Rows: along-track, across-track, up."""
    up = np.array([0.0, 0.0, 1.0])
    return np.array([axis, np.cross(up, axis), up])


def run_pipeline(a, b, truth, F, detector: str, options: dict, descriptor: str = "none",
                 matcher: str = "pair_voting") -> None:
    reg = registry()
    det = reg.create("detector", detector, options)
    desc = reg.create("descriptor", descriptor, {})
    t0 = time.perf_counter()
    ka = det.detect(a)
    t1 = time.perf_counter()
    kb = det.detect(b)
    t2 = time.perf_counter()
    ka, kb = desc.describe(a, ka), desc.describe(b, kb)
    t3 = time.perf_counter()
    off = reg.create("matcher", matcher, {}).match(a, ka, b, kb)
    t4 = time.perf_counter()
    err = F @ (off.d - truth) * 1000
    tm = off.info.get("timings", {})
    label = f"{detector}{'(' + ','.join(f'{k}={v}' for k, v in options.items()) + ')' if options else ''}"
    print(f"{label:70s} kps {len(ka):4d}/{len(kb):4d}  {off.status:12s} err mm "
          f"{err[0]:+6.2f} {err[1]:+6.2f} {err[2]:+6.2f}")
    print(f"    detect {t1 - t0:5.2f} + {t2 - t1:5.2f} s, describe {t3 - t2:5.2f} s, match {t4 - t3:5.2f} s "
          f"(vote {tm.get('vote', 0):.2f}, peaks {tm.get('peaks', 0):.2f}, dense check "
          f"{tm.get('dense_check', 0):.2f}, refine {tm.get('icp_total', tm.get('windows', 0)):.2f}), END TO END {t4 - t0:5.2f} s; "
          f"peak ratio {off.info.get('peak_ratio', float('nan')):.2f}, rival misfit "
          f"{off.info.get('rival_misfit_ratio', float('nan')):.2f}, ties {len(off.ties)}, "
          f"sd mm {np.round(np.sqrt(np.diag(F @ off.cov @ F.T)) * 1000, 2)}")


def vote_700(n: int = 700, repeats: int = 5) -> None:
    """The thesis' exhaustive-pair outlier removal for n keypoints per side, vote only."""
    rng = np.random.default_rng(0)
    a = rng.uniform([0, -3, 0], [25, 3, 5], (n, 3)) + [530000.0, 180000.0, 20.0]
    k = n // 2
    shift = np.array([0.4, -1.2, 0.05])
    b = np.vstack([a[:k] - shift + rng.normal(0, 0.02, (k, 3)), rng.uniform([0, -3, 0], [25, 3, 5], (n - k, 3))
                   + [530000.0, 180000.0, 20.0]])
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        votes = pair_translations(a, b, None, 3.0)
        peaks = find_peaks(votes, 0.1, 5)
        times.append(time.perf_counter() - t)
    err = (peaks[0].d - shift) * 1000
    print(f"vote {n} x {n} keypoints (3 m window): {len(votes):,} pairs, best of {repeats} "
          f"{min(times):.3f} s (median {np.median(times):.3f} s), peak error mm {np.round(err, 1)}")
    # the thesis' way: every pair is a hypothesis, each counts its inliers over all pairs
    all_d = (a[:, None, :] - b[None, :, :]).reshape(-1, 3)
    sample = rng.choice(len(all_d), 200, replace=False)
    t = time.perf_counter()
    for k in sample:  # a benchmark of the slow way, on purpose
        int((((all_d - all_d[k]) ** 2).sum(axis=1) <= 0.01).sum())
    per = (time.perf_counter() - t) / len(sample)
    print(f"    hypothesis by hypothesis (thesis Algorithm 2 over all {len(all_d):,} pairs, numpy): "
          f"{per * 1000:.1f} ms each -> {per * len(all_d) / 3600:.1f} h extrapolated")


def icp_from_offset(a, b, truth, F, ka, kb) -> None:
    """Point-to-plane vs kiss-icp started 0.8 m off along the track (the prototype's test)."""
    start = TileOffset(a.run_id, b.run_id, a.name, b.name, d=truth + 0.8 * F[0], status="ok")
    for opts in ({}, {"method": "kiss"}):
        t = time.perf_counter()
        off = registry().create("matcher", "icp", opts).match(a, ka, b, kb, start)
        err = F @ (off.d - truth) * 1000
        print(f"icp {opts or '(plane)'} from 0.8 m along-track: {off.status}, err mm "
              f"{err[0]:+8.1f} {err[1]:+6.1f} {err[2]:+6.1f} in {time.perf_counter() - t:.2f} s")


def bench_tile(a: PointTile, axis: np.ndarray, label: str, full: bool = True) -> None:
    from railtraj.builtins.iss import PRESETS

    F = frame(axis)
    shift_world = F.T @ SHIFT
    b = second_acquisition(a, shift_world, noise=0.02, seed=1)
    truth = -shift_world
    print(f"\n== {label}: {len(a):,} / {len(b):,} points; errors along / across / up")
    run_pipeline(a, b, truth, F, "iss", {})
    run_pipeline(a, b, truth, F, "iss", PRESETS["tunnel"])
    run_pipeline(a, b, truth, F, "harris3d", {})
    if full:
        run_pipeline(a, b, truth, F, "iss", PRESETS["tunnel"], "fpfh", "mutual_nn")
        det = registry().create("detector", "harris3d", {})
        icp_from_offset(a, b, truth, F, det.detect(a), det.detect(b))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--source", choices=["sim", "synthetic", "auto"], default="auto")
    ap.add_argument("--points", type=int, default=2_000_000)
    args = ap.parse_args()
    vote_700()
    if args.source in ("sim", "auto"):
        try:
            t = time.perf_counter()
            tiles = [(*sim_tile(args.points, featured=True), "railtraj.sim thesis tunnel, tile with a cabinet and a niche", True),
                     (*sim_tile(args.points, featured=False), "railtraj.sim thesis tunnel, ribs and sleepers only", False)]
            print(f"simulated tiles in {time.perf_counter() - t:.1f} s")
        except Exception as exc:  # the simulator is optional here
            if args.source == "sim":
                raise
            print(f"railtraj.sim not usable ({type(exc).__name__}: {exc}); using the numpy tunnel")
            tiles = []
        for a, axis, label, full in tiles:
            bench_tile(a, axis, label, full)
    if args.source == "synthetic" or (args.source == "auto" and not tiles):
        a, axis = synthetic_tile(args.points)
        bench_tile(a, axis, "railtraj.matching.synthetic numpy tunnel (ribs, sleepers, 4 boxes / 12 m)")


if __name__ == "__main__":
    main()
