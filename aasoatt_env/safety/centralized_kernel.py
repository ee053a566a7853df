"""The centralised QP stage in one compiled call (numba; loaded through :mod:`aasoatt_env.compiled`).

:func:`solve_decomposed` is :func:`aasoatt_env.safety.centralized.solve_rows` on a warm-started
step, as loops instead of dozens of small array operations: each robot's box least squares, the
rows they violate and their contact components, the scaled problem of the coupled robots, and the
warm active set on every component (:func:`~aasoatt_env.safety.solvers.active_set_kernel.solve_parts`),
the same operations in the same order.  It answers only where it verifies every component, and then
with the numbers of the numpy stage running the compiled active set, bit for bit
(``tests/test_compiled.py``); otherwise the numpy stage answers the step from its start.
"""

from __future__ import annotations

import math

import numpy as np

from aasoatt_env.model.geometry_kernel import components
from aasoatt_env.numba_jit import jit, nclip
from aasoatt_env.safety.solvers.active_set_kernel import solve_parts

__all__ = ["CLOSED_FORM", "NOT_HERE", "VERIFIED", "box_least_squares", "solve_decomposed"]

CLOSED_FORM = 0
"""No row is violated by the robots' own answers: no QP."""
VERIFIED = 1
"""Every component's warm active set was verified."""
NOT_HERE = -1
"""Not answered here (a component not verified, beyond the dense size, a block not positive definite)."""


@jit
def _box1(A, t, lo, hi, i, out):
    """Robot ``i``'s ``argmin |A_i du - t_i|^2`` in its box into ``out[i]`` (``box_least_squares``' operations).

    The same 2-variable box QP as the local solver's ``local_kernel._box_qp`` (``local._box_qp``), kept
    apart on purpose: this one repeats ``problem.box_least_squares``' operations, NaN and tie rules,
    that one the local solver's.
    """
    a, b, c, d = A[i, 0, 0], A[i, 0, 1], A[i, 1, 0], A[i, 1, 1]
    t0, t1 = t[i, 0], t[i, 1]
    det = a * d - b * c
    x0, x1 = (d * t0 - b * t1) / det, (a * t1 - c * t0) / det
    lo0, lo1, hi0, hi1 = lo[i, 0], lo[i, 1], hi[i, 0], hi[i, 1]
    if not ((x0 < lo0) or (x0 > hi0) or (x1 < lo1) or (x1 > hi1)):
        out[i, 0], out[i, 1] = x0, x1
        return
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


@jit
def box_least_squares(A, target, lo, hi):
    """:func:`aasoatt_env.safety.problem.box_least_squares` of every robot, ``(K, 2)``."""
    out = np.empty((A.shape[0], 2))
    for i in range(A.shape[0]):
        _box1(A, target, lo, hi, i, out)
    return out


@jit
def solve_decomposed(A, target, lo, hi, scale, ri, rj, Gi, Gj, rhs, x_prev, z_warm, settings):
    """One step's centralised QP (module docstring): ``(code, iterations, rows in the QP, du, x, z, eta)``.

    ``x_prev (N, 2)``: the previous scaled point; ``z_warm (m,)``: the previous multipliers on these rows;
    ``settings``: the warm active set's constants (:func:`aasoatt_env.safety.centralized.kernel_settings`).
    The caller checks every shape and index (numba does not).  Only :data:`CLOSED_FORM` and
    :data:`VERIFIED` answers are to be read.
    """
    max_iter, one_change_iter, tol = int(settings[0]), int(settings[1]), settings[2]
    warm_rel, warm_floor, bound_tight, row_norm_min = settings[3], settings[4], settings[5], settings[6]
    dense_max_vars, dense_max_cells = int(settings[7]), int(settings[8])
    n, m = A.shape[0], rhs.shape[0]
    du, x_full, z, eta = np.empty((n, 2)), np.empty((n, 2)), np.zeros(m), np.zeros(m)
    for i in range(n):
        _box1(A, target, lo, hi, i, du)
    # the rows the robots' own answers violate, and the robots of their components
    n_bad, n_rr = 0, 0
    bad = np.zeros(m, np.bool_)
    for q in range(m):
        i = ri[q]
        val = Gi[q, 0] * du[i, 0] + Gi[q, 1] * du[i, 1]
        if rj[q] >= 0:
            j = rj[q]
            val = val + (Gj[q, 0] * du[j, 0] + Gj[q, 1] * du[j, 1])
            n_rr += 1
        else:
            val = val + 0.0
        if val - rhs[q] > 0.0:
            bad[q] = True
            n_bad += 1
    for i in range(n):
        x_full[i, 0], x_full[i, 1] = du[i, 0] / scale[i], du[i, 1] / scale[i]
    if n_bad == 0:
        return CLOSED_FORM, 0, 0, du, x_full, z, eta
    ea, eb = np.empty(n_rr, np.int64), np.empty(n_rr, np.int64)
    k = 0
    for q in range(m):
        if rj[q] >= 0:
            ea[k], eb[k] = ri[q], rj[q]
            k += 1
    label = components(n, ea, eb)
    hit = np.zeros(n, np.bool_)
    for q in range(m):
        if bad[q]:
            hit[label[ri[q]]] = True
    # the coupled robots in order, their groups numbered by component in order of first robot (np.unique's)
    remap = np.full(n, -1, np.int64)
    gnum = np.full(n, -1, np.int64)
    sub = np.empty(n, np.int64)
    groups = np.empty(n, np.int64)
    ns, K = 0, 0
    for i in range(n):
        if hit[label[i]]:
            if gnum[label[i]] < 0:
                gnum[label[i]] = K
                K += 1
            remap[i] = ns
            sub[ns] = i
            groups[ns] = gnum[label[i]]
            ns += 1
    rows = np.empty(m, np.int64)
    ms, nnz = 0, 0
    for q in range(m):
        if remap[ri[q]] >= 0:
            rows[ms] = q
            ms += 1
            nnz += 4 if rj[q] >= 0 else 2
    nv = 2 * ns
    if not (nv <= dense_max_vars or nv * (ms + 2 * nv) <= dense_max_cells):
        return NOT_HERE, 0, ms, du, x_full, z, eta
    # the scaled problem (build_problem's operations)
    H = np.empty((ns, 2, 2))
    sigma = 0.0
    for a in range(ns):
        i = sub[a]
        ss = scale[i] * scale[i]
        for r in range(2):
            for c in range(2):
                H[a, r, c] = 2.0 * (A[i, 0, r] * A[i, 0, c] + A[i, 1, r] * A[i, 1, c]) * ss
                v = abs(H[a, r, c])
                if v != v:
                    sigma = math.nan
                elif v > sigma:
                    sigma = v
    if not (sigma > 0.0):
        return NOT_HERE, 0, ms, du, x_full, z, eta
    LinvT, gt = np.empty((ns, 2, 2)), np.empty(nv)
    lbv, ubv = np.empty(nv), np.empty(nv)
    for a in range(ns):
        i = sub[a]
        for r in range(2):
            for c in range(2):
                H[a, r, c] = H[a, r, c] / sigma
        s = scale[i]
        g0 = -2.0 * (A[i, 0, 0] * target[i, 0] + A[i, 1, 0] * target[i, 1]) * s / sigma
        g1 = -2.0 * (A[i, 0, 1] * target[i, 0] + A[i, 1, 1] * target[i, 1]) * s / sigma
        h00, h10, h11 = H[a, 0, 0], H[a, 1, 0], H[a, 1, 1]
        fa = math.sqrt(h00) if h00 >= 0.0 else math.nan
        fc = h10 / fa
        d2 = h11 - fc * fc
        fd = math.sqrt(d2) if d2 >= 0.0 else math.nan
        if not (h00 > 0.0 and d2 > 0.0 and H[a, 0, 1] == h10):
            return NOT_HERE, 0, ms, du, x_full, z, eta  # a block not positive definite: the reference's other path
        l00, l10, l11 = 1.0 / fa, -fc / (fa * fd), 1.0 / fd
        LinvT[a, 0, 0], LinvT[a, 0, 1], LinvT[a, 1, 0], LinvT[a, 1, 1] = l00, l10, 0.0, l11
        gt[2 * a] = l00 * g0 + 0.0 * g1
        gt[2 * a + 1] = l10 * g0 + l11 * g1
        for h in range(2):
            lbv[2 * a + h], ubv[2 * a + h] = lo[i, h] / s, hi[i, h] / s
    # rows: unit norm in the scaled variables, as CSR (4 entries a robot-robot row, 2 an obstacle row)
    indptr, indices, data = np.empty(ms + 1, np.int64), np.empty(nnz, np.int64), np.empty(nnz)
    nu = np.empty(ms)
    b = np.empty(ms + 2 * nv)
    W0 = np.zeros(ms + 2 * nv, np.bool_)
    zmax = 0.0
    for k in range(ms):
        w = z_warm[rows[k]]
        if w != w:
            zmax = math.nan
        elif w > zmax:
            zmax = w
    zcut = warm_rel * max(zmax, warm_floor) if zmax == zmax else math.nan
    e = 0
    indptr[0] = 0
    for k in range(ms):
        q = rows[k]
        i, si = ri[q], remap[ri[q]]
        gi0, gi1 = Gi[q, 0] * scale[i], Gi[q, 1] * scale[i]
        if rj[q] >= 0:
            j, sj = rj[q], remap[rj[q]]
            gj0, gj1 = Gj[q, 0] * scale[j], Gj[q, 1] * scale[j]
        else:
            sj, gj0, gj1 = -1, 0.0, 0.0
        nrm = math.sqrt((gi0 * gi0 + gi1 * gi1) + (gj0 * gj0 + gj1 * gj1))
        nrm = nrm if nrm > row_norm_min else 1.0
        nu[k] = nrm
        indices[e], indices[e + 1] = 2 * si, 2 * si + 1
        data[e], data[e + 1] = gi0 / nrm, gi1 / nrm
        e += 2
        if sj >= 0:
            indices[e], indices[e + 1] = 2 * sj, 2 * sj + 1
            data[e], data[e + 1] = gj0 / nrm, gj1 / nrm
            e += 2
        indptr[k + 1] = e
        b[k] = rhs[q] / nrm
        W0[k] = z_warm[q] > zcut
    for a in range(ns):
        i = sub[a]
        for h in range(2):
            v = 2 * a + h
            b[ms + v], b[ms + nv + v] = ubv[v], -lbv[v]
            W0[ms + v] = x_prev[i, h] >= ubv[v] - bound_tight
            W0[ms + nv + v] = x_prev[i, h] <= lbv[v] + bound_tight
    y, lam, done = np.zeros(nv), np.zeros(ms + 2 * nv), np.zeros(K, np.bool_)
    used = solve_parts(indptr, indices, data, ms, nv, LinvT, gt, b, W0, groups[:ns].copy(), K, max_iter,
                       one_change_iter, tol, y, lam, done)
    if used < 0:
        return NOT_HERE, 0, ms, du, x_full, z, eta
    verified = 0
    for g in range(K):
        verified += done[g]
    xs = np.empty(nv)
    for a in range(ns):
        y0, y1 = y[2 * a], y[2 * a + 1]
        xs[2 * a] = 0.0 + LinvT[a, 0, 0] * y0 + LinvT[a, 0, 1] * y1  # (einsum's sums start from +0.0)
        xs[2 * a + 1] = 0.0 + LinvT[a, 1, 0] * y0 + LinvT[a, 1, 1] * y1
    if verified < K:
        return NOT_HERE, used, ms, du, x_full, z, eta
    for v in range(nv):
        if not math.isfinite(xs[v]):
            return NOT_HERE, used, ms, du, x_full, z, eta  # (the reference answers zeros then: its path decides)
    for a in range(ns):
        i = sub[a]
        for h in range(2):
            x = xs[2 * a + h]
            du[i, h] = nclip(x * scale[i], lo[i, h], hi[i, h])
            x_full[i, h] = x
    for k in range(ms):
        zk = lam[k]
        zk = zk if zk > 0.0 or zk != zk else 0.0
        zk = zk if math.isfinite(zk) else 0.0
        z[rows[k]] = zk
        eta[rows[k]] = sigma * zk / nu[k]
    return VERIFIED, used, ms, du, x_full, z, eta
