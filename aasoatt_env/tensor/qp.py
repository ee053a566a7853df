"""Every robot's 2-variable QP ``min |w - t|^2  s.t.  n_c' w <= b_c`` exactly, line by line.

``w = A du`` is the robot's control-point acceleration, so the box on ``du`` and the half-rows are half-planes in
``w`` (unit normals).  The answer is ``t`` where feasible; else the optimum lies on a line that ``t`` violates, at
the point of that line's feasible segment closest to ``t``: the nearest of those points over the violated lines is
the unique optimum of the strictly convex QP.  Branch-free, vectorised over robots (only the robots whose ``t`` is
infeasible look at lines), and differentiable: the answer is the closed form of its active set, so autograd
gives the derivative inside each piece; at a boundary between active sets (a multiplier or a slack crossing 0) the
answer is continuous and the derivative one-sided.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

__all__ = ["LocalAnswer", "solve_polygons"]

_CHUNK = 1 << 22  # largest line-by-constraint table (elements) of one chunk
_FEW = 2  # robots with at most this many constraints violated by t look only at those lines
FAR = 1e30  #: right-hand side of a constraint slot that is not there (its normal is 0)


class LocalAnswer(NamedTuple):
    """Answer per robot ``(R, ...)``: ``w``, unit-normal multipliers ``mu`` of its constraints, feasibility."""

    w: torch.Tensor  #: ``(R, 2)``
    mu: torch.Tensor  #: ``(R, C)``: ``2 (t - w) = sum_c mu_c n_c`` on the active constraints
    feasible: torch.Tensor  #: ``(R,)`` bool


def _rel_tol(dtype: torch.dtype) -> float:
    return 1e-10 if dtype == torch.float64 else 2e-5


def solve_polygons(t: torch.Tensor, nx: torch.Tensor, ny: torch.Tensor, b: torch.Tensor,
                   t_box: torch.Tensor | None = None, rows: int = 0) -> LocalAnswer:
    """Project ``t`` ``(R, 2)`` onto the polygons ``nx w_x + ny w_y <= b`` ``(R, C)`` (unit normals).

    A constraint slot that is not there has ``n = 0``, ``b`` = :data:`FAR`.

    Stages: ``t`` itself; ``t_box``, the projection onto the first ``C - rows`` constraints alone (where it meets the
    last ``rows`` it is the optimum; their multipliers are 0, the first ones' are not computed); the lines that ``t``
    violates (:func:`_on_lines`).  An empty polygon's robot gets the projection of least largest violation
    (``feasible`` False; the filter then loosens its rows, :mod:`.relax`).
    """
    R, C = nx.shape
    tol = _rel_tol(t.dtype) * (1.0 + t.abs().amax(dim=1))
    viol0 = nx * t[:, 0:1] + ny * t[:, 1:2] - b
    w, mu = t.clone(), torch.zeros_like(b)
    feasible = torch.ones(R, dtype=torch.bool, device=t.device)
    out = viol0.amax(dim=1) > tol
    if t_box is not None and rows < C:
        box = out
        if rows:  # (no rows: the box's projection is the optimum)
            vb = (nx[:, C - rows:] * t_box[:, 0:1] + ny[:, C - rows:] * t_box[:, 1:2] - b[:, C - rows:]).amax(dim=1)
            box = out & (vb <= tol)
        w = torch.where(box[:, None], t_box, w)
        out = out & ~box
    todo = torch.nonzero(out).flatten()
    if todo.numel() == 0:
        return LocalAnswer(w, mu, feasible)
    t1, nx1, ny1, b1, v1, tol1 = t[todo], nx[todo], ny[todo], b[todo], viol0[todo], tol[todo]
    w1, m1 = torch.zeros_like(t1), torch.zeros_like(b1)
    f1 = torch.ones(todo.numel(), dtype=torch.bool, device=t.device)
    count = (v1 > 0).sum(1)
    few = count <= _FEW
    for group in (few, ~few):  # (most robots violate a few lines: their tables stay small)
        rest = torch.nonzero(group).flatten()
        if rest.numel() == 0:
            continue
        lead = int(count[rest].max())  # the violated lines come first
        o = torch.sort(v1[rest].detach(), dim=1, descending=True, stable=True).indices
        ws, ms, fs = _stage(t1[rest], *(x[rest].gather(1, o) for x in (nx1, ny1, b1, v1)), tol1[rest], lead)
        w1 = w1.index_copy(0, rest, ws)
        m1 = m1.index_copy(0, rest, torch.zeros_like(ms).scatter(1, o, ms))
        f1 = f1.index_copy(0, rest, fs)
    return LocalAnswer(w.index_copy(0, todo, w1), mu.index_copy(0, todo, m1), feasible.index_copy(0, todo, f1))


def _stage(t, nx, ny, b, v, tol, lead: int):
    """Robots with constraints sorted by violation: :func:`_on_lines` of their first ``lead``, a chunk at once."""
    R, C = nx.shape
    per = max(1, _CHUNK // max(1, lead * C))
    parts = [_on_lines(t[i:i + per], nx[i:i + per], ny[i:i + per], b[i:i + per], v[i:i + per], tol[i:i + per], lead)
             for i in range(0, R, per)]
    return tuple(torch.cat(x) for x in zip(*parts)) if len(parts) > 1 else parts[0]


def _on_lines(t, nx, ny, b, v, tol, lead: int):
    """The closest point to ``t`` on each of the first ``lead`` lines that ``t`` violates, within the polygon.

    Along line ``k`` (``p_k + sigma d_k``: ``p_k`` the projection of ``t``, ``d_k`` its unit direction) constraint
    ``m`` reads ``sigma (n_m' d_k) <= b_m - n_m' p_k``, so the polygon leaves an interval ``[lo, hi]`` of ``sigma``
    (empty if ``lo > hi``, or if a parallel constraint excludes the line); the closest point is ``sigma`` = 0 clamped
    into it, at squared distance ``s_k^2 + sigma^2`` from ``t``.  The nearest over the lines is the optimum; none:
    the polygon is empty, and the projection of least largest violation is returned (``feasible`` False).
    Multipliers: ``2 s_k`` on line ``k`` alone, or the two-line system where ``sigma`` sits at an end.
    """
    R, C = nx.shape
    s = torch.clamp(v[:, :lead], min=0.0)
    kx, ky = nx[:, :lead], ny[:, :lead]
    px, py = t[:, 0:1] - s * kx, t[:, 1:2] - s * ky  # (R, L)
    nd = nx[:, None, :] * (-ky)[:, :, None] + ny[:, None, :] * kx[:, :, None]  # n_m' d_k (R, L, C), d_k = (-ny, nx)
    room = b[:, None, :] - (nx[:, None, :] * px[:, :, None] + ny[:, None, :] * py[:, :, None])
    ratio = room / torch.where(nd == 0, torch.ones_like(nd), nd)  # (not used where nd = 0: no 0/0 in the gradient)
    hi, m_hi = torch.where(nd > 0, ratio, float("inf")).min(2)
    lo, m_lo = torch.where(nd < 0, ratio, float("-inf")).max(2)
    shut = ((nd == 0) & (room < -tol[:, None, None])).any(2)
    ok = (v[:, :lead] > 0) & (lo <= hi + tol[:, None]) & ~shut
    sig = torch.minimum(torch.clamp(lo, min=0.0), hi)
    q = torch.where(ok, s * s + sig * sig, float("inf")).detach().argmin(1, keepdim=True)
    feasible = ok.any(1)

    def pick(x):  # each robot's value on its line q
        return x.gather(1, q)[:, 0]

    sq, kxq, kyq = pick(sig), pick(kx), pick(ky)
    w = torch.stack((pick(px) - sq * kyq, pick(py) + sq * kxq), 1)
    with torch.no_grad():
        at_hi, at_lo = (sq >= pick(hi)) & (sq < 0), (sq <= pick(lo)) & (sq > 0)
        m = torch.where(at_hi, pick(m_hi), pick(m_lo))[:, None]
        n2x, n2y = nx.gather(1, m)[:, 0], ny.gather(1, m)[:, 0]
        dx, dy = 2.0 * (t[:, 0] - w[:, 0]), 2.0 * (t[:, 1] - w[:, 1])
        det = kxq * n2y - kyq * n2x
        two = (at_hi | at_lo) & (det != 0)
        d_ = torch.where(two, det, torch.ones_like(det))
        mu1 = torch.where(two, (dx * n2y - dy * n2x) / d_, 2.0 * pick(s))
        mu2 = torch.where(two, (kxq * dy - kyq * dx) / d_, torch.zeros_like(dx))
        mu = torch.zeros((R, C), dtype=t.dtype, device=t.device).scatter(1, q, mu1[:, None])
        mu = mu.scatter_add(1, m, mu2[:, None])
        mu = torch.where(feasible[:, None], mu, torch.zeros_like(mu))
    if not bool(feasible.all()):  # empty polygons: the projection of least largest violation
        bad = torch.nonzero(~feasible).flatten()
        worst = torch.where(v[bad, :lead] > 0, (-room[bad]).amax(2), float("inf")).detach()
        qq = worst.argmin(1, keepdim=True)
        w = w.index_copy(0, bad, torch.stack((px[bad].gather(1, qq)[:, 0], py[bad].gather(1, qq)[:, 0]), 1))
    return w, mu, feasible
