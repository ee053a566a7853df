"""Held-out evaluation during training: the learning curve of the policy itself, not of its exploration.

:class:`HeldOutEval` evaluates the current policy (deterministic actions, the current observation
statistics) every ``eval_every`` agent-steps and once more at the end of the run, on
``eval_episodes`` episodes reset with the seeds ``HELDOUT_SEED + j``.  Training resets draw from
seeds below ``2**32`` and ``HELDOUT_SEED`` is ``2**32``, so no evaluation episode is ever a
training episode.  The episodes run on the training env (bare or behind the filter, as trained)
through :func:`train.evaluate.evaluate_agent`, so the numbers mean what ``aasoatt evaluate``'s do.

Each evaluation adds a row to ``eval.csv`` (rewritten atomically): ``agent_steps``,
``success_rate`` (robots within ``goal_tolerance`` at the end) with its 95% Wilson interval
``success_rate_lo``/``_hi``, ``collision_episode_rate`` (episodes with a collision) with its
interval, ``collisions`` (pairs plus obstacle hits), ``safe_rate``, ``rmse``, ``wall_time_s``; the
same go to TensorBoard under ``eval/`` and into the progress line and ``learning_curve.png``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any, TextIO

from stable_baselines3.common.callbacks import BaseCallback

from train.config import HELDOUT_SEED, TrainConfig

__all__ = ["HeldOutEval"]


class HeldOutEval(BaseCallback):
    """Evaluate the current policy on held-out episodes during training (module docstring).

    Parameters
    ----------
    config : TrainConfig
        The run (``eval_every``, ``eval_episodes``, the env and filter).
    csv_path : path, optional
        ``eval.csv`` (None: not written).
    rows : list of dict, optional
        Rows of the run this one resumes (kept first).
    stream : file, optional
        Where the one-line summaries go (default ``sys.stdout``; None with ``config.progress_bar`` off).
    """

    def __init__(self, config: TrainConfig, csv_path: str | Path | None = None,
                 rows: list[dict[str, float]] | None = None, stream: TextIO | None = None) -> None:
        super().__init__()
        self.config = config
        self.every = int(config.eval_every)
        self.csv_path = Path(csv_path) if csv_path is not None else None
        self.rows: list[dict[str, float]] = list(rows or [])
        self.stream = stream
        self._next = 0
        self._wall0 = self.rows[-1]["wall_time_s"] if self.rows else 0.0

    def _on_training_start(self) -> None:
        self._t0 = time.perf_counter() - self._wall0
        self._next = (self.num_timesteps // self.every + 1) * self.every if self.every else 0

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        if self.every and self.num_timesteps >= self._next:
            self.evaluate()
            self._next = (self.num_timesteps // self.every + 1) * self.every

    def _on_training_end(self) -> None:
        done = self.rows and self.rows[-1]["agent_steps"] == self.num_timesteps
        if self.every and self.num_timesteps >= self.every and not done:
            self.evaluate()

    def _agent(self) -> Any:
        """The policy as it acts now: deterministic, with the current observation statistics."""
        from agents.learned import LearnedAgent
        from train.build import run_spec

        venv = self.model.get_vec_normalize_env()
        stats = None
        if venv is not None and venv.norm_obs:
            stats = (venv.obs_rms.mean.copy(), venv.obs_rms.var.copy(), float(venv.clip_obs), float(venv.epsilon))
        return LearnedAgent(self.model, run_spec(self.config), stats, deterministic=True)

    def evaluate(self) -> dict[str, float]:
        """Run the held-out episodes now; log, record and return the row."""
        from train.build import make_env
        from train.evaluate import evaluate_agent

        cfg = self.config
        tol = cfg.reward.get("goal_tolerance", 0.1)
        res = evaluate_agent("held-out", self._agent(), lambda: make_env(cfg, terminate_on_collision=False),
                             cfg.eval_episodes, HELDOUT_SEED, tol)
        row = {"agent_steps": float(self.num_timesteps), "wall_time_s": time.perf_counter() - self._t0,
               "episodes": float(res.episodes), "success_rate": res.success_rate,
               "success_rate_lo": res.success_ci[0], "success_rate_hi": res.success_ci[1],
               "collision_episode_rate": res.collision_episodes / res.episodes,
               "collision_episode_rate_lo": res.collision_episode_ci[0],
               "collision_episode_rate_hi": res.collision_episode_ci[1],
               "collisions": float(res.collisions), "safe_rate": res.safe_rate, "rmse": res.rmse}
        self.rows.append(row)
        for key in ("success_rate", "collision_episode_rate", "rmse", "safe_rate"):
            self.logger.record(f"eval/{key}", row[key])
        if self.csv_path is not None:
            from train.telemetry import write_csv

            write_csv(self.csv_path, self.rows)
        if cfg.progress_bar or self.stream is not None:
            print(f"held-out ({res.episodes} episodes) at {self.num_timesteps:,} agent-steps: success "
                  f"{100 * res.success_rate:.1f}% [{100 * res.success_ci[0]:.1f}, {100 * res.success_ci[1]:.1f}] | "
                  f"episodes with a collision {res.collision_episodes}/{res.episodes} | RMSE {res.rmse:.3f} m",
                  file=self.stream or sys.stdout, flush=True)
        return row
