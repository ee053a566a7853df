"""The centralised QP stage (the paper's filter): one QP for the team, solved exactly by independent parts.

``min sum_i |A_i du_i - target_i|^2  s.t.  lo <= du <= hi,  rows``.  Without rows every robot's
QP is a box least squares in closed form (:func:`~aasoatt_env.safety.problem.box_least_squares`).
The rows split the team into contact components; a component whose closed-form answers meet
all its rows keeps them (optimal without the rows, and feasible).  Only the components with a
violated row go to the solver (:class:`~aasoatt_env.safety.solvers.SolverPolicy`), as independent
parts of one problem.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from aasoatt_env.compiled import c64, kernels
from aasoatt_env.model.geometry import pair_components
from aasoatt_env.safety.problem import ROW_NORM_MIN, box_least_squares, build_problem
from aasoatt_env.safety.rows import Rows
from aasoatt_env.safety.solvers import SolverPolicy
from aasoatt_env.safety.solvers import active_set as aset
from aasoatt_env.safety.stages import Answer, StepInput, Warm

__all__ = ["Centralized", "avoiding_robots", "kernel_settings", "solve_rows"]


def kernel_settings(policy: SolverPolicy) -> np.ndarray:
    """The warm active set's constants as :func:`~.centralized_kernel.solve_decomposed` reads them."""
    return np.array([aset.PDAS_ITER, aset.one_change_budget(policy.one_change_iter), aset.TOL, aset.WARM_REL,
                     aset.WARM_FLOOR, aset.BOUND_TIGHT, ROW_NORM_MIN, aset.DENSE_MAX_VARS, aset.DENSE_MAX_CELLS],
                    dtype=np.float64)


def avoiding_robots(n: int, rows: Rows, active: np.ndarray) -> np.ndarray:
    """``(N,)``: robots with an ``active`` row (an obstacle row marks its robot only)."""
    out = np.zeros(n, dtype=bool)
    out[rows.ri[active]] = True
    out[rows.rj[active & (rows.rj >= 0)]] = True
    return out


def solve_rows(policy: SolverPolicy, A: np.ndarray, target: np.ndarray, lo: np.ndarray, hi: np.ndarray,
               scale: np.ndarray, rows: Rows, warm: Warm, *, decompose: bool = True,
               compiled: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, object, int]:
    """The QP of the robots and rows given: ``(du, x, z, eta, solution, n_qp)`` (``solution`` None: closed form).

    ``du`` within the bounds, ``x = du / scale`` before clipping (the next warm start), ``z`` the scaled
    multipliers and ``eta`` those in the units of eqn.8, 0 on rows outside the QP.
    """
    n, m = A.shape[0], rows.m
    z, eta = np.zeros(m), np.zeros(m)
    if decompose and policy.exact:
        du = box_least_squares(A, target, lo, hi)
        bad = rows.values(du) - rows.rhs > 0.0
        if not bad.any():
            return du, du / scale[:, None], z, eta, None, 0
        label = pair_components(n, rows.ri, rows.rj, compiled=compiled)
        coupled = np.isin(label, label[rows.ri[bad]])
        groups = np.unique(label[coupled], return_inverse=True)[1].reshape(-1)
    else:
        du, coupled, groups = np.zeros((n, 2)), np.ones(n, dtype=bool), None
    sub, sel = np.flatnonzero(coupled), coupled[rows.ri]
    remap = np.full(n, -1, dtype=np.intp)
    remap[sub] = np.arange(sub.size)
    qri, qrj = rows.ri[sel], rows.rj[sel]
    prob = build_problem(A[sub], target[sub], lo[sub], hi[sub], scale[sub], remap[qri],
                         np.where(qrj >= 0, remap[np.maximum(qrj, 0)], -1), rows.Gi[sel], rows.Gj[sel], rows.rhs[sel])
    x0 = None if warm.x is None else warm.x[sub].ravel()
    sol = policy.solve(prob, x0, None if warm.z is None else warm.z[sel], groups)
    xs = sol.x if sol.x is not None and np.all(np.isfinite(sol.x)) else np.zeros(prob.n)
    x = du / scale[:, None]
    du[sub] = np.clip((xs * prob.scale).reshape(-1, 2), lo[sub], hi[sub])
    x[sub] = xs.reshape(-1, 2)
    zs = np.zeros(prob.m) if sol.z is None else np.where(np.isfinite(sol.z), sol.z, 0.0)
    z[sel] = zs
    eta[sel] = prob.obj_scale * zs / prob.row_norm
    return du, x, z, eta, sol, prob.m


@dataclass(frozen=True)
class Centralized:
    """The centralised QP stage: ``stage(step, rows, target, triggered, warm) -> Answer``.

    With ``compiled`` (and an exact back-end, the decomposition and the warm active set on), a
    warm-started step is first tried in one compiled call
    (:func:`~aasoatt_env.safety.centralized_kernel.solve_decomposed`), which answers it only where
    it verifies every component, with this stage's numbers; else the numpy stage answers it.
    """

    policy: SolverPolicy
    decompose: bool
    eta_tol: float
    compiled: bool
    settings: np.ndarray | None = field(init=False, default=None)
    """The compiled call's constants (None: that call is not made)."""

    def __post_init__(self) -> None:
        if self.compiled and self.decompose and self.policy.active_set and self.policy.exact:
            object.__setattr__(self, "settings", kernel_settings(self.policy))

    def __call__(self, s: StepInput, rows: Rows, target: np.ndarray, triggered: np.ndarray, warm: Warm) -> Answer:
        """Solve the step's QP (module docstring)."""
        if self.settings is not None and warm.x is not None and warm.z is not None:
            k = kernels("centralized")
            code, used, n_qp, du, x, z, eta = k.solve_decomposed(
                s.A, c64(target), s.lo, s.hi, s.scale, rows.ri, rows.rj, rows.Gi, rows.Gj, rows.rhs, c64(warm.x),
                warm.z, self.settings)
            if code == k.CLOSED_FORM:
                return Answer(du, x, z, eta, np.zeros(du.shape[0], dtype=bool), "solved", "closed form: no row binds",
                              0, 0, 0.0)
            if code == k.VERIFIED:
                return Answer(du, x, z, eta, avoiding_robots(du.shape[0], rows, z > self.eta_tol), "solved",
                              aset.VERIFIED_MESSAGE, int(used), int(n_qp), 0.0)
        du, x, z, eta, sol, n_qp = solve_rows(self.policy, s.A, target, s.lo, s.hi, s.scale, rows, warm,
                                        decompose=self.decompose, compiled=self.compiled)
        avoiding = avoiding_robots(du.shape[0], rows, z > self.eta_tol)
        if sol is None:
            return Answer(du, x, z, eta, avoiding, "solved", "closed form: no row binds", 0, 0, 0.0)
        slack = 0.0
        if sol.status != "solved" or not sol.exact:
            slack = float(max(0.0, np.max(rows.values(du) - rows.rhs, initial=0.0)))
        return Answer(du, x, z, eta, avoiding, sol.status, sol.message, sol.iterations, n_qp, slack)
