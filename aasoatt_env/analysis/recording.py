"""Record episodes of a (possibly filtered) parallel env into :class:`~aasoatt_env.analysis.rollout.Rollout`.

:class:`RecordEpisode` is a PettingZoo parallel wrapper that records, after
``reset`` and after every ``step``, the team's positions, velocities, headings,
reference, the actions given, and, behind
:class:`~aasoatt_env.safety.wrapper.AASOATTFilter`, the filter's avoidance
flags, deadlock triggers, solver status, slack and solve time.
:func:`run_episode` drives an agent through one episode and returns the
rollout (and optional rendered frames).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pettingzoo.utils.wrappers import BaseParallelWrapper

from aasoatt_env.analysis.rollout import Rollout, RolloutBuilder

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
        self._has_filter = False

    def _record(self, actions: np.ndarray | None, infos: dict[str, dict]) -> None:
        base = self.env.unwrapped
        assert self._builder is not None
        p_d, v_d, _ = base.reference
        n = len(base.possible_agents)
        extra: dict[str, Any] = {}
        filt = getattr(base, "_control_filter", None)
        if filt is not None and hasattr(filt, "record"):
            extra.update(filt.record())
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
        for a, v in actions.items():
            act[base.possible_agents.index(a)] = v
        out = self.env.step(actions)
        self._record(act, out[4])
        return out

    @property
    def rollout(self) -> Rollout:
        """The episode recorded so far."""
        if self._builder is None:
            raise RuntimeError("RecordEpisode.rollout: nothing recorded yet, call reset() first")
        return self._builder.build()


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

            bar = tqdm(total=base._max_steps, unit="step", desc=base.scenario.name)
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
