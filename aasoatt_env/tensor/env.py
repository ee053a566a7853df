"""``TensorEnv``: ``B`` teams of ``N`` robots as torch tensors, stepped at once (:func:`make_tensor_env`).

The PettingZoo env's dynamics, observations, rewards and episode length: team ``b`` after ``reset(seed=s)`` is the
layout of ``reset(seed=s + b)``, built by the numpy scenario. The step runs the torch stages (:mod:`.model`,
:mod:`.filter`: any device, differentiable) or, chosen when the env is built, the compiled CPU stages
(:mod:`.compiled`). A finished team is reset in the same step from its own generator, and the observation returned
is its new episode's first. Actions are nominal wheel accelerations in units of the bound (behind the filter or
not), or with ``action_mode="point"`` control-point accelerations in units of ``max_point_accel``, turned into
``A^-1 (a - A_dot u)`` at every physics step. No termination on collision; linear references only (``random_goals``,
``circle_swap``, ...).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import fields
from typing import Any

import numpy as np
import torch

from aasoatt_env import validation as check
from aasoatt_env.compiled import NUMBA_MISSING
from aasoatt_env.compiled import available as numba_available
from aasoatt_env.errors import ActionError, ConfigError, ResetNeeded
from aasoatt_env.model import dynamics
from aasoatt_env.model.dynamics import DT
from aasoatt_env.model.geometry import row_norm
from aasoatt_env.safety.config import FilterConfig
from aasoatt_env.sim.env import action_bound, checked_actions, env_settings
from aasoatt_env.sim.observations import OBS_BOUND, SELF_DIM, SLOT_DIM
from aasoatt_env.sim.references import LinearReference
from aasoatt_env.sim.scenarios import Scenario, get_scenario
from aasoatt_env.sim.scenarios.base import check_starts
from aasoatt_env.tensor.compiled import CompiledStages
from aasoatt_env.tensor.filter import BACKUP, FilterOut, backup_check_of, filter_step, torch_config
from aasoatt_env.tensor.model import TensorTeam, check_dtype_device, input_bounds, integrate, kinematics, matvec, pick

__all__ = ["TensorEnv", "make_tensor_env"]

_ENV_KEYS = ("dt", "decision_interval", "action_mode", "sensing_range", "num_neighbors", "num_obstacles", "reward",
             "collision_tolerance", "max_steps", "clip_actions", "differentiable", "backup_check", "compiled")
FLOAT32_REACH: float = 1e3
"""Largest coordinate [m] of a layout in float32: float32 positions there are 0.06 mm apart, well inside the 1 mm
that the float32 guarantee allows (at 1e5 m they are 8 mm apart); farther layouts need float64."""


def _slots(k: int, ok: torch.Tensor, rel_p: torch.Tensor, rel_v: torch.Tensor, gap: torch.Tensor) -> torch.Tensor:
    """``k`` observation slots ``(B, N, k SLOT_DIM)``: ``(rel_p, rel_v, gap, 1)`` where ``ok (B, N, kk)``, else 0."""
    B, N, kk = gap.shape
    part = torch.cat((rel_p, rel_v, gap[..., None], torch.ones_like(gap)[..., None]), -1)
    part = torch.where(ok[..., None], part, 0.0)
    return torch.cat((part, part.new_zeros(B, N, k - kk, SLOT_DIM)), 2).reshape(B, N, -1)


def _compiled(value: bool | None, device: str, differentiable: bool, backup_check: str) -> bool:
    """Whether the env runs :mod:`.compiled`'s stages (``make_tensor_env``'s ``compiled``), or ConfigError why not."""
    why = ("the device is not a CPU" if torch.device(device).type != "cpu" else
           "differentiable=True needs the torch stages' gradient" if differentiable else
           "backup_check='torch' is the torch stages' check" if backup_check == "torch" else
           NUMBA_MISSING if not numba_available() else None)
    if value is None:
        return why is None
    if check.boolean("compiled", value) and why is not None:
        raise ConfigError(f"compiled: got True, but {why}")
    return bool(value)


def make_tensor_env(scenario: str | Scenario = "random_goals", num_envs: int = 1, num_robots: int | None = None,
                    device: str = "cpu", dtype: torch.dtype = torch.float32,
                    filter: FilterConfig | Mapping[str, Any] | bool = True, mode: str | None = None,
                    **options: Any) -> TensorEnv:
    """``num_envs`` teams of ``num_robots`` robots (None: the scenario's number) of ``scenario`` on ``device``.

    ``filter``: True (the defaults), False (bare), a :class:`FilterConfig` or a mapping of its fields (as
    :func:`~aasoatt_env.api.factory.make_env`'s) at the env's ``dt``, decentralised (``mode``:
    :func:`.torch_config`).  ``options``: the env's settings
    (``dt``, ``decision_interval``, ``action_mode``, ``sensing_range`` of the observations, ``num_neighbors``,
    ``num_obstacles``, ``reward``, ``collision_tolerance``, ``max_steps``, ``clip_actions``, ``differentiable``:
    ``step`` records the autograd graph, so losses on its outputs reach the actions and the state through the filter
    and the dynamics; default False: no graph), ``backup_check`` (:data:`~.filter.BACKUP_CHECKS`; None: the numpy
    backup layer on a CPU, the torch check on other devices), ``compiled`` (the numpy env's compiled stages and the
    numpy filter on the tensors' memory, :mod:`.compiled`; None: where the device is a CPU, ``differentiable`` is
    False, the backup check is numpy's and numba imports), other :class:`FilterConfig` fields (the filter's
    ``sensing_range`` only through ``filter``), and the scenario's parameters.
    """
    names = {f.name for f in fields(FilterConfig)}
    env_kw = {k: options.pop(k) for k in list(options) if k in _ENV_KEYS}
    filt_kw = {k: options.pop(k) for k in list(options) if k in names}
    cfg = None
    if filter is not False:
        if isinstance(filter, Mapping) and "dt" in filter:
            raise ConfigError(f"dt: got {filter['dt']!r} in filter; the filter runs at the env's physics step (dt=)")
        cfg = torch_config(filter, mode, dt=env_kw.get("dt", DT), **filt_kw)
    if num_robots is not None:
        options["num_robots"] = num_robots
    return TensorEnv(get_scenario(scenario, **options), num_envs, device, dtype, cfg, **env_kw)


class TensorEnv:
    """Teams of one scenario as tensors (module docstring); ``step`` and ``reset`` as a vector env's."""

    def __init__(self, scenario: Scenario, num_envs: int, device: str, dtype: torch.dtype,
                 config: FilterConfig | None, dt: float = DT, decision_interval: int = 1, action_mode: str = "wheel",
                 sensing_range: float = 3.0, num_neighbors: int = 4, num_obstacles: int = 2, reward: Any = None,
                 collision_tolerance: float = 1e-3, max_steps: int | None = None, clip_actions: bool = False,
                 differentiable: bool = False, backup_check: str | None = None, compiled: bool | None = None) -> None:
        num_envs = check.integer("num_envs", num_envs, lo=1)
        check_dtype_device(dtype, device)
        vars(self).update(env_settings(dt, decision_interval, action_mode, sensing_range, num_neighbors, num_obstacles,
                                       reward, collision_tolerance, max_steps, clip_actions))
        if config is not None and abs(config.dt - self.dt) > 1e-12 * self.dt:
            raise ConfigError(f"dt: the env steps {self.dt:g} s but the filter was configured for {config.dt:g} s")
        self.scenario, self.num_envs, self.device, self.dtype, self.config = scenario, num_envs, device, dtype, config
        self.differentiable = check.boolean("differentiable", differentiable)
        self.backup_check = backup_check_of(backup_check, torch.device(device))  #: the backup stage's implementation
        self.compiled = _compiled(compiled, device, self.differentiable, self.backup_check)  #: :mod:`.compiled` stages
        self._cpu: CompiledStages | None = None
        self.num_robots = scenario.num_robots
        self.obs_dim = SELF_DIM + SLOT_DIM * (self.num_neighbors + self.num_obstacles)
        self._rngs: list[np.random.Generator] = []
        self._dist: torch.Tensor | None = None
        self.team: TensorTeam | None = None
        self.autoreset = True  #: reset finished teams within ``step`` (False: :meth:`reset_done` does)

    # ------------------------------------------------------------------ episodes
    def _t(self, a: Any, dtype: torch.dtype | None = None) -> torch.Tensor:
        return torch.as_tensor(np.asarray(a), device=self.device).to(dtype or self.dtype)

    def _layouts(self, teams: list[int]) -> dict[str, torch.Tensor]:
        """New layouts of ``teams`` from their generators, as tensors."""
        lays = [self.scenario.build(self._rngs[b]) for b in teams]
        for lay in lays:
            if type(lay.reference) is not LinearReference:
                raise ConfigError(f"scenario: {self.scenario.name!r} has a {type(lay.reference).__name__}, expected "
                                  "a LinearReference (the torch env's references are straight lines)")
            check_starts(self.scenario, lay)
            reach = max(np.abs(a).max(initial=0.0) for a in (lay.starts, lay.reference.goals, lay.obstacle_centers))
            if self.dtype == torch.float32 and reach > FLOAT32_REACH:
                raise ConfigError(f"dtype: got torch.float32 for a layout reaching {reach:.6g} m from the origin, "
                                  f"expected coordinates within {FLOAT32_REACH:g} m in float32 (its positions there "
                                  "are too coarse for the safety margin): use torch.float64 or centre the layout")
        if self.team is None:
            self.team = TensorTeam.from_team(lays[0].team, self.dtype, self.device)
            self._profile = lays[0].reference.profile
            if self.compiled:
                self._cpu = CompiledStages(lays[0].team, self.num_envs, self.config, self.dtype)
        steps = [self._max_steps_override or max(1, int(math.ceil(lay.horizon / (self.dt * self.decision_interval)
                                                                  - 1e-9))) for lay in lays]
        return dict(
            pose=self._t(np.stack([dynamics.pose_from_point(lay.team, lay.starts, lay.headings) for lay in lays])),
            starts=self._t(np.stack([lay.reference.starts for lay in lays])),
            goals=self._t(np.stack([lay.reference.goals for lay in lays])),
            durations=self._t(np.stack([lay.reference.durations for lay in lays]), torch.float64),
            oc=self._t(np.stack([lay.obstacle_centers.reshape(-1, 2) for lay in lays])),
            orad=self._t(np.stack([lay.obstacle_radii for lay in lays])),
            max_steps=torch.tensor(steps, device=self.device))

    def reset(self, seed: int | None = None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Start every team's episode; team ``b``'s layout is that of ``seed + b`` (observations ``(B, N, obs)``).

        Without a seed each team's generator goes on (a first reset without one: fresh entropy).
        """
        seed = None if seed is None else check.integer("seed", seed, lo=0)
        if seed is not None or not self._rngs:  # (no seed: each team's generator goes on, as the PettingZoo env's)
            self._rngs = [np.random.default_rng(None if seed is None else seed + b) for b in range(self.num_envs)]
        self.team = None
        self._st = self._layouts(list(range(self.num_envs)))
        B, N = self.num_envs, self.num_robots
        self.pose, self.u = self._st["pose"], torch.zeros(B, N, 2, dtype=self.dtype, device=self.device)
        self.time = torch.zeros(B, dtype=torch.float64, device=self.device)
        self.steps = torch.zeros(B, dtype=torch.long, device=self.device)
        self._avoiding = torch.zeros(B, N, dtype=torch.bool, device=self.device)
        self._refresh()
        return self._observations(), self._infos(None)

    def reset_done(self, done: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Start a new episode of the teams ``done`` ``(B,)`` bool (each from its own generator); all observations."""
        self._require_reset("reset_done()")
        try:
            mask = torch.as_tensor(done, device=self.device)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise ConfigError(f"done: got {check.short_repr(done)}, expected bool of shape ({self.num_envs},)") from exc
        if mask.dtype != torch.bool or tuple(mask.shape) != (self.num_envs,):
            raise ConfigError(f"done: got a {mask.dtype} tensor of shape {tuple(mask.shape)}, expected bool of shape "
                              f"({self.num_envs},) (one flag per team; a (B, N) truncated: truncated[:, 0])")
        self._reset_teams(mask)
        self._refresh()
        return self._observations(), self._infos(None)

    def _reset_teams(self, done: torch.Tensor) -> None:
        """Reset the teams ``done`` ``(B,)`` (same-step autoreset)."""
        teams = torch.nonzero(done).flatten().tolist()
        if not teams:
            return
        new = self._layouts(teams)
        idx = torch.tensor(teams, device=self.device)
        for k, v in new.items():
            self._st[k] = self._st[k].index_copy(0, idx, v)
        self.pose = self.pose.index_copy(0, idx, new["pose"])
        self.u = self.u.index_fill(0, idx, 0.0)
        self.time = self.time.index_fill(0, idx, 0.0)
        self.steps = self.steps.index_fill(0, idx, 0)
        self._avoiding = self._avoiding.index_fill(0, idx, False)
        if self._cpu is not None:
            self._cpu.restart(np.asarray(teams))

    # ------------------------------------------------------------------ step
    @property
    def goals(self) -> torch.Tensor:
        """``(B, N, 2)`` every robot's goal in its team's current episode."""
        return self._st["goals"]

    def reference(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(p_d, v_d, a_d)`` ``(B, N, 2)`` of every team at its own time (``LinearReference``)."""
        st = self._st
        T = st["durations"]
        t = self.time[:, None]
        done = (t >= T)[..., None]
        tau = (torch.clamp(t, min=0.0) / T)[..., None].to(self.dtype)
        delta = st["goals"] - st["starts"]
        Tt = T.to(self.dtype)[..., None]
        zero = torch.zeros_like(delta)
        if self._profile == "linear":
            p, v, a = st["starts"] + tau * delta, delta / Tt, zero
        else:  # the quintic s(tau) and its derivatives
            p = st["starts"] + tau ** 3 * (10.0 - 15.0 * tau + 6.0 * tau * tau) * delta
            v = 30.0 * tau * tau * (1.0 - tau) ** 2 / Tt * delta
            a = 60.0 * tau * (1.0 - tau) * (1.0 - 2.0 * tau) / (Tt * Tt) * delta
        return torch.where(done, st["goals"], p), torch.where(done, zero, v), torch.where(done, zero, a)

    def step(self, actions: torch.Tensor) -> tuple:
        """Hold ``actions`` ``(B, N, 2)`` for ``decision_interval`` physics steps; auto-reset finished teams.

        Returns ``observations (B, N, obs_dim)``, ``rewards``, ``terminated``, ``truncated`` ``(B, N)`` and infos
        (tensors: ``correction``, ``intervened``, ``backup``, ``status``, ``clearance``, ``tracking_error``, and
        ``reset`` ``(B,)``: the team started a new episode in this step); over the decision's physics steps
        ``clearance`` is the least, ``correction`` the largest, ``intervened`` and ``status`` any, as numpy's.
        """
        with torch.set_grad_enabled(self.differentiable and torch.is_grad_enabled()):
            return self._step(actions)

    def _require_reset(self, what: str) -> None:
        if self.team is None:
            raise ResetNeeded(f"{what}: call reset() first")

    def _actions(self, actions: Any) -> torch.Tensor:
        """``actions`` ``(B, N, 2)`` in the env's dtype, checked as the PettingZoo env checks them.

        Behind the filter a nominal of at most ``1e6``, else within ``[-1, 1]`` (``clip_actions``: any finite value,
        clipped).
        """
        B, N = self.num_envs, self.num_robots
        try:
            act = torch.as_tensor(actions, device=self.device)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise ActionError(f"actions: got {check.short_repr(actions)}, expected real numbers of shape ({B}, {N}, 2)"
                              ) from exc
        if act.dtype == torch.bool or act.is_complex() or tuple(act.shape) != (B, N, 2):
            raise ActionError(f"actions: got shape {tuple(act.shape)} (dtype {act.dtype}), expected real numbers of "
                              f"shape ({B}, {N}, 2)")
        nominal = self.config is not None and not self.clip_actions
        peak = act.detach().abs().amax()
        if not bool(peak <= action_bound(nominal, self.clip_actions)):  # (NaN too): the PettingZoo env's error
            checked_actions(act.detach().cpu().double().numpy().reshape(B * N, 2), nominal, self.clip_actions,
                            lambda row: f"actions[{row // N}, {row % N}]")
        act = act.to(self.dtype)
        return act if nominal else torch.clamp(act, -1.0, 1.0)

    def _step(self, actions: torch.Tensor) -> tuple:
        self._require_reset("step()")
        done = torch.nonzero(self.steps >= self._st["max_steps"]).flatten() if not self.autoreset else ()
        if len(done):  # (as the numpy batched env's)
            raise ResetNeeded(f"step(): team(s) {done.tolist()} finished their episode (autoreset=False); call "
                              "reset_done() or reset() first")
        act = self._actions(actions)
        B, N = self.num_envs, self.num_robots
        team, out, low = self.team, None, None
        for _ in range(self.decision_interval):  # (clearance: the least; intervened, status: any, as numpy's)
            du = self._nominal(act)  # (the filter's answer replaces it)
            lo, hi = input_bounds(team, self.u, self.dt)
            if self.config is not None:
                p_d, v_d, _ = self.ref
                oc, orad = self._st["oc"], self._st["orad"]
                last, out = out, (filter_step(team, self.config, self.pose, self.u, du, p_d, v_d, (oc, orad),
                                              self._avoiding, self.backup_check) if self._cpu is None else
                                  self._cpu.step_filter(du, lo, hi, p_d, v_d, oc, orad))
                self._avoiding, du = out.avoiding, out.du
                if last is not None:
                    out = out._replace(correction=torch.maximum(last.correction, out.correction),
                                       intervened=last.intervened | out.intervened, status=last.status | out.status)
            du = torch.minimum(torch.maximum(du, lo), hi)
            self.pose, self.u = (integrate(team, self.pose, self.u, du, self.dt) if self._cpu is None else
                                 self._cpu.integrate(du, self.dt))
            self.time = self.time + self.dt
            self._refresh()
            low = self.clearance if low is None else torch.minimum(low, self.clearance)
        self.steps = self.steps + 1
        self.clearance = low
        rew = self._rewards(act, None if out is None else out.correction)
        truncated = (self.steps >= self._st["max_steps"])
        infos = self._infos(out)
        infos["reset"] = truncated if self.autoreset else torch.zeros_like(truncated)
        if self.autoreset and bool(truncated.any()):
            self._reset_teams(truncated)
            self._refresh()
        return (self._observations(), rew, torch.zeros(B, N, dtype=torch.bool, device=self.device),
                truncated[:, None].expand(B, N), infos)

    def _nominal(self, act: torch.Tensor) -> torch.Tensor:
        """Nominal wheel accelerations ``(B, N, 2)`` of actions in units of the bound (module docstring)."""
        team = self.team
        if self.action_mode == "wheel":
            return act * team.max_wheel_accel[:, None]
        k = kinematics(team, self.pose, self.u)
        det = k.a00 * k.a11 - k.a01 * k.a10
        return matvec(k.a11, -k.a01, -k.a10, k.a00, act * team.max_point_accel[:, None] - k.adot) / det[..., None]

    # ------------------------------------------------------------------ what the agents see
    @property
    def dist(self) -> torch.Tensor:
        """``(B, N, N)`` centre distances of each team's control points now (inf to itself)."""
        if self._dist is None:
            p = self.kin.p
            eye = torch.eye(p.shape[1], dtype=torch.bool, device=p.device)
            self._dist = row_norm(p[:, :, None, :] - p[:, None, :, :]).masked_fill(eye, math.inf)
        return self._dist

    def _refresh(self) -> None:
        """Kinematics, reference, distances and clearance now."""
        self.ref, self._dist = self.reference(), None
        if self._cpu is not None:
            self.kin = self._cpu.kinematics(self.pose, self.u)
            self.clearance = self._cpu.clearance(self._st["oc"], self._st["orad"], max(self.num_neighbors, 1))
            self.tracking_error = row_norm(self.kin.p - self.ref[0])
            return
        self.kin = kinematics(self.team, self.pose, self.u)
        p, N = self.kin.p, self.num_robots
        r = self.team.radius
        clear = (self.dist - r[:, None] - r[None, :]).amin(-1) if N > 1 else torch.full_like(p[..., 0], math.inf)
        oc, orad = self._st["oc"], self._st["orad"]
        self._ogap = row_norm(p[:, :, None, :] - oc[:, None, :, :]) - r[None, :, None] - orad[:, None, :]
        self.clearance = torch.minimum(clear, self._ogap.amin(-1)) if orad.shape[-1] else clear
        self.tracking_error = row_norm(p - self.ref[0])

    def _rewards(self, act: torch.Tensor, corr: torch.Tensor | None) -> torch.Tensor:
        """:func:`aasoatt_env.sim.rewards.rewards`, per robot ``(B, N)``."""
        c = self.reward_config
        collided = (self.clearance < -self.collision_tolerance).to(self.dtype)
        r = -c.tracking * self.tracking_error - c.collision * collided - c.effort * 0.5 * (act * act).sum(-1)
        if c.goal_bonus:
            r = r + c.goal_bonus * (row_norm(self.kin.p - self._st["goals"]) < c.goal_tolerance).to(self.dtype)
        if c.correction and corr is not None:
            r = r - c.correction * corr / self.team.max_wheel_accel
        return r

    def _observations(self) -> torch.Tensor:
        """:func:`aasoatt_env.sim.observations.build_observations` for every team ``(B, N, obs_dim)`` float32."""
        kin, (p_d, v_d, a_d), th = self.kin, self.ref, self.pose[..., 2]
        if self._cpu is not None:
            return self._cpu.observations(self.ref, self._st["goals"], self._st["oc"], self._st["orad"],
                                          self.sensing_range, self.num_neighbors, self.num_obstacles)
        p, v = kin.p, kin.v
        B, N, _ = p.shape
        parts = [p - p_d, self._st["goals"] - p, v, torch.stack((torch.cos(th), torch.sin(th)), -1), self.u, v_d, a_d]
        r = self.team.radius.expand(B, N)
        if self.num_neighbors:  # (exact ties may be ordered otherwise)
            dist, idx = self.dist.topk(min(self.num_neighbors, N - 1), dim=-1, largest=False)
            gap = (-pick(r, idx) - r[..., None]) + dist
            parts.append(_slots(self.num_neighbors, dist <= self.sensing_range, pick(p, idx) - p[:, :, None],
                                pick(v, idx) - v[:, :, None], gap))
        if self.num_obstacles:
            order = torch.sort(self._ogap, dim=-1, stable=True)
            kk = min(self.num_obstacles, self._ogap.shape[-1])
            idx, g = order.indices[..., :kk], order.values[..., :kk]
            ok = g + r[..., None] + pick(self._st["orad"], idx) <= self.sensing_range
            parts.append(_slots(self.num_obstacles, ok, pick(self._st["oc"], idx) - p[:, :, None],
                                (-v)[:, :, None].expand(B, N, kk, 2), g))
        return torch.clamp(torch.cat(parts, -1).to(torch.float32), -OBS_BOUND, OBS_BOUND)

    def _infos(self, out: FilterOut | None) -> dict[str, torch.Tensor]:
        none = torch.zeros(self.num_envs, self.num_robots, dtype=torch.long, device=self.device)  # (no filter step)
        status = none if out is None else out.status
        return {"clearance": self.clearance, "tracking_error": self.tracking_error,
                "correction": none.to(self.dtype) if out is None else out.correction,
                "intervened": none.bool() if out is None else out.intervened, "status": status,
                "backup": (status & BACKUP) > 0}
