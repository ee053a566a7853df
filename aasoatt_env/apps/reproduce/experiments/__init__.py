"""The paper's experiments (Sec. V), each an :class:`~aasoatt_env.apps.reproduce.report.Experiment`.

=======================  ===============================================================================
experiment               what it reproduces
=======================  ===============================================================================
``table1``               Table I: single-robot tracking, SBC's PD law (k3 = 10, 80) vs ours (k3 = 1)
``compare-ca``           the N = 10 comparison of five CA methods (the inline 4-tuples, Fig. "reviewacc")
``table2``               Table II + Fig. 2: eqn.n4 vs ours, N = 20..39
``deadlock-triggers``    Fig. 3a: velocity profiles under four deadlock triggers
``table3``               Table III: deadlock strategies eqn.12a/12b/13, N = 20..60, radius 10, 20 s
``swarm100``             Fig. "100": 100 robots, the three strategies
``obstacles``            Fig. 5: 20 robots, 3 static obstacles
=======================  ===============================================================================

The set-up they share is in :mod:`~aasoatt_env.apps.reproduce.experiments.common`.
"""

from __future__ import annotations

from aasoatt_env.apps.reproduce.experiments.figures import DeadlockTriggers, Obstacles, Swarm100
from aasoatt_env.apps.reproduce.experiments.tables import CompareCA, Table1, Table2, Table3
from aasoatt_env.apps.reproduce.report import Experiment, Settings

__all__ = ["EXPERIMENTS", "Settings"]

EXPERIMENTS: dict[str, Experiment] = {e.name: e for e in (Table1(), CompareCA(), Table2(), DeadlockTriggers(),
                                                          Table3(), Swarm100(), Obstacles())}
"""Experiment registry: name -> experiment, in the order ``all`` runs them."""
