"""A GNSS bias as its own state beside the drift: bounded, and fading back to zero along the track.

Where :mod:`railtraj.sd_check` finds a run's GNSS biased (multipath or a float solution at a
portal, while the SBET still claims 2 cm), the run's error is not the INS drift the smoothness
models. GNSS/INS filters carry such an error as a first-order Gauss-Markov state: of known sd,
correlated over a length, reverting to zero beyond it. So does the adjustment:

    c_r(t) = d_r(t) + b_r(t),      b_r(knot) = S(knot) u(knot)

``d`` is the drift (the run's prior at its reported sd and the smoothness act on ``d = c - b``),
``u`` a unit first-order Gauss-Markov process along the track (``u_0 ~ N(0, I)``,
``u_{k+1} = phi u_k + w``, ``phi = exp(-h / correlation_m)``), and ``S S^T`` the share of the
covariance the sd check widened the run by (its disagreement with the other runs, in the track
frame) that is GNSS's (:func:`gnss_share`), times ``gnss_bias_sd_scale``^2 (2: with one
disagreement's sd the prior shaved a multipath peak by a centimetre). ``b`` bends no more
freely than the freed drift (its second differences at the drift's bend density times
``max_bend_widening``): a first-order process alone wandered between weak pairs in the tunnel
behind a portal (3.7 -> 8.6 cm on the full-size mixed survey with a portal bias). Ties and tile
offsets see ``c`` alone: the bias knots enter only the run's own model rows.

What it changes, against widening the prior and freeing the bend (the earlier treatment, kept
where the run's sd is the smoother's drift): the drift stays held by the GNSS sd the run
reports, and past the last observation of a freed run the bias fades back towards zero over
``correlation_m`` (the smoothness alone extrapolates linearly: at a survey's free end that put a
run 7.5-21 cm off where its GNSS was right to 2 cm; the bias' own smoothness still carries some
of the last rate on), while the corrected sd grows back towards the bias' sd (docs/method.md,
"Session 55").
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import scipy.sparse as sp

from railtraj.adjust.model import CorrectionModel
from railtraj.adjust.observations import Block, assemble


def gnss_share(gnss_like: np.ndarray, knot_distance: np.ndarray, correlation_m: float,
               widened: np.ndarray) -> np.ndarray:
    """Per knot, the share (0-1) of a run's widening taken as a GNSS bias: ``gnss_like`` (1 where
    its reported sd is GNSS's, 0 where it is the smoother's drift), carried into an outage and
    fading over ``correlation_m``: a bias at the portal is where the smoother's bridge starts, so
    it does not stop at the first knot without GNSS (cut there, the drift had to turn by the
    whole bias within 5 m: 5-11 cm off on portal surveys). Computed at the ``widened`` knots only
    (elsewhere 0): tens to hundreds of them against all the run's knots."""
    share = np.zeros(len(gnss_like))
    rows = np.flatnonzero(widened)
    apart = np.abs(knot_distance[rows, None] - knot_distance[None, :])
    share[rows] = np.max(gnss_like[None, :] * np.exp(-apart / correlation_m), axis=1, initial=0.0)
    return share


def bias_scale(covariance: np.ndarray) -> np.ndarray:
    """``S`` (n_knots, 3, 3) with ``S S^T`` = the bias' ``covariance`` (n_knots, 3, 3)."""
    vals, vecs = np.linalg.eigh(covariance)
    return vecs * np.sqrt(np.maximum(vals, 0.0))[:, None, :]


def on_drift(block: Block, to_bias: sp.csr_matrix) -> Block:
    """``block``'s rows on a run's correction ``c`` turned into rows on its drift ``c - b``:
    every coefficient ``a`` of ``c(knot)`` gains ``-a S(knot)`` on ``u(knot)``. ``to_bias``: the
    run's :func:`bias_map`."""
    return replace(block, A=sp.csr_matrix(block.A - block.A @ to_bias), per_axis=None)


def on_bias(block: Block, to_bias: sp.csr_matrix) -> Block:
    """``block``'s rows on a run's correction ``c`` moved onto its bias ``b = S u`` (a
    smoothness of the bias itself). ``to_bias``: the run's :func:`bias_map`."""
    return replace(block, A=sp.csr_matrix(block.A @ to_bias), per_axis=None)


def bias_map(model: CorrectionModel, run_id: str, scale: np.ndarray) -> sp.csr_matrix:
    """The map from a run's correction unknowns to its bias ``S u``: ``S(knot)`` (``scale``,
    (n_knots, 3, 3)) at (correction knot, bias knot)."""
    rk, first = model.runs[run_id], model.bias_first[run_id]
    k = np.arange(rk.count)
    i, j = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
    rows = (3 * (rk.first + k)[:, None, None] + i).ravel()
    cols = (3 * (first + k)[:, None, None] + j).ravel()
    return sp.csr_matrix((scale.ravel(), (rows, cols)), shape=(model.n_unknowns, model.n_unknowns))


def gauss_markov(model: CorrectionModel, run_id: str, correlation_m: float) -> Block:
    """The unit bias process' own rows: ``u_0 = 0`` and ``u_{k+1} - phi_k u_k = 0`` with sd 1 and
    ``sqrt(1 - phi_k^2)``, ``phi_k = exp(-h_k / correlation_m)`` over the ``h_k`` metres between
    knots: stationary, of unit sd at every knot."""
    first, count = model.bias_first[run_id], model.runs[run_id].count
    phi = np.exp(-model.knot_metres(run_id) / correlation_m)
    k = first + np.arange(count - 1)
    knots = np.vstack([[first, first], np.column_stack([k, k + 1])])
    w = np.vstack([[1.0, 0.0], np.column_stack([-phi, np.ones(count - 1)])])
    sd = np.concatenate([[1.0], np.sqrt(np.maximum(1.0 - phi**2, 1e-12))])
    whiten = np.einsum("n,ij->nij", 1.0 / sd, np.eye(3))
    return assemble("gnss_bias", model.n_unknowns, knots, w, np.zeros((count, 3)), whiten, robust=False)


def estimated_bias(model: CorrectionModel, run_id: str, scale: np.ndarray, x: np.ndarray) -> dict:
    """The GNSS bias the adjustment found in a run, for metrics.json: the largest (horizontal norm)
    at a knot, as the run's position minus the truth (``-b``: the correction removes it; m, x/y/z),
    its ``time_s``, and how many metres of the run carry a bias above 2 cm. ``x``: the solution."""
    rk, first = model.runs[run_id], model.bias_first[run_id]
    bias = -np.einsum("nij,nj->ni", scale, x[3 * first:3 * (first + rk.count)].reshape(-1, 3))
    k = int(np.argmax(np.linalg.norm(bias[:, :2], axis=1)))
    above = np.linalg.norm(bias, axis=1) > 0.02
    metres = np.concatenate([np.diff(rk.knot_distance), [0.0]])
    return {"largest_m": [round(float(v), 4) for v in bias[k]], "time_s": round(float(rk.knot_time[k]), 2),
            "metres_above_2cm": round(float(metres[above].sum()), 1)}
