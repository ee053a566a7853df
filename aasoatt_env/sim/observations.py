"""Per-agent observations and neighbour queries, vectorised over the team.

Observation of robot ``i`` (``float32``, length ``14 + 6 (K + K_obs)``):

=========  ==========================================================
index      content
=========  ==========================================================
0:2        tracking error ``p_i - p_d_i`` [m]
2:4        goal relative position ``goal_i - p_i`` [m]
4:6        control-point velocity ``v_i`` [m/s]
6:8        heading ``(cos theta_i, sin theta_i)``
8:10       wheel speeds ``u_i`` [rad/s] (double integrator: velocity)
10:12      reference velocity ``v_d_i`` [m/s]
12:14      reference acceleration ``a_d_i`` [m/s^2]
then K     nearest robots within the sensing range, nearest first, each
slots      ``(dx, dy, dvx, dvy, gap, mask)``: position and velocity of the
           neighbour relative to robot ``i``, surface gap
           ``|p_ij| - r_i - r_j``, and ``mask = 1``; empty slots are zeros
then K_obs nearest static obstacles in range, same layout (velocity 0)
=========  ==========================================================

Every entry is clipped to ``[-OBS_BOUND, OBS_BOUND]`` (``OBS_BOUND = 100``),
which only matters for robots more than 100 m off their reference.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from aasoatt_env.model.geometry import neighbourhood

__all__ = ["OBS_BOUND", "SELF_DIM", "SLOT_DIM", "Proximity", "build_observations", "proximity"]

OBS_BOUND = 100.0
SELF_DIM = 14
SLOT_DIM = 6
_NEG_RADIUS = np.array([1.0, 1.0, 1.0, 1.0, -1.0])


class Proximity(NamedTuple):
    """Neighbour table of one instant, shared by observations, rewards and infos."""

    idx: np.ndarray
    """Indices of each robot's ``k`` nearest robots, nearest first, ``(N, k)`` (-1: none)."""
    dist: np.ndarray
    """Their centre distances ``(N, k)`` (inf: none)."""
    obstacle_gaps: np.ndarray
    """Surface gaps robot-obstacle ``(N, M)``."""
    clearance: np.ndarray
    """Surface gap to the nearest robot or obstacle ``(N,)``; negative when overlapping."""


def proximity(
    p: np.ndarray, radii: np.ndarray, centers: np.ndarray, orad: np.ndarray, k: int = 6, teams: int = 1,
    equal_radii: np.ndarray | None = None,
) -> Proximity:
    """Nearest robots and obstacle gaps of every robot (:func:`aasoatt_env.model.geometry.neighbourhood`).

    ``teams`` equal teams may be stacked in ``p``; the indices then point into the stack.
    """
    return Proximity(*neighbourhood(p, radii, centers, orad, k, teams, equal_radii))


def build_observations(
    *,
    p: np.ndarray,
    v: np.ndarray,
    theta: np.ndarray,
    u: np.ndarray,
    p_d: np.ndarray,
    v_d: np.ndarray,
    a_d: np.ndarray,
    goals: np.ndarray,
    radii: np.ndarray,
    obstacle_centers: np.ndarray,
    obstacle_radii: np.ndarray,
    sensing_range: float,
    k_robots: int,
    k_obstacles: int,
    prox: Proximity,
    obstacle_offset: np.ndarray | None = None,
) -> np.ndarray:
    """Observations of all robots as one ``(N, 14 + 6 (K + K_obs))`` float32 array.

    Several teams can be observed in one call (:mod:`aasoatt_env.sim.batched`):
    their robots stacked, ``prox.idx`` holding indices into the stack, and each
    robot's obstacles found at ``obstacle_offset[i] + k`` of the stacked obstacle
    arrays (``prox.obstacle_gaps`` then has one column per obstacle of a team).
    """
    n = p.shape[0]
    heading = np.exp(1j * theta).view(np.float64).reshape(n, 2)
    parts = [p - p_d, goals - p, v, heading, u, v_d, a_d]
    if k_robots:
        slots = np.zeros((n, k_robots, SLOT_DIM))
        if n > 1:
            idx, dist = prox.idx[:, :k_robots], prox.dist[:, :k_robots]
            ok = dist <= sensing_range
            j = np.where(ok, idx, 0)
            # gather (p, v, -r) of the neighbours, subtract (p, v, r) of the robot
            mine = np.concatenate((p, v, radii[:, None]), axis=1)
            theirs = mine * _NEG_RADIUS
            rel = theirs[j] - mine[:, None, :]
            rel[..., 4] += dist
            slots[..., :5] = rel
            slots[..., 5] = 1.0
            slots[~ok] = 0.0
        parts.append(slots.reshape(n, -1))
    if k_obstacles:
        gaps = prox.obstacle_gaps
        m = gaps.shape[1]
        slots = np.zeros((n, k_obstacles, SLOT_DIM))
        if m:
            kk = min(k_obstacles, m)
            order = np.argsort(gaps, axis=1)[:, :kk]
            g = gaps[np.arange(n)[:, None], order]
            if obstacle_offset is not None:
                order = order + obstacle_offset[:, None]
            ok = g + radii[:, None] + obstacle_radii[order] <= sensing_range
            part = slots[:, :kk]
            part[..., 0:2] = obstacle_centers[order] - p[:, None, :]
            part[..., 2:4] = -v[:, None, :]
            part[..., 4] = g
            part[..., 5] = 1.0
            part[~ok] = 0.0
        parts.append(slots.reshape(n, -1))
    obs = np.concatenate(parts, axis=1, dtype=np.float32)
    return np.minimum(np.maximum(obs, -OBS_BOUND, out=obs), OBS_BOUND, out=obs)
