"""The warm active set: an exact structured solver for the safety QP, tried first from the previous step.

In ``y = L^T x`` (``H = L L^T`` block diagonal) the QP reads ``min 0.5 |y|^2 + gt'y  s.t.  Mt y <= b``; a working set
is solved through its Schur complement.  From the previous working set the primal-dual rule (Hintermueller, Ito,
Kunisch 2002) runs until inconsistent, then a one-change rule.  A point is returned only where the KKT conditions hold
within :data:`TOL`, part by part for independent parts; otherwise the caller's general solver answers.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp

from aasoatt_env.compiled import c64, kernels

__all__ = ["TOL", "ActiveSetParts", "LeastDistanceForm", "dense_least_distance_form",
           "least_distance_form", "one_change_budget", "solve_active_set", "solve_active_set_parts"]

DENSE_MAX_VARS: int = 80  #: problems up to this many variables use dense algebra, whatever their rows
DENSE_MAX_CELLS: int = 400_000  #: larger ones too up to this many entries of their dense rows ``(m + 2n) x n``
SPARSE_DENSE_SCHUR_ROWS: int = 200  #: sparse rows: working sets up to this size factor the Schur complement densely
WARM_REL: float = 1e-6  #: rows whose warm multiplier exceeds this fraction of the largest start in the working set
TOL: float = 1e-10  #: feasibility / dual-sign tolerance of the KKT check (normalised rows, ``|x| <= 1``)
# budgets: a part not verified spends them all before the route's exact solver, which answers sooner than more would
ONE_CHANGE_ITER: int = 8  #: one-change iterations after the primal-dual ones
PDAS_ITER: int = 12  #: iterations of the primal-dual rule from the warm start
BOUND_TIGHT: float = 1e-9  #: a warm start within this of a bound (scaled) starts with the bound in the working set
WARM_FLOOR: float = 1e-300  #: floor of the largest warm multiplier in the working-set cut (no cut of zero)
VERIFIED_MESSAGE: str = "active set (warm, KKT verified)"


class LeastDistanceForm(NamedTuple):
    """``min 0.5|y|^2 + gt'y  s.t.  Mt y <= b`` in ``y = L^T x``; ``Mt`` ``(m + 2n, n)``: the rows, then both bounds."""

    LinvT: np.ndarray
    gt: np.ndarray
    Mt: sp.csr_matrix | np.ndarray
    b: np.ndarray

    def to_x(self, y: np.ndarray) -> np.ndarray:
        """``x = L^{-T} y``."""
        return np.einsum("nij,nj->ni", self.LinvT, y.reshape(-1, 2)).ravel()


def _once(make):
    """``make(prob)`` computed once per problem object (kept in its ``__dict__``)."""
    key = f"_{make.__name__}"

    @functools.wraps(make)
    def once(prob):
        if key not in prob.__dict__:
            prob.__dict__[key] = make(prob)
        return prob.__dict__[key]

    return once


@_once
def _factor(prob) -> tuple[np.ndarray, np.ndarray] | None:
    """``(L^{-T} blocks (N, 2, 2), gt = L^{-1} g)`` of ``prob``; ``None`` if a block is not PD."""
    nb = prob.n // 2
    # the Cholesky factor of every 2x2 block in closed form, L = [[a, 0], [c, d]], and its inverse
    H = prob.H_blocks
    h00, h10, h11 = H[:, 0, 0], H[:, 1, 0], H[:, 1, 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.sqrt(h00)
        c = h10 / a
        d2 = h11 - c * c
        d = np.sqrt(d2)
    if not (np.all(h00 > 0.0) and np.all(d2 > 0.0) and np.all(H[:, 0, 1] == h10)):
        return None  # a block not symmetric positive definite (or not finite)
    Linv = np.zeros((nb, 2, 2))
    Linv[:, 0, 0], Linv[:, 1, 1], Linv[:, 1, 0] = 1.0 / a, 1.0 / d, -c / (a * d)
    return np.transpose(Linv, (0, 2, 1)), np.einsum("nij,nj->ni", Linv, prob.g.reshape(nb, 2)).ravel()


def dense_least_distance_form(prob, rows: bool = True) -> LeastDistanceForm | None:
    """:func:`least_distance_form` with its rows ``Mt`` dense (None without ``rows``), built without scipy.sparse."""
    factor = _factor(prob)
    if factor is None:
        return None
    Mt = _dense_rows(prob, factor[0]) if rows else None
    return LeastDistanceForm(*factor, Mt, np.concatenate((prob.u, prob.ub, -prob.lb)))


def _least_distance_form(prob) -> LeastDistanceForm | None:
    """:class:`LeastDistanceForm` of ``prob``; ``None`` if a Hessian block is not PD."""
    n = prob.n
    nb = n // 2
    factor = _factor(prob)
    if factor is None:
        return None
    LinvT, gt = factor
    # x = T y with T = blockdiag(L^-T): rows C x <= u become (C T) y <= u; bounds +-e_k' T y
    T = sp.csr_matrix((LinvT.reshape(-1), np.repeat(np.arange(n).reshape(nb, 2), 2, axis=0).reshape(-1),
                       np.arange(0, 2 * n + 1, 2)), shape=(n, n))
    Ct = (prob.C @ T).tocsr() if prob.m else sp.csr_matrix((0, n))
    Mt = sp.vstack((Ct, T, -T), format="csr")
    return LeastDistanceForm(LinvT, gt, Mt, np.concatenate((prob.u, prob.ub, -prob.lb)))


least_distance_form = _once(_least_distance_form)  # (once per problem)


def _dense_rows(prob, LinvT: np.ndarray) -> np.ndarray:
    """``least_distance_form(prob).Mt.toarray()``, bit for bit, without scipy.sparse (an entry sums <= 2 products)."""
    n, m = prob.n, prob.m
    nb = n // 2
    C = prob.C
    if getattr(C, "format", None) != "csr" or not C.has_canonical_format:  # (repeated entries: summed in this form)
        return _least_distance_form(prob).Mt.toarray()
    fb = np.repeat(np.arange(m) * nb, np.diff(C.indptr)) + C.indices // 2  # the (row, robot) pairs with an entry
    rb = fb[np.concatenate(([True], fb[1:] != fb[:-1]))] if fb.size else fb  # (sorted: canonical)
    v, k = C.toarray().reshape(-1, 2)[rb], rb % nb
    Md = np.zeros((m + 2 * n, n))
    Md[:m].reshape(-1, 2)[rb] = v[:, 0, None] * LinvT[k, 0, :] + v[:, 1, None] * LinvT[k, 1, :] + 0.0
    k = np.arange(nb)
    Md[m:m + n].reshape(nb, 2, nb, 2)[k, :, k, :] = LinvT + 0.0
    Md[m + n:].reshape(nb, 2, nb, 2)[k, :, k, :] = -LinvT + 0.0
    return Md


class ActiveSetParts(NamedTuple):
    """The answer of :func:`solve_active_set_parts` (on unverified groups an unverified iterate or zeros)."""

    x: np.ndarray  #: ``(n,)`` the scaled point
    z: np.ndarray  #: ``(m,)`` row multipliers ``>= 0``
    iterations: int  #: equality solves
    ok: np.ndarray  #: ``(K,)`` the groups whose part meets the KKT conditions of their own rows
    row_group: np.ndarray  #: ``(m,)`` every row's group


def solve_active_set(prob, x0, z0, max_iter: int = PDAS_ITER, compiled: bool = False,
                     one_change_iter: int | None = None):
    """``(x, z, iterations)`` at the verified optimum, or ``None`` (fall back)."""
    out = solve_active_set_parts(prob, x0, z0, None, max_iter, compiled=compiled, one_change_iter=one_change_iter)
    if out is None or not out.ok.all():
        return None
    return out.x, out.z, out.iterations


def solve_active_set_parts(prob, x0, z0, groups: np.ndarray | None, max_iter: int = PDAS_ITER,
                           compiled: bool = False, one_change_iter: int | None = None) -> ActiveSetParts | None:
    """The warm active set on a problem of independent groups, each verified (and then kept) on its own.

    ``x0``, ``z0``: the previous point and row multipliers; ``groups`` ``(N,)``: each robot's group ``0..K-1`` (None:
    one); ``compiled``: the dense path group by group by the numba kernel, where every group is of a dense size
    (a large problem of small groups too).  ``None`` where the method does not apply (no warm start,
    a block not positive definite, an odd size, ``groups`` not one label per robot or joined by a row).
    """
    n, m = prob.n, prob.m
    if n == 0 or n % 2 or z0 is None or x0 is None or z0.shape[0] != m or x0.shape[0] != n:
        return None
    one_change_iter = one_change_budget(one_change_iter)
    labels = _row_groups(prob, groups)
    if labels is None:
        return None
    K, rg, groups = labels
    dense, W0 = _dense(n, m), warm_working_set(prob, x0, z0)
    if compiled and getattr(prob.C, "format", None) == "csr" and (dense or _parts_dense(rg, K, m)):
        factor = dense_least_distance_form(prob, False)  # (the kernel's algebra is per part)
        if factor is None:
            return None
        LinvT, gt, _, b = factor
        out = _solve_compiled(prob, LinvT, gt, b, W0, groups, K, max_iter, one_change_iter, rg)
        if out is not None:
            return out
    form = dense_least_distance_form(prob) if dense else least_distance_form(prob)  # (the reference's rows)
    if form is None:
        return None
    LinvT, gt, M, b = form
    loop = _WorkingSetLoop(functools.partial(_equality_point, M, dense, gt, b), rg, K)
    W = W0
    for rule, budget in ((_pdas_rule, max_iter), (_one_change_rule, one_change_iter)):
        # the groups not yet verified start each rule from the warm start
        W = loop.run(np.where(loop.done[rg], W, W0), rule, budget, stop_inconsistent=rule is _pdas_rule)
        if loop.done.all():
            break
    return _answer(LinvT, np.zeros(n) if loop.y is None else loop.y, loop.lam, loop.used, loop.done, rg, m)


def _dense(n: int, m: int) -> bool:
    """Whether a problem of ``n`` variables and ``m`` rows takes dense algebra."""
    return n <= DENSE_MAX_VARS or n * (m + 2 * n) <= DENSE_MAX_CELLS


def _parts_dense(rg: np.ndarray, K: int, m: int) -> bool:
    """Whether every part (rows and bounds labelled ``rg``) is of a size that takes dense algebra."""
    rows = np.bincount(rg[:m], minlength=K)
    nv = np.bincount(rg[m:], minlength=K) // 2  # (each variable has two bounds)
    return bool(((nv <= DENSE_MAX_VARS) | (nv * (rows + 2 * nv) <= DENSE_MAX_CELLS)).all())


def _row_groups(prob, groups: np.ndarray | None) -> tuple[int, np.ndarray, np.ndarray] | None:
    """``(K, each row's group (its first entry's; 0 if empty), the robots' groups)``; None if not independent parts."""
    n, m = prob.n, prob.m
    if groups is None:
        return 1, np.zeros(m + 2 * n, dtype=np.intp), np.zeros(n // 2, np.int64)
    groups = np.asarray(groups, dtype=np.intp)
    if groups.shape != (n // 2,) or (groups.size and groups.min() < 0):
        return None  # not a labelling 0..K-1 of the robots (the compiled kernel indexes by it)
    C = prob.C.tocsr()
    nnz = C.indices.shape[0]
    first = C.indices[np.minimum(C.indptr[:-1], nnz - 1)] // 2 if nnz else np.zeros(m, dtype=np.intp)
    vg = np.repeat(groups, 2)
    rg = np.concatenate((np.where(np.diff(C.indptr) > 0, groups[first], 0), vg, vg))
    if not np.array_equal(vg[C.indices], np.repeat(rg[:m], np.diff(C.indptr))):
        return None  # a row joins two groups
    return int(groups.max(initial=-1)) + 1, rg, groups


def warm_working_set(prob, x0: np.ndarray, z0: np.ndarray) -> np.ndarray:
    """The warm working set ``(m + 2n,)`` bool: rows, upper bounds, lower bounds.

    Rows whose multiplier exceeds :data:`WARM_REL` of the largest (solvers leave ~1e-10 on slack rows); bounds it is at.
    """
    n, m = prob.n, prob.m
    W0 = np.zeros(m + 2 * n, dtype=bool)
    W0[:m] = z0 > WARM_REL * max(float(z0.max(initial=0.0)), WARM_FLOOR) if m else False
    W0[m:m + n] = x0 >= prob.ub - BOUND_TIGHT
    W0[m + n:] = x0 <= prob.lb + BOUND_TIGHT
    return W0


def one_change_budget(value: int | None) -> int:
    """The one-change rule's budget: ``value``, or :data:`ONE_CHANGE_ITER` (read when called) for None."""
    return ONE_CHANGE_ITER if value is None else int(value)


def _solve_compiled(prob, LinvT: np.ndarray, gt: np.ndarray, b: np.ndarray, W0: np.ndarray, groups: np.ndarray,
                    K: int, max_iter: int, one_change_iter: int, rg: np.ndarray) -> ActiveSetParts | None:
    """:func:`solve_active_set_parts` by the compiled kernel; None where ``C`` repeats an entry in a row."""
    n, m = prob.n, prob.m
    C = prob.C
    y, lam, done = np.zeros(n), np.zeros(m + 2 * n), np.zeros(K, dtype=bool)
    used = kernels("active_set").solve_parts(
        np.ascontiguousarray(C.indptr, np.int64), np.ascontiguousarray(C.indices, np.int64), c64(C.data), m, n,
        c64(LinvT), c64(gt), c64(b), np.ascontiguousarray(W0), np.ascontiguousarray(groups, np.int64), K, max_iter,
        one_change_iter, TOL, y, lam, done)
    return None if used < 0 else _answer(LinvT, y, lam, int(used), done, rg, m)


def _answer(LinvT: np.ndarray, y: np.ndarray, lam: np.ndarray, used: int, done: np.ndarray, rg: np.ndarray,
            m: int) -> ActiveSetParts:
    """The answer from the point ``y`` and the multipliers of every row and bound (zeros where none verified)."""
    if not done.any():
        return ActiveSetParts(np.zeros(y.shape[0]), np.zeros(m), used, done, rg[:m])
    x = np.einsum("nij,nj->ni", LinvT, y.reshape(-1, 2)).ravel()
    return ActiveSetParts(x, np.maximum(lam[:m], 0.0), used, done, rg[:m])


def _equality_point(M, dense: bool, gt: np.ndarray, b: np.ndarray, W: np.ndarray):
    """``(y, lam, r)`` with the rows ``W`` held as equalities, or None (singular); ``r = M y - b``."""
    idx = np.flatnonzero(W)
    k = idx.shape[0]
    lam = np.zeros(b.shape[0])
    if not k:
        return -gt, lam, (M @ -gt) - b
    Mw = M[idx]
    # (einsum's own loops: OpenBLAS's syrk, gemm and potrf sum in an order set by its thread count)
    S = np.einsum("ik,jk->ij", Mw, Mw) if dense else (Mw @ Mw.T).tocsc()
    rhs = -(Mw @ gt) - b[idx]
    delta = 1e-9 * max(float(S.diagonal().max()), 1e-300)
    if not dense and k <= SPARSE_DENSE_SCHUR_ROWS:  # sparse rows, a small Schur complement: factored dense
        S = S.toarray()
    if isinstance(S, np.ndarray):
        Sr = S + 0.0  # S + delta * I without the identity: off the diagonal S + 0.0, on it S + delta
        Sr.flat[:: k + 1] += delta
        solve = _splu(sp.csc_matrix(Sr))
    else:
        solve = _splu((S + delta * sp.identity(k, format="csc")).tocsc(), permc_spec="MMD_AT_PLUS_A")
    if solve is None:
        return None
    lw = _refine(solve, S, rhs)
    if not np.all(np.isfinite(lw)):
        return None
    y = -gt - Mw.T @ lw
    lam[idx] = lw
    return y, lam, (M @ y) - b


def _splu(A, **options):
    """A solver of ``A l = v`` from scipy's sparse LU of ``A``, or None where it is singular."""
    import scipy.sparse.linalg as spla  # (imported where asked: not by ``aasoatt --help``)

    try:
        return spla.splu(A, **options).solve
    except RuntimeError:
        return None


def _pdas_rule(W: np.ndarray, lam: np.ndarray, r: np.ndarray, prev: np.ndarray | None,
               rg: np.ndarray, todo: np.ndarray) -> np.ndarray:
    """The primal-dual active-set update: every row with ``lambda + r > 0`` (in the groups ``todo``)."""
    return np.where(todo[rg], (lam + r) > 0, W)


def _group_argmin(val: np.ndarray, rg: np.ndarray, K: int) -> np.ndarray:
    """Per group, the first index of its smallest finite value (``-1`` where it has none)."""
    if K == 1:
        k = int(np.argmin(val)) if val.shape[0] else 0
        return np.array([k if val.shape[0] and np.isfinite(val[k]) else -1])
    if not val.shape[0]:
        return np.full(K, -1)
    order = np.lexsort((val, rg))  # by group, then value, then index
    sg = rg[order]
    pos = np.minimum(np.searchsorted(sg, np.arange(K)), sg.shape[0] - 1)
    k = order[pos]
    return np.where((sg[pos] == np.arange(K)) & np.isfinite(val[k]), k, -1)


def _one_change_rule(W: np.ndarray, lam: np.ndarray, r: np.ndarray, prev: np.ndarray | None,
                     rg: np.ndarray, todo: np.ndarray) -> np.ndarray:
    """One change per group of ``todo``: add its most violated row while its multipliers are >= 0, else drop one.

    The row dropped is the first whose multiplier crosses zero from ``prev`` to these (Goldfarb-Idnani's ratio test),
    else the most negative.
    """
    K = todo.shape[0]
    Wn = W.copy()
    neg = lam < -TOL
    gneg = np.zeros(K, dtype=bool)
    gneg[rg[neg]] = True
    add = todo & ~gneg
    if add.any():
        k = _group_argmin(np.where(W | ~add[rg], np.inf, -r), rg, K)[add]
        k = k[k >= 0]
        Wn[k[r[k] > TOL]] = True  # nothing violated outside the working set: no change there
    drop = todo & gneg
    if drop.any():
        k = _group_argmin(np.where(drop[rg], lam, np.inf), rg, K)
        if prev is not None:
            crossed = neg & (prev > TOL) & drop[rg]
            if crossed.any():
                ratio = np.full(lam.shape[0], np.inf)
                ratio[crossed] = prev[crossed] / (prev[crossed] - lam[crossed])
                kc = _group_argmin(ratio, rg, K)
                k = np.where(kc >= 0, kc, k)
        k = k[drop]
        Wn[k[k >= 0]] = False
    return Wn


class _WorkingSetLoop:
    """Iterates a working-set rule group by group, keeping each group's part of the first point that verifies it."""

    def __init__(self, eq, rg: np.ndarray, K: int) -> None:
        self.eq, self.rg, self.K = eq, rg, K
        self.done = np.zeros(K, dtype=bool)
        self.y: np.ndarray | None = None
        self.lam: np.ndarray | None = None
        self.used = 0  # equality solves of every rule: the iterations reported
        self._first: tuple[bytes, object] | None = None  # the first working set and its point (each rule starts there)

    def _point(self, W: np.ndarray):
        """``eq(W)``; the first working set's point is solved once (the next rule starts from it again)."""
        key = W.tobytes()
        if self._first is not None and self._first[0] == key:
            return self._first[1]
        point = self.eq(W)
        self.used += 1
        if self._first is None:
            self._first = (key, point)
        return point

    def run(self, W: np.ndarray, rule, max_iter: int, stop_inconsistent: bool = False) -> np.ndarray:
        """Iterate ``rule`` from ``W`` (at most ``max_iter`` equality solves); ``stop_inconsistent``: as primal-dual."""
        rg, K = self.rg, self.K
        prev = None
        stopped = np.zeros(K, dtype=bool)
        for _ in range(max_iter):
            point = self._point(W)
            if point is None:  # singular working set: the groups verified so far stand
                break
            y, lam, r = point
            # KKT (stationarity by construction), written as what must hold: a NaN anywhere fails its group
            met = ~W | (np.abs(r) <= TOL)
            ok_row = (r <= TOL) & (lam >= -TOL) & met
            bad = np.zeros(K, dtype=bool)
            bad[rg[~ok_row]] = True
            new = ~bad & ~self.done
            if new.any():
                self._keep(new, y, lam)
            if stop_inconsistent:
                stopped[rg[~met]] = True
            todo = ~self.done & ~stopped
            if not todo.any():
                break
            Wn = rule(W, lam, r, prev, rg, todo)
            if np.array_equal(Wn, W):
                break
            W, prev = Wn, lam
        return W

    def _keep(self, new: np.ndarray, y: np.ndarray, lam: np.ndarray) -> None:
        if self.y is None or new.all():
            self.y, self.lam = y.copy(), lam.copy()
        else:
            rows = new[self.rg]
            vars_ = rows[rows.shape[0] - y.shape[0]:]  # the last rows are the variables' lower bounds
            self.y[vars_] = y[vars_]
            self.lam[rows] = lam[rows]
        self.done |= new


def _refine(solve, S, rhs, steps: int = 4):
    """Proximal iterative refinement: solves consistent (possibly singular) ``S l = rhs``."""
    lw = solve(rhs)
    for _ in range(steps):
        res = rhs - S @ lw
        lw = lw + solve(res)
    return lw
