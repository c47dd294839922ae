"""Speed of the global adjustment (``optimizer=spline``) at survey scale.

3 runs x 1 h at 200 Hz (720 000 epochs each) along a 36 km line at 10 m/s, 1 M ties between the
runs (weights 1/n per 25 m tile pair), 1 % of them wrong: build, robust solve and posterior sd.

    .venv/bin/python benchmarks/bench_adjust.py [--hours 1] [--ties 1000000]
"""

from __future__ import annotations

import argparse
import logging
import resource
import time

import numpy as np

from railtraj.data import Ties, Trajectory
from railtraj.plugins import registry


def make_run(run_id: str, hours: float, rate: float, speed: float, t0: float, rng) -> tuple[Trajectory, object]:
    t = t0 + np.arange(0, hours * 3600, 1 / rate)
    s = (t - t0) * speed
    err = np.column_stack([0.5 * np.sin(s / 900 + rng.uniform(0, 6)), 0.4 * np.sin(s / 1300 + rng.uniform(0, 6)),
                           0.05 * np.sin(s / 700)])
    true = np.column_stack([500000 + s, np.full_like(s, 180000.0), np.full_like(s, 10.0)])
    rpy = np.tile([0.0, 0.0, 90.0], (len(t), 1))
    sd = np.full((len(t), 3), 0.5)
    return Trajectory(t, true + err, rpy, sd, run_id=run_id), (t0, speed, err, s)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=1.0)
    ap.add_argument("--ties", type=int, default=1_000_000)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    rng = np.random.default_rng(0)
    runs = {r: make_run(r, args.hours, 200.0, 10.0, t0, rng) for r, t0 in (("a", 0.0), ("b", 1e4), ("c", 2e4))}
    length = args.hours * 3600 * 10.0
    ties = []
    per_pair = args.ties // 2
    for other in ("b", "c"):  # every run against the reference run a
        s = np.sort(rng.uniform(10, length - 10, per_pair))
        (ta0, va, ea, sa), (tb0, vb, eb, sb) = runs["a"][1], runs[other][1]
        feat = np.column_stack([500000 + s, 180000 + rng.uniform(-3, 3, len(s)), 10 + rng.uniform(-1, 4, len(s))])
        xa = feat + np.column_stack([np.interp(s, sa, ea[:, k]) for k in range(3)])
        xb = feat + np.column_stack([np.interp(s, sb, eb[:, k]) for k in range(3)])
        xb += rng.normal(0, 0.003, xb.shape)
        wrong = rng.random(len(s)) < 0.01
        xb[wrong, 0] += 3.0
        ties.append(Ties("a", other, ta0 + s / va, tb0 + s / vb, xa, xb, np.full(len(s), 1 / 20)))
    trajs = {r: v[0] for r, v in runs.items()}
    opt = registry().create("optimizer", "spline", {})
    t = time.perf_counter()
    out = opt.optimize(trajs, ties, [])
    wall = time.perf_counter() - t
    s = np.linspace(100, length - 100, 5000)
    errs = []
    for r in ("b", "c"):
        (t0, v, e, sr), (ta0, va, ea, sa) = runs[r][1], runs["a"][1]
        ca = out["a"].interpolate(ta0 + s / va)[0] - trajs["a"].interpolate(ta0 + s / va)[0]
        cr = out[r].interpolate(t0 + s / v)[0] - trajs[r].interpolate(t0 + s / v)[0]
        ea_s = np.column_stack([np.interp(s, sa, ea[:, k]) for k in range(3)])
        er_s = np.column_stack([np.interp(s, sr, e[:, k]) for k in range(3)])
        errs.append((ea_s + ca) - (er_s + cr))
    rms = float(np.sqrt(np.mean(np.sum(np.vstack(errs) ** 2, axis=1))))
    d = opt.diagnostics
    print(f"epochs {sum(len(v) for v in trajs.values())}, ties {sum(len(x) for x in ties)}, knots {d['knots']}, "
          f"bandwidth {d['bandwidth']}, GNC iterations {d['gnc_iterations']}")
    print(f"solve incl. sd: {wall:.1f} s; ties rejected {d['observations']['tie']['rejected']}; "
          f"inter-run RMS after {rms * 1000:.1f} mm; peak memory "
          f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")


if __name__ == "__main__":
    main()
