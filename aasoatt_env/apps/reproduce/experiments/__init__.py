"""The paper's experiments (Sec. V), one module each, every one a function ``Settings -> Report``.

=======================  ====================================================
experiment               what it reproduces
=======================  ====================================================
``table1``               Table I: single-robot tracking, SBC's PD law
                         (k3 = 10, 80) vs the paper's law (k3 = 1), k4 = 4
``compare-ca``           the N = 10 comparison of five CA methods (inline
                         4-tuples of Sec. V, Fig. "reviewacc")
``table2``               Table II + Fig. 2: eqn.n4 vs ours, N = 20..39
``deadlock-triggers``    Fig. 3a: velocity profiles under four triggers
``table3``               Table III: deadlock strategies eqn.12a/12b/13,
                         N = 20..60, radius 10, 20 s
``swarm100``             Fig. "100": 100 robots, the three strategies
``obstacles``            Fig. 5: 20 robots, 3 static obstacles
=======================  ====================================================

The shared set-up is documented in :mod:`~aasoatt_env.apps.reproduce.experiments.common`.
"""

from __future__ import annotations

from collections.abc import Callable

from aasoatt_env.apps.reproduce.experiments.common import Settings
from aasoatt_env.apps.reproduce.experiments.compare_ca import compare_ca
from aasoatt_env.apps.reproduce.experiments.deadlock_triggers import deadlock_triggers
from aasoatt_env.apps.reproduce.experiments.obstacles import obstacles
from aasoatt_env.apps.reproduce.experiments.swarm100 import swarm100
from aasoatt_env.apps.reproduce.experiments.table1 import table1
from aasoatt_env.apps.reproduce.experiments.table2 import table2
from aasoatt_env.apps.reproduce.experiments.table3 import table3
from aasoatt_env.apps.reproduce.report import Report

__all__ = ["EXPERIMENTS", "Settings"]

EXPERIMENTS: dict[str, Callable[[Settings], Report]] = {
    "table1": table1,
    "compare-ca": compare_ca,
    "table2": table2,
    "deadlock-triggers": deadlock_triggers,
    "table3": table3,
    "swarm100": swarm100,
    "obstacles": obstacles,
}
"""Experiment registry: name -> function."""
