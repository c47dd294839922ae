"""How freely a run's drift may bend: at least as freely as the run's own reported sd says.

The smoothness observations (:func:`railtraj.adjust.observations.smoothness`) are a prior on the
drift. Pinned at the portals by GNSS, a bend of density ``q`` lets the drift wander from them by a
bridge whose sd grows with ``q`` and with the outage's length (about ``q l^1.5``). Where that
bridge is narrower than the sd the run's own GNSS/INS smoother reports, the adjustment claims a
precision nothing gave it: on tunnels half as long as the demo's, with the same drift, the default
density's bridge was 0.4-0.5x the reported sd, the posterior sd 0.36x, while the corrected runs'
absolute error equalled the reported sd (7.5-10.7 % of epochs beyond 3 posterior sd).

So per outage (a stretch of knots whose reported horizontal sd exceeds ``gnss_sd_m``) and per
axis, the density is raised until the model's own prior sd (smoothness and priors, no data) at
the outage's largest reported sd reaches that sd. It is never lowered: a density fitted to the
bends the tile pairs see was overconfident where none sees them (docs/method.md, variance
components, tried). The smoother's sd is the run's best statement of how far its drift may go;
the model should not be surer than that before it has seen any data.
"""

from __future__ import annotations

from functools import partial

import numpy as np
import scipy.sparse as sp

from railtraj.adjust.solve import BandedSystem

#: the density is raised until the prior's sd is within this factor of the reported sd
TOLERANCE = 1.02
#: at most this many evaluations of the prior per outage and axis (each a banded solve)
MAX_ROUNDS = 20


def bend_density(base: float, knot_metres: np.ndarray, prior_sd: np.ndarray, reported_sd: np.ndarray,
                 gnss_sd_m: float) -> tuple[np.ndarray, list[dict]]:
    """Bend density per smoothness row and axis (n_knots - 2, 3), and the outages it was raised in.

    ``knot_metres`` (n_knots - 1,): metres between consecutive knots; ``prior_sd`` (n_knots, 3):
    the sd of each knot's prior observation (weakened for correlation); ``reported_sd``
    (n_knots, 3): the run's own sd at the knots. Each outage's entry: its first and last knot,
    and per axis the factor applied to ``base``.
    """
    n = len(prior_sd)
    q = np.full((max(n - 2, 0), 3), float(base))
    if n < 3:
        return q, []
    span = (0.5 * (knot_metres[:-1] + knot_metres[1:])) ** 1.5  # as in observations.smoothness
    horizontal = np.sqrt(np.mean(reported_sd[:, :2] ** 2, axis=1))
    outages = []
    for first, last in stretches(horizontal > gnss_sd_m):
        rows = np.arange(max(first - 1, 0), min(last - 1, n - 3) + 1)  # bends centred in the outage
        if not len(rows):
            continue
        raised = np.zeros(len(q), bool)
        raised[rows] = True
        factor = np.ones(3)
        for axis in range(3):
            peak = first + int(np.argmax(reported_sd[first:last + 1, axis]))
            prior_at_peak = partial(_raised_prior_sd, raised=raised, bend_sd=q[:, axis] * span,
                                    prior_sd=prior_sd[:, axis], knot=peak)
            factor[axis] = _raise_until(prior_at_peak, float(reported_sd[peak, axis]))
            q[rows, axis] *= factor[axis]
        if (factor > 1.0).any():
            outages.append({"first_knot": int(first), "last_knot": int(last),
                            "factor": [round(float(f), 3) for f in factor]})
    return q, outages


def _raise_until(sd_at, target: float) -> float:
    """The smallest factor >= 1 at which ``sd_at(factor)`` (increasing) reaches ``target``, to
    within ``TOLERANCE``: grown until it passes, then bisected in log space."""
    low, high, f = 1.0, None, 1.0
    for _ in range(MAX_ROUNDS):
        sd = sd_at(f)
        if sd >= target and (f == 1.0 or sd <= target * TOLERANCE):
            return f
        if sd < target:
            low = f
        else:
            high = f
        # the prior's sd grows more slowly than the density where the priors also hold it
        f = f * (target / sd) ** 1.5 if high is None else float(np.sqrt(low * high))
    return high if high is not None else f


def _raised_prior_sd(factor: float, raised: np.ndarray, bend_sd: np.ndarray, prior_sd: np.ndarray,
                     knot: int) -> float:
    """The prior's marginal sd at ``knot`` with the ``raised`` bends' sd times ``factor``."""
    return float(_prior_marginal_sd(np.where(raised, factor, 1.0) * bend_sd, prior_sd)[knot])


def stretches(mask: np.ndarray) -> list[tuple[int, int]]:
    """First and last index of each run of True in ``mask`` (outages, spans without data)."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    return [(int(a), int(b) - 1) for a, b in zip(edges[0::2], edges[1::2], strict=True)]


def _prior_marginal_sd(bend_sd: np.ndarray, prior_sd: np.ndarray) -> np.ndarray:
    """Marginal sd of each knot under the second differences (sd ``bend_sd``) and the priors
    (sd ``prior_sd``) alone, one axis: the diagonal of a pentadiagonal matrix's inverse."""
    n = len(prior_sd)
    D = sp.diags([np.ones(n - 2), -2.0 * np.ones(n - 2), np.ones(n - 2)], [0, 1, 2], shape=(n - 2, n))
    N = D.T @ sp.diags(1.0 / bend_sd**2) @ D + sp.diags(1.0 / prior_sd**2)
    system = BandedSystem(N, perm=np.arange(n))
    idx = np.arange(n)
    return np.sqrt(system.covariance(idx, idx, system.covariance_blocks()))
