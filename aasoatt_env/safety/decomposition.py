"""The centralised filter's QP, solved exactly by independent parts.

Without rows every robot's QP is a 2-variable box least squares (closed form,
:func:`~aasoatt_env.safety.problem.box_least_squares`).  The rows split the
team into independent contact components; a component whose closed-form
answers already meet all its rows is solved by them (optimal for the
relaxation and feasible).  The QP couples only the components with a violated
row, each an independent part of it (verified on its own by the warm active
set, :class:`~aasoatt_env.safety.solvers.SolverPolicy`).

:func:`solve_centralized` is that step.  With the compiled kernels
(:mod:`aasoatt_env.compiled`, part ``"decomposition"``) a warm-started step is
first tried in one compiled call
(:mod:`aasoatt_env.safety.decomposition_kernel`), which answers only where it
verifies every component and then answers as the numpy path does; the numpy
path answers every other step.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from aasoatt_env import validation as check
from aasoatt_env.compiled import c64, kernels
from aasoatt_env.model.geometry import pair_components, row_dot
from aasoatt_env.safety.problem import ROW_NORM_MIN, box_least_squares, build_problem
from aasoatt_env.safety.solvers import SolverPolicy
from aasoatt_env.safety.solvers.active_set import (
    BOUND_TIGHT,
    DENSE_MAX_CELLS,
    DENSE_MAX_VARS,
    PDAS_ITER,
    TOL,
    VERIFIED_MESSAGE,
    WARM_FLOOR,
    WARM_REL,
    ActiveSetParts,
    one_change_budget,
)

__all__ = ["CentralAnswer", "row_values", "solve_centralized"]


class CentralAnswer(NamedTuple):
    """The centralised QP's answer for one step."""

    du: np.ndarray
    """Wheel accelerations ``(N, 2)`` within the bounds."""
    x: np.ndarray
    """The scaled point ``(N, 2)`` (``du / scale`` before clipping): the next step's warm start."""
    z: np.ndarray
    """Multipliers of the scaled rows ``(m,)`` (0 on rows outside the QP): the next step's warm start."""
    eta: np.ndarray
    """Multipliers in ``du`` units ``(m,)``."""
    status: str
    """``"solved"``, ``"relaxed"`` or ``"failed"`` (the solver's status)."""
    message: str
    """Which solver answered."""
    iterations: int
    """The solver's iterations."""
    n_qp: int
    """Rows in the QP."""


WarmRows = Callable[[], "np.ndarray | None"]
"""The previous step's multipliers mapped onto this step's rows ``(m,)``, computed when asked (None: none)."""


def solve_centralized(
    policy: SolverPolicy,
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
    x_prev: np.ndarray | None,
    z_warm: np.ndarray | WarmRows | None,
    *,
    decompose: bool = True,
    compiled: bool = False,
    checked: bool = False,
    tried: bool = False,
    kernel_parts: tuple | None = None,
) -> CentralAnswer:
    """``min sum |A_i du_i - target_i|^2  s.t.  lo <= du <= hi, G du <= rhs`` for the whole team.

    Parameters
    ----------
    policy : SolverPolicy
        Which solver answers (its switch state is updated as by its ``solve``).
    A, target, lo, hi : numpy.ndarray
        Input matrices ``(N, 2, 2)``, desired control-point accelerations and bounds ``(N, 2)``.
    scale : numpy.ndarray
        Positive per-robot scale ``(N,)`` of the scaled variables ``x = du / scale``.
    ri, rj, Gi, Gj, rhs : numpy.ndarray
        The rows (:func:`~aasoatt_env.safety.problem.build_problem`): ``Gi du_ri + Gj du_rj <= rhs``
        for ``m`` rows, ``ri`` in ``[0, N)``, ``rj`` in ``[0, N)`` or ``-1`` on obstacle rows.
    x_prev : numpy.ndarray or None
        The previous step's scaled point ``(N, 2)`` (None: no warm start).
    z_warm : numpy.ndarray, callable or None
        The previous step's multipliers mapped onto these rows ``(m,)``, or a function
        returning them (called only where a QP is solved).
    decompose : bool
        Split by components (only with an exact solver); False: one QP of the whole team.
    compiled : bool
        Try the compiled step first (:mod:`aasoatt_env.safety.decomposition_kernel`).
    checked : bool
        The caller vouches for the shapes and row indices (the filter's own rows, built by this
        library for ``N`` robots): their O(m) check is skipped.  The compiled step reads without
        bounds checks, so anything else must leave this False.
    tried, kernel_parts : bool, tuple or None
        The caller ran the compiled step on these very arrays (the filter's compiled step,
        :mod:`~aasoatt_env.safety.step_kernel`), which did not answer: it is not run again, and
        ``kernel_parts`` is what it handed on (``(x, z, done, iterations)`` of
        :data:`~aasoatt_env.safety.decomposition_kernel.PARTS`, or None).

    Returns
    -------
    CentralAnswer
        ``du`` within the bounds, the warm start of the next step, the multipliers, and
        what answered (``"closed form: no row binds"`` where no robot's own answer
        violates a row).

    Raises
    ------
    ValueError
        An array of the wrong shape, or a row index out of range (named).
    """
    n, m = (A.shape[0], rhs.shape[0]) if checked else _check(A, target, lo, hi, scale, ri, rj, Gi, Gj, rhs, x_prev,
                                                              z_warm)
    warm = _WarmRows(z_warm, None if checked else m)
    decompose = decompose and policy.exact
    if (not tried and compiled and decompose and policy.active_set and policy.compiled and x_prev is not None
            and warm() is not None):
        out = _compiled(policy, A, target, lo, hi, scale, ri, rj, Gi, Gj, rhs, x_prev, warm())
        if isinstance(out, CentralAnswer):
            return out
        kernel_parts = out
    if decompose:
        du = box_least_squares(A, target, lo, hi)
        viol = row_values(Gi, Gj, ri, rj, du) - rhs
        bad = viol > 0.0
        coupled, label = np.zeros(n, dtype=bool), None
        if np.any(bad):
            label = pair_components(n, ri, rj, compiled=compiled)
            coupled = np.isin(label, label[ri[bad]])
        rows = coupled[ri]
    else:
        du = np.empty((n, 2))
        coupled, rows, label = np.ones(n, dtype=bool), np.ones(m, dtype=bool), None
    sub = np.flatnonzero(coupled)
    x_full = du / scale[:, None]
    z, eta = np.zeros(m), np.zeros(m)
    if not sub.size:
        return CentralAnswer(du, x_full, z, eta, "solved", "closed form: no row binds", 0, 0)
    z0 = warm()
    remap = np.full(n, -1, dtype=np.intp)
    remap[sub] = np.arange(sub.size)
    qri, qrj = ri[rows], rj[rows]
    sri, srj = remap[qri], np.where(qrj >= 0, remap[np.maximum(qrj, 0)], -1)
    prob = build_problem(A[sub], target[sub], lo[sub], hi[sub], scale[sub], sri, srj, Gi[rows], Gj[rows], rhs[rows])
    x0 = None if x_prev is None else x_prev[sub].ravel()
    # the coupled components, independent parts of one QP: each verified on its own
    groups = None if label is None else np.unique(label[sub], return_inverse=True)[1].reshape(-1)
    parts = None
    if kernel_parts is not None and groups is not None:  # the kernel's active set on this very problem
        xs, zs, done, used = kernel_parts
        if xs.shape == (prob.n,) and zs.shape == (prob.m,) and done.shape == (int(groups.max(initial=-1)) + 1,):
            parts = ActiveSetParts(xs, zs, used, done, groups[sri])
    sol = policy.solve(prob, x0, None if z0 is None else z0[rows], groups, parts=parts)
    x = sol.x if sol.x is not None and np.all(np.isfinite(sol.x)) else np.zeros(prob.n)
    du[sub] = np.clip((x * prob.scale).reshape(-1, 2), lo[sub], hi[sub])
    x_full[sub] = x.reshape(-1, 2)
    zs = np.where(np.isfinite(sol.z), sol.z, 0.0) if sol.z is not None else np.zeros(prob.m)
    z[rows] = zs
    eta[rows] = prob.obj_scale * zs / prob.row_norm
    return CentralAnswer(du, x_full, z, eta, sol.status, sol.message, sol.iterations, prob.m)


def row_values(Gi: np.ndarray, Gj: np.ndarray, ri: np.ndarray, rj: np.ndarray, du: np.ndarray) -> np.ndarray:
    """``G du`` row by row (``Gj`` ignored on obstacle rows)."""
    du_j = row_dot(Gj, du[np.maximum(rj, 0)])
    return row_dot(Gi, du[ri]) + np.where(rj >= 0, du_j, 0.0)


def _check(A: np.ndarray, target: np.ndarray, lo: np.ndarray, hi: np.ndarray, scale: np.ndarray, ri: np.ndarray,
           rj: np.ndarray, Gi: np.ndarray, Gj: np.ndarray, rhs: np.ndarray, x_prev: np.ndarray | None,
           z_warm: object) -> tuple[int, int]:
    """``(N, m)`` after the shapes and row indices (the compiled step reads without bounds checks)."""
    n = np.shape(A)[0] if np.ndim(A) else -1
    m = np.shape(rhs)[0] if np.ndim(rhs) == 1 else -1
    if np.shape(A) != (n, 2, 2) or m < 0:
        raise ValueError(f"A/rhs: got shapes {np.shape(A)}/{np.shape(rhs)}, expected (N, 2, 2) and (m,)")
    expect = [("target", target, (n, 2)), ("lo", lo, (n, 2)), ("hi", hi, (n, 2)), ("scale", scale, (n,)),
              ("ri", ri, (m,)), ("rj", rj, (m,)), ("Gi", Gi, (m, 2)), ("Gj", Gj, (m, 2))]
    if x_prev is not None:
        expect.append(("x_prev", x_prev, (n, 2)))
    if z_warm is not None and not callable(z_warm):
        expect.append(("z_warm", z_warm, (m,)))
    check.shapes(expect, f" for {n} robots and {m} rows")
    if m:
        ri, rj = np.asarray(ri), np.asarray(rj)
        if ri.dtype.kind not in "iu" or rj.dtype.kind not in "iu":
            raise ValueError(f"ri/rj: row robots must be integer indices, got {ri.dtype}/{rj.dtype}")
        if int(ri.min()) < 0 or int(ri.max()) >= n or int(rj.min()) < -1 or int(rj.max()) >= n:
            raise ValueError(f"ri/rj: row robots must be in [0, {n}) (rj: or -1 for an obstacle row)")
    return n, m


class _WarmRows:
    """``z_warm``'s rows, mapped (called) at most once and only when asked, their shape checked then.

    ``m`` None: not checked (the caller vouches for it).
    """

    def __init__(self, z_warm: np.ndarray | WarmRows | None, m: int | None) -> None:
        self._source, self._m, self._rows, self._done = z_warm, m, None, False

    def __call__(self) -> np.ndarray | None:
        if not self._done:
            rows = self._source() if callable(self._source) else self._source
            if rows is not None and self._m is not None:
                check.shapes((("z_warm", rows, (self._m,)),))
            self._rows, self._done = rows, True
        return self._rows


def _compiled(policy: SolverPolicy, A: np.ndarray, target: np.ndarray, lo: np.ndarray, hi: np.ndarray,
              scale: np.ndarray, ri: np.ndarray, rj: np.ndarray, Gi: np.ndarray, Gj: np.ndarray, rhs: np.ndarray,
              x_prev: np.ndarray, z_warm: np.ndarray) -> CentralAnswer | tuple | None:
    """The step by :func:`~aasoatt_env.safety.decomposition_kernel.solve_decomposed`.

    None: the numpy path's step.  ``(x, z, ok, iterations)``: the numpy path's step, from the warm
    active set's answer on the components (the kernel's :data:`~aasoatt_env.safety.decomposition_kernel.PARTS`).
    """
    t0 = time.perf_counter()
    n, m = A.shape[0], rhs.shape[0]
    du, x, z, eta = np.empty((n, 2)), np.empty((n, 2)), np.empty(m), np.empty(m)
    xs, zs, done = np.empty(2 * n), np.empty(m), np.empty(n, dtype=bool)
    k = kernels("decomposition")
    code, used, n_qp, n_vars, n_parts = k.solve_decomposed(
        c64(A), c64(target), c64(lo), c64(hi), c64(scale), np.ascontiguousarray(ri, np.int64),
        np.ascontiguousarray(rj, np.int64), c64(Gi), c64(Gj), c64(rhs), c64(x_prev), c64(z_warm), PDAS_ITER,
        one_change_budget(policy.one_change_iter), TOL, WARM_REL, WARM_FLOOR, BOUND_TIGHT, ROW_NORM_MIN,
        DENSE_MAX_VARS, DENSE_MAX_CELLS, du, x, z, eta, xs, zs, done)
    if code == k.CLOSED_FORM:
        return CentralAnswer(du, x, z, eta, "solved", "closed form: no row binds", 0, 0)
    if code == k.PARTS:
        return xs[:n_vars], zs[:n_qp], done[:n_parts], int(used)
    elapsed = time.perf_counter() - t0
    if code != k.VERIFIED or policy.needs_problem(int(n_vars), elapsed):
        return None  # (a slow answer: the policy's timing probe needs the problem, which the numpy path builds)
    policy.note_answer(int(n_vars), elapsed)
    return CentralAnswer(du, x, z, eta, "solved", VERIFIED_MESSAGE, int(used), int(n_qp))
