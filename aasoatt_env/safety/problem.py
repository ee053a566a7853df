"""The safety QP in canonical scaled form, and the closed-form answer without rows.

``min sum_i |A_i du_i - target_i|^2  s.t.  lo <= du <= hi, G du <= rhs`` (eqn.finalAA-SOATT) is solved in ``x = du / s``
(``s`` the per-robot bound: the box inside ``[-1, 1]``), the objective over its largest Hessian entry, rows of unit
norm.  The Hessian ``A_i^T A_i = (rho/2)^2 [[1+k^2, 1-k^2], [1-k^2, 1+k^2]]`` is heading independent.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from aasoatt_env import validation as check
from aasoatt_env.compiled import c64, kernels
from aasoatt_env.model.geometry import namespace

__all__ = ["ROW_NORM_MIN", "QPProblem", "box_least_squares", "box_ls", "build_problem"]

ROW_NORM_MIN: float = 1e-12  #: a row whose scaled norm is at most this is left unnormalised (divisor 1)


@dataclass
class QPProblem:
    """Canonical scaled QP ``min 0.5 x'Hx + g'x  s.t. lb <= x <= ub, C x <= u``."""

    H_blocks: np.ndarray  #: ``(N, 2, 2)``, the blocks of the block-diagonal ``H``
    g: np.ndarray  #: ``(n,)``
    C: sp.csr_matrix  #: ``(m, n)``, unit-norm rows
    u: np.ndarray  #: ``(m,)``
    lb: np.ndarray  #: ``(n,)``
    ub: np.ndarray  #: ``(n,)``
    scale: np.ndarray  #: ``(n,)``: ``du = scale * x``
    obj_scale: float  #: the objective's divisor ``sigma``
    row_norm: np.ndarray  #: ``(m,)`` the rows' divisors ``nu``: ``eta_du = sigma * z / nu``
    diagonal: bool  #: every block of ``H`` is diagonal

    @property
    def n(self) -> int:
        """Number of variables."""
        return int(self.g.shape[0])

    @property
    def m(self) -> int:
        """Number of rows."""
        return int(self.u.shape[0])

    def H_dense(self) -> np.ndarray:
        """Dense Hessian ``(n, n)``."""
        n = self.n
        H, k = np.zeros((n, n)), np.arange(0, n, 2)
        H[k, k], H[k, k + 1] = self.H_blocks[:, 0, 0], self.H_blocks[:, 0, 1]
        H[k + 1, k], H[k + 1, k + 1] = self.H_blocks[:, 1, 0], self.H_blocks[:, 1, 1]
        return H

    def H_sparse(self) -> sp.csc_matrix:
        """Sparse block-diagonal Hessian (both entries of every block stored)."""
        n = self.n
        # column 2k holds rows 2k, 2k+1 of block k's first column; column 2k+1 its second
        data = self.H_blocks.transpose(0, 2, 1).reshape(-1)
        indices = (np.arange(0, n, 2)[:, None, None] + np.array([[0, 1], [0, 1]])).reshape(-1)
        return sp.csc_matrix((data, indices, np.arange(0, 2 * n + 1, 2)), shape=(n, n))

    def restrict(self, robots: np.ndarray, rows: np.ndarray) -> QPProblem:
        """The part of robots ``robots`` ``(N,)`` and rows ``rows`` ``(m,)`` (bool), its multipliers the whole's."""
        v = np.repeat(robots, 2)
        return QPProblem(self.H_blocks[robots], self.g[v], self.C[rows][:, v].tocsr(), self.u[rows], self.lb[v],
                         self.ub[v], self.scale[v], self.obj_scale, self.row_norm[rows], self.diagonal)

    def objective(self, x: np.ndarray) -> float:
        """Scaled objective ``0.5 x'Hx + g'x`` of ``x``."""
        xb = x.reshape(-1, 2)
        return float(0.5 * np.einsum("ni,nij,nj->", xb, self.H_blocks, xb) + self.g @ x)


def build_problem(A: np.ndarray, target: np.ndarray, lo: np.ndarray, hi: np.ndarray, scale: np.ndarray, ri: np.ndarray,
                  rj: np.ndarray, Gi: np.ndarray, Gj: np.ndarray, rhs: np.ndarray) -> QPProblem:
    """The scaled canonical problem of ``min sum |A_i du_i - target_i|^2  s.t.  lo <= du <= hi, rows``.

    ``A`` ``(N, 2, 2)``, ``target``, ``lo``, ``hi`` ``(N, 2)``, ``scale`` ``(N,)`` positive; the rows
    ``Gi du_ri + Gj du_rj <= rhs`` (``m`` of them; ``rj = -1``: an obstacle row, ``Gj`` ignored).
    """
    n_rob = A.shape[0]
    s = scale[:, None]
    H = 2.0 * np.einsum("nki,nkj->nij", A, A) * (s[:, :, None] * s[:, None, :])
    sigma = float(np.max(np.abs(H))) if n_rob else 1.0
    H = H / sigma
    g = (-2.0 * np.einsum("nki,nk->ni", A, target) * s / sigma).ravel()
    m, obs = rhs.shape[0], rj < 0
    rjc = np.where(obs, 0, rj)
    Gi_s, Gj_s = Gi * s[ri], np.where(obs[:, None], 0.0, Gj * s[rjc])
    nu = np.sqrt(np.sum(Gi_s**2, axis=1) + np.sum(Gj_s**2, axis=1))
    nu = np.where(nu > ROW_NORM_MIN, nu, 1.0)
    Gi_s /= nu[:, None]
    Gj_s /= nu[:, None]
    # CSR directly: 4 entries per robot-robot row, 2 per obstacle row, indices in the dtype scipy would choose
    keep = np.ones((m, 4), dtype=bool)
    keep[:, 2:] = ~obs[:, None]
    indptr = np.zeros(m + 1, dtype=np.int64)
    np.cumsum(np.where(obs, 2, 4), out=indptr[1:])
    cols = np.stack((2 * ri, 2 * ri + 1, 2 * rjc, 2 * rjc + 1), axis=1)[keep]
    data = np.concatenate((Gi_s, Gj_s), axis=1)[keep]
    itype = np.int32 if max(4 * m, 2 * n_rob) < np.iinfo(np.int32).max else np.int64
    C = sp.csr_matrix((data, cols.astype(itype), indptr.astype(itype)), shape=(m, 2 * n_rob))
    diag = bool(np.all(np.abs(H[:, 0, 1]) <= 1e-12 * np.maximum(np.abs(H[:, 0, 0]), 1e-300)))
    return QPProblem(H_blocks=H, g=g, C=C, u=rhs / nu, lb=(lo / s).ravel(), ub=(hi / s).ravel(),
                     scale=np.repeat(scale, 2), obj_scale=sigma, row_norm=nu, diagonal=diag)


def box_least_squares(A: np.ndarray, target: np.ndarray, lo: np.ndarray, hi: np.ndarray, *,
                      compiled: bool = False) -> np.ndarray:
    """Per robot ``argmin |A_i du_i - target_i|^2  s.t.  lo_i <= du_i <= hi_i`` ``(K, 2)``, in closed form.

    ``A_i^-1 target_i`` inside the box, else the best edge (:func:`best_edge`); ``compiled``: the same numbers.
    """
    k = np.shape(A)[0] if np.ndim(A) == 3 else -1
    check.shapes((("A", A, (k, 2, 2)), ("target", target, (k, 2)), ("lo", lo, (k, 2)), ("hi", hi, (k, 2))),
                 " (A: (K, 2, 2), the others (K, 2))")
    if compiled:
        return kernels("centralized").box_least_squares(c64(A), c64(target), c64(lo), c64(hi))
    return box_ls(A[:, 0, 0], A[:, 0, 1], A[:, 1, 0], A[:, 1, 1], target, lo, hi)


def box_ls(a, b, c, d, target, lo, hi):
    """:func:`box_least_squares` in ``target``'s namespace (numpy, torch: differentiable piecewise).

    ``a, b, c, d``: ``A``'s entries ``(...)``; the others ``(..., 2)``.
    """
    xp = namespace(target)
    t0, t1 = target[..., 0], target[..., 1]
    det = a * d - b * c
    x = xp.stack(((d * t0 - b * t1) / det, (a * t1 - c * t0) / det), axis=-1)
    out = xp.any((x < lo) | (x > hi), axis=-1)
    if not bool(xp.any(out)):
        return x
    # outside: the best edge of the objective 0.5 du' H du + g' du (H = A'A, g = -A' target)
    h00, h01, h11 = a * a + c * c, a * b + c * d, b * b + d * d
    g0, g1 = -(a * t0 + c * t1), -(b * t0 + d * t1)
    ex, ey = best_edge(xp, h00, h01, h11, g0, g1, lo[..., 0], lo[..., 1], hi[..., 0], hi[..., 1])
    return xp.where(out[..., None], xp.stack((ex, ey), axis=-1), x)


def best_edge(xp, h00, h01, h11, g0, g1, lo0, lo1, hi0, hi1):
    """The minimiser of ``0.5 x'Hx + g'x`` over the four edges of the box ``lo <= x <= hi`` (any namespace ``xp``).

    Edges ``x0 = lo, hi``, ``x1 = lo, hi``, each at the clipped parabola minimum along it; the first of equal values.
    """
    f0, f1 = xp.stack((lo0, hi0)), xp.stack((lo1, hi1))
    x0 = xp.concat((f0, xp.clip(-(g0 + h01 * f1) / h00, lo0, hi0)))
    x1 = xp.concat((xp.clip(-(g1 + h01 * f0) / h11, lo1, hi1), f1))
    f = 0.5 * (h00 * x0 * x0 + 2.0 * h01 * x0 * x1 + h11 * x1 * x1) + g0 * x0 + g1 * x1
    ex, ey, best = x0[0], x1[0], f[0]
    for e in range(1, 4):  # (not argmin over the 4 edges: a slow reduction in torch)
        take = f[e] < best
        ex, ey, best = xp.where(take, x0[e], ex), xp.where(take, x1[e], ey), xp.where(take, f[e], best)
    return ex, ey
