"""PPO with parameter sharing on the AA-SOATT parallel env (bare or behind the filter).

Usage::

    python -m train.train --config run.toml --total-timesteps 200000
    python -m train.train --filter true --reward correction=0.5 --run-name ppo_filtered
    aasoatt train ...            # the same flags

Every robot of every env is one slot of :class:`train.vec_env.ParallelVecEnv`
(one shared policy).  The policy acts every ``decision_interval`` physics steps
(default 20, i.e. 10 Hz against the 200 Hz physics/filter); behind
:class:`~aasoatt_env.safety.wrapper.AASOATTFilter` its action is the nominal
that the CBF-QP filters at *every* physics step in between.

Reward design (per robot and decision, :class:`~aasoatt_env.sim.env.RewardConfig`)
------------------------------------------------------------------------------
``r_i = -tracking |p_i - p_d_i| - collision [clearance_i < -tol]
- effort |a_i|^2 / 2 - correction c_i + goal_bonus [|p_i - goal_i| < goal_tol]``

* **Goal reaching** is rewarded through *tracking*: the reference ``p_d_i(t)``
  moves along the straight line to the goal and then stays there, so the
  dense tracking term pulls the robot along the line and holds it at the
  goal (a robot that follows it reaches its goal when the reference ends).
  An optional sparse ``goal_bonus`` pays for being within ``goal_tolerance``.
* **Collision**: a penalty (default 10, i.e. ten decisions' worth of 1 m
  tracking error) for every decision in overlap.  With the default
  ``terminate_on_collision=False`` a colliding robot keeps going and keeps
  paying while it overlaps; with ``True`` its episode ends (see
  :mod:`train.vec_env` for the slot's padding).
* **Effort**: ``effort |a|^2 / 2`` with the normalised action (small, 0.01:
  it only breaks ties towards smooth, low-acceleration control).
* **Filter correction** (``correction``, only with ``filter=True``): penalises
  ``|du_safe - du_nominal| / max_wheel_accel``, the largest per-physics-step
  change the filter made to the robot's nominal in the decision.  It teaches
  the policy to propose actions the filter accepts, so the filter intervenes
  less and the learned behaviour does not rely on it.

Recipe: RandomGoals, 6 robots, evaluated behind the filter
----------------------------------------------------------
::

    nice -n 19 python -m train.train --config train/configs/random_goals_6r_prior.toml
    nice -n 19 python -m train.evaluate --bare runs/ppo_random_goals_6r_prior --episodes 100 \
        --rows "learned (bare)" "learned (bare) + filter" --out results/random_goals_6r_prior.md

400k agent-steps: 86 s of training (4,650 agent-steps/s) on 2 shared cores, one
torch thread.  Measured (seed 0; 100 episodes, seeds 10000-10099, default arena):

=========================  =========  =======  =========  =============  ========================
row                        safe rate  success  RMSE [m]   intervention   collisions (episodes)
=========================  =========  =======  =========  =============  ========================
learned (bare)             27.7%      100.0%   0.060      -              411 (96)
learned (bare) + filter    100.0%     99.5%    0.313      35.3%          0 (0)
=========================  =========  =======  =========  =============  ========================

PPO stiffened the prior's position gain from ``k3 k4 / a_max`` = 0.94 to 1.30
(velocity gain 1.18 -> 1.24); bare, the policy still collides about as often as
the tracking law (the collision penalty is deliberately small: safety is the
filter's job).  Why the
plain ``MlpPolicy`` recipe (defaults) fails here, measured on 100-150k-step runs:

* the needed accelerations are small (~0.1 of ``max_point_accel`` once on
  track) against an exploration noise of ~0.4, and ``-|p - p_d|`` reacts to an
  acceleration only through its double integral: PPO's advantages resolve the
  PD feedback slowly (the policy's gain on ``p - p_d`` even had the wrong sign
  at 100k steps; ep. return plateaued; RMSE > 1 m, success < 7%; a single robot
  alone also learns slowly; ``n_steps``/``gamma``/``velocity_tracking`` shaping
  did not fix it within 100k steps);
* in the default (crowded) arena the collision penalty (10 per decision in
  overlap) is ~40x the per-decision tracking cost of a perfect tracker
  (0.16 collision decisions per robot-decision vs 0.037 m error), so it
  dominates the normalised reward with noise the robot cannot control bare
  (others drive into it);
* a prior-initialised policy that kept ``collision=10`` lost its precision in
  100k steps (success 100% -> 7%, RMSE 0.07 -> 0.30): the residual learned to
  trade tracking for the noisy penalty.

The recipe therefore (i) uses :class:`train.policy.TrackingPriorPolicy`: the
action mean is a *trainable* linear layer on the raw observation initialised
to the tracking law (linear in the observation) plus the MLP residual, (ii)
scales the collision penalty to 1 (the filter provides safety), (iii) adds a
``goal_bonus`` with ``goal_tolerance`` equal to the success radius (0.1 m), and
(iv) trains gently around the prior (``learning_rate`` 1e-4, ``log_std_init``
-1.5, ``gamma`` 0.98 for ~100-decision episodes).

Outputs in the run folder ``<out_dir>/<run_name>``: ``model.zip`` (SB3 PPO),
``policy.json`` (env keywords, filter configuration, policy class: what
:class:`agents.learned.LearnedAgent` needs), ``normalization.npz`` (observation
statistics as plain arrays; nothing is pickled), ``config.json`` (the
:class:`~train.config.TrainConfig`), ``checkpoints/`` and ``tb/`` (tensorboard).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from aasoatt_env.api.factory import make_env as make_aasoatt_env
from aasoatt_env.cli_support import OutputPlan, Parser, add_common_options, run_guarded
from aasoatt_env.errors import ConfigError
from agents.learned import POLICY_FILE, stats_path
from train.config import BACKENDS, TrainConfig, add_config_arguments, config_from_args, split_backend, unique_run_dir
from train.rllib import main as rllib_main
from train.vec_env import ParallelVecEnv, VelocityTrackingShaping

__all__ = ["main", "make_env", "make_vec_env", "train"]


def make_env(config: TrainConfig, filter: bool | None = None, **env_overrides: Any) -> Any:
    """One parallel env of ``config``, behind the filter if ``filter`` (default ``config.filter``).

    Parameters
    ----------
    config : TrainConfig
        Run configuration (env fields and the filter configuration).
    filter : bool, optional
        Override ``config.filter``.
    **env_overrides
        Override :meth:`TrainConfig.env_kwargs` entries (e.g. ``render_mode``).
    """
    use_filter = config.filter if filter is None else filter
    return make_aasoatt_env(**{**config.env_kwargs(), **env_overrides},
                            filter=config.filter_config() if use_filter else None)


def run_spec(config: TrainConfig) -> dict[str, Any]:
    """The ``policy.json`` of a run: what :class:`agents.learned.LearnedAgent` needs to rebuild the policy's env."""
    fc = config.filter_config()
    return {
        "format": 1,
        "env": config.env_kwargs(),
        "filter": dataclasses.asdict(fc) if config.filter else None,
        "policy": "TrackingPriorPolicy" if config.policy_prior == "tracking" else "MlpPolicy",
        "normalize_obs": bool(config.normalize_obs),
    }


def save_stats(venv: Any, path: Path) -> None:
    """Observation statistics of ``VecNormalize`` as plain arrays (``normalization.npz``)."""
    rms = venv.obs_rms
    np.savez(path, mean=np.asarray(rms.mean, np.float64), var=np.asarray(rms.var, np.float64),
             count=np.asarray(rms.count, np.float64), clip_obs=np.asarray(venv.clip_obs, np.float64),
             epsilon=np.asarray(venv.epsilon, np.float64))


def make_vec_env(config: TrainConfig, training: bool = True) -> Any:
    """``VecNormalize?(VecMonitor(ParallelVecEnv))`` with ``config.n_envs`` envs."""
    from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

    venv: Any = ParallelVecEnv([lambda: make_env(config) for _ in range(config.n_envs)])
    if config.velocity_tracking:
        venv = VelocityTrackingShaping(venv, config.velocity_tracking)
    venv = VecMonitor(venv)
    if config.normalize_obs or config.normalize_reward:
        venv = VecNormalize(
            venv, training=training, norm_obs=config.normalize_obs, norm_reward=config.normalize_reward,
            gamma=config.gamma, clip_obs=10.0,
        )
    return venv


def _run_dir(config: TrainConfig) -> Path:
    """A new run folder ``<out_dir>/<name>`` (``<name>_2``, ``_3``, ... when taken): earlier runs are kept."""
    name = config.run_name or (
        f"ppo_{config.scenario}_{config.num_robots}r_{'filter' if config.filter else 'bare'}_s{config.seed}"
    )
    OutputPlan(overwrite=True).folder(config.out_dir, "TrainConfig.out_dir")  # creatable and writable, or say why
    try:
        return unique_run_dir(config.out_dir, name)
    except OSError as exc:
        raise ConfigError(f"TrainConfig.out_dir: cannot create a run folder in {config.out_dir} "
                          f"({exc.strerror or exc})") from None


def build_model(config: TrainConfig, venv: Any, tensorboard_log: str | None = None) -> Any:
    """The SB3 PPO of ``config`` on ``venv`` (seeded: PPO seeds torch, numpy and the env)."""
    import torch
    from stable_baselines3 import PPO

    torch.set_num_threads(config.torch_threads)
    policy: Any = "MlpPolicy"
    policy_kwargs: dict[str, Any] = dict(net_arch=list(config.net_arch), log_std_init=config.log_std_init)
    if config.policy_prior == "tracking":
        import numpy as np

        from agents.prior import TrackingPriorPolicy, tracking_prior_matrix

        probe = make_env(config, filter=False)
        probe.reset(seed=0)
        amax = np.asarray(probe.unwrapped.team.max_point_accel, dtype=float)
        probe.close()
        if not np.allclose(amax, amax[0]):
            raise ConfigError("TrainConfig.policy_prior: got robots with different max_point_accel, "
                              "expected one team-wide value for the shared tracking prior")
        k3, k4 = config.prior_gains
        policy = TrackingPriorPolicy
        policy_kwargs["prior_matrix"] = tracking_prior_matrix(
            int(np.prod(venv.observation_space.shape)), k3, k4, float(amax[0])).tolist()
    return PPO(
        policy, venv,
        learning_rate=config.learning_rate, n_steps=config.n_steps, batch_size=config.batch_size,
        n_epochs=config.n_epochs, gamma=config.gamma, gae_lambda=config.gae_lambda,
        clip_range=config.clip_range, ent_coef=config.ent_coef, vf_coef=config.vf_coef,
        max_grad_norm=config.max_grad_norm,
        policy_kwargs=policy_kwargs,
        tensorboard_log=tensorboard_log, seed=config.seed, device=config.device, verbose=config.verbose,
    )


def _progress_callback(total: int) -> Any:
    """A tqdm progress bar over agent-steps (SB3's own needs ``rich``)."""
    from stable_baselines3.common.callbacks import BaseCallback

    class TqdmCallback(BaseCallback):
        def _on_training_start(self) -> None:
            from tqdm import tqdm

            self.bar = tqdm(total=total, unit="agent-step", dynamic_ncols=True, desc="PPO")

        def _on_step(self) -> bool:
            self.bar.update(self.training_env.num_envs)
            return True

        def _on_training_end(self) -> None:
            self.bar.close()

    return TqdmCallback()


def _checkpoint_callback(folder: Path, every: int, with_stats: bool) -> Any:
    """Save ``ppo_<n>_steps.zip`` (and its ``.normalization.npz``) every ``every`` vectorised steps."""
    from stable_baselines3.common.callbacks import BaseCallback

    class Checkpoint(BaseCallback):
        def _on_step(self) -> bool:
            if self.n_calls % every == 0:
                folder.mkdir(parents=True, exist_ok=True)
                path = folder / f"ppo_{self.num_timesteps}_steps.zip"
                self.model.save(path)
                if with_stats:
                    save_stats(self.model.get_vec_normalize_env(), stats_path(path))
            return True

    return Checkpoint()


def train(config: TrainConfig) -> Path:
    """Train PPO as configured and return the path of the saved ``model.zip``.

    Parameters
    ----------
    config : TrainConfig
        Validated configuration.

    Returns
    -------
    Path
        ``<run>/model.zip``; the run folder also holds ``policy.json``,
        ``normalization.npz`` (when normalising observations), ``config.json``,
        ``checkpoints/`` and ``tb/``.
    """
    probe = make_env(config)  # the env (and filter) settings are checked before any folder is made
    probe.close()
    run = _run_dir(config)
    (run / "config.json").write_text(json.dumps(config.to_dict(), indent=2))
    (run / POLICY_FILE).write_text(json.dumps(run_spec(config), indent=2))
    venv = make_vec_env(config)
    model = build_model(config, venv, str(run / "tb") if config.tensorboard else None)
    callbacks: list[Any] = []
    if config.checkpoint_freq:
        callbacks.append(_checkpoint_callback(run / "checkpoints", max(1, config.checkpoint_freq // venv.num_envs),
                                              config.normalize_obs))
    if config.progress_bar:
        callbacks.append(_progress_callback(config.total_timesteps))
    t0 = time.perf_counter()
    model.learn(total_timesteps=config.total_timesteps, callback=callbacks or None, tb_log_name="ppo")
    elapsed = time.perf_counter() - t0
    model.save(run / "model.zip")
    if config.normalize_obs:
        save_stats(venv, stats_path(run / "model.zip"))
    (run / "train_stats.json").write_text(json.dumps(
        {"wall_time_s": elapsed, "agent_steps": int(model.num_timesteps),
         "agent_steps_per_s": model.num_timesteps / max(elapsed, 1e-9)}, indent=2))
    venv.close()
    return run / "model.zip"


def build_parser(prog: str = "aasoatt train") -> argparse.ArgumentParser:
    """Command-line parser (every :class:`TrainConfig` field is a flag)."""
    parser = Parser(prog=prog, description="Train PPO (parameter sharing) on the AA-SOATT env.",
                    epilog="--backend rllib trains with Ray RLlib instead (its own options: --backend rllib --help)")
    parser.add_argument("--backend", choices=BACKENDS, default="sb3",
                        help="sb3: Stable-Baselines3 on this machine (default); rllib: Ray RLlib (train/rllib.py)")
    add_config_arguments(parser)
    parser.add_argument("--print-config", action="store_true", help="print the merged config and exit")
    add_common_options(parser, overwrite=False)  # every run gets a new folder: nothing to overwrite
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point; returns the exit status.

    The configuration, the env it describes and the output folder are checked
    before training starts; every run gets a new folder (``<name>_2``, ... when
    the name is taken), so earlier runs are never overwritten.  ``--backend rllib``
    hands the command line to :mod:`train.rllib`.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    backend, rest = split_backend(argv)
    if backend == "rllib":  # python -m train.train --backend rllib (this module needs SB3; train.rllib does not)
        return rllib_main(rest, prog="python -m train.train --backend rllib")
    return run_guarded("aasoatt train", argv, _main)


def _main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    config = config_from_args(args)
    if args.print_config:
        print(json.dumps(config.to_dict(), indent=2))
        return 0
    path = train(config)
    print(f"saved {path}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
