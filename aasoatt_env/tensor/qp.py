"""Every robot's 2-variable QP ``min |w - t|^2  s.t.  n_c' w <= b_c`` exactly, by enumerating its active sets.

``w = A du`` is the robot's control-point acceleration, so the box on ``du`` and the half-rows are half-planes in
``w`` (unit normals).  The answer is ``t`` where feasible, else the closest feasible candidate among the projections
onto the violated constraints and the vertices of every two constraints: the unique optimum of the strictly convex
QP (the candidate whose active set is the optimum's).  Branch-free, vectorised over robots (only the robots whose
``t`` is infeasible are enumerated), and differentiable: the answer is the closed form of its active set, so autograd
gives the derivative inside each piece; at a boundary between active sets (a multiplier or a slack crossing 0) the
answer is continuous and the derivative one-sided.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

__all__ = ["LocalAnswer", "solve_polygons"]

_CHUNK = 1 << 22  # largest candidate-by-constraint table (elements) of one enumeration chunk


class LocalAnswer(NamedTuple):
    """Answer per robot ``(R, ...)``: ``w``, unit-normal multipliers ``mu`` of its constraints, feasibility."""

    w: torch.Tensor  #: ``(R, 2)``
    mu: torch.Tensor  #: ``(R, C)``: ``2 (t - w) = sum_c mu_c n_c`` on the active constraints
    feasible: torch.Tensor  #: ``(R,)`` bool


def _rel_tol(dtype: torch.dtype) -> float:
    return 1e-10 if dtype == torch.float64 else 2e-5


def solve_polygons(t: torch.Tensor, nx: torch.Tensor, ny: torch.Tensor, b: torch.Tensor,
                   valid: torch.Tensor) -> LocalAnswer:
    """Project ``t`` ``(R, 2)`` onto the polygons ``nx w_x + ny w_y <= b`` ``(R, C)`` (unit normals where ``valid``).

    An empty polygon's robot gets the candidate of least largest violation (``feasible`` False; not the numpy
    filter's least-violation answer).
    """
    R, C = nx.shape
    tol = _rel_tol(t.dtype) * (1.0 + t.abs().amax(dim=1))
    tx, ty = t[:, 0], t[:, 1]
    viol0 = torch.where(valid, nx * tx[:, None] + ny * ty[:, None] - b, torch.zeros_like(b))
    inside = (viol0 <= tol[:, None]).all(dim=1)
    w = t.clone()
    mu = torch.zeros_like(b)
    feasible = torch.ones(R, dtype=torch.bool, device=t.device)
    todo = torch.nonzero(~inside).flatten()
    if todo.numel() == 0:
        return LocalAnswer(w, mu, feasible)
    per = max(1, _CHUNK // max(1, (C + C * (C - 1) // 2) * C))
    for start in range(0, todo.numel(), per):
        sel = todo[start:start + per]
        ws, ms, fs = _enumerate(t[sel], nx[sel], ny[sel], b[sel], valid[sel], viol0[sel], tol[sel])
        w = w.index_copy(0, sel, ws)
        mu = mu.index_copy(0, sel, ms)
        feasible = feasible.index_copy(0, sel, fs)
    return LocalAnswer(w, mu, feasible)


def _pairs(C: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    ij = torch.triu_indices(C, C, 1, device=device)
    return ij[0], ij[1]


def _enumerate(t, nx, ny, b, valid, viol0, tol):
    """The candidates of the robots given (all infeasible at ``t``) and the closest feasible one."""
    R, C = nx.shape
    dt_ = t.dtype
    tx, ty = t[:, 0:1], t[:, 1:2]
    # projections onto each violated constraint: w = t - s n
    s = viol0
    proj_ok = valid & (s > 0)
    px, py = tx - s * nx, ty - s * ny
    # vertices of every two constraints
    k, l = _pairs(C, t.device)
    n1x, n1y, b1, n2x, n2y, b2 = nx[:, k], ny[:, k], b[:, k], nx[:, l], ny[:, l], b[:, l]
    det = n1x * n2y - n1y * n2x
    vert_ok = valid[:, k] & valid[:, l] & (det.abs() > 1e-9)
    dsafe = torch.where(vert_ok, det, torch.ones_like(det))
    vx = (b1 * n2y - b2 * n1y) / dsafe
    vy = (n1x * b2 - n2x * b1) / dsafe
    cx, cy = torch.cat((px, vx), 1), torch.cat((py, vy), 1)  # (R, Q)
    cand_ok = torch.cat((proj_ok, vert_ok), 1)
    resid = cx[:, :, None] * nx[:, None, :] + cy[:, :, None] * ny[:, None, :] - b[:, None, :]  # (R, Q, C)
    resid = torch.where(valid[:, None, :], resid, torch.full_like(resid, -1.0))
    worst = resid.amax(dim=2)
    ok = cand_ok & (worst <= tol[:, None])
    dist = (cx - tx) ** 2 + (cy - ty) ** 2
    inf = torch.full_like(dist, float("inf"))
    feasible = ok.any(dim=1)
    score = torch.where(feasible[:, None], torch.where(ok, dist, inf), torch.where(cand_ok, worst, inf))
    q = score.detach().argmin(dim=1)
    rows = torch.arange(R, device=t.device)
    w = torch.stack((cx[rows, q], cy[rows, q]), 1)
    # multipliers of the chosen active set (1 or 2 constraints): 2 (t - w) = sum mu_c n_c
    dx, dy = 2.0 * (tx[:, 0] - w[:, 0]), 2.0 * (ty[:, 0] - w[:, 1])
    is_proj = q < C
    qc = torch.clamp(q, max=C - 1)
    qv = torch.clamp(q - C, min=0)
    kk, ll = k[qv], l[qv]
    d_ = dsafe[rows, qv]
    m1 = (dx * n2y[rows, qv] - dy * n2x[rows, qv]) / d_
    m2 = (n1x[rows, qv] * dy - n1y[rows, qv] * dx) / d_
    mu = torch.zeros((R, C), dtype=dt_, device=t.device)
    zero = torch.zeros_like(m1)
    mu = mu.index_put((rows, torch.where(is_proj, qc, kk)), torch.where(is_proj, 2.0 * s[rows, qc], m1))
    mu = mu.index_put((rows, ll), torch.where(is_proj, zero, m2), accumulate=True)
    mu = torch.where(feasible[:, None], mu, torch.zeros_like(mu))
    return w, mu, feasible
