"""The paper's experiments (Sec. V): the tables (:mod:`.tables`) and the figures without a table (:mod:`.figures`)."""

from __future__ import annotations

from aasoatt_env.apps.reproduce.experiments.figures import DeadlockTriggers, Obstacles, Swarm100
from aasoatt_env.apps.reproduce.experiments.tables import CompareCA, Table1, Table2, Table3
from aasoatt_env.apps.reproduce.report import Experiment, Settings

__all__ = ["EXPERIMENTS", "Settings"]

#: Name -> experiment, in the order ``all`` runs them.
EXPERIMENTS: dict[str, Experiment] = {e.name: e for e in (Table1(), CompareCA(), Table2(), DeadlockTriggers(),
                                                          Table3(), Swarm100(), Obstacles())}
