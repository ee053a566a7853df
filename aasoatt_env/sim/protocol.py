"""The contract between the environment and a per-physics-step control filter.

The environment never needs to know what a filter does (as in Robotarium, where
a barrier certificate is a function of the state and the nominal input).  At
every physics step of ``dt`` seconds, also between two decisions of the
policy, :class:`~aasoatt_env.sim.env.AASOATTParallelEnv`:

1. computes the nominal wheel accelerations ``du_nominal (N, 2)`` from the
   held actions;
2. hands the filter a :class:`FilterInput` (the state of this physics step) and
   ``du_nominal``;
3. receives a :class:`FilterOutput`: the wheel accelerations to apply, and per
   robot the size of the change and whether the robot is avoiding a collision;
4. clips the applied ``du`` to the step's input bounds (a filter that keeps
   them, ``keeps_input_bounds = True``, never needs it) and integrates.

The env calls :meth:`ControlFilter.reset` with the episode's team in ``reset``
(and once when the filter is installed into an env that already has one).
It keeps the outputs of the physics steps of the last env step
(:attr:`~aasoatt_env.sim.env.AASOATTParallelEnv.filter_outputs`); it uses only
``correction`` (the reward's correction term) and ``avoiding`` (highlighting
when rendering), and a wrapper reads the rest.  Install a filter with
:meth:`~aasoatt_env.sim.env.AASOATTParallelEnv.set_control_filter`;
:class:`aasoatt_env.safety.wrapper.AASOATTFilter` does this for its
:class:`~aasoatt_env.safety.core.SafetyFilter`.

Several teams in one call (optional).  :class:`~aasoatt_env.sim.batched.BatchedAASOATTEnv`
steps ``K`` independent teams together.  If the teams' filters offer
``grouped(filters)`` (:class:`GroupableFilter`) and it returns a filter
(:class:`GroupedControlFilter`), the batch calls that one filter once per
physics step with all teams stacked: ``inp.team.group`` labels each robot's
team, ``inp.obstacle_groups`` each obstacle's, and no pair of robots (or robot
and obstacle) of different teams may affect the answer.  ``inp.reference``
holds every team's reference at its own time; ``inp.time`` is team 0's.  Else
the batch calls each team's filter with its own input.
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
    """The state the env hands a control filter at one physics step (arrays are read-only views).

    Attributes
    ----------
    time : float
        Simulated time at the start of the step [s].
    dt : float
        Physics step [s].
    team : Team
        Robot parameters.
    pose : numpy.ndarray
        Axle poses ``(N, 3)``: ``x, y, theta``.
    u : numpy.ndarray
        Wheel speeds ``(N, 2)`` (double integrator: velocity).
    kin : Kinematics
        Control points, velocities, ``A`` and ``A_dot u`` of the team.
    lo, hi : numpy.ndarray
        Bounds ``(N, 2)`` on the wheel accelerations of this step (the robots'
        acceleration bound, tightened by their wheel-speed limit).
    reference : tuple of numpy.ndarray
        ``(p_d, v_d, a_d)``, each ``(N, 2)``: the reference at ``time``.
    obstacle_centers : numpy.ndarray
        Static disc obstacles: centres ``(M, 2)``.
    obstacle_radii : numpy.ndarray
        Their radii ``(M,)``.
    obstacle_groups : numpy.ndarray or None
        Grouped input only: the team of each obstacle ``(M,)`` (module docstring).
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
