"""PPO with parameter sharing on the AA-SOATT env (bare or behind the filter).

Usage::

    aasoatt train                                  # the default recipe (train/configs/random_goals_6r.toml)
    aasoatt train --filter true --reward correction=0.5 --run-name ppo_filtered
    aasoatt train --config run.toml --total-timesteps 200000
    python -m train.train ...                      # the same flags

Every robot of every env is one slot of :class:`train.vec_env.BatchedVecEnv`
(one shared policy); the ``n_envs`` teams are stepped by one vectorised physics
call (:class:`~aasoatt_env.sim.batched.BatchedAASOATTEnv`).  The policy acts
every ``decision_interval`` physics steps (default 20, i.e. 10 Hz against the
200 Hz physics/filter); behind :class:`~aasoatt_env.safety.wrapper.AASOATTFilter`
its action is the nominal that the CBF-QP filters at *every* physics step in between.

The default recipe (:class:`~train.config.TrainConfig` defaults)
--------------------------------------------------------------------
A plain MLP policy (SB3 ``MlpPolicy``, ``[64, 64]``, ``log_std_init`` -1)
learned from scratch: ``VecNormalize`` on observations and rewards, point
actions, PPO with 32 envs x 6 robots, ``n_steps`` 64, minibatch 1024, 10
epochs, learning rate 3e-4, ``gamma`` 0.99, no entropy bonus, 1,228,800
agent-steps (100 rollouts).  Short runs judge it wrongly: success rises late
(the README's learning curve).

Reward (per robot and decision, :class:`~aasoatt_env.sim.rewards.RewardConfig`,
recipe weights in :data:`~train.config.TRAIN_REWARD`)::

    r_i = -tracking |p_i - p_d_i| - collision [clearance_i < -tol] - effort |a_i|^2 / 2
          - correction c_i + goal_bonus [|p_i - goal_i| < goal_tolerance]

* **Tracking** (1): the reference ``p_d_i(t)`` slides along the straight line
  to the goal and rests there, so following it brings the robot home.
* **Goal bonus** (0.5 within ``goal_tolerance`` 0.1 m, the evaluation's success radius).
* **Collision** (1 per decision in overlap): the env's default 10 drowns the
  tracking signal in collisions a robot cannot avoid alone, and the MLP does
  not learn.  Safety is the filter's job; with ``terminate_on_collision`` a
  colliding robot's episode ends instead (its slot is padding until its team
  resets, and :class:`train.ppo.SlotPPO` never trains on padding).
* **Effort** (0.01): breaks ties towards smooth accelerations.
* **Filter correction** (``correction``, only with ``filter=True``; 0 by
  default): ``|du_safe - du_nominal| / max_wheel_accel``, the largest change
  the filter made to the robot's nominal in the decision; it asks the policy to
  propose what the filter accepts.

``policy_prior = "tracking"`` (:class:`agents.prior.TrackingPriorPolicy`,
``train/configs/random_goals_6r_prior.toml``) starts from the paper's tracking
law as a trainable linear layer plus an MLP residual: it behaves like the
tracking law from the first step and PPO changes it little, so it is a
baseline, not a policy learned from scratch.

Telemetry (:mod:`train.telemetry`): per rollout, success rate, tracking error,
collisions, filter intervention rate and mean correction go to TensorBoard
(``metrics/``), to ``metrics.csv`` and to the progress line;
``learning_curve.png`` is drawn at the end.

Outputs in the run folder ``<out_dir>/<run_name>``: ``model.zip`` (SB3 PPO),
``policy.json`` (env keywords, filter configuration, policy class: what
:class:`agents.learned.LearnedAgent` needs), ``normalization.npz`` (observation
statistics as plain arrays; nothing is pickled), ``config.json`` (the
:class:`~train.config.TrainConfig`), ``metrics.csv``, ``learning_curve.png``,
``train_stats.json`` (wall time, throughput, which backup-layer implementation the filter ran;
written last: it marks a finished run),
``checkpoints/`` and ``tb/``.  A run that fails is removed, or kept with an ``INCOMPLETE``
file where it already holds a model or checkpoint (:func:`train`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from aasoatt_env.api.factory import make_env as make_aasoatt_env
from aasoatt_env.cli_support import OutputPlan, Parser, add_common_options, run_guarded
from aasoatt_env.errors import ConfigError
from agents.learned import POLICY_ENV_KEYS, POLICY_FILE, stats_path
from train.config import (
    BACKENDS,
    INCOMPLETE_FILE,
    TrainConfig,
    abandon_run,
    add_config_arguments,
    claim_run_dir,
    config_from_args,
    split_backend,
)
from train.rllib import main as rllib_main
from train.telemetry import TelemetryCallback, plot_learning_curve

__all__ = ["INCOMPLETE_FILE", "check_device", "check_init_from", "main", "make_env", "make_vec_env", "train"]


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


def make_vec_env(config: TrainConfig, training: bool = True, group_filter: bool = True) -> Any:
    """``SlotNormalize?(SlotMonitor(BatchedVecEnv))`` over ``config.n_envs`` teams stepped together.

    With ``config.num_workers > 1`` the teams are stepped in that many processes
    (:class:`~aasoatt_env.sim.sharded.ShardedBatchedEnv`); close the returned env to stop them.

    :class:`~train.vec_env.SlotMonitor` and :class:`~train.vec_env.SlotNormalize` are SB3's
    ``VecMonitor`` and ``VecNormalize`` that skip dead-slot padding (``terminate_on_collision``).
    Behind the filter all teams share one filter call per physics step unless ``group_filter=False``
    (:class:`~aasoatt_env.sim.batched.BatchedAASOATTEnv`).
    """
    from aasoatt_env.sim.batched import BatchedAASOATTEnv
    from train.vec_env import BatchedVecEnv, SlotMonitor, SlotNormalize, VelocityTrackingShaping

    fns = [lambda: make_env(config) for _ in range(config.n_envs)]
    if config.num_workers > 1:
        from aasoatt_env.sim.sharded import ShardedBatchedEnv

        batch: Any = ShardedBatchedEnv(fns, config.num_workers, group_filter=group_filter)
    else:
        batch = BatchedAASOATTEnv(fns, group_filter=group_filter)
    venv: Any = BatchedVecEnv(batch, success_radius=config.reward.get("goal_tolerance", 0.1))
    if config.velocity_tracking:
        venv = VelocityTrackingShaping(venv, config.velocity_tracking)
    venv = SlotMonitor(venv)
    if config.normalize_obs or config.normalize_reward:
        venv = SlotNormalize(
            venv, training=training, norm_obs=config.normalize_obs, norm_reward=config.normalize_reward,
            gamma=config.gamma, clip_obs=10.0,
        )
    return venv


def _run_dir(config: TrainConfig) -> tuple[Path, bool]:
    """A new run folder ``<out_dir>/<name>`` (``_2``, ``_3``, ... when taken) and whether it was created.

    Claimed with its ``INCOMPLETE`` file (:func:`train.config.claim_run_dir`): earlier runs are kept.
    """
    name = config.run_name or (
        f"ppo_{config.scenario}_{config.num_robots}r_{'filter' if config.filter else 'bare'}_s{config.seed}"
    )
    OutputPlan(overwrite=True).folder(config.out_dir, "TrainConfig.out_dir")  # creatable and writable, or say why
    try:
        return claim_run_dir(config.out_dir, name)
    except OSError as exc:
        raise ConfigError(f"TrainConfig.out_dir: cannot create a run folder in {config.out_dir} "
                          f"({exc.strerror or exc})") from None


def build_model(config: TrainConfig, venv: Any, tensorboard_log: str | None = None) -> Any:
    """The PPO of ``config`` on ``venv`` (:class:`train.ppo.SlotPPO`; seeded: it seeds torch, numpy and the env)."""
    import torch

    from train.ppo import SlotPPO

    torch.set_num_threads(config.torch_threads)
    policy: Any = "MlpPolicy"
    policy_kwargs: dict[str, Any] = dict(net_arch=list(config.net_arch), log_std_init=config.log_std_init)
    if config.policy_prior == "tracking":
        from agents.prior import TrackingPriorPolicy, tracking_prior_matrix

        k3, k4 = config.prior_gains
        policy = TrackingPriorPolicy
        policy_kwargs["prior_matrix"] = tracking_prior_matrix(
            int(np.prod(venv.observation_space.shape)), k3, k4, _prior_max_accel(config)).tolist()
    return SlotPPO(
        policy, venv,
        learning_rate=config.learning_rate, n_steps=config.n_steps, batch_size=config.batch_size,
        n_epochs=config.n_epochs, gamma=config.gamma, gae_lambda=config.gae_lambda,
        clip_range=config.clip_range, ent_coef=config.ent_coef, vf_coef=config.vf_coef,
        max_grad_norm=config.max_grad_norm,
        policy_kwargs=policy_kwargs,
        tensorboard_log=tensorboard_log, seed=config.seed, device=config.device, verbose=config.verbose,
    )


def _prior_max_accel(config: TrainConfig) -> float:
    """The team-wide ``max_point_accel`` the tracking prior needs (ConfigError if the robots differ)."""
    probe = make_env(config, filter=False)
    probe.reset(seed=0)
    amax = np.asarray(probe.unwrapped.team.max_point_accel, dtype=float)
    probe.close()
    if not np.allclose(amax, amax[0]):
        raise ConfigError("TrainConfig.policy_prior: got robots with different max_point_accel, "
                          "expected one team-wide value for the shared tracking prior")
    return float(amax[0])


def _available_devices(torch: Any) -> list[str]:
    devices = ["auto", "cpu"]
    if torch.cuda.is_available():
        devices += ["cuda"] + [f"cuda:{i}" for i in range(torch.cuda.device_count())]
    mps = getattr(torch.backends, "mps", None)
    if mps is not None and mps.is_available():
        devices.append("mps")
    return devices


def check_device(device: Any) -> None:
    """Raise :class:`ConfigError` unless ``device`` is a torch device that exists on this machine.

    ``"auto"`` (Stable-Baselines3: the GPU if there is one) and ``"cpu"`` always pass; ``"cuda"``,
    ``"cuda:<i>"`` and ``"mps"`` only where that device is present (SB3 would silently train on
    the CPU instead of a missing GPU, and config.json would record the GPU).

    Parameters
    ----------
    device : str
        :attr:`TrainConfig.device` (``--device``).

    Raises
    ------
    ConfigError
        Naming ``--device``, the value and the devices available here.
    """
    if device in ("auto", "cpu"):
        return  # (without importing torch: bad options elsewhere are reported at once)
    import torch

    available = _available_devices(torch)
    ok = False
    if isinstance(device, str):
        try:
            dev = torch.device(device)
        except (RuntimeError, ValueError, TypeError):
            dev = None
        if dev is not None:
            if dev.type == "cpu":
                ok = dev.index in (None, 0)
            elif dev.type == "cuda":
                ok = torch.cuda.is_available() and (dev.index or 0) < torch.cuda.device_count()
            elif dev.type == "mps":
                ok = "mps" in available and dev.index in (None, 0)
    if not ok:
        raise ConfigError(f"TrainConfig.device (--device): got {device!r}, expected a torch device available "
                          f"here, one of {available}")


def _env_defaults() -> dict[str, Any]:
    import inspect

    from aasoatt_env.sim.env import AASOATTParallelEnv

    params = inspect.signature(AASOATTParallelEnv.__init__).parameters
    return {k: p.default for k, p in params.items() if p.default is not inspect.Parameter.empty}


def check_init_from(config: TrainConfig, source: Any, obs_shape: tuple[int, ...] | None = None) -> None:
    """Raise :class:`ConfigError` unless the policy of the run ``config.init_from`` fits ``config``.

    The loaded policy depends on the action mode (what its outputs mean), the observation layout
    (``num_neighbors``, ``num_obstacles``, ``sensing_range``), the decision period
    (``decision_interval``, ``dt``), its class (``policy_prior``), ``net_arch`` and whether its
    observations are normalised (``normalize_obs``): each must be as in the run it comes from.

    Parameters
    ----------
    config : TrainConfig
        The run to start.
    source : agents.learned.LearnedAgent
        The loaded ``config.init_from`` run.
    obs_shape : tuple of int, optional
        Observation shape of ``config``'s env (checked against the policy's when given).

    Raises
    ------
    ConfigError
        One line naming every differing setting, with this run's value and the init_from run's.
    """
    theirs_env = source.spec.get("env", {})
    mine_env = config.env_kwargs()
    defaults = _env_defaults()
    diffs: list[tuple[str, Any, Any]] = []
    for key in POLICY_ENV_KEYS:
        if key not in theirs_env and key not in mine_env:
            continue
        theirs, mine = theirs_env.get(key, defaults.get(key)), mine_env.get(key, defaults.get(key))
        if theirs != mine:
            diffs.append((key, mine, theirs))
    their_prior = {"TrackingPriorPolicy": "tracking", "MlpPolicy": "none"}.get(source.spec.get("policy"),
                                                                             source.spec.get("policy"))
    if their_prior != config.policy_prior:
        diffs.append(("policy_prior", config.policy_prior, their_prior))
    their_arch = getattr(source.model, "policy_kwargs", {}).get("net_arch")
    if their_arch is not None and list(their_arch) != list(config.net_arch):
        diffs.append(("net_arch", list(config.net_arch), list(their_arch)))
    if (source.obs_stats is not None) != config.normalize_obs:
        diffs.append(("normalize_obs", config.normalize_obs, source.obs_stats is not None))
    their_shape = tuple(source.model.observation_space.shape)
    if obs_shape is not None and not diffs and tuple(obs_shape) != their_shape:
        diffs.append(("observation shape", tuple(obs_shape), their_shape))
    if diffs:
        shown = "; ".join(f"{k}: got {mine!r}, the init_from run has {theirs!r}" for k, mine, theirs in diffs)
        raise ConfigError(f"TrainConfig.init_from: {config.init_from} was trained with other settings that its "
                          f"policy depends on ({shown}); expected the same settings as that run")


def init_policy(model: Any, venv: Any, config: TrainConfig, source: Any = None) -> None:
    """Start ``model`` from the run ``config.init_from``: its policy weights and observation statistics.

    Loaded without unpickling (:class:`agents.learned.LearnedAgent`, or ``source`` if already loaded)
    and checked with :func:`check_init_from`; the reward statistics start afresh.
    """
    import torch

    from agents.learned import LearnedAgent

    if source is None:
        source = LearnedAgent.load(config.init_from)  # type: ignore[arg-type]
    check_init_from(config, source, tuple(venv.observation_space.shape))
    state = source.model.policy.state_dict()
    mine = model.policy.state_dict()
    if set(state) != set(mine) or any(state[k].shape != mine[k].shape for k in mine):
        raise ConfigError(f"TrainConfig.init_from: {config.init_from} has another network (net_arch or observation "
                          f"layout), expected net_arch {config.net_arch} and observations of shape "
                          f"{tuple(venv.observation_space.shape)}")
    with torch.no_grad():
        model.policy.load_state_dict(state)
    if source.obs_stats is not None:
        mean, var, _, _ = source.obs_stats
        count = _stats_count(config.init_from)
        rms = venv.obs_rms
        rms.mean, rms.var, rms.count = mean.copy(), var.copy(), count


def _stats_count(path: str | None) -> float:
    from agents.learned import stats_path

    p = Path(path or "")
    p = p / "model.zip" if p.is_dir() else p
    with np.load(stats_path(p), allow_pickle=False) as z:
        return float(z["count"]) if "count" in z else 1e4


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


def _preflight(config: TrainConfig) -> Any:
    """Check everything training needs before a run folder is made; the loaded ``init_from`` run (or None).

    The device (:func:`check_device`), the env and filter settings, the tracking prior's team,
    and the run to start from (:func:`check_init_from`).
    """
    check_device(config.device)
    probe = make_env(config)
    base = probe.unwrapped
    obs_shape = tuple(base.observation_space(base.possible_agents[0]).shape)
    probe.close()
    if config.policy_prior == "tracking":
        _prior_max_accel(config)
    if config.init_from is None:
        return None
    from agents.learned import LearnedAgent

    source = LearnedAgent.load(config.init_from)
    check_init_from(config, source, obs_shape)
    return source


def _abandon(run: Path, created: bool) -> None:
    """After a failed training: remove ``run`` unless it holds a model (then it stays, marked incomplete)."""
    abandon_run(run, keep=(run / "model.zip").is_file() or any((run / "checkpoints").glob("*.zip")), created=created)


def train(config: TrainConfig) -> Path:
    """Train PPO as configured and return the path of the saved ``model.zip``.

    Everything is checked before the run folder is made (:func:`check_device`, the env and
    filter, :func:`check_init_from`).  While training, the run folder holds an
    ``INCOMPLETE`` file (:data:`INCOMPLETE_FILE`), removed once every output is written.
    If training fails or is interrupted, the run folder is removed, unless it already
    holds a model or checkpoint: then it is kept, with its ``INCOMPLETE`` file, and never
    has a ``train_stats.json`` (what marks a finished run).

    Parameters
    ----------
    config : TrainConfig
        Validated configuration.

    Returns
    -------
    Path
        ``<run>/model.zip``; the run folder also holds ``policy.json``,
        ``normalization.npz`` (when normalising observations), ``config.json``,
        ``train_stats.json``, ``checkpoints/`` and ``tb/``.

    Raises
    ------
    ConfigError
        A setting, the device or the ``init_from`` run does not fit (before any folder is made).
    """
    source = _preflight(config)
    run, created = _run_dir(config)
    marker = run / INCOMPLETE_FILE
    try:
        (run / "config.json").write_text(json.dumps(config.to_dict(), indent=2))
        (run / POLICY_FILE).write_text(json.dumps(run_spec(config), indent=2))
        venv = make_vec_env(config)
        try:
            model, telemetry, elapsed = _learn(config, run, venv, source)
        finally:
            venv.close()  # (stops the worker processes of num_workers > 1 on every way out)
        if telemetry.history:
            try:
                plot_learning_curve({config.run_name or run.name: [telemetry.history]}, run / "learning_curve.png",
                                    title=f"{config.scenario}, {config.num_robots} robots, "
                                    f"{'behind the filter' if config.filter else 'bare'}, seed {config.seed}")
            except ImportError:  # matplotlib is an optional extra (render/repro)
                pass
        last = telemetry.history[-1] if telemetry.history else {}
        (run / "train_stats.json").write_text(json.dumps(
            {"wall_time_s": elapsed, "agent_steps": int(model.num_timesteps),
             "agent_steps_per_s": model.num_timesteps / max(elapsed, 1e-9),
             "filter_kernel": _filter_kernel(config),
             "last_rollout": {k: v for k, v in last.items()
                              if isinstance(v, (int, float)) and math.isfinite(v)}},
            indent=2, allow_nan=False))
    except BaseException:
        _abandon(run, created)
        raise
    marker.unlink()
    return run / "model.zip"


def _filter_kernel(config: TrainConfig) -> str | None:
    """Which backup-layer implementation the training filter ran (``kernel="auto"`` resolved), or None bare."""
    if not config.filter:
        return None
    from aasoatt_env.safety.config import FilterConfig

    return "numba" if FilterConfig.merged(config.filter_kwargs).compiled else "numpy"


def _learn(config: TrainConfig, run: Path, venv: Any, source: Any) -> tuple[Any, Any, float]:
    """Build the PPO on ``venv``, learn, save the model and statistics into ``run``: ``(model, telemetry, wall s)``."""
    model = build_model(config, venv, str(run / "tb") if config.tensorboard else None)
    if config.init_from is not None:
        init_policy(model, venv, config, source)
    rollouts = max(1, -(-config.total_timesteps // (config.n_steps * venv.num_envs)))
    telemetry = TelemetryCallback(run / "metrics.csv", config.total_timesteps,
                                  print_every=max(1, rollouts // 20) if config.progress_bar else 0,
                                  success_radius=config.reward.get("goal_tolerance", 0.1))
    callbacks: list[Any] = [telemetry]
    if config.checkpoint_freq:
        callbacks.append(_checkpoint_callback(run / "checkpoints", max(1, config.checkpoint_freq // venv.num_envs),
                                              config.normalize_obs))
    if config.progress_bar:
        workers = f", {config.num_workers} worker processes" if config.num_workers > 1 else ""
        print(f"training {run} ({config.total_timesteps:,} agent-steps, {config.n_envs} envs x "
              f"{config.num_robots} robots{workers}, {'behind the filter' if config.filter else 'bare'})", flush=True)
    t0 = time.perf_counter()
    model.learn(total_timesteps=config.total_timesteps, callback=callbacks, tb_log_name="ppo")
    elapsed = time.perf_counter() - t0
    model.save(run / "model.zip")
    if config.normalize_obs:
        save_stats(venv, stats_path(run / "model.zip"))
    return model, telemetry, elapsed


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
