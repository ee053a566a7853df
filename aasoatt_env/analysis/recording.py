"""Record a (possibly filtered) parallel env's episodes into a :class:`~aasoatt_env.analysis.rollout.Rollout`."""

from __future__ import annotations

from typing import Any

import numpy as np
from pettingzoo.utils.wrappers import BaseParallelWrapper

from aasoatt_env.analysis.rollout import Rollout, RolloutBuilder
from aasoatt_env.cli_support import progress as progress_bar
from aasoatt_env.errors import UsageError
from aasoatt_env.safety.core import SafetyFilter
from aasoatt_env.safety.wrapper import FilterReport

__all__ = ["RecordEpisode", "run_episode"]


class RecordEpisode(BaseParallelWrapper):
    """Record every step of the wrapped :class:`~aasoatt_env.sim.env.AASOATTParallelEnv` (``metadata``: stored)."""

    def __init__(self, env: Any, metadata: dict[str, Any] | None = None) -> None:
        super().__init__(env)
        self._meta = dict(metadata or {})
        self._builder: RolloutBuilder | None = None

    def _record(self, actions: np.ndarray) -> None:
        base = self.env.unwrapped
        if self._builder is None:
            raise UsageError("RecordEpisode: call reset() first")
        p_d, v_d, _ = base.reference
        self._builder.append(time=base.time, positions=base.positions, velocities=base.velocities,
                             headings=base.headings, references=p_d, reference_velocities=v_d,
                             nominal_actions=actions, **_filter_fields(base, len(actions)))

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """Reset and start a new recording."""
        obs, infos = self.env.reset(seed=seed, options=options)
        base = self.env.unwrapped
        c, r = base.obstacles
        meta = {"scenario": base.scenario.name, "dt": base.dt, "decision_interval": base.decision_interval}
        self._builder = RolloutBuilder(dt=base.dt * base.decision_interval, goals=base.goals, radii=base.radii,
                                       obstacle_centers=c, obstacle_radii=r, metadata={**meta, **self._meta})
        self._record(np.zeros((len(base.possible_agents), 2)))
        return obs, infos

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """Step and record."""
        out = self.env.step(actions)  # (checks the actions)
        base, act = self.env.unwrapped, np.zeros((len(self.env.unwrapped.possible_agents), 2))
        known = [a for a in actions if a in base.agent_index]
        act[[base.agent_index[a] for a in known]] = np.reshape([actions[a] for a in known], (-1, 2))
        self._record(act)
        return out

    @property
    def rollout(self) -> Rollout:
        """The episode recorded so far."""
        if self._builder is None:
            raise UsageError("RecordEpisode.rollout: nothing recorded yet, call reset() first")
        return self._builder.build()


def _filter_fields(base: Any, n: int) -> dict[str, Any]:
    """Rollout fields from the env's public filter outputs of the last step (zeros right after reset)."""
    f = base.control_filter
    if f is None:
        return {}
    outputs, amax, full = base.filter_outputs, base.team.max_wheel_accel[:, None], isinstance(f, SafetyFilter)
    if not outputs:
        out = {"avoiding": np.zeros(n, dtype=bool), "actions": np.zeros((n, 2))}
        if full:
            out.update(triggered=np.zeros(n, dtype=bool), backup=np.zeros(n, dtype=bool), solver_status="solved",
                       slack=0.0, solve_time=0.0)
        return out
    if full:
        rep = FilterReport.of(outputs)
        return {"avoiding": rep.avoiding, "triggered": rep.triggered, "backup": rep.backup,
                "solver_status": rep.status, "slack": rep.slack, "solve_time": rep.solve_time,
                "actions": rep.applied / amax}
    # any other control filter: what the protocol guarantees
    return {"avoiding": np.any([o.avoiding for o in outputs], axis=0), "actions": np.asarray(outputs[-1].du) / amax}


def run_episode(env: Any, agent: Any, seed: int | None = None, *, render_every: int | None = None,
                progress: bool = False, metadata: dict[str, Any] | None = None) -> tuple[Rollout, list[np.ndarray]]:
    """Run ``agent`` on ``env`` for one episode: ``(rollout, a frame every render_every steps)``."""
    rec = RecordEpisode(env, metadata)
    obs, _ = rec.reset(seed=seed)
    agent.reset(rec)
    frames: list[np.ndarray] = []
    bar = progress_bar(env.unwrapped.max_steps, env.unwrapped.scenario.name, enabled=progress)
    step = 0
    while rec.agents:
        if render_every and step % render_every == 0:
            frames.append(rec.render())
        obs, *_ = rec.step(agent.act(obs, rec))
        step += 1
        bar.update(1)
    if render_every:
        frames.append(rec.render())
    bar.close()
    return rec.rollout, frames
