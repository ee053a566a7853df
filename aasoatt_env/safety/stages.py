"""What the stages of one filter step hand each other (:mod:`aasoatt_env.safety.core`).

``StepInput`` (the checked state) -> :class:`~aasoatt_env.safety.rows.Pairs` ->
deadlock trigger and target -> :class:`~aasoatt_env.safety.rows.Rows` -> :class:`Answer`
(the QP, centralised or decentralised, warm-started from :class:`Warm`) -> the backup check
-> :class:`~aasoatt_env.safety.result.FilterResult`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from aasoatt_env.model.params import Team

__all__ = ["Answer", "StepInput", "Warm"]


class StepInput(NamedTuple):
    """One step's checked inputs (float64; shapes checked; bounds tightened by a wheel-speed limit)."""

    team: Team
    p: np.ndarray
    """``(N, 2)`` control points."""
    v: np.ndarray
    """``(N, 2)`` their velocities."""
    A: np.ndarray
    """``(N, 2, 2)`` input matrices: ``a = A du + adot``."""
    adot: np.ndarray
    """``(N, 2)`` drift accelerations ``A_dot u``."""
    u: np.ndarray
    """``(N, 2)`` wheel speeds."""
    theta: np.ndarray
    """``(N,)`` headings."""
    nominal: np.ndarray
    """``(N, 2)`` nominal wheel accelerations."""
    lo: np.ndarray
    """``(N, 2)`` lower bounds on ``du``."""
    hi: np.ndarray
    """``(N, 2)`` upper bounds on ``du``."""
    reference: tuple[np.ndarray, np.ndarray] | None
    """``(p_d, v_d)`` or None."""
    obstacles: tuple[np.ndarray, np.ndarray, np.ndarray | None] | None
    """``(centres (M, 2), radii (M,), groups (M,) or None)`` or None."""
    scale: np.ndarray
    """``(N,)`` per-robot scale of the QP's variables ``x = du / scale`` (the largest bound)."""


class Warm(NamedTuple):
    """The previous step's answer, mapped onto this step's rows (the QP's warm start)."""

    x: np.ndarray | None
    """``(N, 2)`` scaled point, or None on a first step."""
    z: np.ndarray | None
    """``(m,)`` scaled row multipliers (0 on rows new at this step), or None."""


class Answer(NamedTuple):
    """The QP stage's answer."""

    du: np.ndarray
    """``(N, 2)`` wheel accelerations within the bounds."""
    x: np.ndarray
    """``(N, 2)`` scaled point (the next step's warm start)."""
    z: np.ndarray
    """``(m,)`` scaled multipliers of the rows (the next warm start)."""
    eta: np.ndarray
    """``(m,)`` multipliers in the units of eqn.8."""
    avoiding: np.ndarray
    """``(N,)`` the robot has a binding row (a multiplier above ``eta_tol``)."""
    status: str
    """``"solved"``, ``"relaxed"`` or ``"failed"``."""
    message: str
    """Which solver answered."""
    iterations: int
    n_qp: int
    """Rows the QP solver saw (0 where the closed form answered)."""
    slack: float
    """Largest violation of a row by ``du`` (0 where solved exactly)."""
