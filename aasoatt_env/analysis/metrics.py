"""Episode metrics of ``SPEC.md`` section 6 (the paper's Sec. V), computed from a :class:`Rollout`.

Conventions
-----------
* Tracking error ``e_i(t) = |p_i(t) - p_d_i(t)|`` (control point to reference
  point).  RMSE, MAE and standard deviation are taken over **all** robots and
  recorded steps pooled together; the standard deviation is the population one
  (``ddof = 0``), i.e. ``std**2 = mean(e**2) - mean(e)**2 = RMSE**2 - MAE**2``.
* Intervention time of robot ``i``: ``(k_last - k_first) * dt`` where ``k_first``
  and ``k_last`` are the first and last recorded steps with ``avoiding[k, i]``
  (0 if never).  With ``dt = 0.005`` this gives multiples of 0.005 as in the
  paper (e.g. 4.4850 s).  The headline number is the mean over **all** robots
  (those that never avoid count as 0).
* Collision: ``|p_i - p_j| < r_i + r_j - tolerance`` (robots) or
  ``|p_i - o_k| < r_i + R_k - tolerance`` (obstacles) at some recorded step.
  The tolerance (default ``1e-3`` m) absorbs the discretisation of the barrier
  guarantee (see ``SPEC.md`` section 4).
* Surface gap: centre distance minus the sum of radii (negative = overlap).
* Safe rate (as in GCBF+): fraction of robots that never collide with another
  robot or an obstacle during the episode.
* Durations of runs of steps (stalls) use the same convention as intervention
  time: a run from step ``a`` to step ``b`` lasts ``(b - a) * dt``.

All pairwise computations are vectorised and chunked over time so that the
temporary ``(chunk, N, N)`` arrays stay below a few tens of megabytes
(``N = 100``, ``T = 4000`` take well under a second).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from aasoatt_env.analysis.rollout import Rollout
from aasoatt_env.errors import ConfigError

__all__ = [
    "CollisionReport",
    "Separation",
    "collisions",
    "deadlocked_robots",
    "final_errors",
    "final_tracking_errors",
    "format_summary",
    "intervention_time",
    "intervention_times",
    "longest_stall",
    "pairwise_min_distance",
    "reach_rate",
    "safe_rate",
    "solver_stats",
    "summarize",
    "tracking_errors",
    "tracking_stats",
]

#: Default collision tolerance [m].
COLLISION_TOLERANCE = 1e-3

#: Budget of float64 elements per temporary pairwise array (about 16 MB).
_CHUNK_ELEMENTS = 1 << 21

# Substrings (lower case) that classify a solver status string.
_FAILED_MARKERS = ("fail", "infeas", "error", "max_iter", "maxiter", "unsolved", "nan", "diverg")
_RELAXED_MARKERS = ("relax", "slack")


def _chunk_steps(n_steps: int, per_step: int) -> int:
    """Return the number of time steps per chunk keeping ``chunk * per_step`` in budget."""
    return max(1, min(n_steps, _CHUNK_ELEMENTS // max(per_step, 1)))


def _check_tolerance(name: str, value: float) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name}: got {value!r}, expected a finite non-negative number") from None
    if not math.isfinite(v) or v < 0:
        raise ConfigError(f"{name}: got {value!r}, expected a finite non-negative number")
    return v


def _require(rollout: Rollout, name: str, metric: str) -> np.ndarray:
    value = getattr(rollout, name)
    if value is None:
        raise ConfigError(f"{metric}: the rollout has no {name!r} field, record it to compute this metric")
    return value


# --------------------------------------------------------------------------- tracking
def tracking_errors(rollout: Rollout) -> np.ndarray:
    """Tracking error of every robot at every recorded step.

    Parameters
    ----------
    rollout : Rollout
        The episode.

    Returns
    -------
    numpy.ndarray, shape (T, N)
        ``e_i(t) = |p_i(t) - p_d_i(t)|``.
    """
    return np.linalg.norm(rollout.positions - rollout.references, axis=-1)


def tracking_stats(rollout: Rollout) -> dict[str, float]:
    """RMSE, MAE, standard deviation and maximum of the tracking error.

    All robots and recorded steps are pooled (``N * T`` samples).  The standard
    deviation is the population one (``ddof = 0``), so
    ``std**2 == rmse**2 - mae**2``.

    Parameters
    ----------
    rollout : Rollout
        The episode.

    Returns
    -------
    dict
        ``{"rmse", "mae", "std", "max"}`` as Python floats.
    """
    e = tracking_errors(rollout)
    return {
        "rmse": float(np.sqrt(np.mean(e**2))),
        "mae": float(np.mean(e)),
        "std": float(np.std(e, ddof=0)),
        "max": float(np.max(e)),
    }


def final_tracking_errors(rollout: Rollout) -> np.ndarray:
    """Tracking error ``|p_i - p_d_i|`` at the last recorded step, shape ``(N,)``."""
    return tracking_errors(rollout)[-1]


def final_errors(rollout: Rollout) -> np.ndarray:
    """Distance of each robot's control point to its goal at the last recorded step.

    Parameters
    ----------
    rollout : Rollout
        The episode.

    Returns
    -------
    numpy.ndarray, shape (N,)
        ``|p_i(T) - g_i|``.
    """
    return np.linalg.norm(rollout.positions[-1] - rollout.goals, axis=-1)


def reach_rate(rollout: Rollout, goal_tolerance: float = 0.1) -> float:
    """Fraction of robots whose final goal distance is at most ``goal_tolerance``.

    Parameters
    ----------
    rollout : Rollout
        The episode.
    goal_tolerance : float, default 0.1
        Distance to the goal [m] that counts as reached.

    Returns
    -------
    float
        In ``[0, 1]``.
    """
    tol = _check_tolerance("goal_tolerance", goal_tolerance)
    return float(np.mean(final_errors(rollout) <= tol))


# ---------------------------------------------------------------- intervention time
def _first_last(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per column of a ``(T, N)`` bool array: any, first and last True index."""
    any_ = mask.any(axis=0)
    first = np.argmax(mask, axis=0)
    last = mask.shape[0] - 1 - np.argmax(mask[::-1], axis=0)
    return any_, first, last


def intervention_times(rollout: Rollout) -> np.ndarray:
    """Per-robot intervention time: from the first to the last step in collision avoidance.

    Parameters
    ----------
    rollout : Rollout
        The episode; needs the ``avoiding`` field.

    Returns
    -------
    numpy.ndarray, shape (N,)
        ``(k_last - k_first) * dt`` [s], 0 for robots that never avoided.

    Raises
    ------
    ConfigError
        If the rollout has no ``avoiding`` field.
    """
    avoiding = _require(rollout, "avoiding", "intervention_times")
    any_, first, last = _first_last(avoiding)
    return np.where(any_, (last - first) * rollout.dt, 0.0)


def intervention_time(rollout: Rollout) -> float:
    """Intervention time averaged over all robots (the paper's headline number).

    Robots that never avoid count as 0.  See :func:`intervention_times`.

    Parameters
    ----------
    rollout : Rollout
        The episode; needs the ``avoiding`` field.

    Returns
    -------
    float
        Mean intervention time [s].
    """
    return float(np.mean(intervention_times(rollout)))


# ---------------------------------------------------------------------- separation
@dataclass(frozen=True)
class Separation:
    """Per-step separation profile of an episode.

    Attributes
    ----------
    min_center_distance : numpy.ndarray, shape (T,)
        Smallest robot-robot centre distance at each step (``inf`` if ``N < 2``).
    min_robot_gap : numpy.ndarray, shape (T,)
        Smallest robot-robot surface gap ``|p_ij| - (r_i + r_j)`` at each step.
    min_obstacle_gap : numpy.ndarray, shape (T,)
        Smallest robot-obstacle surface gap ``|p_i - o_k| - (r_i + R_k)``
        (``inf`` if there are no obstacles).
    closest_pair : numpy.ndarray, shape (T, 2)
        Robot pair ``(i, j)``, ``i < j``, attaining ``min_robot_gap`` (``-1`` if ``N < 2``).
    """

    min_center_distance: np.ndarray
    min_robot_gap: np.ndarray
    min_obstacle_gap: np.ndarray
    closest_pair: np.ndarray

    @property
    def min_gap(self) -> np.ndarray:
        """Smallest surface gap to anything (robot or obstacle) at each step, shape ``(T,)``."""
        return np.minimum(self.min_robot_gap, self.min_obstacle_gap)

    @property
    def overall_min_center_distance(self) -> float:
        """Smallest robot-robot centre distance over the episode."""
        return float(np.min(self.min_center_distance))

    @property
    def overall_min_robot_gap(self) -> float:
        """Smallest robot-robot surface gap over the episode."""
        return float(np.min(self.min_robot_gap))

    @property
    def overall_min_obstacle_gap(self) -> float:
        """Smallest robot-obstacle surface gap over the episode."""
        return float(np.min(self.min_obstacle_gap))

    @property
    def overall_min_gap(self) -> float:
        """Smallest surface gap to anything over the episode."""
        return float(np.min(self.min_gap))


def _robot_scan(
    rollout: Rollout, tolerance: float | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """One chunked pass over all robot pairs.

    Returns the per-step minimum centre distance ``(T,)``, minimum surface gap
    ``(T,)``, the pair attaining it ``(T, 2)`` and, if ``tolerance`` is given, the
    ``(N, N)`` matrix of first collision steps (``-1`` = never; upper triangle).
    """
    T, N = rollout.n_steps, rollout.n_robots
    min_dist = np.full(T, np.inf)
    min_gap = np.full(T, np.inf)
    pair = np.full((T, 2), -1, dtype=np.int64)
    first = np.full((N, N), -1, dtype=np.int64) if tolerance is not None else None
    if N < 2:
        return min_dist, min_gap, pair, first
    r = rollout.radii
    rsum = r[:, None] + r[None, :]
    uniform = bool(np.all(r == r[0]))
    upper = np.triu(np.ones((N, N), dtype=np.bool_), k=1)
    diag_inf = np.where(np.eye(N, dtype=np.bool_), np.inf, 0.0)
    if tolerance is not None:
        thr = rsum - tolerance
        thr2 = np.where(upper & (thr > 0), thr * np.abs(thr), -1.0)  # d2 < -1 never holds
    x = np.ascontiguousarray(rollout.positions[..., 0])
    y = np.ascontiguousarray(rollout.positions[..., 1])
    chunk = _chunk_steps(T, 4 * N * N)
    for s in range(0, T, chunk):
        xs, ys = x[s : s + chunk], y[s : s + chunk]
        c = xs.shape[0]
        dx = xs[:, :, None] - xs[:, None, :]
        dy = ys[:, :, None] - ys[:, None, :]
        d2 = dx * dx + dy * dy
        if first is not None:
            _first_hits(first, d2 < thr2, s)
        d2 += diag_inf
        flat = d2.reshape(c, N * N)
        if uniform:
            k = np.argmin(flat, axis=1)
            dmin = np.sqrt(flat[np.arange(c), k])
            min_dist[s : s + c] = dmin
            min_gap[s : s + c] = dmin - 2.0 * r[0]
        else:
            dist = np.sqrt(flat)
            min_dist[s : s + c] = dist.min(axis=1)
            gap = dist - rsum.ravel()
            k = np.argmin(gap, axis=1)
            min_gap[s : s + c] = gap[np.arange(c), k]
        i, j = np.divmod(k, N)
        pair[s : s + c, 0] = np.minimum(i, j)
        pair[s : s + c, 1] = np.maximum(i, j)
    return min_dist, min_gap, pair, first


def _obstacle_scan(rollout: Rollout, tolerance: float | None) -> tuple[np.ndarray, np.ndarray | None]:
    """Per-step minimum robot-obstacle gap ``(T,)`` and first collision steps ``(N, M)``."""
    T, N, M = rollout.n_steps, rollout.n_robots, rollout.n_obstacles
    min_obs = np.full(T, np.inf)
    first = np.full((N, M), -1, dtype=np.int64) if tolerance is not None else None
    if M == 0:
        return min_obs, first
    rsum = rollout.radii[:, None] + rollout.obstacle_radii[None, :]
    chunk = _chunk_steps(T, 4 * N * M)
    for s in range(0, T, chunk):
        d = rollout.positions[s : s + chunk, :, None, :] - rollout.obstacle_centers[None, None, :, :]
        gap = np.sqrt(np.einsum("tnmk,tnmk->tnm", d, d)) - rsum
        min_obs[s : s + chunk] = gap.min(axis=(1, 2))
        if first is not None:
            _first_hits(first, gap < -tolerance, s)
    return min_obs, first


def pairwise_min_distance(rollout: Rollout) -> Separation:
    """Minimum robot-robot distance and surface gaps at every step.

    Vectorised over robots and chunked over time so that the ``(chunk, N, N)``
    temporaries stay within about 16 MB.

    Parameters
    ----------
    rollout : Rollout
        The episode.

    Returns
    -------
    Separation
        Per-step profiles; its ``overall_*`` properties give the episode minima.
    """
    min_dist, min_gap, pair, _ = _robot_scan(rollout, None)
    min_obs, _ = _obstacle_scan(rollout, None)
    return Separation(min_dist, min_gap, min_obs, pair)


# ---------------------------------------------------------------------- collisions
@dataclass(frozen=True)
class CollisionReport:
    """Collisions of an episode.

    Attributes
    ----------
    robot_pairs : list of tuple (int, int, int)
        ``(i, j, first_step)`` with ``i < j`` for every robot pair that ever
        overlapped beyond the tolerance, sorted by ``(first_step, i, j)``.
    obstacle_hits : list of tuple (int, int, int)
        ``(i, k, first_step)`` for every robot ``i`` / obstacle ``k`` overlap.
    colliding_robots : numpy.ndarray of bool, shape (N,)
        Robots involved in at least one collision of either kind.
    tolerance : float
        The tolerance used [m].
    """

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
        """Number of distinct colliding robot-obstacle pairs."""
        return len(self.obstacle_hits)

    @property
    def n_colliding_robots(self) -> int:
        """Number of robots involved in at least one collision."""
        return int(self.colliding_robots.sum())

    @property
    def any(self) -> bool:
        """Whether anything collided."""
        return bool(self.robot_pairs or self.obstacle_hits)


def _first_hits(first: np.ndarray, hit: np.ndarray, offset: int) -> None:
    """Record in ``first`` (``-1`` = none yet) the first chunk step where ``hit`` is True."""
    any_ = hit.any(axis=0)
    new = any_ & (first < 0)
    if new.any():
        first[new] = np.argmax(hit, axis=0)[new] + offset


def _sorted_triples(first: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> list[tuple[int, int, int]]:
    triples = zip(rows.tolist(), cols.tolist(), first.tolist())
    return sorted(triples, key=lambda t: (t[2], t[0], t[1]))


def collisions(rollout: Rollout, tolerance: float = COLLISION_TOLERANCE) -> CollisionReport:
    """Robot-robot and robot-obstacle overlaps beyond ``tolerance``.

    A robot pair collides at step ``k`` if ``|p_i - p_j| < r_i + r_j - tolerance``;
    a robot and an obstacle if ``|p_i - o_k| < r_i + R_k - tolerance``.

    Parameters
    ----------
    rollout : Rollout
        The episode.
    tolerance : float, default 1e-3
        Overlap [m] tolerated before a contact counts as a collision.

    Returns
    -------
    CollisionReport
        Colliding pairs with their first step, and the robots involved.
    """
    tol = _check_tolerance("tolerance", tolerance)
    first_r = _robot_scan(rollout, tol)[3]
    first_o = _obstacle_scan(rollout, tol)[1]
    assert first_r is not None and first_o is not None
    return _collision_report(rollout, tol, first_r, first_o)


def _collision_report(
    rollout: Rollout, tol: float, first_r: np.ndarray, first_o: np.ndarray
) -> CollisionReport:
    """Assemble a :class:`CollisionReport` from first-collision-step matrices."""
    colliding = np.zeros(rollout.n_robots, dtype=np.bool_)
    ii, jj = np.nonzero(first_r >= 0)
    robot_pairs = _sorted_triples(first_r[ii, jj], ii, jj)
    colliding[ii] = True
    colliding[jj] = True
    ii, kk = np.nonzero(first_o >= 0)
    obstacle_hits = _sorted_triples(first_o[ii, kk], ii, kk)
    colliding[ii] = True
    return CollisionReport(robot_pairs, obstacle_hits, colliding, tol)


def safe_rate(rollout: Rollout, tolerance: float = COLLISION_TOLERANCE) -> float:
    """Fraction of robots that never collide with a robot or an obstacle (GCBF+'s safety rate).

    Parameters
    ----------
    rollout : Rollout
        The episode.
    tolerance : float, default 1e-3
        Collision tolerance [m], see :func:`collisions`.

    Returns
    -------
    float
        In ``[0, 1]``.
    """
    return float(1.0 - np.mean(collisions(rollout, tolerance).colliding_robots))


# ------------------------------------------------------------------------ deadlock
def _longest_runs(mask: np.ndarray) -> np.ndarray:
    """Longest run of consecutive True per column of a ``(T, N)`` bool array (in samples)."""
    T, N = mask.shape
    padded = np.zeros((N, T + 2), dtype=np.int8)
    padded[:, 1:-1] = mask.T
    d = np.diff(padded, axis=1)
    sr, st = np.nonzero(d == 1)  # run starts, row-major: sorted by robot then time
    _, et = np.nonzero(d == -1)  # run ends (exclusive), same order
    out = np.zeros(N, dtype=np.int64)
    np.maximum.at(out, sr, et - st)
    return out


def longest_stall(rollout: Rollout, speed_threshold: float = 0.05, goal_tolerance: float = 0.1) -> np.ndarray:
    """Longest time each robot spends slow while away from its goal.

    A robot is *stalled* at step ``k`` if ``|dp_i(k)| < speed_threshold`` and
    ``|p_i(k) - g_i| > goal_tolerance``.  A run of stalled steps from ``a`` to
    ``b`` lasts ``(b - a) * dt``.

    Parameters
    ----------
    rollout : Rollout
        The episode.
    speed_threshold : float, default 0.05
        Control-point speed [m/s] below which a robot counts as slow.
    goal_tolerance : float, default 0.1
        Distance to the goal [m] within which a slow robot is simply done.

    Returns
    -------
    numpy.ndarray, shape (N,)
        Longest stall duration [s]; ``-dt`` marks robots never stalled.
    """
    v_thr = _check_tolerance("speed_threshold", speed_threshold)
    g_tol = _check_tolerance("goal_tolerance", goal_tolerance)
    speed = np.linalg.norm(rollout.velocities, axis=-1)
    far = np.linalg.norm(rollout.positions - rollout.goals[None], axis=-1) > g_tol
    runs = _longest_runs((speed < v_thr) & far)
    return (runs - 1) * rollout.dt


def deadlocked_robots(
    rollout: Rollout,
    speed_threshold: float = 0.05,
    dwell_time: float = 1.0,
    goal_tolerance: float = 0.1,
) -> np.ndarray:
    """Robots that stay slow, away from their goal, for at least ``dwell_time``.

    Parameters
    ----------
    rollout : Rollout
        The episode.
    speed_threshold : float, default 0.05
        Control-point speed [m/s] below which a robot counts as slow.
    dwell_time : float, default 1.0
        Minimum duration [s] of an uninterrupted stall, measured as
        ``(b - a) * dt`` for a run of steps ``a..b`` (see :func:`longest_stall`).
    goal_tolerance : float, default 0.1
        Distance to the goal [m] within which a slow robot is not stuck.

    Returns
    -------
    numpy.ndarray of bool, shape (N,)
        True for deadlocked robots.
    """
    dwell = _check_tolerance("dwell_time", dwell_time)
    stall = longest_stall(rollout, speed_threshold, goal_tolerance)
    # Half a step of slack so that float rounding of k * dt never flips the verdict.
    return (stall >= 0) & (stall >= dwell - 0.5 * rollout.dt)


# -------------------------------------------------------------------------- solver
def _classify_status(status: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boolean masks ``(relaxed, failed)`` from status strings (case-insensitive substrings)."""
    low = np.char.lower(status.astype(np.str_))
    failed = np.zeros(low.shape, dtype=np.bool_)
    relaxed = np.zeros(low.shape, dtype=np.bool_)
    for m in _FAILED_MARKERS:
        failed |= np.char.find(low, m) >= 0
    for m in _RELAXED_MARKERS:
        relaxed |= np.char.find(low, m) >= 0
    return relaxed & ~failed, failed


def solver_stats(rollout: Rollout) -> dict[str, Any]:
    """Solver health over the episode.

    Status strings are classified case-insensitively: containing one of
    ``fail``, ``infeas``, ``error``, ``max_iter``, ``unsolved``, ``nan``,
    ``diverg`` means *failed*; otherwise containing ``relax`` or ``slack``
    means *relaxed*; anything else (``"optimal"``, ``"solved"``, ...) is fine.
    Missing fields give ``None`` entries.

    Parameters
    ----------
    rollout : Rollout
        The episode.

    Returns
    -------
    dict
        ``relaxed_fraction``, ``failed_fraction``, ``unsafe_fraction`` (steps
        reported outside the safe set), ``backup_fraction`` (steps in which the
        backup layer braked some robot), ``backup_robot_fraction`` (robot-steps
        braked), ``status_counts`` (dict), ``solve_time_median``,
        ``solve_time_mean``, ``solve_time_max`` [s], ``slack_max``,
        ``slack_positive_fraction`` (steps with ``slack > 0``).
    """
    out: dict[str, Any] = {
        "relaxed_fraction": None,
        "failed_fraction": None,
        "unsafe_fraction": None,
        "backup_fraction": None,
        "backup_robot_fraction": None,
        "status_counts": None,
        "solve_time_median": None,
        "solve_time_mean": None,
        "solve_time_max": None,
        "slack_max": None,
        "slack_positive_fraction": None,
    }
    if rollout.solver_status is not None:
        relaxed, failed = _classify_status(rollout.solver_status)
        out["relaxed_fraction"] = float(relaxed.mean())
        out["failed_fraction"] = float(failed.mean())
        out["unsafe_fraction"] = float(np.mean(np.char.lower(rollout.solver_status.astype(np.str_)) == "unsafe"))
        names, counts = np.unique(rollout.solver_status, return_counts=True)
        out["status_counts"] = {str(n): int(c) for n, c in zip(names, counts)}
    if rollout.backup is not None:
        out["backup_fraction"] = float(rollout.backup.any(axis=1).mean())
        out["backup_robot_fraction"] = float(rollout.backup.mean())
    if rollout.solve_time is not None:
        st = rollout.solve_time
        out["solve_time_median"] = float(np.median(st))
        out["solve_time_mean"] = float(np.mean(st))
        out["solve_time_max"] = float(np.max(st))
    if rollout.slack is not None:
        out["slack_max"] = float(np.max(rollout.slack))
        out["slack_positive_fraction"] = float(np.mean(rollout.slack > 0))
    return out


# ------------------------------------------------------------------------- summary
def summarize(
    rollout: Rollout,
    *,
    collision_tolerance: float = COLLISION_TOLERANCE,
    goal_tolerance: float = 0.1,
    speed_threshold: float = 0.05,
    dwell_time: float = 1.0,
) -> dict[str, Any]:
    """All headline numbers of an episode as a JSON-friendly dict.

    Parameters
    ----------
    rollout : Rollout
        The episode.
    collision_tolerance : float, default 1e-3
        See :func:`collisions`.
    goal_tolerance : float, default 0.1
        See :func:`reach_rate` and :func:`deadlocked_robots`.
    speed_threshold, dwell_time : float
        See :func:`deadlocked_robots`.

    Returns
    -------
    dict
        Python ``int`` / ``float`` / ``str`` / ``None`` values (``None`` where
        the rollout lacks the field a metric needs; ``inf`` gaps, e.g. without
        obstacles, are reported as ``None`` too).  Keys: ``n_robots``,
        ``n_steps``, ``duration``, ``intervention_time``,
        ``intervention_time_max``, ``rmse``, ``mae``, ``std``,
        ``max_tracking_error``, ``min_center_distance``, ``min_robot_gap``,
        ``min_obstacle_gap``, ``n_collision_pairs``, ``n_obstacle_collisions``,
        ``n_colliding_robots``, ``safe_rate``, ``final_error_mean``,
        ``final_error_max``, ``final_tracking_error_mean``, ``reach_rate``,
        ``n_deadlocked``, ``triggered_fraction`` and the entries of
        :func:`solver_stats` except ``status_counts``.
    """

    def finite(x: float) -> float | None:
        return float(x) if math.isfinite(x) else None

    tol = _check_tolerance("collision_tolerance", collision_tolerance)
    stats = tracking_stats(rollout)
    min_dist, min_gap, pair, first_r = _robot_scan(rollout, tol)
    min_obs, first_o = _obstacle_scan(rollout, tol)
    sep = Separation(min_dist, min_gap, min_obs, pair)
    assert first_r is not None and first_o is not None
    col = _collision_report(rollout, tol, first_r, first_o)
    fe = final_errors(rollout)
    out: dict[str, Any] = {
        "n_robots": rollout.n_robots,
        "n_steps": rollout.n_steps,
        "duration": rollout.duration,
        "intervention_time": None,
        "intervention_time_max": None,
    }
    if rollout.avoiding is not None:
        it = intervention_times(rollout)
        out["intervention_time"] = float(it.mean())
        out["intervention_time_max"] = float(it.max())
    out.update(
        rmse=stats["rmse"],
        mae=stats["mae"],
        std=stats["std"],
        max_tracking_error=stats["max"],
        min_center_distance=finite(sep.overall_min_center_distance),
        min_robot_gap=finite(sep.overall_min_robot_gap),
        min_obstacle_gap=finite(sep.overall_min_obstacle_gap),
        n_collision_pairs=col.n_robot_pairs,
        n_obstacle_collisions=col.n_obstacle_hits,
        n_colliding_robots=col.n_colliding_robots,
        safe_rate=float(1.0 - col.colliding_robots.mean()),
        final_error_mean=float(fe.mean()),
        final_error_max=float(fe.max()),
        final_tracking_error_mean=float(final_tracking_errors(rollout).mean()),
        reach_rate=reach_rate(rollout, goal_tolerance),
        n_deadlocked=int(deadlocked_robots(rollout, speed_threshold, dwell_time, goal_tolerance).sum()),
        triggered_fraction=None if rollout.triggered is None else float(rollout.triggered.mean()),
    )
    solver = solver_stats(rollout)
    solver.pop("status_counts")
    out.update(solver)
    return out


def format_summary(summary: dict[str, Any], *, precision: int = 4) -> str:
    """Render a :func:`summarize` dict as an aligned two-column text table.

    Parameters
    ----------
    summary : dict
        Output of :func:`summarize` (any flat dict works).
    precision : int, default 4
        Digits after the decimal point for floats.

    Returns
    -------
    str
        One ``name  value`` line per entry; ``None`` shows as ``-``.
    """
    if not summary:
        return ""
    width = max(len(str(k)) for k in summary)
    lines = []
    for key, value in summary.items():
        if value is None:
            text = "-"
        elif isinstance(value, bool):
            text = str(value)
        elif isinstance(value, (int, np.integer)):
            text = str(int(value))
        elif isinstance(value, (float, np.floating)):
            text = f"{float(value):.{precision}f}"
        else:
            text = str(value)
        lines.append(f"{str(key):<{width}}  {text:>12}")
    return "\n".join(lines)
