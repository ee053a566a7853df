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
reward                 :class:`RewardConfig` (tracking, collision, effort, filter
                       correction)
=====================  =========================================================

One ``step`` holds each agent's action for ``decision_interval`` physics steps of
``dt`` seconds (default 0.005 s, the paper's step).  A control filter (see
:class:`aasoatt_env.safety.wrapper.AASOATTFilter`) may be installed with
:meth:`AASOATTParallelEnv.set_control_filter`; it then maps the nominal wheel
accelerations to applied ones at *every* physics step.

Episodes are truncated at the scenario's horizon.  With
``terminate_on_collision=True`` a robot whose clearance falls below
``-collision_tolerance`` terminates: it leaves ``env.agents`` and stays in the
world as a static disc (it stops in place).

Wheel-speed limits (``RobotParams.max_wheel_speed``) are enforced by saturating
the applied ``du`` to the speed-admissible range of the step; ``infos`` reports
``saturated`` when that happened.  Actions outside ``[-1, 1]`` raise
:class:`~aasoatt_env.errors.ActionError` unless ``clip_actions=True``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any, NamedTuple

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from aasoatt_env.model import dynamics
from aasoatt_env.model.dynamics import Kinematics
from aasoatt_env.errors import ActionError, ConfigError
from aasoatt_env.sim.observations import (
    OBS_BOUND,
    SELF_DIM,
    SLOT_DIM,
    Proximity,
    build_observations,
    min_gaps,
    proximity,
)
from aasoatt_env.model.params import Team, check_positive
from aasoatt_env.sim.scenarios import Layout, Scenario, get_scenario

__all__ = ["AASOATTParallelEnv", "RewardConfig", "SimState"]

_FLOAT_MAX = float(np.finfo(np.float64).max)


def _row_norms(x: np.ndarray) -> np.ndarray:
    """Euclidean norms of the rows of an ``(N, 2)`` array."""
    return np.hypot(x[:, 0], x[:, 1])


@dataclass(frozen=True)
class RewardConfig:
    """Per-agent reward of one env step (all weights >= 0).

    ``r_i = -tracking * |p_i - p_d_i| - collision * [clearance_i < -tol]
    - effort * |action_i|^2 / 2 - correction * c_i + goal_bonus * [|p_i - goal_i| < goal_tolerance]``

    where ``c_i`` is the filter's correction ``|du_safe - du_nominal|`` divided by
    the robot's ``max_wheel_accel`` (0 without a filter).
    """

    tracking: float = 1.0
    collision: float = 10.0
    effort: float = 0.01
    correction: float = 0.0
    goal_bonus: float = 0.0
    goal_tolerance: float = 0.05

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ConfigError(f"RewardConfig.{f.name}: got {v!r}, expected a finite number >= 0")


class SimState(NamedTuple):
    """What a control filter sees at one physics step."""

    time: float
    dt: float
    team: Team
    kin: Kinematics
    u: np.ndarray
    theta: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    reference: tuple[np.ndarray, np.ndarray, np.ndarray]
    obstacles: tuple[np.ndarray, np.ndarray]
    active: np.ndarray


ControlFilter = Callable[[SimState, np.ndarray], np.ndarray]


class AASOATTParallelEnv(ParallelEnv):
    """Multi-robot trajectory tracking at acceleration level (see module docstring).

    Parameters
    ----------
    scenario : str or Scenario
        Scenario name (see :data:`aasoatt_env.sim.scenarios.SCENARIOS`) or instance.
    render_mode : {None, "rgb_array", "human"}
        Rendering mode.
    dt : float
        Physics step [s].
    decision_interval : int
        Physics steps per env step (the action is held).
    action_mode : {"wheel", "point"}
        Meaning of actions (module docstring).
    sensing_range : float
        Neighbours farther than this are not observed [m].
    num_neighbors, num_obstacles : int
        Observation slots ``K`` and ``K_obs``.
    reward : RewardConfig or dict, optional
        Reward weights.
    terminate_on_collision : bool
        Terminate robots that collide.
    collision_tolerance : float
        Overlap [m] below which contact does not count as a collision.
    max_steps : int, optional
        Override the horizon in env steps.
    clip_actions : bool
        Clip actions to ``[-1, 1]`` instead of raising.
    **scenario_kwargs
        Passed to the scenario (e.g. ``num_robots=20``).
    """

    metadata = {"render_modes": ["rgb_array", "human"], "name": "aasoatt_v0", "render_fps": 20}

    def __init__(
        self,
        scenario: str | Scenario = "circle_swap",
        render_mode: str | None = None,
        dt: float = 0.005,
        decision_interval: int = 1,
        action_mode: str = "wheel",
        sensing_range: float = 3.0,
        num_neighbors: int = 4,
        num_obstacles: int = 2,
        reward: RewardConfig | dict[str, float] | None = None,
        terminate_on_collision: bool = False,
        collision_tolerance: float = 1e-3,
        max_steps: int | None = None,
        clip_actions: bool = False,
        **scenario_kwargs: Any,
    ) -> None:
        self.scenario = get_scenario(scenario, **scenario_kwargs)
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ConfigError(
                f"render_mode: got {render_mode!r}, expected None or one of {self.metadata['render_modes']}"
            )
        self.render_mode = render_mode
        self.dt = check_positive("dt", dt)
        if int(decision_interval) != decision_interval or decision_interval < 1:
            raise ConfigError(f"decision_interval: got {decision_interval!r}, expected an integer >= 1")
        self.decision_interval = int(decision_interval)
        if action_mode not in ("wheel", "point"):
            raise ConfigError(f"action_mode: got {action_mode!r}, expected 'wheel' or 'point'")
        self.action_mode = action_mode
        self.sensing_range = check_positive("sensing_range", sensing_range)
        for name, val in (("num_neighbors", num_neighbors), ("num_obstacles", num_obstacles)):
            if int(val) != val or val < 0:
                raise ConfigError(f"{name}: got {val!r}, expected an integer >= 0")
        self.num_neighbors, self.num_obstacles = int(num_neighbors), int(num_obstacles)
        self.reward_config = (
            RewardConfig(**reward) if isinstance(reward, dict) else (reward or RewardConfig())
        )
        self.terminate_on_collision = bool(terminate_on_collision)
        if collision_tolerance < 0:
            raise ConfigError(f"collision_tolerance: got {collision_tolerance!r}, expected >= 0")
        self.collision_tolerance = float(collision_tolerance)
        if max_steps is not None and (int(max_steps) != max_steps or max_steps < 1):
            raise ConfigError(f"max_steps: got {max_steps!r}, expected an integer >= 1")
        self._max_steps_override = None if max_steps is None else int(max_steps)
        self.clip_actions = bool(clip_actions)
        self.action_range = "clip" if clip_actions else "strict"
        """``"strict"``: out-of-range actions raise; ``"clip"``: clipped; ``"nominal"``: taken as is
        (set by :class:`~aasoatt_env.safety.wrapper.AASOATTFilter`, whose QP keeps the bounds)."""

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
        self._rng = np.random.default_rng()
        self._renderer: Any = None
        self._trail: list[np.ndarray] = []
        self._layout: Layout | None = None

    # ------------------------------------------------------------------ spaces
    def observation_space(self, agent: str) -> spaces.Box:
        """Observation space of ``agent`` (the same object on every call)."""
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Box:
        """Action space of ``agent`` (the same object on every call)."""
        return self.action_spaces[agent]

    # ------------------------------------------------------------------ filter hook
    def set_control_filter(self, control_filter: ControlFilter | None) -> None:
        """Install (or remove with None) a per-physics-step map ``(SimState, du_nominal) -> du``."""
        self._control_filter = control_filter

    # ------------------------------------------------------------------ reset/step
    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """Start an episode; ``seed`` seeds the scenario's random layout."""
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        layout = self.scenario.build(self._rng)
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
        self._trail = [self._kin.p.copy()]
        self._live_idx = np.arange(layout.team.n)
        self._refresh()
        if self._control_filter is not None and hasattr(self._control_filter, "reset"):
            self._control_filter.reset()  # type: ignore[attr-defined]
        obs = self._observations()
        infos = self._infos()
        if self.render_mode == "human":
            self.render()
        return obs, infos

    def _parse_actions(self, actions: dict[str, Any]) -> np.ndarray:
        if not isinstance(actions, dict):
            raise ActionError(f"actions: got {type(actions).__name__}, expected a dict agent -> action")
        live = self.agents
        n_all = len(self.possible_agents)
        if actions.keys() == set(live):  # fast path: one array, one finiteness/range check
            try:
                arr = np.array([actions[a] for a in live], dtype=np.float64)
            except (TypeError, ValueError):
                arr = None
            if arr is not None and arr.shape == (len(live), 2):
                peak = np.abs(arr).max(initial=0.0)  # NaN propagates, so this also checks finiteness
                if peak <= (1.0 + 1e-6 if self.action_range == "strict" else _FLOAT_MAX):
                    if len(live) == n_all:
                        act = arr
                    else:
                        act = np.zeros((n_all, 2))
                        act[self._live_idx] = arr
                    if self.action_range != "nominal" and peak > 1.0:
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
        if dead:
            raise ActionError(f"actions: agent(s) {dead} are done and must not act")
        for agent, a in actions.items():
            try:
                arr = np.asarray(a, dtype=np.float64)
            except (TypeError, ValueError):
                raise ActionError(f"actions[{agent!r}]: got {a!r}, expected an array of 2 numbers") from None
            if arr.shape != (2,):
                raise ActionError(f"actions[{agent!r}]: got shape {arr.shape}, expected (2,)")
            if not np.all(np.isfinite(arr)):
                raise ActionError(
                    f"actions[{agent!r}]: got non-finite values {arr.tolist()}, expected finite numbers"
                )
            if self.action_range == "strict" and np.any(np.abs(arr) > 1.0 + 1e-6):
                raise ActionError(
                    f"actions[{agent!r}]: got {arr.tolist()}, expected values in [-1, 1] (or clip_actions=True)"
                )
            act[self._index[agent]] = arr
        return act if self.action_range == "nominal" else np.minimum(np.maximum(act, -1.0, out=act), 1.0, out=act)

    def _nominal_du(self, act: np.ndarray, kin: Kinematics) -> np.ndarray:
        if self.action_mode == "wheel":
            return act * self.team.max_wheel_accel[:, None]
        a = act * self.team.max_point_accel[:, None] - kin.adot_u
        return np.linalg.solve(kin.A, a[..., None])[..., 0]

    @property
    def _obstacles(self) -> tuple[np.ndarray, np.ndarray]:
        assert self._layout is not None
        return self._layout.obstacle_centers, self._layout.obstacle_radii

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """Apply the actions for ``decision_interval`` physics steps."""
        if not self.agents:
            raise ActionError("step() called with no live agents; call reset() first")
        act = self._parse_actions(actions)
        self._last_action = act
        team, dt = self.team, self.dt
        saturated = np.zeros(team.n, dtype=bool)
        frozen = ~self._active
        any_frozen = bool(frozen.any())
        between = np.full(team.n, np.inf)  # clearance at the physics steps between decisions
        for sub in range(self.decision_interval):
            kin = self._kin
            lo, hi = dynamics.input_bounds(team, self._u, dt)
            du_nom = self._nominal_du(act, kin)
            if any_frozen:
                du_nom[frozen] = 0.0
            if self._control_filter is not None:
                sim = SimState(
                    self._time,
                    dt,
                    team,
                    kin,
                    self._u,
                    self._pose[:, 2],
                    lo,
                    hi,
                    self._layout.reference(self._time),
                    self._obstacles,
                    self._active,  # type: ignore[union-attr]
                )
                du = np.asarray(self._control_filter(sim, du_nom), dtype=np.float64)
                if du.shape != du_nom.shape or not np.all(np.isfinite(du)):
                    raise ActionError(
                        f"control filter returned shape {du.shape} or non-finite values, expected finite {du_nom.shape}"
                    )
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
                np.minimum(between, min_gaps(self._kin.p, team.radius, *self._obstacles), out=between)
        self._steps += 1
        self._saturated = saturated
        self._trail.append(self._kin.p.copy())
        self._refresh(between if self.decision_interval > 1 else None)

        collided = self._clearance < -self.collision_tolerance
        rewards_arr = self._rewards(act, collided).tolist()
        truncated = self._steps >= self._max_steps
        live = self.agents
        obs = self._observations()
        infos = self._infos()
        idx = self._index
        all_live = len(live) == len(self.possible_agents)
        rewards = dict(zip(live, rewards_arr)) if all_live else {a: rewards_arr[idx[a]] for a in live}
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
        return obs, rewards, terminations, truncations, infos

    # ------------------------------------------------------------------ outputs
    def _refresh(self, between: np.ndarray | None = None) -> None:
        """Recompute what observations, rewards and infos share at the current instant.

        ``between``: clearance over the physics steps since the last decision; the
        reported clearance (and so collisions) is the minimum over the whole env step.
        """
        self._ref_now = self._layout.reference(self._time)  # type: ignore[union-attr]
        self._prox: Proximity = proximity(
            self._kin.p, self.team.radius, *self._obstacles, k=max(self.num_neighbors, 1)
        )
        self._err = _row_norms(self._kin.p - self._ref_now[0])
        self._clearance = self._prox.clearance if between is None else np.minimum(self._prox.clearance, between)

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
            goals=self._layout.reference.goals,
            radii=self.team.radius,  # type: ignore[union-attr]
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

    def _rewards(self, act: np.ndarray, collided: np.ndarray) -> np.ndarray:
        rc = self.reward_config
        r = -rc.tracking * self._err - rc.collision * collided - rc.effort * 0.5 * np.add.reduce(act * act, axis=1)
        if rc.goal_bonus:
            r = r + rc.goal_bonus * (_row_norms(self._kin.p - self.goals) < rc.goal_tolerance)
        corr = getattr(self._control_filter, "last_correction", None)
        if rc.correction and corr is not None:
            r = r - rc.correction * np.asarray(corr) / self.team.max_wheel_accel
        return r

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
        p_d, v_d, _ = self._layout.reference(self._time)  # type: ignore[union-attr]
        return np.concatenate([self._pose.ravel(), self._u.ravel(), p_d.ravel(), v_d.ravel(), [self._time]])

    # ------------------------------------------------------------------ properties
    @property
    def positions(self) -> np.ndarray:
        """Control-point positions ``(N, 2)``."""
        return self._kin.p.copy()

    @property
    def velocities(self) -> np.ndarray:
        """Control-point velocities ``(N, 2)``."""
        return self._kin.v.copy()

    @property
    def headings(self) -> np.ndarray:
        """Headings ``(N,)`` [rad]."""
        return self._pose[:, 2].copy()

    @property
    def poses(self) -> np.ndarray:
        """Axle poses ``(N, 3)``."""
        return self._pose.copy()

    @property
    def wheel_speeds(self) -> np.ndarray:
        """Wheel angular speeds ``(N, 2)`` (double integrator: velocity)."""
        return self._u.copy()

    @property
    def radii(self) -> np.ndarray:
        """Robot radii ``(N,)``."""
        return self.team.radius.copy()

    @property
    def goals(self) -> np.ndarray:
        """Final reference points ``(N, 2)``."""
        return np.asarray(self._layout.reference.goals).copy()  # type: ignore[union-attr]

    @property
    def time(self) -> float:
        """Simulated time [s]."""
        return self._time

    @property
    def reference(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Current reference ``(p_d, v_d, a_d)``, each ``(N, 2)``."""
        p_d, v_d, a_d = self._ref_now
        return p_d.copy(), v_d.copy(), a_d.copy()

    @property
    def obstacles(self) -> tuple[np.ndarray, np.ndarray]:
        """Static obstacles: centres ``(M, 2)`` and radii ``(M,)``."""
        c, r = self._obstacles
        return c.copy(), r.copy()

    @property
    def kinematics(self) -> Kinematics:
        """Current control-point kinematics (``p``, ``v``, ``A``, ``A_dot u``)."""
        return self._kin

    @property
    def layout(self) -> Layout:
        """The episode's layout (team, starts, reference, obstacles, bounds)."""
        assert self._layout is not None, "call reset() first"
        return self._layout

    # ------------------------------------------------------------------ rendering
    def render(self) -> np.ndarray | None:
        """Render the current frame (``rgb_array``: an ``(H, W, 3)`` uint8 array)."""
        if self.render_mode is None:
            return None
        from aasoatt_env.sim.rendering import Frame, Renderer

        if self._renderer is None:
            self._renderer = Renderer()
        avoiding = getattr(self._control_filter, "last_avoiding", None)
        frame = Frame(
            positions=self._kin.p,
            headings=self._pose[:, 2],
            radii=self.team.radius,
            references=self.reference[0],
            goals=self.goals,
            obstacle_centers=self._obstacles[0],
            obstacle_radii=self._obstacles[1],
            trails=np.asarray(self._trail[-400:]),
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
