"""QP back-ends of the safety filter and their registry (:data:`SOLVERS`).

A back-end maps a :class:`~aasoatt_env.safety.problem.QPProblem`, a warm start and options to a :class:`RawAnswer`
within an iteration budget (never a time limit), never falling back by itself (:mod:`.policy` decides).  ``proxsuite``
(default), ``ldp`` (exact NNLS, core dependencies only), ``neural`` (eqn.22, approximate); ``daqp``, ``clarabel``,
``osqp``, ``quadprog``, ``cvxopt`` where installed.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import importlib.util
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from aasoatt_env.errors import SolverError
from aasoatt_env.safety.problem import QPProblem
from aasoatt_env.safety.solvers.active_set import dense_least_distance_form, solve_active_set, warm_working_set

__all__ = ["DENSE_MAX_SIZE", "ITER_LIMIT", "LDP_MAX_VARS", "SOLVERS", "Backend", "RawAnswer", "available_solvers",
           "get_solver"]

DENSE_MAX_SIZE: int = 600  #: largest ``n + m`` solved with proxsuite's dense class (faster on small problems)
LDP_MAX_VARS: int = 500  #: ``ldp``'s largest problem (its NNLS matrix is dense, ``(n + 1) x (m + 2n)``)
LDP_FEAS_TOL: float = 1e-9  #: ``ldp``'s largest violation of a normalised row or bound in an unpolished point
#: iteration budgets of the iterative back-ends: the worst case of a call is a property of its size
ITER_LIMIT: dict[str, int] = {"proxsuite": 200, "proxsuite_inner": 100, "daqp": 2000, "osqp": 20000, "clarabel": 200}
_INF = 1e20


@dataclass
class RawAnswer:
    """What a back-end returns: a point and row multipliers in scaled coordinates, or no answer."""

    x: np.ndarray | None
    z: np.ndarray | None
    ok: bool  #: ``x`` is the back-end's answer to the problem as posed
    iterations: int
    message: str
    infeasible: bool = False  #: rows proved inconsistent by an exact method (``ldp``'s NNLS, DAQP's exitflag -1)


def _proxsuite(prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> RawAnswer:
    import proxsuite

    px = proxsuite.proxqp
    n, m = prob.n, prob.m
    dense = n + m <= DENSE_MAX_SIZE
    if dense:
        d = px.dense
        htype = d.HessianType.Diagonal if prob.diagonal else d.HessianType.Dense
        qp = d.QP(n, 0, m, True, htype, d.DenseBackend.PrimalDualLDLT)
    else:
        qp = px.sparse.QP(n, 0, m + n)
        qp.settings.sparse_backend = px.SparseBackend.SparseCholesky
    s, eps = qp.settings, float(opts.get("eps", 1e-9))
    s.eps_abs, s.eps_rel, s.eps_primal_inf, s.eps_dual_inf = eps, 0.0, 1e-14, 1e-14
    s.check_duality_gap, s.eps_duality_gap_abs, s.eps_duality_gap_rel = True, eps, 0.0
    s.max_iter, s.max_iter_in, s.verbose = ITER_LIMIT["proxsuite"], ITER_LIMIT["proxsuite_inner"], False
    if dense:
        Cd = prob.C.toarray() if m else np.zeros((0, n))
        qp.init(prob.H_dense(), prob.g, None, None, Cd, np.full(m, -_INF), prob.u, prob.lb, prob.ub)
    else:
        C = sp.vstack((prob.C, sp.identity(n, format="csr")), format="csc")
        qp.init(prob.H_sparse(), prob.g, None, None, C, np.concatenate((np.full(m, -_INF), prob.lb)),
                np.concatenate((prob.u, prob.ub)))
    qp.solve()  # (cold: its warm start returned NaN iterates with box constraints on circle-swap instances)
    r = qp.results
    x = np.array(r.x)
    ok = r.info.status == px.PROXQP_SOLVED and bool(np.all(np.isfinite(x)))
    message = f"proxsuite {str(r.info.status).rsplit('.', 1)[-1]} ({'dense' if dense else 'sparse'})"
    return RawAnswer(x, np.array(r.z)[:m], ok, int(r.info.iter), message)


def _ldp(prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> RawAnswer:
    """Exact least-distance programming in ``w = y + L^{-1} g``: one finitely terminating NNLS (Lawson and Hanson).

    The point is polished by the warm active set, or returned unpolished where feasible to ``ldp_feas_tol``.
    """
    n, m = prob.n, prob.m
    if n == 0 or n % 2:
        return RawAnswer(None, None, False, 0, "ldp: needs 2x2 blocks")
    if n > LDP_MAX_VARS:
        return RawAnswer(None, None, False, 0, f"ldp: {n} variables > MAX_VARS = {LDP_MAX_VARS}")
    form = dense_least_distance_form(prob)
    if form is None:
        return RawAnswer(None, None, False, 0, "ldp: Hessian block not positive definite")
    gt, Mt, b = form.gt, form.Mt, form.b
    finite = np.abs(b) < 1e19  # rows or bounds at +-inf are dropped
    if not np.all(finite):
        Mt, b = Mt[finite], b[finite]
    hb = b + Mt @ gt
    E = -np.vstack((Mt.T, hb[None, :]))
    norms = np.linalg.norm(E, axis=0)
    norms = np.where(norms > 0.0, norms, 1.0)
    f = np.zeros(n + 1)
    f[-1] = 1.0
    from scipy.optimize import nnls  # (scipy.optimize imported where asked: not by ``aasoatt --help``)

    try:
        us, _ = nnls(E / norms, f, maxiter=10 * E.shape[1])
    except RuntimeError as exc:  # iteration limit
        return RawAnswer(None, None, False, 0, f"ldp: {exc}")
    u = us / norms
    r = E @ u - f
    if not np.all(np.isfinite(r)) or -r[-1] <= 1e-14:
        return RawAnswer(None, None, False, 0, "ldp: rows inconsistent (NNLS residual zero)", infeasible=True)
    lam = np.zeros(finite.shape[0])
    lam[finite] = u / (-r[-1])
    x, z = form.to_x(-r[:n] / r[-1] - gt), lam[:m]
    polished = solve_active_set(prob, x, z)
    if polished is not None:
        return RawAnswer(polished[0], polished[1], True, 0, "ldp (KKT verified)")
    x = np.clip(x, prob.lb, prob.ub)
    viol = float(np.max(prob.C @ x - prob.u, initial=0.0))
    if viol > float(opts.get("ldp_feas_tol", LDP_FEAS_TOL)) or not np.all(np.isfinite(x)):
        return RawAnswer(None, None, False, 0, f"ldp: point violates a row by {viol:.2g}")
    return RawAnswer(x, np.maximum(z, 0.0), True, 0, "ldp (feasible, KKT polish did not converge)")


def _neural(prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> RawAnswer:
    iters, step = int(opts.get("iterations", 1)), float(opts.get("step", 1.0))
    x = np.zeros(prob.n) if x0 is None else np.clip(x0, prob.lb, prob.ub)
    z = np.zeros(prob.m) if z0 is None else np.maximum(z0, 0.0)
    C, CT = prob.C, prob.C.T.tocsr()
    for _ in range(iters):
        grad = np.einsum("nij,nj->ni", prob.H_blocks, x.reshape(-1, 2)).ravel() + prob.g + CT @ z
        x = np.clip(x - step * grad, prob.lb, prob.ub)
        z = np.maximum(0.0, z + step * (C @ x - prob.u))
    return RawAnswer(x, z, True, iters, f"neural ({iters} iterations)")


def _daqp(prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> RawAnswer:
    import daqp

    n, m = prob.n, prob.m
    # simple_bounds: the box as DAQP's simple bounds (faster); else as rows
    A = prob.C.toarray() if opts.get("simple_bounds") else np.vstack((np.eye(n), prob.C.toarray()))
    warm = {}
    if opts.get("warm_start") and x0 is not None and z0 is not None and x0.shape == (n,) and z0.shape == (m,):
        # its dual start: the warm working set (signs: upper bounds and rows +, lower bounds -; bounds first)
        W = warm_working_set(prob, x0, z0)
        warm["dual_start"] = np.concatenate((W[m:m + n].astype(float) - W[m + n:], W[:m].astype(float)))
    x, _, flag, info = daqp.solve(prob.H_dense(), prob.g, A, np.concatenate((prob.ub, prob.u)),
                                  np.concatenate((prob.lb, np.full(m, -1e30))), np.zeros(n + m, dtype=ctypes.c_int),
                                  iter_limit=ITER_LIMIT["daqp"], **warm)
    lam = np.maximum(np.asarray(info.get("lam", np.zeros(n + m)))[n:], 0.0)  # (bounds first, then the rows)
    return RawAnswer(np.asarray(x), lam, flag >= 1, int(info.get("iterations", 0)), f"daqp exitflag {flag}",
                     infeasible=flag == -1)


def _daqp_least_violation(prob: QPProblem, reg: float, opts: dict) -> RawAnswer:
    """Phase 1 (:func:`~.policy._phase1`) by DAQP's soft rows (weight ``1 / (rho a' H^-1 a) = 1`` here), no slacks."""
    import daqp

    n, m = prob.n, prob.m
    sense = np.zeros(n + m, dtype=ctypes.c_int)
    sense[n:] = 8  # DAQP's SOFT flag
    x, _, flag, info = daqp.solve(np.eye(n) * reg, np.zeros(n), prob.C.toarray(), np.concatenate((prob.ub, prob.u)),
                                  np.concatenate((prob.lb, np.full(m, -1e30))), sense, iter_limit=ITER_LIMIT["daqp"],
                                  rho_soft=reg)
    return RawAnswer(np.asarray(x), None, flag >= 1, int(info.get("iterations", 0)), f"daqp exitflag {flag}")


def _clarabel(prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> RawAnswer:
    import clarabel

    n, m = prob.n, prob.m
    s = clarabel.DefaultSettings()
    s.verbose, s.max_iter = False, ITER_LIMIT["clarabel"]
    s.tol_gap_abs = s.tol_gap_rel = s.tol_feas = 1e-10
    G = sp.vstack((prob.C, sp.identity(n), -sp.identity(n)), format="csc")
    h = np.concatenate((prob.u, prob.ub, -prob.lb))
    sol = clarabel.DefaultSolver(sp.triu(prob.H_sparse(), format="csc"), prob.g, G, h,
                                 [clarabel.NonnegativeConeT(m + 2 * n)], s).solve()
    ok = str(sol.status) in ("Solved", "AlmostSolved")
    return RawAnswer(np.asarray(sol.x), np.asarray(sol.z)[:m], ok, int(sol.iterations), f"clarabel {sol.status}")


def _quadprog(prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> RawAnswer:
    import quadprog

    n, m = prob.n, prob.m
    Ct, b = np.vstack((-prob.C.toarray(), np.eye(n), -np.eye(n))).T, np.concatenate((-prob.u, prob.lb, -prob.ub))
    try:
        x, _, _, it, lagr, _ = quadprog.solve_qp(prob.H_dense(), -prob.g, Ct, b, 0)
    except ValueError as exc:
        return RawAnswer(None, None, False, 0, f"quadprog: {exc}")
    return RawAnswer(np.asarray(x), np.asarray(lagr)[:m], True, int(it[0]), "quadprog solved")


@contextlib.contextmanager
def _c_stdout_silenced():
    """Silence C-level stdout (OSQP prints "Polishing not needed" even with ``verbose=False``)."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # no real file descriptor (captured)
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


def _osqp(prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> RawAnswer:
    import osqp

    n, m = prob.n, prob.m
    solver = osqp.OSQP()
    eps = float(opts.get("eps", 1e-7))
    solver.setup(sp.triu(prob.H_sparse(), format="csc"), prob.g, sp.vstack((prob.C, sp.identity(n)), format="csc"),
                 np.concatenate((np.full(m, -np.inf), prob.lb)), np.concatenate((prob.u, prob.ub)), verbose=False,
                 eps_abs=eps, eps_rel=eps, polishing=True, max_iter=ITER_LIMIT["osqp"])
    if x0 is not None:
        solver.warm_start(x=np.clip(x0, prob.lb, prob.ub))
    with _c_stdout_silenced():
        res = solver.solve()
    status = str(res.info.status)
    ok = status.lower().startswith("solved") and res.x is not None and bool(np.all(np.isfinite(res.x)))
    return RawAnswer(np.asarray(res.x), None if res.y is None else np.asarray(res.y)[:m], ok, int(res.info.iter),
                     f"osqp {status}")


def _cvxopt(prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> RawAnswer:
    import cvxopt

    cvxopt.solvers.options["show_progress"] = False
    n, m = prob.n, prob.m
    H = prob.H_sparse().tocoo()
    G = sp.vstack((prob.C, sp.identity(n), -sp.identity(n))).tocoo()
    try:
        sol = cvxopt.solvers.qp(cvxopt.spmatrix(H.data, H.row.astype(int), H.col.astype(int), (n, n)),
                                cvxopt.matrix(prob.g),
                                cvxopt.spmatrix(G.data, G.row.astype(int), G.col.astype(int), G.shape),
                                cvxopt.matrix(np.concatenate((prob.u, prob.ub, -prob.lb))))
    except (ValueError, ArithmeticError) as exc:
        return RawAnswer(None, None, False, 0, f"cvxopt: {exc}")
    return RawAnswer(np.asarray(sol["x"]).ravel(), np.asarray(sol["z"]).ravel()[:m], sol["status"] == "optimal",
                     int(sol["iterations"]), f"cvxopt {sol['status']}")


@dataclass(frozen=True)
class Backend:
    """A registered QP back-end and what the solver policy needs to know about it."""

    solve: Callable[[QPProblem, np.ndarray | None, np.ndarray | None, dict], RawAnswer]  #: ``(problem, x0, z0, opts)``
    module: str = ""  #: the module it imports (empty: core dependencies only)
    exact: bool = True  #: answers the QP's optimum to its tolerance (False: ``neural``, passed on unverified)
    #: it checks its own answers (``ldp``); others' are polished and verified by the warm active set (which also
    #: makes their last bits a function of the problem)
    verified: bool = False
    deterministic: bool = True  #: its last bits are a function of the problem (proxsuite's: of its memory too)
    may_stall: bool = False  #: it can run out of iterations (an augmented Lagrangian): the exact solvers go first
    route_options: tuple[tuple[str, object], ...] = ()  #: options when the route asks it (not as the configured one)
    #: its own phase-1 solve ``(problem, reg, options) -> RawAnswer`` (None: phase 1's problem with a slack per row)
    least_violation: Callable[[QPProblem, float, dict], RawAnswer] | None = None

    def __call__(self, prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> RawAnswer:
        """Run the back-end."""
        return self.solve(prob, x0, z0, opts)


SOLVERS: dict[str, Backend] = {
    "proxsuite": Backend(_proxsuite, "proxsuite", deterministic=False, may_stall=True),
    "neural": Backend(_neural, exact=False),
    "ldp": Backend(_ldp, verified=True),
    "quadprog": Backend(_quadprog, "quadprog"),
    "clarabel": Backend(_clarabel, "clarabel"),
    "osqp": Backend(_osqp, "osqp"),
    "daqp": Backend(_daqp, "daqp", route_options=(("simple_bounds", True), ("warm_start", True)),
                    least_violation=_daqp_least_violation),
    "cvxopt": Backend(_cvxopt, "cvxopt"),
}
"""Solver registry: name -> :class:`Backend` (adding one: a function and a line here)."""


@functools.cache
def _installed(module: str) -> bool:
    return not module or importlib.util.find_spec(module) is not None


def available_solvers() -> list[str]:
    """Names of the registered solvers whose module is importable."""
    return [k for k, b in SOLVERS.items() if _installed(b.module)]


def get_solver(name: str) -> Backend:
    """Back-end ``name``, or :class:`SolverError` listing the available ones."""
    if not isinstance(name, str) or name not in SOLVERS:
        raise SolverError(f"solver: got {name!r}, expected one of {available_solvers()}")
    backend = SOLVERS[name]
    if not _installed(backend.module):
        raise SolverError(f"solver {name!r} is not installed (pip install {backend.module}); "
                          f"available: {available_solvers()}")
    return backend
