"""Episode metrics of ``docs/technical_brief.md`` section 6 (the paper's Sec. V), computed from a :class:`Rollout`.

RMSE, MAE and the population std of the tracking error pool all robots and steps; a collision is an overlap deeper
than a tolerance (1 mm: the barrier's discretisation); a gap is a centre distance minus the radii.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from aasoatt_env import validation as check
from aasoatt_env.analysis.rollout import Rollout
from aasoatt_env.errors import ConfigError

__all__ = ["CollisionReport", "Separation", "arrival_times", "collisions", "deadlocked_robots", "final_errors",
           "format_summary", "format_value", "intervention_time", "intervention_times", "liveness", "longest_stall",
           "pairwise_min_distance", "reach_rate", "safe_rate", "solver_stats", "summarize", "tracking_errors",
           "tracking_stats"]

COLLISION_TOLERANCE = 1e-3  # default collision tolerance [m]
_CHUNK_ELEMENTS = 1 << 21  # float64 elements per temporary pairwise array (about 16 MB)

# Substrings (lower case) of a failed, and of a relaxed, solver status.
_FAILED_MARKERS = ("fail", "infeas", "error", "max_iter", "maxiter", "unsolved", "nan", "diverg")
_RELAXED_MARKERS = ("relax", "slack")


def _tolerance(name: str, value: float) -> float:
    return check.real(name, value, lo=0.0)


def tracking_errors(rollout: Rollout) -> np.ndarray:
    """Tracking error ``|p_i(t) - p_d_i(t)|`` of every robot at every recorded step, shape ``(T, N)``."""
    return np.linalg.norm(rollout.positions - rollout.references, axis=-1)


def tracking_stats(rollout: Rollout) -> dict[str, float]:
    """``{"rmse", "mae", "std", "max"}`` of the tracking error over all robots and steps (population std)."""
    e = tracking_errors(rollout)
    return {"rmse": float(np.sqrt(np.mean(e**2))), "mae": float(np.mean(e)), "std": float(np.std(e, ddof=0)),
            "max": float(np.max(e))}


def final_errors(rollout: Rollout) -> np.ndarray:
    """Distance ``|p_i(T) - g_i|`` of each robot's control point to its goal at the last step, shape ``(N,)``."""
    return np.linalg.norm(rollout.positions[-1] - rollout.goals, axis=-1)


def reach_rate(rollout: Rollout, goal_tolerance: float = 0.1) -> float:
    """Fraction of robots whose final goal distance is at most ``goal_tolerance`` [m]."""
    return float(np.mean(final_errors(rollout) <= _tolerance("goal_tolerance", goal_tolerance)))


def intervention_times(rollout: Rollout) -> np.ndarray:
    """Per-robot time from the first to the last step with ``avoiding`` [s] (0 if none), shape ``(N,)``."""
    avoiding = rollout.avoiding
    if avoiding is None:
        raise ConfigError("intervention_times: the rollout has no 'avoiding' field, record it to compute this metric")
    first = np.argmax(avoiding, axis=0)
    last = avoiding.shape[0] - 1 - np.argmax(avoiding[::-1], axis=0)
    return np.where(avoiding.any(axis=0), (last - first) * rollout.dt, 0.0)


def intervention_time(rollout: Rollout) -> float:
    """Intervention time averaged over all robots, 0 for those that never avoid (the paper's number)."""
    return float(np.mean(intervention_times(rollout)))


def _smallest(field: str, what: str) -> property:
    """A property: the smallest value of the array ``field`` (``what``) over the episode."""
    return property(lambda self: float(np.min(getattr(self, field))), doc=f"Smallest {what} over the episode.")


@dataclass(frozen=True)
class Separation:
    """Per step: minimum centre distance and gaps (``inf``: no pair), robots ``i < j`` of the smallest gap."""

    min_center_distance: np.ndarray
    min_robot_gap: np.ndarray
    min_obstacle_gap: np.ndarray
    closest_pair: np.ndarray

    @property
    def min_gap(self) -> np.ndarray:
        """Smallest surface gap to anything (robot or obstacle) at each step, shape ``(T,)``."""
        return np.minimum(self.min_robot_gap, self.min_obstacle_gap)

    overall_min_center_distance = _smallest("min_center_distance", "robot-robot centre distance")
    overall_min_robot_gap = _smallest("min_robot_gap", "robot-robot surface gap")
    overall_min_obstacle_gap = _smallest("min_obstacle_gap", "robot-obstacle surface gap")
    overall_min_gap = _smallest("min_gap", "surface gap to anything")


def _scan(rollout: Rollout, obstacles: bool, tolerance: float | None) -> tuple[np.ndarray, ...]:
    """One chunked pass over the robot pairs (or robot-obstacle pairs).

    Per step: the minimum centre distance and gap, the pair ``(i, j)`` of the smallest gap (``inf``, ``-1``: no
    pair); with a ``tolerance``, each pair's first collision step ``(N, N or M)`` (``-1``: never; robots ``i < j``).
    """
    p = rollout.positions
    q, rq = (rollout.obstacle_centers[None], rollout.obstacle_radii) if obstacles else (p, rollout.radii)
    (T, N), M = p.shape[:2], q.shape[1]
    min_dist, min_gap, pair = np.full(T, np.inf), np.full(T, np.inf), np.full((T, 2), -1, dtype=np.int64)
    first = np.full((N, M), -1, dtype=np.int64) if tolerance is not None else np.zeros((0, 0), dtype=np.int64)
    if M < (1 if obstacles else 2):
        return min_dist, min_gap, pair, first
    rsum = rollout.radii[:, None] + rq[None, :]
    uniform = bool(np.all(rsum == rsum[0, 0]))
    skip = np.zeros((N, M)) if obstacles else np.where(np.eye(N, dtype=np.bool_), np.inf, 0.0)
    if tolerance is not None:
        thr = rsum - tolerance
        upper = np.ones((N, M), dtype=np.bool_) if obstacles else np.triu(np.ones((N, N), dtype=np.bool_), k=1)
        thr2 = np.where(upper & (thr > 0), thr * np.abs(thr), -1.0)  # d2 < -1 never holds
    x, y = np.ascontiguousarray(p[..., 0]), np.ascontiguousarray(p[..., 1])
    qx, qy = (q[..., 0], q[..., 1]) if obstacles else (x, y)
    chunk = max(1, min(T, _CHUNK_ELEMENTS // max(4 * N * M, 1)))
    for s in range(0, T, chunk):
        xs, ys = x[s : s + chunk], y[s : s + chunk]
        qxs, qys = (qx, qy) if obstacles else (qx[s : s + chunk], qy[s : s + chunk])
        c = xs.shape[0]
        dx, dy = xs[:, :, None] - qxs[:, None, :], ys[:, :, None] - qys[:, None, :]
        d2 = dx * dx + dy * dy
        if tolerance is not None:
            hit = d2 < thr2
            new = hit.any(axis=0) & (first < 0)
            first[new] = np.argmax(hit, axis=0)[new] + s
        d2 += skip
        flat = d2.reshape(c, N * M)
        if uniform:  # the smallest distance is the smallest gap: one square root per step
            k = np.argmin(flat, axis=1)
            min_dist[s : s + c] = np.sqrt(flat[np.arange(c), k])
            min_gap[s : s + c] = min_dist[s : s + c] - rsum[0, 0]
        else:
            dist = np.sqrt(flat)
            min_dist[s : s + c] = dist.min(axis=1)
            gap = dist - rsum.ravel()
            k = np.argmin(gap, axis=1)
            min_gap[s : s + c] = gap[np.arange(c), k]
        i, j = np.divmod(k, M)
        pair[s : s + c] = np.stack([i, j], axis=1) if obstacles else np.stack([np.minimum(i, j), np.maximum(i, j)], 1)
    return min_dist, min_gap, pair, first


def pairwise_min_distance(rollout: Rollout) -> Separation:
    """Minimum robot-robot distance and surface gaps at every step (see :class:`Separation`)."""
    min_dist, min_gap, pair, _ = _scan(rollout, False, None)
    return Separation(min_dist, min_gap, _scan(rollout, True, None)[1], pair)


@dataclass(frozen=True)
class CollisionReport:
    """Overlaps deeper than ``tolerance`` [m]: ``(i, j or obstacle k, first step)`` sorted by step; robots in one."""

    robot_pairs: list[tuple[int, int, int]]
    obstacle_hits: list[tuple[int, int, int]]
    colliding_robots: np.ndarray
    tolerance: float

    @property
    def n_robot_pairs(self) -> int:
        """Number of distinct colliding robot pairs."""
        return len(self.robot_pairs)

    @property
    def n_obstacle_hits(self) -> int:
        """Number of colliding robot-obstacle pairs."""
        return len(self.obstacle_hits)

    @property
    def n_colliding_robots(self) -> int:
        """Number of robots in a collision."""
        return int(self.colliding_robots.sum())

    @property
    def any(self) -> bool:
        """Whether anything collided."""
        return bool(self.robot_pairs or self.obstacle_hits)


def _scans(rollout: Rollout, tolerance: float) -> tuple[Separation, CollisionReport]:
    tol = _tolerance("tolerance", tolerance)
    min_dist, min_gap, pair, first_r = _scan(rollout, False, tol)
    _, min_obs, _, first_o = _scan(rollout, True, tol)
    colliding = np.zeros(rollout.n_robots, dtype=np.bool_)
    ii, jj = np.nonzero(first_r >= 0)
    oi, ok = np.nonzero(first_o >= 0)
    colliding[ii] = colliding[jj] = colliding[oi] = True
    found = [sorted(zip(rows.tolist(), cols.tolist(), first[rows, cols].tolist()), key=lambda t: (t[2], t[0], t[1]))
             for first, rows, cols in ((first_r, ii, jj), (first_o, oi, ok))]
    return Separation(min_dist, min_gap, min_obs, pair), CollisionReport(found[0], found[1], colliding, tol)


def collisions(rollout: Rollout, tolerance: float = COLLISION_TOLERANCE) -> CollisionReport:
    """Robot-robot and robot-obstacle overlaps deeper than ``tolerance`` [m] (see the module docstring)."""
    return _scans(rollout, tolerance)[1]


def safe_rate(rollout: Rollout, tolerance: float = COLLISION_TOLERANCE) -> float:
    """Fraction of robots that never collide with a robot or an obstacle (GCBF+'s safety rate)."""
    return float(1.0 - np.mean(collisions(rollout, tolerance).colliding_robots))


def longest_stall(rollout: Rollout, speed_threshold: float = 0.05, goal_tolerance: float = 0.1) -> np.ndarray:
    """Longest time [s] each robot moves slower than ``speed_threshold`` away from its goal; ``-dt``: never."""
    slow = np.linalg.norm(rollout.velocities, axis=-1) < _tolerance("speed_threshold", speed_threshold)
    far = np.linalg.norm(rollout.positions - rollout.goals, axis=-1) > _tolerance("goal_tolerance", goal_tolerance)
    padded = np.zeros((rollout.n_robots, rollout.n_steps + 2), dtype=np.int8)  # per robot: 0, stalled?, 0
    padded[:, 1:-1] = (slow & far).T
    d = np.diff(padded, axis=1)
    sr, st = np.nonzero(d == 1)  # run starts, row-major: sorted by robot then time
    _, et = np.nonzero(d == -1)  # run ends (exclusive), same order
    longest = np.zeros(rollout.n_robots, dtype=np.int64)
    np.maximum.at(longest, sr, et - st)
    return (longest - 1) * rollout.dt


def deadlocked_robots(rollout: Rollout, speed_threshold: float = 0.05, dwell_time: float = 1.0,
                      goal_tolerance: float = 0.1) -> np.ndarray:
    """Robots (bool ``(N,)``) that stay stalled (see :func:`longest_stall`) for at least ``dwell_time`` [s]."""
    dwell = _tolerance("dwell_time", dwell_time)
    stall = longest_stall(rollout, speed_threshold, goal_tolerance)
    # Half a step of slack so that float rounding of k * dt never flips the verdict.
    return (stall >= 0) & (stall >= dwell - 0.5 * rollout.dt)


def arrival_times(rollout: Rollout, goal_tolerance: float = 0.1) -> np.ndarray:
    """Per robot ``(N,)``: the time [s] from which it stays within ``goal_tolerance`` of its goal (NaN: not home)."""
    far = np.linalg.norm(rollout.positions - rollout.goals, axis=-1) > _tolerance("goal_tolerance", goal_tolerance)
    last_far = far.shape[0] - 1 - np.argmax(far[::-1], axis=0)  # the last step away from the goal
    k = np.where(far.any(axis=0), last_far + 1, 0)
    return np.where(k < far.shape[0], rollout.times[np.minimum(k, far.shape[0] - 1)] - rollout.times[0], np.nan)


def liveness(rollout: Rollout, goal_tolerance: float = 0.1, speed_threshold: float = 0.05) -> dict[str, Any]:
    """Robots home, the makespan against the straight-line lower bound, and the time spent stalled.

    ``makespan``: time [s] to the last robot home for good (None unless all are); ``lower_bound``: the longest
    start-to-goal straight line over its robot's mean reference speed (reference length / time it moves);
    ``stalled_time_*``: per robot, the total time slower than ``speed_threshold`` away from its goal (mean, max).
    """
    arrive = arrival_times(rollout, goal_tolerance)
    step = np.linalg.norm(np.diff(rollout.references, axis=0), axis=-1)
    moving = (step > 0).sum(axis=0) * rollout.dt
    speed_ref = np.where(moving > 0, step.sum(axis=0) / np.maximum(moving, 1e-12), np.inf)
    bound = float(np.max(np.linalg.norm(rollout.goals - rollout.positions[0], axis=-1) / speed_ref))
    far = np.linalg.norm(rollout.positions - rollout.goals, axis=-1) > goal_tolerance
    slow = np.linalg.norm(rollout.velocities, axis=-1) < _tolerance("speed_threshold", speed_threshold)
    stalled = (far & slow).sum(axis=0) * rollout.dt
    home = bool(np.isfinite(arrive).all())
    makespan = float(np.max(arrive)) if home else None
    return {"home": int(np.isfinite(arrive).sum()), "n_robots": rollout.n_robots, "makespan": makespan,
            "lower_bound": bound, "makespan_ratio": makespan / bound if home and bound > 0 else None,
            "stalled_time_mean": float(stalled.mean()), "stalled_time_max": float(stalled.max())}


def solver_stats(rollout: Rollout) -> dict[str, Any]:
    """Fractions of relaxed, failed, ``unsafe`` and braked steps, status counts, solve times, slack (None: no field).

    A status naming a failure (``fail``, ``infeas``, ...) is failed, else one naming ``relax`` or ``slack`` relaxed.
    """
    out: dict[str, Any] = dict.fromkeys(
        ("relaxed_fraction", "failed_fraction", "unsafe_fraction", "backup_fraction", "backup_robot_fraction",
         "status_counts", "solve_time_median", "solve_time_mean", "solve_time_max", "slack_max",
         "slack_positive_fraction"))
    if rollout.solver_status is not None:
        low = np.char.lower(rollout.solver_status.astype(np.str_))
        failed = np.any([np.char.find(low, m) >= 0 for m in _FAILED_MARKERS], axis=0)
        relaxed = np.any([np.char.find(low, m) >= 0 for m in _RELAXED_MARKERS], axis=0) & ~failed
        names, counts = np.unique(rollout.solver_status, return_counts=True)
        out.update(relaxed_fraction=float(relaxed.mean()), failed_fraction=float(failed.mean()),
                   unsafe_fraction=float(np.mean(low == "unsafe")),
                   status_counts={str(n): int(c) for n, c in zip(names, counts)})
    if rollout.backup is not None:
        out.update(backup_fraction=float(rollout.backup.any(axis=1).mean()),
                   backup_robot_fraction=float(rollout.backup.mean()))
    if rollout.solve_time is not None:
        st = rollout.solve_time
        out.update(solve_time_median=float(np.median(st)), solve_time_mean=float(np.mean(st)),
                   solve_time_max=float(np.max(st)))
    if rollout.slack is not None:
        out.update(slack_max=float(np.max(rollout.slack)), slack_positive_fraction=float(np.mean(rollout.slack > 0)))
    return out


def summarize(rollout: Rollout, *, collision_tolerance: float = COLLISION_TOLERANCE, goal_tolerance: float = 0.1,
              speed_threshold: float = 0.05, dwell_time: float = 1.0) -> dict[str, Any]:
    """All headline numbers (and :func:`solver_stats` but the counts) as JSON values; None: no field, no gap."""

    def finite(x: float) -> float | None:
        return float(x) if math.isfinite(x) else None

    _tolerance("collision_tolerance", collision_tolerance)
    stats = tracking_stats(rollout)
    sep, col = _scans(rollout, collision_tolerance)
    fe = final_errors(rollout)
    it = intervention_times(rollout) if rollout.avoiding is not None else None
    out: dict[str, Any] = {
        "n_robots": rollout.n_robots, "n_steps": rollout.n_steps, "duration": rollout.duration,
        "intervention_time": None if it is None else float(it.mean()),
        "intervention_time_max": None if it is None else float(it.max()),
        "rmse": stats["rmse"], "mae": stats["mae"], "std": stats["std"], "max_tracking_error": stats["max"],
        "min_center_distance": finite(sep.overall_min_center_distance),
        "min_robot_gap": finite(sep.overall_min_robot_gap), "min_obstacle_gap": finite(sep.overall_min_obstacle_gap),
        "n_collision_pairs": col.n_robot_pairs, "n_obstacle_collisions": col.n_obstacle_hits,
        "n_colliding_robots": col.n_colliding_robots, "safe_rate": float(1.0 - col.colliding_robots.mean()),
        "final_error_mean": float(fe.mean()), "final_error_max": float(fe.max()),
        "final_tracking_error_mean": float(tracking_errors(rollout)[-1].mean()),
        "reach_rate": reach_rate(rollout, goal_tolerance),
        "n_deadlocked": int(deadlocked_robots(rollout, speed_threshold, dwell_time, goal_tolerance).sum()),
        "triggered_fraction": None if rollout.triggered is None else float(rollout.triggered.mean()),
    }
    solver = solver_stats(rollout)
    solver.pop("status_counts")
    return {**out, **solver}


def format_value(x: Any, digits: int = 4) -> str:
    """A table cell: ``-`` for None, yes/no for bools, ``digits`` decimals for finite floats."""
    if x is None:
        return "-"
    if isinstance(x, (bool, np.bool_)):
        return "yes" if x else "no"
    if isinstance(x, (float, np.floating)) and math.isfinite(x):
        return f"{x:.{digits}f}"
    return str(int(x)) if isinstance(x, np.integer) else str(x)


def format_summary(summary: dict[str, Any], *, precision: int = 4) -> str:
    """A :func:`summarize` dict (any flat dict) as aligned ``name  value`` lines (see :func:`format_value`).

    Solve times (``solve_time_*``, stored in seconds) print in milliseconds with their unit, e.g. ``1.2500 ms``.
    """
    width = max((len(str(k)) for k in summary), default=0)
    return "\n".join(f"{str(k):<{width}}  {_summary_cell(str(k), v, precision):>12}" for k, v in summary.items())


def _summary_cell(key: str, value: Any, precision: int) -> str:
    if key.startswith("solve_time") and isinstance(value, (float, np.floating)) and math.isfinite(value):
        return f"{1e3 * value:.{precision}f} ms"
    return format_value(value, precision)
