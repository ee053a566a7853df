"""The warm active set compiled (numba; imported only through :mod:`aasoatt_env.compiled`).

:func:`solve_parts` is :func:`aasoatt_env.safety.solvers.active_set.solve_active_set_parts`'s dense path group by group,
rows formed entry by entry as ``active_set._dense_rows`` forms them, in the global order (ties break alike).  It differs
in summation order (points agree to rounding; a dependent working set may verify other parts), in using the Cholesky at
any size, in each group's own regularisation, and in zeroing an unverified group's part.
"""

import math

import numpy as np

from aasoatt_env.numba_jit import jit, jit_reassoc

__all__ = ["solve_parts"]


@jit_reassoc
def _cholesky(S, k, delta, L):
    """Lower Cholesky factor of ``S[:k, :k] + delta I`` into ``L``; False if not positive definite (as ``potrf``)."""
    for j in range(k):
        d = S[j, j] + delta
        for q in range(j):
            d -= L[j, q] * L[j, q]
        if not d > 0.0:
            return False
        d = math.sqrt(d)
        L[j, j] = d
        for i in range(j + 1, k):
            s = S[i, j]
            for q in range(j):
                s -= L[i, q] * L[j, q]
            L[i, j] = s / d
    return True


@jit_reassoc
def _chol_solve(L, k, v, out):
    """``out = S^-1 v`` from the factor ``L`` (two triangular substitutions)."""
    for i in range(k):
        s = v[i]
        for q in range(i):
            s -= L[i, q] * out[q]
        out[i] = s / L[i, i]
    for i in range(k - 1, -1, -1):
        s = out[i]
        for q in range(i + 1, k):
            s -= L[q, i] * out[q]
        out[i] = s / L[i, i]


@jit
def _schur(rb, rc, nbg, idx, k, S, bstart, blist):
    """``S = Mw Mw'`` of the working rows ``idx[:k]``, robot block by block in the dense product's order."""
    for a in range(k):
        for c2 in range(k):
            S[a, c2] = 0.0
    bstart[: nbg + 1] = 0
    for a in range(k):
        for u in range(2):
            if rb[idx[a], u] >= 0:
                bstart[rb[idx[a], u] + 1] += 1
    for blk in range(nbg):
        bstart[blk + 1] += bstart[blk]
    for a in range(k):  # rows in ascending order within each block
        for u in range(2):
            blk = rb[idx[a], u]
            if blk >= 0:
                pos = bstart[blk]
                blist[pos, 0], blist[pos, 1] = a, u
                bstart[blk] += 1
    for blk in range(nbg - 1, -1, -1):  # back to the starts
        bstart[blk + 1] = bstart[blk]
    bstart[0] = 0
    for blk in range(nbg):  # blocks in ascending order: the terms in the order of the dense product
        for p1 in range(bstart[blk], bstart[blk + 1]):
            a, u = blist[p1, 0], blist[p1, 1]
            qa = idx[a]
            for p2 in range(bstart[blk], p1 + 1):
                c2, v = blist[p2, 0], blist[p2, 1]
                qc = idx[c2]
                S[a, c2] += rc[qa, u, 0] * rc[qc, v, 0] + rc[qa, u, 1] * rc[qc, v, 1]
    for a in range(k):
        for c2 in range(a):
            S[c2, a] = S[a, c2]


@jit
def _dot_vec(rb, rc, a, x):
    """``M[a] . x`` of a sparse row and a dense vector ``x (nv,)``."""
    s = 0.0
    for u in range(2):
        ba = rb[a, u]
        if ba < 0:
            break
        s += rc[a, u, 0] * x[2 * ba] + rc[a, u, 1] * x[2 * ba + 1]
    return s


@jit
def _equality_point(rb, rc, nl, nv, gt, b, W, idx, rhs, lw, tmp, res, y, lam, r, bstart, blist):
    """``(y, lam, r)`` with the rows ``W`` as equalities (``_equality_point``); False if singular."""
    k = 0
    for q in range(nl):
        lam[q] = 0.0
        if W[q]:
            idx[k] = q
            k += 1
    for c in range(nv):
        y[c] = 0.0
    if k:
        S, L = np.empty((k, k)), np.empty((k, k))  # sized to the working set (a part's rows can be many more)
        _schur(rb, rc, nv // 2, idx, k, S, bstart, blist)
        dmax = 0.0
        for a in range(k):
            dmax = max(dmax, S[a, a])
            rhs[a] = -_dot_vec(rb, rc, idx[a], gt) - b[idx[a]]
        if not _cholesky(S, k, 1e-9 * max(dmax, 1e-300), L):
            return False
        # proximal iterative refinement (``_refine``): lw = solve(rhs), then four corrections
        _chol_solve(L, k, rhs, lw)
        for _ in range(4):
            for a in range(k):
                s = rhs[a]
                for c2 in range(k):
                    s -= S[a, c2] * lw[c2]
                res[a] = s
            _chol_solve(L, k, res, tmp)
            for a in range(k):
                lw[a] += tmp[a]
        for a in range(k):
            if not math.isfinite(lw[a]):
                return False
        for a in range(k):  # y = -gt - Mw' lw
            q = idx[a]
            lam[q] = lw[a]
            for u in range(2):
                ba = rb[q, u]
                if ba < 0:
                    break
                y[2 * ba] += rc[q, u, 0] * lw[a]
                y[2 * ba + 1] += rc[q, u, 1] * lw[a]
    for c in range(nv):
        y[c] = -gt[c] - y[c]
    for q in range(nl):
        r[q] = _dot_vec(rb, rc, q, y) - b[q]
    return True


@jit
def _kkt(nl, W, lam, r, tol):
    """``(KKT check of _WorkingSetLoop.run, every working row met)``, written as what must hold: a NaN fails."""
    ok = met = True
    for q in range(nl):
        m = (not W[q]) or (abs(r[q]) <= tol)
        ok, met = ok and m and (r[q] <= tol) and (lam[q] >= -tol), met and m
    return ok, met


@jit
def _one_change(nl, W, lam, r, prev, has_prev, tol, Wn):
    """``_one_change_rule`` for one group: add the most violated row, or drop one by the ratio test."""
    for q in range(nl):
        Wn[q] = W[q]
    neg = False
    for q in range(nl):
        if lam[q] < -tol:
            neg = True
            break
    if not neg:
        k, best = -1, math.inf
        for q in range(nl):
            if not W[q] and (k < 0 or -r[q] < best):
                if -r[q] == -r[q]:
                    k, best = q, -r[q]
        if k >= 0 and math.isfinite(best) and r[k] > tol:
            Wn[k] = True
        return
    k, best = -1, math.inf
    for q in range(nl):
        if (k < 0 or lam[q] < best) and lam[q] == lam[q]:
            k, best = q, lam[q]
    if not math.isfinite(best):
        k = -1
    if has_prev:
        kc, bc = -1, math.inf
        for q in range(nl):
            if lam[q] < -tol and prev[q] > tol:
                ratio = prev[q] / (prev[q] - lam[q])
                if (kc < 0 or ratio < bc) and ratio == ratio:
                    kc, bc = q, ratio
        if kc >= 0 and math.isfinite(bc):
            k = kc
    if k >= 0:
        Wn[k] = False


@jit
def _run(rb, rc, nl, nv, gt, b, W0, rule, budget, tol, W, Wn, prev, idx, rhs, lw, tmp, res, y, lam, r, bstart, blist,
         first, yf, lamf, rf):
    """One rule (0: primal-dual, 1: one change) from ``W0``: ``(verified, solves)``; ``first``: ``W0``'s point, kept."""
    for q in range(nl):
        W[q] = W0[q]
    has_prev = False
    used = 0
    for it in range(budget):
        if it == 0 and first[0]:
            ok = not first[1]
            y[:nv] = yf[:nv]
            lam[:nl] = lamf[:nl]
            r[:nl] = rf[:nl]
        else:
            ok = _equality_point(rb, rc, nl, nv, gt, b, W, idx, rhs, lw, tmp, res, y, lam, r, bstart, blist)
            used += 1
            if it == 0:
                first[0], first[1] = True, not ok
                yf[:nv] = y[:nv]
                lamf[:nl] = lam[:nl]
                rf[:nl] = r[:nl]
        if not ok:
            return False, used
        verified, consistent = _kkt(nl, W, lam, r, tol)
        if verified:
            return True, used
        if rule == 0 and not consistent:
            return False, used  # the primal-dual rule leaves a group with an inconsistent working set
        if rule == 0:
            for q in range(nl):
                Wn[q] = (lam[q] + r[q]) > 0
        else:
            _one_change(nl, W, lam, r, prev, has_prev, tol, Wn)
        same = True
        for q in range(nl):
            if Wn[q] != W[q]:
                same = False
                break
        if same:
            return False, used
        for q in range(nl):
            W[q] = Wn[q]
            prev[q] = lam[q]
        has_prev = True
    return False, used


@jit
def _by_group(indptr, indices, m, nb, groups, K):
    """Robots and rows by group (counting sorts): ``(robots, starts, rows, starts)``; starts ``[-1]``: bad rows."""
    rstart, qstart = np.zeros(K + 1, dtype=np.int64), np.zeros(K + 1, dtype=np.int64)
    row_group = np.zeros(m, dtype=np.int64)
    for i in range(nb):
        rstart[groups[i] + 1] += 1
    for q in range(m):
        if indptr[q + 1] > indptr[q]:
            row_group[q] = groups[indices[indptr[q]] // 2]
        for e in range(indptr[q] + 1, indptr[q + 1]):
            if indices[e] <= indices[e - 1]:
                return rstart, np.full(1, -1, dtype=np.int64), row_group, qstart
        qstart[row_group[q] + 1] += 1
    for g in range(K):
        rstart[g + 1] += rstart[g]
        qstart[g + 1] += qstart[g]
    robots, rows = np.empty(nb, dtype=np.int64), np.empty(m, dtype=np.int64)
    fill = rstart[:K].copy()
    for i in range(nb):
        robots[fill[groups[i]]] = i
        fill[groups[i]] += 1
    fill = qstart[:K].copy()
    for q in range(m):
        rows[fill[row_group[q]]] = q
        fill[row_group[q]] += 1
    return robots, rstart, rows, qstart


@jit
def _group_rows(g, srt, indptr, indices, data, m, n, LinvT, gt, b, W0, loc, rb, rc, gidx, bl, W0l, gl):
    """Group ``g``'s rows ``rb``, ``rc`` (``C T``, then ``+-L^-T``) and their data: ``(variables, rows)``, -1: unfit."""
    robots, rstart, rows, qstart = srt
    r0, nbg, mg = rstart[g], rstart[g + 1] - rstart[g], qstart[g + 1] - qstart[g]
    nv = 2 * nbg
    for a in range(nbg):
        loc[robots[r0 + a]] = a
    rb[:mg + 2 * nv] = -1
    rc[:mg + 2 * nv] = 0.0
    for j in range(mg):
        q = rows[qstart[g] + j]
        gidx[j], bl[j], W0l[j] = q, b[q], W0[q]
        for e in range(indptr[q], indptr[q + 1]):
            blk, half = indices[e] // 2, indices[e] % 2
            a = loc[blk]
            u = 0 if (rb[j, 0] < 0 or rb[j, 0] == a) else 1
            if rb[j, u] >= 0 and rb[j, u] != a:
                return -1, -1
            rb[j, u] = a
            for c in range(2):
                rc[j, u, c] += data[e] * LinvT[blk, half, c]
    for a in range(nbg):
        blk = robots[r0 + a]
        for half in range(2):
            vg = 2 * blk + half
            ju, jl = mg + 2 * a + half, mg + nv + 2 * a + half
            gidx[ju], gidx[jl] = m + vg, m + n + vg
            bl[ju], bl[jl] = b[m + vg], b[m + n + vg]
            W0l[ju], W0l[jl] = W0[m + vg], W0[m + n + vg]
            gl[2 * a + half] = gt[vg]
            rb[ju, 0] = rb[jl, 0] = a
            for c in range(2):
                rc[ju, 0, c] = LinvT[blk, half, c] + 0.0
                rc[jl, 0, c] = -LinvT[blk, half, c] + 0.0
    return nv, mg + 2 * nv


@jit
def solve_parts(indptr, indices, data, m, n, LinvT, gt, b, W0, groups, K, max_iter, one_change_iter, tol,
                y_out, lam_out, done):
    """Every group's warm active set (module docstring): the most equality solves of a group.

    A negative answer: rows not of the form handled here (unsorted or repeated columns, a row on more than two robots);
    the caller takes the reference path.
    """
    nb = n // 2
    srt = _by_group(indptr, indices, m, nb, groups, K)
    robots, rstart, _, qstart = srt
    if rstart[0] < 0:
        return -1
    nvmax, nlmax = 0, 0  # the largest group, for the work arrays
    for g in range(K):
        nv = 2 * (rstart[g + 1] - rstart[g])
        nvmax, nlmax = max(nvmax, nv), max(nlmax, (qstart[g + 1] - qstart[g]) + 2 * nv)
    rb, rc = np.empty((nlmax, 2), np.int64), np.empty((nlmax, 2, 2))
    gl, bl = np.empty(nvmax), np.empty(nlmax)
    W0l, W, Wn = np.empty(nlmax, np.bool_), np.empty(nlmax, np.bool_), np.empty(nlmax, np.bool_)
    prev, idx = np.zeros(nlmax), np.empty(nlmax, np.int64)
    rhs, lw, tmp, res = np.empty(nlmax), np.empty(nlmax), np.empty(nlmax), np.empty(nlmax)
    y, lam, r = np.empty(nvmax), np.empty(nlmax), np.empty(nlmax)
    yf, lamf, rf = np.empty(nvmax), np.empty(nlmax), np.empty(nlmax)  # the first working set's point
    first = np.zeros(2, np.bool_)
    bstart, blist = np.empty(nvmax // 2 + 1, np.int64), np.empty((2 * nlmax, 2), np.int64)
    gidx, loc = np.empty(nlmax, np.int64), np.full(nb, -1, np.int64)  # each local row's index, robot's block
    used_max = 0
    for g in range(K):
        nv, nl = _group_rows(g, srt, indptr, indices, data, m, n, LinvT, gt, b, W0, loc, rb, rc, gidx, bl, W0l, gl)
        if nv < 0:
            return -2
        first[0] = first[1] = False
        ok, used = _run(rb, rc, nl, nv, gl, bl, W0l, 0, max_iter, tol, W, Wn, prev, idx, rhs, lw, tmp, res, y,
                        lam, r, bstart, blist, first, yf, lamf, rf)
        if not ok:
            ok, used2 = _run(rb, rc, nl, nv, gl, bl, W0l, 1, one_change_iter, tol, W, Wn, prev, idx, rhs, lw, tmp,
                             res, y, lam, r, bstart, blist, first, yf, lamf, rf)
            used += used2
        used_max = max(used_max, used)
        done[g] = ok
        for a in range(nv // 2):
            blk = robots[rstart[g] + a]
            if ok:
                y_out[2 * blk], y_out[2 * blk + 1] = y[2 * a], y[2 * a + 1]
            loc[blk] = -1
        for j in range(nl if ok else 0):
            lam_out[gidx[j]] = lam[j]
    return used_max
