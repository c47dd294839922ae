"""Scoring against the truth: how wrong are trajectories, how well do clouds agree.

* :func:`score_trajectories`: absolute position error per run (RMS, max, horizontal/vertical,
  per chainage bin) and inter-run consistency: the difference of two runs' errors at the same
  chainage, which is what misaligns their clouds.
* :func:`c2c`: cloud-to-cloud distances from sampled points of one cloud to a local plane fitted
  to their nearest neighbours in the other (robust to point spacing, unlike plain
  nearest-neighbour distance, which is also reported).

Everything returned is plain JSON (floats, lists, dicts).
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy.spatial import cKDTree

from railtraj.data import Trajectory


def _stats(err: np.ndarray) -> dict:
    """RMS, max and mean of (n, 3) east/north/up errors, split horizontal/vertical."""
    if not len(err):
        return {"n": 0}
    h, v = np.linalg.norm(err[:, :2], axis=1), np.abs(err[:, 2])
    d = np.linalg.norm(err, axis=1)
    rms = lambda x: float(np.sqrt(np.mean(x ** 2)))  # noqa: E731
    return {"n": int(len(err)), "rms_3d": rms(d), "rms_h": rms(h), "rms_v": rms(v),
            "max_3d": float(d.max()), "max_h": float(h.max()), "max_v": float(v.max()),
            "mean": [float(x) for x in err.mean(axis=0)]}


def position_error(truth: Trajectory, est: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """Errors (n, 3) = est - truth at the estimate's epochs within the truth's span, and a mask
    of the estimate's epochs used."""
    ok = truth.covers(est.time)
    true_xyz = np.column_stack([np.interp(est.time[ok], truth.time, truth.xyz[:, k]) for k in range(3)])
    return est.xyz[ok] - true_xyz, ok


def chainage_from_truth(truth: dict[str, Trajectory]) -> dict[str, np.ndarray]:
    """A common along-track coordinate when none is given: distance along the first run's true
    path, carried to the other runs by nearest true position in plan."""
    ref = truth[sorted(truth)[0]]
    dist = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(ref.xyz[:, :2], axis=0), axis=1))])
    tree = cKDTree(ref.xyz[:, :2])
    return {r: dist[tree.query(t.xyz[:, :2], workers=-1)[1]] for r, t in truth.items()}


def _bins(ch: np.ndarray, err: np.ndarray, bin_m: float) -> list[dict]:
    """Error statistics per chainage bin."""
    k = np.floor(ch / bin_m).astype(np.int64)
    out = []
    for b in np.unique(k):
        m = k == b
        s = _stats(err[m])
        out.append({"chainage": float((b + 0.5) * bin_m), "rms_h": s["rms_h"], "rms_v": s["rms_v"],
                    "max_h": s["max_h"], "max_v": s["max_v"]})
    return out


def score_trajectories(truth: dict[str, Trajectory], est: dict[str, Trajectory],
                       chainage: dict[str, np.ndarray] | None = None, bin_m: float = 50.0,
                       max_pairs_epochs: int = 5000) -> dict:
    """Score estimated trajectories against the truth (runs present in both).

    ``chainage`` (per truth epoch, per run) places runs along the line for the per-bin figures
    and for consistency; without it, :func:`chainage_from_truth` is used.
    """
    runs = sorted(set(truth) & set(est))
    chainage = chainage if chainage is not None else chainage_from_truth({r: truth[r] for r in runs})
    per_run, errs, all_err = {}, {}, []
    for r in runs:
        err, ok = position_error(truth[r], est[r])
        ch = np.interp(est[r].time[ok], truth[r].time, chainage[r])
        errs[r] = (est[r].time[ok], ch, err)
        all_err.append(err)
        per_run[r] = {**_stats(err), "bins": _bins(ch, err, bin_m)}
    pairs = {}
    for a, b in itertools.combinations(runs, 2):
        ta, cha, ea = errs[a]
        tb, chb, eb = errs[b]
        step = max(1, len(ta) // max_pairs_epochs)
        order = np.argsort(chb)
        inside = (cha >= chb.min()) & (cha <= chb.max())
        sel = np.flatnonzero(inside)[::step]
        eb_at = np.column_stack([np.interp(cha[sel], chb[order], eb[order, k]) for k in range(3)])
        pairs[f"{a}~{b}"] = _stats(ea[sel] - eb_at)
    return {"runs": per_run, "overall": _stats(np.concatenate(all_err)) if all_err else {"n": 0},
            "consistency": pairs, "bin_m": bin_m}


def c2c(points_a: np.ndarray, points_b: np.ndarray, max_dist: float = 1.0, n_sample: int = 100_000,
        k: int = 8, seed: int = 0) -> dict:
    """Cloud-to-cloud distance from (a sample of) ``points_a`` to ``points_b``.

    ``median``/``p95``/``mean`` are distances to the plane through each sample's ``k`` nearest
    neighbours in B; ``nn_*`` the plain nearest-neighbour distances. Samples with no neighbour
    within ``max_dist`` do not overlap and are left out (``overlap`` is their complement).
    """
    a, b = np.asarray(points_a, dtype=float), np.asarray(points_b, dtype=float)
    if not len(a) or len(b) < k:
        return {"n": 0, "overlap": 0.0}
    rng = np.random.default_rng(seed)
    sample = a[rng.choice(len(a), n_sample, replace=False)] if len(a) > n_sample else a
    shift = b.mean(axis=0)
    tree = cKDTree(b - shift)
    dist, idx = tree.query(sample - shift, k=k, distance_upper_bound=max_dist, workers=-1)
    full = np.isfinite(dist).all(axis=1)
    nn = dist[np.isfinite(dist[:, 0]), 0]
    if not full.any():
        return {"n": 0, "overlap": float(len(nn) / len(sample))}
    nb = b[idx[full]] - shift                                   # (m, k, 3)
    centre = nb.mean(axis=1)
    x = nb - centre[:, None]
    _, vec = np.linalg.eigh(np.einsum("mki,mkj->mij", x, x))
    normal = vec[:, :, 0]
    d = np.abs(np.einsum("mi,mi->m", sample[full] - shift - centre, normal))
    return {"n": int(full.sum()), "overlap": float(len(nn) / len(sample)),
            "median": float(np.median(d)), "p95": float(np.percentile(d, 95)),
            "mean": float(d.mean()), "nn_median": float(np.median(nn)),
            "nn_p95": float(np.percentile(nn, 95))}


def tie_errors(truth: dict[str, Trajectory], delivered: dict[str, Trajectory], ties, poses=None) -> np.ndarray:
    """Error (n, 3) east/north/up of each tie's offset ``xyz_a - xyz_b`` against the true one.

    The object run b measured at ``xyz_b`` (time ``time_b``) truly lies at ``X`` (b's delivered
    trajectory swapped for its true one); run a, measuring it at ``time_a``, put it at ``X``
    moved by a's drift then. The true offset is that point minus ``xyz_b``; the error is
    ``xyz_a`` minus that point. Exact for the simulator, whose errors are trajectory errors.
    ``poses`` (a :class:`railtraj.georef.PoseCache`) serves many tie sets of the same runs.
    """
    from railtraj.georef import regeoreference_points

    x_true = regeoreference_points(ties.xyz_b, ties.time_b, delivered[ties.run_b], truth[ties.run_b], poses)
    a_true = regeoreference_points(x_true, ties.time_a, truth[ties.run_a], delivered[ties.run_a], poses)
    return ties.xyz_a - a_true


def offset_errors(truth: dict[str, Trajectory], delivered: dict[str, Trajectory], offsets) -> dict:
    """Error (east, north, up) of every ``ok`` tile-pair offset, keyed by the offset's position in
    ``offsets``: the weighted mean of its ties' errors (its estimate where its features are), or
    for a pair without ties (resolved jointly along the track) the error at its reference point."""
    from railtraj.data import Ties
    from railtraj.georef import PoseCache

    out, poses = {}, PoseCache()
    for k, o in enumerate(offsets):
        if o.status != "ok":
            continue
        if o.ties is not None and len(o.ties):
            out[k] = np.average(tie_errors(truth, delivered, o.ties, poses), axis=0, weights=o.ties.weight)
        elif "ref_point" in o.info.get("piecewise", {}):  # an offset observed at its reference point
            xyz_b = np.array([o.info["piecewise"]["ref_point"]])
            tie = Ties(o.run_a, o.run_b, [o.info["time_a"]], [o.info["time_b"]], xyz_b + o.d, xyz_b, [1.0])
            out[k] = tie_errors(truth, delivered, tie, poses)[0]
    return out


def score_offsets(truth: dict[str, Trajectory], delivered: dict[str, Trajectory], offsets) -> dict:
    """How far the ``ok`` tile-pair offsets are from the truth, where their ties are.

    Per ok pair the error is :func:`offset_errors`; reported as RMS and max per axis (east,
    north, up), and the share of pairs within 1 cm on every axis.
    """
    per_pair = offset_errors(truth, delivered, offsets)
    if not per_pair:
        return {"ok_pairs": 0}
    e = np.array(list(per_pair.values()))
    return {"ok_pairs": len(e), "rms_m": np.sqrt((e**2).mean(axis=0)).tolist(),
            "max_abs_m": np.abs(e).max(axis=0).tolist(),
            "within_1cm": float((np.abs(e) <= 0.01).all(axis=1).mean())}
