"""Observations of the corrections as whitened rows of one sparse linear system.

Every observation is a 3-vector ``sum_j w_j c(knot_j) = v`` with covariance ``C``. It becomes three
rows ``W (sum_j w_j c_j) = W v`` with ``W^T W = C^-1`` (rows of ``W`` may be zero: a direction the
observation does not constrain). All are built at once with numpy broadcasting, never one
observation at a time, and stacked into a :class:`Block` per kind:

* ``prior``: ``c_r(knot) = 0`` with the trajectory's reported sd (pinned where GNSS was good);
* ``smoothness``: second differences of consecutive knots ``= 0`` (changes of drift rate, not
  the drift itself, are penalised), sd from a drift model (see :func:`smoothness`);
* ``tie``: ``c_b(t_b) - c_a(t_a) = x_a - x_b`` (a feature seen by two runs);
* ``offset``: a weak tile pair ``c_b(t_b) - c_a(t_a) = d`` in its constrained directions only;
* ``drift_rate``: how an unresolved pair's ``c_b - c_a`` changes between the ends of its windows,
  along the track only (whatever alias the pair sits on);
* ``control``: ``c_r(t) = X - seen`` (a surveyed point seen in a run's cloud).

Each block also carries an information weight per observation (a tie of a pair with n ties
weighs 1/n) kept apart from the whitening, so that the robust test in :mod:`railtraj.adjust.solve`
judges a residual by the observation's own sd, whatever its weight.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from railtraj.adjust.model import CorrectionModel


@dataclass
class Block:
    """Whitened rows of one kind of observation: ``A x ~ b``, 3 rows per observation."""

    kind: str
    A: sp.csr_matrix  # (3n, n_unknowns)
    b: np.ndarray  # (3n,)
    weight: np.ndarray  # (n,) information weight
    dof: np.ndarray  # (n,) constrained directions (non-zero rows of W)
    robust: bool  # judged by the robust kernel (ties, offsets, control) or trusted (model priors)
    labels: dict[str, np.ndarray] | None = None  # columns naming each observation (for reports)
    per_axis: sp.csr_matrix | None = None  # (n, n_knots) when the whitening is a scalar per observation

    def __len__(self) -> int:
        return len(self.weight)


def assemble(kind: str, n_unknowns: int, knots: np.ndarray, w: np.ndarray, value: np.ndarray,
             whiten: np.ndarray, weight: np.ndarray | None = None, robust: bool = True,
             labels: dict[str, np.ndarray] | None = None) -> Block:
    """Rows ``whiten_i @ (sum_j w[i, j] c[knots[i, j]] - value_i)`` for n observations.

    ``knots``, ``w``: (n, m); ``value``: (n, 3); ``whiten``: (n, 3, 3).
    """
    n, m = knots.shape
    rows = np.broadcast_to(3 * np.arange(n)[:, None, None, None] + np.arange(3)[None, :, None, None], (n, 3, 3, m))
    cols = np.broadcast_to(3 * knots[:, None, None, :] + np.arange(3)[None, None, :, None], (n, 3, 3, m))
    vals = (whiten[:, :, :, None] * w[:, None, None, :]).ravel()
    nz = vals != 0  # isotropic whitening: keep 3 x m entries per observation, not 9 x m
    A = sp.csr_matrix((vals[nz], (rows.ravel()[nz], cols.ravel()[nz])), shape=(3 * n, n_unknowns))
    A.sum_duplicates()
    b = np.einsum("nij,nj->ni", whiten, value).ravel()
    dof = (np.abs(whiten).sum(axis=2) > 0).sum(axis=1)
    scalar = whiten[:, 0, 0]
    per_axis = None
    if n and np.array_equal(whiten, scalar[:, None, None] * np.eye(3)):  # the 3 axes decouple
        rows = np.broadcast_to(np.arange(n)[:, None], (n, m))
        per_axis = sp.csr_matrix(((scalar[:, None] * w).ravel(), (rows.ravel(), knots.ravel())),
                                 shape=(n, n_unknowns // 3))
        per_axis.sum_duplicates()
    weight = np.ones(n) if weight is None else np.asarray(weight, float)
    return Block(kind, A, b, weight, dof, robust, labels, per_axis)


def isotropic(sd: np.ndarray) -> np.ndarray:
    """(n, 3, 3) whitening for per-axis sd (n, 3) or one sd per observation (n,)."""
    sd = np.asarray(sd, float)
    sd = np.repeat(sd[:, None], 3, axis=1) if sd.ndim == 1 else sd
    return np.einsum("ni,ij->nij", 1.0 / sd, np.eye(3))


def from_covariance(cov: np.ndarray, max_sd: float = np.inf) -> np.ndarray:
    """(n, 3, 3) whitening for full covariances; directions with sd above ``max_sd`` get no row."""
    vals, vecs = np.linalg.eigh(cov)
    vals = np.maximum(vals, 1e-12)
    scale = np.where(np.sqrt(vals) <= max_sd, 1.0 / np.sqrt(vals), 0.0)
    return np.einsum("ni,nji->nij", scale, vecs)


def relative(model: CorrectionModel, run_a: str, t_a: np.ndarray, run_b: str, t_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Knots and weights of ``c_b(t_b) - c_a(t_a)``."""
    ka, wa = model.weights(run_a, t_a)
    kb, wb = model.weights(run_b, t_b)
    return np.hstack([ka, kb]), np.hstack([-wa, wb])


def prior(model: CorrectionModel, run_id: str, sd_at_knots: np.ndarray, extra_cov: np.ndarray | None = None) -> Block:
    """``c_r(knot) = 0`` with the run's reported sd at each knot, plus ``extra_cov`` (n, 3, 3)
    where the run's sd was found to understate its error (:mod:`railtraj.sd_check`)."""
    rk = model.runs[run_id]
    knots = rk.first + np.arange(rk.count)[:, None]
    if extra_cov is None:
        whiten = isotropic(sd_at_knots)
    else:
        whiten = from_covariance(np.einsum("ni,ij->nij", np.asarray(sd_at_knots, float) ** 2, np.eye(3)) + extra_cov)
    return assemble("prior", model.n_unknowns, knots, np.ones((rk.count, 1)), np.zeros((rk.count, 3)),
                    whiten, robust=False)


def smoothness(model: CorrectionModel, run_id: str, curvature_sd: float | np.ndarray,
               relax: np.ndarray | None = None) -> Block:
    """Second differences of consecutive knots ``= 0``.

    The drift's bend along the track is modelled as white noise of density ``curvature_sd``
    (m/m^1.5; one value, or one per second difference and axis, (n_knots - 2, 3): see
    :mod:`railtraj.adjust.stiffness`): over knots ``h`` metres apart a second difference has sd
    ``curvature_sd * h^1.5``.
    A constant drift rate costs nothing; a change of rate is what is penalised. Per metre, not per
    second: a tunnel's drift grows from portal to portal over the tunnel's length whatever the
    speed (a smoother ties both ends), so a fast run's drift bends no faster along the track.
    ``relax`` (n_knots, 3, 3): where the run's error is not that drift (a GNSS bias found by
    :mod:`railtraj.sd_check`), the bend's covariance grows by ``sd^2 relax`` at the middle knot.
    """
    rk = model.runs[run_id]
    if rk.count < 3:
        return assemble("smoothness", model.n_unknowns, np.zeros((0, 3), np.int64), np.zeros((0, 3)),
                        np.zeros((0, 3)), np.zeros((0, 3, 3)), robust=False)
    k = rk.first + np.arange(rk.count - 2)
    h = model.knot_metres(run_id)
    density = np.broadcast_to(np.asarray(curvature_sd, float), (len(k), 3))
    sd = np.maximum(density * ((0.5 * (h[:-1] + h[1:])) ** 1.5)[:, None], 1e-6)
    n = len(k)
    whiten = isotropic(sd) if relax is None else from_covariance(
        np.einsum("ni,nij,nj->nij", sd, np.eye(3) + relax[1:-1], sd))
    return assemble("smoothness", model.n_unknowns, np.column_stack([k, k + 1, k + 2]),
                    np.tile([1.0, -2.0, 1.0], (n, 1)), np.zeros((n, 3)), whiten, robust=False)
