"""Which solver answers a safety QP: a pure function of the problem's size and the configuration.

:meth:`SolverPolicy.solve` never raises on numerical trouble, never returns NaN, reads no clock, keeps no state: without
rows the closed form; ``neural``'s point as it is; the warm active set where it verifies; else the route (:func:`route`,
exact solvers first, answers taken verified).  Infeasibility is never an iterative solver's word: phase 1 finds each
row's least violation (bounds hard), the rows are loosened by it and the QP solved again (status ``"relaxed"``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp

from aasoatt_env.model.portable import solve2
from aasoatt_env.safety.problem import QPProblem
from aasoatt_env.safety.solvers.active_set import (
    VERIFIED_MESSAGE,
    ActiveSetParts,
    solve_active_set,
    solve_active_set_parts,
)
from aasoatt_env.safety.solvers.backends import LDP_MAX_VARS, RawAnswer, available_solvers, get_solver

__all__ = ["EXACT_ROUTE", "PHASE1_REG", "PHASE1_ROUTE", "REST_CHUNK", "SEVERITY", "QPSolution", "SolverPolicy", "route",
           "solve_qp"]

_FEAS_TOL = 1e-7
SEVERITY: tuple[str, ...] = ("solved", "relaxed", "failed")  #: :attr:`QPSolution.status`, from best to worst
#: most variables of one problem of the parts the warm active set left (whole parts; their cost grows faster than size)
REST_CHUNK: int = 128
PHASE1_REG: float = 1e-8  #: phase 1's weight of ``0.5 |x|^2`` beside the violations' ``0.5 |s|^2`` (a unique point)

#: ``(solver, most variables)`` asked first, where installed, before a back-end that may stall (exact, or a proof)
EXACT_ROUTE: tuple[tuple[str, int], ...] = (("daqp", 500), ("ldp", LDP_MAX_VARS))
#: ``(solver, fewest, most variables)`` of a phase-1 problem (``ldp``'s NNLS is badly conditioned on large ones)
PHASE1_ROUTE: tuple[tuple[str, int, int], ...] = (("daqp", 0, 1600), ("clarabel", 121, 10**9), ("ldp", 0, 120))


@dataclass
class QPSolution:
    """A :meth:`SolverPolicy.solve` answer in scaled coordinates."""

    x: np.ndarray
    z: np.ndarray
    status: str  #: ``"solved"``, ``"relaxed"`` (rows loosened by ``slack``) or ``"failed"``
    slack: float
    iterations: int
    message: str  #: which solver answered, and why
    exact: bool = True  #: False where an approximate back-end answered (its point is not verified)


def route(solver: str, n: int) -> list[tuple[str, dict]]:
    """The solvers asked for a problem of ``n`` variables with back-end ``solver``, in order, with their options."""
    installed, stall = available_solvers(), get_solver(solver).may_stall  # the exact solvers go before a staller
    steps = [(k, dict(get_solver(k).route_options)) for k, top in EXACT_ROUTE if stall and n <= top and k in installed]
    return [*steps, (solver, {})]


def _phase1_order(solver: str, n1: int) -> list[str]:
    """The solvers of a phase-1 problem of ``n1`` variables (:data:`PHASE1_ROUTE`), each once, installed."""
    installed = available_solvers()
    preferred = [k for k, lo, hi in PHASE1_ROUTE if lo <= n1 <= hi]
    order = ([*preferred, solver] if get_solver(solver).may_stall else [solver, *preferred])
    order += ["ldp"] if n1 <= LDP_MAX_VARS else []
    return [k for k in dict.fromkeys(order) if k in installed]


@dataclass(frozen=True)
class SolverPolicy:
    """The safety QP's solver (module docstring): a back-end and how the exact path runs."""

    solver: str  #: a name in :data:`~.backends.SOLVERS`
    active_set: bool = True  #: try the warm active set first
    compiled: bool = False  #: the warm active set by its compiled kernel
    one_change_iter: int | None = None  #: the warm active set's one-change budget (None: its default)
    iterations: int = 1  #: ``neural``'s projected primal-dual updates per call

    @property
    def exact(self) -> bool:
        """Whether the back-end's answers are exact."""
        return get_solver(self.solver).exact

    def solve(self, prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None,
              groups: np.ndarray | None = None, relaxed: bool = False) -> QPSolution:
        """Solve ``prob`` from ``(x0, z0)``; ``groups`` ``(N,)``: independent parts; ``relaxed``: phase 1 first."""
        backend = get_solver(self.solver)
        if prob.m == 0 and prob.diagonal and backend.exact:
            return QPSolution(np.clip(_unconstrained(prob), prob.lb, prob.ub), np.zeros(0), "solved", 0.0, 0, "no rows")
        if not backend.exact:
            raw = backend(prob, x0, z0, {"iterations": self.iterations})
            return QPSolution(raw.x, _nonneg(raw.z, prob.m), "solved", 0.0, raw.iterations, raw.message, exact=False)
        if not (self.active_set and x0 is not None and z0 is not None):
            return self._routed(prob, x0, z0, relaxed)
        part = solve_active_set_parts(prob, x0, z0, groups, compiled=self.compiled,
                                      one_change_iter=self.one_change_iter)
        if part is None or not part.ok.any():
            sol = self._routed(prob, x0, z0, relaxed)
            sol.iterations += 0 if part is None else part.iterations
            return sol
        if part.ok.all():
            return QPSolution(part.x, part.z, "solved", 0.0, part.iterations, VERIFIED_MESSAGE)
        return self._rest(prob, x0, z0, groups, part, relaxed)

    def _rest(self, prob: QPProblem, x0: np.ndarray, z0: np.ndarray, groups: np.ndarray,
              part: ActiveSetParts, relaxed: bool) -> QPSolution:
        """The parts the active set verified, and the route's answers on the others.

        In chunks of whole parts of at most :data:`REST_CHUNK` variables (a larger part alone): small problems for
        the exact solvers and phase 1.
        """
        bad = np.flatnonzero(~part.ok)
        size = 2 * np.bincount(groups, minlength=part.ok.shape[0])[bad]
        chunk = np.zeros(part.ok.shape[0], dtype=np.intp)
        chunk[bad] = _chunks(size, REST_CHUNK)
        x, z = part.x.copy(), part.z.copy()
        answers = []
        for c in range(int(chunk[bad].max()) + 1):
            mine = ~part.ok & (chunk == c)
            robots, rows = mine[groups], mine[part.row_group]
            v = np.repeat(robots, 2)
            rest = self._routed(prob.restrict(robots, rows), x0[v], z0[rows], relaxed)
            x[v], z[rows] = rest.x, rest.z
            answers.append(rest)
        worst = max(answers, key=lambda a: SEVERITY.index(a.status))
        return QPSolution(x, z, worst.status, max(a.slack for a in answers),
                          part.iterations + sum(a.iterations for a in answers),
                          f"{VERIFIED_MESSAGE} on {int(part.ok.sum())} of {part.ok.shape[0]} parts; the other "
                          f"{bad.shape[0]}" + (f" in {len(answers)} chunks" if len(answers) > 1 else "")
                          + f": {worst.message}")

    def _ask(self, prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None, loosened: bool = False) -> RawAnswer:
        """The route's first verified answer (``loosened``: its first solver's), or the last answer, not ok.

        The configured back-end's answer is taken unverified where it is deterministic; another's only verified.
        """
        steps = route(self.solver, prob.n)[:1] if loosened else route(self.solver, prob.n)
        raw, iterations, notes = RawAnswer(None, None, False, 0, ""), 0, []
        for name, opts in steps:
            backend = get_solver(name)
            raw = backend(prob, x0, z0, opts)
            iterations += raw.iterations
            configured = name == self.solver
            if raw.ok and not backend.verified and (not configured or not backend.deterministic):
                polished = solve_active_set(prob, raw.x, _nonneg(raw.z, prob.m), compiled=self.compiled)
                if polished is not None:
                    raw.x, raw.z, raw.message = polished[0], polished[1], raw.message + " (KKT verified)"
                elif not configured:
                    raw.ok, raw.message = False, raw.message + ", KKT check failed"
            notes.append(raw.message)
            if raw.ok or raw.infeasible:
                break
        raw.iterations, raw.message = iterations, ", then ".join(notes)
        return raw

    def _routed(self, prob: QPProblem, x0: np.ndarray | None, z0: np.ndarray | None,
                phase1_first: bool = False) -> QPSolution:
        """The route's answer, else phase 1 and the loosened problem (``phase1_first``: phase 1 before the route)."""
        p1 = _phase1(prob, self.solver) if phase1_first else None
        if p1 is None or float(np.max(p1[1], initial=0.0)) <= _FEAS_TOL:  # (not asked, failed, or consistent rows)
            raw = self._ask(prob, x0, z0)
        else:
            raw = RawAnswer(None, None, False, 0, "phase 1 first (the previous step was relaxed)")
        if raw.ok:
            return QPSolution(raw.x, _nonneg(raw.z, prob.m), "solved", 0.0, raw.iterations, raw.message)
        if not phase1_first:
            p1 = _phase1(prob, self.solver)
        if p1 is None:
            return QPSolution(np.clip(_unconstrained(prob), prob.lb, prob.ub), np.zeros(prob.m), "failed", 0.0,
                              raw.iterations, f"{raw.message}; phase 1 failed too")
        x1, viol = p1
        tstar = float(np.max(viol, initial=0.0))
        relaxed = tstar > _FEAS_TOL
        # the loosened QP by the route's first solver only (others spend their budgets on these degenerate problems)
        raw2 = self._ask(replace(prob, u=prob.u + viol * (1.0 + 1e-6) + _FEAS_TOL), x0, z0, loosened=True)
        msg = f"{raw.message}; phase 1: largest row violation {tstar:.3g} ({int(np.sum(viol > _FEAS_TOL))} rows)"
        status = "relaxed" if relaxed else "solved"
        if raw2.ok:
            return QPSolution(raw2.x, _nonneg(raw2.z, prob.m), status, tstar if relaxed else 0.0,
                              raw.iterations + raw2.iterations, msg)
        return QPSolution(x1, np.zeros(prob.m), "relaxed", tstar, raw.iterations + raw2.iterations,
                          msg + "; the loosened problem failed, the phase-1 point returned")


def _chunks(size: np.ndarray, most: int) -> np.ndarray:
    """Each part's chunk: consecutive parts of ``size`` variables, a chunk at most ``most`` (a larger part alone)."""
    chunk, total, out = 0, 0, np.zeros(size.shape[0], dtype=np.intp)
    for k, s in enumerate(size.tolist()):  # (the parts the active set left: few)
        if total and total + s > most:
            chunk, total = chunk + 1, 0
        out[k], total = chunk, total + s
    return out


def solve_qp(prob: QPProblem, solver: str = "proxsuite", x0: np.ndarray | None = None, z0: np.ndarray | None = None,
             **options: object) -> QPSolution:
    """One QP: ``SolverPolicy(solver, **options).solve(prob, x0, z0)`` (warm active set off by default)."""
    options.setdefault("active_set", False)
    return SolverPolicy(solver, **options).solve(prob, x0, z0)  # type: ignore[arg-type]


def _phase1(prob: QPProblem, solver: str) -> tuple[np.ndarray, np.ndarray] | None:
    """The point and row violations ``s* >= 0`` of ``min 0.5 |s|^2 + 0.5 reg |x|^2  s.t.  C x - s <= u`` (bounds hard).

    One slack per row: a hopeless row (a pair inside ``d_s``) is loosened alone.  None if no solver answers.
    """
    n, m = prob.n, prob.m
    slacked = None
    for name in _phase1_order(solver, n + m + m % 2):
        backend = get_solver(name)
        # (only the point's recomputed violations are used: an unpolished exact point is accepted looser)
        opts = {"ldp_feas_tol": 1e-6, **({} if name == solver else dict(backend.route_options))}
        if backend.least_violation is not None:
            raw = backend.least_violation(prob, PHASE1_REG, opts)
        else:
            slacked = _slacked(prob) if slacked is None else slacked
            raw = backend(slacked, None, None, opts)
        if raw.ok and raw.x is not None and np.all(np.isfinite(raw.x[:n])):
            x = np.clip(raw.x[:n], prob.lb, prob.ub)
            return x, np.maximum(prob.C @ x - prob.u, 0.0)
    return None


def _slacked(prob: QPProblem) -> QPProblem:
    """:func:`_phase1`'s problem with its slack variables (2x2 Hessian blocks: a padding variable fixed at 0)."""
    n, m = prob.n, prob.m
    pad = m % 2
    ns = m + pad
    Hb = np.concatenate((np.broadcast_to(np.eye(2) * PHASE1_REG, (n // 2, 2, 2)),
                         np.broadcast_to(np.eye(2), (ns // 2, 2, 2))))
    C = sp.hstack([prob.C, -sp.identity(m, format="csr")] + ([sp.csr_matrix((m, 1))] if pad else []), format="csr")
    ub = np.concatenate((prob.ub, np.full(m, 1e6), np.zeros(pad)))
    return QPProblem(Hb, np.zeros(n + ns), C, prob.u, np.concatenate((prob.lb, np.zeros(ns))), ub, np.ones(n + ns),
                     1.0, np.ones(m), True)


def _nonneg(z: np.ndarray | None, m: int) -> np.ndarray:
    if z is None or z.shape[0] != m or not np.all(np.isfinite(z)):
        return np.zeros(m)
    return np.maximum(z, 0.0)


def _unconstrained(prob: QPProblem) -> np.ndarray:
    return -solve2(prob.H_blocks, prob.g.reshape(-1, 2)).ravel()
