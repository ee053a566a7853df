"""The decentralised filter's local solver compiled (numba; imported only through :mod:`aasoatt_env.compiled`).

:func:`solve_all` is :func:`~.local.solve_local_qps` after its checks, robot by robot on the reference's table:
Goldfarb-Idnani's dual active set in the plane (a dependent constraint with no positive coefficient certifies an empty
polygon), a KKT check, and for a robot not verified the enumeration of every candidate; phase 1 as the reference's
(line search by regula falsi first).  Answers: the reference's to rounding.  Only plain loops are factored out (a
helper calling others pays its array arguments' reference counts on every robot).
"""

import math

import numpy as np

from aasoatt_env.numba_jit import jit, nclip, nmax, nmin
from aasoatt_env.safety.solvers.local import PAD_B as _PAD_B
from aasoatt_env.safety.solvers.polygons import LV_ITERS as _LV_ITERS

__all__ = ["solve_all"]

_INF = math.inf
_EPS_Z = 1e-22  # a new normal with less squared component than this off the active ones depends on them
_EPS_R = 1e-14  # coefficients of a dependent normal below this count as non-positive
_LS_ITERS = 4  # regula falsi steps of phase 1's line search before its exact piecewise minimiser


@jit
def _vertex(n1x, n1y, b1, n2x, n2y, b2, yx, yy):
    """Vertex of lines ``n' y = b`` (inf/NaN if parallel), the determinant, multipliers of ``y``'s projection on it."""
    det = n1x * n2y - n1y * n2x
    vx, vy = (b1 * n2y - b2 * n1y) / det, (n1x * b2 - n2x * b1) / det
    dx, dy = yx - vx, yy - vy
    return vx, vy, det, (dx * n2y - dy * n2x) / det, (n1x * dy - n1y * dx) / det


# --------------------------------------------------------------------------- dual active set, one robot
@jit
def _active_set(nx, ny, b, nk, y0x, y0y, tk, max_iter, st):
    """Dual active set on one robot's table ``[0, nk)``; the state into ``st`` (:func:`_start`); iterations.

    Adds the most violated constraint ``p``: a full step onto it (none active), to the vertex with ``n1`` or a partial
    one dropping ``n1`` (one), a partial step dropping one (two); a step that cannot be taken: a certificate (status 2).
    """
    yx, yy = y0x, y0y
    nw, w0, w1, p = 0, 0, 0, -1
    l1 = l2 = lp = r1s = r2s = 0.0
    status = 0
    its = 0
    for it in range(max_iter):
        its = it + 1
        if p < 0:
            kmax, vmax = _argmax(nx, ny, b, nk, yx, yy)
            if vmax <= tk:
                status = 1
                break
            p, lp = kmax, 0.0
        npx, npy = nx[p], ny[p]
        if nw == 0:
            t = (npx * yx + npy * yy - b[p]) / (npx * npx + npy * npy)
            yx -= t * npx
            yy -= t * npy
            w0, l1, nw, p, lp = p, lp + t, 1, -1, 0.0
        elif nw == 1:
            n1x, n1y = nx[w0], ny[w0]
            r1 = n1x * npx + n1y * npy
            zx, zy = npx - r1 * n1x, npy - r1 * n1y
            zz = zx * zx + zy * zy
            t1 = (npx * yx + npy * yy - b[p]) / zz if zz > _EPS_Z else _INF
            q1 = l1 / r1 if r1 > _EPS_R else _INF
            full = t1 <= q1
            t = nmin(t1, q1)
            bad = not math.isfinite(t)
            if bad:
                r1s, r2s, status, t, full = r1, 0.0, 2, 0.0, False
            yx, yy = yx - t * zx, yy - t * zy
            l1 = nmax(l1 - t * r1, 0.0) if full else 0.0  # a partial step drops n1
            if full:
                w1, l2, nw, p, lp = p, lp + t, 2, -1, 0.0
            else:
                l2, nw, lp = 0.0, 1 if bad else 0, lp + t
            if bad:
                break
        else:
            n1x, n1y, n2x, n2y = nx[w0], ny[w0], nx[w1], ny[w1]
            det = n1x * n2y - n1y * n2x
            r1 = (npx * n2y - npy * n2x) / det
            r2 = (n1x * npy - n1y * npx) / det
            q1 = l1 / r1 if r1 > _EPS_R else _INF
            q2 = l2 / r2 if r2 > _EPS_R else _INF
            t = nmin(q1, q2)
            bad = not math.isfinite(t)
            if bad:
                r1s, r2s, status, t = r1, r2, 2, 0.0
            nl1, nl2 = nmax(l1 - t * r1, 0.0), nmax(l2 - t * r2, 0.0)
            if (q1 <= q2) and not bad:  # n1 leaves: n2 moves into its place
                w0, l1 = w1, nl2
            else:
                l1 = nl1
            l2, nw, lp = nl2 if bad else 0.0, 2 if bad else 1, lp + t
            if bad:
                break
    if status == 0:
        status = 3  # iteration cap
    st[0], st[1], st[2], st[3], st[4], st[5] = yx, yy, nw, w0, w1, l1
    st[6], st[7], st[8], st[9], st[10], st[11] = l2, p, lp, status, r1s, r2s
    return its


@jit
def _argmax(nx, ny, b, nk, px, py):
    """Most violated slot of a table at ``(px, py)`` and its ``n' y - b`` (numpy's ``argmax``: the first NaN wins)."""
    kmax, vmax = 0, nx[0] * px + ny[0] * py - b[0]
    if vmax != vmax:
        return kmax, vmax
    for s in range(1, nk):
        v = nx[s] * px + ny[s] * py - b[s]
        if v != v:
            return s, v
        if v > vmax:
            kmax, vmax = s, v
    return kmax, vmax


@jit
def _verify(nx, ny, b, nk, y0x, y0y, tk, st, out):
    """The KKT check of one robot's active set or certificate: ``out = (yx, yy, mu0, mu1)``; a failed one: status 3."""
    status, nw = int(st[9]), int(st[2])
    out[0], out[1], out[2], out[3] = y0x, y0y, 0.0, 0.0
    if status == 1 and nw > 0:
        w0, w1 = int(st[3]), int(st[4])
        n1x, n1y, b1 = nx[w0], ny[w0], b[w0]
        m1 = n1x * y0x + n1y * y0y - b1
        m2 = 0.0
        px, py = y0x - m1 * n1x, y0y - m1 * n1y
        if nw == 2:
            px, py, _, m1, m2 = _vertex(n1x, n1y, b1, nx[w1], ny[w1], b[w1], y0x, y0y)
        vmax = _argmax(nx, ny, b, nk, px, py)[1]
        ok = (vmax <= tk) and (m1 >= -tk) and (m2 >= -tk) and math.isfinite(px) and math.isfinite(py)
        out[0], out[1], out[2], out[3] = px, py, nmax(m1, 0.0), nmax(m2, 0.0)
        if not ok:
            st[9] = 3.0
    elif status == 2:  # n_p = r1 n1 + r2 n2 with r <= 0: n_p'y <= b_p and -r_k n_k'y <= -r_k b_k add to 0 <= b_p - r'b
        p, w0, w1 = int(st[7]), int(st[3]), int(st[4])
        f1 = st[10] if nw >= 1 else 0.0 * st[10]
        f2 = st[11] if nw == 2 else 0.0 * st[11]
        resx = nx[p] - f1 * nx[w0] - f2 * nx[w1]
        resy = ny[p] - f1 * ny[w0] - f2 * ny[w1]
        gap = b[p] - f1 * b[w0] - f2 * b[w1]
        conf = (gap < -tk) and (math.hypot(resx, resy) <= 1e-9) and (f1 <= _EPS_R) and (f2 <= _EPS_R)
        if not conf:
            st[9] = 3.0


@jit
def _enumerate(nx, ny, b, nk, y0x, y0y, tk, st, out):
    """The nearest feasible candidate (``y0``, its projections, the vertices) into ``out``; status, slots in ``st``."""
    best_d = _INF
    by, bx = y0y, y0x
    bnw, bw0, bw1 = 0, 0, 0
    bm0, bm1 = 0.0, 0.0
    # candidate 0: y0
    if math.isfinite(y0x) and math.isfinite(y0y) and _argmax(nx, ny, b, nk, y0x, y0y)[1] <= tk:
        best_d = 0.0
    # projections onto single lines
    for j in range(nk):
        mu = nx[j] * y0x + ny[j] * y0y - b[j]
        sx, sy = y0x - mu * nx[j], y0y - mu * ny[j]
        if not (mu >= -tk and math.isfinite(sx) and math.isfinite(sy) and _argmax(nx, ny, b, nk, sx, sy)[1] <= tk):
            continue
        d = (sx - y0x) * (sx - y0x) + (sy - y0y) * (sy - y0y)
        if d < best_d:
            best_d, bx, by, bnw, bw0, bw1, bm0, bm1 = d, sx, sy, 1, j, 0, mu, 0.0
    # vertices of two lines, in np.triu_indices order
    for ia in range(nk):
        for ib in range(ia + 1, nk):
            vx, vy, det, m1, m2 = _vertex(nx[ia], ny[ia], b[ia], nx[ib], ny[ib], b[ib], y0x, y0y)
            if not (abs(det) > 1e-12 and m1 >= -tk and m2 >= -tk and math.isfinite(vx) and math.isfinite(vy)
                    and _argmax(nx, ny, b, nk, vx, vy)[1] <= tk):
                continue
            d = (vx - y0x) * (vx - y0x) + (vy - y0y) * (vy - y0y)
            if d < best_d:
                best_d, bx, by, bnw, bw0, bw1, bm0, bm1 = d, vx, vy, 2, ia, ib, m1, m2
    feas = math.isfinite(best_d)
    if not feas:
        bx, by, bnw, bw0, bw1 = y0x, y0y, 0, 0, 0
    out[0], out[1] = bx, by
    out[2] = nmax(bm0, 0.0) if (feas and bnw >= 1) else 0.0
    out[3] = nmax(bm1, 0.0) if (feas and bnw == 2) else 0.0
    st[9] = 1.0 if feas else 2.0
    st[2], st[3], st[4] = bnw, bw0, bw1


@jit
def _solve(nx, ny, b, nk, y0x, y0y, tk, max_iter, st, out):
    """One robot's projection: active set, check, enumeration; returns ``(iterations, enumerated)``."""
    its = _active_set(nx, ny, b, nk, y0x, y0y, tk, max_iter, st)
    _verify(nx, ny, b, nk, y0x, y0y, tk, st, out)
    if int(st[9]) == 3:
        _enumerate(nx, ny, b, nk, y0x, y0y, tk, st, out)
        return its, 1
    return its, 0


# --------------------------------------------------------------------------- phase 1 (least violation), one robot
@jit
def _box_qp(hxx, hxy, hyy, gx, gy, lox, loy, hix, hiy):
    """One robot's ``argmin 0.5 d'Hd + g'd  s.t.  lo <= d <= hi`` (strictly convex ``H``): inside, else an edge."""
    det = hxx * hyy - hxy * hxy
    dx = -(hyy * gx - hxy * gy) / det
    dy = -(hxx * gy - hxy * gx) / det
    if (dx >= lox) and (dx <= hix) and (dy >= loy) and (dy <= hiy):
        return dx, dy
    best, bx, by = _INF, dx, dy
    for e in range(4):  # the edges d_x = lo, hi, then d_y = lo, hi: the other coordinate's minimiser
        if e < 2:
            x = lox if e == 0 else hix
            y = nclip(-(gy + hxy * x) / hyy, loy, hiy)
        else:
            y = loy if e == 2 else hiy
            x = nclip(-(gx + hxy * y) / hxx, lox, hix)
        f = 0.5 * (hxx * x * x + 2 * hxy * x * y + hyy * y * y) + gx * x + gy * y
        if f < best:
            best, bx, by = f, x, y
    return bx, by


@jit
def _line_min(res, delta, n, te, order):
    """The exact minimiser on ``[0, 1]`` of one robot's ``0.5 sum_r (res_r + t delta_r)_+^2`` (as ``polygons``)."""
    a0 = b0 = 0.0
    for r in range(n):
        te[r] = 2.0
        if delta[r] != 0.0:
            v = -res[r] / delta[r]
            if v > 0.0 and v < 1.0:
                te[r] = v
        if res[r] > 0.0 or (res[r] == 0.0 and delta[r] > 0.0):
            a0 += res[r] * delta[r]
            b0 += delta[r] * delta[r]
    order[:n] = np.argsort(te[:n])
    # piece j = 0 .. n: [start_j, end_j] with sums A_j, B_j
    A, B, start = a0, b0, 0.0
    ca, cb = 0.0, 0.0
    for j in range(n + 1):
        end = min(te[order[j]], 1.0) if j < n else 1.0
        if A + end * B >= 0.0 or j == n:
            return nclip(-A / B if B > 0.0 else (start if A >= 0.0 else end), start, end)
        r = order[j]
        dl = delta[r] if te[r] < 2.0 else 0.0
        sg = 1.0 if dl > 0.0 else (-1.0 if dl < 0.0 else 0.0)
        ca += sg * dl * res[r]
        cb += sg * dl * dl
        A, B, start = a0 + ca, b0 + cb, end
    return 1.0


@jit
def _line_search(res, delta, n, d0, d1, te, order):
    """Phase 1's line search given ``phi'(0) < 0 < phi'(1)``: regula falsi (Illinois), then :func:`_line_min`."""
    a, bb, fa, fb, side = 0.0, 1.0, d0, d1, 0.0
    tol = 1e-13 * (abs(d0) + abs(d1))
    for _ in range(_LS_ITERS):
        t = (a * fb - bb * fa) / (fb - fa)
        ft = 0.0  # phi'(t)
        for r in range(n):
            ft += nmax(res[r] + t * delta[r], 0.0) * delta[r]
        if not (abs(ft) > tol):
            return t
        if ft < 0:
            if side > 0:
                fb = 0.5 * fb  # the same end kept twice: halve its weight
            a, fa, side = t, ft, 1.0
        else:
            if side < 0:
                fa = 0.5 * fa
            bb, fb, side = t, ft, -1.0
    return _line_min(res, delta, n, te, order)


@jit
def _least_violation(gx, gy, hh, n, lb0, lb1, ub0, ub1, x0, x1, res, delta, on, te, order):
    """``polygons.least_violation`` of one robot over its ``n`` unit rows; returns the point (violations: caller)."""
    span = max(max(ub0 - lb0, ub1 - lb1), 1e-300)
    for _ in range(_LV_ITERS):
        grx = gry = hxx = hxy = hyy = 0.0
        for r in range(n):
            v = gx[r] * x0 + gy[r] * x1 - hh[r]
            res[r] = v
            on[r] = v > 0
            if on[r]:
                grx += v * gx[r]
                gry += v * gy[r]
                hxx += gx[r] * gx[r]
                hxy += gx[r] * gy[r]
                hyy += gy[r] * gy[r]
        eps = 1e-10 * (hxx + hyy) + 1e-300
        dx, dy = _box_qp(hxx + eps, hxy, hyy + eps, grx, gry, lb0 - x0, lb1 - x1, ub0 - x0, ub1 - x1)
        d1, same = 0.0, True
        for r in range(n):
            dl = gx[r] * dx + gy[r] * dy
            delta[r] = dl
            rn = res[r] + dl
            if rn > 0:
                d1 += rn * dl
            if (rn > 0) != on[r]:
                same = False
        full = d1 <= 0.0
        t = 1.0 if full else _line_search(res, delta, n, grx * dx + gry * dy, d1, te, order)
        step = t * max(abs(dx), abs(dy))
        x0, x1 = nclip(x0 + t * dx, lb0, ub0), nclip(x1 + t * dy, lb1, ub1)
        if (full and same) or not (step > 1e-11 * span):
            break
    return x0, x1


# --------------------------------------------------------------------------- every robot
@jit
def solve_all(H, g, lb, ub, owner, G, h, relax, relax_tol, tol, max_iter, x, lam, lam_box, feasible, loosened,
              bad_block):
    """Every robot's QP (module docstring) into the outputs (``bad_block``: raise); ``(iterations, enumerated)``."""
    rows, counts, K = _by_owner(owner, g.shape[0])
    nx, ny, b, slot_row = np.empty(K), np.empty(K), np.empty(K), np.empty(K, dtype=np.int64)  # the table
    gx, gy, hh, ln, res, delta, te = (np.empty(K), np.empty(K), np.empty(K), np.empty(K), np.empty(K), np.empty(K),
                                      np.empty(K))  # phase 1's rows and work
    on, order, st, out = np.empty(K, dtype=np.bool_), np.empty(K, dtype=np.int64), np.zeros(12), np.zeros(4)
    its_all, n_enum = 0, 0
    for k in range(g.shape[0]):
        h00, h10, h11 = H[k, 0, 0], 0.5 * (H[k, 1, 0] + H[k, 0, 1]), H[k, 1, 1]
        l11 = math.sqrt(h00) if h00 > 0 else 0.0
        l21 = h10 / l11
        d = h11 - l21 * l21
        if not ((h00 > 0) and (d > 0) and math.isfinite(l21) and math.isfinite(d)):
            bad_block[k] = True
            continue
        l22 = math.sqrt(d)
        i11, i22 = 1.0 / l11, 1.0 / l22
        i21 = -l21 * i11 * i22
        y0x, y0y = -i11 * g[k, 0], -(i21 * g[k, 0] + i22 * g[k, 1])
        xu0, xu1 = i11 * y0x + i21 * y0y, i22 * y0y
        cons = (xu0 < lb[k, 0]) or (xu0 > ub[k, 0]) or (xu1 < lb[k, 1]) or (xu1 > ub[k, 1])
        if not cons:
            for q in range(counts[k], counts[k + 1]):
                r = rows[q]
                if G[r, 0] * xu0 + G[r, 1] * xu1 - h[r] > 0.0:
                    cons = True
                    break
        if not cons:
            x[k, 0], x[k, 1] = xu0, xu1
            continue
        tk = tol * (1.0 + max(abs(y0x), abs(y0y)))
        s0 = math.sqrt(i11 * i11 + i21 * i21)
        nk, zero_inf = _table(k, i11, i21, i22, s0, lb, ub, G, h, rows, counts, tk, relax, loosened, nx, ny, b,
                              slot_row)
        _start(st, out, y0x, y0y)
        st[9] = 2.0
        if not zero_inf:
            its, en = _solve(nx, ny, b, nk, y0x, y0y, tk, max_iter, st, out)
            its_all, n_enum = max(its_all, its), n_enum + en
        status = int(st[9])
        feasible[k] = status == 1
        yx, yy, mu0, mu1 = out[0], out[1], out[2], out[3]
        if status != 1 and relax:  # phase 1 on the rows normalised in x, the bounds hard, from the last point
            nr = nk - 4
            _phase1_rows(l11, l21, l22, nr, nx, ny, b, gx, gy, hh, ln)
            p0, p1 = i11 * st[0] + i21 * st[1], i22 * st[1]
            p0 = nmin(nmax(p0 if math.isfinite(p0) else 0.0, lb[k, 0]), ub[k, 0])
            p1 = nmin(nmax(p1 if math.isfinite(p1) else 0.0, lb[k, 1]), ub[k, 1])
            q0, q1 = _least_violation(gx, gy, hh, nr, lb[k, 0], lb[k, 1], ub[k, 0], ub[k, 1], p0, p1, res, delta, on,
                                      te, order)
            _loosen(q0, q1, nr, relax_tol[k], gx, gy, hh, ln, b, slot_row, G, loosened)
            _start(st, out, y0x, y0y)
            its, en = _solve(nx, ny, b, nk, y0x, y0y, tk, max_iter, st, out)
            its_all, n_enum = max(its_all, its), n_enum + en
            status = 1 if int(st[9]) == 1 else 4  # 4: a failed relaxation keeps the phase-1 point
            yx, yy, mu0, mu1 = (out[0], out[1], out[2], out[3]) if status == 1 else (l11 * q0 + l21 * q1, l22 * q1,
                                                                                      mu0, mu1)
        if status == 2 or status == 3:  # infeasible without relax: the minimiser over the bounds alone
            _box_only(k, i11, i21, i22, y0x, y0y, xu0, xu1, lb, ub, tk, max_iter, nx, ny, b, st, out, x)
            continue
        x[k, 0] = nclip(i11 * yx + i21 * yy, lb[k, 0], ub[k, 0])
        x[k, 1] = nclip(i22 * yy, lb[k, 1], ub[k, 1])
        for s in range(int(st[2]) if status == 1 else 0):  # the active slots' multipliers: mu / |L^-1 G_r|
            slot, mu = (int(st[3]), mu0) if s == 0 else (int(st[4]), mu1)
            r = slot_row[slot]
            if r >= 0:
                ax, ay = i11 * G[r, 0], i21 * G[r, 0] + i22 * G[r, 1]
                lam[r] += mu / math.sqrt(ax * ax + ay * ay)
            else:
                lam_box[k, slot // 2, slot % 2] += mu / (s0 if slot % 2 == 0 else i22)
    return its_all, n_enum


@jit
def _by_owner(owner, n):
    """The rows sorted by owner, stably (``rows[counts[k]:counts[k + 1]]``: robot ``k``'s), and the table size."""
    counts = np.zeros(n + 1, dtype=np.int64)
    for r in range(owner.shape[0]):
        counts[owner[r] + 1] += 1
    kmax = counts.max()
    for k in range(n):
        counts[k + 1] += counts[k]
    rows = np.empty(owner.shape[0], dtype=np.int64)
    fill = counts[:n].copy()
    for r in range(owner.shape[0]):
        rows[fill[owner[r]]] = r
        fill[owner[r]] += 1
    return rows, counts, 4 + kmax


@jit
def _start(st, out, y0x, y0y):
    """A fresh state ``st`` at ``y0``: ``yx, yy, nw, w0, w1, l1, l2, p, lp, status, r1, r2`` (``p = -1``: none)."""
    st[:] = 0.0
    st[0], st[1], st[7] = y0x, y0y, -1.0
    out[0], out[1], out[2], out[3] = y0x, y0y, 0.0, 0.0


@jit
def _table(k, i11, i21, i22, s0, lb, ub, G, h, rows, counts, tk, relax, loosened, nx, ny, b, slot_row):
    """Robot ``k``'s half-planes: the bounds, then its rows with a normal; ``(slots, a zero row 0 <= h < 0)``."""
    nx[0], ny[0], b[0] = i11 / s0, i21 / s0, ub[k, 0] / s0
    nx[1], ny[1], b[1] = 0.0, 1.0, ub[k, 1] / i22
    nx[2], ny[2], b[2] = -nx[0], -ny[0], -lb[k, 0] / s0
    nx[3], ny[3], b[3] = 0.0, -1.0, -lb[k, 1] / i22
    for s in range(4):
        slot_row[s] = -1
    nk, zero_inf = 4, False
    zero_tol = 1e-300 + 1e-14 * min(s0, i22)
    for q in range(counts[k], counts[k + 1]):
        r = rows[q]
        ax = i11 * G[r, 0]
        ay = i21 * G[r, 0] + i22 * G[r, 1]
        nrm = math.sqrt(ax * ax + ay * ay)
        if nrm <= zero_tol:  # a row 0 <= h
            if h[r] < -tk:
                zero_inf = True
                if relax:
                    loosened[r] = -h[r] * (1.0 + 1e-6)  # met by loosening it to 0 <= 0
            continue
        inv = 1.0 / nrm
        if not h[r] * inv < _PAD_B:  # never violated: the reference's padding (neither enumerated nor loosened)
            continue
        nx[nk], ny[nk], b[nk] = ax * inv, ay * inv, h[r] * inv
        slot_row[nk] = r
        nk += 1
    return nk, zero_inf


@jit
def _phase1_rows(l11, l21, l22, nr, nx, ny, b, gx, gy, hh, ln):
    """The table's ``nr`` rows normalised in ``x`` (``G / |G| = L n / |L n|``) and the norms ``|L n|``."""
    for j in range(nr):
        ax = l11 * nx[4 + j]
        ay = l21 * nx[4 + j] + l22 * ny[4 + j]
        ln[j] = math.sqrt(ax * ax + ay * ay)
        inv = 1.0 / ln[j]
        gx[j], gy[j], hh[j] = ax * inv, ay * inv, b[4 + j] * inv


@jit
def _loosen(q0, q1, nr, rtk, gx, gy, hh, ln, b, slot_row, G, loosened):
    """Each row loosened by its violation at the phase-1 point ``(q0, q1)`` and ``rtk``, in the table and its units."""
    for j in range(nr):
        loosen = nmax(gx[j] * q0 + gy[j] * q1 - hh[j], 0.0) * (1.0 + 1e-6) + rtk
        b[4 + j] = b[4 + j] + loosen * ln[j]
        r = slot_row[4 + j]
        loosened[r] = loosen * math.sqrt(G[r, 0] * G[r, 0] + G[r, 1] * G[r, 1])


@jit
def _box_only(k, i11, i21, i22, y0x, y0y, xu0, xu1, lb, ub, tk, max_iter, nx, ny, b, st, out, x):
    """Robot ``k``'s minimiser over its bounds alone (an infeasible robot without relaxation)."""
    if (xu0 < lb[k, 0]) or (xu0 > ub[k, 0]) or (xu1 < lb[k, 1]) or (xu1 > ub[k, 1]):
        _start(st, out, y0x, y0y)
        _solve(nx, ny, b, 4, y0x, y0y, tk, max_iter, st, out)
        xu0 = nclip(i11 * out[0] + i21 * out[1], lb[k, 0], ub[k, 0])
        xu1 = nclip(i22 * out[1], lb[k, 1], ub[k, 1])
    x[k, 0], x[k, 1] = xu0, xu1
