"""What a PPO run is built from: its envs, its model, its device and the run it starts from.

:func:`make_vec_env` and :func:`build_model` build what :func:`train.train.train` trains;
:func:`check_device` and :func:`check_init_from` check, before a run folder is made, what would
otherwise fail (or silently differ) later; :func:`save_model` and :func:`save_stats` write a
model and its statistics atomically.
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from aasoatt_env.api.factory import make_env as make_aasoatt_env
from aasoatt_env.errors import ConfigError, DataFileError
from agents.learned import POLICY_ENV_KEYS, read_stats, stats_path
from agents.run_spec import RECORD_ENTRY, record_bytes
from agents.sb3_model import check_parameter_count, parameter_count
from train.config import TrainConfig
from train.runs import atomic_path, save_npz

__all__ = ["build_model", "check_device", "check_init_from", "check_network", "init_policy", "make_env",
           "make_vec_env", "run_spec", "save_model", "save_stats"]


def make_env(config: TrainConfig, filter: bool | None = None, **env_overrides: Any) -> Any:
    """One parallel env of ``config``, behind the filter if ``filter`` (default ``config.filter``)."""
    use_filter = config.filter if filter is None else filter
    return make_aasoatt_env(**{**config.env_kwargs(), **env_overrides},
                            filter=config.filter_config() if use_filter else None)


def run_spec(config: TrainConfig) -> dict[str, Any]:
    """The ``policy.json`` of a run: what :class:`agents.learned.LearnedAgent` needs to rebuild the policy's env."""
    import dataclasses

    return {
        "format": 1,
        "env": config.env_kwargs(),
        "filter": dataclasses.asdict(config.filter_config()) if config.filter else None,
        "policy": "TrackingPriorPolicy" if config.policy_prior == "tracking" else "MlpPolicy",
        "normalize_obs": bool(config.normalize_obs),
    }


def save_model(model: Any, path: Path, spec: dict[str, Any]) -> Path:
    """``model.save`` to ``path`` atomically, with the policy record of ``spec`` inside the zip."""
    with atomic_path(path, suffix=".zip") as tmp:
        model.save(tmp)
        with zipfile.ZipFile(tmp, "a") as archive:
            archive.writestr(RECORD_ENTRY, record_bytes(spec))
    return path


def save_stats(venv: Any, path: Path) -> None:
    """``VecNormalize``'s running statistics as plain arrays (``normalization.npz``), atomically.

    Observation statistics (``mean``, ``var``, ``count``, ``clip_obs``, ``epsilon``) when it
    normalises observations, return statistics (``ret_mean``, ``ret_var``, ``ret_count``: to resume)
    when it normalises rewards.
    """
    arrays: dict[str, np.ndarray] = {}
    if venv.norm_obs:
        rms = venv.obs_rms
        arrays.update(mean=np.asarray(rms.mean, np.float64), var=np.asarray(rms.var, np.float64),
                      count=np.asarray(rms.count, np.float64), clip_obs=np.asarray(venv.clip_obs, np.float64),
                      epsilon=np.asarray(venv.epsilon, np.float64))
    if venv.norm_reward:
        ret = venv.ret_rms
        arrays.update(ret_mean=np.asarray(ret.mean, np.float64).reshape(()),
                      ret_var=np.asarray(ret.var, np.float64).reshape(()),
                      ret_count=np.asarray(ret.count, np.float64))
    save_npz(path, **arrays)


def load_stats(venv: Any, path: Path) -> None:
    """Set ``venv``'s running statistics from a ``normalization.npz`` (checked: shapes, finite, ranges)."""
    obs_dim = int(np.prod(venv.observation_space.shape))
    arrays = read_stats(path, obs_dim, need_obs=bool(venv.norm_obs))
    if venv.norm_obs:
        rms = venv.obs_rms
        rms.mean, rms.var = arrays["mean"].copy(), arrays["var"].copy()
        rms.count = float(arrays.get("count", np.float64(1e4)))
    if venv.norm_reward and "ret_var" in arrays:
        ret = venv.ret_rms
        ret.mean, ret.var = float(arrays["ret_mean"]), float(arrays["ret_var"])
        ret.count = float(arrays.get("ret_count", np.float64(1e4)))


def make_vec_env(config: TrainConfig, training: bool = True, group_filter: bool = True) -> Any:
    """``SlotNormalize?(SlotMonitor(BatchedVecEnv))`` over ``config.n_envs`` teams stepped together.

    With ``config.num_workers > 1`` the teams are stepped in that many processes
    (:class:`~aasoatt_env.sim.sharded.ShardedBatchedEnv`); close the returned env to stop them.
    :class:`~train.vec_env.SlotMonitor` and :class:`~train.vec_env.SlotNormalize` are SB3's
    ``VecMonitor`` and ``VecNormalize`` that skip dead-slot padding (``terminate_on_collision``).
    Behind the filter all teams share one filter call per physics step unless ``group_filter=False``.
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
        venv = SlotNormalize(venv, training=training, norm_obs=config.normalize_obs,
                             norm_reward=config.normalize_reward, gamma=config.gamma, clip_obs=10.0)
    return venv


def check_network(config: TrainConfig, obs_dim: int) -> None:
    """Refuse a ``net_arch`` whose network would exceed the loaders' parameter bound (before it is built)."""
    n = parameter_count(obs_dim, 2, list(config.net_arch), prior=config.policy_prior == "tracking")
    try:
        check_parameter_count(n, "TrainConfig.net_arch")
    except DataFileError as exc:
        raise ConfigError(f"{exc} (a run must be loadable)") from None


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
            int(np.prod(venv.observation_space.shape)), k3, k4, prior_max_accel(config)).tolist()
    return SlotPPO(
        policy, venv,
        learning_rate=config.learning_rate, n_steps=config.n_steps, batch_size=config.batch_size,
        n_epochs=config.n_epochs, gamma=config.gamma, gae_lambda=config.gae_lambda,
        clip_range=config.clip_range, ent_coef=config.ent_coef, vf_coef=config.vf_coef,
        max_grad_norm=config.max_grad_norm, policy_kwargs=policy_kwargs,
        tensorboard_log=tensorboard_log, seed=config.seed, device=config.device, verbose=config.verbose,
    )


def prior_max_accel(config: TrainConfig) -> float:
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

    ``"auto"`` (the GPU if there is one) and ``"cpu"`` always pass; ``"cuda"``, ``"cuda:<i>"`` and
    ``"mps"`` only where that device is present (SB3 would silently train on the CPU instead of a
    missing GPU, and config.json would record the GPU).
    """
    if device in ("auto", "cpu"):
        return  # (without importing torch: bad options elsewhere are reported at once)
    import torch

    available = _available_devices(torch)
    ok = False
    if isinstance(device, str) and "\x00" not in device:
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


def check_init_from(config: TrainConfig, source: Any, obs_shape: tuple[int, ...] | None = None,
                    field: str = "init_from") -> None:
    """Raise :class:`ConfigError` unless the policy of the run ``source`` fits ``config``.

    The loaded policy depends on the action mode, the observation layout (``num_neighbors``,
    ``num_obstacles``, ``sensing_range``), the decision period (``decision_interval``, ``dt``),
    its class (``policy_prior``), ``net_arch`` and ``normalize_obs``: each must be as in the
    run it comes from.  ``field`` names the option (``init_from`` or ``resume``).
    """
    theirs_env, mine_env, defaults = source.spec.get("env", {}), config.env_kwargs(), _env_defaults()
    diffs: list[tuple[str, Any, Any]] = []
    for key in POLICY_ENV_KEYS:
        if key in theirs_env or key in mine_env:
            theirs, mine = theirs_env.get(key, defaults.get(key)), mine_env.get(key, defaults.get(key))
            if theirs != mine:
                diffs.append((key, mine, theirs))
    their_prior = {"TrackingPriorPolicy": "tracking", "MlpPolicy": "none"}.get(source.spec.get("policy"))
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
        shown = "; ".join(f"{k}: got {mine!r}, the {field} run has {theirs!r}" for k, mine, theirs in diffs)
        raise ConfigError(f"TrainConfig.{field}: {getattr(config, field)} was trained with other settings that its "
                          f"policy depends on ({shown}); expected the same settings as that run")


def init_policy(model: Any, venv: Any, config: TrainConfig, source: Any = None) -> None:
    """Start ``model`` from the run ``config.init_from``: its policy weights and observation statistics.

    Loaded by :class:`agents.learned.LearnedAgent` (or ``source`` if already loaded) and checked with
    :func:`check_init_from`; the reward statistics start afresh.
    """
    import torch

    from agents.learned import LearnedAgent

    if source is None:
        source = LearnedAgent.load(config.init_from)  # type: ignore[arg-type]
    check_init_from(config, source, tuple(venv.observation_space.shape))
    with torch.no_grad():
        model.policy.load_state_dict(source.model.policy.state_dict())
    if source.obs_stats is not None:
        mean, var, _, _ = source.obs_stats
        rms = venv.obs_rms
        rms.mean, rms.var = mean.copy(), var.copy()
        stats = read_stats(stats_path(source.model.path), mean.shape[0])
        rms.count = float(stats.get("count", np.float64(1e4)))
