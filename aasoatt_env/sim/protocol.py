"""The contract between the env and a per-physics-step control filter (``docs/env.md``)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from aasoatt_env.model.dynamics import Kinematics
from aasoatt_env.model.params import Team

__all__ = ["ControlFilter", "FilterInput", "FilterOutput", "GroupableFilter", "GroupedControlFilter"]


@dataclass(frozen=True)
class FilterInput:
    """The state the env hands a control filter at one physics step (arrays not to be changed).

    ``time`` [s] at the start of the step of ``dt`` [s]; axle ``pose (N, 3)`` (``x, y, theta``), wheel speeds
    ``u (N, 2)`` and their ``kin``; bounds ``lo``, ``hi`` ``(N, 2)`` on this step's wheel accelerations;
    ``reference`` ``(p_d, v_d, a_d)`` at ``time``; static discs ``(M, 2)``, ``(M,)`` (and, grouped, their teams).
    """

    time: float
    dt: float
    team: Team
    pose: np.ndarray
    u: np.ndarray
    kin: Kinematics
    lo: np.ndarray
    hi: np.ndarray
    reference: tuple[np.ndarray, np.ndarray, np.ndarray]
    obstacle_centers: np.ndarray
    obstacle_radii: np.ndarray
    obstacle_groups: np.ndarray | None = None

    @property
    def theta(self) -> np.ndarray:
        """Headings ``(N,)``."""
        return self.pose[:, 2]


@runtime_checkable
class FilterOutput(Protocol):
    """A filter's answer: finite ``du (N, 2)``, ``correction = |du - du_nominal| (N,)``, ``avoiding (N,)`` bool."""

    du: np.ndarray
    correction: np.ndarray
    avoiding: np.ndarray


@runtime_checkable
class ControlFilter(Protocol):
    """A per-physics-step map from nominal to applied wheel accelerations (``keeps_input_bounds``: in ``[lo, hi]``)."""

    keeps_input_bounds: bool

    def reset(self, team: Team) -> None:
        """Start an episode of ``team`` (forget warm starts and memory)."""

    def __call__(self, inp: FilterInput, nominal_du: np.ndarray) -> FilterOutput:
        """Filter one physics step."""


@runtime_checkable
class GroupedControlFilter(ControlFilter, Protocol):
    """A control filter of ``K`` teams stacked into one input (``team.group``, ``obstacle_groups``; ``docs/env.md``)."""

    def reset_rows(self, rows: np.ndarray, team: Team) -> None:
        """Forget the memory of robots ``rows`` (their team starts an episode); ``team``: the new stack."""


@runtime_checkable
class GroupableFilter(ControlFilter, Protocol):
    """A control filter that can stand in for itself and other teams' filters in one call."""

    def grouped(self, filters: Sequence[ControlFilter]) -> GroupedControlFilter | None:
        """One filter for the stack of the teams of ``filters`` (this one among them), or None if it cannot."""
