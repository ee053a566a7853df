"""QP solvers of the safety filter.

The back-ends and their registry (:mod:`~.backends`), which answers which problem (:mod:`~.policy`), the exact
solvers of the core dependencies (:mod:`~.active_set`, :mod:`~.ldp`) and every robot's 2-variable QP at once
(:mod:`~.local`, the decentralised filter).
"""

from aasoatt_env.safety.solvers.backends import SOLVERS, Backend, RawAnswer, available_solvers, get_solver
from aasoatt_env.safety.solvers.policy import EXACT_ROUTE, PHASE1_ROUTE, QPSolution, SolverPolicy, route, solve_qp

__all__ = ["EXACT_ROUTE", "PHASE1_ROUTE", "SOLVERS", "Backend", "QPSolution", "RawAnswer", "SolverPolicy",
           "available_solvers", "get_solver", "route", "solve_qp"]
