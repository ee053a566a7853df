"""Safety-filter core: CBF rows, QP solvers and deadlock resolution, independent of any environment.

>>> from aasoatt_env.safety import SafetyFilter
>>> f = SafetyFilter(team)                    # doctest: +SKIP
>>> du, info = f.step(kin, u, theta, du_nom, lo, hi, reference=(p_d, v_d))  # doctest: +SKIP
"""

from __future__ import annotations

from aasoatt_env.safety.barriers import BARRIERS, get_barrier
from aasoatt_env.safety.config import FilterConfig, auto_margin
from aasoatt_env.safety.core import FilterResult, SafetyFilter
from aasoatt_env.safety.deadlock import STRATEGIES, TRIGGERS
from aasoatt_env.model.geometry import obstacle_pairs, robot_pairs
from aasoatt_env.safety.solvers.policy import SOLVERS, available_solvers, build_problem, solve_qp

__all__ = [
    "BARRIERS",
    "SOLVERS",
    "STRATEGIES",
    "TRIGGERS",
    "FilterConfig",
    "FilterResult",
    "SafetyFilter",
    "auto_margin",
    "available_solvers",
    "build_problem",
    "get_barrier",
    "obstacle_pairs",
    "robot_pairs",
    "solve_qp",
]
