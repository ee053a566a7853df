"""PPO with parameter sharing on the AA-SOATT env (bare or behind the filter).

Usage::

    aasoatt train                                  # the default recipe (train/configs/random_goals_6r.toml)
    aasoatt train --filter true --reward correction=0.5 --run-name ppo_filtered
    aasoatt train --config run.toml --total-timesteps 200000
    aasoatt train --resume runs/RUN                # continue a run (optimiser, step counter, statistics)
    aasoatt train --seeds 0 1 2                    # one run per seed, then mean and spread
    python -m train.train ...                      # the same flags

Every robot of every env is one slot of :class:`train.vec_env.BatchedVecEnv` (one shared policy);
the ``n_envs`` teams are stepped by one vectorised physics call
(:class:`~aasoatt_env.sim.batched.BatchedAASOATTEnv`).  The policy acts every ``decision_interval``
physics steps (default 20, i.e. 10 Hz against the 200 Hz physics/filter); behind
:class:`~aasoatt_env.safety.wrapper.AASOATTFilter` its action is the nominal that the CBF-QP
filters at *every* physics step in between.

The default recipe (:class:`~train.config.TrainConfig` defaults): a plain MLP policy (SB3
``MlpPolicy``, ``[64, 64]``, ``log_std_init`` -1) learned from scratch, ``VecNormalize`` on
observations and rewards, point actions, PPO with 32 envs x 6 robots, ``n_steps`` 64, minibatch
1024, 10 epochs, learning rate 3e-4, ``gamma`` 0.99, no entropy bonus, 1,228,800 agent-steps
(100 rollouts).  Short runs judge it wrongly: success rises late.

Reward (per robot and decision, :class:`~aasoatt_env.sim.rewards.RewardConfig`, recipe weights
in :data:`~train.config.TRAIN_REWARD`)::

    r_i = -tracking |p_i - p_d_i| - collision [clearance_i < -tol] - effort |a_i|^2 / 2
          - correction c_i + goal_bonus [|p_i - goal_i| < goal_tolerance]

The reference ``p_d_i(t)`` slides to the goal and rests there, so tracking it brings the robot
home; the goal bonus marks the evaluation's success radius; collision costs 1 (the env's 10
drowns the tracking signal in collisions a robot cannot avoid alone: safety is the filter's
job); the effort term breaks ties towards smooth accelerations; the correction penalty (only
behind the filter) asks the policy to propose what the filter accepts.

Telemetry: per rollout (:mod:`train.telemetry`) success, tracking error, collisions and the
filter's intervention and correction in the training rollouts; every ``eval_every`` agent-steps
the held-out evaluation (:mod:`train.heldout`), on seeds never used for training.  Both go to
TensorBoard, to ``metrics.csv`` / ``eval.csv`` and to the progress line; ``learning_curve.png``
is drawn at the end.

Outputs in the run folder ``<out_dir>/<run_name>`` (every file written atomically):
``model.zip`` (SB3 PPO, with its policy record), ``policy.json`` (what
:class:`agents.learned.LearnedAgent` needs), ``normalization.npz`` (running statistics as plain
arrays), ``config.json``, ``metrics.csv``, ``eval.csv``, ``learning_curve.png``,
``train_stats.json`` (wall time, throughput, the filter's kernel; written last: it marks a
finished run), ``checkpoints/`` and ``tb/``.  A run that fails is removed, or kept with an
``INCOMPLETE`` file where it already holds a model or checkpoint (it can then be resumed).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from aasoatt_env.cli_support import OutputPlan, Parser, add_common_options, run_guarded
from aasoatt_env.errors import ConfigError
from agents.learned import POLICY_FILE, stats_path
from train.build import (
    build_model,
    check_device,
    check_init_from,
    check_network,
    init_policy,
    make_env,
    make_vec_env,
    prior_max_accel,
    run_spec,
    save_model,
    save_stats,
)
from train.config import BACKENDS, INCOMPLETE_FILE, TrainConfig, abandon_run, claim_run_dir
from train.options import add_config_arguments, config_from_args, split_backend
from train.runs import write_json
from train.telemetry import TelemetryCallback, plot_learning_curve

__all__ = ["INCOMPLETE_FILE", "build_model", "check_device", "check_init_from", "init_policy", "main", "make_env",
           "make_vec_env", "train"]


def run_name(config: TrainConfig) -> str:
    """The run folder name: ``config.run_name`` or one from scenario, robots, filter and seed."""
    return config.run_name or (
        f"ppo_{config.scenario}_{config.num_robots}r_{'filter' if config.filter else 'bare'}_s{config.seed}")


def _run_dir(config: TrainConfig) -> tuple[Path, bool]:
    """A new run folder ``<out_dir>/<name>`` (``_2``, ``_3``, ... when taken) and whether it was created."""
    OutputPlan(overwrite=True).folder(config.out_dir, "TrainConfig.out_dir")  # creatable and writable, or say why
    try:
        return claim_run_dir(config.out_dir, run_name(config))
    except OSError as exc:
        raise ConfigError(f"TrainConfig.out_dir: cannot create a run folder in {config.out_dir} "
                          f"({exc.strerror or exc})") from None


def _checkpoint_callback(folder: Path, every: int, spec: dict[str, Any], with_stats: bool) -> Any:
    """Save ``ppo_<n>_steps.zip`` (and its ``.normalization.npz``) every ``every`` vectorised steps, atomically."""
    from stable_baselines3.common.callbacks import BaseCallback

    class Checkpoint(BaseCallback):
        def _on_step(self) -> bool:
            if self.n_calls % every == 0:
                folder.mkdir(parents=True, exist_ok=True)
                path = folder / f"ppo_{self.num_timesteps}_steps.zip"
                if with_stats:  # (the statistics first: a checkpoint zip always has its statistics)
                    save_stats(self.model.get_vec_normalize_env(), stats_path(path))
                save_model(self.model, path, spec)
            return True

    return Checkpoint()


def _preflight(config: TrainConfig) -> tuple[Any, Any]:
    """Check everything training needs before a run folder is made: ``(init_from run, resumed run)`` (or Nones).

    The device, the env and filter settings, the network's size, the tracking prior's team, and
    the run to start from or to continue (the settings its policy depends on).
    """
    check_device(config.device)
    probe = make_env(config)
    base = probe.unwrapped
    obs_shape = tuple(base.observation_space(base.possible_agents[0]).shape)
    probe.close()
    check_network(config, int(obs_shape[0]))
    if config.policy_prior == "tracking":
        prior_max_accel(config)
    if config.resume is not None:
        from train.resume import load_resumed

        return None, load_resumed(config, obs_shape)
    if config.init_from is None:
        return None, None
    from agents.learned import LearnedAgent

    source = LearnedAgent.load(config.init_from)
    check_init_from(config, source, obs_shape)
    return source, None


def _abandon(run: Path, created: bool) -> None:
    """After a failed training: remove ``run`` unless it holds a model (then it stays, marked incomplete)."""
    abandon_run(run, keep=(run / "model.zip").is_file() or any((run / "checkpoints").glob("*.zip")), created=created)


def train(config: TrainConfig) -> Path:
    """Train PPO as configured and return the path of the saved ``model.zip``.

    Everything is checked before the run folder is made (the device, the env and filter, the
    network's size, the run to start from or resume).  While training, the run folder holds an
    ``INCOMPLETE`` file, removed once every output is written.  If training fails or is
    interrupted, the run folder is removed, unless it already holds a model or checkpoint: then
    it is kept, with its ``INCOMPLETE`` file and no ``train_stats.json`` (it can be resumed).

    Raises
    ------
    ConfigError
        A setting, the device or the ``init_from``/``resume`` run does not fit (before any folder is made).
    """
    source, resumed = _preflight(config)
    run, created = _run_dir(config)
    try:
        write_json(run / "config.json", config.to_dict())
        write_json(run / POLICY_FILE, run_spec(config))
        venv = make_vec_env(config)
        try:
            model, telemetry, heldout, elapsed = _learn(config, run, venv, source, resumed)
        finally:
            venv.close()  # (stops the worker processes of num_workers > 1 on every way out)
        _finish(config, run, model, telemetry, heldout, elapsed)
    except BaseException:
        _abandon(run, created)
        raise
    (run / INCOMPLETE_FILE).unlink()
    return run / "model.zip"


def _finish(config: TrainConfig, run: Path, model: Any, telemetry: Any, heldout: Any, elapsed: float) -> None:
    """The learning curve, then ``train_stats.json`` (what marks a finished run)."""
    if telemetry.history:
        try:
            plot_learning_curve({run.name: [telemetry.history]}, run / "learning_curve.png",
                                title=f"{config.scenario}, {config.num_robots} robots, "
                                f"{'behind the filter' if config.filter else 'bare'}, seed {config.seed}",
                                heldout={run.name: [heldout.rows]})
        except ImportError:  # matplotlib is an optional extra (render/repro)
            pass
    last = telemetry.history[-1] if telemetry.history else {}
    steps_this_run = model.num_timesteps - model._num_timesteps_at_start
    write_json(run / "train_stats.json", {
        "wall_time_s": elapsed, "agent_steps": int(model.num_timesteps), "agent_steps_this_run": int(steps_this_run),
        "agent_steps_per_s": steps_this_run / max(elapsed, 1e-9), "resumed_from": config.resume,
        "filter_kernel": _filter_kernel(config),
        "last_rollout": {k: v for k, v in last.items() if isinstance(v, (int, float)) and math.isfinite(v)},
        "last_heldout": heldout.rows[-1] if heldout.rows else None})


def _filter_kernel(config: TrainConfig) -> str | None:
    """Which backup-layer implementation the training filter ran (``kernel="auto"`` resolved), or None bare."""
    if not config.filter:
        return None
    return "numba" if config.filter_config().compiled else "numpy"


def _learn(config: TrainConfig, run: Path, venv: Any, source: Any, resumed: Any) -> tuple[Any, Any, Any, float]:
    """Build (or resume) the PPO on ``venv``, learn, save model and statistics: ``(model, telemetry, held-out, s)``."""
    from train.heldout import HeldOutEval

    model = build_model(config, venv, str(run / "tb") if config.tensorboard else None)
    if resumed is not None:
        from train.resume import resume_into

        resume_into(model, venv, config, resumed)
    elif config.init_from is not None:
        init_policy(model, venv, config, source)
    start = model.num_timesteps
    todo = config.total_timesteps - start
    rollouts = max(1, -(-todo // (config.n_steps * venv.num_envs)))
    telemetry = TelemetryCallback(run / "metrics.csv", config.total_timesteps,
                                  print_every=max(1, rollouts // 20) if config.progress_bar else 0,
                                  success_radius=config.reward.get("goal_tolerance", 0.1),
                                  history=resumed.metrics if resumed else None)
    heldout = HeldOutEval(config, run / "eval.csv", rows=resumed.evals if resumed else None)
    spec = run_spec(config)
    callbacks: list[Any] = [telemetry, heldout]
    if config.checkpoint_freq:
        callbacks.append(_checkpoint_callback(run / "checkpoints", max(1, config.checkpoint_freq // venv.num_envs),
                                              spec, config.normalize_obs or config.normalize_reward))
    if config.progress_bar:
        workers = f", {config.num_workers} worker processes" if config.num_workers > 1 else ""
        what = f"resuming {config.resume} at {start:,}" if resumed else "training"
        print(f"{what}: {run} ({config.total_timesteps:,} agent-steps, {config.n_envs} envs x "
              f"{config.num_robots} robots{workers}, {'behind the filter' if config.filter else 'bare'})", flush=True)
    t0 = time.perf_counter()
    try:
        model.learn(total_timesteps=todo, callback=callbacks, tb_log_name="ppo", reset_num_timesteps=resumed is None)
    except ValueError:
        _check_diverged(config, model)
        raise
    elapsed = time.perf_counter() - t0
    if config.normalize_obs or config.normalize_reward:
        save_stats(venv, stats_path(run / "model.zip"))
    save_model(model, run / "model.zip", spec)
    return model, telemetry, heldout, elapsed


def _check_diverged(config: TrainConfig, model: Any) -> None:
    """Name the hyper-parameters when training failed because the policy's weights became non-finite."""
    import torch

    if all(bool(torch.isfinite(p).all()) for p in model.policy.parameters()):
        return
    raise ConfigError(
        f"TrainConfig: training diverged at {model.num_timesteps:,} agent-steps (the policy's weights became "
        f"non-finite) with learning_rate={config.learning_rate:g}, ent_coef={config.ent_coef:g}, "
        f"vf_coef={config.vf_coef:g}, max_grad_norm={config.max_grad_norm:g}; expected settings that keep PPO "
        "stable (lower learning_rate first)") from None


def build_parser(prog: str = "aasoatt train") -> argparse.ArgumentParser:
    """Command-line parser (every :class:`TrainConfig` field is a flag, plus ``--seeds``)."""
    parser = Parser(prog=prog, description="Train PPO (parameter sharing) on the AA-SOATT env.",
                    epilog="--backend rllib trains with Ray RLlib instead (its own options: --backend rllib --help)")
    parser.add_argument("--backend", choices=BACKENDS, default="sb3",
                        help="sb3: Stable-Baselines3 on this machine (default); rllib: Ray RLlib (train/rllib.py)")
    add_config_arguments(parser)
    parser.add_argument("--seeds", type=int, nargs="+", default=None, metavar="SEED",
                        help="train one run per seed (in <out-dir>/<run-name>/s<seed>) and report mean and spread")
    parser.add_argument("--print-config", action="store_true", help="print the merged config and exit")
    add_common_options(parser, overwrite=False)  # every run gets a new folder: nothing to overwrite
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point; returns the exit status.

    The configuration, the env it describes and the output folder are checked before training
    starts; every run gets a new folder, so earlier runs are never overwritten.  ``--backend
    rllib`` hands the command line to :mod:`train.rllib`.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    backend, rest = split_backend(argv)
    if backend == "rllib":  # python -m train.train --backend rllib (this module needs SB3; train.rllib does not)
        from train.rllib import main as rllib_main

        return rllib_main(rest, prog="python -m train.train --backend rllib")
    return run_guarded("aasoatt train", argv, _main)


def _main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    config = config_from_args(args)
    if args.seeds is not None:
        from train.seeds import train_seeds

        if args.seed is not None:
            raise ConfigError(f"--seeds: got {args.seeds} with --seed {args.seed}, expected one of them")
        configs = train_seeds(config, args.seeds, "--seeds", dry_run=True)
        if args.print_config:
            print(json.dumps([c.to_dict() for c in configs], indent=2))
            return 0
        train_seeds(config, args.seeds, "--seeds")
        return 0
    if args.print_config:
        print(json.dumps(config.to_dict(), indent=2))
        return 0
    path = train(config)
    print(f"saved {path}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
