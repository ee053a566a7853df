"""The step of the env and the batch: ``K`` teams in stacked arrays, every operation per robot or per team."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from aasoatt_env.compiled import available as compiled_available
from aasoatt_env.errors import ActionError
from aasoatt_env.model import dynamics
from aasoatt_env.model.dynamics import Kinematics
from aasoatt_env.model.geometry import Proximity, neighbourhood
from aasoatt_env.model.params import Team, stack_teams
from aasoatt_env.model.tracking import point_accel_to_du
from aasoatt_env.sim.observations import build_observations
from aasoatt_env.sim.protocol import FilterInput, FilterOutput
from aasoatt_env.sim.references import ReferenceStack
from aasoatt_env.sim.rewards import rewards

__all__ = ["TeamStack"]


def _part(x: np.ndarray, sl: slice | None) -> np.ndarray:
    """Rows ``sl`` of a stacked array as a fresh array, as a team's own env hands its filter (None: all of it)."""
    return x if sl is None else x[sl].copy()


def _intervened(out: Any) -> np.ndarray:
    """A filter output's ``intervened`` flags, or ``correction > 0`` for outputs without them."""
    flag = getattr(out, "intervened", None)
    return np.asarray(flag if flag is not None else np.asarray(out.correction) > 0.0, dtype=bool)


class TeamStack:
    """The state and the step of ``K`` teams of ``N`` robots.

    A subclass sets the env's settings, ``_bases`` (the teams' envs, whose ``_control_filter`` is read at every
    step), ``_grouped`` (one filter for all teams, or None), ``_offset`` (first team's number in messages).
    """

    _stack_teams: ClassVar[bool] = True  # one Team with `group` labels (False: the one team as it is)

    def _init_stack(self, k: int, n: int) -> None:
        self._k, self._n = k, n
        self._layouts: list[Any] = [None] * k
        self._teams: list[Team | None] = [None] * k
        self._team: Team | None = None
        self._team_ids: list[int] | None = None
        self._times, self._steps, self._max_steps = np.zeros(k), np.zeros(k, np.int64), np.zeros(k, np.int64)
        self._pose, self._u, self._last_action = np.zeros((k * n, 3)), np.zeros((k * n, 2)), np.zeros((k * n, 2))
        self._active, self._saturated = np.zeros(k * n, dtype=bool), np.zeros(k * n, dtype=bool)
        self._clearance = np.full(k * n, np.inf)
        self._kin: Kinematics | None = None
        self._filter_resets: list[int] = []
        self._compiled = compiled_available()  # the compiled forms of the env's stages, where numba imports

    def _take_team(self, k: int, src: TeamStack, j: int) -> None:
        n = self._n
        a, b = slice(k * n, (k + 1) * n), slice(j * n, (j + 1) * n)
        self._layouts[k], self._teams[k] = src._layouts[j], src._teams[j]
        for name in ("_pose", "_u", "_active", "_saturated", "_last_action", "_clearance"):
            getattr(self, name)[a] = getattr(src, name)[b]
        for name in ("_times", "_steps", "_max_steps"):
            getattr(self, name)[k] = getattr(src, name)[j]

    def _restack(self) -> None:
        """Rebuild the team, kinematics, goals, references and obstacles after (some teams') resets."""
        ids = [id(t) for t in self._teams]
        if ids != self._team_ids:
            self._team = stack_teams(self._teams) if self._stack_teams else self._teams[0]
            self._team_ids = ids
            r = self._team.radius.reshape(self._k, self._n)
            self._equal_radii = r.min(axis=1) == r.max(axis=1)
        self._kin = dynamics.kinematics(self._team, self._pose, self._u, self._compiled)
        layouts = self._layouts
        self._goals = np.concatenate([np.asarray(lay.reference.goals, dtype=np.float64) for lay in layouts])
        self._ref_stack = ReferenceStack([lay.reference for lay in layouts])
        uniform = len({lay.obstacle_radii.shape[0] for lay in layouts}) == 1
        self._ocenters = np.stack([lay.obstacle_centers for lay in layouts]) if uniform else None
        self._oradii = np.stack([lay.obstacle_radii for lay in layouts]) if uniform else None
        self._stackable = uniform  # one neighbour query for all (ragged obstacles: one per team)
        m = self._ocenters.shape[1] if uniform else 0
        self._obs_obstacles = (self._ocenters.reshape(-1, 2), self._oradii.ravel(),
                               np.repeat(np.arange(self._k) * m, self._n) if m and self._k > 1 else None
                               ) if uniform else None  # as build_observations reads them (None: ragged)
        if self._grouped is not None:
            n = self._n
            rows = np.concatenate([np.arange(k * n, (k + 1) * n) for k in self._filter_resets]
                                  + [np.empty(0, dtype=np.intp)])
            self._grouped.reset_rows(rows, self._team)
            self._group_obstacles = (np.concatenate([lay.obstacle_centers for lay in layouts]).reshape(-1, 2),
                                     np.concatenate([lay.obstacle_radii for lay in layouts]),
                                     np.concatenate([np.full(lay.obstacle_radii.shape[0], k, dtype=np.int64)
                                                     for k, lay in enumerate(layouts)]))
        self._filter_resets = []
        self._ref_now = self._references()

    def _references(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every team's reference at its own time (read-only: shared with the filter's input)."""
        ref = self._ref_stack(self._times)
        for r in ref:
            r.flags.writeable = False
        return ref

    def _nominal_du(self, act: np.ndarray, kin: Kinematics) -> np.ndarray:
        if self.action_mode == "wheel":
            return act * self._team.max_wheel_accel[:, None]
        return point_accel_to_du(kin, act * self._team.max_point_accel[:, None])

    def _physics(self, act: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, list[list[FilterOutput]]]:
        """Hold ``act`` for ``decision_interval`` physics steps (all or none): saturated, clearance between, outputs."""
        team, dt, steps = self._team, self.dt, self.decision_interval
        pose, u, kin = self._pose, self._u, self._kin
        any_frozen = not self._active.all()
        frozen = ~self._active if any_frozen else None
        saturated = np.zeros(pose.shape[0], dtype=bool)
        between = None
        filters = [b._control_filter for b in self._bases]
        outputs: list[list[FilterOutput]] = []
        times = self._times
        try:
            for sub in range(steps):
                lo, hi = dynamics.input_bounds(team, u, dt)
                du_nom = self._nominal_du(act, kin)
                if any_frozen:
                    du_nom[frozen] = 0.0
                du = du_nom
                if filters[0] is not None:
                    du, outs = self._filter(filters, sub, pose, u, kin, lo, hi, du_nom)
                    outputs.append(outs)
                clipped = np.minimum(np.maximum(du, lo), hi)
                if (clipped != du).any():
                    saturated |= np.abs(clipped - du).max(axis=1) > 1e-9
                new_pose, new_u = dynamics.integrate(team, pose, u, clipped, dt, self._compiled)
                if any_frozen:
                    new_pose[frozen], new_u[frozen] = pose[frozen], 0.0
                pose, u = new_pose, new_u
                self._times = self._times + dt
                kin = dynamics.kinematics(team, pose, u, self._compiled)
                if sub < steps - 1:
                    gaps = self._neighbours(kin.p, 0).clearance
                    between = gaps if between is None else np.minimum(between, gaps)
            ref = self._references()  # (a reference that fails here leaves the state as it was)
        except BaseException:
            self._times = times
            raise
        self._pose, self._u, self._kin, self._ref_now = pose, u, kin, ref
        return saturated, between, outputs

    def _filter(self, filters: list[Any], sub: int, pose: np.ndarray, u: np.ndarray, kin: Kinematics,
                lo: np.ndarray, hi: np.ndarray, du_nom: np.ndarray) -> tuple[np.ndarray, list[FilterOutput]]:
        """The applied ``du`` of all teams and the filter outputs: one grouped call, or one call per team."""
        ref = self._ref_now if sub == 0 else self._references()
        if self._grouped is not None:
            inp = FilterInput(float(self._times[0]), self.dt, self._team, pose, u, kin, lo, hi,
                              ref, *self._group_obstacles)
            out = self._grouped(inp, du_nom)
            return self._checked(out, None, du_nom.shape[0]), [out]
        n, one = self._n, self._k == 1
        du = du_nom if one else np.empty_like(du_nom)
        outs = []
        for k, filt in enumerate(filters):
            sl = None if one else slice(k * n, (k + 1) * n)
            lay = self._layouts[k]
            inp = FilterInput(float(self._times[k]), self.dt, self._teams[k], _part(pose, sl), _part(u, sl),
                              kin if one else Kinematics(*(_part(x, sl) for x in kin)), _part(lo, sl), _part(hi, sl),
                              tuple(_part(r, sl) for r in ref), lay.obstacle_centers, lay.obstacle_radii)
            out = filt(inp, _part(du_nom, sl))
            d = self._checked(out, k, n)
            if one:
                du = d
            else:
                du[sl] = d
            outs.append(out)
        return du, outs

    def _checked(self, out: Any, k: int | None, rows: int) -> np.ndarray:
        """A filter output's ``du``: finite, ``(rows, 2)`` (``k``: the team of a per-team call)."""
        d = np.asarray(out.du, dtype=np.float64)
        if d.shape != (rows, 2) or not np.isfinite(d).all():
            who = ("the grouped control filter" if k is None else "control filter" if self._k == 1
                   else f"control filter of team {k + self._offset}")
            raise ActionError(f"{who} returned shape {d.shape} or non-finite values, expected finite ({rows}, 2)")
        return d

    def _neighbours(self, p: np.ndarray, k: int) -> Proximity:
        """:func:`~aasoatt_env.model.geometry.neighbourhood` of every team (indices into the stack)."""
        if self._stackable:
            return neighbourhood(p, self._team.radius, self._ocenters, self._oradii, k, self._k, self._equal_radii,
                                 compiled=self._compiled)
        n = self._n
        parts = [neighbourhood(p[j * n:(j + 1) * n], t.radius, lay.obstacle_centers, lay.obstacle_radii, k,
                               compiled=self._compiled)
                 for j, (t, lay) in enumerate(zip(self._teams, self._layouts))]
        return Proximity(np.concatenate([np.where(q.idx >= 0, q.idx + j * n, -1) for j, q in enumerate(parts)]),
                         np.concatenate([q.dist for q in parts]),
                         np.concatenate([q.obstacle_gaps for q in parts]) if self._ocenters is not None else None,
                         np.concatenate([q.clearance for q in parts]))

    def _refresh(self, between: np.ndarray | None = None, reference: bool = True) -> None:
        """Reference, neighbour table, tracking error and clearance now (the smallest with ``between``'s)."""
        if reference:
            self._ref_now = self._references()
        self._prox = self._neighbours(self._kin.p, max(self.num_neighbors, 1))
        self._err = np.hypot(*(self._kin.p - self._ref_now[0]).T)
        clearance = self._prox.clearance
        self._clearance = clearance if between is None else np.minimum(clearance, between)
        self._collided = self._clearance < -self.collision_tolerance

    def _observations(self, j: int | None = None) -> np.ndarray:
        """Every robot's observation (``j``: team ``j``'s, with its own neighbour query)."""
        if j is None and self._obs_obstacles is None:  # teams with different numbers of obstacles: one call per team
            return np.concatenate([self._observations(j) for j in range(self._k)])
        sl, kin, (p_d, v_d, a_d) = slice(None), self._kin, self._ref_now
        if j is None:
            (centers, radii, offset), prox = self._obs_obstacles, self._prox
        else:
            sl, lay, offset = slice(j * self._n, (j + 1) * self._n), self._layouts[j], None
            centers, radii = lay.obstacle_centers, lay.obstacle_radii
            prox = neighbourhood(kin.p[sl], self._teams[j].radius, centers, radii, max(self.num_neighbors, 1),
                                 compiled=self._compiled)
        return build_observations(
            p=kin.p[sl], v=kin.v[sl], theta=self._pose[sl, 2], u=self._u[sl], p_d=p_d[sl], v_d=v_d[sl], a_d=a_d[sl],
            goals=self._goals[sl], radii=self._team.radius[sl], obstacle_centers=centers, obstacle_radii=radii,
            sensing_range=self.sensing_range, k_robots=self.num_neighbors, k_obstacles=self.num_obstacles,
            prox=prox, obstacle_offset=offset, compiled=self._compiled)

    def _decide(self, act: np.ndarray, saturated: np.ndarray, between: np.ndarray | None,
                outputs: list[list[FilterOutput]]) -> tuple:
        """``(obs, rewards, collided, terminated, truncated, correction, goal_distance)`` of the decision just stepped.

        ``terminated``, ``correction`` (the largest) and ``goal_distance`` are None where not needed.
        """
        self._last_action, self._saturated = act, saturated
        self._steps += 1
        self._refresh(between, reference=False)
        collided = self._collided
        corr = None
        if outputs:
            per_step = [np.asarray(outs[0].correction, dtype=np.float64) if len(outs) == 1 else
                        np.concatenate([np.asarray(o.correction, dtype=np.float64) for o in outs]) for outs in outputs]
            corr = per_step[0] if len(per_step) == 1 else np.max(per_step, axis=0)
        goal = np.hypot(*(self._kin.p - self._goals).T) if self.reward_config.goal_bonus else None
        rew = rewards(self.reward_config, self._err, collided, act, goal,
                      None if corr is None else corr / self._team.max_wheel_accel)
        obs = self._observations()
        terminated = None
        if self.terminate_on_collision:
            terminated = collided & self._active
            self._active = self._active & ~terminated
        return obs, rew, collided, terminated, self._steps >= self._max_steps, corr, goal

    @staticmethod
    def _filter_flags(outputs: list[list[FilterOutput]]) -> tuple[np.ndarray, np.ndarray]:
        """``intervened`` and ``avoiding`` of every robot at any physics step of the decision."""
        return (np.any([np.concatenate([_intervened(o) for o in outs]) for outs in outputs], axis=0),
                np.any([np.concatenate([np.asarray(o.avoiding, dtype=bool) for o in outs]) for outs in outputs],
                       axis=0))
