"""The warm active set compiled (numba; imported only through :mod:`aasoatt_env.compiled`).

:func:`solve_parts` is :func:`aasoatt_env.safety.solvers.active_set.solve_active_set_parts`
on its dense path, written once per group (an independent part of the problem:
a coupled component of a team, or a team of a stack) instead of once per array
operation on the whole problem.  Each group's rows (its own rows of ``C``, then
the upper and then the lower bounds of its variables, in the global order, so
every "first index" tie is broken as the reference breaks it) are formed in
``y = L^T x`` entry by entry as
:func:`~aasoatt_env.safety.solvers.active_set._dense_rows` forms them, and kept
sparse (a row touches at most two robots); then the primal-dual rule from the
warm start (left when the working set turns inconsistent), then the one-change
rule from the warm start (whose point is not solved again), each equality point
from a Cholesky factor of the regularised Schur complement with four steps of
iterative refinement, and the same KKT check (primal feasibility, multiplier
signs, the working rows met as equalities, all within
:data:`~aasoatt_env.safety.solvers.active_set.TOL`).  A group is kept at the
first point that passes it; the caller sends the others to the general solver,
as with the reference.

Where the two differ:

- sums are added in another order (the Schur complement block by block, the
  factor and its solves with reassociated, vectorised sums; BLAS in the
  reference), the factor is this module's Cholesky also above 500 working rows
  (the reference switches to a sparse LU there): the points agree to rounding;
- so where a working set is dependent (more rows than the part's variables,
  met by the primal-dual rule from a poor start), the regularised solve is
  ill-conditioned (multipliers ~1e9) and the last bits decide the next working
  set: the two may then verify different parts (tests: never from the filter's
  warm starts seen, about 2% of parts from cold starts); an unverified part
  goes to the general solver, whose answer is the same optimum;
- the Schur complement's regularisation ``1e-9`` times its largest diagonal
  entry is the group's here, the whole working set's in the reference: a group
  whose working rows are all zero rows (``0 <= b``) is singular here (its
  regularisation vanishes) and can be verified there; on parts scaled 1e3 apart
  in one stack, the kernel verified ~4% more parts than the reference (an
  adversarial tester's count; none differed on real teams);
- a singular working set ends that group's rule here; in the reference it ends
  the rule for every group not yet verified (those groups then go on to the
  next rule or the general solver);
- an unverified group's part of the returned point and multipliers is zero (the
  reference leaves its last iterate there; the caller reads neither);
- the iterations reported are the largest count of equality solves of any
  group (the reference counts its whole-problem solves).
"""

from __future__ import annotations

import math

import numpy as np

from aasoatt_env.numba_jit import jit as _jit
from aasoatt_env.numba_jit import jit_reassoc as _jit_reassoc

__all__ = ["solve_parts"]


@_jit_reassoc
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


@_jit_reassoc
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


@_jit
def _schur(rb, rc, nbg, idx, k, S, bstart, blist):
    """``S = Mw Mw'`` of the working rows ``idx[:k]``, robot block by robot block (rows meet only on shared robots).

    ``bstart (nbg + 1,)`` and ``blist (2 k, 2)`` are work arrays: the working rows on each block and their slot.
    """
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


@_jit
def _dot_vec(rb, rc, a, x):
    """``M[a] . x`` of a sparse row and a dense vector ``x (nv,)``."""
    s = 0.0
    for u in range(2):
        ba = rb[a, u]
        if ba < 0:
            break
        s += rc[a, u, 0] * x[2 * ba] + rc[a, u, 1] * x[2 * ba + 1]
    return s


@_jit
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


@_jit
def _verified(nl, W, lam, r, tol):
    """The KKT check of ``_WorkingSetLoop.run`` (written as what must hold: a NaN fails)."""
    for q in range(nl):
        if not ((r[q] <= tol) and (lam[q] >= -tol) and ((not W[q]) or (abs(r[q]) <= tol))):
            return False
    return True


@_jit
def _consistent(nl, W, r, tol):
    """Every working row met as an equality within ``tol`` (a NaN is not)."""
    for q in range(nl):
        if W[q] and not (abs(r[q]) <= tol):
            return False
    return True


@_jit
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


@_jit
def _run(rb, rc, nl, nv, gt, b, W0, rule, budget, tol, W, Wn, prev, idx, rhs, lw, tmp, res, y, lam, r, bstart, blist,
         first, yf, lamf, rf):
    """Iterate one rule (0: primal-dual, 1: one change) from ``W0``; returns ``(verified, equality solves)``.

    ``first[0]``: the point of ``W0`` is in ``yf, lamf, rf`` (``first[1]``: it was singular), kept by the first
    rule for the second (the reference's ``_WorkingSetLoop._point``).
    """
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
        if _verified(nl, W, lam, r, tol):
            return True, used
        if rule == 0 and not _consistent(nl, W, r, tol):
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


@_jit
def solve_parts(indptr, indices, data, m, n, LinvT, gt, b, W0, groups, K, max_iter, one_change_iter, tol,
                y_out, lam_out, done):
    """Every group's warm active set (module docstring); fills ``y_out (n,)``, ``lam_out (m + 2n,)``, ``done (K,)``.

    ``groups (n / 2,)`` and ``K`` as the caller checked them (no row joins two groups; a row's group is that of its
    first entry, an empty row's 0).  Returns the largest count of equality solves of a group, or a negative
    number where the rows are not of the form this kernel handles (a row with unsorted or repeated columns, or
    on more than two robots): the caller takes the reference path.
    """
    nb = n // 2
    # robots and rows by group (counting sorts, stable)
    rstart = np.zeros(K + 1, dtype=np.int64)
    for i in range(nb):
        rstart[groups[i] + 1] += 1
    row_group = np.zeros(m, dtype=np.int64)
    for q in range(m):
        if indptr[q + 1] > indptr[q]:
            row_group[q] = groups[indices[indptr[q]] // 2]
        for e in range(indptr[q] + 1, indptr[q + 1]):
            if indices[e] <= indices[e - 1]:
                return -1  # unsorted or repeated columns: not the dense rows of the reference
    qstart = np.zeros(K + 1, dtype=np.int64)
    for q in range(m):
        qstart[row_group[q] + 1] += 1
    for g in range(K):
        rstart[g + 1] += rstart[g]
        qstart[g + 1] += qstart[g]
    robots = np.empty(nb, dtype=np.int64)
    fill = rstart[:K].copy()
    for i in range(nb):
        robots[fill[groups[i]]] = i
        fill[groups[i]] += 1
    rows = np.empty(m, dtype=np.int64)
    fill = qstart[:K].copy()
    for q in range(m):
        rows[fill[row_group[q]]] = q
        fill[row_group[q]] += 1
    # largest group, for the work arrays
    nvmax, nlmax = 0, 0
    for g in range(K):
        nv = 2 * (rstart[g + 1] - rstart[g])
        nvmax = max(nvmax, nv)
        nlmax = max(nlmax, (qstart[g + 1] - qstart[g]) + 2 * nv)
    rb = np.empty((nlmax, 2), np.int64)  # the local robot blocks of each local row (-1: none)
    rc = np.empty((nlmax, 2, 2))  # and the row's two coefficients on each
    gl, bl = np.empty(nvmax), np.empty(nlmax)
    W0l, W, Wn = np.empty(nlmax, np.bool_), np.empty(nlmax, np.bool_), np.empty(nlmax, np.bool_)
    prev, idx = np.zeros(nlmax), np.empty(nlmax, np.int64)
    rhs, lw, tmp, res = np.empty(nlmax), np.empty(nlmax), np.empty(nlmax), np.empty(nlmax)
    y, lam, r = np.empty(nvmax), np.empty(nlmax), np.empty(nlmax)
    yf, lamf, rf = np.empty(nvmax), np.empty(nlmax), np.empty(nlmax)  # the first working set's point
    first = np.zeros(2, np.bool_)
    bstart, blist = np.empty(nvmax // 2 + 1, np.int64), np.empty((2 * nlmax, 2), np.int64)
    gidx = np.empty(nlmax, np.int64)  # global index of each local row
    loc = np.full(nb, -1, np.int64)  # local block of each robot of the group
    used_max = 0
    for g in range(K):
        r0, r1 = rstart[g], rstart[g + 1]
        nbg = r1 - r0
        nv = 2 * nbg
        mg = qstart[g + 1] - qstart[g]
        nl = mg + 2 * nv
        for a in range(nbg):
            loc[robots[r0 + a]] = a
        rb[:nl] = -1
        rc[:nl] = 0.0
        for j in range(mg):  # the group's rows of C T, entry by entry as the reference forms them
            q = rows[qstart[g] + j]
            gidx[j] = q
            bl[j] = b[q]
            W0l[j] = W0[q]
            for e in range(indptr[q], indptr[q + 1]):
                col = indices[e]
                blk, half = col // 2, col % 2
                a = loc[blk]
                u = 0 if (rb[j, 0] < 0 or rb[j, 0] == a) else 1
                if rb[j, u] >= 0 and rb[j, u] != a:
                    return -2  # a row on three robots: not these problems' rows
                rb[j, u] = a
                for c in range(2):
                    rc[j, u, c] += data[e] * LinvT[blk, half, c]
        for a in range(nbg):  # the bounds: +-L^-T blocks
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
        first[0] = first[1] = False
        ok, used = _run(rb, rc, nl, nv, gl, bl, W0l, 0, max_iter, tol, W, Wn, prev, idx, rhs, lw, tmp, res, y,
                        lam, r, bstart, blist, first, yf, lamf, rf)
        if not ok:
            ok, used2 = _run(rb, rc, nl, nv, gl, bl, W0l, 1, one_change_iter, tol, W, Wn, prev, idx, rhs, lw, tmp,
                             res, y, lam, r, bstart, blist, first, yf, lamf, rf)
            used += used2
        used_max = max(used_max, used)
        done[g] = ok
        if ok:
            for a in range(nbg):
                blk = robots[r0 + a]
                y_out[2 * blk], y_out[2 * blk + 1] = y[2 * a], y[2 * a + 1]
            for j in range(nl):
                lam_out[gidx[j]] = lam[j]
        for a in range(nbg):
            loc[robots[r0 + a]] = -1
    return used_max
