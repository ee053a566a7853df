"""Least violation of an infeasible robot's rows, as the numpy local solver computes it (``solvers/local._lv_core``).

Per robot ``min 0.5 sum_r (g_r x - h_r)_+^2  s.t.  lb <= x <= ub`` over its rows normalised in ``x``: convex and
piecewise quadratic; each iteration minimises the violated rows' quadratic over the box (closed form, a ``1e-10``
relative proximal term on the step) and moves to the exact minimiser on the segment to it.  The violations at the
minimum are unique, so the loosened rows (``violation (1 + 1e-6) + RELAX_TOL * scale``) are the numpy filter's.
"""

from __future__ import annotations

import torch

__all__ = ["least_violation"]

_STOP = {torch.float64: 1e-11, torch.float32: 1e-6}
"""A step shorter than this times the box's span ends a robot's iteration: numpy's in float64; in float32 the
rounding of ``x`` (about ``1e-7`` relative) would keep the active set flickering to ``max_iter``."""


def _box_qp(hxx, hxy, hyy, gx, gy, lox, loy, hix, hiy):
    """Per robot ``argmin 0.5 d'Hd + g'd  s.t.  lo <= d <= hi`` (strictly convex ``H``): inside, else the best edge."""
    det = hxx * hyy - hxy * hxy
    dx = -(hyy * gx - hxy * gy) / det
    dy = -(hxx * gy - hxy * gx) / det
    inside = (dx >= lox) & (dx <= hix) & (dy >= loy) & (dy <= hiy)
    if bool(inside.all()):
        return dx, dy
    best = torch.full_like(dx, float("inf"))
    bx, by = dx, dy
    for e, c in enumerate((lox, hix, loy, hiy)):
        ex = c if e < 2 else torch.minimum(torch.maximum(-(gx + hxy * c) / hxx, lox), hix)
        ey = torch.minimum(torch.maximum(-(gy + hxy * c) / hyy, loy), hiy) if e < 2 else c
        f = 0.5 * (hxx * ex * ex + 2 * hxy * ex * ey + hyy * ey * ey) + gx * ex + gy * ey
        take = ~inside & (f < best)
        best, bx, by = torch.where(take, f, best), torch.where(take, ex, bx), torch.where(take, ey, by)
    return bx, by


def _line_min(res: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """Per robot the exact minimiser on ``[0, 1]`` of ``0.5 sum_r (res_r + t delta_r)_+^2`` (``(P, K)``)."""
    P = res.shape[0]
    safe = torch.where(delta != 0, delta, torch.ones_like(delta))
    te = -res / safe
    ev = (delta != 0) & (te > 0) & (te < 1)
    te = torch.where(ev, te, torch.full_like(te, 2.0))
    ts, order = torch.sort(te, dim=1)
    dl = torch.where(ev, delta, torch.zeros_like(delta)).gather(1, order)
    rs = res.gather(1, order)
    sg = torch.sign(dl)
    on0 = (res > 0) | ((res == 0) & (delta > 0))
    a0 = torch.where(on0, res * delta, torch.zeros_like(res)).sum(1, keepdim=True)
    b0 = torch.where(on0, delta * delta, torch.zeros_like(res)).sum(1, keepdim=True)
    A = torch.cat((a0, a0 + torch.cumsum(sg * dl * rs, 1)), 1)
    B = torch.cat((b0, b0 + torch.cumsum(sg * dl * dl, 1)), 1)
    ends = torch.clamp(torch.cat((ts, torch.ones(P, 1, dtype=res.dtype, device=res.device)), 1), max=1.0)
    starts = torch.cat((torch.zeros(P, 1, dtype=res.dtype, device=res.device), ends[:, :-1]), 1)
    up = A + ends * B >= 0
    k = torch.where(up.any(1), up.to(torch.int8).argmax(1), torch.full((P,), ends.shape[1] - 1, device=res.device))
    a, b = A.gather(1, k[:, None])[:, 0], B.gather(1, k[:, None])[:, 0]
    s0, s1 = starts.gather(1, k[:, None])[:, 0], ends.gather(1, k[:, None])[:, 0]
    t = torch.where(b > 0, -a / torch.where(b > 0, b, torch.ones_like(b)), torch.where(a >= 0, s0, s1))
    return torch.minimum(torch.maximum(t, s0), s1)


def least_violation(gx: torch.Tensor, gy: torch.Tensor, hh: torch.Tensor, lb: torch.Tensor, ub: torch.Tensor,
                    x: torch.Tensor, max_iter: int = 40) -> torch.Tensor:
    """Each row's violation ``(P, K)`` at the least-violation point over the box (module docstring).

    Unit rows ``gx, gy, hh`` (a slot that is not there: ``0, 0, +large``), bounds ``(P, 2)``, a start ``x``.
    """
    with torch.no_grad():
        x = x.clone()
        span = torch.clamp((ub - lb).amax(1), min=1e-300)
        stop = _STOP.get(x.dtype, _STOP[torch.float32])
        act = torch.ones(x.shape[0], dtype=torch.bool, device=x.device)
        for _ in range(max_iter):
            if not bool(act.any()):
                break
            res = gx * x[:, 0:1] + gy * x[:, 1:2] - hh
            on = res > 0
            ra = torch.where(on, res, torch.zeros_like(res))
            gxo, gyo = torch.where(on, gx, torch.zeros_like(gx)), torch.where(on, gy, torch.zeros_like(gy))
            grx, gry = (ra * gx).sum(1), (ra * gy).sum(1)
            hxx, hxy, hyy = (gxo * gx).sum(1), (gxo * gy).sum(1), (gyo * gy).sum(1)
            eps = 1e-10 * (hxx + hyy) + 1e-300
            dx, dy = _box_qp(hxx + eps, hxy, hyy + eps, grx, gry, lb[:, 0] - x[:, 0], lb[:, 1] - x[:, 1],
                             ub[:, 0] - x[:, 0], ub[:, 1] - x[:, 1])
            delta = gx * dx[:, None] + gy * dy[:, None]
            rn = res + delta
            d1 = (torch.where(rn > 0, rn, torch.zeros_like(rn)) * delta).sum(1)
            full = d1 <= 0.0
            t = torch.ones_like(d1)
            part = torch.nonzero(~full).flatten()
            if part.numel():
                t = t.index_copy(0, part, _line_min(res[part], delta[part]))
            new = torch.stack((torch.minimum(torch.maximum(x[:, 0] + t * dx, lb[:, 0]), ub[:, 0]),
                               torch.minimum(torch.maximum(x[:, 1] + t * dy, lb[:, 1]), ub[:, 1])), 1)
            x = torch.where(act[:, None], new, x)
            same = full & ((rn > 0) == on).all(1)
            act = act & ~same & (t * torch.maximum(dx.abs(), dy.abs()) > stop * span)
        return torch.clamp(gx * x[:, 0:1] + gy * x[:, 1:2] - hh, min=0.0)
