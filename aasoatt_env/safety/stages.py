"""What the stages of one filter step hand each other (:mod:`aasoatt_env.safety.core`).

:class:`StepInput` -> :class:`~.rows.Pairs` -> the deadlock trigger and target -> :class:`~.rows.Rows` ->
:class:`Answer` (the QP, warm-started from :class:`Warm`) -> the backup check -> :class:`~.result.FilterResult`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from aasoatt_env.model.params import Team

__all__ = ["BACKUP", "GROUPED", "RELAXED", "UNSAFE", "Answer", "StepInput", "Warm"]

#: per-robot ``flags`` bits (0: the robot's answer is its own QP's optimum): ``RELAXED`` its QP, or its negotiation
#: group's, was infeasible (rows loosened); ``GROUPED`` answered by its negotiation group; ``BACKUP`` braked by the
#: backup layer; ``UNSAFE`` the backup layer found it outside the safe set
RELAXED, GROUPED, BACKUP, UNSAFE = 1, 2, 4, 8


class StepInput(NamedTuple):
    """One step's checked inputs (float64; shapes checked; bounds tightened by a wheel-speed limit)."""

    team: Team
    p: np.ndarray  #: ``(N, 2)`` control points
    v: np.ndarray  #: ``(N, 2)`` their velocities
    A: np.ndarray  #: ``(N, 2, 2)`` input matrices: ``a = A du + adot``
    adot: np.ndarray  #: ``(N, 2)`` drift accelerations ``A_dot u``
    u: np.ndarray  #: ``(N, 2)`` wheel speeds
    theta: np.ndarray  #: ``(N,)`` headings
    nominal: np.ndarray  #: ``(N, 2)`` nominal wheel accelerations
    lo: np.ndarray  #: ``(N, 2)`` bounds on ``du``
    hi: np.ndarray  #: ``(N, 2)``
    reference: tuple[np.ndarray, np.ndarray] | None  #: ``(p_d, v_d)`` or None
    obstacles: tuple[np.ndarray, np.ndarray, np.ndarray | None] | None  #: ``(centres, radii, groups or None)``
    scale: np.ndarray  #: ``(N,)`` of the QP's variables ``x = du / scale`` (the largest bound)
    near: bool = False  #: every nominal within :func:`~.inputs.bound_nominal`'s reach, known (False: not known)


class Warm(NamedTuple):
    """The previous step's answer mapped onto this step's rows (the QP's warm start; None on a first step)."""

    x: np.ndarray | None  #: ``(N, 2)`` scaled point
    z: np.ndarray | None  #: ``(m,)`` scaled row multipliers (0 on rows new at this step)
    #: try the compiled solve first (not where it failed at this step already, nor after a step it did not answer)
    compiled: bool = True
    relaxed: bool = False  #: the previous step's rows were inconsistent (its status ``"relaxed"``): phase 1 first


class Answer(NamedTuple):
    """The QP stage's answer (``x`` and ``z`` are the next step's warm start)."""

    du: np.ndarray  #: ``(N, 2)`` within the bounds
    x: np.ndarray  #: ``(N, 2)`` scaled point
    z: np.ndarray  #: ``(m,)`` scaled row multipliers
    eta: np.ndarray  #: ``(m,)`` in the units of eqn.8
    avoiding: np.ndarray  #: ``(N,)`` the robot has a binding row (a multiplier above ``eta_tol``)
    status: str  #: ``"solved"``, ``"relaxed"`` or ``"failed"``
    message: str  #: which solver answered
    iterations: int
    n_qp: int  #: rows the QP solver saw (0 where the closed form answered)
    slack: float  #: largest violation of a row by ``du`` (0 where solved exactly)
    #: the closed form or the warm active set answered every part (the next step tries the compiled solve first)
    warm_verified: bool = False
    flags: np.ndarray | None = None  #: ``(N,)`` :data:`RELAXED`/:data:`GROUPED` bits (decentralised mode)
