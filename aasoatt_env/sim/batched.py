"""``BatchedAASOATTEnv``: several independent teams stepped by one vectorised physics call.

RL trainers run ``n_envs`` copies of an env in one process.  Stepping them one
by one pays numpy's per-call overhead ``n_envs`` times at every physics step
(20 per decision by default), on arrays of a handful of robots.  This class
keeps the state of all teams in stacked arrays ``(n_envs * N, ...)`` and runs
each physics step once for everyone: nominal accelerations, input bounds,
integration, kinematics and clearances; the observations, rewards and infos of
a decision are also computed once for all teams.

Without a filter, or behind one with ``group_filter=False``, it is
**bit-identical** to ``n_envs`` separate :class:`~aasoatt_env.sim.env.AASOATTParallelEnv`
stepped with the same actions (``tests/test_batched.py`` checks every array):
every operation is either per robot or per team (distances never cross teams),
and each team keeps its own scenario generator, clock, horizon and control filter.
Behind the filter this holds with the QP solvers whose answer is a function of
the problem alone (``quadprog``, ``daqp``, ``ldp``); the default ``proxsuite``
answers the same problem with differences in the last bits (~1e-15) depending
on where its work arrays lie in memory, so batch and separate envs agree to
rounding there, not bit for bit.

Control filter: teams behind a filter (their envs have one installed, e.g. by
:class:`~aasoatt_env.safety.wrapper.AASOATTFilter`) are filtered at every physics
step.  When the teams' filters can stand in for each other
(``grouped``, :class:`~aasoatt_env.sim.protocol.GroupableFilter`; the
:class:`~aasoatt_env.safety.core.SafetyFilter` can when all share one
configuration) and ``group_filter=True`` (default), one filter call takes all
teams stacked, ``team.group`` keeping them apart: one neighbour search, one QP
of independent blocks and one backup check per physics step instead of ``K``.
The answers are each team's own up to rounding (the stacked QP is solved in one
piece), so trajectories agree with separate envs to rounding, not bit for bit.
``group_filter=False`` calls each team's own filter with its own
:class:`~aasoatt_env.sim.protocol.FilterInput` (one call per team), which is
bit-identical to separate envs with the deterministic QP solvers below.

API (the style of Gymnasium's vector envs; ``K = num_envs`` teams of ``N`` robots,
``D`` observation entries):

===============================  ==========================================================
``reset(seed, options)``         ``obs (K, N, D) float32, infos``; ``seed``: None, an int
                                 (team ``k`` gets ``seed + k``) or one int/None per team
``step(actions (K, N, 2))``      ``obs, rewards (K, N), terminations (K, N), truncations
                                 (K, N), infos`` (arrays); actions of done agents are ignored
``live``                         ``(K, N)`` bool: agents that act at the next ``step``
``autoreset=True``               a team whose episode ended is reset inside ``step`` (its
                                 generator continues, no seed): ``obs`` holds the new
                                 episode's first observation, ``infos["final_obs"]`` the last
                                 one and ``infos["_final_obs"] (K,)`` which teams were reset
                                 (Gymnasium's same-step autoreset)
``infos``                        arrays of the step just taken (for a reset team: of its
                                 last step): ``tracking_error``, ``clearance``, ``collision``,
                                 ``saturated``, ``goal_distance`` ``(K, N)``, ``time (K,)``;
                                 behind a filter ``filter_intervened``, ``filter_avoiding``,
                                 ``filter_correction`` [rad/s^2] ``(K, N)`` (over the physics
                                 steps of the decision: any / any / largest)
``envs``                         the teams' own envs (layouts, filters, generators); call
                                 ``sync()`` before reading their state or rendering them
===============================  ==========================================================

An agent that terminates (``terminate_on_collision``) stays in the world as a
frozen disc until its team's episode ends, as in the single env; its rows of
``obs``/``rewards`` are still computed (``live`` says which rows count).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from gymnasium import spaces

from aasoatt_env.errors import ActionError, ConfigError, ResetNeeded
from aasoatt_env.model import dynamics
from aasoatt_env.model.dynamics import Kinematics
from aasoatt_env.model.geometry import KDTREE_MIN_ROBOTS, min_gaps
from aasoatt_env.model.params import Team, stack_teams
from aasoatt_env.sim.env import _NOMINAL_MAX, AASOATTParallelEnv
from aasoatt_env.sim.observations import Proximity, build_observations, proximity
from aasoatt_env.sim.protocol import FilterInput, GroupedControlFilter
from aasoatt_env.sim.references import ReferenceStack
from aasoatt_env.sim.rewards import rewards as reward_terms

__all__ = ["BatchedAASOATTEnv"]

_FULL_SORT_MAX = 64
"""As :data:`aasoatt_env.model.geometry._FULL_SORT_MAX`: full row sort up to this many robots."""


class BatchedAASOATTEnv:
    """``K`` teams of one scenario stepped together (see the module docstring).

    Parameters
    ----------
    env_fns : sequence of callables
        Each returns an :class:`~aasoatt_env.sim.env.AASOATTParallelEnv`, or a
        wrapper of one (e.g. :class:`~aasoatt_env.safety.wrapper.AASOATTFilter`:
        the filter it installs is used, its own ``step`` is not).  All must have
        the same agents, spaces, ``dt``, ``decision_interval``, action mode,
        observation slots, reward and termination settings.
    autoreset : bool
        Reset a team inside ``step`` when its episode ends (default), else
        ``step`` raises :class:`~aasoatt_env.errors.ResetNeeded` for a finished
        team until ``reset`` is called.
    group_filter : bool
        Filter all teams in one call when their filters allow it (module
        docstring); False: one call per team.
    team_offset : int
        Number of the first team in error messages (a shard of a larger batch,
        :class:`~aasoatt_env.sim.sharded.ShardedBatchedEnv`, names teams as the whole batch does).
    """

    metadata = {"autoreset_mode": "same_step"}

    def __init__(self, env_fns: Sequence[Callable[[], Any]], *, autoreset: bool = True,
                 group_filter: bool = True, team_offset: int = 0) -> None:
        if len(env_fns) < 1:
            raise ConfigError(f"env_fns: got {len(env_fns)} callables, expected at least 1")
        self.envs: list[Any] = [fn() for fn in env_fns]
        bases = [getattr(e, "unwrapped", e) for e in self.envs]
        for k, b in enumerate(bases):
            if not isinstance(b, AASOATTParallelEnv):
                raise ConfigError(f"env_fns[{k}]: got {type(b).__name__}, expected an AASOATTParallelEnv (or a "
                                  "wrapper of one)")
        self._bases: list[AASOATTParallelEnv] = bases
        first = bases[0]
        self.shared_settings: dict[str, Any] = shared_settings(first)
        """The settings every team of a batch has in common (:data:`SHARED_SETTINGS`, and ``filtered``)."""
        for k, b in enumerate(bases[1:], 1):
            check_shared(shared_settings(b), self.shared_settings, int(team_offset) + k)
        self.autoreset = bool(autoreset)
        self._offset = int(team_offset)
        self.num_envs = len(bases)
        self.possible_agents: list[str] = list(first.possible_agents)
        self.num_agents = len(self.possible_agents)
        self.dt, self.decision_interval, self.action_mode = first.dt, first.decision_interval, first.action_mode
        self.reward_config = first.reward_config
        self.terminate_on_collision = first.terminate_on_collision
        self.collision_tolerance = first.collision_tolerance
        agent_obs = first.observation_space(self.possible_agents[0])
        agent_act = first.action_space(self.possible_agents[0])
        self.agent_observation_space: spaces.Box = agent_obs
        """One robot's observation space ``Box(D,)``."""
        self.agent_action_space: spaces.Box = agent_act
        """One robot's action space ``Box(-1, 1, (2,))``."""
        n, k = self.num_agents, self.num_envs
        (self.single_observation_space, self.single_action_space, self.observation_space,
         self.action_space) = batch_spaces(agent_obs, n, k)
        self._filtered = first.control_filter is not None
        self._nominal = self._filtered and bool(first.control_filter.keeps_input_bounds) and not first.clip_actions
        self.nominal_actions = self._nominal
        """Whether actions are nominal wheel accelerations for a filter that keeps the bounds (up to 1e6) rather
        than normalised actions in ``[-1, 1]``."""
        self._grouped: GroupedControlFilter | None = None
        """One filter for all teams (``grouped``), or None: one call per team."""
        if self._filtered and group_filter:
            make = getattr(first.control_filter, "grouped", None)
            self._grouped = make([b.control_filter for b in bases]) if callable(make) else None
        self._filter_resets: list[int] = []
        self._started = False
        self._layouts: list[Any] = [None] * k
        self._teams: list[Team | None] = [None] * k
        self._team: Team | None = None
        self._times = [0.0] * k
        self._steps = np.zeros(k, dtype=np.int64)
        self._max_steps = np.zeros(k, dtype=np.int64)
        self._done = np.zeros(k, dtype=bool)
        kn = k * n
        self._pose = np.zeros((kn, 3))
        self._u = np.zeros((kn, 2))
        self._active = np.zeros(kn, dtype=bool)
        self._saturated = np.zeros(kn, dtype=bool)
        self._last_action = np.zeros((kn, 2))
        self._clearance = np.full(kn, np.inf)
        self._kin: Kinematics | None = None
        self._base_index = np.repeat(np.arange(k) * n, n)
        """Index of each robot's team's first robot in the stack ``(K N,)``."""

    # ------------------------------------------------------------------ properties
    @property
    def live(self) -> np.ndarray:
        """``(K, N)`` bool: agents that act at the next ``step`` (a copy)."""
        return (self._active & ~np.repeat(self._done, self.num_agents)).reshape(self.num_envs, self.num_agents)

    @property
    def filtered(self) -> bool:
        """True when the teams are behind a control filter."""
        return self._filtered

    @property
    def grouped_filter(self) -> GroupedControlFilter | None:
        """The one filter that takes all teams per physics step, or None (unfiltered, or one call per team)."""
        return self._grouped

    @property
    def max_steps(self) -> np.ndarray:
        """Horizon of each team's current episode in env steps ``(K,)``."""
        return self._max_steps.copy()

    @property
    def elapsed_steps(self) -> np.ndarray:
        """Env steps taken in each team's current episode ``(K,)``."""
        return self._steps.copy()

    # ------------------------------------------------------------------ reset
    def reset(
        self, seed: int | Sequence[int | None] | None = None,
        options: dict | Sequence[dict | None] | None = None,
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset every team.

        ``seed``: None, an int (team ``k`` gets ``seed + k``) or one int/None per team;
        ``options``: None, one dict for every team, or one dict/None per team.
        """
        seeds, opts = per_team_reset_args(seed, options, self.num_envs)
        k_all = self.num_envs
        obs = np.zeros((k_all, self.num_agents, *self.agent_observation_space.shape), dtype=np.float32)
        for k in range(k_all):
            obs[k] = self._reset_team(k, seeds[k], opts[k])
        self._restack()
        self._started = True
        return obs, {}

    def _reset_team(self, k: int, seed: int | None, options: dict | None) -> np.ndarray:
        """Reset team ``k`` through its own env; copy its state into the stack and return its observations."""
        env, base = self.envs[k], self._bases[k]
        obs_d, _ = env.reset(seed=seed, options=options)
        n = self.num_agents
        sl = slice(k * n, (k + 1) * n)
        self._layouts[k] = base.layout
        self._teams[k] = base.team
        self._pose[sl] = base._pose
        self._u[sl] = base._u
        self._times[k] = base._time
        self._steps[k] = 0
        self._max_steps[k] = base.max_steps
        self._done[k] = False
        self._filter_resets.append(k)
        self._active[sl] = True
        self._saturated[sl] = False
        self._last_action[sl] = 0.0
        self._clearance[sl] = base._clearance
        return np.stack([obs_d[a] for a in self.possible_agents])

    def _restack(self) -> None:
        """Rebuild the stacked team and per-team constants after resets (the kinematics from the state)."""
        teams = self._teams
        if self._team is None or getattr(self, "_team_ids", None) != [id(t) for t in teams]:
            self._team = stack_teams(teams)  # type: ignore[arg-type]
            self._team_ids = [id(t) for t in teams]
            r = self._team.radius.reshape(self.num_envs, self.num_agents)
            self._equal_radii = r.min(axis=1) == r.max(axis=1)
        self._kin = dynamics.kinematics(self._team, self._pose, self._u)
        layouts = self._layouts
        self._goals = np.concatenate([np.asarray(lay.reference.goals, dtype=np.float64) for lay in layouts])
        self._ref_stack = ReferenceStack([lay.reference for lay in layouts])
        m = {lay.obstacle_radii.shape[0] for lay in layouts}
        self._m_obs = m.pop() if len(m) == 1 else None
        """Obstacles per team when every team has the same number (batched obstacle queries), else None."""
        if self._m_obs:
            self._ocenters = np.stack([lay.obstacle_centers for lay in layouts])
            self._oradii = np.stack([lay.obstacle_radii for lay in layouts])
        self._batched_geometry = self.num_agents < KDTREE_MIN_ROBOTS and self._m_obs is not None
        if self._grouped is not None:
            n = self.num_agents
            rows = np.concatenate([np.arange(k * n, (k + 1) * n) for k in self._filter_resets]
                                  + [np.empty(0, dtype=np.intp)])
            self._grouped.reset_rows(rows, self._team)
            self._obstacles = (np.concatenate([lay.obstacle_centers for lay in layouts]).reshape(-1, 2),
                               np.concatenate([lay.obstacle_radii for lay in layouts]),
                               np.concatenate([np.full(lay.obstacle_radii.shape[0], k, dtype=np.int64)
                                               for k, lay in enumerate(layouts)]))
        self._filter_resets = []

    # ------------------------------------------------------------------ step
    def _parse_actions(self, actions: Any) -> np.ndarray:
        live = self._active & ~np.repeat(self._done, self.num_agents)
        return parse_actions(actions, live.reshape(self.num_envs, self.num_agents), self._nominal,
                             self.shared_settings["clip_actions"], self._offset)

    def _nominal_du(self, act: np.ndarray, kin: Kinematics) -> np.ndarray:
        team = self._team
        assert team is not None
        if self.action_mode == "wheel":
            return act * team.max_wheel_accel[:, None]
        a = act * team.max_point_accel[:, None] - kin.adot_u
        return np.linalg.solve(kin.A, a[..., None])[..., 0]

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Hold each team's actions for ``decision_interval`` physics steps (see the module docstring)."""
        if not self._started:
            raise ResetNeeded("step(): call reset() first")
        if self._done.any():
            raise finished_error(np.flatnonzero(self._done) + self._offset)
        act = self._parse_actions(actions)
        k_all, n = self.num_envs, self.num_agents
        team, dt = self._team, self.dt
        assert team is not None and self._kin is not None
        pose, u, kin = self._pose, self._u, self._kin
        frozen = ~self._active
        any_frozen = bool(frozen.any())
        saturated = np.zeros(k_all * n, dtype=bool)
        between = np.full(k_all * n, np.inf)
        outputs: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # per physics step, all robots
        filters = [b.control_filter for b in self._bases] if self._filtered else None
        times = list(self._times)  # restored if a physics step fails: the stack's state is untouched then
        try:
            for sub in range(self.decision_interval):
                lo, hi = dynamics.input_bounds(team, u, dt)
                du_nom = self._nominal_du(act, kin)
                if any_frozen:
                    du_nom[frozen] = 0.0
                if filters is not None:
                    du = self._filter(filters, outputs, pose, u, kin, lo, hi, du_nom)
                else:
                    du = du_nom
                clipped = np.minimum(np.maximum(du, lo), hi)
                if (clipped != du).any():
                    saturated |= np.abs(clipped - du).max(axis=1) > 1e-9
                new_pose, new_u = dynamics.integrate(team, pose, u, clipped, dt)
                if any_frozen:
                    new_pose[frozen], new_u[frozen] = pose[frozen], 0.0
                pose, u = new_pose, new_u
                self._times = [t + dt for t in self._times]
                kin = dynamics.kinematics(team, pose, u)
                if sub < self.decision_interval - 1:
                    np.minimum(between, self._min_gaps(kin.p), out=between)
        except BaseException:
            self._times = times
            raise
        self._pose, self._u, self._kin = pose, u, kin
        self._last_action = act
        self._steps += 1
        self._saturated = saturated

        # the decision's outputs, all teams at once ----------------------------------------
        p_d, v_d, a_d = self._references()
        prox = self._proximity(kin.p)
        err = np.hypot(*(kin.p - p_d).T)
        clearance = prox.clearance if self.decision_interval == 1 else np.minimum(prox.clearance, between)
        self._clearance = clearance
        collided = clearance < -self.collision_tolerance
        infos: dict[str, Any] = {}
        correction = None
        if filters is not None:
            corr = outputs[0][0] if len(outputs) == 1 else np.max([o[0] for o in outputs], axis=0)
            correction = corr / team.max_wheel_accel
            infos["filter_correction"] = corr.reshape(k_all, n)
            infos["filter_intervened"] = np.any([o[1] for o in outputs], axis=0).reshape(k_all, n)
            infos["filter_avoiding"] = np.any([o[2] for o in outputs], axis=0).reshape(k_all, n)
        goal_dist = np.hypot(*(kin.p - self._goals).T)
        rew = reward_terms(self.reward_config, err, collided, act,
                           goal_dist if self.reward_config.goal_bonus else None, correction)
        obs = self._observations(kin, p_d, v_d, a_d, prox)
        live_before = self._active & ~np.repeat(self._done, n)
        truncated_team = self._steps >= self._max_steps
        truncated = np.repeat(truncated_team, n) & live_before
        if self.terminate_on_collision:
            terminated = collided & self._active
            self._active = self._active & ~terminated
        else:
            terminated = np.zeros(k_all * n, dtype=bool)
        self._done = truncated_team | ~self._active.reshape(k_all, n).any(axis=1)
        infos.update(
            tracking_error=err.reshape(k_all, n), clearance=clearance.reshape(k_all, n).copy(),
            collision=collided.reshape(k_all, n), saturated=saturated.reshape(k_all, n).copy(),
            goal_distance=goal_dist.reshape(k_all, n), time=np.array(self._times),
        )
        obs3 = obs.reshape(k_all, n, -1)
        if self.autoreset and self._done.any():
            infos["final_obs"] = obs3.copy()
            infos["_final_obs"] = self._done.copy()
            for k in np.flatnonzero(self._done):
                obs3[k] = self._reset_team(int(k), None, None)
            self._restack()
        return (obs3, rew.reshape(k_all, n), terminated.reshape(k_all, n), truncated.reshape(k_all, n), infos)

    def _filter(self, filters: list[Any], outputs: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
                pose: np.ndarray, u: np.ndarray, kin: Kinematics, lo: np.ndarray, hi: np.ndarray,
                du_nom: np.ndarray) -> np.ndarray:
        """The applied ``du`` of all teams: one grouped call, or one call per team with its own input.

        Appends ``(correction, intervened, avoiding)`` of every robot to ``outputs``.
        """
        if self._grouped is not None:
            oc, orad, ogroup = self._obstacles
            inp = FilterInput(self._times[0], self.dt, self._team, pose, u, kin, lo, hi,  # type: ignore[arg-type]
                              self._ref_stack(self._times), oc, orad, ogroup)
            out = self._grouped(inp, du_nom)
            du = self._checked(out, None, du_nom.shape[0])
            outputs.append((np.asarray(out.correction, dtype=np.float64), _intervened(out),
                            np.asarray(out.avoiding, dtype=bool)))
            return du
        n = self.num_agents
        du = np.empty_like(du_nom)
        outs = []
        for k, filt in enumerate(filters):
            sl = slice(k * n, (k + 1) * n)
            lay = self._layouts[k]
            t = self._times[k]
            # fresh arrays, as a team's own env hands its filter (not views into the stack)
            inp = FilterInput(t, self.dt, self._teams[k], pose[sl].copy(), u[sl].copy(),  # type: ignore[arg-type]
                              Kinematics(kin.p[sl].copy(), kin.v[sl].copy(), kin.A[sl].copy(),
                                         kin.adot_u[sl].copy()), lo[sl].copy(), hi[sl].copy(),
                              lay.reference(t), lay.obstacle_centers, lay.obstacle_radii)
            out = filt(inp, du_nom[sl].copy())
            du[sl] = self._checked(out, k, n)
            outs.append(out)
        outputs.append((np.concatenate([np.asarray(o.correction, dtype=np.float64) for o in outs]),
                        np.concatenate([_intervened(o) for o in outs]),
                        np.concatenate([np.asarray(o.avoiding, dtype=bool) for o in outs])))
        return du

    def _checked(self, out: Any, k: int | None, rows: int) -> np.ndarray:
        """A filter output's ``du``: finite, ``(rows, 2)`` (``k``: the team of a per-team call)."""
        d = np.asarray(out.du, dtype=np.float64)
        if d.shape != (rows, 2) or not np.all(np.isfinite(d)):
            who = "the grouped control filter" if k is None else f"control filter of team {k + self._offset}"
            raise ActionError(f"{who} returned shape {d.shape} or non-finite values, expected finite ({rows}, 2)")
        return d

    # ------------------------------------------------------------------ per-decision helpers
    def _references(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        self._ref_now = self._ref_stack(self._times)
        return self._ref_now

    def _min_gaps(self, p: np.ndarray) -> np.ndarray:
        """Each robot's clearance to its own team and obstacles (``geometry.min_gaps`` per team)."""
        if not self._batched_geometry:
            return self._per_team(lambda k, sl, lay: min_gaps(p[sl], self._teams[k].radius, lay.obstacle_centers,
                                                              lay.obstacle_radii))
        gap, _ = self._robot_gaps(p)
        if self._m_obs:
            gap = np.minimum(gap, self._obstacle_gaps(p).min(axis=2).ravel())
        return gap

    def _per_team(self, fn: Callable[[int, slice, Any], np.ndarray]) -> np.ndarray:
        n = self.num_agents
        return np.concatenate([fn(k, slice(k * n, (k + 1) * n), lay) for k, lay in enumerate(self._layouts)])

    def _distances(self, p: np.ndarray) -> np.ndarray:
        """Centre distances within each team ``(K, N, N)`` (inf on the diagonal)."""
        k, n = self.num_envs, self.num_agents
        z = np.ascontiguousarray(p, dtype=np.float64).view(np.complex128)[:, 0].reshape(k, n)
        d = np.abs(z[:, :, None] - z[:, None, :])
        ar = np.arange(n)
        d[:, ar, ar] = np.inf
        return d

    def _robot_gaps(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Surface gap to the nearest robot of the same team ``(K N,)`` and the distances ``(K, N, N)``."""
        d = self._distances(p)
        team = self._team
        assert team is not None
        r = team.radius.reshape(self.num_envs, self.num_agents)
        if self.num_agents <= 1:
            return np.full(p.shape[0], np.inf), d
        if self._equal_radii.all():
            gap = np.minimum.reduce(d, axis=2) - 2.0 * r
        else:
            gap = np.where(self._equal_radii[:, None], np.minimum.reduce(d, axis=2) - 2.0 * r,
                           (d - r[:, :, None] - r[:, None, :]).min(axis=2))
        return gap.ravel(), d

    def _obstacle_gaps(self, p: np.ndarray) -> np.ndarray:
        """Robot-obstacle surface gaps of each team ``(K, N, M)`` (``geometry.obstacle_gaps``)."""
        p3 = p.reshape(self.num_envs, self.num_agents, 2)
        dx = p3[:, :, 0:1] - self._ocenters[:, None, :, 0]
        dy = p3[:, :, 1:2] - self._ocenters[:, None, :, 1]
        team = self._team
        assert team is not None
        r = team.radius.reshape(self.num_envs, self.num_agents)
        return np.sqrt(dx * dx + dy * dy) - r[:, :, None] - self._oradii[:, None, :]

    def _proximity(self, p: np.ndarray) -> Proximity:
        """:func:`~aasoatt_env.sim.observations.proximity` of every team, indices into the stack."""
        n, k_all = self.num_agents, self.num_envs
        k = max(self._bases[0].num_neighbors, 1)
        if not self._batched_geometry:
            parts = [proximity(p[k0 * n:(k0 + 1) * n], self._teams[k0].radius, lay.obstacle_centers,  # type: ignore
                               lay.obstacle_radii, k=k) for k0, lay in enumerate(self._layouts)]
            idx = np.concatenate([np.where(q.idx >= 0, q.idx + k0 * n, -1) for k0, q in enumerate(parts)])
            m = {q.obstacle_gaps.shape[1] for q in parts}
            og = np.concatenate([q.obstacle_gaps for q in parts]) if len(m) == 1 else None
            return Proximity(idx, np.concatenate([q.dist for q in parts]), og,  # type: ignore[arg-type]
                             np.concatenate([q.clearance for q in parts]))
        gap, d = self._robot_gaps(p)
        kk = min(k, n - 1)
        if kk <= 0:
            idx = np.full((k_all * n, k), -1, dtype=np.intp)
            dist = np.full((k_all * n, k), np.inf)
        else:
            if n <= _FULL_SORT_MAX or kk >= n - 1:
                order = np.argsort(d, axis=2)[:, :, :kk]
            else:
                part = np.argpartition(d, kk - 1, axis=2)[:, :, :kk]
                order = np.take_along_axis(part, np.argsort(np.take_along_axis(d, part, axis=2), axis=2), axis=2)
            dk = np.take_along_axis(d, order, axis=2)
            idx = np.full((k_all, n, k), -1, dtype=np.intp)
            dist = np.full((k_all, n, k), np.inf)
            idx[:, :, :kk] = order + (np.arange(k_all) * n)[:, None, None]
            dist[:, :, :kk] = dk
            idx, dist = idx.reshape(k_all * n, k), dist.reshape(k_all * n, k)
        if self._m_obs:
            og = self._obstacle_gaps(p)
            gap = np.minimum(gap, og.min(axis=2).ravel())
            og = og.reshape(k_all * n, -1)
        else:
            og = np.zeros((k_all * n, 0))
        return Proximity(idx, dist, og, gap)

    def _observations(self, kin: Kinematics, p_d: np.ndarray, v_d: np.ndarray, a_d: np.ndarray,
                      prox: Proximity) -> np.ndarray:
        base = self._bases[0]
        team = self._team
        assert team is not None
        if prox.obstacle_gaps is None:  # teams with different numbers of obstacles: one call per team
            return np.concatenate([self._team_observations(k, kin, p_d, v_d, a_d) for k in range(self.num_envs)])
        m = self._m_obs or 0
        if m:
            centers, radii = self._ocenters.reshape(-1, 2), self._oradii.ravel()
            offset = np.repeat(np.arange(self.num_envs) * m, self.num_agents)
        else:
            centers, radii, offset = np.zeros((0, 2)), np.zeros(0), None
        return build_observations(
            p=kin.p, v=kin.v, theta=self._pose[:, 2], u=self._u, p_d=p_d, v_d=v_d, a_d=a_d, goals=self._goals,
            radii=team.radius, obstacle_centers=centers, obstacle_radii=radii, sensing_range=base.sensing_range,
            k_robots=base.num_neighbors, k_obstacles=base.num_obstacles, prox=prox, obstacle_offset=offset,
        )

    def _team_observations(self, k: int, kin: Kinematics, p_d: np.ndarray, v_d: np.ndarray,
                           a_d: np.ndarray) -> np.ndarray:
        n = self.num_agents
        sl = slice(k * n, (k + 1) * n)
        base, lay, team = self._bases[0], self._layouts[k], self._teams[k]
        assert team is not None
        prox = proximity(kin.p[sl], team.radius, lay.obstacle_centers, lay.obstacle_radii,
                         k=max(base.num_neighbors, 1))
        return build_observations(
            p=kin.p[sl], v=kin.v[sl], theta=self._pose[sl, 2], u=self._u[sl], p_d=p_d[sl], v_d=v_d[sl],
            a_d=a_d[sl], goals=self._goals[sl], radii=team.radius, obstacle_centers=lay.obstacle_centers,
            obstacle_radii=lay.obstacle_radii, sensing_range=base.sensing_range, k_robots=base.num_neighbors,
            k_obstacles=base.num_obstacles, prox=prox,
        )

    # ------------------------------------------------------------------ the teams' own envs
    def sync(self) -> None:
        """Write the batch's state into the teams' own envs (``envs``), e.g. before rendering them."""
        if not self._started:
            raise ResetNeeded("sync(): call reset() first")
        n = self.num_agents
        for k, base in enumerate(self._bases):
            sl = slice(k * n, (k + 1) * n)
            base._load_state(self._pose[sl], self._u[sl], self._times[k], int(self._steps[k]), self._active[sl],
                             self._saturated[sl], self._last_action[sl], self._clearance[sl],
                             bool(self._steps[k] >= self._max_steps[k]))

    def render(self) -> tuple[Any, ...]:
        """One frame per team (their envs' ``render()``; needs a ``render_mode``)."""
        self.sync()
        return tuple(env.render() for env in self.envs)

    def env_get(self, k: int, name: str) -> Any:
        """Attribute ``name`` of team ``k``'s own env (``k`` as a sequence index: ``-1`` is the last team)."""
        return getattr(self.envs[team_index(k, self.num_envs)], name)

    def env_set(self, k: int, name: str, value: Any) -> None:
        """Set attribute ``name`` of team ``k``'s own env."""
        setattr(self.envs[team_index(k, self.num_envs)], name, value)

    def env_call(self, k: int, name: str, *args: Any, **kwargs: Any) -> Any:
        """Call method ``name`` of team ``k``'s own env, after :meth:`sync` (its state is the batch's)."""
        k = team_index(k, self.num_envs)
        self.sync()
        return getattr(self.envs[k], name)(*args, **kwargs)

    def env_is_wrapped(self, k: int, wrapper_class: type) -> bool:
        """Whether team ``k``'s own env is (PettingZoo-)wrapped by ``wrapper_class``."""
        e = self.envs[team_index(k, self.num_envs)]
        while e is not None:
            if isinstance(e, wrapper_class):
                return True
            e = getattr(e, "env", None)
        return False

    def close(self) -> None:
        """Close the teams' envs."""
        for env in self.envs:
            env.close()


def _intervened(out: Any) -> np.ndarray:
    """A filter output's ``intervened`` flags, or ``correction > 0`` for outputs without them."""
    flag = getattr(out, "intervened", None)
    return np.asarray(flag if flag is not None else np.asarray(out.correction) > 0.0, dtype=bool)


def batch_spaces(agent_obs: spaces.Box, n: int, k: int) -> tuple[spaces.Box, spaces.Box, spaces.Box, spaces.Box]:
    """A team's and the batch's spaces from one robot's observation space.

    ``(N, D)`` and ``(N, 2)`` for a team, ``(K, N, D)`` and ``(K, N, 2)`` for the batch (actions in ``[-1, 1]``).
    """
    team_obs = spaces.Box(np.broadcast_to(agent_obs.low, (n, *agent_obs.shape)),
                          np.broadcast_to(agent_obs.high, (n, *agent_obs.shape)), dtype=agent_obs.dtype)
    batch_obs = spaces.Box(np.broadcast_to(agent_obs.low, (k, n, *agent_obs.shape)),
                           np.broadcast_to(agent_obs.high, (k, n, *agent_obs.shape)), dtype=agent_obs.dtype)
    return (team_obs, spaces.Box(-1.0, 1.0, (n, 2), np.float32), batch_obs,
            spaces.Box(-1.0, 1.0, (k, n, 2), np.float32))


SHARED_SETTINGS = ("possible_agents", "dt", "decision_interval", "action_mode", "num_neighbors", "num_obstacles",
                   "sensing_range", "reward_config", "terminate_on_collision", "collision_tolerance", "clip_actions")
"""Settings every team of a batch shares (attributes of :class:`~aasoatt_env.sim.env.AASOATTParallelEnv`)."""


def shared_settings(env: AASOATTParallelEnv) -> dict[str, Any]:
    """The :data:`SHARED_SETTINGS` of a team's env, and whether it is behind a filter (``filtered``)."""
    return {**{name: getattr(env, name) for name in SHARED_SETTINGS}, "filtered": env.control_filter is not None}


def check_shared(got: dict[str, Any], want: dict[str, Any], k: int) -> None:
    """Raise :class:`ConfigError` naming ``env_fns[k]`` if its shared settings differ from env 0's."""
    if got["filtered"] != want["filtered"]:
        raise ConfigError(f"env_fns[{k}]: behind a filter or not, unlike env 0; a batch is one or the other")
    for name in SHARED_SETTINGS:
        if got[name] != want[name]:
            raise ConfigError(f"env_fns[{k}]: {name} differs from env 0's ({got[name]!r} vs {want[name]!r}); a "
                              "batch shares one setting")


def parse_actions(actions: Any, live: np.ndarray, nominal: bool, clip: bool, offset: int = 0) -> np.ndarray:
    """Validated actions ``(K N, 2)`` float64 of teams ``(K, N)`` = ``live.shape`` (done agents' rows zeroed).

    ``nominal``: values up to 1e6 pass as they are (:attr:`BatchedAASOATTEnv.nominal_actions`);
    otherwise values up to ``1 + 1e-6`` are accepted and clipped to ``[-1, 1]``, every finite
    value with ``clip`` (``clip_actions``).  ``offset``: number of the first team in messages.
    """
    k, n = live.shape
    try:
        arr = np.asarray(actions)
    except (TypeError, ValueError):
        raise ActionError(f"actions: got {type(actions).__name__}, expected an array ({k}, {n}, 2)") from None
    if arr.dtype.kind not in "fiu" or arr.size != k * n * 2 or arr.shape not in ((k, n, 2), (k * n, 2)):
        raise ActionError(f"actions: got shape {arr.shape} (dtype {arr.dtype}), expected real numbers of "
                          f"shape ({k}, {n}, 2)")
    act = arr.reshape(k * n, 2).astype(np.float64)
    act[~live.ravel()] = 0.0  # the env ignores actions of agents that are done
    peak = np.abs(act).max(initial=0.0)
    if not np.isfinite(peak):
        bad = np.flatnonzero(~np.isfinite(act).all(axis=1))[0]
        raise ActionError(f"actions[{bad // n + offset}, {bad % n}]: got non-finite values {act[bad].tolist()}, "
                          "expected finite numbers")
    accept = _NOMINAL_MAX if nominal else (np.inf if clip else 1.0 + 1e-6)
    if peak > accept:
        bad = int(np.flatnonzero(np.abs(act).max(axis=1) > accept)[0])
        raise ActionError(f"actions[{bad // n + offset}, {bad % n}]: got {act[bad].tolist()}, expected values in "
                          + (f"[-{_NOMINAL_MAX:g}, {_NOMINAL_MAX:g}]" if nominal else "[-1, 1] (or clip_actions=True)"))
    if not nominal and peak > 1.0:
        np.minimum(np.maximum(act, -1.0, out=act), 1.0, out=act)
    return act


def finished_error(teams: np.ndarray) -> ResetNeeded:
    """The error of ``step`` on teams that finished their episode (``autoreset=False``)."""
    return ResetNeeded(f"step(): team(s) {np.asarray(teams).tolist()} finished their episode (autoreset=False); "
                       "call reset() first")


def team_index(k: Any, num_envs: int) -> int:
    """Team number ``k`` in ``[0, num_envs)`` (negative ``k`` counts from the end), or :class:`ConfigError`."""
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not -num_envs <= k < num_envs:
        raise ConfigError(f"k: got {k!r}, expected a team number in [0, {num_envs}) (or from -{num_envs})")
    return int(k) % num_envs


def per_team_reset_args(seed: int | Sequence[int | None] | None, options: dict | Sequence[dict | None] | None,
                        k_all: int) -> tuple[list[int | None], list[dict | None]]:
    """``reset``'s ``seed`` and ``options`` as one entry per team (validated; see :meth:`BatchedAASOATTEnv.reset`)."""
    if seed is None or isinstance(seed, (int, np.integer)):
        seeds: list[int | None] = [None if seed is None else int(seed) + k for k in range(k_all)]
    else:
        seeds = list(seed)
        if len(seeds) != k_all:
            raise ConfigError(f"seed: got {len(seeds)} seeds, expected one per team ({k_all})")
    if options is None or isinstance(options, dict):
        opts: list[dict | None] = [options] * k_all
    else:
        opts = list(options)
        if len(opts) != k_all or not all(o is None or isinstance(o, dict) for o in opts):
            raise ConfigError(f"options: got a sequence of {len(opts)} entries, expected None, one dict, or one "
                              f"dict/None per team ({k_all})")
    return seeds, opts
