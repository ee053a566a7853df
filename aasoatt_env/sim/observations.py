"""Per-agent observations (``14 + 6 (K + K_obs)`` entries; the table: ``docs/env.md``) and neighbour queries."""

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
    """Each robot's ``k`` nearest robots ``idx``/``dist (N, k)`` (-1/inf: none), nearest first, obstacle gaps.

    ``obstacle_gaps (N, M)``: surface gaps; ``clearance (N,)``: to the nearest of either (negative: overlap).
    """

    idx: np.ndarray
    dist: np.ndarray
    obstacle_gaps: np.ndarray
    clearance: np.ndarray


def proximity(p: np.ndarray, radii: np.ndarray, centers: np.ndarray, orad: np.ndarray, k: int = 6, teams: int = 1,
              equal_radii: np.ndarray | None = None) -> Proximity:
    """:func:`~aasoatt_env.model.geometry.neighbourhood` as a :class:`Proximity` (``teams`` stacked: stack indices)."""
    return Proximity(*neighbourhood(p, radii, centers, orad, k, teams, equal_radii))


def build_observations(*, p: np.ndarray, v: np.ndarray, theta: np.ndarray, u: np.ndarray, p_d: np.ndarray,
                       v_d: np.ndarray, a_d: np.ndarray, goals: np.ndarray, radii: np.ndarray,
                       obstacle_centers: np.ndarray, obstacle_radii: np.ndarray, sensing_range: float, k_robots: int,
                       k_obstacles: int, prox: Proximity, obstacle_offset: np.ndarray | None = None) -> np.ndarray:
    """Observations of all robots as one ``(N, 14 + 6 (K + K_obs))`` float32 array.

    Stacked teams: ``prox.idx`` holds stack indices, and robot ``i``'s obstacle ``k`` is entry
    ``obstacle_offset[i] + k`` of the stacked obstacle arrays.
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
