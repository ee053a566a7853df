"""The centralised QP stage in one compiled call, and the fused step (numba; loaded by :mod:`aasoatt_env.compiled`).

:func:`solve_decomposed` is :func:`~.centralized.solve_rows` on a warm step in the numpy order of operations,
answering (bit for bit) only where the warm active set verifies every component.  :func:`fused_step` (:mod:`.fused`)
calls the stages' kernels in the pipeline's order, so with their numbers.
"""

import math

import numpy as np

from aasoatt_env.model.geometry_kernel import components
from aasoatt_env.numba_jit import jit, nclip
from aasoatt_env.safety.backup.kernels import gate_full
from aasoatt_env.safety.rows_kernel import aasoatt_rows
from aasoatt_env.safety.solvers.active_set_kernel import solve_parts

__all__ = ["CLOSED_FORM", "NOT_HERE", "VERIFIED", "box_least_squares", "fused_step", "solve_decomposed"]

CLOSED_FORM = 0  #: no row is violated by the robots' own answers: no QP
VERIFIED = 1  #: every component's warm active set was verified
NOT_HERE = -1  #: not answered here (a component not verified, beyond the dense size, a block not positive definite)


@jit
def box_least_squares(A, target, lo, hi):
    """:func:`aasoatt_env.safety.problem.box_least_squares` of every robot: ``argmin |A_i du - t_i|^2`` in its box."""
    out = np.empty((A.shape[0], 2))
    for i in range(A.shape[0]):
        a, b, c, d = A[i, 0, 0], A[i, 0, 1], A[i, 1, 0], A[i, 1, 1]
        t0, t1 = target[i, 0], target[i, 1]
        det = a * d - b * c
        x0, x1 = (d * t0 - b * t1) / det, (a * t1 - c * t0) / det
        lo0, lo1, hi0, hi1 = lo[i, 0], lo[i, 1], hi[i, 0], hi[i, 1]
        if not ((x0 < lo0) or (x0 > hi0) or (x1 < lo1) or (x1 > hi1)):
            out[i, 0], out[i, 1] = x0, x1
            continue
        h00, h01, h11 = a * a + c * c, a * b + c * d, b * b + d * d
        g0, g1 = -(a * t0 + c * t1), -(b * t0 + d * t1)
        best, fbest, e0, e1 = -1, 0.0, 0.0, 0.0
        for k in range(4):  # the edges x0 = lo, x0 = hi, x1 = lo, x1 = hi; the first of equal values
            if k < 2:
                y0 = lo0 if k == 0 else hi0
                y1 = nclip(-(g1 + h01 * y0) / h11, lo1, hi1)
            else:
                y1 = lo1 if k == 2 else hi1
                y0 = nclip(-(g0 + h01 * y1) / h00, lo0, hi0)
            f = 0.5 * (h00 * y0 * y0 + 2.0 * h01 * y0 * y1 + h11 * y1 * y1) + g0 * y0 + g1 * y1
            if best < 0 or f < fbest or (f != f and fbest == fbest):  # numpy's argmin: the first NaN wins
                best, fbest, e0, e1 = k, f, y0, y1
                if f != f:
                    break
        out[i, 0], out[i, 1] = e0, e1
    return out


@jit
def _coupled(n, ri, rj, bad, n_rr):
    """The robots of components with a violated row: ``(robots, groups by first robot, count, K, local index)``."""
    ea, eb = np.empty(n_rr, np.int64), np.empty(n_rr, np.int64)
    k = 0
    for q in range(rj.shape[0]):
        if rj[q] >= 0:
            ea[k], eb[k] = ri[q], rj[q]
            k += 1
    label = components(n, ea, eb)
    hit = np.zeros(n, np.bool_)
    for q in range(bad.shape[0]):
        if bad[q]:
            hit[label[ri[q]]] = True
    remap, gnum = np.full(n, -1, np.int64), np.full(n, -1, np.int64)
    sub, groups = np.empty(n, np.int64), np.empty(n, np.int64)
    ns, K = 0, 0
    for i in range(n):
        if hit[label[i]]:
            if gnum[label[i]] < 0:
                gnum[label[i]] = K
                K += 1
            remap[i], sub[ns], groups[ns] = ns, i, gnum[label[i]]
            ns += 1
    return sub[:ns], groups[:ns].copy(), ns, K, remap


@jit
def _scaled(A, target, lo, hi, scale, sub):
    """The scaled problem's blocks (``build_problem``'s operations): ``(ok, sigma, L^-T, gt, lb, ub)``."""
    ns = sub.shape[0]
    H = np.empty((ns, 2, 2))
    sigma = 0.0
    for a in range(ns):
        i = sub[a]
        ss = scale[i] * scale[i]
        for r in range(2):
            for c in range(2):
                H[a, r, c] = 2.0 * (A[i, 0, r] * A[i, 0, c] + A[i, 1, r] * A[i, 1, c]) * ss
                v = abs(H[a, r, c])
                sigma = math.nan if v != v else (v if v > sigma else sigma)
    LinvT, gt, lbv, ubv = np.empty((ns, 2, 2)), np.empty(2 * ns), np.empty(2 * ns), np.empty(2 * ns)
    if not (sigma > 0.0):
        return False, sigma, LinvT, gt, lbv, ubv
    H /= sigma
    for a in range(ns):
        i = sub[a]
        s = scale[i]
        g0 = -2.0 * (A[i, 0, 0] * target[i, 0] + A[i, 1, 0] * target[i, 1]) * s / sigma
        g1 = -2.0 * (A[i, 0, 1] * target[i, 0] + A[i, 1, 1] * target[i, 1]) * s / sigma
        h00, h10, h11 = H[a, 0, 0], H[a, 1, 0], H[a, 1, 1]
        fa = math.sqrt(h00) if h00 >= 0.0 else math.nan
        fc = h10 / fa
        d2 = h11 - fc * fc
        fd = math.sqrt(d2) if d2 >= 0.0 else math.nan
        if not (h00 > 0.0 and d2 > 0.0 and H[a, 0, 1] == h10):
            return False, sigma, LinvT, gt, lbv, ubv  # a block not positive definite: the reference's other path
        l00, l10, l11 = 1.0 / fa, -fc / (fa * fd), 1.0 / fd
        LinvT[a, 0, 0], LinvT[a, 0, 1], LinvT[a, 1, 0], LinvT[a, 1, 1] = l00, l10, 0.0, l11
        gt[2 * a] = l00 * g0 + 0.0 * g1
        gt[2 * a + 1] = l10 * g0 + l11 * g1
        for h in range(2):
            lbv[2 * a + h], ubv[2 * a + h] = lo[i, h] / s, hi[i, h] / s
    return True, sigma, LinvT, gt, lbv, ubv


@jit
def _csr_rows(rows, ri, rj, Gi, Gj, rhs, scale, remap, sub, lbv, ubv, x_prev, z_warm, nnz, settings):
    """The coupled rows at unit norm in the scaled variables as CSR: ``(indptr, indices, data, norms, b, W0)``."""
    warm_rel, warm_floor, bound_tight, row_norm_min = settings[3], settings[4], settings[5], settings[6]
    ms, nv = rows.shape[0], 2 * sub.shape[0]
    indptr, indices, data = np.empty(ms + 1, np.int64), np.empty(nnz, np.int64), np.empty(nnz)
    nu, b, W0 = np.empty(ms), np.empty(ms + 2 * nv), np.zeros(ms + 2 * nv, np.bool_)
    zmax = 0.0
    for k in range(ms):
        w = z_warm[rows[k]]
        zmax = math.nan if w != w else (w if w > zmax else zmax)
    zcut = warm_rel * max(zmax, warm_floor) if zmax == zmax else math.nan
    e = 0
    indptr[0] = 0
    for k in range(ms):
        q = rows[k]
        i, si = ri[q], remap[ri[q]]
        gi0, gi1 = Gi[q, 0] * scale[i], Gi[q, 1] * scale[i]
        sj, gj0, gj1 = -1, 0.0, 0.0
        if rj[q] >= 0:
            j, sj = rj[q], remap[rj[q]]
            gj0, gj1 = Gj[q, 0] * scale[j], Gj[q, 1] * scale[j]
        nrm = math.sqrt((gi0 * gi0 + gi1 * gi1) + (gj0 * gj0 + gj1 * gj1))
        nu[k] = nrm = nrm if nrm > row_norm_min else 1.0
        for si_, g0, g1 in ((si, gi0, gi1), (sj, gj0, gj1)):
            if si_ >= 0:
                indices[e], indices[e + 1], data[e], data[e + 1] = 2 * si_, 2 * si_ + 1, g0 / nrm, g1 / nrm
                e += 2
        indptr[k + 1] = e
        b[k], W0[k] = rhs[q] / nrm, z_warm[q] > zcut
    for a in range(sub.shape[0]):
        for h in range(2):
            v = 2 * a + h
            b[ms + v], b[ms + nv + v] = ubv[v], -lbv[v]
            W0[ms + v] = x_prev[sub[a], h] >= ubv[v] - bound_tight
            W0[ms + nv + v] = x_prev[sub[a], h] <= lbv[v] + bound_tight
    return indptr, indices, data, nu, b, W0


@jit
def solve_decomposed(A, target, lo, hi, scale, ri, rj, Gi, Gj, rhs, x_prev, z_warm, settings):
    """One step's centralised QP (module docstring): ``(code, iterations, rows in the QP, du, x, z, eta)``.

    ``settings``: :func:`aasoatt_env.safety.centralized.kernel_settings`.  The caller checks every shape and index.
    """
    n, m = A.shape[0], rhs.shape[0]
    du, x_full, z, eta = box_least_squares(A, target, lo, hi), np.empty((n, 2)), np.zeros(m), np.zeros(m)
    bad, n_rr = np.zeros(m, np.bool_), 0
    for q in range(m):  # the rows the robots' own answers violate, and the number of robot-robot rows
        i, j = ri[q], rj[q]
        other = Gj[q, 0] * du[j, 0] + Gj[q, 1] * du[j, 1] if j >= 0 else 0.0
        bad[q] = (Gi[q, 0] * du[i, 0] + Gi[q, 1] * du[i, 1]) + other - rhs[q] > 0.0
        n_rr += 1 if j >= 0 else 0
    for i in range(n):
        x_full[i, 0], x_full[i, 1] = du[i, 0] / scale[i], du[i, 1] / scale[i]
    if not bad.any():
        return CLOSED_FORM, 0, 0, du, x_full, z, eta
    sub, groups, ns, K, remap = _coupled(n, ri, rj, bad, n_rr)
    rows, ms, nnz = np.empty(m, np.int64), 0, 0
    for q in range(m):
        if remap[ri[q]] >= 0:
            rows[ms], ms, nnz = q, ms + 1, nnz + (4 if rj[q] >= 0 else 2)
    nv = 2 * ns
    if not (nv <= int(settings[7]) or nv * (ms + 2 * nv) <= int(settings[8])):  # beyond the dense size
        return NOT_HERE, 0, ms, du, x_full, z, eta
    ok, sigma, LinvT, gt, lbv, ubv = _scaled(A, target, lo, hi, scale, sub)
    if not ok:
        return NOT_HERE, 0, ms, du, x_full, z, eta
    indptr, indices, data, nu, b, W0 = _csr_rows(rows[:ms], ri, rj, Gi, Gj, rhs, scale, remap, sub, lbv, ubv,
                                                 x_prev, z_warm, nnz, settings)
    y, lam, done = np.zeros(nv), np.zeros(ms + 2 * nv), np.zeros(K, np.bool_)
    used = solve_parts(indptr, indices, data, ms, nv, LinvT, gt, b, W0, groups, K, int(settings[0]),
                       int(settings[1]), settings[2], y, lam, done)
    xs = np.empty(nv)
    for a in range(ns):
        y0, y1 = y[2 * a], y[2 * a + 1]
        xs[2 * a] = 0.0 + LinvT[a, 0, 0] * y0 + LinvT[a, 0, 1] * y1  # (einsum's sums start from +0.0)
        xs[2 * a + 1] = 0.0 + LinvT[a, 1, 0] * y0 + LinvT[a, 1, 1] * y1
    if used < 0 or not done.all() or not np.isfinite(xs).all():  # (a non-finite point: the reference decides)
        return NOT_HERE, max(used, 0), ms, du, x_full, z, eta
    for a in range(ns):
        i = sub[a]
        for h in range(2):
            du[i, h] = nclip(xs[2 * a + h] * scale[i], lo[i, h], hi[i, h])
            x_full[i, h] = xs[2 * a + h]
    for k in range(ms):
        zk = lam[k] if lam[k] > 0.0 and math.isfinite(lam[k]) else 0.0
        z[rows[k]] = zk
        eta[rows[k]] = sigma * zk / nu[k]
    return VERIFIED, used, ms, du, x_full, z, eta


@jit
def warm_rows(prev_keys, prev_z, keys):
    """The previous multipliers on these rows' keys (``prev_keys`` increasing; 0 for a new row)."""
    out = np.zeros(keys.shape[0])
    P = prev_keys.shape[0]
    for r in range(keys.shape[0]):
        k, a, b = keys[r], 0, P
        while a < b:
            mid = (a + b) // 2
            if prev_keys[mid] < k:
                a = mid + 1
            else:
                b = mid
        if a < P and prev_keys[a] == k:
            out[r] = prev_z[a]
    return out


@jit
def fused_step(rows_in, qp_in, prev, settings, eta_tol, gate_in, gate_block):
    """One warm step's rows, QP and quick backup check (:mod:`.fused`).

    ``rows_in``: :func:`aasoatt_rows`' arguments; ``qp_in``: ``(target, lo, hi, scale)``; ``prev``: ``(x, keys, z)``;
    ``gate_in``: ``(pose, u, dt, levels, limit, tol)``; ``gate_block``: the gate's team, pair and obstacle block.
    Returns ``(solved, passed, rows, (iterations, n_qp, du, x, z, eta), avoiding, backup)``; ``passed``: nothing
    broken and only robots leaving their range limit braked, so ``backup = (du, braking, nudged, margin)`` is the
    backup stage's answer (nothing to hold or repair).
    """
    rows = aasoatt_rows(*rows_in)
    ri, rj, Gi, Gj, rhs, pairs, keys, h_min, gap_min = rows
    target, lo, hi, scale = qp_in
    code, used, n_qp, du, x, z, eta = solve_decomposed(rows_in[3], target, lo, hi, scale, ri, rj, Gi, Gj, rhs,
                                                       prev[0], warm_rows(prev[1], prev[2], keys), settings)
    n = du.shape[0]
    avoiding = np.zeros(n, np.bool_)
    for r in range(z.shape[0]):
        if z[r] > eta_tol:
            avoiding[ri[r]] = True
            if rj[r] >= 0:
                avoiding[rj[r]] = True
    solved = code == CLOSED_FORM or code == VERIFIED
    passed, gdu, braking, nudged, margin = False, du, np.zeros(n, np.bool_), np.zeros(n, np.bool_), 0.0
    if solved:
        pose, u, dt, levels, limit, tol = gate_in
        gdu, braking, broken, _, _, out_of_range, _, _, margin = gate_full(pose, u, du, dt, levels, True,
                                                                           *gate_block, limit, tol, False)
        passed = True
        for i in range(n):
            passed = passed and not (broken[i] or (braking[i] and not out_of_range[i]))
            nudged[i] = not braking[i] and (abs(gdu[i, 0] - du[i, 0]) > 1e-9 * scale[i]
                                            or abs(gdu[i, 1] - du[i, 1]) > 1e-9 * scale[i])
    return solved, passed, rows, (used, n_qp, du, x, z, eta), avoiding, (gdu, braking, nudged, margin)
