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

__all__ = ["OBS_BOUND", "SELF_DIM", "SLOT_DIM", "Proximity", "build_observations", "k_nearest", "min_gaps", "proximity"]

OBS_BOUND = 100.0
SELF_DIM = 14
SLOT_DIM = 6
_BRUTE_FORCE_MAX = 256


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


def k_nearest(p: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Indices ``(N, k)`` and distances ``(N, k)`` of each point's k nearest other points.

    Brute force up to 256 points (also returning the full distance matrix), a
    k-d tree above (O(N log N) time, O(N k) memory, matrix None).  Missing
    neighbours (fewer than ``k`` others) get index -1 and distance inf.
    """
    n = p.shape[0]
    kk = min(k, n - 1)
    idx = np.full((n, k), -1, dtype=np.intp)
    dist = np.full((n, k), np.inf)
    if kk <= 0:
        return idx, dist, None
    if n <= _BRUTE_FORCE_MAX:
        dx = p[:, 0:1] - p[:, 0]
        dy = p[:, 1:2] - p[:, 1]
        d = np.sqrt(dx * dx + dy * dy)
        d.flat[:: n + 1] = np.inf
        part = np.argpartition(d, kk - 1, axis=1)[:, :kk] if kk < n - 1 else np.argsort(d, axis=1)[:, :kk]
        rows = np.arange(n)[:, None]
        pd = d[rows, part]
        order = np.argsort(pd, axis=1)
        idx[:, :kk] = part[rows, order]
        dist[:, :kk] = pd[rows, order]
        return idx, dist, d
    from scipy.spatial import cKDTree

    dd, ii = cKDTree(p).query(p, k=kk + 1)
    idx[:, :kk], dist[:, :kk] = ii[:, 1:], dd[:, 1:]
    return idx, dist, None


def proximity(
    p: np.ndarray, radii: np.ndarray, centers: np.ndarray, orad: np.ndarray, k: int = 6
) -> Proximity:
    """Nearest robots and obstacle gaps of every robot.

    The robot clearance is exact for teams up to 256 robots (all pairs); above,
    it is taken over the ``max(k, 6)`` nearest centres, exact for equal radii.
    """
    n = p.shape[0]
    idx, dist, full = k_nearest(p, max(k, 6) if n > _BRUTE_FORCE_MAX else k)
    if full is not None:
        gap = (full - radii[:, None] - radii[None, :]).min(axis=1) if n > 1 else np.full(n, np.inf)
        idx, dist = idx[:, :k], dist[:, :k]
    else:
        valid = idx >= 0
        gap = np.where(valid, dist - radii[:, None] - radii[np.where(valid, idx, 0)], np.inf).min(axis=1)
        idx, dist = idx[:, :k], dist[:, :k]
    if centers.shape[0]:
        dx = p[:, 0:1] - centers[:, 0]
        dy = p[:, 1:2] - centers[:, 1]
        og = np.sqrt(dx * dx + dy * dy) - radii[:, None] - orad[None, :]
        gap = np.minimum(gap, og.min(axis=1))
    else:
        og = np.zeros((n, 0))
    return Proximity(idx, dist, og, gap)


def min_gaps(p: np.ndarray, radii: np.ndarray, centers: np.ndarray, orad: np.ndarray) -> np.ndarray:
    """Clearance ``(N,)`` only (cheaper than :func:`proximity`; used between decisions)."""
    n = p.shape[0]
    if n > _BRUTE_FORCE_MAX:
        return proximity(p, radii, centers, orad, k=6).clearance
    gap = np.full(n, np.inf)
    if n > 1:
        dx = p[:, 0:1] - p[:, 0]
        dy = p[:, 1:2] - p[:, 1]
        g = np.sqrt(dx * dx + dy * dy) - radii[:, None] - radii[None, :]
        g.flat[:: n + 1] = np.inf
        gap = g.min(axis=1)
    if centers.shape[0]:
        dx = p[:, 0:1] - centers[:, 0]
        dy = p[:, 1:2] - centers[:, 1]
        gap = np.minimum(gap, (np.sqrt(dx * dx + dy * dy) - radii[:, None] - orad[None, :]).min(axis=1))
    return gap


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
) -> np.ndarray:
    """Observations of all robots as one ``(N, 14 + 6 (K + K_obs))`` float32 array."""
    n = p.shape[0]
    obs = np.zeros((n, SELF_DIM + SLOT_DIM * (k_robots + k_obstacles)))
    obs[:, 0:2] = p - p_d
    obs[:, 2:4] = goals - p
    obs[:, 4:6] = v
    obs[:, 6] = np.cos(theta)
    obs[:, 7] = np.sin(theta)
    obs[:, 8:10] = u
    obs[:, 10:12] = v_d
    obs[:, 12:14] = a_d
    if k_robots and n > 1:
        idx, dist = prox.idx[:, :k_robots], prox.dist[:, :k_robots]
        ok = dist <= sensing_range
        j = np.where(ok, idx, 0)
        slots = obs[:, SELF_DIM : SELF_DIM + SLOT_DIM * k_robots].reshape(n, k_robots, SLOT_DIM)
        slots[..., 0:2] = p[j] - p[:, None, :]
        slots[..., 2:4] = v[j] - v[:, None, :]
        slots[..., 4] = dist - radii[:, None] - radii[j]
        slots[..., 5] = 1.0
        slots[~ok] = 0.0
    m = obstacle_centers.shape[0]
    if k_obstacles and m:
        gaps = prox.obstacle_gaps
        kk = min(k_obstacles, m)
        order = np.argsort(gaps, axis=1)[:, :kk]
        rows = np.arange(n)[:, None]
        g = gaps[rows, order]
        ok = g + radii[:, None] + obstacle_radii[order] <= sensing_range
        start = SELF_DIM + SLOT_DIM * k_robots
        slots = obs[:, start : start + SLOT_DIM * kk].reshape(n, kk, SLOT_DIM)
        slots[..., 0:2] = obstacle_centers[order] - p[:, None, :]
        slots[..., 2:4] = -v[:, None, :]
        slots[..., 4] = g
        slots[..., 5] = 1.0
        slots[~ok] = 0.0
    np.clip(obs, -OBS_BOUND, OBS_BOUND, out=obs)
    return obs.astype(np.float32)
