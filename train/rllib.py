"""Shared-policy PPO on the AA-SOATT env with Ray RLlib (new API stack): one machine or a Ray cluster.

Usage (in the virtual environment of the ``rllib`` extra, see README "Use it from your RL library")::

    aasoatt train --backend rllib --num-robots 4 --num-env-runners 2 --iterations 50    # local Ray
    python -m train.rllib --config run.toml                                               # the same

    ray start --head --num-cpus 8          # a cluster: on the head node (``ray start --address HEAD:6379``
                                           # on every other node, all in the same virtual environment)
    aasoatt train --backend rllib --address auto --num-env-runners 16 --iterations 500

    # continue a run (same settings, a new run folder):
    aasoatt train --backend rllib --config runs/RUN/config.json --resume runs/RUN --iterations 100

The same command scales from this machine to a cluster: ``--address`` joins a running Ray
cluster (``auto``: the one started on this node with ``ray start``; or ``HOST:PORT``), and
``--num-env-runners`` sets how many sampling processes Ray spreads over its nodes (0: sample in
the driver).  Every node needs this package and the ``rllib`` extra installed (the env runners
build the env themselves).

What is trained
---------------
Every robot is an agent of RLlib's ``ParallelPettingZooEnv`` around
:func:`aasoatt_env.make_env` (behind :class:`~aasoatt_env.safety.wrapper.AASOATTFilter` unless
``--filter false``), and all of them map to one RLModule, ``"shared"`` (parameter sharing, as
the Stable-Baselines3 backend does).  PPO is RLlib's ``DefaultPPOTorchRLModule``: separate
actor and critic MLPs of ``net_arch`` (tanh), a diagonal Gaussian policy.  Observations are not
normalised (no connector with state: the checkpoint's RLModule is the whole policy).  The
env, reward and filter fields, and the TOML/JSON/command-line handling, are those of
:class:`train.config.TrainConfig`; the PPO fields follow RLlib's names where they differ.

Outputs in the run folder ``<out_dir>/<run_name>`` (a new folder, ``_2``, ``_3``, ... if the name
is taken: a run never overwrites another):

=================================  =============================================================
file                               content
=================================  =============================================================
``config.json``                    the :class:`RLlibConfig`
``policy.json``                    env keywords, filter configuration, the RLModule's model
                                   config, ``"backend": "rllib"`` (what
                                   :class:`agents.rllib_agent.RLlibAgent` needs)
``rl_module.npz``                  the final weights of the shared RLModule (plain arrays)
``checkpoints/iter_<n>/``          RLlib checkpoints (``Algorithm.from_checkpoint`` resumes
                                   one), each with its own ``rl_module.npz``
``progress.jsonl``                 one line of metrics per iteration
``train_stats.json``               wall time, env and agent steps, throughput
=================================  =============================================================

While training, the folder also holds an ``INCOMPLETE`` file, removed at the end.  A run that
fails or is interrupted is removed, or kept with its ``INCOMPLETE`` file (and no
``train_stats.json``) when it already has a checkpoint (:func:`train.config.abandon_run`).

``aasoatt evaluate --bare <run>`` (or ``--filtered <run>``) evaluates the policy in the same
table as the Stable-Baselines3 runs, without starting Ray.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from aasoatt_env.errors import ConfigError
from train.config import INCOMPLETE_FILE, EnvConfig, abandon_run, add_config_arguments, claim_run_dir, config_from_args

RAY_MISSING = ("Ray RLlib is not installed; install the rllib extra in a virtual environment of its own "
               "(ray[rllib] pins gymnasium 1.2), e.g. python3 -m venv .venv-rllib && "
               ".venv-rllib/bin/pip install -e \".[rllib]\" (README: Use it from your RL library)")
"""What the RLlib commands say without Ray (``aasoatt train --backend rllib``, a run of it given to evaluate or run)."""

__all__ = ["ENV_NAME", "MODULE_ID", "RLlibConfig", "build_algorithm_config", "main", "make_rllib_env", "train"]

ENV_NAME = "aasoatt"
"""The name the env creator is registered under with ``ray.tune.registry.register_env``."""
MODULE_ID = "shared"
"""The one RLModule every robot maps to."""
WEIGHTS_FILE = "rl_module.npz"
POLICY_FILE = "policy.json"


@dataclass
class RLlibConfig(EnvConfig):
    """Configuration of one RLlib PPO run (see the module docstring).

    The env and filter fields are those of :class:`train.config.EnvConfig`; ``filter`` defaults
    to true here.

    Attributes
    ----------
    iterations : int
        ``Algorithm.train()`` calls; each samples ``train_batch_size`` env steps (times the
        robots: agent-steps) and runs ``num_epochs`` of minibatch updates.
    num_env_runners : int
        Sampling processes (Ray actors, spread over the cluster's nodes); 0 samples in the driver.
    num_envs_per_env_runner : int
        Envs stepped together by each env runner.
    rollout_fragment_length : int
        Env steps per env and ``sample()`` call of an env runner (0: RLlib's ``"auto"``, the
        batch split evenly over the runners' envs).
    sample_timeout_s : float
        How long the driver waits for a remote env runner's ``sample()``; results that come later
        are discarded (RLlib's default of 60 s is too short for one runner sampling a whole
        filtered batch on a loaded machine).
    num_learners : int
        Learner processes (0: the learner runs in the driver; >0 for several GPUs or nodes).
    num_gpus_per_learner : float
        GPUs per learner (0: CPU).
    train_batch_size : int
        Env steps per iteration and learner (RLlib's ``train_batch_size_per_learner``).
    minibatch_size : int
        PPO minibatch size (at most ``train_batch_size``).
    num_epochs : int
        Passes over each batch.
    learning_rate, gamma, gae_lambda, clip_range, ent_coef, vf_coef : float
        PPO hyper-parameters (RLlib: ``lr``, ``gamma``, ``lambda_``, ``clip_param``,
        ``entropy_coeff``, ``vf_loss_coeff``).
    vf_clip : float
        RLlib's ``vf_clip_param``: value-loss clipping in return units (RLlib's default of 10 is
        far below our returns of several hundred per robot, so it is large by default).
    max_grad_norm : float
        RLlib's ``grad_clip`` (global norm).
    net_arch : list of int
        Hidden layers of the actor and the critic MLPs.
    seed : int
        Seed of RLlib (env runners, envs, torch).
    address : str or None
        Ray cluster to join (``"auto"``, ``"HOST:PORT"``, ``"ray://HOST:10001"``); None starts a
        local Ray instance (unless this process already has one).
    num_cpus : int or None
        CPUs of the local Ray instance (default: all); not with ``address``.
    checkpoint_every : int
        Iterations between checkpoints (0: only the final one).
    resume : str or None
        Continue from this checkpoint (``checkpoints/iter_<n>``) or run folder (its last
        checkpoint): the algorithm's whole state (weights, optimiser, counters) is restored and
        ``iterations`` more are trained into a new run folder.  The env and model settings must
        be those of the checkpoint (``--config <run>/config.json``).
    out_dir, run_name : str
        Parent folder of runs and the run folder name (default from scenario, filter and seed).
    torch_threads : int
        ``torch.set_num_threads`` in the driver (1 is fastest for small MLPs on few cores).
    verbose : int
        0: quiet; 1: one line per iteration.
    """

    filter: bool = True
    iterations: int = 100
    num_env_runners: int = 0
    num_envs_per_env_runner: int = 1
    rollout_fragment_length: int = 0
    sample_timeout_s: float = 600.0
    num_learners: int = 0
    num_gpus_per_learner: float = 0.0
    train_batch_size: int = 4000
    minibatch_size: int = 512
    num_epochs: int = 10
    learning_rate: float = 3e-4
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_range: float = 0.2
    ent_coef: float = 0.0
    vf_coef: float = 0.5
    vf_clip: float = 1e4
    max_grad_norm: float = 0.5
    net_arch: list[int] = field(default_factory=lambda: [64, 64])
    seed: int = 0
    address: str | None = None
    num_cpus: int | None = None
    checkpoint_every: int = 10
    resume: str | None = None
    out_dir: str = "runs"
    run_name: str | None = None
    torch_threads: int = 1
    verbose: int = 1

    def _validate(self) -> None:
        self._validate_env()
        for name in ("iterations", "num_envs_per_env_runner", "train_batch_size", "num_epochs", "torch_threads"):
            self._int(name, 1)
        for name in ("num_env_runners", "num_learners", "seed", "checkpoint_every", "verbose",
                     "rollout_fragment_length"):
            self._int(name, 0)
        self._int("minibatch_size", 1)
        if self.minibatch_size > self.train_batch_size:
            raise self._err("minibatch_size", f"at most train_batch_size = {self.train_batch_size}")
        self._float("num_gpus_per_learner", 0.0)
        self._float("sample_timeout_s", 0.0, lo_open=True)
        self._float("learning_rate", 0.0, 1.0, lo_open=True)
        self._float("gamma", 0.0, 1.0)
        self._float("gae_lambda", 0.0, 1.0)
        self._float("clip_range", 0.0, 10.0, lo_open=True)
        self._float("ent_coef", 0.0)
        self._float("vf_coef", 0.0)
        self._float("vf_clip", 0.0, lo_open=True)
        self._float("max_grad_norm", 0.0, lo_open=True)
        self._net_arch()
        if self.address is not None and (not isinstance(self.address, str) or not self.address):
            raise self._err("address", "a Ray address ('auto', 'HOST:PORT', 'ray://HOST:PORT') or None")
        if self.num_cpus is not None:
            self._int("num_cpus", 1)
            if self.address is not None:
                raise ConfigError(f"RLlibConfig.num_cpus: got {self.num_cpus!r} with address={self.address!r}, "
                                  "expected None (a running cluster has its own CPUs)")
        if self.resume is not None and (not isinstance(self.resume, str) or not self.resume):
            raise self._err("resume", "a checkpoint or run folder, or None")
        self._validate_run_folder()

    # ------------------------------------------------------------------ helpers
    def default_run_name(self) -> str:
        """``rllib_ppo_<scenario>_<N>r_<filter|bare>_s<seed>``."""
        return f"rllib_ppo_{self.scenario}_{self.num_robots}r_{'filter' if self.filter else 'bare'}_s{self.seed}"

    def model_config(self) -> dict[str, Any]:
        """The RLModule's ``model_config`` (complete, so the module rebuilds identically from ``policy.json``)."""
        return {"fcnet_hiddens": list(self.net_arch), "fcnet_activation": "tanh", "vf_share_layers": False}

    def env_config(self) -> dict[str, Any]:
        """RLlib's ``env_config``: the env keywords and the filter configuration (None: bare)."""
        return {"env": self.env_kwargs(), "filter": dataclasses.asdict(self.filter_config()) if self.filter else None}

    def run_spec(self) -> dict[str, Any]:
        """The ``policy.json`` of a run (what :class:`agents.rllib_agent.RLlibAgent` needs)."""
        import ray

        ec = self.env_config()
        return {
            "format": 1,
            "backend": "rllib",
            "env": ec["env"],
            "filter": ec["filter"],
            "policy": "DefaultPPOTorchRLModule",
            "module_id": MODULE_ID,
            "model_config": self.model_config(),
            "normalize_obs": False,
            "ray_version": ray.__version__,
        }


# ---------------------------------------------------------------------- env and algorithm
def make_rllib_env(env_config: dict[str, Any]) -> Any:
    """RLlib env creator: ``ParallelPettingZooEnv(make_env(**env, filter=filter))`` (runs in every env runner)."""
    from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv

    from aasoatt_env.api.factory import make_env

    return ParallelPettingZooEnv(make_env(**env_config["env"], filter=env_config.get("filter")))


def _to_shared(agent_id: Any, episode: Any, **kwargs: Any) -> str:
    """Policy mapping: every robot acts with the shared module."""
    return MODULE_ID


def build_algorithm_config(config: RLlibConfig) -> Any:
    """The ``PPOConfig`` (new API stack) of ``config``; ``.build_algo()`` gives the algorithm."""
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.multi_rl_module import MultiRLModuleSpec
    from ray.rllib.core.rl_module.rl_module import RLModuleSpec

    return (
        PPOConfig()
        .api_stack(enable_rl_module_and_learner=True, enable_env_runner_and_connector_v2=True)
        .environment(ENV_NAME, env_config=config.env_config())
        .framework("torch")
        .env_runners(num_env_runners=config.num_env_runners,
                     num_envs_per_env_runner=config.num_envs_per_env_runner,
                     rollout_fragment_length=config.rollout_fragment_length or "auto",
                     sample_timeout_s=config.sample_timeout_s)
        .learners(num_learners=config.num_learners, num_gpus_per_learner=config.num_gpus_per_learner)
        .multi_agent(policies={MODULE_ID}, policy_mapping_fn=_to_shared)
        .rl_module(rl_module_spec=MultiRLModuleSpec(
            rl_module_specs={MODULE_ID: RLModuleSpec(model_config=config.model_config())}))
        .training(
            train_batch_size_per_learner=config.train_batch_size, minibatch_size=config.minibatch_size,
            num_epochs=config.num_epochs, lr=config.learning_rate, gamma=config.gamma,
            lambda_=config.gae_lambda, clip_param=config.clip_range, entropy_coeff=config.ent_coef,
            vf_loss_coeff=config.vf_coef, vf_clip_param=config.vf_clip, grad_clip=config.max_grad_norm,
        )
        .debugging(seed=config.seed)
    )


def _module_weights(algo: Any) -> dict[str, np.ndarray]:
    """The shared RLModule's weights from the learner (local or remote) as numpy arrays."""
    from ray.rllib.core import COMPONENT_LEARNER, COMPONENT_LEARNER_GROUP, COMPONENT_RL_MODULE

    state = algo.get_state(components=f"{COMPONENT_LEARNER_GROUP}/{COMPONENT_LEARNER}/{COMPONENT_RL_MODULE}/"
                                      f"{MODULE_ID}")
    weights = state[COMPONENT_LEARNER_GROUP][COMPONENT_LEARNER][COMPONENT_RL_MODULE][MODULE_ID]
    return {k: np.asarray(v) for k, v in weights.items()}


def resume_checkpoint(path: str) -> Path:
    """The RLlib checkpoint to resume from: ``path`` itself, or the last ``checkpoints/iter_<n>`` of a run folder."""
    p = Path(path).expanduser()
    if (p / "rllib_checkpoint.json").is_file():
        return p.resolve()
    found = sorted((p / "checkpoints").glob("iter_*/rllib_checkpoint.json"))
    if not found:
        raise ConfigError(f"RLlibConfig.resume: got {path!r}, expected an RLlib checkpoint folder or a run folder "
                          "with checkpoints/iter_<n>")
    return found[-1].parent.resolve()


def _save(algo: Any, run: Path, iteration: int) -> Path:
    """An RLlib checkpoint ``checkpoints/iter_<n>`` with the module's weights as ``rl_module.npz`` beside it."""
    ckpt = run / "checkpoints" / f"iter_{iteration:06d}"
    algo.save_to_path(str(ckpt.resolve()))  # RLlib wants an absolute path (a relative one is read as a URI)
    np.savez(ckpt / WEIGHTS_FILE, **_module_weights(algo))
    return ckpt


def _metrics(result: dict[str, Any], iteration: int, wall: float, iter_s: float) -> dict[str, Any]:
    """One ``progress.jsonl`` row from ``Algorithm.train()``'s result."""

    def num(x: Any) -> float | None:
        try:
            v = float(x)
        except (TypeError, ValueError):
            return None
        return v if math.isfinite(v) else None

    er = result.get("env_runners", {})
    agent_steps = er.get("num_agent_steps_sampled_lifetime")
    iter_steps = er.get("num_agent_steps_sampled")
    agent_returns = er.get("agent_episode_returns_mean")
    learner = result.get("learners", {}).get(MODULE_ID, {})
    row = {
        "iteration": iteration,
        "wall_s": wall,
        "iter_s": iter_s,
        "env_steps": num(er.get("num_env_steps_sampled_lifetime")),
        "agent_steps": num(sum(agent_steps.values()) if isinstance(agent_steps, dict) else agent_steps),
        "iter_agent_steps": num(sum(iter_steps.values()) if isinstance(iter_steps, dict) else iter_steps),
        "episodes": num(er.get("num_episodes_lifetime")),
        "episode_return_mean": num(er.get("episode_return_mean")),  # team: sum over robots
        "robot_return_mean": num(np.mean(list(agent_returns.values()))) if isinstance(agent_returns, dict)
        and agent_returns else None,
        "episode_len_mean": num(er.get("episode_len_mean")),
    }
    for key in ("policy_loss", "vf_loss", "entropy", "mean_kl_loss", "vf_explained_var"):
        if key in learner:
            row[key] = num(learner[key])
    return row


def _fmt(x: float | None, spec: str) -> str:
    return "-" if x is None else format(x, spec)


# ---------------------------------------------------------------------- training
def train(config: RLlibConfig) -> Path:
    """Train PPO as configured; return the run folder (see the module docstring for its files).

    Starts a local Ray instance (or joins ``config.address``) unless this process already
    has one, and shuts down only the instance it started.
    """
    import ray
    import torch
    from ray.tune.registry import register_env

    torch.set_num_threads(config.torch_threads)
    resume = resume_checkpoint(config.resume) if config.resume is not None else None
    started = not ray.is_initialized()
    if started:
        if config.address is None:
            ray.init(num_cpus=config.num_cpus, include_dashboard=False, logging_level="WARNING")
        else:
            ray.init(address=config.address, logging_level="WARNING")
    try:
        register_env(ENV_NAME, make_rllib_env)
        algo = build_algorithm_config(config).build_algo()
        if resume is not None:
            algo.restore_from_path(str(resume))
    except BaseException:
        if started:
            ray.shutdown()
        raise
    # the run folder is made once Ray and the algorithm are up: a failed start leaves no folder behind
    run: Path | None = None
    created = False
    t0 = time.perf_counter()
    row: dict[str, Any] = {}
    run_steps = 0.0
    first = int(algo.iteration)  # 0, or the iterations of the resumed checkpoint
    last = first + config.iterations
    try:
        run, created = claim_run_dir(config.out_dir, config.run_name or config.default_run_name())
        (run / "config.json").write_text(json.dumps(config.to_dict(), indent=2))
        (run / POLICY_FILE).write_text(json.dumps(config.run_spec(), indent=2))
        with (run / "progress.jsonl").open("w") as log:
            for it in range(first + 1, last + 1):
                t1 = time.perf_counter()
                result = algo.train()
                now = time.perf_counter()
                row = _metrics(result, it, now - t0, now - t1)
                run_steps += row["iter_agent_steps"] or 0.0
                log.write(json.dumps(row) + "\n")
                log.flush()
                if config.verbose:
                    print(f"iter {it}/{last}  {row['iter_s']:.1f} s  env steps {_fmt(row['env_steps'], '.0f')}  "
                          f"return/robot {_fmt(row['robot_return_mean'], '.1f')}", flush=True)
                if config.checkpoint_every and it % config.checkpoint_every == 0 and it < last:
                    _save(algo, run, it)
        elapsed = time.perf_counter() - t0
        ckpt = _save(algo, run, last)
        np.savez(run / WEIGHTS_FILE, **dict(np.load(ckpt / WEIGHTS_FILE, allow_pickle=False)))
        (run / "train_stats.json").write_text(json.dumps({
            "wall_time_s": elapsed, "iterations": config.iterations, "resumed_from": str(resume) if resume else None,
            "env_steps": row.get("env_steps"),
            "agent_steps": row.get("agent_steps"), "agent_steps_this_run": run_steps,
            "agent_steps_per_s": run_steps / max(elapsed, 1e-9),
            "num_env_runners": config.num_env_runners, "ray_nodes": len(ray.nodes()),
            "final_checkpoint": str(ckpt.relative_to(run)),
        }, indent=2))
    except BaseException:
        # a failed or interrupted run: removed, or kept (marked incomplete) when it has a checkpoint
        if run is not None:
            abandon_run(run, keep=any((run / "checkpoints").glob("iter_*")), created=created)
        raise
    finally:
        algo.stop()
        if started:
            ray.shutdown()
    (run / INCOMPLETE_FILE).unlink()
    return run


# ---------------------------------------------------------------------- command line
def build_parser(prog: str = "python -m train.rllib") -> argparse.ArgumentParser:
    """Command-line parser (every :class:`RLlibConfig` field is a flag)."""
    parser = argparse.ArgumentParser(
        prog=prog, description="Train PPO (parameter sharing) on the AA-SOATT env with Ray RLlib, locally or on a "
                               "Ray cluster (--address).")
    add_config_arguments(parser, RLlibConfig)
    parser.add_argument("--print-config", action="store_true", help="print the merged config and exit")
    return parser


def main(argv: Sequence[str] | None = None, prog: str = "python -m train.rllib") -> int:
    """Command-line entry point; returns the exit status."""
    args = build_parser(prog).parse_args(argv)
    try:
        config = config_from_args(args, RLlibConfig)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.print_config:
        print(json.dumps(config.to_dict(), indent=2))
        return 0
    if importlib.util.find_spec("ray") is None:
        print(f"error: {RAY_MISSING}", file=sys.stderr)
        return 2
    run = train(config)
    print(f"saved {run}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
