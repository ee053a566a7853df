"""PettingZoo parallel env of acceleration-actuated robots ``robot_0 .. robot_{N-1}`` (``docs/env.md``)."""

from __future__ import annotations

import math
import warnings
from collections import deque
from collections.abc import Callable, Mapping
from types import MappingProxyType
from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from aasoatt_env import validation as check
from aasoatt_env.errors import ActionError, ConfigError, ResetNeeded, UsageError
from aasoatt_env.model import dynamics
from aasoatt_env.model.dynamics import DT
from aasoatt_env.sim.observations import OBS_BOUND, SELF_DIM, SLOT_DIM
from aasoatt_env.sim.protocol import ControlFilter, FilterOutput
from aasoatt_env.sim.rendering import Frame, Renderer
from aasoatt_env.sim.rewards import RewardConfig
from aasoatt_env.sim.scenarios import Layout, Scenario, get_scenario
from aasoatt_env.sim.scenarios.base import check_starts
from aasoatt_env.sim.stack import TeamStack

__all__ = ["MAX_NEIGHBOR_SLOTS", "TRAIL_LENGTH", "AASOATTParallelEnv", "action_bound", "checked_actions",
           "env_settings", "parse_actions", "real_actions"]

MAX_NEIGHBOR_SLOTS: int = 256
"""Largest ``num_neighbors`` / ``num_obstacles`` (observation slots) accepted."""
TRAIL_LENGTH: int = 400
"""Control-point positions kept for rendering trails."""
FILTERED_MIN_COLLISION_TOLERANCE: float = 1e-9
"""Smallest ``collision_tolerance`` [m] with ``terminate_on_collision`` behind a filter (its guarantee's rounding)."""


# the envs' one set of action checks; errors name the agent (env) or the `[team, robot]` entry (batches)
_NOMINAL_MAX = 1e6  # largest nominal action behind a filter (in units of the bound): larger ones are a bug

_FLOAT_MAX = float(np.finfo(np.float64).max)
_REAL = "(a float or integer dtype)"


def _bool_at(value: Any) -> tuple[int, ...] | None:
    """Index of the first boolean inside nested lists/tuples (a bool, or a boolean array or tensor), or None."""
    if isinstance(value, np.ndarray):
        return () if value.dtype.kind == "b" else None
    dtype = getattr(value, "dtype", None)
    if dtype is not None:
        return () if "bool" in str(dtype) else None
    if isinstance(value, (bool, np.bool_)):
        return ()
    if isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            at = _bool_at(v)
            if at is not None:
                return (i, *at)
    return None


def real_actions(value: Any, name: Callable[[tuple[int, ...]], str], expected: str,
                 shape: tuple[int, ...] | None = None) -> np.ndarray:
    """``value`` as an array of real numbers (no booleans, even one among numbers; of ``shape``), else an error."""
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError):
        raise ActionError(f"{name(())}: got {type(value).__name__}, expected {expected} {_REAL}") from None
    if arr.dtype.kind not in "fiu":
        raise ActionError(f"{name(())}: got shape {arr.shape} (dtype {arr.dtype}), expected {expected} {_REAL}")
    at = None if isinstance(value, np.ndarray) else _bool_at(value)
    if at is not None:
        raise ActionError(f"{name(at)}: got booleans, expected {expected} {_REAL}")
    if shape is not None and arr.shape != shape:
        raise ActionError(f"{name(())}: got shape {arr.shape}, expected {shape}")
    return arr


def action_bound(nominal: bool, clip: bool) -> float:
    """The largest action magnitude accepted: a ``nominal``'s, any finite one with ``clip``, else ``1 + 1e-6``."""
    return _NOMINAL_MAX if nominal else (_FLOAT_MAX if clip else 1.0 + 1e-6)


def checked_actions(act: np.ndarray, nominal: bool, clip: bool, name: Callable[[int], str]) -> np.ndarray:
    """Finite actions ``(R, 2)`` within their bound, clipped (in place) to ``[-1, 1]`` unless ``nominal``.

    The bound is ``_NOMINAL_MAX`` for a ``nominal``, else ``1 + 1e-6`` (any finite value with ``clip``).
    """
    peak = float(np.abs(act).max(initial=0.0))
    accept = action_bound(nominal, clip)
    if not peak <= accept:  # also NaN and inf
        if not math.isfinite(peak):
            bad = int(np.flatnonzero(~np.isfinite(act).all(axis=1))[0])
            raise ActionError(f"{name(bad)}: got non-finite values {act[bad].tolist()}, expected finite numbers")
        bad = int(np.flatnonzero(np.abs(act).max(axis=1) > accept)[0])
        raise ActionError(f"{name(bad)}: got {act[bad].tolist()}, expected " + (
            f"a nominal within [-{_NOMINAL_MAX:g}, {_NOMINAL_MAX:g}] (in units of the wheel-acceleration bound; "
            "the filter keeps the bounds)" if nominal else "values in [-1, 1] (or clip_actions=True)"))
    if not nominal and peak > 1.0:
        np.minimum(np.maximum(act, -1.0, out=act), 1.0, out=act)
    return act


def env_settings(dt: Any, decision_interval: Any, action_mode: Any, sensing_range: Any, num_neighbors: Any,
                 num_obstacles: Any, reward: Any, collision_tolerance: Any, max_steps: Any,
                 clip_actions: Any) -> dict[str, Any]:
    """The settings every env (numpy or torch) shares, checked, as the env's attributes."""
    return dict(dt=check.real("dt", dt, lo=1e-6, hi=0.1),
                decision_interval=check.integer("decision_interval", decision_interval, lo=1, hi=10_000),
                action_mode=check.choice("action_mode", action_mode, ("wheel", "point")),
                sensing_range=check.positive("sensing_range", sensing_range, hi=1e6),
                num_neighbors=check.integer("num_neighbors", num_neighbors, lo=0, hi=MAX_NEIGHBOR_SLOTS),
                num_obstacles=check.integer("num_obstacles", num_obstacles, lo=0, hi=MAX_NEIGHBOR_SLOTS),
                reward_config=RewardConfig.coerce(reward),
                collision_tolerance=check.real("collision_tolerance", collision_tolerance, lo=0.0, hi=1.0),
                _max_steps_override=None if max_steps is None else check.integer("max_steps", max_steps, lo=1,
                                                                                  hi=10**12),
                clip_actions=check.boolean("clip_actions", clip_actions))


def parse_actions(actions: Any, live: np.ndarray, nominal: bool, clip: bool, offset: int = 0) -> np.ndarray:
    """Checked actions ``(K N, 2)`` of teams ``(K, N) = live.shape`` (done agents' rows 0, first team ``offset``)."""
    k, n = live.shape
    expected = f"real numbers of shape ({k}, {n}, 2)"

    def robot(at: tuple[int, ...]) -> str:  # an entry of nested (K, N, 2) or (K N, 2) sequences
        if not at:
            return "actions"
        if np.ndim(actions) == 3:
            return f"actions[{at[0] + offset}" + (f", {at[1]}]" if len(at) > 1 else "]")
        return f"actions[{at[0] // n + offset}, {at[0] % n}]"

    arr = real_actions(actions, robot, expected)
    if arr.size != k * n * 2 or arr.shape not in ((k, n, 2), (k * n, 2)):
        raise ActionError(f"actions: got shape {arr.shape} (dtype {arr.dtype}), expected {expected}")
    act = arr.reshape(k * n, 2).astype(np.float64)
    act[~live.ravel()] = 0.0  # the env ignores actions of agents that are done
    return checked_actions(act, nominal, clip, lambda row: f"actions[{row // n + offset}, {row % n}]")


def _after_reset(name: str, get: Callable[[AASOATTParallelEnv], Any], doc: str) -> property:
    """A read-only property that raises :class:`ResetNeeded` before the first ``reset``."""

    def fget(self: AASOATTParallelEnv) -> Any:
        self._require_reset(name)
        return get(self)

    return property(fget, doc=doc)


class AASOATTParallelEnv(ParallelEnv, TeamStack):
    """Multi-robot trajectory tracking at acceleration level (``docs/env.md``).

    ``scenario``: a name of :data:`~aasoatt_env.sim.scenarios.SCENARIOS` (``**scenario_kwargs``: its
    parameters) or a :class:`Scenario`; ``num_neighbors``, ``num_obstacles``: observation slots for neighbours
    within ``sensing_range`` [m]; ``max_steps`` overrides the scenario's horizon.
    """

    metadata = {"render_modes": ["rgb_array", "human"], "name": "aasoatt_v0", "render_fps": 20}
    _stack_teams = False

    def __init__(self, scenario: str | Scenario = "circle_swap", render_mode: str | None = None, dt: float = DT,
                 decision_interval: int = 1, action_mode: str = "wheel", sensing_range: float = 3.0,
                 num_neighbors: int = 4, num_obstacles: int = 2,
                 reward: RewardConfig | Mapping[str, float] | None = None, terminate_on_collision: bool = False,
                 collision_tolerance: float = 1e-3, max_steps: int | None = None, clip_actions: bool = False,
                 **scenario_kwargs: Any) -> None:
        if render_mode is not None:
            check.choice("render_mode", render_mode, self.metadata["render_modes"])
        vars(self).update(env_settings(dt, decision_interval, action_mode, sensing_range, num_neighbors, num_obstacles,
                                       reward, collision_tolerance, max_steps, clip_actions))
        self.terminate_on_collision = check.boolean("terminate_on_collision", terminate_on_collision)
        self.scenario = get_scenario(scenario, **scenario_kwargs)
        self.render_mode = render_mode
        n = self.scenario.num_robots
        self.possible_agents = [f"robot_{i}" for i in range(n)]
        self.agents: list[str] = []
        self._index = {a: i for i, a in enumerate(self.possible_agents)}
        obs_dim = SELF_DIM + SLOT_DIM * (self.num_neighbors + self.num_obstacles)
        obs_space = spaces.Box(-OBS_BOUND, OBS_BOUND, (obs_dim,), np.float32)
        self.observation_spaces = dict.fromkeys(self.possible_agents, obs_space)
        self.action_spaces = dict.fromkeys(self.possible_agents, spaces.Box(-1.0, 1.0, (2,), np.float32))
        self.state_space = spaces.Box(-np.inf, np.inf, (9 * n + 1,), np.float64)
        self._bases, self._grouped, self._offset = [self], None, 0
        self._control_filter: ControlFilter | None = None
        self._filter_outputs: tuple[FilterOutput, ...] = ()
        self._rng = np.random.default_rng()
        self._renderer: Any = None
        self._trail: deque[np.ndarray] = deque(maxlen=TRAIL_LENGTH)
        self._warned_dead = False
        self._init_stack(1, n)

    def observation_space(self, agent: str) -> spaces.Box:
        """Observation space of ``agent`` (one object for all)."""
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Box:
        """Action space of ``agent`` (one object for all)."""
        return self.action_spaces[agent]

    @property
    def agent_index(self) -> Mapping[str, int]:
        """Read-only map agent name -> robot index (row of every ``(N, ...)`` array)."""
        return MappingProxyType(self._index)

    def set_control_filter(self, control_filter: ControlFilter | None) -> None:
        """Install the control filter (:mod:`aasoatt_env.sim.protocol`; one per env), or remove it with None."""
        if control_filter is None:
            self._control_filter, self._filter_outputs = None, ()
            return
        if not isinstance(control_filter, ControlFilter):
            raise ConfigError(f"control_filter: got {type(control_filter).__name__}, expected an object with "
                              "reset(team), __call__(FilterInput, nominal_du) and keeps_input_bounds "
                              "(aasoatt_env.sim.protocol.ControlFilter)")
        if self.terminate_on_collision and self.collision_tolerance < FILTERED_MIN_COLLISION_TOLERANCE:
            raise ConfigError(  # a robot terminated for less stops in place: an input the filter cannot plan for
                f"collision_tolerance: got {self.collision_tolerance:g} with terminate_on_collision=True, expected "
                f">= {FILTERED_MIN_COLLISION_TOLERANCE:g} m behind a control filter (its guarantee's rounding)")
        if self._control_filter is not None and self._control_filter is not control_filter:
            raise UsageError(f"this env already has a control filter ({type(self._control_filter).__name__}); an env "
                             "takes one filter: wrap it once, or remove the first with set_control_filter(None)")
        self._control_filter = control_filter
        if self._layouts[0] is not None:
            control_filter.reset(self.team)

    @property
    def control_filter(self) -> ControlFilter | None:
        """The control filter (None: actions as they are)."""
        return self._control_filter

    @property
    def filter_outputs(self) -> tuple[FilterOutput, ...]:
        """The control filter's outputs at the physics steps of the last ``step`` (or empty)."""
        return self._filter_outputs

    @property
    def _nominal_actions(self) -> bool:
        """Actions are a nominal the filter projects (may leave ``[-1, 1]``)."""
        f = self._control_filter
        return f is not None and bool(f.keeps_input_bounds) and not self.clip_actions

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """Start an episode; ``seed`` (an integer >= 0) seeds the layout; ``options`` (a dict) is ignored."""
        seed = None if seed is None else check.integer("seed", seed, lo=0)
        if options is not None and not isinstance(options, Mapping):
            raise ConfigError(f"options: got {type(options).__name__}, expected a dict or None")
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        layout = self.scenario.build(self._rng)
        check_starts(self.scenario, layout)
        self._init_stack(1, layout.team.n)  # a fresh state
        self.team, self._layouts[0], self._teams[0] = layout.team, layout, layout.team
        self._pose = dynamics.pose_from_point(layout.team, layout.starts, layout.headings)
        self._max_steps[0] = self._max_steps_override or max(
            1, int(math.ceil(layout.horizon / (self.dt * self.decision_interval) - 1e-9)))
        self._active[:] = True
        self.agents, self._live_idx, self._filter_outputs = list(self.possible_agents), np.arange(self._n), ()
        try:
            self._restack()
            self._refresh()
        except BaseException:  # a reference that cannot be evaluated: no episode
            self._layouts, self.agents = [None], []
            raise
        self._trail.clear()
        self._trail.append(self._kin.p.copy())  # type: ignore[union-attr]
        if self._control_filter is not None:
            self._control_filter.reset(self.team)
        obs, infos = self._agent_observations(), self._infos()
        if self.render_mode == "human":
            self.render()
        return obs, infos

    def _require_reset(self, what: str) -> None:
        if self._layouts[0] is None:
            raise ResetNeeded(f"{what}: call reset() first")

    def _check_agents(self, actions: dict[str, Any]) -> None:
        unknown = [a for a in actions if a not in self._index]
        if unknown:
            raise ActionError(f"actions: unknown agent(s) {unknown}; agents are "
                              f"{self.possible_agents[0]}..{self.possible_agents[-1]}")
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ActionError(f"actions: missing action for live agent(s) {missing}")
        if not self._warned_dead:
            self._warned_dead = True
            dead = [a for a in actions if a not in self.agents]
            warnings.warn(f"actions for agent(s) that are done are ignored ({dead}); this warning is shown once "
                          "per env", UserWarning, stacklevel=4)

    def _parse_actions(self, actions: dict[str, Any]) -> np.ndarray:
        """The live agents' actions as ``(N, 2)`` float64 (rows of agents that are done: 0), checked."""
        if not isinstance(actions, dict):
            raise ActionError(f"actions: got {type(actions).__name__}, expected a dict agent -> action")
        live = self.agents
        if actions.keys() != set(live):
            self._check_agents(actions)
        values = [actions[a] for a in live]
        try:  # one array when every action is a numpy array of numbers (the common case)
            arr = np.asarray(values) if all(d.kind in "fiu" for d in {v.dtype for v in values}) else None
        except (AttributeError, TypeError, ValueError):
            arr = None
        if arr is None or arr.shape != (len(live), 2):
            arr = np.array([real_actions(v, lambda _, a=a: f"actions[{a!r}]", "2 real numbers", (2,))
                            for a, v in zip(live, values)], dtype=np.float64)
        if len(live) == len(self.possible_agents):
            act = arr.astype(np.float64)
        else:
            act = np.zeros((len(self.possible_agents), 2))
            act[self._live_idx] = arr
        return checked_actions(act, self._nominal_actions, self.clip_actions,
                               lambda row: f"actions[{self.possible_agents[row]!r}]")

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """Apply the actions for ``decision_interval`` physics steps."""
        self._require_reset("step()")
        if not self.agents:
            raise ResetNeeded("step() called with no live agents (the episode is over); call reset() first")
        act = self._parse_actions(actions)
        saturated, between, outputs = self._physics(act)
        self._filter_outputs = tuple(outs[0] for outs in outputs) if outputs else ()
        self._trail.append(self._kin.p.copy())  # type: ignore[union-attr]
        obs, rew, _, term, finished, _, _ = self._decide(act, saturated, between, outputs)
        live, idx = self.agents, self._index
        rew = rew.tolist()
        obs, infos = self._agent_observations(obs), self._infos()
        rewards = dict(zip(live, rew)) if len(live) == self._n else {a: rew[idx[a]] for a in live}
        terminations = dict.fromkeys(live, False) if term is None else {a: bool(term[idx[a]]) for a in live}
        truncated = bool(finished[0])
        truncations = dict.fromkeys(live, truncated)
        self.agents = [] if truncated else list(live) if term is None else [a for a in live if not terminations[a]]
        if len(self.agents) != len(live):
            self._live_idx = np.array([idx[a] for a in self.agents], dtype=np.intp)
        if self.render_mode == "human":
            self.render()
        return obs, rewards, terminations, truncations, infos

    def _load_state(self, batch: TeamStack, k: int, truncated: bool) -> None:
        """Take this episode's state from team ``k`` of ``batch``, which steps it; then report what it computed."""
        self._take_team(0, batch, k)
        self._kin = dynamics.kinematics(self.team, self._pose, self._u)
        self.agents = [] if truncated else [a for a, on in zip(self.possible_agents, self._active) if on]
        self._live_idx = np.array([self._index[a] for a in self.agents], dtype=np.intp)
        clearance = self._clearance.copy()
        self._refresh()
        self._clearance, self._collided = clearance, clearance < -self.collision_tolerance
        if not self._trail or not np.array_equal(self._trail[-1], self._kin.p):
            self._trail.append(self._kin.p.copy())

    def _agent_observations(self, obs: np.ndarray | None = None) -> dict[str, np.ndarray]:
        obs = self._observations() if obs is None else obs
        if len(self.agents) == self._n:
            return dict(zip(self.agents, obs))
        return {a: obs[self._index[a]] for a in self.agents}

    def _infos(self) -> dict[str, dict[str, Any]]:
        err, clr, sat, col = (x.tolist() for x in (self._err, self._clearance, self._saturated, self._collided))
        t = float(self._times[0])
        return {a: {"tracking_error": err[i], "clearance": clr[i], "collision": col[i], "saturated": sat[i], "time": t}
                for a, i in ((a, self._index[a]) for a in self.agents)}

    def state(self) -> np.ndarray:
        """Global state: poses (3N), wheel speeds (2N), reference points (2N), velocities (2N), time."""
        self._require_reset("state()")
        p_d, v_d, _ = self._ref_now
        return np.concatenate([self._pose.ravel(), self._u.ravel(), p_d.ravel(), v_d.ravel(), self._times])

    positions = _after_reset("positions", lambda e: e._kin.p.copy(), "Control-point positions ``(N, 2)``.")
    velocities = _after_reset("velocities", lambda e: e._kin.v.copy(), "Control-point velocities ``(N, 2)``.")
    headings = _after_reset("headings", lambda e: e._pose[:, 2].copy(), "Headings ``(N,)`` [rad].")
    poses = _after_reset("poses", lambda e: e._pose.copy(), "Axle poses ``(N, 3)``.")
    wheel_speeds = _after_reset("wheel_speeds", lambda e: e._u.copy(), "Wheel speeds ``(N, 2)`` [rad/s].")
    radii = _after_reset("radii", lambda e: e.team.radius.copy(), "Robot radii ``(N,)``.")
    goals = _after_reset("goals", lambda e: np.asarray(e.layout.reference.goals).copy(), "Goals ``(N, 2)``.")
    time = _after_reset("time", lambda e: float(e._times[0]), "Simulated time [s].")
    max_steps = _after_reset("max_steps", lambda e: int(e._max_steps[0]), "Episode length in env steps.")
    reference = _after_reset("reference", lambda e: tuple(r.copy() for r in e._ref_now), "``(p_d, v_d, a_d)`` now.")
    obstacles = _after_reset("obstacles", lambda e: (e.layout.obstacle_centers.copy(), e.layout.obstacle_radii.copy()),
                             "Static obstacles: centres ``(M, 2)`` and radii ``(M,)``.")
    layout = _after_reset("layout", lambda e: e._layouts[0], "The episode's :class:`.Layout`.")
    kinematics = _after_reset("kinematics", lambda e: e._kin, "Control-point kinematics ``(p, v, A, A_dot u)``.")

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
        lay: Layout = self.layout
        frame = Frame(positions=self._kin.p, headings=self._pose[:, 2], radii=self.team.radius,  # type: ignore
                      references=self._ref_now[0], goals=self.goals, obstacle_centers=lay.obstacle_centers,
                      obstacle_radii=lay.obstacle_radii, trails=np.asarray(self._trail), avoiding=avoiding,
                      time=float(self._times[0]), title=self.scenario.name, world_bounds=lay.bounds)
        if self.render_mode == "human":
            self._renderer.show(frame)
            return None
        return self._renderer.rgb_array(frame)

    def close(self) -> None:
        """Release the renderer."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
