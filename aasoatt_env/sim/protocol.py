"""The contract between the environment and a per-physics-step control filter.

The environment never needs to know what a filter does (as in Robotarium, where a barrier
certificate is a function of the state and the nominal input).  At every physics step
(also between two decisions of the policy) the env computes the nominal wheel
accelerations ``du_nominal (N, 2)`` from the held actions, hands the filter a
:class:`FilterInput` and ``du_nominal``, receives a :class:`FilterOutput`, clips the applied
``du`` to the step's input bounds (a filter with ``keeps_input_bounds = True`` never needs
it) and integrates.  It calls :meth:`ControlFilter.reset` with the episode's team in
``reset`` (and when a filter is installed into an env that has one), keeps the outputs of
the last env step (``filter_outputs``) and reads only their ``correction`` (the reward)
and ``avoiding`` (rendering).

Several teams in one call (optional): :class:`~aasoatt_env.sim.batched.BatchedAASOATTEnv`
asks the teams' filters for ``grouped(filters)`` (:class:`GroupableFilter`); a filter it
returns (:class:`GroupedControlFilter`) is called once per physics step with all teams
stacked: ``inp.team.group`` labels each robot's team and ``inp.obstacle_groups`` each
obstacle's, and no pair across teams may affect the answer.  ``inp.reference`` holds every
team's reference at its own time; ``inp.time`` is team 0's.
"""

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

    Attributes
    ----------
    time, dt : float
        Simulated time at the start of the step and the physics step [s].
    team : Team
        Robot parameters.
    pose, u : numpy.ndarray
        Axle poses ``(N, 3)`` (``x, y, theta``) and wheel speeds ``(N, 2)``.
    kin : Kinematics
        Control points, velocities, ``A`` and ``A_dot u`` of the team.
    lo, hi : numpy.ndarray
        Bounds ``(N, 2)`` on this step's wheel accelerations (acceleration and speed limits).
    reference : tuple of numpy.ndarray
        ``(p_d, v_d, a_d)``, each ``(N, 2)``, at ``time``.
    obstacle_centers, obstacle_radii : numpy.ndarray
        Static disc obstacles ``(M, 2)`` and ``(M,)``.
    obstacle_groups : numpy.ndarray or None
        Grouped input only: the team of each obstacle ``(M,)``.
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
    """What a control filter returns for one physics step (any object with these attributes)."""

    du: np.ndarray
    """Wheel accelerations to apply ``(N, 2)``, finite."""
    correction: np.ndarray
    """``|du - du_nominal|`` per robot ``(N,)``."""
    avoiding: np.ndarray
    """``(N,)`` bool: the robot is in collision avoidance at this step."""


@runtime_checkable
class ControlFilter(Protocol):
    """A per-physics-step map from the nominal wheel accelerations to applied ones."""

    keeps_input_bounds: bool
    """True when every ``du`` it returns lies within ``[lo, hi]`` whatever the nominal;
    the env then accepts actions outside ``[-1, 1]`` as the (unclipped) nominal."""

    def reset(self, team: Team) -> None:
        """Start an episode of ``team`` (forget warm starts and memory)."""
        ...

    def __call__(self, inp: FilterInput, nominal_du: np.ndarray) -> FilterOutput:
        """Filter one physics step."""
        ...


@runtime_checkable
class GroupedControlFilter(ControlFilter, Protocol):
    """A control filter of ``K`` independent teams stacked into one input (module docstring)."""

    def reset_rows(self, rows: np.ndarray, team: Team) -> None:
        """Forget the memory of robots ``rows`` (their team starts an episode); ``team``: the new stack."""
        ...


@runtime_checkable
class GroupableFilter(ControlFilter, Protocol):
    """A control filter that can stand in for itself and other teams' filters in one call."""

    def grouped(self, filters: Sequence[ControlFilter]) -> GroupedControlFilter | None:
        """One filter for the stack of the teams of ``filters`` (this one among them), or None if it cannot."""
        ...
