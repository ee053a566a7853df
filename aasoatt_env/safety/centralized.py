"""The centralised QP stage (the paper's filter): one QP for the team, solved exactly by independent parts.

Each robot's answer without rows is a box least squares in closed form; a contact component whose answers meet its
rows keeps them (optimal), the others go to the solver (:class:`~.solvers.SolverPolicy`) as independent parts.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from aasoatt_env.compiled import c64, kernels
from aasoatt_env.model.geometry import pair_components
from aasoatt_env.safety.problem import ROW_NORM_MIN, box_least_squares, build_problem
from aasoatt_env.safety.rows import Rows
from aasoatt_env.safety.solvers import SolverPolicy
from aasoatt_env.safety.solvers import active_set as aset
from aasoatt_env.safety.stages import Answer, StepInput, Warm

__all__ = ["WARM_MESSAGES", "Centralized", "TeamAnswer", "avoiding_robots", "compiled_settings", "kernel_settings",
           "solve_rows", "solve_team"]


def kernel_settings(policy: SolverPolicy) -> np.ndarray:
    """The warm active set's constants as :func:`~.centralized_kernel.solve_decomposed` reads them."""
    return np.array([aset.PDAS_ITER, aset.one_change_budget(policy.one_change_iter), aset.TOL, aset.WARM_REL,
                     aset.WARM_FLOOR, aset.BOUND_TIGHT, ROW_NORM_MIN, aset.DENSE_MAX_VARS, aset.DENSE_MAX_CELLS], float)


def avoiding_robots(n: int, rows: Rows, active: np.ndarray, active_j: np.ndarray | None = None) -> np.ndarray:
    """``(N,)``: robots with an ``active`` row (``active_j``: where the ``rj`` halves are; obstacle rows: ``ri``'s)."""
    out = np.zeros(n, dtype=bool)
    out[rows.ri[active]] = True
    out[rows.rj[(active if active_j is None else active_j) & (rows.rj >= 0)]] = True
    return out


def solve_rows(policy: SolverPolicy, A: np.ndarray, target: np.ndarray, lo: np.ndarray, hi: np.ndarray,
               scale: np.ndarray, rows: Rows, warm: Warm, *, decompose: bool = True,
               compiled: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, object, int]:
    """The QP of the robots and rows given: ``(du, x, z, eta, solution, n_qp)`` (``solution`` None: closed form).

    ``x = du / scale`` before clipping (the next warm start); ``z`` scaled, ``eta`` in eqn.8's units, 0 off the QP.
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
    sol = policy.solve(prob, x0, None if warm.z is None else warm.z[sel], groups, warm.relaxed)
    xs = sol.x if sol.x is not None and np.all(np.isfinite(sol.x)) else np.zeros(prob.n)
    x = du / scale[:, None]
    du[sub] = np.clip((xs * prob.scale).reshape(-1, 2), lo[sub], hi[sub])
    x[sub] = xs.reshape(-1, 2)
    zs = np.zeros(prob.m) if sol.z is None else np.where(np.isfinite(sol.z), sol.z, 0.0)
    z[sel] = zs
    eta[sel] = prob.obj_scale * zs / prob.row_norm
    return du, x, z, eta, sol, prob.m


class TeamAnswer(NamedTuple):
    """:func:`solve_team`'s answer (multipliers 0 on rows outside the QP)."""

    du: np.ndarray
    x: np.ndarray
    z: np.ndarray
    eta: np.ndarray
    status: str
    message: str
    iterations: int
    n_qp: int
    exact: bool


def solve_team(policy: SolverPolicy, A: np.ndarray, target: np.ndarray, lo: np.ndarray, hi: np.ndarray,
               scale: np.ndarray, rows: Rows, warm: Warm, *, decompose: bool, compiled: bool,
               settings: np.ndarray | None) -> TeamAnswer:
    """The QP: the compiled call where it verifies (``settings``, warm start; same numbers), else :func:`solve_rows`."""
    if settings is not None and warm.x is not None and warm.z is not None and warm.compiled:
        k = kernels("centralized")
        code, used, n_qp, du, x, z, eta = k.solve_decomposed(A, c64(target), lo, hi, scale, rows.ri, rows.rj,
                                                             rows.Gi, rows.Gj, rows.rhs, c64(warm.x), warm.z,
                                                             settings)
        if code in (k.CLOSED_FORM, k.VERIFIED):  # (the closed form: used = n_qp = 0)
            message = CLOSED_FORM_MESSAGE if code == k.CLOSED_FORM else aset.VERIFIED_MESSAGE
            return TeamAnswer(du, x, z, eta, "solved", message, int(used), int(n_qp), True)
    du, x, z, eta, sol, n_qp = solve_rows(policy, A, target, lo, hi, scale, rows, warm, decompose=decompose,
                                          compiled=compiled)
    if sol is None:
        return TeamAnswer(du, x, z, eta, "solved", CLOSED_FORM_MESSAGE, 0, 0, True)
    return TeamAnswer(du, x, z, eta, sol.status, sol.message, sol.iterations, n_qp, sol.exact)


CLOSED_FORM_MESSAGE = "closed form: no row binds"
WARM_MESSAGES = (aset.VERIFIED_MESSAGE, CLOSED_FORM_MESSAGE)  #: the answers of the closed form or the warm active set


@dataclass(frozen=True)
class Centralized:
    """The centralised QP stage: ``stage(step, rows, target, triggered, warm) -> Answer`` (:func:`solve_team`)."""

    policy: SolverPolicy
    decompose: bool
    eta_tol: float
    compiled: bool
    settings: np.ndarray | None = field(init=False, default=None)  #: the compiled call's (None: not made)

    def __post_init__(self) -> None:
        object.__setattr__(self, "settings", compiled_settings(self.policy, self.compiled, self.decompose))

    def __call__(self, s: StepInput, rows: Rows, target: np.ndarray, triggered: np.ndarray, warm: Warm) -> Answer:
        """Solve the step's QP (module docstring)."""
        a = solve_team(self.policy, s.A, target, s.lo, s.hi, s.scale, rows, warm, decompose=self.decompose,
                       compiled=self.compiled, settings=self.settings)
        checked = a.status != "solved" or not a.exact  # (an exact solve meets its rows)
        slack = float(max(0.0, np.max(rows.values(a.du) - rows.rhs, initial=0.0))) if checked else 0.0
        return Answer(a.du, a.x, a.z, a.eta, avoiding_robots(a.du.shape[0], rows, a.z > self.eta_tol), a.status,
                      a.message, a.iterations, a.n_qp, slack, a.message in WARM_MESSAGES)


def compiled_settings(policy: SolverPolicy, compiled: bool, decompose: bool = True) -> np.ndarray | None:
    """:func:`kernel_settings` where :func:`solve_team` makes its compiled call (None: it does not)."""
    if compiled and decompose and policy.active_set and policy.exact:
        return kernel_settings(policy)
    return None
