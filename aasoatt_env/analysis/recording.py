"""Record episodes of a (possibly filtered) parallel env into :class:`~aasoatt_env.analysis.rollout.Rollout`.

:class:`RecordEpisode` is a PettingZoo parallel wrapper that records, after
``reset`` and after every ``step``, the team's positions, velocities, headings,
reference, the actions given, and, behind a control filter, what the env's
public ``filter_outputs`` say: the applied actions and avoidance flags, plus,
for the :class:`~aasoatt_env.safety.core.SafetyFilter`, deadlock triggers,
solver status, slack and solve time.
:func:`run_episode` drives an agent through one episode and returns the
rollout (and optional rendered frames).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pettingzoo.utils.wrappers import BaseParallelWrapper

from aasoatt_env.analysis.rollout import Rollout, RolloutBuilder
from aasoatt_env.errors import UsageError
from aasoatt_env.safety.core import SafetyFilter
from aasoatt_env.safety.wrapper import FilterReport

__all__ = ["RecordEpisode", "run_episode"]


class RecordEpisode(BaseParallelWrapper):
    """Record every env step of the wrapped parallel env.

    Parameters
    ----------
    env : ParallelEnv
        An :class:`~aasoatt_env.sim.env.AASOATTParallelEnv`, possibly wrapped.
    metadata : dict, optional
        JSON-serialisable metadata stored in the rollout.
    """

    def __init__(self, env: Any, metadata: dict[str, Any] | None = None) -> None:
        super().__init__(env)
        self._meta = dict(metadata or {})
        self._builder: RolloutBuilder | None = None

    def _record(self, actions: np.ndarray | None, infos: dict[str, dict]) -> None:
        base = self.env.unwrapped
        if self._builder is None:
            raise UsageError("RecordEpisode: call reset() first")
        p_d, v_d, _ = base.reference
        n = len(base.possible_agents)
        extra = _filter_fields(base, n)
        self._builder.append(
            time=base.time,
            positions=base.positions,
            velocities=base.velocities,
            headings=base.headings,
            references=p_d,
            reference_velocities=v_d,
            nominal_actions=actions if actions is not None else np.zeros((n, 2)),
            **extra,
        )

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """Reset and start a new recording."""
        obs, infos = self.env.reset(seed=seed, options=options)
        base = self.env.unwrapped
        c, r = base.obstacles
        meta = {"scenario": base.scenario.name, "dt": base.dt, "decision_interval": base.decision_interval}
        meta.update(self._meta)
        self._builder = RolloutBuilder(
            dt=base.dt * base.decision_interval,
            goals=base.goals,
            radii=base.radii,
            obstacle_centers=c,
            obstacle_radii=r,
            metadata=meta,
        )
        self._record(None, infos)
        return obs, infos

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """Step and record."""
        base = self.env.unwrapped
        act = np.zeros((len(base.possible_agents), 2))
        idx = base.agent_index
        for a, v in actions.items():
            if a in idx:
                act[idx[a]] = v
        out = self.env.step(actions)
        self._record(act, out[4])
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
    outputs = base.filter_outputs
    amax = base.team.max_wheel_accel[:, None]
    if isinstance(f, SafetyFilter):
        if outputs:
            rep = FilterReport.of(outputs)
            return {"avoiding": rep.avoiding, "triggered": rep.triggered, "backup": rep.backup,
                    "solver_status": rep.status, "slack": rep.slack, "solve_time": rep.solve_time,
                    "actions": rep.applied / amax}
        return {"avoiding": np.zeros(n, dtype=bool), "triggered": np.zeros(n, dtype=bool),
                "backup": np.zeros(n, dtype=bool), "solver_status": "solved", "slack": 0.0, "solve_time": 0.0,
                "actions": np.zeros((n, 2))}
    if outputs:  # any other control filter: what the protocol guarantees
        return {"avoiding": np.any([o.avoiding for o in outputs], axis=0), "actions": np.asarray(outputs[-1].du) / amax}
    return {"avoiding": np.zeros(n, dtype=bool), "actions": np.zeros((n, 2))}


def run_episode(
    env: Any,
    agent: Any,
    seed: int | None = None,
    *,
    render_every: int | None = None,
    progress: bool = False,
    metadata: dict[str, Any] | None = None,
) -> tuple[Rollout, list[np.ndarray]]:
    """Run ``agent`` on ``env`` for one episode and return ``(rollout, frames)``.

    Parameters
    ----------
    env : ParallelEnv
        The (possibly filtered) parallel env; ``render_mode="rgb_array"`` is
        needed for frames.
    agent : Agent
        Anything with ``reset(env)`` and ``act(observations, env)``.
    seed : int, optional
        Reset seed.
    render_every : int, optional
        Keep a rendered frame every this many env steps.
    progress : bool
        Show a tqdm progress bar (if tqdm is installed).
    metadata : dict, optional
        Stored in the rollout.
    """
    rec = RecordEpisode(env, metadata)
    obs, _ = rec.reset(seed=seed)
    agent.reset(rec)
    frames: list[np.ndarray] = []
    base = env.unwrapped
    bar = None
    if progress:
        try:
            from tqdm import tqdm

            bar = tqdm(total=base.max_steps, unit="step", desc=base.scenario.name)
        except ImportError:  # pragma: no cover - tqdm is in the render/train extras
            bar = None
    step = 0
    while rec.agents:
        if render_every and step % render_every == 0:
            frames.append(rec.render())
        obs, *_ = rec.step(agent.act(obs, rec))
        step += 1
        if bar is not None:
            bar.update(1)
    if render_every:
        frames.append(rec.render())
    if bar is not None:
        bar.close()
    return rec.rollout, frames
