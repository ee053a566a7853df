"""Shared-policy PPO on the AA-SOATT env with Ray RLlib (new API stack): one machine or a Ray cluster.

Usage (in the virtual environment of the ``rllib`` extra, see README "Use it from your RL library")::

    aasoatt train --backend rllib                                    # the default task, behind the filter
    aasoatt train --backend rllib --num-env-runners 2 --iterations 50
    python -m train.rllib --config run.toml                           # the same

    ray start --head --num-cpus 8          # a cluster: on the head node (``ray start --address HEAD:6379``
                                           # on every other node, all in the same virtual environment)
    aasoatt train --backend rllib --address auto --num-env-runners 16

    aasoatt train --backend rllib --resume runs/RUN --iterations 100  # continue a run (a new run folder)

The same command scales from this machine to a cluster: ``--address`` joins a running Ray
cluster (``auto``: the one started on this node; or ``HOST:PORT``), ``--num-env-runners`` sets
how many sampling processes Ray spreads over its nodes (0: sample in the driver).  Every node
needs this package and the ``rllib`` extra installed.

What is trained
---------------
Each env runner steps ``num_envs_per_env_runner`` teams of the task together
(:class:`train.rllib_env.SlotVectorEnv`: one batched physics step, one policy forward pass and,
behind :class:`~aasoatt_env.safety.wrapper.AASOATTFilter` (unless ``--filter false``), one
filter call per decision for all its robots); every robot is one sub-env of RLlib's vector env
and all share one RLModule (parameter sharing, as the Stable-Baselines3 backend does).  PPO is
RLlib's ``DefaultPPOTorchRLModule``: separate actor and critic MLPs of ``net_arch`` (tanh), a
diagonal Gaussian policy, observations not normalised (the saved module is the whole policy).
The env, reward (:data:`train.config.TRAIN_REWARD` laid under ``reward``) and filter fields
and the TOML/JSON/command-line handling are those of :class:`train.config.TrainConfig`; the
default batch (32 teams x robots x 64 decisions per iteration, minibatch 1024, 10 epochs) is the
Stable-Baselines3 recipe's.

Outputs in the run folder ``<out_dir>/<run_name>`` (a new folder, ``_2``, ``_3``, ... if the name
is taken), every file written atomically:

=================================  =============================================================
file                               content
=================================  =============================================================
``config.json``                    the :class:`RLlibConfig`
``policy.json``                    env keywords, filter configuration, the RLModule's model
                                   config, ``"backend": "rllib"`` (what
                                   :class:`agents.rllib_agent.RLlibAgent` needs)
``rl_module.npz``                  the final weights of the shared RLModule (plain arrays, with
                                   the policy record)
``checkpoints/iter_<n>/``          RLlib checkpoints (``--resume`` continues one), each with its
                                   own ``rl_module.npz``
``progress.jsonl``                 one line of metrics per iteration (``success``: robots that
                                   ended their episode within the goal tolerance)
``train_stats.json``               wall time, env and agent steps, throughput
=================================  =============================================================

While training, the folder also holds an ``INCOMPLETE`` file, removed at the end; a run that
fails is removed, or kept with it when it has a checkpoint (:func:`train.runs.abandon_run`).
``aasoatt evaluate --filtered <run>`` evaluates the policy without starting Ray.
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

from aasoatt_env.errors import ConfigError
from train.config import LIMITS, TRAIN_REWARD, EnvConfig
from train.options import add_config_arguments, config_from_args
from train.policies import RAY_MISSING
from train.rllib_env import log_success, make_rllib_env, slots_per_team
from train.rllib_files import MODULE_ID, WEIGHTS_FILE, resume_checkpoint, save_checkpoint, weights_with_record
from train.runs import INCOMPLETE_FILE, abandon_run, check_path, claim_run_dir, save_npz, write_json, write_text

__all__ = ["ENV_NAME", "MODULE_ID", "RAY_MISSING", "RLlibConfig", "build_algorithm_config", "main", "make_rllib_env",
           "train"]

ENV_NAME = "aasoatt"
"""The name the env creator is registered under with ``ray.tune.registry.register_env``."""
POLICY_FILE = "policy.json"


@dataclass
class RLlibConfig(EnvConfig):
    """Configuration of one RLlib PPO run (see the module docstring).

    The env and filter fields are those of :class:`train.config.EnvConfig` (``filter`` defaults to
    true here; ``terminate_on_collision`` is not supported: teams end their episodes together).
    Bounds: :data:`train.config.LIMITS`.

    Attributes
    ----------
    iterations : int
        ``Algorithm.train()`` calls of this run; each samples ``train_batch_size`` agent-steps and
        runs ``num_epochs`` of minibatch updates.
    num_env_runners : int
        Sampling processes (Ray actors, spread over the cluster's nodes); 0 samples in the driver.
    num_envs_per_env_runner : int
        Teams each env runner steps together (its robots are the vector env's sub-envs).
    rollout_fragment_length : int
        Decisions per robot and ``sample()`` call (0: RLlib's ``"auto"``, the batch split evenly).
    sample_timeout_s : float
        How long the driver waits for a remote env runner's ``sample()`` (at most a day).
    num_learners : int
        Learner processes (0: the learner runs in the driver; >0 for several GPUs or nodes).
    num_gpus_per_learner : float
        GPUs per learner (0: CPU).
    train_batch_size : int
        Agent-steps per iteration and learner (0: 64 decisions of every robot of every runner,
        the Stable-Baselines3 recipe's rollout).
    minibatch_size : int
        PPO minibatch size (at most ``train_batch_size``; with the automatic batch, at most the batch).
    num_epochs : int
        Passes over each batch.
    learning_rate, gamma, gae_lambda, clip_range, ent_coef, vf_coef : float
        PPO hyper-parameters (RLlib: ``lr``, ``gamma``, ``lambda_``, ``clip_param``,
        ``entropy_coeff``, ``vf_loss_coeff``).
    vf_clip : float
        RLlib's ``vf_clip_param`` in return units (large by default: returns are in the hundreds).
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
        checkpoint; its ``config.json`` is the base of this run's): the algorithm's whole state
        is restored (RLlib unpickles it: your own runs only) and ``iterations`` more are trained
        into a new run folder.
    out_dir, run_name : str
        Parent folder of runs and the run folder name (default from scenario, filter and seed).
    torch_threads : int
        ``torch.set_num_threads`` in the driver.
    verbose : int
        0: quiet; 1: one line per iteration.
    """

    filter: bool = True
    iterations: int = 100
    num_env_runners: int = 0
    num_envs_per_env_runner: int = 32
    rollout_fragment_length: int = 0
    sample_timeout_s: float = 600.0
    num_learners: int = 0
    num_gpus_per_learner: float = 0.0
    train_batch_size: int = 0
    minibatch_size: int = 1024
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
        if isinstance(self.reward, dict):
            self.reward = {**TRAIN_REWARD, **self.reward}
        self._validate_env()
        if self.terminate_on_collision:
            raise self._err("terminate_on_collision", "false (the RLlib backend's teams end their episodes together)")
        if self.max_steps is not None and self.max_steps < 2:
            raise self._err("max_steps", "None or at least 2 (an RLlib episode starts after one decision at rest)")
        self._validate_sizes()
        self._float("num_gpus_per_learner", 0.0, 64.0)
        self._float("sample_timeout_s", 0.0, 86_400.0, lo_open=True)
        self._float("learning_rate", 0.0, 1.0, lo_open=True)
        for name in ("gamma", "gae_lambda"):
            self._float(name, 0.0, 1.0)
        self._float("clip_range", 0.0, 10.0, lo_open=True)
        self._float("ent_coef", 0.0, 10.0)
        self._float("vf_coef", 0.0, 100.0)
        self._float("vf_clip", 0.0, 1e9, lo_open=True)
        self._float("max_grad_norm", 0.0, 1000.0, lo_open=True)
        self._net_arch()
        if self.address is not None:
            check_path(self.address, self._name("address"))
        if self.num_cpus is not None:
            self._int("num_cpus", 1, 4096)
            if self.address is not None:
                raise ConfigError(f"RLlibConfig.num_cpus: got {self.num_cpus!r} with address={self.address!r}, "
                                  "expected None (a running cluster has its own CPUs)")
        if self.resume is not None:
            self.resume = check_path(self.resume, self._name("resume"))
        self._validate_run_folder()

    def _validate_sizes(self) -> None:
        lim = LIMITS
        self._int("seed", 0, lim["seed"])
        self._int("iterations", 1, lim["iterations"])
        self._int("checkpoint_every", 0, lim["iterations"])
        self._int("num_env_runners", 0, lim["workers"])
        self._int("num_learners", 0, lim["workers"])
        self._int("torch_threads", 1, lim["workers"])
        self._int("num_envs_per_env_runner", 1, lim["teams"])
        if self.num_envs_per_env_runner * self.num_robots > lim["slots"]:
            raise self._err("num_envs_per_env_runner", f"at most {lim['slots'] // self.num_robots} teams of "
                            f"{self.num_robots} robots (at most {lim['slots']} robots per env runner)")
        self._int("rollout_fragment_length", 0, lim["n_steps"])
        self._int("train_batch_size", 0, lim["rollout"])
        self._int("minibatch_size", 1, lim["rollout"])
        if self.train_batch_size and self.minibatch_size > self.train_batch_size:
            raise self._err("minibatch_size", f"at most train_batch_size = {self.train_batch_size}")
        self._int("num_epochs", 1, lim["epochs"])
        self._int("verbose", 0, 2)

    # ------------------------------------------------------------------ helpers
    def default_run_name(self) -> str:
        """``rllib_ppo_<scenario>_<N>r_<filter|bare>_s<seed>``."""
        return f"rllib_ppo_{self.scenario}_{self.num_robots}r_{'filter' if self.filter else 'bare'}_s{self.seed}"

    def batch_size(self) -> int:
        """Agent-steps per iteration: ``train_batch_size``, or 64 decisions of every runner's every robot."""
        if self.train_batch_size:
            return self.train_batch_size
        return min(64 * max(1, self.num_env_runners) * self.num_envs_per_env_runner * self.num_robots,
                   LIMITS["rollout"])

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
        return {"format": 1, "backend": "rllib", "env": ec["env"], "filter": ec["filter"],
                "policy": "DefaultPPOTorchRLModule", "module_id": MODULE_ID, "model_config": self.model_config(),
                "normalize_obs": False, "ray_version": ray.__version__}


# ---------------------------------------------------------------------- algorithm
def build_algorithm_config(config: RLlibConfig) -> Any:
    """The ``PPOConfig`` (new API stack) of ``config``; ``.build_algo()`` gives the algorithm."""
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.rl_module import RLModuleSpec

    slots = config.num_envs_per_env_runner * slots_per_team(config.env_kwargs())
    return (
        PPOConfig()
        .api_stack(enable_rl_module_and_learner=True, enable_env_runner_and_connector_v2=True)
        .environment(ENV_NAME, env_config=config.env_config(), normalize_actions=False, clip_actions=False)
        .framework("torch")
        .env_runners(num_env_runners=config.num_env_runners, num_envs_per_env_runner=slots,
                     gym_env_vectorize_mode="vector_entry_point",
                     rollout_fragment_length=config.rollout_fragment_length or "auto",
                     sample_timeout_s=config.sample_timeout_s)
        .learners(num_learners=config.num_learners, num_gpus_per_learner=config.num_gpus_per_learner)
        .rl_module(rl_module_spec=RLModuleSpec(model_config=config.model_config()))
        .training(
            train_batch_size_per_learner=config.batch_size(),
            minibatch_size=min(config.minibatch_size, config.batch_size()),
            num_epochs=config.num_epochs, lr=config.learning_rate, gamma=config.gamma,
            lambda_=config.gae_lambda, clip_param=config.clip_range, entropy_coeff=config.ent_coef,
            vf_loss_coeff=config.vf_coef, vf_clip_param=config.vf_clip, grad_clip=config.max_grad_norm,
        )
        .callbacks(on_episode_end=log_success)
        .debugging(seed=config.seed)
    )


def _metrics(result: dict[str, Any], iteration: int, wall: float, iter_s: float) -> dict[str, Any]:
    """One ``progress.jsonl`` row from ``Algorithm.train()``'s result."""

    def num(x: Any) -> float | None:
        try:
            v = float(sum(x.values()) if isinstance(x, dict) else x)
        except (TypeError, ValueError):
            return None
        return v if math.isfinite(v) else None

    er = result.get("env_runners", {})
    learner = result.get("learners", {}).get(MODULE_ID, {})
    row = {
        "iteration": iteration, "wall_s": wall, "iter_s": iter_s,
        "agent_steps": num(er.get("num_env_steps_sampled_lifetime")),  # one sub-env step is one robot's decision
        "iter_agent_steps": num(er.get("num_env_steps_sampled")),
        "episodes": num(er.get("num_episodes_lifetime")),
        "robot_return_mean": num(er.get("episode_return_mean")),
        "episode_len_mean": num(er.get("episode_len_mean")),
        "success": num(er.get("success")),
    }
    for key in ("policy_loss", "vf_loss", "entropy", "mean_kl_loss", "vf_explained_var"):
        if key in learner:
            row[key] = num(learner[key])
    return row


def _fmt(x: float | None, spec: str) -> str:
    return "-" if x is None else format(x, spec)


# ---------------------------------------------------------------------- training
def _start(config: RLlibConfig) -> tuple[Any, bool, Path | None]:
    """Ray (started or joined unless this process has one) and the algorithm: ``(algo, started, resumed from)``."""
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
    return algo, started, resume


def _iterate(config: RLlibConfig, algo: Any, run: Path, spec: dict[str, Any]) -> tuple[list[dict], float]:
    """The iterations of this run, one ``progress.jsonl`` row each (the file rewritten atomically)."""
    rows: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    first = int(algo.iteration)  # 0, or the iterations of the resumed checkpoint
    last = first + config.iterations
    for it in range(first + 1, last + 1):
        t1 = time.perf_counter()
        result = algo.train()
        now = time.perf_counter()
        rows.append(_metrics(result, it, now - t0, now - t1))
        write_text(run / "progress.jsonl", "".join(json.dumps(r) + "\n" for r in rows))
        if config.verbose:
            r = rows[-1]
            print(f"iter {it}/{last}  {r['iter_s']:.1f} s  agent-steps {_fmt(r['agent_steps'], ',.0f')}  "
                  f"return/robot {_fmt(r['robot_return_mean'], '.1f')}  success {_fmt(r['success'], '.1%')}",
                  flush=True)
        if config.checkpoint_every and it % config.checkpoint_every == 0 and it < last:
            save_checkpoint(algo, run, it, spec)
    return rows, time.perf_counter() - t0


def train(config: RLlibConfig) -> Path:
    """Train PPO as configured; return the run folder (see the module docstring for its files).

    Starts a local Ray instance (or joins ``config.address``) unless this process already
    has one, and shuts down only the instance it started.  The run folder is made once Ray
    and the algorithm are up: a failed start leaves no folder behind.
    """
    import ray

    algo, started, resume = _start(config)
    run: Path | None = None
    created = False
    try:
        run, created = claim_run_dir(config.out_dir, config.run_name or config.default_run_name())
        spec = config.run_spec()
        write_json(run / "config.json", config.to_dict())
        write_json(run / POLICY_FILE, spec)
        rows, elapsed = _iterate(config, algo, run, spec)
        ckpt = save_checkpoint(algo, run, int(algo.iteration), spec)
        save_npz(run / WEIGHTS_FILE, **weights_with_record(algo, spec))
        run_steps = sum(r["iter_agent_steps"] or 0.0 for r in rows)
        write_json(run / "train_stats.json", {
            "wall_time_s": elapsed, "iterations": config.iterations, "resumed_from": str(resume) if resume else None,
            "agent_steps": rows[-1].get("agent_steps"), "agent_steps_this_run": run_steps,
            "agent_steps_per_s": run_steps / max(elapsed, 1e-9), "success_last_iteration": rows[-1].get("success"),
            "num_env_runners": config.num_env_runners, "ray_nodes": len(ray.nodes()),
            "final_checkpoint": str(ckpt.relative_to(run))})
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
    """Command-line entry point; returns the exit status (2 for a bad option or file, before anything starts)."""
    from aasoatt_env.errors import AASOATTError

    args = build_parser(prog).parse_args(argv)
    try:
        config = config_from_args(args, RLlibConfig)
    except AASOATTError as exc:
        print(f"error: {' '.join(str(exc).split())}", file=sys.stderr)
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
