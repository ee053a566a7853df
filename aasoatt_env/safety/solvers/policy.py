"""The whole solver policy of the safety QP: which back-end answers which problem, and what happens without an answer.

:func:`solve_qp` never raises on numerical trouble and never returns NaN.  In order:

1. a problem without rows and with diagonal Hessian blocks is solved in closed form;
2. an approximate back-end (``Backend.exact`` False, the paper's ``neural``) is
   run and its point passed through as it is;
3. with ``active_set=True`` or ``prefer_exact=True`` and a warm start, the exact
   structured active-set method (:mod:`~aasoatt_env.safety.solvers.active_set`)
   is tried first and accepted only where the KKT conditions hold;
   ``prefer_exact`` then also asks the exact path's solvers (``exact_solvers``:
   DAQP where installed, then ``ldp``)
   before the back-end, taking an answer only where it is verified (by ``ldp`` itself,
   or by the warm active set from the answer);
   with independent parts (:meth:`SolverPolicy.solve`'s ``groups``) the parts it
   verifies are answered and only the others go on, as one smaller problem;
4. the back-end; where it gives no answer, its registered fallbacks
   (:attr:`~aasoatt_env.safety.solvers.backends.Backend.fallbacks`; for
   proxsuite: the exact ``ldp`` solver, then after a stall proxsuite's other class);
5. infeasibility verdicts are never trusted: a phase-1 problem
   ``min |s|^2 s.t. box, C x - s <= u, s >= 0`` (always feasible; bounds stay
   hard; one slack per row, so only the rows that cannot be met are loosened)
   finds the least violation of each row (by :data:`PHASE1_SOLVERS`, ``ldp``, the back-end:
   :func:`_phase1`).  If every least violation is ~0 the
   problem is re-solved with rows loosened by a hair (status ``"solved"``),
   otherwise each row by its own violation (status ``"relaxed"``,
   ``slack = max_k s*_k``).

:class:`SolverPolicy` adds the one piece of memory: after a back-end that may
stall (``Backend.may_stall``) needed a fallback, or was slow where ``ldp`` is
at least twice as fast on the same problem (a timing probe), the next
:data:`EXACT_STEPS` calls take the exact path first (step 3 with
``prefer_exact``), doubling on repeated switches.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from aasoatt_env.errors import UsageError
from aasoatt_env.safety.problem import QPProblem
from aasoatt_env.safety.solvers.active_set import (
    VERIFIED_MESSAGE,
    ActiveSetParts,
    solve_active_set,
    solve_active_set_parts,
)
from aasoatt_env.safety.solvers.backends import SOLVERS, Backend, RawAnswer, available_solvers, get_solver
from aasoatt_env.safety.solvers.ldp import MAX_VARS as LDP_MAX_VARS

__all__ = ["EXACT_FIRST_VARS", "EXACT_SOLVERS", "EXACT_STEPS", "PHASE1_LDP_MAX_VARS", "PHASE1_SOLVERS",
           "SLOW_SOLVE_S", "QPSolution", "SolverPolicy", "solve_qp"]

_FEAS_TOL = 1e-7

EXACT_STEPS: int = 200
"""Calls for which :class:`SolverPolicy` goes straight to the exact path after a stall
or a slow solve: a back-end that stalls on a congested problem (proxsuite on a 60-robot
circle swap) stalls on the next ones too, and each stall costs its whole iteration
budget.  Doubled on each repeated switch (up to 16x)."""
EXACT_SOLVERS: tuple[str, ...] = ("daqp", "ldp")
"""The exact path's solvers after the warm active set, in order, where installed (:class:`SolverPolicy`'s
``exact_solvers``; ``pip install "aasoatt[fast]"`` adds DAQP): each answer is taken only where verified
(``Backend.verified``: ``ldp``; DAQP's by the warm active set started from it), and DAQP's proof of
infeasibility goes straight to phase 1.  Measured (2026-12-02): on 21 negotiation groups of 80-90 robots
that the warm active set missed DAQP answered in 2.4 ms where ``ldp`` took 11-16, and proved an infeasible
54-robot group's rows inconsistent in 1.3 ms where ``ldp`` took 8; a relaxed 13-robot part of a 20-robot
team under random actions (proof, phase 1, relaxed QP) took 0.63 ms where ``ldp``'s path took 2.1."""
EXACT_FIRST_VARS: int = 100
"""Problems with up to this many variables (50 robots in one coupled group) take the exact path
first (warm active set, then the exact solvers, :data:`EXACT_SOLVERS`; the back-end only if they fail): ``ldp``
is exact, proves infeasibility (where an augmented Lagrangian only runs out of iterations) and is fast at
this size."""
SLOW_SOLVE_S: float = 0.05
"""A solve slower than this [s] triggers the ``ldp`` timing probe."""
PHASE1_LDP_MAX_VARS: int = 120
"""Phase-1 problems (the variables and one slack per row) up to this size go to ``ldp`` before the
back-end (after :data:`PHASE1_SOLVERS`, with a back-end that may stall), larger ones after it: ``ldp``'s
NNLS slows down sharply on the phase-1 problem, whose 1e-8 regulariser conditions it badly (0.8 ms at 44
variables, 220-311 ms at 226-254, where Clarabel took 5.7 and proxsuite 11-34 with 20-50% of them
unanswered; infeasible negotiation groups of 30-40 robots, 2026-12-02)."""
PHASE1_SOLVERS: tuple[tuple[str, int, int | None], ...] = (("daqp", 0, 400), ("clarabel", 121, None))
"""Solvers preferred for phase-1 problems where the back-end may stall, in order, where installed, each for
phase-1 problems of ``lo`` to ``hi`` variables (None: any).  DAQP took 0.05 ms on the 44-variable phase 1 of
a 13-robot part (``ldp`` 0.8) and 0.9 ms at 226-254 variables (``ldp`` 220-311); it is dense, and on a
phase-1 problem whose every row binds (robots each between two contradicting rows) it took 18 ms at 400
variables, 59 at 600 and 534 at 1,200, where Clarabel took 5-14 ms and the configured back-end 12-23
(2026-12-02); Clarabel (an interior-point method, ~5 ms at any of these sizes) only beyond
:data:`PHASE1_LDP_MAX_VARS`."""


@dataclass
class QPSolution:
    """Outcome of :func:`solve_qp` in scaled coordinates."""

    x: np.ndarray
    z: np.ndarray
    status: str
    """``"solved"``, ``"relaxed"`` (rows loosened by ``slack``) or ``"failed"``."""
    slack: float
    iterations: int
    message: str
    """Which back-end answered, and why."""
    solve_time: float
    fallback: bool = False
    """True when the requested back-end gave no answer and a registered fallback did."""
    exact: bool = True
    """False when an approximate back-end answered (its point is not verified)."""


def _answer(prob: QPProblem, backend: Backend, x0: np.ndarray | None, z0: np.ndarray | None,
            opts: dict) -> tuple[RawAnswer, bool]:
    """The back-end's answer, or its fallbacks' (``(raw, used_fallback)``)."""
    raw = backend(prob, x0, z0, opts)
    if raw.ok:
        return raw, False
    iterations, messages = raw.iterations, [raw.message]
    for name, after_stall, extra in backend.fallbacks:
        if after_stall and not raw.stalled:
            continue
        nxt = get_solver(name)(prob, x0, z0, {**opts, **extra})
        iterations += nxt.iterations
        messages.append(nxt.message)
        if nxt.ok:
            nxt.iterations, nxt.message = iterations, ", then ".join(messages)
            return nxt, True
    return RawAnswer(raw.x, raw.z, False, iterations, ", then ".join(messages), raw.stalled), False


def _helper(name: str, opts: dict) -> tuple[Backend, dict]:
    """Back-end ``name`` as the policy asks it itself, and its options (with its ``helper_options``)."""
    backend = get_solver(name)
    return backend, {**opts, **dict(backend.helper_options)}


def _exact(prob: QPProblem, names: tuple[str, ...], x0: np.ndarray | None, z0: np.ndarray | None,
           opts: dict) -> RawAnswer:
    """The exact path's answer: the first installed of ``names`` that answers or proves the rows inconsistent.

    An answer is taken only where it is verified: by the back-end itself (``Backend.verified``: ``ldp``),
    or by the warm active set started from it (the KKT conditions to its tolerance, the point polished
    there); an answer that does not verify goes on to the next name.
    """
    installed = available_solvers()
    raw, messages = RawAnswer(None, None, False, 0, f"none of {list(names)} installed"), []
    for name in names:
        if name not in installed:
            continue
        backend, kw = _helper(name, opts)
        raw = backend(prob, x0, z0, kw)
        note = raw.message if raw.message.startswith(name) else f"{name}: {raw.message}"
        if raw.ok and not backend.verified:
            polished = solve_active_set(prob, raw.x, _nonneg(raw.z, prob.m))
            if polished is None:
                raw.ok, note = False, note + ", KKT check failed"
            else:
                raw.x, raw.z, note = polished[0], polished[1], note + " (KKT verified)"
        messages.append(note)
        if raw.ok or raw.infeasible:
            break
    if messages:
        raw.message = ", then ".join(messages)
    return raw


def check_exact_solvers(value: object, name: str = "exact_solvers") -> tuple[str, ...]:
    """``value`` as a tuple of registered exact solver names, or :class:`UsageError` naming ``name``."""
    exact = [k for k, b in SOLVERS.items() if b.exact]
    if isinstance(value, str) or not isinstance(value, (tuple, list)):
        raise UsageError(f"{name}: got {value!r}, expected a tuple of solver names among {exact}")
    for item in value:
        if item not in exact:
            raise UsageError(f"{name}: {item!r} is not a registered exact solver; registered: {exact}")
    return tuple(value)


def check_budget(value: object, name: str = "one_change_iter") -> int | None:
    """``value`` as an iteration budget (a non-negative int, or None), or :class:`UsageError` naming ``name``."""
    if value is None:
        return None
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < 0:
        raise UsageError(f"{name}: got {value!r}, expected a non-negative int (or None: the default)")
    return int(value)


def _phase1(prob: QPProblem, solver: str, opts: dict) -> tuple[np.ndarray, np.ndarray] | None:
    """Least row violations ``s* >= 0`` (one slack per row, bounds hard); None if even this fails.

    Solves ``min 0.5 |s|^2 (+ a 1e-8 regulariser on x)  s.t.  C x - s <= u, lb <= x <= ub``.
    A slack per row means one hopeless row (say a pair already inside ``d_s``) is
    loosened alone: every row that can still be met keeps (numerically) zero slack.
    Solved by the first of these that answers: where ``solver`` may stall, the installed
    :data:`PHASE1_SOLVERS` for this size, then ``ldp`` if small (:data:`PHASE1_LDP_MAX_VARS`),
    ``solver``, then ``ldp`` if larger; a back-end that does not stall (``daqp``, as
    ``aasoatt reproduce`` runs) is asked first, as before, then the others.
    """
    n, m = prob.n, prob.m
    backend = get_solver(solver)
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
    # point is accepted at a looser feasibility (the 1e-8 regulariser conditions it badly): ldp_feas_tol
    installed = available_solvers()
    preferred = [k for k, lo, hi in PHASE1_SOLVERS if lo <= p1.n and (hi is None or p1.n <= hi)]
    small = p1.n <= PHASE1_LDP_MAX_VARS  # ldp before the back-end (its NNLS is slow on large phase-1 problems)
    first = preferred + (["ldp"] if small else []) if backend.may_stall else []
    last = ["clarabel"] if small else ["ldp"] if p1.n <= LDP_MAX_VARS else []
    order = [*first, solver, *preferred, *last]
    raw, p1_opts = None, {**opts, "ldp_feas_tol": 1e-6}
    for name in dict.fromkeys(order):  # in order, each once
        if name not in installed:
            continue
        # the configured back-end as configured; another as the policy asks it itself (its helper options)
        cand, kw = (backend, p1_opts) if name == solver else _helper(name, p1_opts)
        raw, _ = _answer(p1, cand, None, None, kw)
        if raw.ok and raw.x is not None:
            break
    if raw is None or not raw.ok or raw.x is None:
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
    """Solve ``prob`` (module docstring); never raises on numerical trouble, never returns NaN.

    Options (``**opts``): ``eps`` (proxsuite/OSQP tolerance), ``iterations`` and
    ``step`` (``neural``), ``alternate`` (proxsuite's other class),
    ``active_set`` (first the warm-started exact active-set method),
    ``prefer_exact`` (first the warm active set, then the exact path's solvers, the
    back-end only if they fail), ``exact_solvers`` (those solvers, in order,
    :data:`EXACT_SOLVERS` by default), ``compiled`` (the warm active set's compiled kernel,
    :mod:`aasoatt_env.compiled`), ``one_change_iter`` (the warm active set's
    one-change budget, :data:`~aasoatt_env.safety.solvers.active_set.ONE_CHANGE_ITER`).
    """
    tried = bool(opts.pop("active_set_tried", False))  # the caller ran it on this very warm start
    compiled = bool(opts.pop("compiled", False))
    budget = check_budget(opts.pop("one_change_iter", None))
    exact = check_exact_solvers(opts.pop("exact_solvers", EXACT_SOLVERS))
    backend = get_solver(solver)
    t0 = time.perf_counter()
    if prob.m == 0 and prob.diagonal and backend.exact:
        x = np.clip(_unconstrained(prob), prob.lb, prob.ub)
        return QPSolution(x, np.zeros(0), "solved", 0.0, 0, "no rows", time.perf_counter() - t0)
    if not backend.exact:
        raw = backend(prob, x0, z0, opts)
        return QPSolution(raw.x, raw.z, "solved", 0.0, raw.iterations, raw.message, time.perf_counter() - t0,
                          exact=False)
    exact_first = bool(opts.get("prefer_exact")) and prob.n <= LDP_MAX_VARS
    if x0 is not None and z0 is not None and (opts.get("active_set") or exact_first) and not tried:
        fast = solve_active_set(prob, x0, z0, compiled=compiled, one_change_iter=budget)
        if fast is not None:
            return QPSolution(fast[0], fast[1], "solved", 0.0, fast[2], VERIFIED_MESSAGE,
                              time.perf_counter() - t0)
    raw = None
    if exact_first:
        raw = _exact(prob, exact, x0, z0, opts)
        if raw.ok:
            return QPSolution(raw.x, _nonneg(raw.z, prob.m), "solved", 0.0, 0,
                              f"{raw.message}; {solver} skipped (prefer_exact)", time.perf_counter() - t0)
        used_fallback = False
    if raw is None or not raw.infeasible:  # an exact infeasibility certificate goes straight to phase 1
        raw, used_fallback = _answer(prob, backend, x0, z0, opts)
    if raw.ok:
        return QPSolution(raw.x, _nonneg(raw.z, prob.m), "solved", 0.0, raw.iterations, raw.message,
                          time.perf_counter() - t0, used_fallback)
    first = raw.message
    p1 = _phase1(prob, solver, opts)
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
    raw2, fb2 = (_exact(p2, exact, x1, None, opts), False) if exact_first else _answer(p2, backend, x1, None, opts)
    if not raw2.ok and exact_first:
        raw2, fb2 = _answer(p2, backend, x1, None, opts)
    status = "relaxed" if relaxed else "solved"
    msg = f"{solver}: {first}; phase-1 largest row violation {tstar:.3g} ({int(np.sum(viol > _FEAS_TOL))} rows)"
    if raw2.ok:
        return QPSolution(raw2.x, _nonneg(raw2.z, prob.m), status, tstar if relaxed else 0.0,
                          raw.iterations + raw2.iterations, msg, time.perf_counter() - t0, used_fallback or fb2)
    return QPSolution(x1, np.zeros(prob.m), "relaxed", tstar, raw.iterations + raw2.iterations,
                      msg + "; phase-2 failed, returning the phase-1 point", time.perf_counter() - t0)


class SolverPolicy:
    """:func:`solve_qp` with memory: the exact path for a while after a stall or a slow solve.

    Parameters
    ----------
    solver : str
        Registered back-end name.
    active_set : bool
        Always try the warm-started exact active-set method first.
    options : dict, optional
        Back-end options (e.g. ``iterations`` of ``neural``).
    compiled : bool
        Run the warm active set in its compiled kernel (:mod:`aasoatt_env.compiled`).
    exact_first : bool
        Always take the exact path first (the warm active set, then ``exact_solvers``, up to ``ldp``'s
        size limit; the back-end only where they fail), not only on small problems or after a stall.  The
        decentralised filter's negotiation groups use it: their QPs change shape from step to
        step, and proxsuite 0.8's sparse class (problems with more than
        :data:`~aasoatt_env.safety.solvers.backends.DENSE_MAX_SIZE` variables and rows) crashed
        the process on one of them (an 81-robot group, feasible: ``ldp`` and Clarabel solve it).
    one_change_iter : int, optional
        The warm active set's one-change budget (None:
        :data:`~aasoatt_env.safety.solvers.active_set.ONE_CHANGE_ITER`).
    exact_solvers : tuple of str
        The exact path's solvers after the warm active set, in order, where installed
        (:data:`EXACT_SOLVERS` by default; ``ldp`` is always installed).
    """

    def __init__(self, solver: str, active_set: bool = False, options: dict | None = None,
                 compiled: bool = False, exact_first: bool = False, one_change_iter: int | None = None,
                 exact_solvers: tuple[str, ...] = EXACT_SOLVERS) -> None:
        self.solver = solver
        self.backend = get_solver(solver)
        self.active_set = bool(active_set)
        self.compiled = bool(compiled)
        self.exact_first = bool(exact_first)
        self.one_change_iter = check_budget(one_change_iter)
        self.exact_solvers = check_exact_solvers(exact_solvers)
        self.options = dict(options or {})
        self.reset()

    def reset(self) -> None:
        """Forget the switch state."""
        self._exact_steps = 0
        self._stalls = 0

    @property
    def exact(self) -> bool:
        """Whether the back-end's answers are exact."""
        return self.backend.exact

    def solve(self, prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None,
              groups: np.ndarray | None = None, parts: ActiveSetParts | None = None) -> QPSolution:
        """Solve ``prob``, warm-started from ``(x0, z0)`` where the back-end uses them.

        ``groups`` ``(N,)``: the independent parts of ``prob`` (a group ``0..K-1`` per robot,
        no row between groups).  With the warm active set, every part it verifies is
        answered by it and only the other parts go on to the back-end, as one smaller
        problem: one hard or infeasible part does not send the whole stack to the
        back-end and to phase 1.  ``parts``: the warm active set's answer on these groups
        from this warm start, already computed (the compiled decomposition's, on the same
        problem): used instead of running it again.
        """
        if (groups is not None and self.active_set and self.backend.exact and x0 is not None and z0 is not None
                and int(np.max(groups, initial=0)) > 0):
            t0 = time.perf_counter()
            part = parts if parts is not None else solve_active_set_parts(
                prob, x0, z0, groups, compiled=self.compiled, one_change_iter=self.one_change_iter)
            if part is not None:
                return self._rest(prob, x0, z0, groups, part, t0)
        return self._solve(prob, x0, z0)

    def _rest(self, prob: QPProblem, x0: np.ndarray, z0: np.ndarray, groups: np.ndarray,
              part: ActiveSetParts, t0: float) -> QPSolution:
        """The parts the active set verified, and the back-end's answer on the others."""
        msg = VERIFIED_MESSAGE
        if part.ok.all():
            sol = QPSolution(part.x, part.z, "solved", 0.0, part.iterations, msg, time.perf_counter() - t0)
            self._count(prob, sol)
            return sol
        robots, rows = ~part.ok[groups], ~part.ok[part.row_group]
        if not part.ok.any():
            sol = self._solve(prob, x0, z0, active_set_tried=True)
            sol.iterations += part.iterations
            return sol
        v = np.repeat(robots, 2)
        rest = self._solve(prob.restrict(robots, rows), x0[v], z0[rows], active_set_tried=True)
        x, z = part.x.copy(), part.z.copy()
        x[v], z[rows] = rest.x, rest.z
        return QPSolution(x, z, rest.status, rest.slack, part.iterations + rest.iterations,
                          f"{msg} on {int(part.ok.sum())} of {part.ok.shape[0]} parts; the other "
                          f"{int((~part.ok).sum())}: {rest.message}", time.perf_counter() - t0,
                          rest.fallback, rest.exact)

    def _solve(self, prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, **extra: bool) -> QPSolution:
        opts = {**self.options, **extra, "compiled": self.compiled, "one_change_iter": self.one_change_iter,
                "exact_solvers": self.exact_solvers}
        if self.active_set:
            opts["active_set"] = True
        if not self.backend.may_stall:
            return solve_qp(prob, self.solver, x0, z0, **opts)
        if self._exact_path(prob.n):
            return solve_qp(prob, self.solver, x0, z0, prefer_exact=True, **opts)
        sol = solve_qp(prob, self.solver, x0, z0, **opts)
        self._adapt(prob, sol)
        return sol

    def _exact_path(self, n_vars: int) -> bool:
        """Whether a call on ``n_vars`` variables takes the exact path first (small, or a switch on; counted down)."""
        if self._on_exact_path(n_vars):
            self._exact_steps = max(self._exact_steps - 1, 0)
            return True
        return False

    def _on_exact_path(self, n_vars: int) -> bool:
        return self.exact_first or self._exact_steps > 0 or n_vars <= EXACT_FIRST_VARS

    def _count(self, prob: QPProblem, sol: QPSolution) -> None:
        """The switch state after a call the active set answered without :meth:`_solve` (as if through it)."""
        if self.backend.may_stall and not self._exact_path(prob.n):
            self._adapt(prob, sol)

    def needs_problem(self, n_vars: int, solve_time: float) -> bool:
        """Whether noting a verified answer of ``n_vars`` variables taking ``solve_time`` s needs the problem.

        True where :meth:`solve` would probe ``ldp`` on it (:meth:`_adapt`: a slow answer
        outside the exact path, small enough for ``ldp``); no state changes.
        """
        return (self.backend.may_stall and not self._on_exact_path(n_vars) and solve_time > SLOW_SOLVE_S
                and n_vars <= LDP_MAX_VARS)

    def note_answer(self, n_vars: int, solve_time: float) -> None:
        """The switch state after the warm active set answered a problem of ``n_vars`` variables elsewhere.

        For a caller that runs the warm active set itself (the compiled decomposition,
        :mod:`aasoatt_env.safety.decomposition`, whose ``solve_time`` is its whole call):
        the state :meth:`solve` would have left.  Where :meth:`needs_problem`, the caller
        must call :meth:`solve` instead (``UsageError`` here).
        """
        if self.needs_problem(n_vars, solve_time):
            raise UsageError("note_answer: this answer needs the problem for ldp's timing probe; call solve()")
        if self.backend.may_stall and not self._exact_path(n_vars) and solve_time <= SLOW_SOLVE_S:
            self._stalls = 0  # (_adapt of a fast answer without a stall; a slow one beyond ldp's size changes nothing)

    def _adapt(self, prob: QPProblem, sol: QPSolution) -> None:
        """Switch to the exact path if the back-end stalled, or was slow where ``ldp`` is faster.

        A stall (``sol.fallback``) switches at once; a solve slower than
        :data:`SLOW_SOLVE_S` switches only if ``ldp`` solves the same problem in
        less than half the time (its answer, exact too, is discarded).  The
        switch lasts ``EXACT_STEPS * 2**k`` calls, ``k`` the number of switches
        since the back-end last ran fast.
        """
        switch = sol.fallback
        if not switch and sol.solve_time > SLOW_SOLVE_S and prob.n <= LDP_MAX_VARS:
            probe = solve_qp(prob, "ldp")
            switch = probe.status == "solved" and probe.solve_time < 0.5 * sol.solve_time
        if switch:
            self._exact_steps = EXACT_STEPS * 2 ** min(self._stalls, 4)
            self._stalls += 1
        elif sol.solve_time <= SLOW_SOLVE_S:
            self._stalls = 0


def _nonneg(z: np.ndarray | None, m: int) -> np.ndarray:
    if z is None or z.shape[0] != m or not np.all(np.isfinite(z)):
        return np.zeros(m)
    return np.maximum(z, 0.0)


def _unconstrained(prob: QPProblem) -> np.ndarray:
    gb = prob.g.reshape(-1, 2)
    return -np.linalg.solve(prob.H_blocks, gb[..., None])[..., 0].ravel()
