"""GNSS at a tunnel portal: a bias every run may share, which no relative observation shows.

Passing from open sky into a tunnel (or out of it), a receiver loses the satellites behind the
portal wall and picks up reflections from it, and the smoother may still call its solution good.
The thesis (section 4.2.3, figures 4.19-4.21) found its one failure there: a metre-level
misalignment near a tunnel entrance, "GNSS data deteriorated due to the sudden change from the
open sky to the indoor environment, which was still used as a reliable observation", in both runs
(larger in run 1). Runs through one portal minutes apart see nearly the same satellites and the
same wall, so they can share the bias; then every tile pair and every same-track comparison
agrees, :mod:`railtraj.sd_check` has nothing to convict, and the corrected sd repeats the
centimetres the runs report. Held-out commensurate 4803 (two runs biased alike at one portal):
0.38 m off at 1.2 cm reported, 15.5 % of epochs beyond 3 sd, worst 32 sd.

So the corrected sd of every run keeps ``sd_m`` (per axis, in quadrature) within ``reach_m`` of
each place where its reported sd passes between GNSS quality and an outage, fading out over
``fade_m`` beyond, except near control, which the adjustment follows instead. Positions are not
changed: only the sd (and so the anchors' weights) says that the GNSS there is unverified.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from railtraj.data import Trajectory, reports_gnss


@dataclass
class PortalOptions:
    sd_m: float = 0.10          # sd (per axis) a portal's GNSS keeps in the corrected sd (0: none)
    reach_m: float = 40.0       # metres of the run either side of the portal it is kept over ...
    fade_m: float = 40.0        # ... fading out over so many metres beyond
    gnss_sd_m: float = 0.10     # a run reports GNSS where its horizontal sd is at most this


def portal_weight(traj: Trajectory, options: PortalOptions, control_at: np.ndarray | None = None) -> np.ndarray:
    """Per epoch of ``traj``, 1 within ``reach_m`` (along its path) of a portal, where its reported
    horizontal sd passes ``gnss_sd_m``, fading linearly to 0 over ``fade_m`` beyond; 0 near
    control (within ``reach_m`` in plan, back to 1 over ``fade_m``)."""
    crossing = _crossings(traj, options)
    if not len(crossing):
        return np.zeros(len(traj))
    path = traj.travelled()
    # the portals along the path (increasing: it only grows), between two sentinels
    at = np.concatenate([[-np.inf], 0.5 * (path[crossing] + path[crossing + 1]), [np.inf]])
    after = np.searchsorted(at, path)
    nearest = np.minimum(path - at[after - 1], at[after] - path)
    weight = _fade(nearest, options)
    if control_at is not None and len(control_at):
        to_control, _ = cKDTree(np.asarray(control_at)[:, :2]).query(traj.xyz[:, :2])
        weight *= 1.0 - _fade(to_control, options)
    return weight


def with_portal_sd(corrected: dict[str, Trajectory], reported: dict[str, Trajectory], options: PortalOptions,
                   control_at: np.ndarray | None = None) -> tuple[dict[str, Trajectory], dict, str]:
    """The ``corrected`` runs with ``sd_m`` added in quadrature to their sd near the portals of
    the ``reported`` runs (:func:`portal_weight`); metrics (per run: portals, epochs widened) and a
    note ('' when nothing was widened)."""
    if not options.sd_m > 0:
        return corrected, {"sd_m": 0.0}, ""
    out, per_run = dict(corrected), {}
    for run, traj in sorted(corrected.items()):
        source = reported.get(run, traj)
        if traj.sd is None or source.sd is None:
            continue
        weight = np.interp(traj.time, source.time, portal_weight(source, options, control_at))
        if not weight.any():
            continue
        sd = np.sqrt(traj.sd ** 2 + (options.sd_m * weight[:, None]) ** 2)
        out[run] = traj.with_positions(traj.xyz, sd)
        per_run[run] = {"portals": len(_crossings(source, options)), "epochs": int((weight > 0).sum())}
    metrics = {"sd_m": options.sd_m, "reach_m": options.reach_m, "fade_m": options.fade_m, "runs": per_run}
    if not per_run:
        return out, metrics, ""
    note = (f"GNSS at the portals ({sum(r['portals'] for r in per_run.values())} crossings of "
            f"{len(per_run)} run(s)) is unverified where there is no control: runs through one portal can "
            f"share a multipath bias no tile pair shows, so the corrected sd there keeps {options.sd_m:.2f} m "
            f"per axis over {options.reach_m:.0f} m either side (pipeline.portal; control there settles it)")
    return out, metrics, note


def _crossings(traj: Trajectory, options: PortalOptions) -> np.ndarray:
    """Indices ``i`` where the run's reported horizontal sd passes ``gnss_sd_m`` between epochs
    ``i`` and ``i + 1``: its portals (none without sd)."""
    if traj.sd is None or len(traj) < 2:
        return np.zeros(0, dtype=np.int64)
    gnss = reports_gnss(traj.sd, options.gnss_sd_m)
    return np.flatnonzero(gnss[1:] != gnss[:-1])


def _fade(distance: np.ndarray, options: PortalOptions) -> np.ndarray:
    """1 within ``reach_m``, linearly to 0 at ``reach_m + fade_m``."""
    return np.clip(1.0 - (distance - options.reach_m) / max(options.fade_m, 1e-9), 0.0, 1.0)


__all__ = ["PortalOptions", "portal_weight", "with_portal_sd"]
