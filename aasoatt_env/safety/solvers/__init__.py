"""QP solvers of the safety filter: the back-ends (:mod:`~.backends`) and which answers (:mod:`~.policy`).

The exact solvers of the core dependencies are :mod:`~.active_set` and the ``ldp`` back-end; :mod:`~.local` solves
every robot's 2-variable QP at once (the decentralised filter).
"""

from aasoatt_env.safety.solvers.backends import SOLVERS, Backend, RawAnswer, available_solvers, get_solver
from aasoatt_env.safety.solvers.policy import EXACT_ROUTE, PHASE1_ROUTE, QPSolution, SolverPolicy, route, solve_qp

__all__ = ["EXACT_ROUTE", "PHASE1_ROUTE", "SOLVERS", "Backend", "QPSolution", "RawAnswer", "SolverPolicy",
           "available_solvers", "get_solver", "route", "solve_qp"]
