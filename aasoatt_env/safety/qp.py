"""The safety QP and its solver registry.

Problem (eqn.finalAA-SOATT), in wheel accelerations ``du``::

    min  sum_i |A_i du_i - target_i|^2   s.t.  lo <= du <= hi,   G du <= rhs

It is solved in scaled coordinates ``x = du / s`` (``s`` the per-robot
acceleration bound, so the box is inside ``[-1, 1]``), with the objective divided
by its largest Hessian entry and every row normalised to unit norm.  The Hessian
is the constant 2x2 block diagonal ``A_i^T A_i = (rho/2)^2 [[1+k^2, 1-k^2],
[1-k^2, 1+k^2]]`` (heading independent), diagonal when ``l = b``; the proxsuite
back-end uses ``HessianType.Diagonal`` then.  :class:`QPProblem` holds that
canonical form ``min 0.5 x'Hx + g'x  s.t. lb <= x <= ub, C x <= u``.

Solvers (:data:`SOLVERS`, by name):

``proxsuite`` (default)
    Dense ``PrimalDualLDLT`` with native box constraints up to
    :data:`DENSE_MAX_SIZE` variables + rows, sparse ``SparseCholesky`` (box as
    rows) above.  With ``active_set=True`` and a warm start (``x0``, ``z0`` from
    the previous step) first a few iterations of the exact structured
    active-set method of :mod:`aasoatt_env.safety.active_set`, accepted only
    when the full KKT conditions hold.  Settings from SPEC section 4: tight ``eps_primal_inf`` /
    ``eps_dual_inf``, ``check_duality_gap`` with a tight gap; a bounded iteration
    budget (:data:`PROX_MAX_ITER`, :data:`PROX_MAX_ITER_IN`).  When proxsuite
    runs out of iterations or calls the problem infeasible, the exact ``ldp``
    solver below answers instead (up to :data:`~aasoatt_env.safety.ldp.MAX_VARS`
    variables; above, the other proxsuite back-end is tried).  The result's
    message says which solver answered.
``ldp``
    Exact least-distance programming by NNLS (Lawson-Hanson, scipy), KKT-verified
    (:mod:`aasoatt_env.safety.ldp`); needs only the core dependencies; dense, for
    teams of up to a few hundred robots in one QP.
``neural``
    The paper's projection neural network (eqn.22), explicit Euler with
    ``eps = dt``: ``iterations`` projected primal-dual updates per call,
    warm-started; never fails, only approximates the optimum.
``quadprog``, ``clarabel``, ``osqp``, ``daqp``, ``cvxopt``
    Optional, used when installed (``cvxopt`` is what Robotarium's barrier
    certificates call: ``cvxopt.solvers.qp``, interior point, default tolerances).

Infeasibility verdicts are never trusted: :func:`solve_qp` confirms them with a
phase-1 problem ``min |s|^2 s.t. box, C x - s <= u, s >= 0`` (always feasible;
bounds stay hard; one slack per row, so only the rows that cannot be met are
loosened).  If every least violation ``s*_k`` is ~0 the problem is re-solved
with rows loosened by a hair (status ``"solved"``), otherwise each row by its
own ``s*_k`` (status ``"relaxed"``, ``slack = max_k s*_k``).
"""

from __future__ import annotations

import contextlib
import functools
import importlib.util
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from aasoatt_env.errors import SolverError
from aasoatt_env.safety.active_set import solve_active_set
from aasoatt_env.safety.ldp import FEAS_TOL as LDP_FEAS_TOL
from aasoatt_env.safety.ldp import MAX_VARS as LDP_MAX_VARS
from aasoatt_env.safety.ldp import solve_ldp

__all__ = [
    "DENSE_MAX_SIZE",
    "QPProblem",
    "QPSolution",
    "SOLVERS",
    "available_solvers",
    "box_least_squares",
    "build_problem",
    "solve_qp",
]

DENSE_MAX_SIZE: int = 600
"""Largest ``n + m`` (variables + rows) solved with proxsuite's dense class.

Measured on packed layouts: dense PrimalDualLDLT 2.7 ms vs sparse 4.2 ms at
n + m = 340 (N = 39), but 16.5 ms vs 9.5 ms at n + m = 990 (N = 100)."""

PROX_MAX_ITER: int = 200
"""proxsuite's outer (``max_iter``) iteration budget before the exact fallback is asked."""
PROX_MAX_ITER_IN: int = 100
"""proxsuite's inner (``max_iter_in``) iteration budget per outer iteration.

The closed loops of the test suite and the radius-6 campaign need at most ~260
iterations in all; with proxsuite's default (1,500) a degenerate 60-robot
problem ran 1.45 million iterations (140 s) before giving up."""

_INF = 1e20
_FEAS_TOL = 1e-7


@dataclass
class QPProblem:
    """Canonical scaled QP ``min 0.5 x'Hx + g'x  s.t. lb <= x <= ub, C x <= u``."""

    H_blocks: np.ndarray
    """Hessian blocks ``(N, 2, 2)`` (block diagonal)."""
    g: np.ndarray
    """Linear term ``(n,)``."""
    C: sp.csr_matrix
    """Rows ``(m, n)``, unit norm."""
    u: np.ndarray
    """Row bounds ``(m,)``."""
    lb: np.ndarray
    """Lower bounds ``(n,)``."""
    ub: np.ndarray
    """Upper bounds ``(n,)``."""
    scale: np.ndarray
    """``du = scale * x``, ``(n,)``."""
    obj_scale: float
    """Objective divisor ``sigma``."""
    row_norm: np.ndarray
    """Row divisors ``nu`` (``eta_du = sigma * z / nu``), ``(m,)``."""
    diagonal: bool
    """True where every block of ``H`` is diagonal."""

    @property
    def n(self) -> int:
        """Number of variables."""
        return int(self.g.shape[0])

    @property
    def m(self) -> int:
        """Number of rows."""
        return int(self.u.shape[0])

    def H_dense(self) -> np.ndarray:
        """Dense Hessian ``(n, n)``."""
        n = self.n
        H = np.zeros((n, n))
        if n:
            k = np.arange(0, n, 2)
            H[k, k], H[k, k + 1] = self.H_blocks[:, 0, 0], self.H_blocks[:, 0, 1]
            H[k + 1, k], H[k + 1, k + 1] = self.H_blocks[:, 1, 0], self.H_blocks[:, 1, 1]
        return H

    def H_sparse(self) -> sp.csc_matrix:
        """Sparse block-diagonal Hessian (both entries of every block stored)."""
        n = self.n
        if not n:
            return sp.csc_matrix((0, 0))
        # column 2k holds rows 2k, 2k+1 of block k's first column; column 2k+1 its second
        data = self.H_blocks.transpose(0, 2, 1).reshape(-1)
        indices = (np.arange(0, n, 2)[:, None, None] + np.array([[0, 1], [0, 1]])).reshape(-1)
        return sp.csc_matrix((data, indices, np.arange(0, 2 * n + 1, 2)), shape=(n, n))

    def objective(self, x: np.ndarray) -> float:
        """Scaled objective ``0.5 x'Hx + g'x`` of ``x``."""
        xb = x.reshape(-1, 2)
        return float(0.5 * np.einsum("ni,nij,nj->", xb, self.H_blocks, xb) + self.g @ x)


@dataclass
class QPSolution:
    """Outcome of :func:`solve_qp` in scaled coordinates."""

    x: np.ndarray
    z: np.ndarray
    status: str
    slack: float
    iterations: int
    message: str
    solve_time: float
    fallback: bool = False
    """True when proxsuite gave no answer and the exact ``ldp`` solver did."""


@dataclass
class _Raw:
    x: np.ndarray | None
    z: np.ndarray | None
    ok: bool
    iterations: int
    message: str
    fallback: bool = False


def build_problem(
    A: np.ndarray,
    target: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    scale: np.ndarray,
    ri: np.ndarray,
    rj: np.ndarray,
    Gi: np.ndarray,
    Gj: np.ndarray,
    rhs: np.ndarray,
) -> QPProblem:
    """Assemble the scaled canonical problem.

    Parameters
    ----------
    A : numpy.ndarray
        Input matrices ``(N, 2, 2)``.
    target : numpy.ndarray
        Desired control-point accelerations ``(N, 2)``.
    lo, hi : numpy.ndarray
        Bounds on ``du``, ``(N, 2)``.
    scale : numpy.ndarray
        Positive per-robot scale of ``du`` ``(N,)``.
    ri, rj : numpy.ndarray
        Robots of each row ``(m,)``; ``rj = -1`` for obstacle rows.
    Gi, Gj : numpy.ndarray
        Row coefficients on ``du_i`` and ``du_j`` ``(m, 2)`` (``Gj`` ignored where ``rj < 0``).
    rhs : numpy.ndarray
        Row right-hand sides ``(m,)``.
    """
    n_rob = A.shape[0]
    s = scale[:, None]
    AtA = np.einsum("nki,nkj->nij", A, A)
    H = 2.0 * AtA * (s[:, :, None] * s[:, None, :])
    sigma = float(np.max(np.abs(H))) if n_rob else 1.0
    H = H / sigma
    g = (-2.0 * np.einsum("nki,nk->ni", A, target) * s / sigma).ravel()
    m = rhs.shape[0]
    Gi_s = Gi * s[ri]
    obs = rj < 0
    rjc = np.where(obs, 0, rj)
    Gj_s = np.where(obs[:, None], 0.0, Gj * s[rjc])
    nu = np.sqrt(np.sum(Gi_s**2, axis=1) + np.sum(Gj_s**2, axis=1))
    nu = np.where(nu > 1e-12, nu, 1.0)
    Gi_s /= nu[:, None]
    Gj_s /= nu[:, None]
    # CSR directly: 4 entries per robot-robot row, 2 per obstacle row
    cols = np.stack((2 * ri, 2 * ri + 1, 2 * rjc, 2 * rjc + 1), axis=1)
    data = np.concatenate((Gi_s, Gj_s), axis=1)
    keep = np.ones((m, 4), dtype=bool)
    keep[:, 2:] = ~obs[:, None]
    indptr = np.zeros(m + 1, dtype=np.int64)
    np.cumsum(np.where(obs, 2, 4), out=indptr[1:])
    C = sp.csr_matrix((data[keep], cols[keep], indptr), shape=(m, 2 * n_rob))
    diag = bool(np.all(np.abs(H[:, 0, 1]) <= 1e-12 * np.maximum(np.abs(H[:, 0, 0]), 1e-300)))
    return QPProblem(
        H_blocks=H,
        g=g,
        C=C,
        u=rhs / nu,
        lb=(lo / s).ravel(),
        ub=(hi / s).ravel(),
        scale=np.repeat(scale, 2),
        obj_scale=sigma,
        row_norm=nu,
        diagonal=diag,
    )


def box_least_squares(A: np.ndarray, target: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Per robot ``argmin |A_i du_i - target_i|^2  s.t.  lo_i <= du_i <= hi_i``, in closed form.

    The QP of a robot in no row: two variables, a box.  If the unconstrained
    minimiser ``A_i^{-1} target_i`` is inside the box it is the answer; otherwise
    the optimum lies on an edge, and on each of the four edges the objective is
    a convex parabola minimised by clipping; the best edge point wins.

    Parameters
    ----------
    A : numpy.ndarray
        Invertible input matrices ``(K, 2, 2)``.
    target : numpy.ndarray
        Desired control-point accelerations ``(K, 2)``.
    lo, hi : numpy.ndarray
        Bounds ``(K, 2)`` with ``lo <= hi``.

    Returns
    -------
    numpy.ndarray
        ``du`` ``(K, 2)``, inside the bounds.
    """
    a, b, c, d = A[:, 0, 0], A[:, 0, 1], A[:, 1, 0], A[:, 1, 1]
    t0, t1 = target[:, 0], target[:, 1]
    det = a * d - b * c
    x = np.stack(((d * t0 - b * t1) / det, (a * t1 - c * t0) / det), axis=1)
    out = (x < lo) | (x > hi)
    bad = np.flatnonzero(out[:, 0] | out[:, 1])
    if bad.size == 0:
        return x
    Ab, tb, lb, ub = A[bad], target[bad], lo[bad], hi[bad]
    H = np.einsum("kai,kaj->kij", Ab, Ab)
    g = -np.einsum("kai,ka->ki", Ab, tb)
    best = np.full(bad.size, np.inf)
    sol = np.empty((bad.size, 2))
    for fix in (0, 1):
        free = 1 - fix
        for bound in (lb, ub):
            c = np.empty((bad.size, 2))
            c[:, fix] = bound[:, fix]
            c[:, free] = np.clip(-(g[:, free] + H[:, free, fix] * c[:, fix]) / H[:, free, free],
                                 lb[:, free], ub[:, free])
            f = 0.5 * np.einsum("ki,kij,kj->k", c, H, c) + np.einsum("ki,ki->k", g, c)
            better = f < best
            best = np.where(better, f, best)
            sol[better] = c[better]
    x[bad] = sol
    return x


# ---------------------------------------------------------------- back-ends
def _prox_settings(settings: object, eps: float) -> None:
    settings.eps_abs = eps
    settings.eps_rel = 0.0
    settings.eps_primal_inf = 1e-14
    settings.eps_dual_inf = 1e-14
    settings.check_duality_gap = True
    settings.eps_duality_gap_abs = eps
    settings.eps_duality_gap_rel = 0.0
    settings.max_iter = PROX_MAX_ITER
    settings.max_iter_in = PROX_MAX_ITER_IN
    settings.verbose = False


def _proxsuite(prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> _Raw:
    import proxsuite

    px = proxsuite.proxqp
    eps = float(opts.get("eps", 1e-9))
    n, m = prob.n, prob.m
    dense = opts.get("dense")
    if dense is None:
        dense = n + m <= DENSE_MAX_SIZE
    if dense:
        d = px.dense
        htype = d.HessianType.Diagonal if prob.diagonal else d.HessianType.Dense
        qp = d.QP(n, 0, m, True, htype, d.DenseBackend.PrimalDualLDLT)
        _prox_settings(qp.settings, eps)
        Cd = prob.C.toarray() if m else np.zeros((0, n))
        qp.init(prob.H_dense(), prob.g, None, None, Cd, np.full(m, -_INF), prob.u, prob.lb, prob.ub)
    else:
        qp = px.sparse.QP(n, 0, m + n)
        _prox_settings(qp.settings, eps)
        qp.settings.sparse_backend = px.SparseBackend.SparseCholesky
        C = sp.vstack((prob.C, sp.identity(n, format="csr")), format="csc")
        qp.init(
            prob.H_sparse(), prob.g, None, None, C,
            np.concatenate((np.full(m, -_INF), prob.lb)), np.concatenate((prob.u, prob.ub)),
        )
    # Warm start is not used: with box constraints proxsuite 0.8 returned NaN
    # iterates from a warm start on circle-swap instances (and SPEC section 4
    # measured 0-30 % gain at best); the cold solve takes a handful of iterations.
    qp.solve()
    r = qp.results
    st = r.info.status
    ok = st == px.PROXQP_SOLVED
    x = np.array(r.x)
    if ok and not np.all(np.isfinite(x)):
        ok = False
    raw = _Raw(x, np.array(r.z)[:m], ok, int(r.info.iter), str(st).rsplit(".", 1)[-1])
    if ok or not opts.get("fallback", True):
        return raw
    # proxsuite ran out of iterations or called the problem infeasible: ask the exact
    # least-distance solver (finite active-set method, KKT-verified) before anything else
    if prob.n <= LDP_MAX_VARS:
        fb = _ldp(prob, x0, z0, opts)
        fb.iterations += raw.iterations
        fb.message = f"{raw.message} ({'dense' if dense else 'sparse'}), then {fb.message}"
        fb.fallback = True
        return fb
    if st == px.PROXQP_MAX_ITER_REACHED and opts.get("dense") is None:
        # too large for the dense fallback: the two back-ends stall on different problems
        other = _proxsuite(prob, x0, z0, {**opts, "dense": not dense, "fallback": False})
        other.iterations += raw.iterations
        other.message = f"{raw.message} ({'dense' if dense else 'sparse'}), then {other.message}"
        return other
    return raw


def _ldp(prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> _Raw:
    x, z, message = solve_ldp(prob, float(opts.get("ldp_feas_tol", LDP_FEAS_TOL)))
    return _Raw(x, z, x is not None, 0, message)


def _neural(prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> _Raw:
    iters = int(opts.get("iterations", 1))
    step = float(opts.get("step", 1.0))
    x = np.zeros(prob.n) if x0 is None else np.clip(x0, prob.lb, prob.ub)
    z = np.zeros(prob.m) if z0 is None else np.maximum(z0, 0.0)
    Hb = prob.H_blocks
    C, CT = prob.C, prob.C.T.tocsr()
    for _ in range(iters):
        grad = np.einsum("nij,nj->ni", Hb, x.reshape(-1, 2)).ravel() + prob.g + CT @ z
        x = np.clip(x - step * grad, prob.lb, prob.ub)
        z = np.maximum(0.0, z + step * (C @ x - prob.u))
    return _Raw(x, z, True, iters, f"neural ({iters} iterations)")


def _quadprog(prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> _Raw:
    import quadprog

    n, m = prob.n, prob.m
    Ct = np.vstack((-prob.C.toarray(), np.eye(n), -np.eye(n))).T if n else np.zeros((0, 0))
    b = np.concatenate((-prob.u, prob.lb, -prob.ub))
    try:
        x, _, _, it, lagr, _ = quadprog.solve_qp(prob.H_dense(), -prob.g, Ct, b, 0)
    except ValueError as exc:
        return _Raw(None, None, False, 0, str(exc))
    return _Raw(np.asarray(x), np.asarray(lagr)[:m], True, int(it[0]), "solved")


def _clarabel(prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> _Raw:
    import clarabel

    n, m = prob.n, prob.m
    Aq = sp.vstack((prob.C, sp.identity(n), -sp.identity(n)), format="csc")
    b = np.concatenate((prob.u, prob.ub, -prob.lb))
    s = clarabel.DefaultSettings()
    s.verbose = False
    s.tol_gap_abs = s.tol_gap_rel = s.tol_feas = 1e-10
    solver = clarabel.DefaultSolver(sp.triu(prob.H_sparse(), format="csc"), prob.g, Aq, b,
                                    [clarabel.NonnegativeConeT(m + 2 * n)], s)
    sol = solver.solve()
    ok = str(sol.status) in ("Solved", "AlmostSolved")
    return _Raw(np.asarray(sol.x), np.asarray(sol.z)[:m], ok, int(sol.iterations), str(sol.status))


@contextlib.contextmanager
def _c_stdout_silenced():
    """Silence C-level stdout (OSQP 1.x prints "Polishing not needed" even with verbose=False)."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # no real file descriptor (e.g. captured)
        yield
        return
    sys.stdout.flush()
    saved = os.dup(fd)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), fd)
            yield
    finally:
        os.dup2(saved, fd)
        os.close(saved)


def _osqp(prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> _Raw:
    import osqp

    n, m = prob.n, prob.m
    Aq = sp.vstack((prob.C, sp.identity(n)), format="csc")
    lower = np.concatenate((np.full(m, -np.inf), prob.lb))
    upper = np.concatenate((prob.u, prob.ub))
    solver = osqp.OSQP()
    eps = float(opts.get("eps", 1e-7))
    solver.setup(sp.triu(prob.H_sparse(), format="csc"), prob.g, Aq, lower, upper, verbose=False,
                 eps_abs=eps, eps_rel=eps, polishing=True, max_iter=20000)
    if x0 is not None:
        solver.warm_start(x=np.clip(x0, prob.lb, prob.ub))
    with _c_stdout_silenced():
        res = solver.solve()
    status = str(res.info.status)
    ok = status.lower().startswith("solved") and res.x is not None and np.all(np.isfinite(res.x))
    return _Raw(np.asarray(res.x), np.asarray(res.y)[:m] if res.y is not None else None,
                ok, int(res.info.iter), status)


def _daqp(prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> _Raw:
    import ctypes

    import daqp

    n, m = prob.n, prob.m
    A = np.vstack((np.eye(n), prob.C.toarray()))
    bu = np.concatenate((prob.ub, prob.u))
    bl = np.concatenate((prob.lb, np.full(m, -1e30)))
    sense = np.zeros(n + m, dtype=ctypes.c_int)
    x, _, exitflag, info = daqp.solve(prob.H_dense(), prob.g, A, bu, bl, sense)
    ok = exitflag >= 1
    lam = np.asarray(info.get("lam", np.zeros(n + m)))[n:]
    return _Raw(np.asarray(x), np.maximum(lam, 0.0), ok, int(info.get("iter", 0)), f"exitflag {exitflag}")


def _cvxopt(prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> _Raw:
    import cvxopt

    cvxopt.solvers.options["show_progress"] = False
    n, m = prob.n, prob.m
    H = prob.H_sparse().tocoo()
    P = cvxopt.spmatrix(H.data, H.row.astype(int), H.col.astype(int), (n, n))
    G = sp.vstack((prob.C, sp.identity(n), -sp.identity(n))).tocoo()
    Gm = cvxopt.spmatrix(G.data, G.row.astype(int), G.col.astype(int), G.shape)
    h = cvxopt.matrix(np.concatenate((prob.u, prob.ub, -prob.lb)))
    try:
        sol = cvxopt.solvers.qp(P, cvxopt.matrix(prob.g), Gm, h)
    except (ValueError, ArithmeticError) as exc:
        return _Raw(None, None, False, 0, str(exc))
    ok = sol["status"] == "optimal"
    return _Raw(np.asarray(sol["x"]).ravel(), np.asarray(sol["z"]).ravel()[:m], ok, int(sol["iterations"]),
                str(sol["status"]))


Backend = Callable[[QPProblem, "np.ndarray | None", "np.ndarray | None", dict], _Raw]

SOLVERS: dict[str, tuple[Backend, str]] = {
    "proxsuite": (_proxsuite, "proxsuite"),
    "neural": (_neural, ""),
    "ldp": (_ldp, ""),
    "quadprog": (_quadprog, "quadprog"),
    "clarabel": (_clarabel, "clarabel"),
    "osqp": (_osqp, "osqp"),
    "daqp": (_daqp, "daqp"),
    "cvxopt": (_cvxopt, "cvxopt"),
}
"""Solver registry: name -> (back-end, module it needs)."""


@functools.cache
def _installed(module: str) -> bool:
    return not module or importlib.util.find_spec(module) is not None


def available_solvers() -> list[str]:
    """Names of the registered solvers whose module is importable."""
    return [k for k, (_, mod) in SOLVERS.items() if _installed(mod)]


def get_solver(name: str) -> Backend:
    """Back-end ``name``, or :class:`SolverError` listing the available ones."""
    if name not in SOLVERS:
        raise SolverError(f"solver: got {name!r}, expected one of {available_solvers()}")
    fn, mod = SOLVERS[name]
    if not _installed(mod):
        raise SolverError(f"solver {name!r} is not installed (pip install {mod}); available: {available_solvers()}")
    return fn


def _phase1(prob: QPProblem, backend: Backend, opts: dict) -> tuple[np.ndarray, np.ndarray] | None:
    """Least row violations ``s* >= 0`` (one slack per row, bounds hard); None if even this fails.

    Solves ``min 0.5 |s|^2 (+ a 1e-8 regulariser on x)  s.t.  C x - s <= u, lb <= x <= ub``.
    A slack per row means one hopeless row (say a pair already inside ``d_s``) is
    loosened alone: every row that can still be met keeps (numerically) zero slack.
    """
    n, m = prob.n, prob.m
    reg = 1e-8
    pad = m % 2  # keep 2x2 Hessian blocks
    ns = m + pad
    Hb = np.concatenate((prob.H_blocks * reg, np.broadcast_to(np.eye(2), (ns // 2, 2, 2))))
    if pad:
        Hb = Hb.copy()
        Hb[-1, 1, 1] = 1.0  # the padding variable is fixed to 0 by its bounds
    blocks = [prob.C, -sp.identity(m, format="csr")]
    if pad:
        blocks.append(sp.csr_matrix((m, 1)))
    C = sp.hstack(blocks, format="csr")
    big = 1e6
    ub_s = np.full(ns, big)
    if pad:
        ub_s[-1] = 0.0
    p1 = QPProblem(
        H_blocks=Hb, g=np.zeros(n + ns), C=C, u=prob.u,
        lb=np.concatenate((prob.lb, np.zeros(ns))), ub=np.concatenate((prob.ub, ub_s)),
        scale=np.ones(n + ns), obj_scale=1.0, row_norm=np.ones(m), diagonal=prob.diagonal,
    )
    # the phase-1 point is only used through its recomputed violations: an exact solver's
    # point is accepted at a looser feasibility (the 1e-8 regulariser conditions it badly)
    raw = backend(p1, None, None, {**opts, "ldp_feas_tol": 1e-6})
    if not raw.ok or raw.x is None:
        if backend is not _clarabel and _installed("clarabel"):
            raw = _clarabel(p1, None, None, opts)
        if not raw.ok or raw.x is None:
            return None
    x = np.clip(raw.x[:n], prob.lb, prob.ub)
    viol = np.maximum(prob.C @ x - prob.u, 0.0)
    return x, viol


def solve_qp(
    prob: QPProblem,
    solver: str = "proxsuite",
    x0: np.ndarray | None = None,
    z0: np.ndarray | None = None,
    **opts: float,
) -> QPSolution:
    """Solve ``prob``; never raises on numerical trouble, never returns NaN.

    Returns status ``"solved"``, ``"relaxed"`` (rows loosened by ``slack``,
    in normalised row units) or ``"failed"`` (``x`` is then the clipped unconstrained optimum).

    Options (``**opts``): ``eps`` (proxsuite/OSQP tolerance), ``iterations`` and
    ``step`` (``neural``), ``dense`` (force a proxsuite back-end), ``active_set``
    (proxsuite: first the warm-started exact active-set method), ``prefer_exact``
    (proxsuite: first the warm active set, then ``ldp``, proxsuite only if both
    fail; what :class:`~aasoatt_env.safety.core.SafetyFilter` asks for in the
    steps after proxsuite needed the fallback).
    """
    backend = get_solver(solver)
    t0 = time.perf_counter()
    if prob.m == 0 and prob.diagonal and solver != "neural":
        x = np.clip(_unconstrained(prob), prob.lb, prob.ub)
        return QPSolution(x, np.zeros(0), "solved", 0.0, 0, "no rows", time.perf_counter() - t0)
    if solver == "neural":
        raw = backend(prob, x0, z0, opts)
        return QPSolution(raw.x, raw.z, "solved", 0.0, raw.iterations, raw.message, time.perf_counter() - t0)
    exact_first = solver == "proxsuite" and bool(opts.get("prefer_exact")) and prob.n <= LDP_MAX_VARS
    if solver == "proxsuite" and x0 is not None and z0 is not None and (opts.get("active_set") or exact_first):
        fast = solve_active_set(prob, x0, z0)
        if fast is not None:
            return QPSolution(fast[0], fast[1], "solved", 0.0, fast[2], "active set (warm, KKT verified)",
                              time.perf_counter() - t0)
    if exact_first:
        raw = _ldp(prob, x0, z0, opts)
        if raw.ok:
            return QPSolution(raw.x, _nonneg(raw.z, prob.m), "solved", 0.0, 0,
                              f"{raw.message}; proxsuite skipped (prefer_exact)", time.perf_counter() - t0)
    raw = backend(prob, x0, z0, opts)
    if raw.ok:
        return QPSolution(raw.x, _nonneg(raw.z, prob.m), "solved", 0.0, raw.iterations, raw.message,
                          time.perf_counter() - t0, raw.fallback)
    first = raw.message
    p1 = _phase1(prob, backend, opts)
    if p1 is None:
        x = np.clip(_unconstrained(prob), prob.lb, prob.ub)
        return QPSolution(x, np.zeros(prob.m), "failed", 0.0, raw.iterations,
                          f"{solver}: {first}; phase-1 failed too", time.perf_counter() - t0)
    x1, viol = p1
    tstar = float(np.max(viol, initial=0.0))
    relaxed = tstar > _FEAS_TOL
    loosen = viol * (1.0 + 1e-6) + _FEAS_TOL
    p2 = QPProblem(prob.H_blocks, prob.g, prob.C, prob.u + loosen, prob.lb, prob.ub, prob.scale,
                   prob.obj_scale, prob.row_norm, prob.diagonal)
    raw2 = backend(p2, x1, None, opts)
    status = "relaxed" if relaxed else "solved"
    msg = f"{solver}: {first}; phase-1 largest row violation {tstar:.3g} ({int(np.sum(viol > _FEAS_TOL))} rows)"
    if raw2.ok:
        return QPSolution(raw2.x, _nonneg(raw2.z, prob.m), status, tstar if relaxed else 0.0,
                          raw.iterations + raw2.iterations, msg, time.perf_counter() - t0,
                          raw.fallback or raw2.fallback)
    return QPSolution(x1, np.zeros(prob.m), "relaxed", tstar, raw.iterations + raw2.iterations,
                      msg + "; phase-2 failed, returning the phase-1 point", time.perf_counter() - t0)


def _nonneg(z: np.ndarray | None, m: int) -> np.ndarray:
    if z is None or z.shape[0] != m or not np.all(np.isfinite(z)):
        return np.zeros(m)
    return np.maximum(z, 0.0)


def _unconstrained(prob: QPProblem) -> np.ndarray:
    gb = prob.g.reshape(-1, 2)
    return -np.linalg.solve(prob.H_blocks, gb[..., None])[..., 0].ravel()

