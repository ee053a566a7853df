"""``aasoatt train --resume RUN``: continue a Stable-Baselines3 run where it stopped.

The run to continue is a finished run folder (its ``model.zip``), an interrupted one (its latest
checkpoint) or a checkpoint given directly.  What continues:

* the policy weights and the Adam optimiser's state (:func:`agents.sb3_model.read_optimizer_state`),
  read by fixed names and shapes like every model file;
* the step counter (``num_timesteps``) and the update counter: ``total_timesteps`` is the total of
  the whole run, so an interrupted run resumed with its own config ends where it would have;
* the running statistics of observation and reward normalisation (``normalization.npz``);
* the learning curve: the new run folder's ``metrics.csv`` and ``eval.csv`` start with the earlier
  rows up to the resumed step, so the curve is one continuous line.

The training envs are reset with seeds derived from the run's seed and the resumed step (new
episodes, still below the held-out seeds).  The settings the policy depends on must be those of
the run (:func:`train.build.check_init_from`); the run's ``config.json`` is the base of the new
configuration (:func:`train.options.config_from_args`), so ``--resume RUN`` alone continues it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from aasoatt_env.errors import ConfigError, DataFileError
from agents.learned import stats_path
from train.config import LIMITS, TrainConfig

__all__ = ["Resumed", "find_resume_model", "load_resumed", "resume_into"]

_CHECKPOINT = re.compile(r"ppo_(\d+)_steps\.zip")


@dataclass
class Resumed:
    """What a resumed run continues from (:func:`load_resumed`)."""

    model_zip: Path
    agent: Any
    steps: int
    metrics: list[dict[str, float]] = field(default_factory=list)
    evals: list[dict[str, float]] = field(default_factory=list)


def find_resume_model(path: str) -> Path:
    """The model zip to resume from: ``path`` itself, a finished run's ``model.zip``, or its latest checkpoint."""
    p = Path(path)
    if p.is_file():
        return p
    if not p.is_dir():
        raise ConfigError(f"TrainConfig.resume: got {path!r}, expected a run folder or checkpoint (no such path)")
    if (p / "model.zip").is_file() and (p / "train_stats.json").is_file():
        return p / "model.zip"
    found = sorted(((int(m.group(1)), c) for c in (p / "checkpoints").glob("ppo_*_steps.zip")
                    if (m := _CHECKPOINT.fullmatch(c.name))), key=lambda t: t[0])
    if found:
        return found[-1][1]
    if (p / "model.zip").is_file():
        return p / "model.zip"
    raise ConfigError(f"TrainConfig.resume: {path!r} holds no model.zip and no checkpoints/ppo_<n>_steps.zip; "
                      "expected a run folder of aasoatt train")


def _earlier_rows(run: Path, name: str, steps: int) -> list[dict[str, float]]:
    """The rows of ``run/name`` up to ``steps`` (none if the table is missing)."""
    from train.telemetry import read_metrics

    table = run / name
    if not table.is_file():
        return []
    return [r for r in read_metrics(table) if r.get("agent_steps", np.inf) <= steps]


def load_resumed(config: TrainConfig, obs_shape: tuple[int, ...]) -> Resumed:
    """Load and check the run ``config.resume`` (before a run folder is made).

    Raises
    ------
    ConfigError
        The run's policy does not fit ``config``, or it has already reached ``total_timesteps``.
    DataFileError
        A file of it is missing or not what training writes.
    """
    from agents.learned import LearnedAgent
    from train.build import check_init_from

    model_zip = find_resume_model(config.resume)  # type: ignore[arg-type]
    agent = LearnedAgent.load(model_zip)
    check_init_from(config, agent, obs_shape, field="resume")
    steps = agent.model.num_timesteps
    if steps >= config.total_timesteps:
        raise ConfigError(f"TrainConfig.total_timesteps: got {config.total_timesteps:,}, but {model_zip} has already "
                          f"trained {steps:,} agent-steps; expected a larger total to continue to")
    if config.normalize_reward and not stats_path(model_zip).is_file():
        raise DataFileError(f"{stats_path(model_zip)}: missing; the run normalised its rewards")
    run = model_zip.parent.parent if model_zip.parent.name == "checkpoints" else model_zip.parent
    return Resumed(model_zip, agent, steps, _earlier_rows(run, "metrics.csv", steps),
                   _earlier_rows(run, "eval.csv", steps))


def resume_into(model: Any, venv: Any, config: TrainConfig, resumed: Resumed) -> None:
    """Continue ``resumed`` in the freshly built ``model`` and ``venv``: weights, optimiser, counters, statistics."""
    import torch

    from agents.sb3_model import read_optimizer_state
    from train.build import load_stats

    optimizer_state = read_optimizer_state(resumed.model_zip, model.policy.optimizer)
    with torch.no_grad():
        model.policy.load_state_dict(resumed.agent.model.policy.state_dict())
    model.policy.optimizer.load_state_dict(optimizer_state)
    model.num_timesteps = resumed.steps
    model._n_updates = resumed.agent.model.n_updates
    if config.normalize_obs or config.normalize_reward:
        load_stats(venv, stats_path(resumed.model_zip))
    venv.seed((config.seed + resumed.steps) % (LIMITS["seed"] + 1))  # new episodes, below the held-out seeds
