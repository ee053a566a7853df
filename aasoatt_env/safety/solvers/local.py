"""Every robot's 2-variable QP at once, exactly: the decentralised filter's local solver.

Robot ``k``: ``min 0.5 x' H_k x + g_k' x  s.t.  lb_k <= x <= ub_k, G_r x <= h_r``, in ``y = L_k^T x`` the projection
of ``y0 = -L^-1 g`` onto a polygon of unit half-planes (:func:`~.polygons.solve_polygons`).  ``relax=True``: an empty
polygon's rows are loosened by their least violation (bounds hard, :func:`~.polygons.least_violation`) times
``1 + 1e-6`` plus a tolerance, as the centralised policy does.  ``compiled=True``: :mod:`~.local_kernel`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from aasoatt_env.compiled import c64, kernels
from aasoatt_env.safety.problem import box_ls
from aasoatt_env.safety.solvers.polygons import FAR, least_violation, solve_polygons

__all__ = ["LocalSolution", "solve_local_qps"]

TOL: float = 1e-10  #: the feasibility tolerance (relative to ``1 + |y0|_inf``; the kernel's KKT check's too)
MAX_ITER: int = 50  #: the compiled kernel's active-set iterations before it enumerates a robot's candidates
RELAX_TOL: float = 1e-7  #: loosening on top of the least violation, in the normalised row's units (the policy's)
PAD_B: float = 1e300  #: a row whose ``h / |L^-1 G|`` is not below this never binds: left out of the table


class LocalSolution(NamedTuple):
    """Answer of :func:`solve_local_qps`; multipliers in the rows' own units (of the loosened row if relaxed)."""

    x: np.ndarray  #: ``(N, 2)`` minimisers (``relax``: an infeasible robot's least-violation answer; else over the box)
    lam: np.ndarray  #: ``(M,)`` row multipliers (0 on an infeasible robot's rows without ``relax``)
    lam_box: np.ndarray  #: ``(N, 2, 2)`` bound multipliers (``[:, 0]``: ``x <= ub``)
    feasible: np.ndarray  #: ``(N,)`` the polygon is non-empty
    loosened: np.ndarray  #: ``(M,)`` each row's loosening
    iterations: int  #: the compiled kernel's most active-set iterations of a robot and pass (numpy: 0, it has none)
    n_enumerated: int  #: robots the compiled kernel enumerated (numpy: 0)


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


class Table(NamedTuple):
    """Half-planes ``n' y <= b`` of every robot ``(N, K)``: slots 0-3 ``x <= ub``, ``x >= lb``, then its rows.

    ``row``: each slot's row, or -1 (a bound; padding: ``n = 0``, ``b = FAR``).
    """

    nx: np.ndarray
    ny: np.ndarray
    b: np.ndarray
    row: np.ndarray


def _table(linv, lb, ub, owner, G, h, tol_k, infeasible, zero_bad) -> Table:
    """The :class:`Table` but zero rows (with ``h < 0``: marked bad, robot infeasible) and never-binding ones."""
    n = lb.shape[0]
    i11, i21, i22 = linv  # L^-1 = [[i11, 0], [i21, i22]]
    slot, counts = _slots(owner, n)
    K = 4 + int(counts.max(initial=0))
    nx, ny = np.zeros((n, K)), np.zeros((n, K))
    b, row = np.full((n, K), FAR), np.full((n, K), -1, dtype=np.intp)
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
    inv = 1.0 / nrm[ok]
    hn = h[ok] * inv
    keep = hn < PAD_B
    ok, inv, hn = ok[keep], inv[keep], hn[keep]
    fi = owner[ok] * K + 4 + slot[ok]
    nx.reshape(-1)[fi] = ax[ok] * inv
    ny.reshape(-1)[fi] = ay[ok] * inv
    b.reshape(-1)[fi] = hn
    row.reshape(-1)[fi] = ok
    return Table(nx, ny, b, row)


def solve_local_qps(H: np.ndarray, g: np.ndarray, lb: np.ndarray, ub: np.ndarray, owner: np.ndarray, G: np.ndarray,
                    h: np.ndarray, *, relax: bool = False, relax_tol: float | np.ndarray = RELAX_TOL, tol: float = TOL,
                    max_iter: int = MAX_ITER, compiled: bool = False) -> LocalSolution:
    """Solve every robot's 2-variable QP exactly (module docstring).

    ``H`` ``(N, 2, 2)``, ``g``, ``lb <= ub`` ``(N, 2)``; rows ``G_r x <= h_r`` of robot ``owner[r]`` (``h = +inf``:
    never binds).  ``relax_tol``: one or ``(N,)``, in the row's units normalised in ``x``; ``tol``: relative to
    ``1 + |y0|_inf`` (the filter clips each nominal to its bounds first); ``max_iter``: the compiled kernel's
    active-set iterations.  ``compiled``: the same decisions, answers to rounding (a relaxed robot's to the
    least-violation iteration's stopping tolerance).
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
    _solve_all(H, g, lb, ub, owner, G, h, relax, rt, tol, out)
    return out


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


def _solve_all(H, g, lb, ub, owner, G, h, relax: bool, rt, tol: float, out: LocalSolution) -> None:
    """The numpy path of :func:`solve_local_qps`: fills ``out``'s arrays."""
    x, lam, lam_box, feasible, loosened = out[:5]
    s = _unconstrained(H, g, lb, ub, owner, G, h, tol, x)
    if s is None:
        return
    ns = s.sub.size
    zero_infeasible, zero_bad = np.zeros(ns, dtype=bool), np.zeros(s.h.shape[0], dtype=bool)
    T = _table(s.linv, s.lb, s.ub, s.owner, s.G, s.h, s.tol_k, zero_infeasible, zero_bad)
    ans = solve_polygons(s.y0, T.nx, T.ny, T.b, tol=tol)
    ok = ans.feasible & ~zero_infeasible  # (a row 0 <= h < 0: infeasible as it stands)
    feasible[s.sub] = ok
    ys, mu, done = np.array(ans.w), ans.mu, ok.copy()
    bad = np.flatnonzero(~ok)
    xb = _box_minimisers(s, bad) if bad.size else None
    if bad.size and relax:
        done[bad] = _relax(T, s, bad, np.broadcast_to(rt, (x.shape[0],))[s.sub], xb, tol, ys, mu, loosened)
        zb = np.flatnonzero(zero_bad)
        loosened[s.rsel[zb]] = -s.h[zb] * (1.0 + 1e-6)  # a zero row is met by loosening it to 0 <= 0
    i11, i21, i22 = s.linv
    xs = np.stack((i11 * ys[:, 0] + i21 * ys[:, 1], i22 * ys[:, 1]), axis=1)
    x[s.sub] = np.minimum(np.maximum(xs, s.lb), s.ub)
    if bad.size and not relax:  # infeasible without relax: the minimiser over the bounds alone
        x[s.sub[bad]] = xb
    _multipliers(T, s, np.flatnonzero(done), mu, lam, lam_box)


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


def _box_minimisers(s: _Sub, idx: np.ndarray) -> np.ndarray:
    """The minimisers ``(len(idx), 2)`` over the bounds alone of robots ``idx``: ``|L' x - y0|^2`` over the box."""
    l11, l21, l22 = (v[idx] for v in s.lfac)
    return box_ls(l11, l21, np.zeros_like(l11), l22, s.y0[idx], s.lb[idx], s.ub[idx])


def _multipliers(T: Table, s: _Sub, done: np.ndarray, mu: np.ndarray, lam, lam_box) -> None:
    """The robots ``done``'s multipliers into ``lam``, ``lam_box``: ``mu / 2`` over ``|L^-1 G_r|`` (``|L^-1 e_i|``)."""
    if done.size == 0:
        return
    i11, i21, i22 = (v[done] for v in s.linv)
    m = np.maximum(0.5 * mu[done], 0.0)  # (>= 0 at the optimum: a negative one is rounding)
    s0 = np.sqrt(i11 * i11 + i21 * i21)
    lam_box[s.sub[done]] = (m[:, :4] / np.stack((s0, i22, s0, i22), axis=1)).reshape(-1, 2, 2)
    ri, ci = np.nonzero(T.row[done, 4:] >= 0)
    r = T.row[done[ri], 4 + ci]
    ax = i11[ri] * s.G[r, 0]
    ay = i21[ri] * s.G[r, 0] + i22[ri] * s.G[r, 1]
    lam[s.rsel[r]] = m[ri, 4 + ci] / np.sqrt(ax * ax + ay * ay)


def _relax(T: Table, s: _Sub, bad, rtol, x0, tol: float, ys, mu, loosened) -> np.ndarray:
    """Least-violation answers of robots ``bad`` from ``x0`` (into ``ys``, ``mu``, ``loosened``); which got one."""
    l11, l21, l22 = (v[bad] for v in s.lfac)
    nx, ny, b = T.nx[bad, 4:], T.ny[bad, 4:], T.b[bad, 4:]  # the rows (the bounds stay hard)
    real = T.row[bad, 4:] >= 0
    # the rows normalised in x: G ~ L n, so G / |G| = L n / |L n|, h / |G| = b / |L n|
    gx = l11[:, None] * nx
    gy = l21[:, None] * nx + l22[:, None] * ny
    ln = np.sqrt(gx * gx + gy * gy)
    inv = 1.0 / np.where(real, ln, 1.0)
    gx, gy, hh = gx * inv, gy * inv, np.where(real, b * inv, FAR)
    x1, viol = least_violation(gx, gy, hh, s.lb[bad], s.ub[bad], x0)
    loosen_n = (viol * (1.0 + 1e-6) + rtol[bad][:, None]) * real  # in normalised x units
    # in y units: (G x - h) / |L^-1 G| = |L n| (G x - h) / |G|
    b2 = np.concatenate((T.b[bad, :4], b + loosen_n * ln), axis=1)
    rows = T.row[bad, 4:][real]
    loosened[s.rsel[rows]] = loosen_n[real] * np.sqrt(s.G[rows, 0] ** 2 + s.G[rows, 1] ** 2)
    again = solve_polygons(s.y0[bad], T.nx[bad], T.ny[bad], b2, tol=tol)
    ok = again.feasible
    ys[bad] = np.where(ok[:, None], again.w, np.stack((l11 * x1[:, 0] + l21 * x1[:, 1], l22 * x1[:, 1]), axis=1))
    mu[bad] = again.mu
    return ok
