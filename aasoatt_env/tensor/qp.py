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
                   t_box: torch.Tensor | None = None, rows: int = 0) -> LocalAnswer:
    """Project ``t`` ``(R, 2)`` onto the polygons ``nx w_x + ny w_y <= b`` ``(R, C)`` (unit normals).

    A constraint slot that is not there has ``n = 0``, ``b`` = :data:`FAR`.

    Stages: ``t`` itself; ``t_box``, the projection onto the first ``C - rows`` constraints alone (where it meets the
    last ``rows`` it is the optimum; their multipliers are 0, the first ones' are not computed); the projections
    onto the violated constraints of ``t`` (a feasible one is the optimum: the polygon lies in that half-plane); the
    vertices.  An empty polygon's robot gets the candidate of least largest violation (``feasible`` False; the
    filter then loosens its rows, :mod:`.relax`).
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
    few = (v1 > 0).sum(1) <= _FEW
    for group in (few, ~few):
        rest = torch.nonzero(group).flatten()
        if rest.numel() == 0:
            continue
        # the optimum lies on a constraint that t violates: with at most _FEW of them, those come first
        lead = min(_FEW, C) if bool(few[rest[0]]) else C
        o = torch.sort(v1[rest].detach(), dim=1, descending=True, stable=True).indices
        ws, ms, fs = _stage(t1[rest], *(x[rest].gather(1, o) for x in (nx1, ny1, b1, v1)), tol1[rest], lead)
        w1 = w1.index_copy(0, rest, ws)
        m1 = m1.index_copy(0, rest, torch.zeros_like(ms).scatter(1, o, ms))
        f1 = f1.index_copy(0, rest, fs)
    return LocalAnswer(w.index_copy(0, todo, w1), mu.index_copy(0, todo, m1), feasible.index_copy(0, todo, f1))


def _stage(t, nx, ny, b, v, tol, lead: int):
    """Robots with constraints sorted by violation: the closest feasible projection onto one of the first ``lead``.

    A feasible one is the optimum; else the closest feasible vertex of a pair with a constraint among them.
    """
    R, C = nx.shape
    s = torch.clamp(v[:, :lead], min=0.0)
    px, py = t[:, 0:1] - s * nx[:, :lead], t[:, 1:2] - s * ny[:, :lead]  # (R, lead)
    worst = (px[:, :, None] * nx[:, None, :] + py[:, :, None] * ny[:, None, :] - b[:, None, :]).amax(2)
    ok = (v[:, :lead] > 0) & (worst <= tol[:, None])
    q = torch.where(ok, s, torch.full_like(s, float("inf"))).detach().argmin(1)
    one = ok.any(1)
    r = torch.arange(R, device=t.device)
    w = torch.stack((px[r, q], py[r, q]), 1)
    mu = torch.zeros_like(b).index_put((r, q), 2.0 * s[r, q])
    feasible = torch.ones_like(one)
    rest = torch.nonzero(~one).flatten()
    if rest.numel():
        k, m = _pairs(C, lead, t.device)
        per = max(1, _CHUNK // max(1, k.numel() * C))
        pxa = torch.cat((px, torch.zeros(R, C - lead, dtype=t.dtype, device=t.device)), 1)
        pya = torch.cat((py, torch.zeros(R, C - lead, dtype=t.dtype, device=t.device)), 1)
        va = torch.cat((v[:, :lead], torch.full((R, C - lead), -1.0, dtype=t.dtype, device=t.device)), 1)
        for start in range(0, rest.numel(), per):
            sel = rest[start:start + per]
            ws, ms, fs = _vertices(t[sel], nx[sel], ny[sel], b[sel], tol[sel], pxa[sel], pya[sel], va[sel], k, m)
            w, mu, feasible = w.index_copy(0, sel, ws), mu.index_copy(0, sel, ms), feasible.index_copy(0, sel, fs)
    return w, mu, feasible


FAR = 1e30  #: right-hand side of a constraint slot that is not there (its normal is 0)


_FEW = 2  # robots with at most this many constraints violated by t pair only those with the others


def _pairs(C: int, lead: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """Index pairs ``k < m`` of ``C`` constraints with ``k < lead``."""
    ij = torch.triu_indices(C, C, 1, device=device)
    keep = ij[0] < lead
    return ij[0][keep], ij[1][keep]


def _vertices(t, nx, ny, b, tol, px, py, viol0, k, m):
    """The closest feasible vertex of the constraint pairs ``k, m`` of the robots given (no feasible projection).

    None feasible: the projection or vertex of least largest violation.
    """
    R, C = nx.shape
    n1x, n1y, b1, n2x, n2y, b2 = nx[:, k], ny[:, k], b[:, k], nx[:, m], ny[:, m], b[:, m]
    det = n1x * n2y - n1y * n2x
    vert_ok = (det.abs() > 1e-9) & (b1 < FAR) & (b2 < FAR)
    dsafe = torch.where(vert_ok, det, torch.ones_like(det))
    vx = (b1 * n2y - b2 * n1y) / dsafe
    vy = (n1x * b2 - n2x * b1) / dsafe
    worst = (vx[:, :, None] * nx[:, None, :] + vy[:, :, None] * ny[:, None, :] - b[:, None, :]).amax(2)
    ok = vert_ok & (worst <= tol[:, None])
    tx, ty = t[:, 0:1], t[:, 1:2]
    dist = (vx - tx) ** 2 + (vy - ty) ** 2
    inf = torch.full_like(dist, float("inf"))
    feasible = ok.any(dim=1)
    rows = torch.arange(R, device=t.device)
    q = torch.where(ok, dist, inf).detach().argmin(dim=1)
    w = torch.stack((vx[rows, q], vy[rows, q]), 1)
    dx, dy = 2.0 * (tx[:, 0] - w[:, 0]), 2.0 * (ty[:, 0] - w[:, 1])
    d_ = dsafe[rows, q]
    mu = torch.zeros((R, C), dtype=t.dtype, device=t.device)
    mu = mu.index_put((rows, k[q]), (dx * n2y[rows, q] - dy * n2x[rows, q]) / d_)
    mu = mu.index_put((rows, m[q]), (n1x[rows, q] * dy - n1y[rows, q] * dx) / d_, accumulate=True)
    if not bool(feasible.all()):  # empty polygons: the candidate of least largest violation
        pw = (px[:, :, None] * nx[:, None, :] + py[:, :, None] * ny[:, None, :] - b[:, None, :]).amax(2)
        pw = torch.where(viol0 > 0, pw, inf[:, :C])
        score = torch.cat((pw, torch.where(vert_ok, worst, inf)), 1).detach()
        qq = score.argmin(1)
        cx, cy = torch.cat((px, vx), 1), torch.cat((py, vy), 1)
        wb = torch.stack((cx[rows, qq], cy[rows, qq]), 1)
        w = torch.where(feasible[:, None], w, wb)
        mu = torch.where(feasible[:, None], mu, torch.zeros_like(mu))
    return w, mu, feasible
