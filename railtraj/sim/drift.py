"""The GNSS/INS error model: what the smoothed trajectory a surveyor receives gets wrong.

Under open sky the solution is good: a small, smooth noise. In a tunnel the INS runs free between
two GNSS fixes; a forward-backward smoother ties both ends, so the error is zero at the portals
and largest in the middle. Each outage gets a smooth drift of envelope ``(4 u (1 - u))^1.5``
(``u`` = fraction of the outage) with a random horizontal direction and wander, scaled so its
peak is a random fraction of the configured maximum. The reported sd follows the same envelope,
like a smoother's RMS. Hazards the sd does not show: a multipath bias at one portal (carried into
the tunnel and decaying to the far portal) and a constant heading bias.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

from railtraj.data import Trajectory


@dataclass(frozen=True)
class Multipath:
    """A GNSS multipath bias at the ``portal``-th portal ``run_id`` passes (0 = the first).

    ``bias`` is east, north, up in metres; it builds up over ``ramp`` metres of open sky before
    the portal and fades linearly to zero at the end of the outage behind it.
    """

    run_id: str
    portal: int = 0
    bias: tuple[float, float, float] = (0.25, -0.2, 0.08)
    ramp: float = 40.0


@dataclass(frozen=True)
class DriftSpec:
    """Error model settings; lengths in metres, times in seconds."""

    max_horizontal: float = 1.5
    max_vertical: float = 0.2
    min_fraction: float = 0.6
    open_noise: tuple[float, float, float] = (0.008, 0.008, 0.012)
    open_noise_tau: float = 1.0
    sd_open: tuple[float, float, float] = (0.015, 0.015, 0.025)
    sd_scale: float = 0.5
    roughness: float = 0.0          # an integrated random walk this large against the smooth drift (0: none)
    heading_bias_deg: float = 0.0
    heading_bias_runs: tuple[str, ...] = ()
    multipath: tuple[Multipath, ...] = ()
    # every outage's drift direction turned by this (degrees): with the alignment's heading turned
    # as much, the errors stay the same in the track's frame (a heading is then tried on its own)
    azimuth_turn_deg: float = 0.0


def outages(open_sky: np.ndarray) -> list[tuple[int, int]]:
    """Index ranges ``[i0, i1)`` of consecutive epochs without sky."""
    covered = np.concatenate([[False], ~np.asarray(open_sky, dtype=bool), [False]])
    edges = np.flatnonzero(np.diff(covered.astype(np.int8)))
    return [(int(a), int(b)) for a, b in zip(edges[0::2], edges[1::2], strict=True)]


def envelope(n: int, open_start: bool = True, open_end: bool = True) -> np.ndarray:
    """Growth of the smoothed INS error over an outage of ``n`` epochs, peak 1.

    With GNSS at both ends it is ``(4 u (1 - u))^1.5``; with GNSS at one end only (the run starts
    or ends inside), it grows from that end.
    """
    u = (np.arange(n) + 0.5) / n
    if open_start and open_end:
        return (4 * u * (1 - u)) ** 1.5
    if open_start:
        return u ** 1.5
    if open_end:
        return (1 - u) ** 1.5
    return np.ones(n)


def _smooth_noise(n: int, dt: float, tau: float, rng: np.random.Generator) -> np.ndarray:
    """Unit-variance noise (n, 3), exponentially correlated over ``tau`` seconds (white if 0)."""
    w = rng.standard_normal((n, 3))
    if tau <= 0:
        return w
    a = np.exp(-dt / tau)
    x = lfilter([np.sqrt(1 - a * a)], [1, -a], w, axis=0)
    return x


def _bridged_walk(n: int, env: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """An integrated random walk (n, 3) (white acceleration, as an INS's velocity error wanders)
    that is zero where the outage meets open sky, tapered like ``env``: drift whose rate changes
    everywhere, not only on the smooth envelope's scale."""
    u = np.linspace(0, 1, n)[:, None]
    walk = np.cumsum(np.cumsum(rng.standard_normal((n, 3)), axis=0), axis=0)
    start_open, end_open = env[0] < 0.5, env[-1] < 0.5
    if start_open and end_open:
        walk -= walk[0] + u * (walk[-1] - walk[0])
    elif start_open:
        walk -= walk[0]
    elif end_open:
        walk -= walk[-1]
    return walk * np.cbrt(env)[:, None]


def _outage_drift(n: int, env: np.ndarray, spec: DriftSpec, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """One outage's drift (n, 3): envelope x (constant direction + a slow wander), scaled."""
    u = np.linspace(0, 1, n)
    az = rng.uniform(0, 2 * np.pi) + np.radians(spec.azimuth_turn_deg)
    wander = rng.uniform(0.0, 0.4) * np.sin(2 * np.pi * rng.uniform(0.5, 1.5) * u + rng.uniform(0, 2 * np.pi))
    horiz = env[:, None] * (np.array([np.sin(az), np.cos(az)]) + wander[:, None]
                            * np.array([np.cos(az), -np.sin(az)]))
    vert = env * (rng.choice([-1.0, 1.0]) + 0.3 * np.sin(2 * np.pi * rng.uniform(0.5, 1.5) * u))
    if spec.roughness > 0:
        walk = _bridged_walk(n, env, rng)
        horiz += walk[:, :2] * (spec.roughness * np.linalg.norm(horiz, axis=1).max()
                                / max(np.linalg.norm(walk[:, :2], axis=1).max(), 1e-12))
        vert += walk[:, 2] * (spec.roughness * np.abs(vert).max() / max(np.abs(walk[:, 2]).max(), 1e-12))
    peak_h = rng.uniform(spec.min_fraction, 1.0) * spec.max_horizontal
    peak_v = rng.uniform(spec.min_fraction, 1.0) * spec.max_vertical
    horiz *= peak_h / max(np.linalg.norm(horiz, axis=1).max(), 1e-12)
    vert *= peak_v / max(np.abs(vert).max(), 1e-12)
    return np.column_stack([horiz, vert]), {"peak_horizontal": peak_h, "peak_vertical": peak_v}


def _multipath(mp: Multipath, chainage: np.ndarray, open_sky: np.ndarray,
               spans: list[tuple[int, int]]) -> tuple[np.ndarray, dict]:
    """Weight (n,) of a multipath bias at one portal crossing: ramp before, linear fade after."""
    n = len(chainage)
    w = np.zeros(n)
    crossings = sorted([(a, a, b, "entry") for a, b in spans if a > 0]
                       + [(b - 1, a, b, "exit") for a, b in spans if b < n])
    if mp.portal >= len(crossings):
        return w, {"applied": False}
    k, a, b, kind = crossings[mp.portal]
    dist = np.abs(chainage - chainage[k])
    outside = np.zeros(n, dtype=bool)
    outside[:a] = kind == "entry"
    outside[b:] = kind == "exit"
    ramp = outside & open_sky & (dist < mp.ramp)
    w[ramp] = 0.5 * (1 + np.cos(np.pi * dist[ramp] / mp.ramp))
    fade = np.linspace(1.0, 0.0, b - a) if kind == "entry" else np.linspace(0.0, 1.0, b - a)
    w[a:b] = fade
    return w, {"applied": True, "portal_chainage": float(chainage[k]), "kind": kind,
               "bias": list(mp.bias)}


def drift(true: Trajectory, chainage: np.ndarray, open_sky: np.ndarray, spec: DriftSpec,
          rng: np.random.Generator) -> tuple[Trajectory, dict]:
    """The trajectory a surveyor would receive for ``true``, with its reported sd, and a summary
    of the errors put in (JSON-ready)."""
    n = len(true)
    dt = float(np.median(np.diff(true.time)))
    env_all = np.zeros(n)
    err = np.zeros((n, 3))
    info: dict = {"outages": []}
    spans = outages(open_sky)
    for a, b in spans:
        env = envelope(b - a, a > 0, b < n)
        d, peaks = _outage_drift(b - a, env, spec, rng)
        err[a:b] += d
        env_all[a:b] = env
        info["outages"].append({"t0": float(true.time[a]), "t1": float(true.time[b - 1]),
                                "chainage": [float(chainage[a]), float(chainage[b - 1])], **peaks})
    noise = _smooth_noise(n, dt, spec.open_noise_tau, rng) * np.asarray(spec.open_noise)
    err += noise * (1.0 - env_all)[:, None]
    for mp in spec.multipath:
        if mp.run_id == true.run_id:
            w, mp_info = _multipath(mp, chainage, open_sky, spans)
            err += w[:, None] * np.asarray(mp.bias)
            info["multipath"] = mp_info
    rpy = true.rpy.copy()
    if spec.heading_bias_deg and (not spec.heading_bias_runs or true.run_id in spec.heading_bias_runs):
        rpy[:, 2] = np.mod(rpy[:, 2] + spec.heading_bias_deg, 360.0)
        info["heading_bias_deg"] = spec.heading_bias_deg
    peak = np.array([spec.max_horizontal, spec.max_horizontal, spec.max_vertical]) * spec.sd_scale
    sd = np.asarray(spec.sd_open) + env_all[:, None] * peak
    info["max_error_horizontal"] = float(np.linalg.norm(err[:, :2], axis=1).max())
    info["max_error_vertical"] = float(np.abs(err[:, 2]).max())
    return Trajectory(true.time, true.xyz + err, rpy, sd, true.run_id), info
