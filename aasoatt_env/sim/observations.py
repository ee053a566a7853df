"""Per-agent observations: ``14 + 6 (K + K_obs)`` entries (the table: ``docs/env.md``)."""

from __future__ import annotations

import numpy as np

from aasoatt_env.compiled import kernels
from aasoatt_env.model.geometry import Proximity

__all__ = ["OBS_BOUND", "SELF_DIM", "SLOT_DIM", "build_observations"]

OBS_BOUND = 100.0
SELF_DIM = 14
SLOT_DIM = 6
_NEG_RADIUS = np.array([1.0, 1.0, 1.0, 1.0, -1.0])


def build_observations(*, p: np.ndarray, v: np.ndarray, theta: np.ndarray, u: np.ndarray, p_d: np.ndarray,
                       v_d: np.ndarray, a_d: np.ndarray, goals: np.ndarray, radii: np.ndarray,
                       obstacle_centers: np.ndarray, obstacle_radii: np.ndarray, sensing_range: float, k_robots: int,
                       k_obstacles: int, prox: Proximity, obstacle_offset: np.ndarray | None = None,
                       compiled: bool = False) -> np.ndarray:
    """Observations of all robots as one ``(N, 14 + 6 (K + K_obs))`` float32 array.

    Stacked teams: ``prox.idx`` holds stack indices, and robot ``i``'s obstacle ``k`` is entry
    ``obstacle_offset[i] + k`` of the stacked obstacle arrays.  ``compiled``: the same numbers by
    :mod:`.observations_kernel`.
    """
    n = p.shape[0]
    if compiled:
        gaps = prox.obstacle_gaps if k_obstacles and prox.obstacle_gaps is not None else np.empty((n, 0))
        has_offset = obstacle_offset is not None
        return kernels("observations").observations(
            p, v, theta, u, p_d, v_d, a_d, goals, radii, obstacle_centers, obstacle_radii, float(sensing_range),
            int(k_robots), int(k_obstacles), prox.idx, prox.dist, gaps,
            obstacle_offset if has_offset else np.zeros(0, np.intp), has_offset, SELF_DIM, SLOT_DIM, OBS_BOUND)
    obs = np.zeros((n, SELF_DIM + SLOT_DIM * (k_robots + k_obstacles)), dtype=np.float32)  # each entry cast once
    heading = np.exp(1j * theta).view(np.float64).reshape(n, 2)
    np.concatenate((p - p_d, goals - p, v, heading, u, v_d, a_d), axis=1, out=obs[:, :SELF_DIM])
    slots = obs[:, SELF_DIM:].reshape(n, k_robots + k_obstacles, SLOT_DIM)  # a view
    if k_robots and n > 1:
        idx, dist = prox.idx[:, :k_robots], prox.dist[:, :k_robots]
        ok = dist <= sensing_range
        j = np.where(ok, idx, 0)
        # gather (p, v, -r) of the neighbours, subtract (p, v, r) of the robot
        mine = np.concatenate((p, v, radii[:, None]), axis=1)
        rel = (mine * _NEG_RADIUS)[j] - mine[:, None, :]
        rel[..., 4] += dist
        rel[~ok] = 0.0
        slots[:, :k_robots, :5] = rel
        slots[:, :k_robots, 5] = ok
    m = prox.obstacle_gaps.shape[1] if k_obstacles else 0
    if m:
        gaps, kk = prox.obstacle_gaps, min(k_obstacles, m)
        order = gaps.argsort(axis=1, kind="stable")[:, :kk]  # (ties: the first obstacle, as the kernel)
        g = gaps[np.arange(n)[:, None], order]
        if obstacle_offset is not None:
            order = order + obstacle_offset[:, None]
        ok = g + radii[:, None] + obstacle_radii[order] <= sensing_range
        part = np.empty((n, kk, SLOT_DIM))
        part[..., 0:2] = obstacle_centers[order] - p[:, None, :]
        part[..., 2:4] = -v[:, None, :]
        part[..., 4] = g
        part[..., 5] = 1.0
        part[~ok] = 0.0
        slots[:, k_robots:k_robots + kk] = part
    return np.minimum(np.maximum(obs, -OBS_BOUND, out=obs), OBS_BOUND, out=obs)
