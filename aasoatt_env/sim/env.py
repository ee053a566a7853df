"""PettingZoo parallel environment of acceleration-actuated differential-drive robots.

=====================  =========================================================
agents                 ``robot_0`` ... ``robot_{N-1}``
action space           ``Box(-1, 1, (2,), float32)`` per agent
                       ``action_mode="wheel"`` (default): normalised wheel angular
                       accelerations, ``du = action * max_wheel_accel``;
                       ``action_mode="point"``: normalised control-point
                       acceleration ``a = action * a_max`` mapped to wheels by
                       ``du = A^{-1} (a - A_dot u)`` and then *saturated* to the
                       input bounds (documented clipping; ``infos["saturated"]``)
observation space      ``Box(-100, 100, (14 + 6 (K + K_obs),), float32)``, see
                       :mod:`aasoatt_env.sim.observations`
state space            ``Box(-inf, inf, (9 N + 1,), float64)``: poses, wheel speeds,
                       reference points and velocities, time
reward                 :class:`~aasoatt_env.sim.rewards.RewardConfig` (tracking,
                       collision, effort, filter correction, goal bonus)
=====================  =========================================================

One ``step`` holds each agent's action for ``decision_interval`` physics steps of
``dt`` seconds (default :data:`~aasoatt_env.model.dynamics.DT`, the paper's
5 ms).  A control filter (:class:`~aasoatt_env.sim.protocol.ControlFilter`, e.g.
the one :class:`aasoatt_env.safety.wrapper.AASOATTFilter` installs) may be set
with :meth:`AASOATTParallelEnv.set_control_filter`; it then maps the nominal
wheel accelerations to applied ones at *every* physics step (the protocol is
documented in :mod:`aasoatt_env.sim.protocol`).

Episodes are truncated at the scenario's horizon.  With
``terminate_on_collision=True`` a robot whose clearance falls below
``-collision_tolerance`` terminates: it leaves ``env.agents`` and stays in the
world as a static disc (it stops in place).  Actions given for agents that are
already done are ignored (clients such as TorchRL send an action for every
agent of a group); a ``UserWarning`` says so once per env.

Wheel-speed limits (``RobotParams.max_wheel_speed``) are enforced by saturating
the applied ``du`` to the speed-admissible range of the step; ``infos`` reports
``saturated`` when that happened.  Actions outside ``[-1, 1]`` raise
:class:`~aasoatt_env.errors.ActionError` unless ``clip_actions=True``.
"""

from __future__ import annotations

import math
import warnings
from collections import deque
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from aasoatt_env import validation as check
from aasoatt_env.errors import ActionError, ConfigError, ResetNeeded, UsageError
from aasoatt_env.model import dynamics
from aasoatt_env.model.dynamics import DT, Kinematics
from aasoatt_env.model.geometry import min_gaps
from aasoatt_env.sim.observations import OBS_BOUND, SELF_DIM, SLOT_DIM, Proximity, build_observations, proximity
from aasoatt_env.sim.protocol import ControlFilter, FilterInput, FilterOutput
from aasoatt_env.sim.rendering import Frame, Renderer
from aasoatt_env.sim.rewards import RewardConfig, rewards
from aasoatt_env.sim.scenarios import Layout, Scenario, get_scenario
from aasoatt_env.sim.scenarios.base import check_clear_of_obstacles, check_no_overlap

__all__ = ["MAX_NEIGHBOR_SLOTS", "TRAIL_LENGTH", "AASOATTParallelEnv"]

MAX_NEIGHBOR_SLOTS: int = 256
"""Largest ``num_neighbors`` / ``num_obstacles`` (observation slots) accepted."""
TRAIL_LENGTH: int = 400
"""Control-point positions kept for rendering trails (memory stays flat over long episodes)."""

_FLOAT_MAX = float(np.finfo(np.float64).max)
_NOMINAL_MAX = 1e6
"""Largest nominal action accepted behind a filter (in units of the bound): larger ones are a bug upstream."""


FILTERED_MIN_COLLISION_TOLERANCE: float = 1e-9
"""Smallest ``collision_tolerance`` [m] with ``terminate_on_collision`` behind a control filter: the
safety filter's guarantee allows this much floating-point rounding (its gatekeeper forgives at most half
of it, :data:`aasoatt_env.safety.repair.GATE_TOL`, the rest covers the rounding of the simulator's steps)."""


class AASOATTParallelEnv(ParallelEnv):
    """Multi-robot trajectory tracking at acceleration level (see module docstring).

    Parameters
    ----------
    scenario : str or Scenario
        Scenario name (see :data:`aasoatt_env.sim.scenarios.SCENARIOS`) or instance.
    render_mode : {None, "rgb_array", "human"}
        Rendering mode.
    dt : float
        Physics step [s], in ``[1e-6, 0.1]``.
    decision_interval : int
        Physics steps per env step (the action is held), ``1..10000``.
    action_mode : {"wheel", "point"}
        Meaning of actions (module docstring).
    sensing_range : float
        Neighbours farther than this are not observed [m].
    num_neighbors, num_obstacles : int
        Observation slots ``K`` and ``K_obs``, ``0..256``.
    reward : RewardConfig or mapping, optional
        Reward weights.
    terminate_on_collision : bool
        Terminate robots that collide.
    collision_tolerance : float
        Overlap [m] below which contact does not count as a collision, in ``[0, 1]``.
    max_steps : int, optional
        Override the horizon in env steps.
    clip_actions : bool
        Clip actions to ``[-1, 1]`` instead of raising.
    **scenario_kwargs
        Passed to the scenario (e.g. ``num_robots=20``); unknown names raise ``TypeError``.
    """

    metadata = {"render_modes": ["rgb_array", "human"], "name": "aasoatt_v0", "render_fps": 20}

    def __init__(
        self,
        scenario: str | Scenario = "circle_swap",
        render_mode: str | None = None,
        dt: float = DT,
        decision_interval: int = 1,
        action_mode: str = "wheel",
        sensing_range: float = 3.0,
        num_neighbors: int = 4,
        num_obstacles: int = 2,
        reward: RewardConfig | Mapping[str, float] | None = None,
        terminate_on_collision: bool = False,
        collision_tolerance: float = 1e-3,
        max_steps: int | None = None,
        clip_actions: bool = False,
        **scenario_kwargs: Any,
    ) -> None:
        if render_mode is not None:
            check.choice("render_mode", render_mode, self.metadata["render_modes"])
        self.dt = check.real("dt", dt, lo=1e-6, hi=0.1)
        self.decision_interval = check.integer("decision_interval", decision_interval, lo=1, hi=10_000)
        self.action_mode = check.choice("action_mode", action_mode, ("wheel", "point"))
        self.sensing_range = check.positive("sensing_range", sensing_range, hi=1e6)
        self.num_neighbors = check.integer("num_neighbors", num_neighbors, lo=0, hi=MAX_NEIGHBOR_SLOTS)
        self.num_obstacles = check.integer("num_obstacles", num_obstacles, lo=0, hi=MAX_NEIGHBOR_SLOTS)
        self.reward_config = RewardConfig.coerce(reward)
        self.terminate_on_collision = check.boolean("terminate_on_collision", terminate_on_collision)
        self.collision_tolerance = check.real("collision_tolerance", collision_tolerance, lo=0.0, hi=1.0)
        self._max_steps_override = None if max_steps is None else check.integer(
            "max_steps", max_steps, lo=1, hi=10**12)
        self.clip_actions = check.boolean("clip_actions", clip_actions)
        self.scenario = get_scenario(scenario, **scenario_kwargs)
        self.render_mode = render_mode

        n = self.scenario.num_robots
        self.possible_agents = [f"robot_{i}" for i in range(n)]
        self.agents: list[str] = []
        self._index = {a: i for i, a in enumerate(self.possible_agents)}
        obs_dim = SELF_DIM + SLOT_DIM * (self.num_neighbors + self.num_obstacles)
        self._obs_space = spaces.Box(-OBS_BOUND, OBS_BOUND, (obs_dim,), np.float32)
        self._act_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.observation_spaces = {a: self._obs_space for a in self.possible_agents}
        self.action_spaces = {a: self._act_space for a in self.possible_agents}
        self.state_space = spaces.Box(-np.inf, np.inf, (9 * n + 1,), np.float64)
        self._control_filter: ControlFilter | None = None
        self._filter_outputs: tuple[FilterOutput, ...] = ()
        self._rng = np.random.default_rng()
        self._renderer: Any = None
        self._trail: deque[np.ndarray] = deque(maxlen=TRAIL_LENGTH)
        self._layout: Layout | None = None
        self._ref_of: tuple[Layout | None, float] = (None, math.nan)  # (layout, time) of _ref_now
        self._warned_dead = False

    # ------------------------------------------------------------------ spaces
    def observation_space(self, agent: str) -> spaces.Box:
        """Observation space of ``agent`` (the same object on every call)."""
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Box:
        """Action space of ``agent`` (the same object on every call)."""
        return self.action_spaces[agent]

    @property
    def agent_index(self) -> Mapping[str, int]:
        """Read-only map agent name -> robot index (row of every ``(N, ...)`` array)."""
        return MappingProxyType(self._index)

    # ------------------------------------------------------------------ control filter
    def set_control_filter(self, control_filter: ControlFilter | None) -> None:
        """Install a per-physics-step control filter (:mod:`aasoatt_env.sim.protocol`), or remove it with None.

        An env has at most one control filter: installing a second one raises
        :class:`~aasoatt_env.errors.UsageError` (wrapping an env in two filters
        would silently disable the inner one); remove the first with
        ``set_control_filter(None)``.  A filter installed after ``reset`` is
        reset with the current team at once.
        """
        if control_filter is None:
            self._control_filter = None
            self._filter_outputs = ()
            return
        if not isinstance(control_filter, ControlFilter):
            raise ConfigError(
                f"control_filter: got {type(control_filter).__name__}, expected an object with "
                "reset(team), __call__(FilterInput, nominal_du) and keeps_input_bounds "
                "(aasoatt_env.sim.protocol.ControlFilter)"
            )
        if self.terminate_on_collision and self.collision_tolerance < FILTERED_MIN_COLLISION_TOLERANCE:
            # a terminated robot stops in place at once: an input the filter did not return, so the pairs
            # behind it are no longer brake-safe; rounding alone (1e-16 m) would set it off at 0
            raise ConfigError(
                f"collision_tolerance: got {self.collision_tolerance:g} with terminate_on_collision=True, expected "
                f">= {FILTERED_MIN_COLLISION_TOLERANCE:g} m behind a control filter (the safety filter's guarantee "
                "allows that much rounding; a robot terminated for less would stop in place, an input the filter "
                "cannot plan for)")
        if self._control_filter is not None and self._control_filter is not control_filter:
            raise UsageError(
                f"this env already has a control filter ({type(self._control_filter).__name__}); an env takes "
                "one filter: wrap it once, or remove the first with set_control_filter(None)"
            )
        self._control_filter = control_filter
        if self._layout is not None:
            control_filter.reset(self.team)

    @property
    def control_filter(self) -> ControlFilter | None:
        """The installed control filter (None: actions are applied as they are)."""
        return self._control_filter

    @property
    def filter_outputs(self) -> tuple[FilterOutput, ...]:
        """The control filter's outputs at the physics steps of the last ``step`` (empty without a filter)."""
        return self._filter_outputs

    @property
    def _nominal_actions(self) -> bool:
        """Actions are a nominal the filter projects (may leave ``[-1, 1]``)."""
        f = self._control_filter
        return f is not None and bool(f.keeps_input_bounds) and not self.clip_actions

    # ------------------------------------------------------------------ reset/step
    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """Start an episode; ``seed`` (an integer >= 0) seeds the scenario's random layout.

        ``options`` (None or a dict) is accepted for API compatibility and ignored: this env has no reset options.
        """
        if seed is not None:
            seed = check.integer("seed", seed, lo=0)
        if options is not None and not isinstance(options, Mapping):
            raise ConfigError(f"options: got {type(options).__name__}, expected a dict or None")
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        layout = self.scenario.build(self._rng)
        # every layout starts without overlap (the filter's guarantee starts there), a user's scenario too
        where = f"scenario {self.scenario.name or type(self.scenario).__name__!r}: starts"
        check_no_overlap(where, layout.starts, layout.team.radius, layout.team.group)
        check_clear_of_obstacles(where, layout.starts, layout.team.radius,
                                 (layout.obstacle_centers, layout.obstacle_radii))
        self._layout = layout
        self.team = layout.team
        self._pose = dynamics.pose_from_point(layout.team, layout.starts, layout.headings)
        self._u = np.zeros((layout.team.n, 2))
        self._time = 0.0
        self._steps = 0
        self._max_steps = self._max_steps_override or max(
            1, int(math.ceil(layout.horizon / (self.dt * self.decision_interval) - 1e-9))
        )
        self._active = np.ones(layout.team.n, dtype=bool)
        self._last_action = np.zeros((layout.team.n, 2))
        self._saturated = np.zeros(layout.team.n, dtype=bool)
        self.agents = list(self.possible_agents)
        self._kin = dynamics.kinematics(self.team, self._pose, self._u)
        self._trail.clear()
        self._trail.append(self._kin.p.copy())
        self._live_idx = np.arange(layout.team.n)
        self._filter_outputs = ()
        self._refresh()
        if self._control_filter is not None:
            self._control_filter.reset(self.team)
        obs = self._observations()
        infos = self._infos()
        if self.render_mode == "human":
            self.render()
        return obs, infos

    def _require_reset(self, what: str) -> None:
        if self._layout is None:
            raise ResetNeeded(f"{what}: call reset() first")

    def _parse_actions(self, actions: dict[str, Any]) -> np.ndarray:
        if not isinstance(actions, dict):
            raise ActionError(f"actions: got {type(actions).__name__}, expected a dict agent -> action")
        live = self.agents
        n_all = len(self.possible_agents)
        nominal = self._nominal_actions
        limit = _NOMINAL_MAX if nominal else (_FLOAT_MAX if self.clip_actions else 1.0 + 1e-6)
        if actions.keys() == set(live):  # fast path: one array, one type/finiteness/range check
            try:
                arr = np.asarray([actions[a] for a in live])
            except (TypeError, ValueError):
                arr = None
            if arr is not None and arr.shape == (len(live), 2) and arr.dtype.kind in "fiu":
                arr = arr.astype(np.float64, copy=False)
                peak = np.abs(arr).max(initial=0.0)  # NaN propagates, so this also checks finiteness
                if peak <= limit:
                    if len(live) == n_all:
                        act = arr.copy()
                    else:
                        act = np.zeros((n_all, 2))
                        act[self._live_idx] = arr
                    if not nominal and peak > 1.0:
                        np.minimum(np.maximum(act, -1.0, out=act), 1.0, out=act)
                    return act
        act = np.zeros((n_all, 2))
        unknown = [a for a in actions if a not in self._index]
        if unknown:
            raise ActionError(
                f"actions: unknown agent(s) {unknown}; agents are "
                f"{self.possible_agents[0]}..{self.possible_agents[-1]}"
            )
        missing = [a for a in live if a not in actions]
        if missing:
            raise ActionError(f"actions: missing action for live agent(s) {missing}")
        dead = [a for a in actions if a not in live]
        if dead and not self._warned_dead:
            self._warned_dead = True
            warnings.warn(
                f"actions for agent(s) that are done are ignored ({dead}); this warning is shown once per env",
                UserWarning, stacklevel=3,
            )
        for agent in live:
            a = actions[agent]
            try:
                arr = np.asarray(a)
            except (TypeError, ValueError):
                raise ActionError(f"actions[{agent!r}]: got {a!r}, expected an array of 2 real numbers") from None
            if arr.dtype.kind not in "fiu":
                raise ActionError(f"actions[{agent!r}]: got {a!r} (dtype {arr.dtype}), expected 2 real numbers")
            if arr.shape != (2,):
                raise ActionError(f"actions[{agent!r}]: got shape {arr.shape}, expected (2,)")
            arr = arr.astype(np.float64)
            if not np.all(np.isfinite(arr)):
                raise ActionError(
                    f"actions[{agent!r}]: got non-finite values {arr.tolist()}, expected finite numbers"
                )
            if not (nominal or self.clip_actions) and np.any(np.abs(arr) > 1.0 + 1e-6):
                raise ActionError(
                    f"actions[{agent!r}]: got {arr.tolist()}, expected values in [-1, 1] (or clip_actions=True)"
                )
            if nominal and np.any(np.abs(arr) > _NOMINAL_MAX):
                raise ActionError(
                    f"actions[{agent!r}]: got {arr.tolist()}, expected a nominal within [-{_NOMINAL_MAX:g}, "
                    f"{_NOMINAL_MAX:g}] (in units of the wheel-acceleration bound; the filter keeps the bounds)"
                )
            act[self._index[agent]] = arr
        return act if nominal else np.minimum(np.maximum(act, -1.0, out=act), 1.0, out=act)

    def _nominal_du(self, act: np.ndarray, kin: Kinematics) -> np.ndarray:
        if self.action_mode == "wheel":
            return act * self.team.max_wheel_accel[:, None]
        a = act * self.team.max_point_accel[:, None] - kin.adot_u
        return np.linalg.solve(kin.A, a[..., None])[..., 0]

    @property
    def _obstacles(self) -> tuple[np.ndarray, np.ndarray]:
        layout = self.layout
        return layout.obstacle_centers, layout.obstacle_radii

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """Apply the actions for ``decision_interval`` physics steps."""
        self._require_reset("step()")
        if not self.agents:
            raise ResetNeeded("step() called with no live agents (the episode is over); call reset() first")
        act = self._parse_actions(actions)
        self._last_action = act
        team, dt = self.team, self.dt
        saturated = np.zeros(team.n, dtype=bool)
        frozen = ~self._active
        any_frozen = bool(frozen.any())
        between = np.full(team.n, np.inf)  # clearance at the physics steps between decisions
        filt = self._control_filter
        outputs: list[FilterOutput] = []
        centers, orad = self._obstacles
        for sub in range(self.decision_interval):
            kin = self._kin
            lo, hi = dynamics.input_bounds(team, self._u, dt)
            du_nom = self._nominal_du(act, kin)
            if any_frozen:
                du_nom[frozen] = 0.0
            if filt is not None:
                inp = FilterInput(self._time, dt, team, self._pose, self._u, kin, lo, hi,
                                  self._reference_at(self._time), centers, orad)
                out = filt(inp, du_nom)
                du = np.asarray(out.du, dtype=np.float64)
                if du.shape != du_nom.shape or not np.all(np.isfinite(du)):
                    raise ActionError(
                        f"control filter returned shape {du.shape} or non-finite values, expected finite {du_nom.shape}"
                    )
                outputs.append(out)
            else:
                du = du_nom
            clipped = np.minimum(np.maximum(du, lo), hi)
            if (clipped != du).any():
                saturated |= np.abs(clipped - du).max(axis=1) > 1e-9
            pose, u = dynamics.integrate(team, self._pose, self._u, clipped, dt)
            if any_frozen:
                pose[frozen], u[frozen] = self._pose[frozen], 0.0
            self._pose, self._u = pose, u
            self._time += dt
            self._kin = dynamics.kinematics(team, pose, u)
            if sub < self.decision_interval - 1:
                np.minimum(between, min_gaps(self._kin.p, team.radius, centers, orad), out=between)
        self._filter_outputs = tuple(outputs)
        self._steps += 1
        self._saturated = saturated
        self._trail.append(self._kin.p.copy())
        self._refresh(between if self.decision_interval > 1 else None)

        collided = self._clearance < -self.collision_tolerance
        correction = None
        if outputs:
            corr = outputs[0].correction if len(outputs) == 1 else np.max([o.correction for o in outputs], axis=0)
            correction = np.asarray(corr) / team.max_wheel_accel
        goal_dist = None
        if self.reward_config.goal_bonus:
            goal_dist = np.hypot(*(self._kin.p - self._layout.reference.goals).T)  # type: ignore[union-attr]
        rewards_arr = rewards(self.reward_config, self._err, collided, act, goal_dist, correction).tolist()
        truncated = self._steps >= self._max_steps
        live = self.agents
        obs = self._observations()
        infos = self._infos()
        idx = self._index
        all_live = len(live) == len(self.possible_agents)
        rewards_d = dict(zip(live, rewards_arr)) if all_live else {a: rewards_arr[idx[a]] for a in live}
        if self.terminate_on_collision:
            terminated_mask = collided & self._active
            terminations = {a: bool(terminated_mask[idx[a]]) for a in live}
            self._active &= ~terminated_mask
        else:
            terminations = dict.fromkeys(live, False)
        truncations = dict.fromkeys(live, truncated)
        self.agents = [] if truncated else [a for a in live if not terminations[a]]
        if len(self.agents) != len(live):
            self._live_idx = np.array([idx[a] for a in self.agents], dtype=np.intp)
        if self.render_mode == "human":
            self.render()
        return obs, rewards_d, terminations, truncations, infos

    def _load_state(
        self, pose: np.ndarray, u: np.ndarray, time: float, steps: int, active: np.ndarray, saturated: np.ndarray,
        last_action: np.ndarray, clearance: np.ndarray, truncated: bool,
    ) -> None:
        """Take the state of this episode from :class:`~aasoatt_env.sim.batched.BatchedAASOATTEnv`, which steps it.

        Afterwards the env reports (positions, ``state()``, ``render()``) what the batch computed.
        """
        self._pose, self._u = pose.copy(), u.copy()
        self._time, self._steps = float(time), int(steps)
        self._active = active.copy()
        self._saturated, self._last_action = saturated.copy(), last_action.copy()
        self._kin = dynamics.kinematics(self.team, self._pose, self._u)
        live = [] if truncated else [a for a, on in zip(self.possible_agents, self._active) if on]
        self.agents = live
        self._live_idx = np.array([self._index[a] for a in live], dtype=np.intp)
        self._refresh()
        self._clearance = clearance.copy()
        if not self._trail or not np.array_equal(self._trail[-1], self._kin.p):
            self._trail.append(self._kin.p.copy())

    # ------------------------------------------------------------------ outputs
    def _refresh(self, between: np.ndarray | None = None) -> None:
        """Recompute what observations, rewards and infos share at the current instant.

        ``between``: clearance over the physics steps since the last decision; the
        reported clearance (and so collisions) is the minimum over the whole env step.
        """
        # read-only views (the reference's own arrays stay as they are): shared with the next step's filter input
        self._ref_now = tuple(np.asarray(r).view() for r in self._layout.reference(self._time))  # type: ignore[union-attr]
        for r in self._ref_now:
            r.flags.writeable = False
        self._ref_of = (self._layout, self._time)
        self._prox: Proximity = proximity(
            self._kin.p, self.team.radius, *self._obstacles, k=max(self.num_neighbors, 1)
        )
        self._err = np.hypot(*(self._kin.p - self._ref_now[0]).T)
        self._clearance = self._prox.clearance if between is None else np.minimum(self._prox.clearance, between)

    def _reference_at(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The reference at ``t``: the one :meth:`_refresh` evaluated when it was for this layout at ``t``."""
        layout, t_now = self._ref_of
        if layout is self._layout and t == t_now:
            return self._ref_now
        return self._layout.reference(t)  # type: ignore[union-attr]

    def _observations(self) -> dict[str, np.ndarray]:
        p_d, v_d, a_d = self._ref_now
        kin = self._kin
        obs = build_observations(
            p=kin.p,
            v=kin.v,
            theta=self._pose[:, 2],
            u=self._u,
            p_d=p_d,
            v_d=v_d,
            a_d=a_d,
            goals=self._layout.reference.goals,  # type: ignore[union-attr]
            radii=self.team.radius,
            obstacle_centers=self._obstacles[0],
            obstacle_radii=self._obstacles[1],
            sensing_range=self.sensing_range,
            k_robots=self.num_neighbors,
            k_obstacles=self.num_obstacles,
            prox=self._prox,
        )
        if len(self.agents) == len(self.possible_agents):
            return dict(zip(self.agents, obs))
        idx = self._index
        return {a: obs[idx[a]] for a in self.agents}

    def _infos(self) -> dict[str, dict[str, Any]]:
        clearance = self._clearance
        err = self._err.tolist()
        clr = clearance.tolist()
        col = (clearance < -self.collision_tolerance).tolist()
        sat = self._saturated.tolist()
        t = self._time
        idx = self._index
        out = {}
        for a in self.agents:
            i = idx[a]
            out[a] = {
                "tracking_error": err[i],
                "clearance": clr[i],
                "collision": col[i],
                "saturated": sat[i],
                "time": t,
            }
        return out

    def state(self) -> np.ndarray:
        """Global state: poses (3N), wheel speeds (2N), reference points (2N), velocities (2N), time."""
        self._require_reset("state()")
        p_d, v_d, _ = self._ref_now
        return np.concatenate([self._pose.ravel(), self._u.ravel(), p_d.ravel(), v_d.ravel(), [self._time]])

    # ------------------------------------------------------------------ properties
    @property
    def positions(self) -> np.ndarray:
        """Control-point positions ``(N, 2)``."""
        self._require_reset("positions")
        return self._kin.p.copy()

    @property
    def velocities(self) -> np.ndarray:
        """Control-point velocities ``(N, 2)``."""
        self._require_reset("velocities")
        return self._kin.v.copy()

    @property
    def headings(self) -> np.ndarray:
        """Headings ``(N,)`` [rad]."""
        self._require_reset("headings")
        return self._pose[:, 2].copy()

    @property
    def poses(self) -> np.ndarray:
        """Axle poses ``(N, 3)``."""
        self._require_reset("poses")
        return self._pose.copy()

    @property
    def wheel_speeds(self) -> np.ndarray:
        """Wheel angular speeds ``(N, 2)`` (double integrator: velocity)."""
        self._require_reset("wheel_speeds")
        return self._u.copy()

    @property
    def radii(self) -> np.ndarray:
        """Robot radii ``(N,)``."""
        self._require_reset("radii")
        return self.team.radius.copy()

    @property
    def goals(self) -> np.ndarray:
        """Final reference points ``(N, 2)``."""
        self._require_reset("goals")
        return np.asarray(self.layout.reference.goals).copy()

    @property
    def time(self) -> float:
        """Simulated time [s]."""
        self._require_reset("time")
        return self._time

    @property
    def max_steps(self) -> int:
        """Episode length in env steps (the horizon, or ``max_steps``)."""
        self._require_reset("max_steps")
        return self._max_steps

    @property
    def reference(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Current reference ``(p_d, v_d, a_d)``, each ``(N, 2)``."""
        self._require_reset("reference")
        p_d, v_d, a_d = self._ref_now
        return p_d.copy(), v_d.copy(), a_d.copy()

    @property
    def obstacles(self) -> tuple[np.ndarray, np.ndarray]:
        """Static obstacles: centres ``(M, 2)`` and radii ``(M,)``."""
        self._require_reset("obstacles")
        c, r = self._obstacles
        return c.copy(), r.copy()

    @property
    def kinematics(self) -> Kinematics:
        """Current control-point kinematics (``p``, ``v``, ``A``, ``A_dot u``)."""
        self._require_reset("kinematics")
        return self._kin

    @property
    def layout(self) -> Layout:
        """The episode's layout (team, starts, reference, obstacles, bounds)."""
        if self._layout is None:
            raise ResetNeeded("layout: call reset() first")
        return self._layout

    # ------------------------------------------------------------------ rendering
    def render(self) -> np.ndarray | None:
        """Render the current frame (``rgb_array``: an ``(H, W, 3)`` uint8 array)."""
        if self.render_mode is None:
            return None
        self._require_reset("render()")
        if self._renderer is None:
            self._renderer = Renderer()
        avoiding = None
        if self._filter_outputs:
            avoiding = np.any([np.asarray(o.avoiding) for o in self._filter_outputs], axis=0)
        frame = Frame(
            positions=self._kin.p,
            headings=self._pose[:, 2],
            radii=self.team.radius,
            references=self._ref_now[0],
            goals=self.goals,
            obstacle_centers=self._obstacles[0],
            obstacle_radii=self._obstacles[1],
            trails=np.asarray(self._trail),
            avoiding=avoiding,
            sensing_range=None,
            time=self._time,
            title=self.scenario.name,
            world_bounds=self.layout.bounds,
        )
        if self.render_mode == "human":
            self._renderer.show(frame)
            return None
        return self._renderer.rgb_array(frame)

    def close(self) -> None:
        """Release the renderer."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
