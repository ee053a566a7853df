"""QP solvers of the safety filter.

* :mod:`~aasoatt_env.safety.solvers.backends`: one function per back-end and the registry
  :data:`SOLVERS` (adding a solver: one function, one registry line);
* :mod:`~aasoatt_env.safety.solvers.policy`: :class:`SolverPolicy`, which solver answers which
  problem (a pure function of its size and the configuration), infeasibility and relaxation;
* :mod:`~aasoatt_env.safety.solvers.active_set`, :mod:`~aasoatt_env.safety.solvers.ldp`: the exact
  solvers of the core dependencies; :mod:`~aasoatt_env.safety.solvers.local`: every robot's
  2-variable QP at once (the decentralised filter).
"""

from aasoatt_env.safety.solvers.backends import SOLVERS, Backend, RawAnswer, available_solvers, get_solver
from aasoatt_env.safety.solvers.policy import EXACT_ROUTE, PHASE1_ROUTE, QPSolution, SolverPolicy, route, solve_qp

__all__ = ["EXACT_ROUTE", "PHASE1_ROUTE", "SOLVERS", "Backend", "QPSolution", "RawAnswer", "SolverPolicy",
           "available_solvers", "get_solver", "route", "solve_qp"]
