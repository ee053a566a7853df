"""``aasoatt train --seeds 0 1 2``: one run per training seed, then the mean and spread of their results.

A result from one seed says little about a recipe: PPO runs of the same settings differ.  The
runs go into one new folder ``<out_dir>/<name>/`` (``s0/``, ``s1/``, ...), trained one after the
other with the same configuration but the seed; the summary is of each run's final held-out
evaluation (:mod:`train.heldout`): for success, the share of episodes with a collision, the
tracking RMSE and the safe rate, the mean, the sample standard deviation and the lowest and
highest over seeds (``seeds.json``, ``seeds.md``), and the learning curves of all seeds in one
figure (mean and band, ``learning_curve.png``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from aasoatt_env.errors import ConfigError
from train.config import INCOMPLETE_FILE, LIMITS, TrainConfig, abandon_run, claim_run_dir
from train.intervals import spread
from train.runs import write_json, write_text

__all__ = ["SUMMARY_KEYS", "summarize_seeds", "train_seeds"]

SUMMARY_KEYS = ("success_rate", "collision_episode_rate", "rmse", "safe_rate")
"""Held-out metrics summarised over seeds."""


def _check_seeds(config: TrainConfig, seeds: Sequence[Any], flag: str) -> list[int]:
    ok = isinstance(seeds, (list, tuple)) and 1 <= len(seeds) <= 100 and all(
        isinstance(s, int) and not isinstance(s, bool) and 0 <= s <= LIMITS["seed"] for s in seeds)
    if not ok:
        raise ConfigError(f"{flag}: got {str(seeds)[:80]}, expected 1 to 100 integers in [0, {LIMITS['seed']}]")
    dup = sorted({s for s in seeds if list(seeds).count(s) > 1})
    if dup:
        raise ConfigError(f"{flag}: got {dup} more than once, expected each seed at most once")
    if config.resume is not None:
        raise ConfigError(f"{flag}: got seeds with --resume, expected one of them (resume one run at a time)")
    if not 0 < config.eval_every <= config.total_timesteps:
        raise ConfigError(f"{flag}: needs held-out evaluations to summarise, expected eval_every in [1, "
                          f"total_timesteps = {config.total_timesteps:,}] (got {config.eval_every:,})")
    return list(seeds)


def train_seeds(config: TrainConfig, seeds: Sequence[int], flag: str = "seeds",
                dry_run: bool = False) -> list[TrainConfig]:
    """Train ``config`` once per seed into a new group folder and summarise (module docstring).

    With ``dry_run`` only the per-seed configurations are built and checked (nothing is made).
    Returns the configurations trained.
    """
    from train.train import run_name, train

    seeds = _check_seeds(config, seeds, flag)
    name = config.run_name or run_name(dataclasses.replace(config, run_name=None)).rsplit("_s", 1)[0] + "_seeds"
    configs = [dataclasses.replace(config, seed=s, run_name=f"s{s}") for s in seeds]
    if dry_run:
        return configs
    group, created = claim_run_dir(config.out_dir, name)
    runs: list[Path] = []
    try:
        for cfg in configs:
            runs.append(train(dataclasses.replace(cfg, out_dir=str(group))).parent)
        summarize_seeds(group, runs, seeds)
    except BaseException:
        abandon_run(group, keep=bool(runs), created=created)
        raise
    (group / INCOMPLETE_FILE).unlink()
    return configs


def summarize_seeds(group: Path, runs: Sequence[Path], seeds: Sequence[int]) -> dict[str, Any]:
    """Mean and spread of the runs' final held-out evaluations; ``seeds.json``, ``seeds.md``, the curves."""
    from train.telemetry import plot_learning_curve, read_metrics

    evals = [read_metrics(run / "eval.csv") if (run / "eval.csv").is_file() else [] for run in runs]
    finals = [rows[-1] if rows else {} for rows in evals]
    summary = {key: spread([f.get(key, math.nan) for f in finals]) for key in SUMMARY_KEYS}
    data = {"seeds": list(seeds), "runs": [r.name for r in runs], "final_heldout": finals, "summary": summary}
    write_json(group / "seeds.json", data)
    lines = [f"### {group.name}: {len(runs)} seeds ({', '.join(map(str, seeds))}), final held-out evaluation", "",
             "| metric | mean | std | min | max |", "|---|---:|---:|---:|---:|"]
    for key, s in summary.items():
        scale, fmt = (100.0, ".1f") if key != "rmse" else (1.0, ".3f")
        cells = " | ".join(format(scale * s[k], fmt) for k in ("mean", "std", "min", "max"))
        lines.append(f"| {key} | {cells} |")
    table = "\n".join(lines)
    write_text(group / "seeds.md", table + "\n")
    print(table, flush=True)
    try:
        plot_learning_curve({group.name: [read_metrics(r / "metrics.csv") for r in runs]},
                            group / "learning_curve.png", title=f"{group.name}: {len(runs)} seeds",
                            heldout={group.name: evals})
    except ImportError:  # matplotlib is an optional extra
        pass
    return data
