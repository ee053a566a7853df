"""The filter's first stages: the pairs within the sensing range, and their barrier rows.

One row per pair, linear in the wheel accelerations, the margins added to the safety distance; :func:`numpy_rows`
(any barrier and strategy) and :class:`CompiledRows` (:mod:`~.rows_kernel`) give the same numbers bit for bit.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from aasoatt_env.compiled import kernels
from aasoatt_env.model.geometry import brute_candidates, obstacle_pairs, robot_pairs, row_dot, uses_brute_force
from aasoatt_env.model.params import Team
from aasoatt_env.safety.barriers import PairGeometry, barrier_rows, get_barrier
from aasoatt_env.safety.config import MARGIN_FADE_SPEED, FilterConfig, auto_margin
from aasoatt_env.safety.deadlock import STRATEGIES, rotation

if TYPE_CHECKING:  # pragma: no cover
    from aasoatt_env.safety.stages import StepInput

__all__ = ["CompiledRows", "Pairs", "Rows", "find_pairs", "gap_initial", "kernel_rows", "numpy_rows"]


class Pairs(NamedTuple):
    """The pairs of one step within the sensing range."""

    robots: np.ndarray  #: ``(P, 2)`` robot pairs ``(i, j)``, ``i < j``, sorted (of one group with ``Team.group``)
    obstacles: np.ndarray  #: ``(Q, 2)`` robot-obstacle pairs ``(i, k)``

    def vectors(self, p: np.ndarray, centers: np.ndarray | None) -> np.ndarray:
        """``(P + Q, 2)``: from each pair's robot ``i`` to the other member."""
        out = p[self.robots[:, 1]] - p[self.robots[:, 0]]
        if self.obstacles.shape[0]:
            out = np.concatenate((out, centers[self.obstacles[:, 1]] - p[self.obstacles[:, 0]]))
        return out

    def index(self) -> np.ndarray:
        """``(P + Q, 2)`` pairs, an obstacle pair as ``(i, -1)``."""
        if not self.obstacles.shape[0]:
            return self.robots
        obs = np.stack((self.obstacles[:, 0], np.full(self.obstacles.shape[0], -1, np.intp)), axis=1)
        return np.concatenate((self.robots, obs))


class Rows(NamedTuple):
    """The barrier rows of one step: ``Gi du_ri + Gj du_rj <= rhs``, one per pair, robot pairs first."""

    ri: np.ndarray  #: ``(m,)``
    rj: np.ndarray  #: ``(m,)``, ``-1`` on an obstacle row (robot ``ri``'s alone)
    Gi: np.ndarray  #: ``(m, 2)``
    Gj: np.ndarray  #: ``(m, 2)``, zero on obstacle rows
    rhs: np.ndarray  #: ``(m,)``
    pairs: np.ndarray  #: ``(m, 2)``: ``(i, j)``, or ``(i, -1 - k)`` for obstacle ``k``
    keys: np.ndarray  #: ``(m,)`` warm-start keys, increasing: ``i * B + j``, ``i * B + N + k`` for obstacle ``k``
    barrier_min: float  #: smallest barrier value ``h`` with the true safety distance (``inf`` without rows)
    gap_min: float  #: smallest surface gap ``|p_ij| - d_s`` (``D - max d_s`` without pairs)

    @property
    def m(self) -> int:
        """Number of rows."""
        return int(self.rhs.shape[0])

    def values(self, du: np.ndarray) -> np.ndarray:
        """``Gi du_ri + Gj du_rj`` of every row."""
        return row_dot(self.Gi, du[self.ri]) + row_dot(self.Gj, du[np.maximum(self.rj, 0)])


def find_pairs(team: Team, p: np.ndarray, sensing_range: float, obstacles: tuple | None, compiled: bool) -> Pairs:
    """The robot pairs and robot-obstacle pairs within ``sensing_range`` of the control points ``p``."""
    if compiled and uses_brute_force(team.n, team.group):
        robots = kernels("rows").pairs_within(p, *brute_candidates(team.n, team.group), sensing_range * sensing_range)
    else:
        robots = robot_pairs(p, sensing_range, groups=team.group, compiled=compiled)
    if obstacles is None:
        return Pairs(robots, _NO_PAIRS)
    return Pairs(robots, obstacle_pairs(p, obstacles[0], obstacles[1], sensing_range, groups=team.group,
                                        obstacle_groups=obstacles[2]))


_NO_PAIRS = np.empty((0, 2), dtype=np.intp)


def gap_initial(cfg: FilterConfig, team: Team) -> float:
    """The smallest gap reported without pairs: ``D - max d_s``."""
    return cfg.sensing_range - 2.0 * float(team.radius.max(initial=0.0))


def numpy_rows(cfg: FilterConfig, s: StepInput, pairs: Pairs, triggered: np.ndarray) -> Rows:
    """The rows of ``cfg.barrier`` for every pair (eqn.12c's strategy rotates those of the ``triggered`` robots)."""
    team, p, v, adot = s.team, s.p, s.v, s.adot
    n, rad, amax = p.shape[0], team.radius, team.max_point_accel
    ri, rj = pairs.robots[:, 0], pairs.robots[:, 1]
    state = np.concatenate((p, v, adot), axis=1)  # (one gather per side)
    rel = state[ri] - state[rj]
    gp, gv, ga = rel[:, 0:2], rel[:, 2:4], rel[:, 4:6]
    ds, ap, out = rad[ri] + rad[rj], amax[ri] + amax[rj], pairs.robots
    n_obs = 0 if s.obstacles is None else s.obstacles[1].shape[0]
    if pairs.obstacles.shape[0]:
        oi, ok = pairs.obstacles[:, 0], pairs.obstacles[:, 1]
        oc, orad = s.obstacles[0], s.obstacles[1]
        gp, gv, ga = np.concatenate((gp, p[oi] - oc[ok])), np.concatenate((gv, v[oi])), np.concatenate((ga, adot[oi]))
        ds, ap = np.concatenate((ds, rad[oi] + orad[ok])), np.concatenate((ap, amax[oi]))
        ri, rj = np.concatenate((ri, oi)), np.concatenate((rj, np.full(oi.shape[0], -1, np.intp)))
        out = np.concatenate((out, np.stack((oi, -1 - ok), axis=1)))
    margin = cfg.pair_margin(gv)
    if cfg.speed_margin:
        sp2 = row_dot(v, v)
        margin = margin + cfg.speed_margin * (sp2[ri] + np.where(rj >= 0, sp2[np.maximum(rj, 0)], 0.0))
    barrier = get_barrier(cfg.barrier)
    g = PairGeometry(ri, rj, gp, gv, ga, ds, ds, ap)
    h = barrier.value(g, cfg)
    gap = np.sqrt(row_dot(gp, gp)) - ds
    strategy = STRATEGIES[cfg.deadlock]
    if strategy.rotates_rows:
        on = triggered[ri] | ((rj >= 0) & triggered[np.maximum(rj, 0)])
        g = g._replace(p=strategy.rotate_rows(gp, on, rotation(cfg.rotation_deg)))
    c, rhs, keep = barrier_rows(cfg.barrier, g._replace(d_s=ds + margin), cfg)
    ri, rj, out = ri[keep], rj[keep], out[keep]
    obs = rj < 0
    Gi = np.einsum("pki,pk->pi", s.A[ri], c)
    Gj = -np.einsum("pki,pk->pi", s.A[np.maximum(rj, 0)], c)
    Gj[obs] = 0.0
    keys = ri.astype(np.int64) * (n + n_obs + 1) + np.where(obs, n - 1 - out[:, 1], rj)
    return Rows(ri, rj, Gi, Gj, rhs, out, keys, float(h.min(initial=np.inf)),
                float(gap.min(initial=gap_initial(cfg, team))))


class CompiledRows:
    """:func:`numpy_rows` by the barrier's compiled kernel, the same numbers (for strategies that keep the rows)."""

    def __init__(self, cfg: FilterConfig) -> None:
        self._kernel = getattr(kernels("rows"), get_barrier(cfg.barrier).kernel)
        self._gains = (cfg.k1, cfg.k2, np.nan if cfg.safety_margin is None else float(cfg.safety_margin),
                       auto_margin(cfg.dt), MARGIN_FADE_SPEED, cfg.speed_margin)
        self._team, self._gap = None, 0.0

    def __call__(self, cfg: FilterConfig, s: StepInput, pairs: Pairs, triggered: np.ndarray) -> Rows:
        """The step's rows (``triggered`` is not read: the strategy keeps the rows)."""
        return kernel_rows(self._kernel(*self.args(cfg, s, pairs)))

    def args(self, cfg: FilterConfig, s: StepInput, pairs: Pairs) -> tuple:
        """The kernel's arguments for this step."""
        if s.team is not self._team:
            self._team, self._gap = s.team, gap_initial(cfg, s.team)
        oc, orad = (_NO_CENTERS, _NO_RADII) if s.obstacles is None else s.obstacles[:2]
        return (s.p, s.v, s.adot, s.A, s.team.radius, pairs.robots, pairs.obstacles, oc, orad, *self._gains, self._gap)


def kernel_rows(out: tuple) -> Rows:
    """:class:`Rows` of a rows kernel's ``(ri, rj, Gi, Gj, rhs, pairs, keys, h_min, gap_min)``."""
    return Rows(*out[:7], float(out[7]), float(out[8]))


_NO_CENTERS = np.empty((0, 2))
_NO_RADII = np.empty(0)
