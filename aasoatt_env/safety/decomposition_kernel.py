"""The centralised filter's exact decomposition in one compiled call (numba; through :mod:`aasoatt_env.compiled`).

:func:`solve_decomposed` is what :func:`aasoatt_env.safety.decomposition.solve_centralized`
does in numpy on a warm-started step, written as loops over the robots and rows
of one call instead of dozens of small array operations (whose overhead, not
their arithmetic, is a small team's or a training stack's step):

1. every robot's box least squares in closed form
   (:func:`~aasoatt_env.safety.problem.box_least_squares`, the same operations
   in the same order);
2. the rows those answers violate, the contact components
   (:func:`~aasoatt_env.model.geometry_kernel.components`) and the robots of the
   components with a violated row;
3. the scaled problem of those robots
   (:func:`~aasoatt_env.safety.problem.build_problem`), its block Cholesky
   factor and the warm working set
   (:func:`~aasoatt_env.safety.solvers.active_set.solve_active_set_parts`),
   the same operations in the same order;
4. the warm active set on every component
   (:func:`aasoatt_env.safety.solvers.active_set_kernel.solve_parts`, the kernel
   the reference calls on these problems);
5. the answer assembled as the filter assembles it.

It answers only where every component is verified.  Where some of two or more
components are not, it hands the warm active set's answer on all of them to the
reference (:data:`PARTS`), which builds the same problem and goes on from there
with the unverified ones (the policy's ``solve(..., parts=)``).  Otherwise (and where the
reference would not take this kernel's path: a problem beyond the dense size,
a Hessian block not positive definite, rows the active-set kernel does not
handle) it returns a negative code and changes nothing the caller reads, and
the caller runs the reference path, which decides that step as before.  Where
it answers, its numbers are those of the numpy decomposition running the
compiled active set, bit for bit (``tests/test_compiled.py`` compares every
step of filtered episodes; the closed forms on random robots equal numpy's,
where a tie of a number with a signed zero bound may give the other zero, as
numpy's own clip does between its scalar and vector code, and a NaN the other
sign); against ``kernel="numpy"`` (the numpy active set too) they agree to
rounding, as that kernel's points do.
"""

from __future__ import annotations

import math

import numpy as np

from aasoatt_env.model.geometry_kernel import components
from aasoatt_env.numba_jit import jit, nclip
from aasoatt_env.safety.solvers.active_set_kernel import solve_parts

__all__ = ["box_least_squares", "search_rows", "solve_decomposed"]

CLOSED_FORM = 0
"""Return code: no row is violated by the robots' own answers (no QP)."""
VERIFIED = 1
"""Return code: every component's warm active set was verified."""
NOT_HERE = -1
"""Return code: the caller takes the reference path (its outputs are not to be read)."""
PARTS = 2
"""Return code: some of two or more components were not verified; the warm active set's answer on every
component is in ``xs, zs, done`` (the reference path takes it over for the problem it builds)."""


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
def search_rows(sorted_keys, z_of, keys, out):
    """``out[r]``: ``z_of`` at the key ``keys[r]`` of ``sorted_keys`` (non-decreasing), 0 where none.

    ``numpy.searchsorted``'s leftmost position, as the filter's warm start takes it
    (:meth:`aasoatt_env.safety.core.SafetyFilter`, which keeps its rows in key order).
    """
    P = sorted_keys.shape[0]
    for r in range(keys.shape[0]):
        k, a, b = keys[r], 0, P
        while a < b:
            mid = (a + b) // 2
            if sorted_keys[mid] < k:
                a = mid + 1
            else:
                b = mid
        out[r] = z_of[a] if a < P and sorted_keys[a] == k else 0.0


@jit
def box_least_squares(A, target, lo, hi):
    """:func:`aasoatt_env.safety.problem.box_least_squares` of every robot, ``(K, 2)``."""
    out = np.empty((A.shape[0], 2))
    for i in range(A.shape[0]):
        _box1(A, target, lo, hi, i, out)
    return out


@jit
def solve_decomposed(A, target, lo, hi, scale, ri, rj, Gi, Gj, rhs, x_prev, z_warm, max_iter, one_change_iter, tol,
                     warm_rel, warm_floor, bound_tight, row_norm_min, dense_max_vars, dense_max_cells, du, x_full, z,
                     eta, xs_out, zs_out, done_out):
    """One centralised step's QP part (module docstring); fills ``du, x_full (N, 2)``, ``z, eta (m,)``.

    ``x_prev (N, 2)``: the previous step's scaled point; ``z_warm (m,)``: the previous multipliers mapped onto
    these rows; the constants are those of :mod:`~aasoatt_env.safety.solvers.active_set` and
    :data:`~aasoatt_env.safety.problem.ROW_NORM_MIN`, passed by the caller (one home each).  The caller
    checks every shape and index (the kernel reads without bounds checks).  Returns ``(code, iterations,
    rows in the QP, variables in the QP, components)``: :data:`CLOSED_FORM`, :data:`VERIFIED`,
    :data:`NOT_HERE` (nothing filled is to be read) or :data:`PARTS`: then ``xs_out[:variables]``
    (``(2N,)``) holds the scaled point of the coupled robots, ``zs_out[:rows]`` (``(m,)``) the
    multipliers of their rows (``>= 0``, NaN kept) and ``done_out[:components]`` (``(N,)``) which
    components were verified: what :func:`~aasoatt_env.safety.solvers.active_set.solve_active_set_parts`
    answers on the problem the reference builds (its point ``x``, ``z`` and ``ok``), so the reference
    goes on from there.
    """
    n, m = A.shape[0], rhs.shape[0]
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
    z[:] = 0.0
    eta[:] = 0.0
    if n_bad == 0:
        return CLOSED_FORM, 0, 0, 0, 0
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
        return NOT_HERE, 0, ms, nv, K
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
        return NOT_HERE, 0, ms, nv, K
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
            return NOT_HERE, 0, ms, nv, K  # a block not positive definite: the reference's other path
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
        return NOT_HERE, 0, ms, nv, K
    verified = 0
    for g in range(K):
        verified += done[g]
    xs = np.empty(nv)
    for a in range(ns):
        y0, y1 = y[2 * a], y[2 * a + 1]
        xs[2 * a] = 0.0 + LinvT[a, 0, 0] * y0 + LinvT[a, 0, 1] * y1  # (einsum's sums start from +0.0)
        xs[2 * a + 1] = 0.0 + LinvT[a, 1, 0] * y0 + LinvT[a, 1, 1] * y1
    if verified < K:
        if K < 2:  # (the reference runs one part's active set inside the solver policy's own path)
            return NOT_HERE, used, ms, nv, K
        for v in range(nv):  # (no group verified: the reference's point is zeros, unread by its next step)
            xs_out[v] = xs[v] if verified else 0.0
        for k in range(ms):
            zk = lam[k] if verified else 0.0
            zs_out[k] = zk if zk > 0.0 or zk != zk else 0.0  # np.maximum(lam, 0.0): +0.0 for -0.0, NaN kept
        for g in range(K):
            done_out[g] = done[g]
        return PARTS, used, ms, nv, K
    for v in range(nv):
        if not math.isfinite(xs[v]):
            return NOT_HERE, used, ms, nv, K  # (the reference answers zeros then: its path decides)
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
    return VERIFIED, used, ms, nv, K
