"""Solve the stacked observations: sparse normal equations, a banded solve, GNC for outliers.

* **Banded solve.** Knots are linked only to their neighbours and, through ties, to the knots of
  other runs at the same place, so a reverse Cuthill-McKee ordering makes the normal matrix
  banded; LAPACK's banded Cholesky then solves it in ``O(n b^2)``.
* **Posterior covariance without one marginal per knot.** The banded matrix is cut into blocks
  of the bandwidth (block tridiagonal); one backward sweep (as in a Rauch-Tung-Striebel
  smoother) gives every diagonal block of the inverse and the blocks beside it, which is all
  that interpolating a correction's sd between two knots needs.
* **Robustness that does not depend on weights** (GNC with truncated least squares, Yang et al.
  2020): each robust observation is judged by its whitened residual (chi-square with its own
  degrees of freedom), not by its information weight. The kernel starts convex and is tightened
  step by step; observations whose residual stays beyond the threshold end with weight 0 and
  are reported as rejected.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp
from scipy.sparse.csgraph import reverse_cuthill_mckee

from railtraj.adjust.observations import Block

log = logging.getLogger(__name__)


@dataclass
class Solution:
    x: np.ndarray  # (n_unknowns,)
    gnc_weight: list[np.ndarray]  # per block, (n_obs,) final robust weight (1 for trusted blocks)
    chi2_per_obs: list[np.ndarray]  # per block, whitened squared residual per observation
    iterations: int
    banded: BandedSystem


class BandedSystem:
    """A symmetric positive definite sparse matrix, reordered to a band, factorised once."""

    def __init__(self, N: sp.spmatrix, min_block: int = 12, perm: np.ndarray | None = None) -> None:
        N = sp.csr_matrix(N)
        self.n = N.shape[0]
        if perm is None:
            perm = reverse_cuthill_mckee(N, symmetric_mode=True).astype(np.int64)
        self.perm = perm
        self.inv = np.empty_like(self.perm)
        self.inv[self.perm] = np.arange(self.n)
        P = sp.triu(N[self.perm][:, self.perm], format="coo")
        self.bandwidth = int((P.col - P.row).max()) if P.nnz else 0
        self.upper = P
        band = np.zeros((self.bandwidth + 1, self.n))
        band[self.bandwidth + P.row - P.col, P.col] = P.data
        self.chol = la.cholesky_banded(band, lower=False, check_finite=False)
        self.block = max(self.bandwidth, min_block)

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        y = la.cho_solve_banded((self.chol, False), rhs[self.perm], check_finite=False)
        return y[self.inv]

    def covariance_blocks(self) -> tuple[np.ndarray, np.ndarray]:
        """Diagonal (nb, B, B) and upper off-diagonal (nb-1, B, B) blocks of the inverse, in the
        band order (block tridiagonal selected inversion)."""
        B, n = self.block, self.n
        nb = -(-n // B)
        D = np.zeros((nb, B, B))
        E = np.zeros((max(nb - 1, 0), B, B))
        i, j, v = self.upper.row, self.upper.col, self.upper.data
        bi, bj = i // B, j // B
        same = bi == bj
        D[bi[same], i[same] % B, j[same] % B] = v[same]
        D[bi[same], j[same] % B, i[same] % B] = v[same]
        nxt = ~same
        E[bi[nxt], i[nxt] % B, j[nxt] % B] = v[nxt]
        pad = np.arange(n, nb * B)
        D[-1, pad % B, pad % B] = 1.0
        S_inv = np.empty_like(D)
        G = np.empty_like(E)
        S = D[0]
        for k in range(nb):
            c = la.cho_factor(S, check_finite=False)
            S_inv[k] = la.cho_solve(c, np.eye(B), check_finite=False)
            if k < nb - 1:
                G[k] = S_inv[k] @ E[k]
                S = D[k + 1] - E[k].T @ G[k]
        cov = np.empty_like(D)
        off = np.empty_like(E)
        cov[-1] = S_inv[-1]
        for k in range(nb - 2, -1, -1):
            off[k] = -G[k] @ cov[k + 1]
            cov[k] = S_inv[k] - off[k] @ G[k].T
        return cov, off

    def covariance(self, p: np.ndarray, q: np.ndarray, blocks: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """Entries ``inv(N)[p, q]`` (original numbering) for pairs within one block of each other."""
        cov, off = blocks
        B = self.block
        a, b = self.inv[p], self.inv[q]
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        blo, bhi = lo // B, hi // B
        if (bhi - blo > 1).any():
            raise ValueError("covariance requested between unknowns more than one block apart")
        out = np.where(blo == bhi, cov[blo, lo % B, hi % B], 0.0)
        nxt = bhi == blo + 1
        out[nxt] = off[blo[nxt], lo[nxt] % B, hi[nxt] % B]
        return out


class NormalEquations:
    """``sum A^T diag(w) A`` and ``sum A^T diag(w) b`` for changing robust weights ``w``.

    Trusted blocks are summed once. A block whose whitening is a scalar per observation (ties)
    is one (n, knots) matrix shared by the three axes; its Gram entries are precomputed per
    observation, so a new set of weights costs one ``bincount``, not a sparse product.
    """

    def __init__(self, blocks: list[Block], n: int) -> None:
        self.blocks, self.n = blocks, n
        self.fixed = sp.csr_matrix((n, n))
        self.fixed_rhs = np.zeros(n)
        self.gram: dict[int, tuple] = {}
        for k, blk in enumerate(blocks):
            if not len(blk):
                continue
            if not blk.robust:
                N, r = _product(blk, blk.weight)
                self.fixed, self.fixed_rhs = self.fixed + N, self.fixed_rhs + r
            elif blk.per_axis is not None:
                self.gram[k] = _gram_cache(blk.per_axis)

    def build(self, weights: list[np.ndarray]) -> tuple[sp.csr_matrix, np.ndarray]:
        N, rhs = self.fixed, self.fixed_rhs.copy()
        for k, (blk, w) in enumerate(zip(self.blocks, weights, strict=True)):
            if not blk.robust or not len(blk):
                continue
            w = blk.weight * w
            if k in self.gram:
                obs_of, products, pos, pattern = self.gram[k]
                data = np.bincount(pos, weights=products * w[obs_of], minlength=pattern.nnz)
                N1 = _symmetric(sp.csr_matrix((data, pattern.indices, pattern.indptr), shape=pattern.shape))
                N = N + sp.kron(N1, sp.identity(3), format="csr")
                rhs += (blk.per_axis.T @ (w[:, None] * blk.b.reshape(-1, 3))).ravel()
            else:
                Nk, r = _product(blk, w)
                N, rhs = N + Nk, rhs + r
        return N.tocsr(), rhs


def _product(blk: Block, w: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    Aw = blk.A.multiply(np.repeat(w, 3)[:, None]).tocsr()
    return (blk.A.T @ Aw).tocsr(), Aw.T @ blk.b


def _gram_cache(A1: sp.csr_matrix) -> tuple:
    """Per observation, every product ``A1[i, j] A1[i, l]`` and where it lands in ``A1^T A1``."""
    counts = np.diff(A1.indptr)
    m = int(counts.max())
    n = A1.shape[0]
    cols = np.zeros((n, m), np.int64)
    vals = np.zeros((n, m))
    slot = np.arange(A1.nnz) - np.repeat(A1.indptr[:-1], counts)
    row = np.repeat(np.arange(n), counts)
    cols[row, slot], vals[row, slot] = A1.indices, A1.data
    a, b = np.triu_indices(m)  # the upper triangle: A1^T A1 is symmetric
    row_k, col_k = cols[:, a].ravel(), cols[:, b].ravel()
    products = (vals[:, a] * vals[:, b] * np.where(a == b, 1.0, 2.0)).ravel()
    obs_of = np.repeat(np.arange(n), len(a))
    keep = products != 0
    lo, hi = np.minimum(row_k, col_k)[keep], np.maximum(row_k, col_k)[keep]
    products, obs_of = products[keep], obs_of[keep]
    K = A1.shape[1]
    uniq, pos = np.unique(lo * K + hi, return_inverse=True)
    pattern = sp.csr_matrix((np.ones(len(uniq)), (uniq // K, uniq % K)), shape=(K, K))
    pattern.sort_indices()
    # csr_matrix from sorted unique (row, col) pairs keeps their order: data index == position in uniq
    return obs_of, products, pos.astype(np.int64), pattern


def _symmetric(upper: sp.csr_matrix) -> sp.csr_matrix:
    """The full symmetric matrix from its upper triangle holding doubled off-diagonal sums."""
    return (0.5 * (upper + upper.T)).tocsr()  # off-diagonal: halves on both sides; diagonal: kept


def squared_residuals(blk: Block, x: np.ndarray) -> np.ndarray:
    """Whitened squared residual norm per observation."""
    r = blk.A @ x - blk.b
    return (r.reshape(-1, 3) ** 2).sum(axis=1)


def solve(blocks: list[Block], n: int, confidence: float = 0.999, max_iterations: int = 60,
          mu_step: float = 2.0) -> Solution:
    """Least squares over all blocks, with GNC-TLS on the robust ones (weights 0..1)."""
    robust = [b.robust and len(b) > 0 for b in blocks]
    from scipy.stats import chi2  # scipy.stats takes ~0.7 s to import: not at `railtraj --help`

    bound = [chi2.ppf(confidence, np.maximum(b.dof, 1)) for b in blocks]
    gnc = [np.ones(len(b)) for b in blocks]
    mu, it, perm = None, 0, None
    normal = NormalEquations(blocks, n)
    while True:
        N, rhs = normal.build(gnc)
        system = BandedSystem(N, perm=perm)
        perm = system.perm  # the pattern does not change with the weights: order once
        x = system.solve(rhs)
        r2 = [squared_residuals(b, x) if len(b) else np.zeros(0) for b in blocks]
        if not any(robust) or it >= max_iterations:
            break
        ratio = np.concatenate([r / c for r, c, rb in zip(r2, bound, robust, strict=True) if rb])
        if mu is None:
            if ratio.max() <= 1.0:
                break  # every robust observation within its bound: plain least squares is the answer
            mu = 1.0 / (2.0 * ratio.max() - 1.0)
        else:
            mu *= mu_step
        changed = 0.0
        for k in range(len(blocks)):
            if robust[k]:
                new = _tls_weight(r2[k], bound[k], mu)
                changed = max(changed, float(np.abs(new - gnc[k]).max()))
                gnc[k] = new
        it += 1
        binary = all(np.all((g == 0) | (g == 1)) for g, rb in zip(gnc, robust, strict=True) if rb)
        if binary and changed == 0.0:
            break
    log.debug("GNC: %d iterations, bandwidth %d", it, system.bandwidth)
    return Solution(x, gnc, r2, it, system)


def _tls_weight(r2: np.ndarray, bound: np.ndarray, mu: float) -> np.ndarray:
    """GNC weights of the truncated least-squares kernel at control parameter ``mu``."""
    lo, hi = mu / (mu + 1.0) * bound, (mu + 1.0) / mu * bound
    mid = np.sqrt(bound * mu * (mu + 1.0) / np.maximum(r2, 1e-300)) - mu
    return np.where(r2 <= lo, 1.0, np.where(r2 >= hi, 0.0, np.clip(mid, 0.0, 1.0)))
