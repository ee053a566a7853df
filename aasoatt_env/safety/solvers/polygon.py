"""Projections of many points onto convex polygons at once: the local solver's steps 2-4.

Each robot's polygon is a table of unit half-planes ``n' y <= b`` (:class:`Table`); :func:`solve` projects its point
``y0``, vectorised with masks: (2) Goldfarb-Idnani's dual active set in the plane (a dependent new constraint with no
positive coefficient is a Farkas certificate of an empty polygon); (3) a KKT check of the final active set and of each
certificate; (4) the robots not verified by enumerating every candidate (``y0``, its projections, the vertices).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["PAD_B", "State", "Table", "solve", "vertex"]

_EPS_Z = 1e-22  # a new normal with less squared component than this off the active ones depends on them
_EPS_R = 1e-14  # coefficients of a dependent normal below this count as non-positive
PAD_B = 1e300  #: right-hand side of padding slots (never violated)
_ENUM_CHUNK = 1 << 20  # the largest candidate-by-constraint table (elements) of one enumeration chunk


class Table(NamedTuple):
    """Half-planes ``n' y <= b`` of every robot, ``(N, K)``: slots 0-3 the bounds; ``row``: each slot's row or -1."""

    nx: np.ndarray
    ny: np.ndarray
    b: np.ndarray
    row: np.ndarray

    def flat(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """The tables flattened (slot ``k`` of robot ``r`` at ``r K + k``) and ``K``."""
        return self.nx.reshape(-1), self.ny.reshape(-1), self.b.reshape(-1), self.nx.shape[1]


def vertex(n1x, n1y, b1, n2x, n2y, b2, yx, yy):
    """Vertex of lines ``n' y = b`` (inf/NaN if parallel), the determinant, multipliers of ``y``'s projection on it."""
    det = n1x * n2y - n1y * n2x
    vx, vy = (b1 * n2y - b2 * n1y) / det, (n1x * b2 - n2x * b1) / det
    dx, dy = yx - vx, yy - vy
    return vx, vy, det, (dx * n2y - dy * n2x) / det, (n1x * dy - n1y * dx) / det


class State:
    """Active-set state of every robot of a table.

    The point ``yx, yy``; the active slots ``w0, w1`` (``nw`` of them) and their multipliers ``l1, l2``; the
    constraint ``p`` being added (-1: none) and its multiplier ``lp``; ``status`` (0 running, 1 optimal,
    2 certificate, 3 enumerate); a certificate's coefficients ``r1, r2``.
    """

    def __init__(self, n: int, y0: np.ndarray) -> None:
        self.yx, self.yy = y0[:, 0].copy(), y0[:, 1].copy()
        self.nw, self.w0, self.w1 = (np.zeros(n, dtype=np.intp) for _ in range(3))
        self.l1, self.l2, self.lp, self.r1, self.r2 = (np.zeros(n) for _ in range(5))
        self.p = np.full(n, -1, dtype=np.intp)
        self.status = np.zeros(n, dtype=np.int8)

    def reset(self, idx: np.ndarray, y0: np.ndarray) -> None:
        """Robots ``idx`` start again from ``y0``."""
        self.yx[idx], self.yy[idx] = y0[idx, 0], y0[idx, 1]
        for arr in (self.nw, self.w0, self.w1, self.l1, self.l2, self.lp, self.status, self.r1, self.r2):
            arr[idx] = 0
        self.p[idx] = -1


def _active_set(T: Table, S: State, y0, tol_k, start, max_iter) -> int:
    """Step 2 for robots ``start``: Goldfarb-Idnani in the plane, one step per robot and iteration; the iterations."""
    act = start
    iterations = 0
    for it in range(max_iter):
        if act.size == 0:
            break
        iterations = it + 1
        act = _add_most_violated(T, S, tol_k, act)
        if act.size == 0:
            break
        k = S.nw[act]
        _step_none(T, S, act[k == 0])
        dead = _step_one(T, S, act[k == 1])
        if _step_two(T, S, act[k == 2]) | dead:  # robots with a certificate leave
            act = act[S.status[act] == 0]
    S.status[act] = 3  # iteration cap
    return iterations


def _add_most_violated(T: Table, S: State, tol_k, act) -> np.ndarray:
    """Robots ``act`` without a constraint in progress take their most violated one, or are optimal; the rest."""
    need = act[S.p[act] < 0]
    if need.size:
        if need.size == T.nx.shape[0]:
            V = T.nx * S.yx[:, None] + T.ny * S.yy[:, None] - T.b
        else:
            V = T.nx[need] * S.yx[need, None] + T.ny[need] * S.yy[need, None] - T.b[need]
        kmax = V.argmax(axis=1)
        vmax = V.reshape(-1)[np.arange(need.size) * T.nx.shape[1] + kmax]
        fine = vmax <= tol_k[need]
        if np.any(fine):
            S.status[need[fine]] = 1
            act = act[S.status[act] == 0]
            if act.size == 0:
                return act
            kmax, need = kmax[~fine], need[~fine]
        S.p[need] = kmax
        S.lp[need] = 0.0
    return act


def _step_none(T: Table, S: State, a) -> None:
    """Robots ``a`` without an active constraint: a full step onto the new one ``n_p``."""
    if a.size:
        NX, NY, B, K = T.flat()
        pk = S.p[a]
        ip = a * K + pk
        npx, npy = NX[ip], NY[ip]
        t = (npx * S.yx[a] + npy * S.yy[a] - B[ip]) / (npx * npx + npy * npy)
        S.yx[a] -= t * npx
        S.yy[a] -= t * npy
        S.w0[a], S.l1[a], S.nw[a], S.p[a], S.lp[a] = pk, S.lp[a] + t, 1, -1, 0.0


def _dead(S: State, a, bad, r1, r2) -> bool:
    """Robots ``a[bad]`` hold a certificate of an empty polygon (coefficients ``r1``, ``r2``); whether any do."""
    if not np.any(bad):
        return False
    d = a[bad]
    S.status[d], S.r1[d], S.r2[d] = 2, r1[bad], r2[bad] if r2 is not None else 0.0
    return True


def _step_one(T: Table, S: State, a) -> bool:
    """Robots ``a`` with one active constraint ``n1``: a full step to the vertex, or a partial one dropping ``n1``."""
    if not a.size:
        return False
    NX, NY, B, K = T.flat()
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
    dead = _dead(S, a, bad, r1, None)
    if dead:
        t[bad] = 0.0
        full &= ~bad
    S.yx[a], S.yy[a] = yx - t * zx, yy - t * zy
    lpa = S.lp[a] + t
    S.l1[a] = np.where(full, np.maximum(l1 - t * r1, 0.0), 0.0)  # a partial step drops n1
    S.w1[a], S.l2[a] = np.where(full, pk, S.w1[a]), np.where(full, lpa, 0.0)
    S.nw[a] = np.where(full, 2, np.where(bad, 1, 0))
    S.p[a], S.lp[a] = np.where(full, -1, pk), np.where(full, 0.0, lpa)
    return dead


def _step_two(T: Table, S: State, a) -> bool:
    """Robots ``a`` with two active constraints (they span the plane): a partial step dropping one of them."""
    if not a.size:
        return False
    NX, NY, B, K = T.flat()
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
    dead = _dead(S, a, bad, r1, r2)
    if dead:
        t[bad] = 0.0
    l1, l2 = np.maximum(l1 - t * r1, 0.0), np.maximum(l2 - t * r2, 0.0)
    drop0 = (q1 <= q2) & ~bad  # n1 leaves: n2 moves into its place
    S.w0[a], S.l1[a] = np.where(drop0, w1, w0), np.where(drop0, l2, l1)
    S.l2[a] = np.where(bad, l2, 0.0)
    S.nw[a] = np.where(bad, 2, 1)
    S.lp[a] += t
    return dead


def _verify(T: Table, S: State, y0, tol_k, idx) -> tuple[np.ndarray, np.ndarray]:
    """Step 3 for robots ``idx``: points and multipliers ``(len(idx), 2)`` from the active sets (failed: status 3)."""
    NX, NY, B, K = T.flat()
    y = y0[idx].copy()
    mu = np.zeros((idx.shape[0], 2))
    st = S.status[idx]
    moved = np.flatnonzero((st == 1) & (S.nw[idx] > 0))
    if moved.size:
        r = idx[moved]
        i0, i1 = r * K + S.w0[r], r * K + S.w1[r]
        n1x, n1y, b1, n2x, n2y, b2 = NX[i0], NY[i0], B[i0], NX[i1], NY[i1], B[i1]
        yx, yy = y0[r, 0], y0[r, 1]
        m1 = n1x * yx + n1y * yy - b1
        m2 = np.zeros(r.size)
        px, py = yx - m1 * n1x, yy - m1 * n1y
        two = S.nw[r] == 2
        if np.any(two):
            with np.errstate(divide="ignore", invalid="ignore"):
                vx, vy, _, v1, v2 = vertex(n1x, n1y, b1, n2x, n2y, b2, yx, yy)
            m1, m2 = np.where(two, v1, m1), np.where(two, v2, 0.0)
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


def _enumerate(T: Table, idx, y0, tol_k):
    """Step 4 for robots ``idx`` (one or more): ``(y, active slots (., 2), count, multipliers (., 2), feasible)``."""
    K, q = T.nx.shape[1], idx.shape[0]
    out_y, out_mu, out_w = np.zeros((q, 2)), np.zeros((q, 2)), np.zeros((q, 2), dtype=np.intp)
    out_nw, out_ok = np.zeros(q, dtype=np.intp), np.zeros(q, dtype=bool)
    valid = T.b[idx] < PAD_B
    kk = int((K - 1 - valid[:, ::-1].argmax(axis=1)).max()) + 1  # the last valid slot (the bounds always are)
    ia, ib = np.triu_indices(kk, k=1)
    chunk = max(1, _ENUM_CHUNK // ((1 + kk + ia.size) * K))
    for s in range(0, idx.size, chunk):
        sub = idx[s:s + chunk]
        r = sub.shape[0]
        nx, ny, b = T.nx[sub][:, :kk], T.ny[sub][:, :kk], T.b[sub][:, :kk]
        yx0, yy0 = y0[sub, 0:1], y0[sub, 1:2]
        mu_s = nx * yx0 + ny * yy0 - b  # projections onto single lines
        sx, sy = yx0 - mu_s * nx, yy0 - mu_s * ny
        with np.errstate(divide="ignore", invalid="ignore"):
            vx, vy, det, m1, m2 = vertex(nx[:, ia], ny[:, ia], b[:, ia], nx[:, ib], ny[:, ib], b[:, ib], yx0, yy0)
        cx, cy = np.concatenate((yx0, sx, vx), axis=1), np.concatenate((yy0, sy, vy), axis=1)
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
        single, pair = (best >= 1) & (best <= kk), best > kk
        pj = np.maximum(best - 1 - kk, 0)
        out_nw[sl] = np.where(pair, 2, np.where(single, 1, 0))
        out_w[sl, 0] = np.where(pair, ia[pj], np.where(single, best - 1, 0))
        out_w[sl, 1] = np.where(pair, ib[pj], 0)
        out_mu[sl, 0] = np.where(feas & (best >= 1), np.maximum(mua[rr, best], 0.0), 0.0)
        out_mu[sl, 1] = np.where(feas & pair, np.maximum(mub[rr, best], 0.0), 0.0)
    return out_y, out_w, out_nw, out_mu, out_ok


def solve(T: Table, S: State, y0, tol_k, idx, max_iter) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Steps 2-4 for robots ``idx``: ``(points, multipliers, iterations, enumerated)``; status and slots into ``S``."""
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
