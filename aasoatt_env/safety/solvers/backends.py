"""Back-ends of the safety QP and their registry (:data:`SOLVERS`, by name).

Each back-end takes a :class:`~aasoatt_env.safety.problem.QPProblem`, an optional
warm start and options, and returns a raw answer (:class:`RawAnswer`); it never
falls back to anything by itself.  What to do with an answer, or with no answer
(fallbacks, confirming infeasibility verdicts, relaxing rows, switching paths
after a stall), is decided in one place: :mod:`aasoatt_env.safety.solvers.policy`.
Each registry entry (:class:`Backend`) says what the policy needs to know: the
module it imports, whether its answer is exact, and which back-ends answer when
it gives none.

``proxsuite`` (default)
    Dense ``PrimalDualLDLT`` with native box constraints up to
    :data:`DENSE_MAX_SIZE` variables + rows, sparse ``SparseCholesky`` (box as
    rows) above.  Settings from ``docs/technical_brief.md`` section 4: tight ``eps_primal_inf`` /
    ``eps_dual_inf``, ``check_duality_gap`` with a tight gap; a bounded iteration
    budget (:data:`PROX_MAX_ITER`, :data:`PROX_MAX_ITER_IN`).  Option
    ``alternate=True`` uses the dense class for a problem the sparse class would take (the two
    stall on different problems); for a problem small enough for the dense class it gives no
    answer, because the sparse class did not return on some small infeasible problems with huge
    linear terms (an adversary's nominal of 1e6).
``ldp``
    Exact least-distance programming by NNLS (Lawson-Hanson, scipy), KKT-verified
    (:mod:`aasoatt_env.safety.solvers.ldp`); needs only the core dependencies; dense, for
    teams of up to a few hundred robots in one QP.
``neural``
    The paper's projection neural network (eqn.22), explicit Euler with
    ``eps = dt``: ``iterations`` projected primal-dual updates per call,
    warm-started; never fails, only approximates the optimum.
``quadprog``, ``clarabel``, ``osqp``, ``daqp``, ``cvxopt``
    Optional, used when installed (``cvxopt`` is what Robotarium's barrier
    certificates call: ``cvxopt.solvers.qp``, interior point, default tolerances).
    ``daqp`` takes option ``simple_bounds=True``: the box as DAQP's simple bounds
    (2-2.5x faster on the negotiation groups' problems, answers equal to rounding);
    without it the box stays rows, as before, so ``solver="daqp"`` runs keep their
    numbers.  The policy passes it when it asks DAQP itself (:attr:`Backend.helper_options`).
"""

from __future__ import annotations

import contextlib
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
from aasoatt_env.safety.solvers.ldp import FEAS_TOL as LDP_FEAS_TOL
from aasoatt_env.safety.solvers.ldp import solve_ldp

__all__ = [
    "DENSE_MAX_SIZE",
    "PROX_MAX_ITER",
    "PROX_MAX_ITER_IN",
    "SOLVERS",
    "Backend",
    "RawAnswer",
    "available_solvers",
    "get_solver",
]

DENSE_MAX_SIZE: int = 600
"""Largest ``n + m`` (variables + rows) solved with proxsuite's dense class.

The dense class is the faster one on small problems and the sparse one on large
ones; the cross-over was chosen by timing both on packed layouts
(``benchmarks/bench_filter.py``)."""

PROX_MAX_ITER: int = 200
"""proxsuite's outer (``max_iter``) iteration budget before the exact fallback is asked."""
PROX_MAX_ITER_IN: int = 100
"""proxsuite's inner (``max_iter_in``) iteration budget per outer iteration.

The closed loops of the test suite and the radius-6 campaign need at most ~260
iterations in all; with proxsuite's default (1,500) a degenerate 60-robot
problem ran 1.45 million iterations (140 s) before giving up."""

_INF = 1e20


@dataclass
class RawAnswer:
    """What a back-end returns: a point and multipliers in scaled coordinates, or no answer."""

    x: np.ndarray | None
    z: np.ndarray | None
    ok: bool
    """True when ``x`` is the back-end's answer to the problem as posed."""
    iterations: int
    message: str
    stalled: bool = False
    """True when the back-end ran out of its iteration budget (no verdict on the problem)."""
    infeasible: bool = False
    """True when the back-end reports the rows inconsistent by an exact method (``ldp``'s NNLS residual, DAQP's
    exitflag -1, to its tolerances): the policy then skips its other back-ends and goes to phase 1, which
    finds the least violations (all ~0 for a feasible problem: then the rows are loosened by a hair)."""



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


def _proxsuite(prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> RawAnswer:
    import proxsuite

    px = proxsuite.proxqp
    eps = float(opts.get("eps", 1e-9))
    n, m = prob.n, prob.m
    dense = n + m <= DENSE_MAX_SIZE
    if opts.get("alternate"):
        if dense:  # not dense -> sparse: on a small infeasible problem with a huge linear term
            # (nominal 1e6) the sparse class did not return (proxsuite 0.8.0, 40 s and more)
            return RawAnswer(np.zeros(n), np.zeros(m), False, 0, "alternate class skipped (small problem)")
        dense = True
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
    # iterates from a warm start on circle-swap instances (and ``docs/technical_brief.md`` section 4
    # measured 0-30 % gain at best); the cold solve takes a handful of iterations.
    qp.solve()
    r = qp.results
    st = r.info.status
    ok = st == px.PROXQP_SOLVED
    x = np.array(r.x)
    if ok and not np.all(np.isfinite(x)):
        ok = False
    message = f"{str(st).rsplit('.', 1)[-1]} ({'dense' if dense else 'sparse'})"
    return RawAnswer(x, np.array(r.z)[:m], ok, int(r.info.iter), message, stalled=st == px.PROXQP_MAX_ITER_REACHED)


def _ldp(prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> RawAnswer:
    x, z, message = solve_ldp(prob, float(opts.get("ldp_feas_tol", LDP_FEAS_TOL)))
    return RawAnswer(x, z, x is not None, 0, message, infeasible="inconsistent" in message)


def _neural(prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> RawAnswer:
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
    return RawAnswer(x, z, True, iters, f"neural ({iters} iterations)")


def _quadprog(prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> RawAnswer:
    import quadprog

    n, m = prob.n, prob.m
    Ct = np.vstack((-prob.C.toarray(), np.eye(n), -np.eye(n))).T if n else np.zeros((0, 0))
    b = np.concatenate((-prob.u, prob.lb, -prob.ub))
    try:
        x, _, _, it, lagr, _ = quadprog.solve_qp(prob.H_dense(), -prob.g, Ct, b, 0)
    except ValueError as exc:
        return RawAnswer(None, None, False, 0, str(exc))
    return RawAnswer(np.asarray(x), np.asarray(lagr)[:m], True, int(it[0]), "solved")


def _clarabel(prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> RawAnswer:
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
    return RawAnswer(np.asarray(sol.x), np.asarray(sol.z)[:m], ok, int(sol.iterations), str(sol.status))


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


def _osqp(prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> RawAnswer:
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
    return RawAnswer(np.asarray(res.x), np.asarray(res.y)[:m] if res.y is not None else None,
                ok, int(res.info.iter), status)


def _daqp(prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> RawAnswer:
    import ctypes

    import daqp

    n, m = prob.n, prob.m
    # simple_bounds (module docstring): the first n of the n + m bounds are then DAQP's simple bounds
    A = prob.C.toarray() if opts.get("simple_bounds") else np.vstack((np.eye(n), prob.C.toarray()))
    bu = np.concatenate((prob.ub, prob.u))
    bl = np.concatenate((prob.lb, np.full(m, -1e30)))
    sense = np.zeros(n + m, dtype=ctypes.c_int)
    x, _, exitflag, info = daqp.solve(prob.H_dense(), prob.g, A, bu, bl, sense)
    ok = exitflag >= 1
    lam = np.maximum(np.asarray(info.get("lam", np.zeros(n + m)))[n:], 0.0)  # (the bounds' first, then the rows')
    return RawAnswer(np.asarray(x), lam, ok, int(info.get("iter", 0)), f"exitflag {exitflag}",
                     infeasible=exitflag == -1)


def _cvxopt(prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> RawAnswer:
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
        return RawAnswer(None, None, False, 0, str(exc))
    ok = sol["status"] == "optimal"
    return RawAnswer(np.asarray(sol["x"]).ravel(), np.asarray(sol["z"]).ravel()[:m], ok, int(sol["iterations"]),
                str(sol["status"]))


BackendFn = Callable[[QPProblem, "np.ndarray | None", "np.ndarray | None", dict], RawAnswer]


@dataclass(frozen=True)
class Backend:
    """A registered QP back-end and what the solver policy needs to know about it."""

    solve: BackendFn
    """``solve(problem, x0, z0, options) -> RawAnswer``."""
    module: str = ""
    """Module it imports (empty: core dependencies only)."""
    exact: bool = True
    """True when an answer is the QP's optimum (to the back-end's tolerance); False for
    approximations (``neural``), whose answers are passed through unverified."""
    fallbacks: tuple[tuple[str, bool, dict], ...] = ()
    """``(back-end, only_after_a_stall, options)`` tried in order when this one gives no answer."""
    may_stall: bool = False
    """True when the back-end can run out of iterations on these problems (then the
    policy takes the exact path for a while, see :class:`~aasoatt_env.safety.solvers.policy.SolverPolicy`)."""
    verified: bool = False
    """True when the back-end checks its own answers (``ldp``: KKT-verified, or feasible to 1e-9): the
    policy's exact path takes them as they are; another back-end's answer there is taken only once the
    warm active set verifies it."""
    helper_options: tuple[tuple[str, object], ...] = ()
    """Options the policy adds when it asks this back-end itself (its exact path, phase-1 problems), not as
    the configured solver."""

    def __call__(self, prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, opts: dict) -> RawAnswer:
        """Run the back-end."""
        return self.solve(prob, x0, z0, opts)


SOLVERS: dict[str, Backend] = {
    "proxsuite": Backend(
        _proxsuite, "proxsuite", may_stall=True,
        fallbacks=(("ldp", False, {}), ("proxsuite", True, {"alternate": True})),
    ),
    "neural": Backend(_neural, exact=False),
    "ldp": Backend(_ldp, verified=True),
    "quadprog": Backend(_quadprog, "quadprog"),
    "clarabel": Backend(_clarabel, "clarabel"),
    "osqp": Backend(_osqp, "osqp"),
    "daqp": Backend(_daqp, "daqp", helper_options=(("simple_bounds", True),)),
    "cvxopt": Backend(_cvxopt, "cvxopt"),
}
"""Solver registry: name -> :class:`Backend`.  Adding a solver is one function and one line here."""


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
        raise SolverError(
            f"solver {name!r} is not installed (pip install {backend.module}); available: {available_solvers()}"
        )
    return backend
