"""Every robot's 2-variable QP exactly, on numpy arrays or torch tensors: one source for both decentralised filters.

:func:`solve_polygons` projects ``t`` onto each robot's polygon of unit half-planes; :func:`least_violation` gives an
empty polygon's least row violation over the bounds.  Written in the inputs' namespace (the numpy :mod:`.local` in
``y = L' x``, :mod:`aasoatt_env.tensor.filter` in ``w = A du``), vectorised over robots, and on tensors differentiable:
the answer is the closed form of its active set (one-sided derivative where the active set changes); nothing that
autograd needs is changed in place.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import numpy as np

from aasoatt_env.model.geometry import namespace
from aasoatt_env.safety.problem import best_edge

__all__ = ["FAR", "LV_ITERS", "LocalAnswer", "least_violation", "solve_polygons"]

FAR = 1e30  #: right-hand side of a constraint slot that is not there (its normal is 0; finite in float32)
LV_ITERS: int = 40  #: :func:`least_violation`'s iterations (it stops sooner once a step is negligible)
_CHUNK = 1 << 22  # largest line-by-constraint table (elements) of one chunk
_FEW = 2  # robots with at most this many constraints violated by t are a stage apart (their tables stay small) ...
_SPLIT = 1 << 16  # ... where one stage's line-by-constraint table would have more elements than this


class LocalAnswer(NamedTuple):
    """Answer per robot ``(R, ...)``: ``w``, unit-normal multipliers ``mu`` of its constraints, feasibility."""

    w: Any  #: ``(R, 2)``
    mu: Any  #: ``(R, C)``: ``2 (t - w) = sum_c mu_c n_c`` on the active constraints
    feasible: Any  #: ``(R,)`` bool


def _quiet(f):
    """``f`` without numpy's warnings: its infinities and divisions by 0 happen where a mask drops them."""

    @functools.wraps(f)
    def run(*args, **kwargs):
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            return f(*args, **kwargs)

    return run


def _const(x):
    """``x`` outside autograd (a torch tensor detached; a numpy array as it is)."""
    return x.detach() if hasattr(x, "detach") else x


def _put(xp, base, idx, new):
    """``base`` with its rows ``idx`` replaced by ``new``: a new array (autograd sees nothing changed in place)."""
    if isinstance(base, np.ndarray):  # (numpy: the short way)
        out = base.copy()
        out[idx] = new
        return out
    n = base.shape[0]
    pos = xp.arange(n, device=idx.device)
    pos[idx] = xp.arange(n, n + idx.shape[0], device=idx.device)
    return xp.take(xp.concat((base, new), axis=0), pos, axis=0)


def _rel_tol(xp, dtype) -> float:
    return 1e-10 if dtype == xp.float64 else 2e-5


@_quiet
def solve_polygons(t, nx, ny, b, t_box=None, rows: int = 0, tol: float | None = None) -> LocalAnswer:
    """Project ``t`` ``(R, 2)`` onto the polygons ``nx w_x + ny w_y <= b`` ``(R, C)`` (unit normals).

    An absent slot has ``n = 0``, ``b`` = :data:`FAR`; ``tol`` is relative to ``1 + |t|_inf`` (None: ``1e-10`` in
    float64, ``2e-5`` else).  Stages: ``t``; ``t_box`` (the projection onto the first ``C - rows`` constraints: the
    optimum where it meets the last ``rows``, whose multipliers are then 0, the others' not computed); the lines that
    ``t`` violates (:func:`_on_lines`).  An empty polygon gets the projection of least largest violation (``feasible``
    False; the filters loosen its rows, :func:`least_violation`).
    """
    xp = namespace(t)
    R, C = nx.shape
    tol = (_rel_tol(xp, t.dtype) if tol is None else tol) * (1.0 + xp.max(xp.abs(t), axis=1))
    viol0 = nx * t[:, 0:1] + ny * t[:, 1:2] - b
    w, mu = t, xp.zeros_like(b)
    out = xp.max(viol0, axis=1) > tol
    feasible = xp.ones_like(out)
    if t_box is not None and rows < C:
        box = out
        if rows:  # (no rows: the box's projection is the optimum)
            vb = xp.max(nx[:, C - rows:] * t_box[:, 0:1] + ny[:, C - rows:] * t_box[:, 1:2] - b[:, C - rows:], axis=1)
            box = out & (vb <= tol)
        w = xp.where(box[:, None], t_box, w)
        out = out & ~box
    todo = xp.nonzero(out)[0]
    if todo.shape[0] == 0:
        return LocalAnswer(w, mu, feasible)
    every = todo.shape[0] == R
    t1, nx1, ny1, b1, v1, tol1 = (x if every else xp.take(x, todo, axis=0) for x in (t, nx, ny, b, viol0, tol))
    count = xp.count_nonzero(v1 > 0, axis=1)
    few = count <= _FEW
    if todo.shape[0] * C * int(xp.max(count)) <= _SPLIT:  # (a small table: one stage)
        few = xp.ones_like(few)
    w1, f1 = xp.zeros_like(t1), xp.ones_like(few)
    for group in (few, ~few):  # (most robots violate a few lines: their tables stay small)
        rest = xp.nonzero(group)[0]
        if rest.shape[0] == 0:
            continue
        whole = rest.shape[0] == todo.shape[0]
        part = (t1, nx1, ny1, b1, v1, tol1, count)
        tr, nxr, nyr, br, vr, tolr, cr = part if whole else (xp.take(x, rest, axis=0) for x in part)
        o = xp.argsort(-_const(vr), axis=1, stable=True)[:, :int(xp.max(cr))]  # the violated lines
        lines = (xp.take_along_axis(x, o, axis=1) for x in (nxr, nyr, vr))
        ws, fs = _stage(xp, tr, *lines, nxr, nyr, br, tolr)
        w1, f1 = (ws, fs) if whole else (_put(xp, w1, rest, ws), _put(xp, f1, rest, fs))
    m1 = _multipliers(xp, *(_const(x) for x in (t1, w1, nx1, ny1, b1)), tol1, f1)
    if every:
        return LocalAnswer(w1, m1, f1)
    return LocalAnswer(_put(xp, w, todo, w1), _put(xp, mu, todo, m1), _put(xp, feasible, todo, f1))


def _stage(xp, t, kx, ky, vk, nx, ny, b, tol):
    """:func:`_on_lines` of robots' ``L`` lines ``(R, L)`` within their constraints ``(R, C)``, a chunk at once."""
    R, C = nx.shape
    per = max(1, _CHUNK // max(1, kx.shape[1] * C))
    parts = [_on_lines(xp, *(x[i:i + per] for x in (t, kx, ky, vk, nx, ny, b, tol))) for i in range(0, R, per)]
    return tuple(xp.concat(x) for x in zip(*parts)) if len(parts) > 1 else parts[0]


def _on_lines(xp, t, kx, ky, vk, nx, ny, b, tol):
    """The optimum ``(w, feasible)``: the nearest to ``t`` of the closest points on the violated lines ``k``.

    On line ``k`` (``p_k + sigma d_k``) the polygon leaves ``sigma`` in ``[lo, hi]`` (empty if ``lo > hi``, or a
    parallel constraint, ``|n' d_k|`` below ``1e-11`` or ``1e-6`` below float64, excludes it); the closest point is
    ``sigma = 0`` clamped into it.  None on any line: the polygon is empty, ``w`` its least largest violation.
    """
    s = xp.clip(vk, 0.0, None)
    px, py = t[:, 0:1] - s * kx, t[:, 1:2] - s * ky  # (R, L)
    nd = nx[:, None, :] * (-ky)[:, :, None] + ny[:, None, :] * kx[:, :, None]  # n_m' d_k (R, L, C), d_k = (-ny, nx)
    room = b[:, None, :] - (nx[:, None, :] * px[:, :, None] + ny[:, None, :] * py[:, :, None])
    par = xp.abs(nd) <= (1e-11 if t.dtype == xp.float64 else 1e-6)  # parallel to line k (rounding: duplicate lines)
    ratio = room / xp.where(par, 1.0, nd)  # (not used where parallel: no 0/0 in the gradient)
    hi = xp.min(xp.where(~par & (nd > 0), ratio, float("inf")), axis=2)
    lo = xp.max(xp.where(~par & (nd < 0), ratio, float("-inf")), axis=2)
    shut = xp.any(par & (room < -tol[:, None, None]), axis=2)
    ok = (vk > 0) & (lo <= hi + tol[:, None]) & ~shut
    sig = xp.minimum(xp.clip(lo, 0.0, None), hi)
    q = xp.argmin(_const(xp.where(ok, s * s + sig * sig, float("inf"))), axis=1, keepdims=True)
    feasible = xp.any(ok, axis=1)

    wq = xp.take_along_axis(xp.stack((px - sig * ky, py + sig * kx)), q[None], axis=2)[..., 0]  # on its line q
    w = xp.stack((wq[0], wq[1]), axis=1)
    if not bool(xp.all(feasible)):  # empty polygons: the projection of least largest violation
        bad = xp.nonzero(~feasible)[0]
        worst = xp.where(xp.take(vk, bad, axis=0) > 0, xp.max(-xp.take(room, bad, axis=0), axis=2),
                         float("inf"))
        qq = xp.argmin(_const(worst), axis=1, keepdims=True)
        pxq = xp.take_along_axis(xp.take(px, bad, axis=0), qq, axis=1)[:, 0]
        pyq = xp.take_along_axis(xp.take(py, bad, axis=0), qq, axis=1)[:, 0]
        w = _put(xp, w, bad, xp.stack((pxq, pyq), axis=1))
    return w, feasible


def _multipliers(xp, t, w, nx, ny, b, tol, feasible):
    """``(R, C)`` unit-normal multipliers at the optimum ``w``: ``2 (t - w) = sum_c mu_c n_c``, ``mu >= 0``.

    The active normals nearest in angle to ``t - w`` on either side of it span it (valid, if not unique, at a
    degenerate vertex); one along it (to ``1e-9`` rad) or one side empty: the nearest normal alone.
    """
    R, C = nx.shape
    rx, ry = t[:, 0:1] - w[:, 0:1], t[:, 1:2] - w[:, 1:2]
    act = xp.abs(nx * w[:, 0:1] + ny * w[:, 1:2] - b) <= tol[:, None]
    dot, cross = nx * rx + ny * ry, nx * ry - ny * rx
    along = xp.abs(cross) <= 1e-9 * xp.sqrt(rx * rx + ry * ry)
    left, right = act & (cross >= 0), act & (cross < 0)
    i = xp.argmax(xp.where(left, dot, float("-inf")), axis=1, keepdims=True)
    j = xp.argmax(xp.where(right, dot, float("-inf")), axis=1, keepdims=True)
    has_l, has_r = xp.any(left, axis=1), xp.any(right, axis=1)
    one = ~(has_l & has_r) | xp.any(act & along & (dot > 0), axis=1)
    i = xp.where(one[:, None], xp.argmax(xp.where(act, dot, float("-inf")), axis=1, keepdims=True), i)

    (n1x, n2x), (n1y, n2y) = xp.permute_dims(xp.take_along_axis(xp.stack((nx, ny)), xp.concat((i, j), axis=1)[None],
                                                                axis=2), (0, 2, 1))
    dx, dy = 2.0 * rx[:, 0], 2.0 * ry[:, 0]
    det = n1x * n2y - n1y * n2x
    two = ~one & (det != 0)
    d_ = xp.where(two, det, 1.0)
    mu1 = xp.where(two, (dx * n2y - dy * n2x) / d_, n1x * dx + n1y * dy)
    mu2 = xp.where(two, (n1x * dy - n1y * dx) / d_, 0.0)
    mu = xp.zeros((R, C), dtype=t.dtype, device=t.device)
    r = xp.arange(R, device=i.device)
    mu[r, i[:, 0]] = mu1
    mu[r, j[:, 0]] = mu[r, j[:, 0]] + mu2
    return xp.where((feasible & (has_l | has_r))[:, None], mu, 0.0)


# --------------------------------------------------------------------------- least violation of an empty polygon
def _box_qp(xp, hxx, hxy, hyy, gx, gy, lox, loy, hix, hiy):
    """Per robot ``argmin 0.5 d'Hd + g'd  s.t.  lo <= d <= hi`` (strictly convex ``H``): inside, else the best edge."""
    det = hxx * hyy - hxy * hxy
    dx = -(hyy * gx - hxy * gy) / det
    dy = -(hxx * gy - hxy * gx) / det
    inside = (dx >= lox) & (dx <= hix) & (dy >= loy) & (dy <= hiy)
    if bool(xp.all(inside)):
        return dx, dy
    ex, ey = best_edge(xp, hxx, hxy, hyy, gx, gy, lox, loy, hix, hiy)
    return xp.where(inside, dx, ex), xp.where(inside, dy, ey)


def _line_min(xp, res, delta):
    """Per robot the exact minimiser on ``[0, 1]`` of ``0.5 sum_r (res_r + t delta_r)_+^2`` (``(P, K)``).

    The derivative is piecewise linear and non-decreasing: the minimiser lies in the first piece (between sorted
    switching points) at whose end it is non-negative.
    """
    te = -res / xp.where(delta != 0, delta, 1.0)
    ev = (delta != 0) & (te > 0) & (te < 1)
    te = xp.where(ev, te, 2.0)
    order = xp.argsort(te, axis=1, stable=True)
    ts, dl, rs = xp.take_along_axis(xp.stack((te, xp.where(ev, delta, 0.0), res)), order[None], axis=2)
    sg = xp.sign(dl)  # delta > 0: the row switches on; delta < 0: off
    on0 = (res > 0) | ((res == 0) & (delta > 0))
    a0 = xp.sum(xp.where(on0, res * delta, 0.0), axis=1, keepdims=True)
    b0 = xp.sum(xp.where(on0, delta * delta, 0.0), axis=1, keepdims=True)
    A = xp.concat((a0, a0 + xp.cumulative_sum(sg * dl * rs, axis=1)), axis=1)
    B = xp.concat((b0, b0 + xp.cumulative_sum(sg * dl * dl, axis=1)), axis=1)
    one, zero = xp.ones_like(a0), xp.zeros_like(a0)
    ends = xp.clip(xp.concat((ts, one), axis=1), None, 1.0)
    starts = xp.concat((zero, ends[:, :-1]), axis=1)
    up = A + ends * B >= 0
    k = xp.where(xp.any(up, axis=1), xp.argmax(xp.astype(up, xp.int8), axis=1), ends.shape[1] - 1)[:, None]
    a, b, s0, s1 = xp.take_along_axis(xp.stack((A, B, starts, ends)), k[None], axis=2)[..., 0]
    t = xp.where(b > 0, -a / xp.where(b > 0, b, 1.0), xp.where(a >= 0, s0, s1))
    return xp.minimum(xp.maximum(t, s0), s1)


@_quiet
def least_violation(gx, gy, hh, lb, ub, x, max_iter: int = LV_ITERS):
    """The least-violation point ``(P, 2)`` of each robot's rows over its box and their violations there ``(P, K)``.

    Per robot ``min 0.5 sum_r (g_r x - h_r)_+^2  s.t.  lb <= x <= ub`` (unit rows ``gx, gy, hh``, absent slots ``0, 0,``
    :data:`FAR`; bounds ``(P, 2)``) from ``x``: each iteration minimises the violated rows' quadratic over the box
    (closed form, ``1e-10`` relative proximal term) and moves to the exact minimiser on the segment (:func:`_line_min`),
    until a step is below ``1e-11`` of the box (``1e-6`` below float64).  The violations at the minimum are unique, so
    the loosened rows are the same from any start.  Outside autograd.
    """
    xp = namespace(x)
    gx, gy, hh, lb, ub, x = (_const(a) for a in (gx, gy, hh, lb, ub, x))
    span = xp.clip(xp.max(ub - lb, axis=1), 1e-300, None)
    stop = 1e-11 if x.dtype == xp.float64 else 1e-6
    act = xp.ones_like(span, dtype=xp.bool)
    for _ in range(max_iter):
        if not bool(xp.any(act)):
            break
        res = gx * x[:, 0:1] + gy * x[:, 1:2] - hh
        on = res > 0
        ra = xp.where(on, res, 0.0)
        gxo, gyo = xp.where(on, gx, 0.0), xp.where(on, gy, 0.0)
        grx, gry = xp.sum(ra * gx, axis=1), xp.sum(ra * gy, axis=1)
        hxx, hxy, hyy = xp.sum(gxo * gx, axis=1), xp.sum(gxo * gy, axis=1), xp.sum(gyo * gy, axis=1)
        eps = 1e-10 * (hxx + hyy) + 1e-300
        dx, dy = _box_qp(xp, hxx + eps, hxy, hyy + eps, grx, gry, lb[:, 0] - x[:, 0], lb[:, 1] - x[:, 1],
                         ub[:, 0] - x[:, 0], ub[:, 1] - x[:, 1])
        delta = gx * dx[:, None] + gy * dy[:, None]
        rn = res + delta
        d1 = xp.sum(xp.where(rn > 0, rn, 0.0) * delta, axis=1)  # the slope at the full step
        full = d1 <= 0.0
        t = xp.ones_like(d1)
        part = xp.nonzero(~full)[0]
        if part.shape[0]:
            t = _put(xp, t, part, _line_min(xp, xp.take(res, part, axis=0), xp.take(delta, part, axis=0)))
        new = xp.stack((xp.minimum(xp.maximum(x[:, 0] + t * dx, lb[:, 0]), ub[:, 0]),
                        xp.minimum(xp.maximum(x[:, 1] + t * dy, lb[:, 1]), ub[:, 1])), axis=1)
        x = xp.where(act[:, None], new, x)
        # done: a negligible step, or a full step that kept the violated set (it minimised that set's quadratic)
        same = full & xp.all((rn > 0) == on, axis=1)
        act = act & ~same & (t * xp.maximum(xp.abs(dx), xp.abs(dy)) > stop * span)
    return x, xp.clip(gx * x[:, 0:1] + gy * x[:, 1:2] - hh, 0.0, None)
