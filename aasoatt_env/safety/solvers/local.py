"""Exact solver for many independent 2-variable QPs at once (the decentralised filter's per-robot QPs).

Robot ``k`` solves::

    min  0.5 x' H_k x + g_k' x   s.t.  lb_k <= x <= ub_k,   G_r x <= h_r  for its rows r

with ``H_k`` a 2x2 symmetric positive definite matrix.  In ``y = L_k^T x``
(``H_k = L_k L_k^T``, closed-form 2x2 Cholesky) the objective is
``0.5 |y - y0|^2 + const`` with ``y0 = -L^-1 g`` and every constraint, the four
bounds included, is a half-plane ``n' y <= b`` (normalised, ``|n| = 1``): each
QP is the projection of a point onto a convex polygon.

Method, vectorised across robots with masks (no Python loop over robots or rows):

0. a robot whose unconstrained minimiser meets its bounds and all its rows is
   answered by it (exactly; most robots of a spread-out team);
1. the constraints of the other robots are packed into an ``(N, K)`` table (four
   bound slots, then the robot's rows, padded with slots never violated);
2. the dual active-set method of Goldfarb and Idnani specialised to the plane:
   add the most violated constraint, taking a partial step and dropping the
   active constraint whose multiplier reaches zero first; at most two
   constraints are active; a new constraint that depends on the active ones with
   no positive coefficient proves the polygon empty (a Farkas certificate of at
   most three constraints);
3. a KKT check on the point recomputed from the final active set (primal
   feasibility of every constraint and multiplier signs within
   ``tol * (1 + |y0|_inf)``), and a check of each infeasibility certificate;
4. robots not verified (iteration cap, a failed check) are solved by exact
   enumeration: every candidate point (``y0``, the projection onto each single
   constraint line, each vertex of two non-parallel lines) with its multipliers;
   the optimum is the nearest candidate that is feasible with non-negative
   multipliers, and the polygon is empty when there is none.

With ``relax=True`` a robot whose polygon is empty gets the least-violation
answer of its own QP, as :func:`aasoatt_env.safety.solvers.policy.solve_qp` gives
the centralised one: phase 1 finds the least violation ``s_r`` of each of its
rows with the bounds hard (:func:`least_violation`), every row is loosened by
``s_r (1 + 1e-6)`` plus a tolerance, and the loosened QP is solved by steps 2-4.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from aasoatt_env.compiled import c64, kernels

__all__ = ["LocalSolution", "least_violation", "solve_local_qps"]

TOL: float = 1e-10
"""Feasibility / multiplier-sign tolerance of the KKT check (normalised half-planes, relative to ``1 + |y0|_inf``)."""
MAX_ITER: int = 50
"""Active-set iterations before the unfinished robots go to the enumeration."""
RELAX_TOL: float = 1e-7
"""Default loosening on top of the least violation, in units of the normalised row (the policy's value)."""
_EPS_Z = 1e-22
"""A new constraint whose normal has less than this squared component off the active ones depends on them."""
_EPS_R = 1e-14
"""Coefficients of a dependent normal below this count as non-positive."""
_PAD_B = 1e300
"""Right-hand side of padding slots (never violated)."""
_ENUM_CHUNK = 1 << 20
"""Largest candidate-by-constraint table of one enumeration chunk (elements)."""


class LocalSolution(NamedTuple):
    """Answer of :func:`solve_local_qps`."""

    x: np.ndarray
    """Minimisers ``(N, 2)`` (within the bounds).  Infeasible robots: their least-violation answer with
    ``relax=True``, else the minimiser over the bounds alone."""
    lam: np.ndarray
    """Multiplier of each row ``(M,)`` (``>= 0``) in the units of the objective and of the row as given
    (of the loosened row for relaxed robots; 0 on rows of infeasible robots without ``relax``)."""
    lam_box: np.ndarray
    """Multipliers of the bounds ``(N, 2, 2)``: ``[:, 0]`` of ``x <= ub``, ``[:, 1]`` of ``x >= lb``."""
    feasible: np.ndarray
    """``(N,)``: the robot's own polygon is non-empty."""
    loosened: np.ndarray
    """How much each row was loosened ``(M,)`` in its own units (0 except on rows of relaxed robots)."""
    iterations: int
    """Active-set iterations run (the largest over the robots and the two passes)."""
    n_enumerated: int
    """Robots answered by the exact enumeration."""


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
    if m == 0:
        return np.zeros(0, dtype=np.intp), counts
    starts = np.cumsum(counts) - counts
    if np.all(owner[1:] >= owner[:-1]):
        return np.arange(m) - starts[owner], counts
    key = owner.astype(np.int16 if n <= np.iinfo(np.int16).max else np.int32)  # int16: radix sort
    order = np.argsort(key, kind="stable")
    slot = np.empty(m, dtype=np.intp)
    slot[order] = np.arange(m) - starts[owner[order]]
    return slot, counts


class _Table(NamedTuple):
    """Half-planes ``n' y <= b`` of every robot, padded to ``(N, K)``; slots 0-3 are the bounds."""

    nx: np.ndarray
    ny: np.ndarray
    b: np.ndarray
    row: np.ndarray
    """Row of each slot ``(N, K)``, -1 for the bounds and padding."""


def _table(linv, lb, ub, owner, G, h, tol_k, infeasible, zero_bad) -> _Table:
    """Build the :class:`_Table`.

    A zero row with a negative right-hand side (``0 <= h < 0``, left out of the table)
    marks its robot infeasible and itself in ``zero_bad``.
    """
    n = lb.shape[0]
    i11, i21, i22 = linv  # L^-1 = [[i11, 0], [i21, i22]]
    slot, counts = _slots(owner, n)
    K = 4 + int(counts.max(initial=0))
    nx = np.zeros((n, K))
    ny = np.zeros((n, K))
    b = np.full((n, K), _PAD_B)
    row = np.full((n, K), -1, dtype=np.intp)
    # bounds: x_i <= ub_i is (L^-1 e_i)' y <= ub_i; L^-1 e_0 = (i11, i21), L^-1 e_1 = (0, i22)
    s0 = np.sqrt(i11 * i11 + i21 * i21)
    nx[:, 0], ny[:, 0], b[:, 0] = i11 / s0, i21 / s0, ub[:, 0] / s0
    ny[:, 1], b[:, 1] = 1.0, ub[:, 1] / i22
    nx[:, 2], ny[:, 2], b[:, 2] = -nx[:, 0], -ny[:, 0], -lb[:, 0] / s0
    ny[:, 3], b[:, 3] = -1.0, -lb[:, 1] / i22
    if owner.shape[0]:
        ax = i11[owner] * G[:, 0]
        ay = i21[owner] * G[:, 0] + i22[owner] * G[:, 1]
        nrm = np.sqrt(ax * ax + ay * ay)
        # a row whose normal vanishes (relative to the robot's bounds) reads 0 <= h
        zero = nrm <= 1e-300 + 1e-14 * np.minimum(s0, i22)[owner]
        if np.any(zero):
            zb = np.flatnonzero(zero & (h < -tol_k[owner]))
            infeasible[owner[zb]] = True
            zero_bad[zb] = True
            ok = np.flatnonzero(~zero)
            ax, ay, nrm, hh, fi = ax[ok], ay[ok], nrm[ok], h[ok], owner[ok] * K + 4 + slot[ok]
        else:
            ok, hh, fi = np.arange(owner.shape[0]), h, owner * K + 4 + slot
        inv = 1.0 / nrm
        nx.reshape(-1)[fi] = ax * inv
        ny.reshape(-1)[fi] = ay * inv
        b.reshape(-1)[fi] = hh * inv
        row.reshape(-1)[fi] = ok
    return _Table(nx, ny, b, row)


def _vertex(n1x, n1y, b1, n2x, n2y, b2):
    """Intersection of two lines ``n' y = b`` (arrays; NaN/inf where parallel) and the determinant."""
    det = n1x * n2y - n1y * n2x
    with np.errstate(divide="ignore", invalid="ignore"):
        return (b1 * n2y - b2 * n1y) / det, (n1x * b2 - n2x * b1) / det, det


class _State:
    """Active-set state of every robot of a table (1-D arrays)."""

    def __init__(self, n: int, y0: np.ndarray) -> None:
        self.yx, self.yy = y0[:, 0].copy(), y0[:, 1].copy()
        self.nw = np.zeros(n, dtype=np.intp)
        self.w0 = np.zeros(n, dtype=np.intp)
        self.w1 = np.zeros(n, dtype=np.intp)
        self.l1 = np.zeros(n)
        self.l2 = np.zeros(n)
        self.p = np.full(n, -1, dtype=np.intp)
        self.lp = np.zeros(n)
        self.status = np.zeros(n, dtype=np.int8)  # 0 running, 1 optimal, 2 certificate, 3 enumerate
        self.r1 = np.zeros(n)  # coefficients of a dependent new constraint (infeasibility certificate)
        self.r2 = np.zeros(n)

    def reset(self, idx: np.ndarray, y0: np.ndarray) -> None:
        self.yx[idx], self.yy[idx] = y0[idx, 0], y0[idx, 1]
        for arr in (self.nw, self.w0, self.w1, self.l1, self.l2, self.lp, self.status, self.r1, self.r2):
            arr[idx] = 0
        self.p[idx] = -1


def _active_set(T: _Table, S: _State, y0, tol_k, start, max_iter) -> int:
    """Goldfarb-Idnani in the plane for robots ``start`` of ``T`` (module docstring step 2); iterations run.

    Each iteration first gives every robot without a constraint in progress the most
    violated one (or finishes it), then takes one step per robot, by the size of its
    active set: none (a full step onto the new constraint), one (a full step to the
    vertex, or a partial step that drops the old constraint), two (a partial step that
    drops one of them, or the certificate of an empty polygon).
    """
    K = T.nx.shape[1]
    NX, NY, B = T.nx.reshape(-1), T.ny.reshape(-1), T.b.reshape(-1)
    n = T.nx.shape[0]
    act = start
    iterations = 0
    for it in range(max_iter):
        if act.size == 0:
            break
        iterations = it + 1
        need = act[S.p[act] < 0]
        if need.size:
            if need.size == n:
                V = T.nx * S.yx[:, None] + T.ny * S.yy[:, None] - T.b
            else:
                V = T.nx[need] * S.yx[need, None] + T.ny[need] * S.yy[need, None] - T.b[need]
            kmax = V.argmax(axis=1)
            vmax = V.reshape(-1)[np.arange(need.size) * K + kmax]
            fine = vmax <= tol_k[need]
            if np.any(fine):
                S.status[need[fine]] = 1
                act = act[S.status[act] == 0]
                if act.size == 0:
                    break
                kmax, need = kmax[~fine], need[~fine]
            S.p[need] = kmax
            S.lp[need] = 0.0
        k = S.nw[act]
        dead = []
        # ---- no active constraint: a full step onto n_p
        a = act[k == 0]
        if a.size:
            pk = S.p[a]
            ip = a * K + pk
            npx, npy = NX[ip], NY[ip]
            t = (npx * S.yx[a] + npy * S.yy[a] - B[ip]) / (npx * npx + npy * npy)
            S.yx[a] -= t * npx
            S.yy[a] -= t * npy
            S.w0[a], S.l1[a], S.nw[a], S.p[a], S.lp[a] = pk, S.lp[a] + t, 1, -1, 0.0
        # ---- one active constraint n1
        a = act[k == 1]
        if a.size:
            pk, w0 = S.p[a], S.w0[a]
            ip, i0 = a * K + pk, a * K + w0
            npx, npy, n1x, n1y = NX[ip], NY[ip], NX[i0], NY[i0]
            yx, yy, l1 = S.yx[a], S.yy[a], S.l1[a]
            r1 = n1x * npx + n1y * npy
            zx, zy = npx - r1 * n1x, npy - r1 * n1y
            zz = zx * zx + zy * zy
            with np.errstate(divide="ignore", invalid="ignore"):
                t1 = np.where(zz > _EPS_Z, (npx * yx + npy * yy - B[ip]) / zz, np.inf)
                q1 = np.where(r1 > _EPS_R, l1 / r1, np.inf)
            full = t1 <= q1
            t = np.minimum(t1, q1)
            bad = ~np.isfinite(t)
            if np.any(bad):
                dead.append((a[bad], r1[bad], np.zeros(int(bad.sum()))))
                t[bad] = 0.0
                full &= ~bad
            S.yx[a], S.yy[a] = yx - t * zx, yy - t * zy
            lpa = S.lp[a] + t
            S.l1[a] = np.where(full, np.maximum(l1 - t * r1, 0.0), 0.0)  # a partial step drops n1
            S.w1[a], S.l2[a] = np.where(full, pk, S.w1[a]), np.where(full, lpa, 0.0)
            S.nw[a] = np.where(full, 2, np.where(bad, 1, 0))
            S.p[a], S.lp[a] = np.where(full, -1, pk), np.where(full, 0.0, lpa)
        # ---- two active constraints n1, n2 (they span the plane): partial steps only
        a = act[k == 2]
        if a.size:
            pk, w0, w1 = S.p[a], S.w0[a], S.w1[a]
            ip, i0, i1 = a * K + pk, a * K + w0, a * K + w1
            npx, npy, n1x, n1y, n2x, n2y = NX[ip], NY[ip], NX[i0], NY[i0], NX[i1], NY[i1]
            l1, l2 = S.l1[a], S.l2[a]
            det = n1x * n2y - n1y * n2x
            r1 = (npx * n2y - npy * n2x) / det
            r2 = (n1x * npy - n1y * npx) / det
            with np.errstate(divide="ignore", invalid="ignore"):
                q1 = np.where(r1 > _EPS_R, l1 / r1, np.inf)
                q2 = np.where(r2 > _EPS_R, l2 / r2, np.inf)
            t = np.minimum(q1, q2)
            bad = ~np.isfinite(t)
            if np.any(bad):
                dead.append((a[bad], r1[bad], r2[bad]))
                t[bad] = 0.0
            l1, l2 = np.maximum(l1 - t * r1, 0.0), np.maximum(l2 - t * r2, 0.0)
            drop0 = (q1 <= q2) & ~bad  # n1 leaves: n2 moves into its place
            S.w0[a], S.l1[a] = np.where(drop0, w1, w0), np.where(drop0, l2, l1)
            S.l2[a] = np.where(bad, l2, 0.0)
            S.nw[a] = np.where(bad, 2, 1)
            S.lp[a] += t
        if dead:
            d = np.concatenate([x[0] for x in dead])
            S.status[d] = 2
            S.r1[d] = np.concatenate([x[1] for x in dead])
            S.r2[d] = np.concatenate([x[2] for x in dead])
            act = act[S.status[act] == 0]
    S.status[act] = 3  # iteration cap
    return iterations


def _verify(T: _Table, S: _State, y0, tol_k, idx) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Module docstring step 3 for robots ``idx``: recompute the optimal points, check certificates.

    Returns the points ``(len(idx), 2)`` and multipliers ``(len(idx), 2)`` of the active slots; robots that
    fail a check get status 3.
    """
    K = T.nx.shape[1]
    NX, NY, B = T.nx.reshape(-1), T.ny.reshape(-1), T.b.reshape(-1)
    y = y0[idx].copy()
    mu = np.zeros((idx.shape[0], 2))
    st = S.status[idx]
    moved = np.flatnonzero((st == 1) & (S.nw[idx] > 0))
    if moved.size:
        r = idx[moved]
        i0, i1 = r * K + S.w0[r], r * K + S.w1[r]
        n1x, n1y, b1, n2x, n2y, b2 = NX[i0], NY[i0], B[i0], NX[i1], NY[i1], B[i1]
        k = S.nw[r]
        yx, yy = y0[r, 0], y0[r, 1]
        m1 = n1x * yx + n1y * yy - b1
        m2 = np.zeros(r.size)
        px, py = yx - m1 * n1x, yy - m1 * n1y
        two = k == 2
        if np.any(two):
            vx, vy, det = _vertex(n1x, n1y, b1, n2x, n2y, b2)
            dx, dy = yx - vx, yy - vy
            with np.errstate(divide="ignore", invalid="ignore"):
                m1 = np.where(two, (dx * n2y - dy * n2x) / det, m1)
                m2 = np.where(two, (n1x * dy - n1y * dx) / det, 0.0)
            px, py = np.where(two, vx, px), np.where(two, vy, py)
        V = T.nx[r] * px[:, None] + T.ny[r] * py[:, None] - T.b[r]
        vmax = V.reshape(-1)[np.arange(r.size) * K + V.argmax(axis=1)]
        tk = tol_k[r]
        ok = (vmax <= tk) & (m1 >= -tk) & (m2 >= -tk) & np.isfinite(px) & np.isfinite(py)
        y[moved, 0], y[moved, 1] = px, py
        mu[moved, 0], mu[moved, 1] = np.maximum(m1, 0.0), np.maximum(m2, 0.0)
        S.status[r[~ok]] = 3
    dead = idx[st == 2]
    if dead.size:
        k = S.nw[dead]
        ip, i0, i1 = dead * K + S.p[dead], dead * K + S.w0[dead], dead * K + S.w1[dead]
        f1, f2 = (k >= 1) * S.r1[dead], (k == 2) * S.r2[dead]
        # n_p = r1 n1 + r2 n2 with r <= 0: n_p'y <= b_p and -r_k n_k'y <= -r_k b_k add up to 0 <= b_p - r'b
        resx = NX[ip] - f1 * NX[i0] - f2 * NX[i1]
        resy = NY[ip] - f1 * NY[i0] - f2 * NY[i1]
        gap = B[ip] - f1 * B[i0] - f2 * B[i1]
        conf = (gap < -tol_k[dead]) & (np.hypot(resx, resy) <= 1e-9) & (f1 <= _EPS_R) & (f2 <= _EPS_R)
        S.status[dead[~conf]] = 3
    return y, mu


def _enumerate(T: _Table, idx, y0, tol_k):
    """Exact enumeration for robots ``idx`` (module docstring step 4): ``(y, w (., 2), nw, mu (., 2), feasible)``."""
    K = T.nx.shape[1]
    out_y = np.zeros((idx.shape[0], 2))
    out_w = np.zeros((idx.shape[0], 2), dtype=np.intp)
    out_nw = np.zeros(idx.shape[0], dtype=np.intp)
    out_mu = np.zeros((idx.shape[0], 2))
    out_ok = np.zeros(idx.shape[0], dtype=bool)
    if idx.size == 0:
        return out_y, out_w, out_nw, out_mu, out_ok
    valid = T.b[idx] < _PAD_B
    last = K - 1 - valid[:, ::-1].argmax(axis=1)  # the bounds are always valid
    kk = int(last.max()) + 1
    ia, ib = np.triu_indices(kk, k=1)
    n_cand = 1 + kk + ia.size
    chunk = max(1, _ENUM_CHUNK // (n_cand * K))
    for s in range(0, idx.size, chunk):
        sub = idx[s:s + chunk]
        r = sub.shape[0]
        nx, ny, b = T.nx[sub][:, :kk], T.ny[sub][:, :kk], T.b[sub][:, :kk]
        yx0, yy0 = y0[sub, 0:1], y0[sub, 1:2]
        mu_s = nx * yx0 + ny * yy0 - b  # projections onto single lines
        sx, sy = yx0 - mu_s * nx, yy0 - mu_s * ny
        vx, vy, det = _vertex(nx[:, ia], ny[:, ia], b[:, ia], nx[:, ib], ny[:, ib], b[:, ib])  # vertices
        dx, dy = yx0 - vx, yy0 - vy
        with np.errstate(divide="ignore", invalid="ignore"):
            m1 = (dx * ny[:, ib] - dy * nx[:, ib]) / det
            m2 = (nx[:, ia] * dy - ny[:, ia] * dx) / det
        cx = np.concatenate((yx0, sx, vx), axis=1)
        cy = np.concatenate((yy0, sy, vy), axis=1)
        mua = np.concatenate((np.zeros((r, 1)), mu_s, m1), axis=1)
        mub = np.concatenate((np.zeros((r, 1 + kk)), m2), axis=1)
        tk = tol_k[sub][:, None]
        good = np.concatenate((np.ones((r, 1), bool), mu_s >= -tk, (np.abs(det) > 1e-12) & (m1 >= -tk) & (m2 >= -tk)),
                              axis=1)
        good &= np.isfinite(cx) & np.isfinite(cy)
        with np.errstate(invalid="ignore", over="ignore"):
            viol = (T.nx[sub][:, None, :] * cx[:, :, None] + T.ny[sub][:, None, :] * cy[:, :, None]
                    - T.b[sub][:, None, :]).max(axis=2)
        good &= viol <= tk
        dist = np.where(good, (cx - yx0) ** 2 + (cy - yy0) ** 2, np.inf)
        best = dist.argmin(axis=1)
        rr = np.arange(r)
        feas = np.isfinite(dist[rr, best])
        sl = slice(s, s + r)
        out_ok[sl] = feas
        out_y[sl, 0], out_y[sl, 1] = cx[rr, best], cy[rr, best]
        single = (best >= 1) & (best <= kk)
        pair = best > kk
        pj = np.maximum(best - 1 - kk, 0)
        out_nw[sl] = np.where(pair, 2, np.where(single, 1, 0))
        out_w[sl, 0] = np.where(pair, ia[pj], np.where(single, best - 1, 0))
        out_w[sl, 1] = np.where(pair, ib[pj], 0)
        out_mu[sl, 0] = np.where(feas & (best >= 1), np.maximum(mua[rr, best], 0.0), 0.0)
        out_mu[sl, 1] = np.where(feas & pair, np.maximum(mub[rr, best], 0.0), 0.0)
    return out_y, out_w, out_nw, out_mu, out_ok


def _solve(T: _Table, S: _State, y0, tol_k, idx, max_iter) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Steps 2-4 for robots ``idx``: points ``y``, active multipliers ``mu`` ``(len(idx), 2)``, iterations, enumerated.

    Sets ``S.status`` (1 optimal, 2 infeasible) and the active slots ``S.w0, S.w1, S.nw`` of ``idx``.
    """
    its = _active_set(T, S, y0, tol_k, idx, max_iter)
    y, mu = _verify(T, S, y0, tol_k, idx)
    enum = np.flatnonzero(S.status[idx] == 3)
    if enum.size:
        e = idx[enum]
        ye, we, nwe, mue, oke = _enumerate(T, e, y0, tol_k)
        S.status[e] = np.where(oke, 1, 2)
        y[enum], mu[enum] = ye, mue
        S.w0[e], S.w1[e], S.nw[e] = we[:, 0], we[:, 1], nwe
    return y, mu, its, int(enum.size)


def solve_local_qps(
    H: np.ndarray,
    g: np.ndarray,
    lb: np.ndarray,
    ub: np.ndarray,
    owner: np.ndarray,
    G: np.ndarray,
    h: np.ndarray,
    *,
    relax: bool = False,
    relax_tol: float | np.ndarray = RELAX_TOL,
    tol: float = TOL,
    max_iter: int = MAX_ITER,
    compiled: bool = False,
) -> LocalSolution:
    """Solve every robot's 2-variable QP exactly (module docstring).

    Parameters
    ----------
    H : numpy.ndarray
        Hessian blocks ``(N, 2, 2)``, symmetric positive definite.
    g : numpy.ndarray
        Linear terms ``(N, 2)``.
    lb, ub : numpy.ndarray
        Bounds ``(N, 2)`` with ``lb <= ub``.
    owner : numpy.ndarray
        Robot of each row ``(M,)``, in ``[0, N)``.
    G : numpy.ndarray
        Row coefficients ``(M, 2)``.
    h : numpy.ndarray
        Row right-hand sides ``(M,)``.
    relax : bool
        Answer robots whose polygon is empty with their least-violation point (module docstring).
    relax_tol : float or numpy.ndarray
        Loosening on top of each least violation (per robot ``(N,)`` or one value), in units of the
        row normalised in ``x``.
    tol : float
        KKT tolerance on the normalised half-planes, relative to ``1 + |y0|_inf``.
    max_iter : int
        Active-set iterations before the enumeration answers the rest.
    compiled : bool
        Solve in the compiled kernel (:mod:`aasoatt_env.safety.solvers.local_kernel`, one loop over
        the robots; ``ImportError`` without numba): the same decisions, numbers to rounding
        (:mod:`aasoatt_env.compiled`).

    Returns
    -------
    LocalSolution

    Notes
    -----
    The KKT tolerance is relative to ``1 + |y0|_inf`` (``y0`` the unconstrained minimiser in the
    metric of the objective): an unconstrained minimiser far outside the bounds' scale (a nominal
    of 1e10 against bounds of 1) loosens the check with it.  The filter clips each robot's nominal
    to its bounds before it forms ``g``, which keeps ``|y0|`` at the bounds' scale.
    """
    H = np.asarray(H, dtype=np.float64)
    g = np.asarray(g, dtype=np.float64)
    lb = np.asarray(lb, dtype=np.float64)
    ub = np.asarray(ub, dtype=np.float64)
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
    x = np.empty((n, 2))
    lam = np.zeros(m)
    lam_box = np.zeros((n, 2, 2))
    feasible = np.ones(n, dtype=bool)
    loosened = np.zeros(m)
    if n == 0:
        return LocalSolution(x, lam, lam_box, feasible, loosened, 0, 0)
    if compiled:
        bad = np.zeros(n, dtype=bool)
        rt = np.broadcast_to(rt, (n,))
        its, n_enum = kernels("local").solve_all(
            *(c64(a) for a in (H, g, lb, ub)), np.ascontiguousarray(owner, dtype=np.int64), c64(G), c64(h),
            bool(relax), c64(rt), float(tol), int(max_iter), x, lam, lam_box, feasible, loosened, bad)
        if np.any(bad):
            _bad_blocks(np.flatnonzero(bad))
        return LocalSolution(x, lam, lam_box, feasible, loosened, int(its), int(n_enum))
    l11, l21, l22 = _cholesky(H)
    i11, i22 = 1.0 / l11, 1.0 / l22
    i21 = -l21 * i11 * i22
    y0 = np.stack((-i11 * g[:, 0], -(i21 * g[:, 0] + i22 * g[:, 1])), axis=1)  # -L^-1 g
    x[:, 0] = i11 * y0[:, 0] + i21 * y0[:, 1]  # the unconstrained minimiser L^-T y0
    x[:, 1] = i22 * y0[:, 1]
    # step 0: robots whose unconstrained minimiser meets its bounds and every row are done
    cons = (x[:, 0] < lb[:, 0]) | (x[:, 0] > ub[:, 0]) | (x[:, 1] < lb[:, 1]) | (x[:, 1] > ub[:, 1])
    if m:
        viol = G[:, 0] * x[owner, 0] + G[:, 1] * x[owner, 1] - h
        cons |= np.bincount(owner[viol > 0.0], minlength=n) > 0
    sub = np.flatnonzero(cons)
    if sub.size == 0:
        return LocalSolution(x, lam, lam_box, feasible, loosened, 0, 0)
    if sub.size < n:
        remap = np.full(n, -1, dtype=np.intp)
        remap[sub] = np.arange(sub.size)
        rsel = np.flatnonzero(cons[owner]) if m else np.zeros(0, dtype=np.intp)
        s_owner = remap[owner[rsel]]
        Gs, hs = G[rsel], h[rsel]
    else:
        rsel, s_owner, Gs, hs = np.arange(m), owner, G, h
    ns = sub.size
    si11, si21, si22 = i11[sub], i21[sub], i22[sub]
    sy0, slb, sub_ = y0[sub], lb[sub], ub[sub]
    tol_k = tol * (1.0 + np.maximum(np.abs(sy0[:, 0]), np.abs(sy0[:, 1])))
    zero_infeasible = np.zeros(ns, dtype=bool)
    zero_bad = np.zeros(hs.shape[0], dtype=bool)
    T = _table((si11, si21, si22), slb, sub_, s_owner, Gs, hs, tol_k, zero_infeasible, zero_bad)
    S = _State(ns, sy0)
    S.status[zero_infeasible] = 2  # a row 0 <= h < 0: infeasible as it stands
    start = np.flatnonzero(~zero_infeasible)
    y, mu, its, n_enum = _solve(T, S, sy0, tol_k, start, max_iter)
    ys = sy0.copy()
    mus = np.zeros((ns, 2))
    ys[start], mus[start] = y, mu
    feas = S.status == 1
    feasible[sub] = feas
    bad = np.flatnonzero(~feas)
    if bad.size and relax:
        rt = np.broadcast_to(rt, (n,))[sub]
        its2, n2 = _relax(T, S, sy0, tol_k, bad, (l11[sub], l21[sub], l22[sub]), slb, sub_, Gs, rt,
                          ys, mus, loosened, rsel, max_iter)
        its, n_enum = max(its, its2), n_enum + n2
        zb = np.flatnonzero(zero_bad)
        loosened[rsel[zb]] = -hs[zb] * (1.0 + 1e-6)  # a zero row is met by loosening it to 0 <= 0
    xs = np.stack((si11 * ys[:, 0] + si21 * ys[:, 1], si22 * ys[:, 1]), axis=1)
    x[sub] = np.minimum(np.maximum(xs, slb), sub_)
    # multipliers of the active slots, in the units of the rows as given: mu / |L^-1 G_r|
    done = np.flatnonzero(S.status == 1)
    K = T.nx.shape[1]
    s0 = np.sqrt(si11 * si11 + si21 * si21)
    for s, wk in ((0, S.w0), (1, S.w1)):
        sel = done[S.nw[done] > s]
        slot = wk[sel]
        r = T.row.reshape(-1)[sel * K + slot]
        isrow = r >= 0
        rs, ss = sel[isrow], r[isrow]
        a_x = si11[rs] * Gs[ss, 0]
        a_y = si21[rs] * Gs[ss, 0] + si22[rs] * Gs[ss, 1]
        np.add.at(lam, rsel[ss], mus[rs, s] / np.sqrt(a_x * a_x + a_y * a_y))
        bs = sel[~isrow]
        bslot = slot[~isrow]
        np.add.at(lam_box, (sub[bs], bslot // 2, bslot % 2), mus[bs, s] / np.where(bslot % 2 == 0, s0[bs], si22[bs]))
    still = sub[(S.status == 2) | (S.status == 3)]
    if still.size:  # infeasible without relax (or a failed relaxation): the minimiser over the bounds alone
        box_only = solve_local_qps(H[still], g[still], lb[still], ub[still], np.zeros(0, np.intp), np.zeros((0, 2)),
                                   np.zeros(0), tol=tol, max_iter=max_iter)
        x[still] = box_only.x
    return LocalSolution(x, lam, lam_box, feasible, loosened, its, n_enum)


def _relax(T, S, y0, tol_k, bad, lfac, lb, ub, Gs, rtol, ys, mus, loosened, rsel, max_iter):
    """Least-violation answers of the infeasible robots ``bad`` (table indices); fills ``ys, mus, loosened``."""
    l11, l21, l22 = (v[bad] for v in lfac)
    nx, ny, b = T.nx[bad, 4:], T.ny[bad, 4:], T.b[bad, 4:]  # the rows (the bounds stay hard)
    real = b < _PAD_B
    # the rows normalised in x: G ~ L n, so G / |G| = L n / |L n|, h / |G| = b / |L n|
    gx = l11[:, None] * nx
    gy = l21[:, None] * nx + l22[:, None] * ny
    ln = np.sqrt(gx * gx + gy * gy)
    inv = 1.0 / np.where(real, ln, 1.0)
    gx, gy = gx * inv, gy * inv
    hh = np.where(real, b * inv, _PAD_B)
    # start from the active-set point where it stopped (inside the bounds after clipping)
    i11, i22 = 1.0 / l11, 1.0 / l22
    i21 = -l21 * i11 * i22
    x0 = np.stack((i11 * S.yx[bad] + i21 * S.yy[bad], i22 * S.yy[bad]), axis=1)
    x0 = np.minimum(np.maximum(np.where(np.isfinite(x0), x0, 0.0), lb[bad]), ub[bad])
    x1, viol = _lv_core(gx, gy, hh, lb[bad], ub[bad], x0)
    loosen_n = (viol * (1.0 + 1e-6) + rtol[bad][:, None]) * real  # in normalised x units
    T.b[bad, 4:] = b + loosen_n * ln  # in y units: (G x - h) / |L^-1 G| = |L n| * (G x - h) / |G|
    rows = T.row[bad, 4:][real]
    gn = np.sqrt(Gs[rows, 0] ** 2 + Gs[rows, 1] ** 2)
    loosened[rsel[rows]] = loosen_n[real] * gn
    S.reset(bad, y0)
    y, mu, its, n_enum = _solve(T, S, y0, tol_k, bad, max_iter)
    ok = S.status[bad] == 1
    ys[bad] = np.where(ok[:, None], y, 0.0)
    mus[bad] = np.where(ok[:, None], mu, 0.0)
    # a failed relaxation (not seen) keeps the phase-1 point
    fail = ~ok
    if np.any(fail):
        l11f, l21f, l22f = l11[fail], l21[fail], l22[fail]
        ys[bad[fail], 0] = l11f * x1[fail, 0] + l21f * x1[fail, 1]
        ys[bad[fail], 1] = l22f * x1[fail, 1]
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
    for fx in (lox, hix):  # edges d_x = const
        cy = np.clip(-(gy + hxy * fx) / hyy, loy, hiy)
        f = 0.5 * (hxx * fx * fx + 2 * hxy * fx * cy + hyy * cy * cy) + gx * fx + gy * cy
        take = ~inside & (f < best)
        best, bx, by = np.where(take, f, best), np.where(take, fx, bx), np.where(take, cy, by)
    for fy in (loy, hiy):  # edges d_y = const
        cx = np.clip(-(gx + hxy * fy) / hxx, lox, hix)
        f = 0.5 * (hxx * cx * cx + 2 * hxy * cx * fy + hyy * fy * fy) + gx * cx + gy * fy
        take = ~inside & (f < best)
        best, bx, by = np.where(take, f, best), np.where(take, cx, bx), np.where(take, fy, by)
    return bx, by


def _line_search(res: np.ndarray, delta: np.ndarray, d0: np.ndarray, d1: np.ndarray, iters: int = 4) -> np.ndarray:
    """Per robot ``argmin_{t in [0, 1]} phi(t) = 0.5 sum_r (res_r + t delta_r)_+^2``, exactly.

    Needs ``phi'(0) = d0 < 0 < d1 = phi'(1)``.  ``phi'`` is continuous, non-decreasing and
    piecewise linear: a few steps of regula falsi with the Illinois rule land on its root
    exactly once the bracket lies in one linear piece (most robots); the others go to
    :func:`_line_min`.
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
    """Per robot the exact ``argmin_{t in [0, 1]} 0.5 sum_r (res_r + t delta_r)_+^2`` (``res``, ``delta`` ``(P, K)``).

    The derivative ``sum_active (res + t delta) delta`` is continuous, non-decreasing and
    linear between the points where a row switches on or off: sort those, accumulate the
    active sums, and solve the linear piece where the derivative turns non-negative.
    """
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


def _lv_core(gx, gy, hh, lb, ub, x, max_iter: int = 40):
    """Phase-1 iterations on unit rows ``(P, K)`` (padding: ``hh = _PAD_B``); ``(x, violations (P, K))``."""
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


def least_violation(
    lb: np.ndarray,
    ub: np.ndarray,
    owner: np.ndarray,
    G: np.ndarray,
    h: np.ndarray,
    *,
    x0: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Phase 1 of each robot: the least violation of each of its rows, bounds hard.

    Per robot ``min F(x) = 0.5 sum_r ((G_r x - h_r)_+ / |G_r|)^2  s.t.  lb <= x <= ub``
    (rows normalised, one slack per row, so a row that cannot be met is loosened
    alone, as in :func:`aasoatt_env.safety.solvers.policy.solve_qp`).  ``F`` is
    convex and piecewise quadratic; each iteration minimises, over the box, the
    quadratic of the rows violated at the current point (a 2-variable box QP in
    closed form, with a ``1e-10`` relative proximal term where those rows do not
    span the plane) and moves to the exact minimiser of ``F`` on the segment
    towards it (:func:`_line_search`); once the violated set is the final one a
    full step lands on the minimiser.  Vectorised across robots; a robot stops
    when its step is below ``1e-11`` of its box.  The violations
    ``s_r = (G_r x - h_r)_+`` are unique even where the minimiser is not.

    Parameters
    ----------
    lb, ub : numpy.ndarray
        Bounds ``(N, 2)``.
    owner, G, h : numpy.ndarray
        Rows as in :func:`solve_local_qps`.
    x0 : numpy.ndarray, optional
        Starting points ``(N, 2)`` (default: the centres of the boxes).

    Returns
    -------
    x : numpy.ndarray
        A minimiser per robot ``(N, 2)`` (within the bounds).
    s : numpy.ndarray
        Violation of each row at ``x``, ``(M,)``, in the units of the row as given.
    """
    lb = np.asarray(lb, float)
    ub = np.asarray(ub, float)
    owner = np.asarray(owner, np.intp).reshape(-1)
    G = np.asarray(G, float).reshape(-1, 2)
    h = np.asarray(h, float).reshape(-1)
    n = lb.shape[0]
    x = 0.5 * (lb + ub) if x0 is None else np.clip(np.asarray(x0, float), lb, ub)
    if owner.size == 0 or n == 0:
        return x, np.zeros(owner.shape[0])
    nrm = np.sqrt(G[:, 0] * G[:, 0] + G[:, 1] * G[:, 1])
    nrm = np.where(nrm > 1e-300, nrm, 1.0)
    slot, counts = _slots(owner, n)
    K = max(1, int(counts.max(initial=0)))
    gx = np.zeros((n, K))
    gy = np.zeros((n, K))
    hh = np.full((n, K), _PAD_B)
    gx[owner, slot], gy[owner, slot], hh[owner, slot] = G[:, 0] / nrm, G[:, 1] / nrm, h / nrm
    x, _ = _lv_core(gx, gy, hh, lb, ub, x)
    s = np.maximum(G[:, 0] * x[owner, 0] + G[:, 1] * x[owner, 1] - h, 0.0)
    return x, s
