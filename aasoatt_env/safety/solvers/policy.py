"""The safety QP: :func:`solve_qp`, which never raises on numerical trouble and never returns NaN.

The problem and its scaled canonical form are in :mod:`aasoatt_env.safety.problem`,
the solvers (by name, :data:`SOLVERS`) in :mod:`aasoatt_env.safety.solvers.backends`.
With ``solver="proxsuite"``, ``active_set=True`` and a warm start (``x0``, ``z0``
from the previous step) :func:`solve_qp` first tries a few iterations of the
exact structured active-set method of :mod:`aasoatt_env.safety.solvers.active_set`,
accepted only when the full KKT conditions hold.

Infeasibility verdicts are never trusted: :func:`solve_qp` confirms them with a
phase-1 problem ``min |s|^2 s.t. box, C x - s <= u, s >= 0`` (always feasible;
bounds stay hard; one slack per row, so only the rows that cannot be met are
loosened).  If every least violation ``s*_k`` is ~0 the problem is re-solved
with rows loosened by a hair (status ``"solved"``), otherwise each row by its
own ``s*_k`` (status ``"relaxed"``, ``slack = max_k s*_k``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from aasoatt_env.safety.solvers import backends as _backends
from aasoatt_env.safety.solvers.active_set import solve_active_set
from aasoatt_env.safety.solvers.backends import DENSE_MAX_SIZE, SOLVERS, Backend, _clarabel, _ldp, available_solvers, get_solver
from aasoatt_env.safety.solvers.ldp import MAX_VARS as LDP_MAX_VARS
from aasoatt_env.safety.problem import QPProblem, box_least_squares, build_problem

__all__ = [
    "DENSE_MAX_SIZE",
    "QPProblem",
    "QPSolution",
    "SOLVERS",
    "available_solvers",
    "box_least_squares",
    "build_problem",
    "get_solver",
    "solve_qp",
]

_FEAS_TOL = 1e-7


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
        if backend is not _clarabel and _backends._installed("clarabel"):
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
