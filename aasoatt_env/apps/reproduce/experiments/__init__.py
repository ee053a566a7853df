"""The paper's experiments (Sec. V), each an :class:`~aasoatt_env.apps.reproduce.report.Experiment`.

Tables (:mod:`.tables`): ``table1``, ``compare-ca``, ``table2``, ``table3``; figures without a table
(:mod:`.figures`): ``deadlock-triggers``, ``swarm100``, ``obstacles``; their shared set-up: :mod:`.common`.
"""

from __future__ import annotations

from aasoatt_env.apps.reproduce.experiments.figures import DeadlockTriggers, Obstacles, Swarm100
from aasoatt_env.apps.reproduce.experiments.tables import CompareCA, Table1, Table2, Table3
from aasoatt_env.apps.reproduce.report import Experiment, Settings

__all__ = ["EXPERIMENTS", "Settings"]

EXPERIMENTS: dict[str, Experiment] = {e.name: e for e in (Table1(), CompareCA(), Table2(), DeadlockTriggers(),
                                                          Table3(), Swarm100(), Obstacles())}
"""Experiment registry: name -> experiment, in the order ``all`` runs them."""
