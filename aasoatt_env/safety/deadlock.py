"""Deadlock resolution: strategies (what changes) and triggers (when).

``Q(q)`` is the rotation by ``q``; ``zeta_i`` is ``zeta`` while robot ``i`` is
triggered, else 0.  Strategies (:data:`STRATEGIES`), acting on the target
control-point acceleration ``target`` (the nominal ``A du_nom``) or on the rows:

``none``
    nothing.
``rotate_nominal`` (eqn.12a, Wang 2017)
    ``target <- (I - Q) target`` while triggered.
``rotate_reference_velocity`` (eqn.12b)
    ``v_d <- (I - zeta Q) v_d``; for an arbitrary nominal this is the target
    correction ``-(k3 + k4) zeta Q v_d`` (exact for the tracking law eqn.12).
``auxiliary_velocity`` (eqn.13, default)
    ``target += -zeta Q (A u - v_d + k3 ell)``, ``ell = p - p_d``.
``rotate_relative_position`` (eqn.12c, He 2024)
    ``p_ij <- (I - Q) p_ij`` in the rows of pairs with a triggered member
    (everywhere in the row: normal and right-hand side).  This changes the
    barrier itself, so the safety guarantee is lost while it is active: in a
    6-robot swap pairs came as close as 0.23 m for ``d_s = 0.96`` (the paper
    reports Zeno behaviour with it).  Provided for comparison only.

Triggers (:data:`TRIGGERS`), evaluated at the start of a step:

``multiplier`` (Algorithm 1)
    some multiplier of a row involving robot ``i`` was positive at the previous step.
``low_speed`` (Wang 2017)
    ``|v_i| < low_speed`` while the robot is not done (``|v_d_i| >= low_speed``
    or ``|ell_i| > goal_tol``; without a reference: while it was avoiding).
``stalled``
    the robot moved less than ``stall_distance`` over ``stall_time`` and is not
    done (as above).
``heading`` (He 2024)
    the heading points, within ``heading_deg``, at the nearest neighbour or
    obstacle inside the sensing range.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from aasoatt_env.errors import ConfigError

__all__ = ["STRATEGIES", "TRIGGERS", "DeadlockState", "rotation", "target_correction", "trigger"]

STRATEGIES: tuple[str, ...] = (
    "none",
    "rotate_nominal",
    "rotate_reference_velocity",
    "auxiliary_velocity",
    "rotate_relative_position",
)
"""Registered deadlock strategies."""

TRIGGERS: tuple[str, ...] = ("multiplier", "low_speed", "stalled", "heading")
"""Registered deadlock triggers."""

NEEDS_REFERENCE: frozenset[str] = frozenset({"rotate_reference_velocity", "auxiliary_velocity"})
"""Strategies that need ``reference=(p_d, v_d)``."""


def rotation(q_deg: float) -> np.ndarray:
    """Rotation matrix ``Q(q)`` (eqn.14) for ``q`` in degrees."""
    q = math.radians(q_deg)
    return np.array([[math.cos(q), -math.sin(q)], [math.sin(q), math.cos(q)]])


@dataclass
class DeadlockState:
    """Memory of the triggers between steps."""

    avoiding: np.ndarray | None = None
    history: list[np.ndarray] = field(default_factory=list)


def trigger(
    name: str,
    state: DeadlockState,
    *,
    p: np.ndarray,
    v: np.ndarray,
    theta: np.ndarray,
    reference: tuple[np.ndarray, np.ndarray] | None,
    pair_idx: np.ndarray,
    pair_vec: np.ndarray,
    cfg: object,
) -> np.ndarray:
    """Boolean ``(N,)``: robots whose deadlock strategy is on this step.

    Parameters
    ----------
    name : str
        Trigger name (see module docstring).
    state : DeadlockState
        Memory, updated in place (position history).
    p, v : numpy.ndarray
        Control-point positions and velocities ``(N, 2)``.
    theta : numpy.ndarray
        Headings ``(N,)``.
    reference : tuple of numpy.ndarray or None
        ``(p_d, v_d)``.
    pair_idx : numpy.ndarray
        ``(P, 2)`` pairs inside the sensing range; second column ``-1`` for obstacles.
    pair_vec : numpy.ndarray
        ``(P, 2)``: ``p_j - p_i`` (the vector from robot ``i`` towards the other member).
    cfg : FilterConfig
        Thresholds.
    """
    n = p.shape[0]
    prev = state.avoiding if state.avoiding is not None else np.zeros(n, dtype=bool)
    if name == "multiplier":
        return prev.copy()
    if reference is not None:
        ell = p - reference[0]
        not_done = (np.linalg.norm(reference[1], axis=1) >= cfg.low_speed) | (
            np.linalg.norm(ell, axis=1) > cfg.goal_tol
        )
    else:
        not_done = prev
    if name == "low_speed":
        return (np.linalg.norm(v, axis=1) < cfg.low_speed) & not_done
    if name == "stalled":
        dwell = max(1, int(round(cfg.stall_time / cfg.dt)))
        state.history.append(p.copy())
        if len(state.history) > dwell + 1:
            del state.history[0]
        if len(state.history) <= dwell:
            return np.zeros(n, dtype=bool)
        moved = np.linalg.norm(p - state.history[0], axis=1)
        return (moved < cfg.stall_distance) & not_done
    if name == "heading":
        return _heading(n, theta, pair_idx, pair_vec, cfg.heading_deg)
    raise ConfigError(f"trigger: got {name!r}, expected one of {sorted(TRIGGERS)}")


def _heading(n: int, theta: np.ndarray, pair_idx: np.ndarray, pair_vec: np.ndarray, half_deg: float) -> np.ndarray:
    out = np.zeros(n, dtype=bool)
    if pair_idx.shape[0] == 0:
        return out
    i, j = pair_idx[:, 0], pair_idx[:, 1]
    rob = j >= 0
    # each robot-robot pair is seen from both ends; obstacles only from the robot
    who = np.concatenate((i, j[rob]))
    vec = np.concatenate((pair_vec, -pair_vec[rob]))
    dist = np.linalg.norm(vec, axis=1)
    nearest = np.full(n, np.inf)
    np.minimum.at(nearest, who, dist)
    is_nearest = dist <= nearest[who]
    head = np.stack((np.cos(theta), np.sin(theta)), axis=1)[who]
    cosang = np.einsum("ij,ij->i", head, vec) / np.maximum(dist, 1e-12)
    hit = is_nearest & (cosang >= math.cos(math.radians(half_deg)))
    out[who[hit]] = True
    return out


def target_correction(
    name: str,
    target: np.ndarray,
    zeta: np.ndarray,
    Q: np.ndarray,
    *,
    v: np.ndarray,
    reference: tuple[np.ndarray, np.ndarray] | None,
    p: np.ndarray,
    k3: float,
    k4: float,
) -> np.ndarray:
    """Target control-point accelerations after the strategy ``name`` (new array).

    ``zeta`` is ``(N,)``, zero for robots not triggered.  Row-level strategies
    (``rotate_relative_position``) and ``none`` return ``target`` unchanged.
    """
    on = zeta > 0
    if name in ("none", "rotate_relative_position") or not np.any(on):
        return target.copy()
    if name == "rotate_nominal":
        rotated = target @ (np.eye(2) - Q).T
        return np.where(on[:, None], rotated, target)
    if reference is None:
        raise ConfigError(f"deadlock strategy {name!r} needs reference=(p_d, v_d); got None")
    p_d, v_d = reference
    if name == "rotate_reference_velocity":
        return target - (k3 + k4) * zeta[:, None] * (v_d @ Q.T)
    if name == "auxiliary_velocity":
        e = v - v_d + k3 * (p - p_d)
        return target - zeta[:, None] * (e @ Q.T)
    raise ConfigError(f"deadlock: got {name!r}, expected one of {sorted(STRATEGIES)}")
