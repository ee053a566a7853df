"""QP solvers of the safety filter: the back-end registry and the one solver policy.

* :mod:`~aasoatt_env.safety.solvers.backends`: one function per back-end and the
  registry :data:`SOLVERS` (adding a solver: one function, one registry line);
* :mod:`~aasoatt_env.safety.solvers.policy`: :func:`solve_qp` and
  :class:`SolverPolicy`, everything about fallbacks, infeasibility and path switching;
* :mod:`~aasoatt_env.safety.solvers.active_set`, :mod:`~aasoatt_env.safety.solvers.ldp`:
  the exact solvers that need only the core dependencies.
"""

from aasoatt_env.safety.solvers.backends import SOLVERS, Backend, RawAnswer, available_solvers, get_solver
from aasoatt_env.safety.solvers.policy import EXACT_STEPS, SLOW_SOLVE_S, QPSolution, SolverPolicy, solve_qp

__all__ = [
    "EXACT_STEPS",
    "SLOW_SOLVE_S",
    "SOLVERS",
    "Backend",
    "QPSolution",
    "RawAnswer",
    "SolverPolicy",
    "available_solvers",
    "get_solver",
    "solve_qp",
]
