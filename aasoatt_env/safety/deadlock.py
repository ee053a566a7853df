"""Deadlock resolution: strategies (what changes) and triggers (when), both registries.

Strategies (``docs/technical_brief.md`` section 5) change the QP's target or the rows of triggered robots
(``rotate_relative_position`` is Zeno-prone: the filter warns; ``yield``: :mod:`.liveness`).  Triggers: ``multiplier``
(Algorithm 1: a row active at the previous step), ``low_speed``, ``stalled``, ``heading`` (pointing within
``heading_deg`` at the nearest neighbour or obstacle); all but ``heading`` spare robots done at their goals.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from aasoatt_env.safety.liveness import YieldMemory, yield_target

if TYPE_CHECKING:  # pragma: no cover
    from aasoatt_env.safety.config import FilterConfig

__all__ = ["STRATEGIES", "TRIGGERS", "TRIGGERS_WITHOUT_PAIRS", "DeadlockState", "Strategy", "TriggerContext",
           "rotation"]


def rotation(q_deg: float) -> np.ndarray:
    """Rotation matrix ``Q(q)`` (eqn.14) for ``q`` in degrees."""
    q = math.radians(q_deg)
    return np.array([[math.cos(q), -math.sin(q)], [math.sin(q), math.cos(q)]])


@dataclass
class DeadlockState:
    """The triggers' memory between steps."""

    avoiding: np.ndarray | None = None
    history: list[np.ndarray] = field(default_factory=list)
    liveness: YieldMemory | None = None  #: the ``yield`` strategy's memory


class TriggerContext(NamedTuple):
    """What a trigger sees at the start of a step."""

    p: np.ndarray  #: ``(N, 2)`` control points
    v: np.ndarray  #: ``(N, 2)`` their velocities
    theta: np.ndarray  #: ``(N,)`` headings
    reference: tuple[np.ndarray, np.ndarray] | None  #: ``(p_d, v_d)`` or None
    pair_idx: np.ndarray  #: ``(P, 2)`` pairs inside the sensing range; second column ``-1`` for obstacles
    pair_vec: np.ndarray  #: ``(P, 2)``: ``p_j - p_i`` (from robot ``i`` towards the other member)
    cfg: FilterConfig


TriggerFn = Callable[[DeadlockState, TriggerContext], np.ndarray]  #: ``(N,) bool``; may update the memory


def _not_done(state: DeadlockState, c: TriggerContext) -> np.ndarray:
    if c.reference is None:
        return state.avoiding if state.avoiding is not None else np.zeros(c.p.shape[0], dtype=bool)
    ell, v_d = c.p - c.reference[0], c.reference[1]
    return ((np.sqrt(v_d[:, 0] * v_d[:, 0] + v_d[:, 1] * v_d[:, 1]) >= c.cfg.low_speed)
            | (np.sqrt(ell[:, 0] * ell[:, 0] + ell[:, 1] * ell[:, 1]) > c.cfg.goal_tol))


def _multiplier(state: DeadlockState, c: TriggerContext) -> np.ndarray:
    return np.zeros(c.p.shape[0], dtype=bool) if state.avoiding is None else state.avoiding & _not_done(state, c)


def _low_speed(state: DeadlockState, c: TriggerContext) -> np.ndarray:
    return (np.linalg.norm(c.v, axis=1) < c.cfg.low_speed) & _not_done(state, c)


def _stalled(state: DeadlockState, c: TriggerContext) -> np.ndarray:
    dwell = max(1, int(round(c.cfg.stall_time / c.cfg.dt)))
    state.history.append(c.p.copy())
    if len(state.history) > dwell + 1:
        del state.history[0]
    if len(state.history) <= dwell:
        return np.zeros(c.p.shape[0], dtype=bool)
    moved = np.linalg.norm(c.p - state.history[0], axis=1)
    return (moved < c.cfg.stall_distance) & _not_done(state, c)


def _heading(state: DeadlockState, c: TriggerContext) -> np.ndarray:
    n = c.p.shape[0]
    out = np.zeros(n, dtype=bool)
    if c.pair_idx.shape[0] == 0:
        return out
    i, j = c.pair_idx[:, 0], c.pair_idx[:, 1]
    rob = j >= 0
    # each robot-robot pair is seen from both ends; obstacles only from the robot
    who = np.concatenate((i, j[rob]))
    vec = np.concatenate((c.pair_vec, -c.pair_vec[rob]))
    dist = np.linalg.norm(vec, axis=1)
    nearest = np.full(n, np.inf)
    np.minimum.at(nearest, who, dist)
    is_nearest = dist <= nearest[who]
    head = np.stack((np.cos(c.theta), np.sin(c.theta)), axis=1)[who]
    cosang = np.einsum("ij,ij->i", head, vec) / np.maximum(dist, 1e-12)
    hit = is_nearest & (cosang >= math.cos(math.radians(c.cfg.heading_deg)))
    out[who[hit]] = True
    return out


TRIGGERS: dict[str, TriggerFn] = {"multiplier": _multiplier, "low_speed": _low_speed, "stalled": _stalled,
                                  "heading": _heading}
"""Trigger registry: name -> ``trigger(memory, context)`` (adding one: a function and a line here)."""

#: triggers known to read no pairs (they get empty ``pair_idx``/``pair_vec``); any other, yours too, gets them
TRIGGERS_WITHOUT_PAIRS: frozenset[str] = frozenset({"multiplier", "low_speed", "stalled"})


class TargetContext(NamedTuple):
    """What a target correction sees (``TriggerContext``'s fields and the tracking gains; a stateful one more)."""

    v: np.ndarray
    p: np.ndarray
    reference: tuple[np.ndarray, np.ndarray] | None
    k3: float
    k4: float
    memory: DeadlockState | None = None  #: a stateful strategy's memory (the rest: a stateful strategy's too)
    robot_pairs: np.ndarray = np.zeros((0, 2), np.intp)  #: ``(P, 2)`` robot pairs in the sensing range
    obstacle_pairs: np.ndarray = np.zeros((0, 2), np.intp)  #: ``(Q, 2)`` ``(robot, obstacle)`` in the range
    obstacles: tuple[np.ndarray, np.ndarray] | None = None  #: ``(centres (M, 2), radii (M,))``
    radius: np.ndarray = np.zeros(0)  #: ``(N,)`` robot radii
    adot: np.ndarray = np.zeros((0, 2))  #: ``(N, 2)`` drift accelerations ``A_dot u``
    cfg: FilterConfig | None = None  #: the filter's configuration


def _rotate_nominal(target: np.ndarray, zeta: np.ndarray, Q: np.ndarray, c: TargetContext) -> np.ndarray:
    return np.where((zeta > 0)[:, None], target @ (np.eye(2) - Q).T, target)


def _rotate_reference_velocity(target: np.ndarray, zeta: np.ndarray, Q: np.ndarray, c: TargetContext) -> np.ndarray:
    return target - (c.k3 + c.k4) * zeta[:, None] * (c.reference[1] @ Q.T)  # type: ignore[index]


def _auxiliary_velocity(target: np.ndarray, zeta: np.ndarray, Q: np.ndarray, c: TargetContext) -> np.ndarray:
    p_d, v_d = c.reference  # type: ignore[misc]
    e = c.v - v_d + c.k3 * (c.p - p_d)
    return target - zeta[:, None] * (e @ Q.T)


@dataclass(frozen=True)
class Strategy:
    """A deadlock strategy: how it changes the target acceleration and/or the rows."""

    equation: str  #: the paper's label
    #: ``target(target, zeta, Q, context) -> new target`` for the triggered robots (None: unchanged)
    target: Callable[[np.ndarray, np.ndarray, np.ndarray, TargetContext], np.ndarray] | None = None
    rotates_rows: bool = False  #: it rotates ``p_ij`` in the rows of triggered pairs (eqn.12c)
    needs_reference: bool = False  #: ``reference=(p_d, v_d)`` is required
    #: it runs at every step, on every robot (``zeta`` 0 where untriggered), with memory, pairs and radii
    stateful: bool = False

    @property
    def active(self) -> bool:
        """False for the ``none`` strategy (no trigger is evaluated)."""
        return self.target is not None or self.rotates_rows

    def correct_target(self, target: np.ndarray, zeta: np.ndarray, Q: np.ndarray, ctx: TargetContext) -> np.ndarray:
        """The target control-point accelerations after the strategy (a new array)."""
        if self.target is None or not (self.stateful or (zeta > 0).any()):
            return target.copy()
        return self.target(target, zeta, Q, ctx)

    def rotate_rows(self, geo_p: np.ndarray, on: np.ndarray, Q: np.ndarray) -> np.ndarray:
        """Relative positions of the rows after the strategy (``on``: rows with a triggered member)."""
        if not self.rotates_rows or not np.any(on):
            return geo_p
        return np.where(on[:, None], geo_p @ (np.eye(2) - Q).T, geo_p)


STRATEGIES: dict[str, Strategy] = {
    "none": Strategy("-"),
    "rotate_nominal": Strategy("eqn.12a", _rotate_nominal),
    "rotate_reference_velocity": Strategy("eqn.12b", _rotate_reference_velocity, needs_reference=True),
    "auxiliary_velocity": Strategy("eqn.13", _auxiliary_velocity, needs_reference=True),
    "rotate_relative_position": Strategy("eqn.12c", rotates_rows=True),
    "yield": Strategy("eqn.13 + right of way", yield_target, needs_reference=True, stateful=True),
}
"""Strategy registry: name -> :class:`Strategy`; adding one is a function and a line here."""
