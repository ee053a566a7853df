"""Every robot's 2-variable QP at once, exactly: the decentralised filter's local solver.

Robot ``k`` solves ``min 0.5 x' H_k x + g_k' x  s.t.  lb_k <= x <= ub_k, G_r x <= h_r``.  In ``y = L_k^T x`` (``H_k =
L_k L_k^T``) each QP projects ``y0 = -L^-1 g`` onto a polygon of unit half-planes: a robot whose minimiser meets its
constraints is answered by it, the others by :mod:`~aasoatt_env.safety.solvers.polygon`.  With ``relax=True`` an empty
polygon's robot gets its least-violation answer, as :func:`~aasoatt_env.safety.solvers.policy.solve_qp` gives the
centralised one: each row is loosened by its least violation (bounds hard) times ``1 + 1e-6`` plus a tolerance.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from aasoatt_env.compiled import c64, kernels
from aasoatt_env.safety.solvers.polygon import PAD_B, State, Table, solve

__all__ = ["LocalSolution", "solve_local_qps"]

TOL: float = 1e-10  #: the KKT check's feasibility / multiplier-sign tolerance (relative to ``1 + |y0|_inf``)
MAX_ITER: int = 50  #: active-set iterations before the unfinished robots go to the enumeration
RELAX_TOL: float = 1e-7  #: loosening on top of the least violation, in the normalised row's units (the policy's)
LS_ITERS: int = 4  #: regula falsi steps of phase 1's line search before its exact piecewise minimiser
LV_ITERS: int = 40  #: phase 1's iterations (it stops sooner once a step is negligible)


class LocalSolution(NamedTuple):
    """Answer of :func:`solve_local_qps`; multipliers in the rows' own units (of the loosened row if relaxed)."""

    x: np.ndarray  #: ``(N, 2)`` minimisers (``relax``: an infeasible robot's least-violation answer; else over the box)
    lam: np.ndarray  #: ``(M,)`` row multipliers (0 on an infeasible robot's rows without ``relax``)
    lam_box: np.ndarray  #: ``(N, 2, 2)`` bound multipliers (``[:, 0]``: ``x <= ub``)
    feasible: np.ndarray  #: ``(N,)`` the polygon is non-empty
    loosened: np.ndarray  #: ``(M,)`` each row's loosening
    iterations: int  #: the most of a robot and pass
    n_enumerated: int  #: robots enumerated


def _cholesky(H: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(l11, l21, l22)`` of ``H = L L^T`` per robot; ``ValueError`` if a block is not positive definite."""
    h00, h10, h11 = H[:, 0, 0], 0.5 * (H[:, 1, 0] + H[:, 0, 1]), H[:, 1, 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        l11 = np.sqrt(h00)
        l21 = h10 / l11
        d = h11 - l21 * l21
        l22 = np.sqrt(d)
    good = (h00 > 0) & (d > 0) & np.isfinite(l21) & np.isfinite(d)
    if not np.all(good):
        _bad_blocks(np.flatnonzero(~good))
    return l11, l21, l22


def _bad_blocks(bad: np.ndarray) -> None:
    raise ValueError(f"H: block(s) {bad[:5].tolist()} not symmetric positive definite")


def _slots(owner: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Rank of each row among its owner's rows ``(M,)`` and the row count per robot ``(N,)``."""
    m = owner.shape[0]
    counts = np.bincount(owner, minlength=n)
    starts = np.cumsum(counts) - counts
    if np.all(owner[1:] >= owner[:-1]):
        return np.arange(m) - starts[owner], counts
    key = owner.astype(np.int16 if n <= np.iinfo(np.int16).max else np.int32)  # int16: radix sort
    order = np.argsort(key, kind="stable")
    slot = np.empty(m, dtype=np.intp)
    slot[order] = np.arange(m) - starts[owner[order]]
    return slot, counts


def _table(linv, lb, ub, owner, G, h, tol_k, infeasible, zero_bad) -> Table:
    """Build the :class:`Table`; a zero row with ``h < 0`` (left out) marks its robot infeasible and itself bad."""
    n = lb.shape[0]
    i11, i21, i22 = linv  # L^-1 = [[i11, 0], [i21, i22]]
    slot, counts = _slots(owner, n)
    K = 4 + int(counts.max(initial=0))
    nx, ny = np.zeros((n, K)), np.zeros((n, K))
    b, row = np.full((n, K), PAD_B), np.full((n, K), -1, dtype=np.intp)
    # bounds: x_i <= ub_i is (L^-1 e_i)' y <= ub_i; L^-1 e_0 = (i11, i21), L^-1 e_1 = (0, i22)
    s0 = np.sqrt(i11 * i11 + i21 * i21)
    nx[:, 0], ny[:, 0], b[:, 0] = i11 / s0, i21 / s0, ub[:, 0] / s0
    ny[:, 1], b[:, 1] = 1.0, ub[:, 1] / i22
    nx[:, 2], ny[:, 2], b[:, 2] = -nx[:, 0], -ny[:, 0], -lb[:, 0] / s0
    ny[:, 3], b[:, 3] = -1.0, -lb[:, 1] / i22
    ax = i11[owner] * G[:, 0]
    ay = i21[owner] * G[:, 0] + i22[owner] * G[:, 1]
    nrm = np.sqrt(ax * ax + ay * ay)
    zero = nrm <= 1e-300 + 1e-14 * np.minimum(s0, i22)[owner]  # a vanishing normal: the row reads 0 <= h
    zb = np.flatnonzero(zero & (h < -tol_k[owner]))
    infeasible[owner[zb]] = True
    zero_bad[zb] = True
    ok = np.flatnonzero(~zero)
    ax, ay, nrm, hh, fi = ax[ok], ay[ok], nrm[ok], h[ok], owner[ok] * K + 4 + slot[ok]
    inv = 1.0 / nrm
    nx.reshape(-1)[fi] = ax * inv
    ny.reshape(-1)[fi] = ay * inv
    b.reshape(-1)[fi] = hh * inv
    row.reshape(-1)[fi] = ok
    return Table(nx, ny, b, row)


def solve_local_qps(H: np.ndarray, g: np.ndarray, lb: np.ndarray, ub: np.ndarray, owner: np.ndarray, G: np.ndarray,
                    h: np.ndarray, *, relax: bool = False, relax_tol: float | np.ndarray = RELAX_TOL, tol: float = TOL,
                    max_iter: int = MAX_ITER, compiled: bool = False) -> LocalSolution:
    """Solve every robot's 2-variable QP exactly (module docstring).

    ``H`` ``(N, 2, 2)``, ``g``, ``lb <= ub`` ``(N, 2)``; rows ``G_r x <= h_r`` of robot ``owner[r]`` (``h = +inf``:
    never binds).  ``relax_tol``: one or ``(N,)``, in the row's units normalised in ``x``.  ``compiled``: by
    :mod:`~aasoatt_env.safety.solvers.local_kernel` (the same decisions, numbers to rounding).  ``tol`` is relative to
    ``1 + |y0|_inf``, so the filter clips each nominal to its bounds before it forms ``g``.
    """
    H, g, lb, ub, owner, G, h, rt = _checked(H, g, lb, ub, owner, G, h, relax_tol, tol, max_iter)
    n, m = g.shape[0], owner.shape[0]
    out = LocalSolution(np.empty((n, 2)), np.zeros(m), np.zeros((n, 2, 2)), np.ones(n, dtype=bool), np.zeros(m), 0, 0)
    if n == 0:
        return out
    if compiled:
        bad = np.zeros(n, dtype=bool)
        its, n_enum = kernels("local").solve_all(
            *(c64(a) for a in (H, g, lb, ub)), np.ascontiguousarray(owner, dtype=np.int64), c64(G), c64(h),
            bool(relax), c64(np.broadcast_to(rt, (n,))), float(tol), int(max_iter), *out[:5], bad)
        if np.any(bad):
            _bad_blocks(np.flatnonzero(bad))
        return out._replace(iterations=int(its), n_enumerated=int(n_enum))
    its, n_enum = _solve_all(H, g, lb, ub, owner, G, h, relax, rt, tol, max_iter, out)
    return out._replace(iterations=its, n_enumerated=n_enum)


def _checked(H, g, lb, ub, owner, G, h, relax_tol, tol, max_iter) -> tuple:
    """The arguments of :func:`solve_local_qps` as arrays; ``ValueError`` naming a bad one."""
    H, g, lb, ub = (np.asarray(a, dtype=np.float64) for a in (H, g, lb, ub))
    owner = np.asarray(owner, dtype=np.intp).reshape(-1)
    G = np.asarray(G, dtype=np.float64).reshape(-1, 2)
    h = np.asarray(h, dtype=np.float64).reshape(-1)
    n, m = g.shape[0], owner.shape[0]
    if H.shape != (n, 2, 2) or g.shape != (n, 2) or lb.shape != (n, 2) or ub.shape != (n, 2):
        raise ValueError(f"H/g/lb/ub: got shapes {H.shape}/{g.shape}/{lb.shape}/{ub.shape}, expected (N,2,2)/(N,2)")
    if G.shape[0] != m or h.shape[0] != m:
        raise ValueError(f"owner/G/h: got {m}/{G.shape[0]}/{h.shape[0]} rows, expected equal counts")
    if m and (owner.min() < 0 or owner.max() >= n):
        raise ValueError("owner: row owner outside [0, N)")
    if np.any(lb > ub):
        raise ValueError("lb/ub: need lb <= ub")
    for name, a in (("H", H), ("g", g), ("lb", lb), ("ub", ub), ("G", G)):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name}: expected finite values, got {a[~np.isfinite(a)][:3].tolist()}")
    if np.any(np.isnan(h) | (h == -np.inf)):
        raise ValueError("h: expected finite values or +inf (a row that never binds), got NaN or -inf")
    if not (np.isfinite(tol) and tol > 0):
        raise ValueError(f"tol: expected a finite tolerance > 0, got {tol!r}")
    if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 0:
        raise ValueError(f"max_iter: expected an integer >= 0, got {max_iter!r}")
    rt = np.asarray(relax_tol, dtype=np.float64)
    if rt.ndim and rt.shape != (n,):
        raise ValueError(f"relax_tol: got shape {rt.shape}, expected one value or one per robot ({n},)")
    if not (np.all(np.isfinite(rt)) and np.all(rt >= 0)):
        raise ValueError("relax_tol: expected finite values >= 0")
    return H, g, lb, ub, owner, G, h, rt


class _Sub(NamedTuple):
    """The robots ``sub`` left to solve, their rows ``rsel`` (``owner`` renumbered), ``L^-1``, ``L``, ``y0``, bounds."""

    sub: np.ndarray
    rsel: np.ndarray
    owner: np.ndarray
    G: np.ndarray
    h: np.ndarray
    linv: tuple
    lfac: tuple
    y0: np.ndarray
    lb: np.ndarray
    ub: np.ndarray
    tol_k: np.ndarray


def _solve_all(H, g, lb, ub, owner, G, h, relax: bool, rt, tol: float, max_iter: int,
               out: LocalSolution) -> tuple[int, int]:
    """The numpy path of :func:`solve_local_qps`: fills ``out``'s arrays; ``(iterations, robots enumerated)``."""
    x, lam, lam_box, feasible, loosened = out[:5]
    s = _unconstrained(H, g, lb, ub, owner, G, h, tol, x)
    if s is None:
        return 0, 0
    ns = s.sub.size
    zero_infeasible, zero_bad = np.zeros(ns, dtype=bool), np.zeros(s.h.shape[0], dtype=bool)
    T = _table(s.linv, s.lb, s.ub, s.owner, s.G, s.h, s.tol_k, zero_infeasible, zero_bad)
    S = State(ns, s.y0)
    S.status[zero_infeasible] = 2  # a row 0 <= h < 0: infeasible as it stands
    start = np.flatnonzero(~zero_infeasible)
    y, mu, its, n_enum = solve(T, S, s.y0, s.tol_k, start, max_iter)
    ys, mus = s.y0.copy(), np.zeros((ns, 2))
    ys[start], mus[start] = y, mu
    feasible[s.sub] = S.status == 1
    bad = np.flatnonzero(S.status != 1)
    if bad.size and relax:
        its2, n2 = _relax(T, S, s, bad, np.broadcast_to(rt, (x.shape[0],))[s.sub], ys, mus, loosened, max_iter)
        its, n_enum = max(its, its2), n_enum + n2
        zb = np.flatnonzero(zero_bad)
        loosened[s.rsel[zb]] = -s.h[zb] * (1.0 + 1e-6)  # a zero row is met by loosening it to 0 <= 0
    i11, i21, i22 = s.linv
    xs = np.stack((i11 * ys[:, 0] + i21 * ys[:, 1], i22 * ys[:, 1]), axis=1)
    x[s.sub] = np.minimum(np.maximum(xs, s.lb), s.ub)
    _multipliers(T, S, s, mus, lam, lam_box)
    still = s.sub[(S.status == 2) | (S.status == 3)]
    if still.size:  # infeasible without relax (or a failed relaxation): the minimiser over the bounds alone
        x[still] = solve_local_qps(H[still], g[still], lb[still], ub[still], np.zeros(0, np.intp), np.zeros((0, 2)),
                                   np.zeros(0), tol=tol, max_iter=max_iter).x
    return its, n_enum


def _unconstrained(H, g, lb, ub, owner, G, h, tol: float, x: np.ndarray) -> _Sub | None:
    """Step 0: ``x`` the unconstrained minimisers; the robots that they leave (None: none)."""
    n = g.shape[0]
    l11, l21, l22 = _cholesky(H)
    i11, i22 = 1.0 / l11, 1.0 / l22
    i21 = -l21 * i11 * i22
    y0 = np.stack((-i11 * g[:, 0], -(i21 * g[:, 0] + i22 * g[:, 1])), axis=1)  # -L^-1 g
    x[:, 0] = i11 * y0[:, 0] + i21 * y0[:, 1]  # L^-T y0
    x[:, 1] = i22 * y0[:, 1]
    cons = (x[:, 0] < lb[:, 0]) | (x[:, 0] > ub[:, 0]) | (x[:, 1] < lb[:, 1]) | (x[:, 1] > ub[:, 1])
    viol = G[:, 0] * x[owner, 0] + G[:, 1] * x[owner, 1] - h
    cons |= np.bincount(owner[viol > 0.0], minlength=n) > 0
    sub = np.flatnonzero(cons)
    if sub.size == 0:
        return None
    remap = np.full(n, -1, dtype=np.intp)
    remap[sub] = np.arange(sub.size)
    rsel = np.flatnonzero(cons[owner])
    s_owner, Gs, hs = remap[owner[rsel]], G[rsel], h[rsel]
    sy0 = y0[sub]
    tol_k = tol * (1.0 + np.maximum(np.abs(sy0[:, 0]), np.abs(sy0[:, 1])))
    return _Sub(sub, rsel, s_owner, Gs, hs, (i11[sub], i21[sub], i22[sub]), (l11[sub], l21[sub], l22[sub]), sy0,
                lb[sub], ub[sub], tol_k)


def _multipliers(T: Table, S: State, s: _Sub, mus, lam, lam_box) -> None:
    """The optimal robots' active multipliers into ``lam`` and ``lam_box``, in the units of the rows as given."""
    i11, i21, i22 = s.linv
    done = np.flatnonzero(S.status == 1)
    K = T.nx.shape[1]
    s0 = np.sqrt(i11 * i11 + i21 * i21)
    for k, wk in ((0, S.w0), (1, S.w1)):
        sel = done[S.nw[done] > k]
        slot = wk[sel]
        r = T.row.reshape(-1)[sel * K + slot]
        isrow = r >= 0
        rs, ss = sel[isrow], r[isrow]
        a_x = i11[rs] * s.G[ss, 0]
        a_y = i21[rs] * s.G[ss, 0] + i22[rs] * s.G[ss, 1]
        np.add.at(lam, s.rsel[ss], mus[rs, k] / np.sqrt(a_x * a_x + a_y * a_y))  # mu / |L^-1 G_r|
        bs, bslot = sel[~isrow], slot[~isrow]
        np.add.at(lam_box, (s.sub[bs], bslot // 2, bslot % 2), mus[bs, k] / np.where(bslot % 2 == 0, s0[bs], i22[bs]))


def _relax(T: Table, S: State, s: _Sub, bad, rtol, ys, mus, loosened, max_iter: int) -> tuple[int, int]:
    """Least-violation answers of the infeasible robots ``bad`` (table indices); fills ``ys, mus, loosened``."""
    l11, l21, l22 = (v[bad] for v in s.lfac)
    i11, i21, i22 = (v[bad] for v in s.linv)
    nx, ny, b = T.nx[bad, 4:], T.ny[bad, 4:], T.b[bad, 4:]  # the rows (the bounds stay hard)
    real = b < PAD_B
    # the rows normalised in x: G ~ L n, so G / |G| = L n / |L n|, h / |G| = b / |L n|
    gx = l11[:, None] * nx
    gy = l21[:, None] * nx + l22[:, None] * ny
    ln = np.sqrt(gx * gx + gy * gy)
    inv = 1.0 / np.where(real, ln, 1.0)
    gx, gy, hh = gx * inv, gy * inv, np.where(real, b * inv, PAD_B)
    # from the active set's last point (inside the bounds after clipping)
    x0 = np.stack((i11 * S.yx[bad] + i21 * S.yy[bad], i22 * S.yy[bad]), axis=1)
    x0 = np.minimum(np.maximum(np.where(np.isfinite(x0), x0, 0.0), s.lb[bad]), s.ub[bad])
    x1, viol = _lv_core(gx, gy, hh, s.lb[bad], s.ub[bad], x0)
    loosen_n = (viol * (1.0 + 1e-6) + rtol[bad][:, None]) * real  # in normalised x units
    T.b[bad, 4:] = b + loosen_n * ln  # in y units: (G x - h) / |L^-1 G| = |L n| * (G x - h) / |G|
    rows = T.row[bad, 4:][real]
    loosened[s.rsel[rows]] = loosen_n[real] * np.sqrt(s.G[rows, 0] ** 2 + s.G[rows, 1] ** 2)
    S.reset(bad, s.y0)
    y, mu, its, n_enum = solve(T, S, s.y0, s.tol_k, bad, max_iter)
    ok = S.status[bad] == 1
    ys[bad] = np.where(ok[:, None], y, 0.0)
    mus[bad] = np.where(ok[:, None], mu, 0.0)
    fail = ~ok
    if np.any(fail):  # a failed relaxation keeps the phase-1 point
        ys[bad[fail], 0] = l11[fail] * x1[fail, 0] + l21[fail] * x1[fail, 1]
        ys[bad[fail], 1] = l22[fail] * x1[fail, 1]
        S.status[bad[fail]] = 4  # relaxed by phase 1 alone (no multipliers)
    return its, n_enum


def _box_qp(hxx, hxy, hyy, gx, gy, lox, loy, hix, hiy):
    """Per robot ``argmin 0.5 d'Hd + g'd  s.t.  lo <= d <= hi`` for strictly convex 2x2 ``H`` (closed form)."""
    det = hxx * hyy - hxy * hxy
    with np.errstate(divide="ignore", invalid="ignore"):  # det 0: a robot without violated rows (an edge wins)
        dx = -(hyy * gx - hxy * gy) / det
        dy = -(hxx * gy - hxy * gx) / det
    inside = (dx >= lox) & (dx <= hix) & (dy >= loy) & (dy <= hiy)
    if np.all(inside):
        return dx, dy
    best = np.full(dx.shape, np.inf)
    bx, by = dx.copy(), dy.copy()
    for e, c in enumerate((lox, hix, loy, hiy)):  # the edges d_x = lo, hi, then d_y = lo, hi
        ex = c if e < 2 else np.clip(-(gx + hxy * c) / hxx, lox, hix)
        ey = np.clip(-(gy + hxy * c) / hyy, loy, hiy) if e < 2 else c
        f = 0.5 * (hxx * ex * ex + 2 * hxy * ex * ey + hyy * ey * ey) + gx * ex + gy * ey
        take = ~inside & (f < best)
        best, bx, by = np.where(take, f, best), np.where(take, ex, bx), np.where(take, ey, by)
    return bx, by


def _line_search(res: np.ndarray, delta: np.ndarray, d0: np.ndarray, d1: np.ndarray,
                 iters: int = LS_ITERS) -> np.ndarray:
    """Per robot ``argmin_{t in [0, 1]} phi(t) = 0.5 sum_r (res_r + t delta_r)_+^2``, given ``phi'(0) < 0 < phi'(1)``.

    ``phi'`` is continuous, non-decreasing, piecewise linear: regula falsi (Illinois) lands on its root once the
    bracket lies in one piece (most robots); the others go to :func:`_line_min`, which sorts the points where a row
    switches and solves the piece where ``phi'`` turns non-negative.
    """
    one = np.ones(res.shape[1])
    a, b = np.zeros(d0.shape), np.ones(d0.shape)
    fa, fb = d0.copy(), d1.copy()
    side = np.zeros(d0.shape)
    t = np.ones(d0.shape)
    tol = 1e-13 * (np.abs(d0) + np.abs(d1))
    act = np.arange(d0.shape[0])  # robots still searching: one that has landed keeps its root
    for _ in range(iters):
        ta = (a[act] * fb[act] - b[act] * fa[act]) / (fb[act] - fa[act])
        t[act] = ta
        ft = (np.maximum(res[act] + ta[:, None] * delta[act], 0.0) * delta[act]) @ one
        left = np.abs(ft) > tol[act]
        act, ta, ft = act[left], ta[left], ft[left]
        if act.size == 0:
            return t
        neg = ft < 0
        sd = side[act]
        a[act], fa[act] = np.where(neg, ta, a[act]), np.where(neg, ft, fa[act])
        b[act], fb[act] = np.where(neg, b[act], ta), np.where(neg, fb[act], ft)
        fb[act] = np.where(neg & (sd > 0), 0.5 * fb[act], fb[act])  # the same end kept twice: halve its weight
        fa[act] = np.where(~neg & (sd < 0), 0.5 * fa[act], fa[act])
        side[act] = np.where(neg, 1.0, -1.0)
    t[act] = _line_min(res[act], delta[act])
    return t


def _line_min(res: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Per robot the exact minimiser of :func:`_line_search`'s ``phi`` on ``[0, 1]`` (``res``, ``delta`` ``(P, K)``)."""
    p = res.shape[0]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # padding rows: res = -1e300
        te = -res / delta
    ev = (delta != 0) & (te > 0) & (te < 1)
    te = np.where(ev, te, 2.0)
    order = np.argsort(te, axis=1)
    ts = np.take_along_axis(te, order, axis=1)
    dl = np.take_along_axis(np.where(ev, delta, 0.0), order, axis=1)
    rs = np.take_along_axis(res, order, axis=1)
    sg = np.sign(dl)  # delta > 0: the row switches on; delta < 0: off
    on0 = (res > 0) | ((res == 0) & (delta > 0))
    a0 = np.where(on0, res * delta, 0.0).sum(axis=1)
    b0 = np.where(on0, delta * delta, 0.0).sum(axis=1)
    A = np.concatenate((a0[:, None], a0[:, None] + np.cumsum(sg * dl * rs, axis=1)), axis=1)
    B = np.concatenate((b0[:, None], b0[:, None] + np.cumsum(sg * dl * dl, axis=1)), axis=1)
    ends = np.minimum(np.concatenate((ts, np.ones((p, 1))), axis=1), 1.0)
    starts = np.concatenate((np.zeros((p, 1)), ends[:, :-1]), axis=1)
    up = A + ends * B >= 0
    k = np.where(up.any(axis=1), up.argmax(axis=1), ends.shape[1] - 1)
    r = np.arange(p)
    a, b, s0, s1 = A[r, k], B[r, k], starts[r, k], ends[r, k]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(b > 0, -a / b, np.where(a >= 0, s0, s1))
    return np.clip(t, s0, s1)


def _lv_core(gx, gy, hh, lb, ub, x, max_iter: int = LV_ITERS):
    """Phase 1 on unit rows ``(P, K)`` (padding: ``hh = PAD_B``) from ``x``: ``(x, violations (P, K))``.

    Per robot ``min 0.5 sum_r (g_r x - h_r)_+^2  s.t.  lb <= x <= ub``, convex and piecewise quadratic: each iteration
    minimises the violated rows' quadratic over the box (closed form, a ``1e-10`` relative proximal term) and moves to
    the exact minimiser on the segment to it, until a step is below ``1e-11`` of the box.  The violations are unique.
    """
    x = x.copy()
    P, K = gx.shape
    one = np.ones(K)
    span = np.maximum(np.maximum(ub[:, 0] - lb[:, 0], ub[:, 1] - lb[:, 1]), 1e-300)
    act = np.arange(P)
    for _ in range(max_iter):
        if act.size == 0:
            break
        if act.size == P:
            gxa, gya, hha, xa = gx, gy, hh, x.copy()
        else:
            gxa, gya, hha, xa = gx[act], gy[act], hh[act], x[act]
        res = gxa * xa[:, 0:1] + gya * xa[:, 1:2] - hha
        on = res > 0
        ra = res * on
        gxo, gyo = gxa * on, gya * on
        grx, gry = (ra * gxa) @ one, (ra * gya) @ one
        hxx, hxy, hyy = (gxo * gxa) @ one, (gxo * gya) @ one, (gyo * gya) @ one
        eps = 1e-10 * (hxx + hyy) + 1e-300
        dx, dy = _box_qp(hxx + eps, hxy, hyy + eps, grx, gry, lb[act, 0] - xa[:, 0], lb[act, 1] - xa[:, 1],
                         ub[act, 0] - xa[:, 0], ub[act, 1] - xa[:, 1])
        delta = gxa * dx[:, None] + gya * dy[:, None]
        rn = res + delta
        on1 = rn > 0
        d1 = (rn * on1 * delta) @ one  # phi'(1): the full step is the minimiser on the segment where <= 0
        full = d1 <= 0.0
        t = np.ones(act.size)
        part = np.flatnonzero(~full)
        if part.size:
            t[part] = _line_search(res[part], delta[part], grx[part] * dx[part] + gry[part] * dy[part], d1[part])
        x[act, 0] = np.clip(xa[:, 0] + t * dx, lb[act, 0], ub[act, 0])
        x[act, 1] = np.clip(xa[:, 1] + t * dy, lb[act, 1], ub[act, 1])
        # done: a negligible step, or a full step that kept the violated set (it minimised F's own quadratic)
        same = full & ((on1 != on) @ one == 0)
        act = act[~same & (t * np.maximum(np.abs(dx), np.abs(dy)) > 1e-11 * span[act])]
    viol = np.maximum(gx * x[:, 0:1] + gy * x[:, 1:2] - hh, 0.0)
    return x, viol
