"""The safety layer: barrier rows, deadlock strategies, QP solvers, the backup layer, the filter and its wrapper.

>>> from aasoatt_env.safety import SafetyFilter
>>> f = SafetyFilter(team)                    # doctest: +SKIP
>>> du, info = f.step(kin, u, theta, du_nom, lo, hi, reference=(p_d, v_d))  # doctest: +SKIP

The core (:mod:`~aasoatt_env.safety.core`) needs no environment; the wrapper
(:mod:`~aasoatt_env.safety.wrapper`) installs it into one through :mod:`aasoatt_env.sim.protocol`.
"""

from __future__ import annotations

from aasoatt_env.safety.barriers import BARRIERS, get_barrier
from aasoatt_env.safety.config import FilterConfig, auto_margin
from aasoatt_env.safety.core import SafetyFilter
from aasoatt_env.safety.deadlock import STRATEGIES, TRIGGERS
from aasoatt_env.safety.problem import build_problem
from aasoatt_env.safety.result import STATUSES, FilterResult
from aasoatt_env.safety.rows import Pairs, Rows
from aasoatt_env.safety.solvers import SOLVERS, SolverPolicy, available_solvers, solve_qp
from aasoatt_env.safety.warm_up import warm_up
from aasoatt_env.safety.wrapper import AASOATTFilter, FilterReport

__all__ = ["BARRIERS", "SOLVERS", "STATUSES", "STRATEGIES", "TRIGGERS", "AASOATTFilter", "FilterConfig",
           "FilterReport", "FilterResult", "Pairs", "Rows", "SafetyFilter", "SolverPolicy", "auto_margin",
           "available_solvers", "build_problem", "get_barrier", "solve_qp", "warm_up"]
