"""``TrainConfig``: every knob of a PPO run, from a TOML/JSON file and the command line.

Precedence: dataclass defaults < the resumed run's ``config.json`` (``--resume``) < config file
(``--config run.toml`` or ``.json``) < command-line flags (:mod:`train.options`).  The configuration
is validated once, in ``__post_init__``, before anything is built or written; every error is a
:class:`~aasoatt_env.errors.ConfigError` of the form ``"TrainConfig.<field>: got X, expected Y"``.

Every size a user chooses has an upper bound (:data:`LIMITS`), so a typo cannot start a run
that exhausts memory or never ends: teams, robots per batch, agent-steps, rollout length and
buffer, epochs, workers, held-out episodes, and the filter's ``neural_iterations``.

The defaults of :class:`TrainConfig` are the recipe that learns from scratch
(``train/configs/random_goals_6r.toml``): a plain MLP, observations and rewards normalised, point
actions, 32 envs x 6 robots, 1.23M agent-steps.  ``reward`` entries are laid over the recipe's
reward (:data:`TRAIN_REWARD`), key by key, wherever they come from.

:class:`EnvConfig` holds the env and filter fields that every training backend shares:
:class:`TrainConfig` (Stable-Baselines3) and :class:`train.rllib.RLlibConfig` (Ray RLlib) extend it.

Example ``run.toml``::

    scenario = "random_goals"
    num_robots = 6
    total_timesteps = 1_500_000
    filter = true
    [reward]
    correction = 0.5
    [filter_kwargs]
    barrier = "aasoatt"
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field, fields
from typing import Any

from aasoatt_env import validation as check
from aasoatt_env.errors import ConfigError
from aasoatt_env.safety.config import FilterConfig
from aasoatt_env.sim.rewards import RewardConfig
from aasoatt_env.sim.scenarios import SCENARIOS
from agents.sb3_model import MAX_LAYER_SIZE, MAX_LAYERS
from train.runs import INCOMPLETE_FILE, abandon_run, check_name, check_path, claim_run_dir, unique_run_dir

__all__ = ["BACKENDS", "HELDOUT_SEED", "INCOMPLETE_FILE", "LIMITS", "TRAIN_REWARD", "EnvConfig", "TrainConfig",
           "abandon_run", "add_config_arguments", "claim_run_dir", "config_from_args", "load_config_file",
           "parse_config", "split_backend", "unique_run_dir"]

_ACTION_MODES = ("wheel", "point")

TRAIN_REWARD: dict[str, float] = {"tracking": 1.0, "collision": 1.0, "effort": 0.01, "goal_bonus": 0.5,
                                   "goal_tolerance": 0.1}
"""The reward of the default recipe (:class:`TrainConfig`); ``reward`` entries replace these key by key.

``collision`` 1 rather than the env's 10: with 10, collisions a robot cannot avoid alone (others drive
into it) drown the tracking signal and a plain MLP does not learn (``docs/technical_brief.md`` section 10).
``goal_tolerance`` 0.1 m is the evaluation's success radius."""

BACKENDS = ("sb3", "rllib")
"""``aasoatt train --backend``: ``sb3`` (:mod:`train.train`, the default) or ``rllib`` (:mod:`train.rllib`)."""

LIMITS: dict[str, int] = {
    "seed": 2**31 - 1,              # training reset seeds stay below 2**32 (HELDOUT_SEED)
    "teams": 4096,                  # n_envs, RLlib's teams per env runner
    "slots": 1 << 16,               # robots stepped together: n_envs * num_robots
    "agent_steps": 10**10,          # total_timesteps, checkpoint_freq, eval_every
    "n_steps": 1 << 16,             # rollout length per slot
    "rollout": 1 << 21,             # rollout buffer (n_steps * slots; RLlib's train_batch_size)
    "epochs": 1000,                 # n_epochs, num_epochs
    "workers": 256,                 # num_workers, torch_threads, RLlib's runners and learners
    "episodes": 10_000,             # eval_episodes
    "neural_iterations": 1000,      # filter_kwargs.neural_iterations while training
    "iterations": 100_000,          # RLlib's iterations, checkpoint_every
}
"""Upper bounds of every size a user chooses (checked before anything is built)."""

HELDOUT_SEED = 2**32
"""First seed of the held-out evaluation episodes during training (episode ``j``: ``HELDOUT_SEED + j``).
Training resets draw from seeds below ``2**32`` (``seed`` <= ``LIMITS["seed"]``), so the two never meet."""


@dataclass
class EnvConfig:
    """The env and safety-filter fields of a training run (shared by every backend).

    Attributes
    ----------
    scenario : str
        Scenario name (``aasoatt_env.sim.scenarios.SCENARIOS``).
    num_robots : int
        Robots per env (one policy slot each).
    scenario_kwargs : dict
        Extra scenario parameters (``arena_size``, ``speed``, ...).
    dt : float
        Physics step [s] (0.005: the 200 Hz of the filter); the filter runs at this step.
    decision_interval : int
        Physics steps per policy decision (20: the policy acts at 10 Hz).
    action_mode : {"point", "wheel"}
        ``"point"``: actions are normalised control-point accelerations
        (easier to learn); ``"wheel"``: normalised wheel accelerations.
    num_neighbors, num_obstacles : int
        Observation slots.
    terminate_on_collision : bool
        End a robot's episode when it collides (see :mod:`train.vec_env`).
    max_steps : int or None
        Override of the episode horizon in env steps.
    reward : dict
        :class:`~aasoatt_env.sim.env.RewardConfig` fields.
    filter : bool
        Train behind :class:`~aasoatt_env.safety.wrapper.AASOATTFilter`.
    filter_kwargs : dict
        Arguments of the filter (``barrier``, ``deadlock``, ``solver``, gains); its ``dt`` is
        ``dt`` (a different one is refused), ``neural_iterations`` at most
        ``LIMITS["neural_iterations"]``.
    """

    scenario: str = "random_goals"
    num_robots: int = 6
    scenario_kwargs: dict[str, Any] = field(default_factory=dict)
    dt: float = 0.005
    decision_interval: int = 20
    action_mode: str = "point"
    num_neighbors: int = 4
    num_obstacles: int = 2
    terminate_on_collision: bool = False
    max_steps: int | None = None
    reward: dict[str, float] = field(default_factory=dict)
    filter: bool = False
    filter_kwargs: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._validate()

    # ------------------------------------------------------------------ validation
    def _name(self, name: str) -> str:
        return f"{type(self).__name__}.{name}"

    def _err(self, name: str, expected: str) -> ConfigError:
        return ConfigError(f"{self._name(name)}: got {check.short_repr(getattr(self, name))}, expected {expected}")

    def _net_arch(self) -> None:
        """``net_arch``: 1 to ``MAX_LAYERS`` sizes in ``[1, MAX_LAYER_SIZE]`` (what the loaders accept)."""
        arch = self.net_arch  # type: ignore[attr-defined]
        if not (isinstance(arch, (list, tuple)) and 1 <= len(arch) <= MAX_LAYERS
                and all(isinstance(h, int) and not isinstance(h, bool) and 1 <= h <= MAX_LAYER_SIZE for h in arch)):
            raise self._err("net_arch", f"a list of 1 to {MAX_LAYERS} layer sizes in [1, {MAX_LAYER_SIZE}] (a run "
                            "must be loadable)")
        self.net_arch = list(arch)  # type: ignore[attr-defined]

    def _int(self, name: str, lo: int, hi: int) -> None:
        """An integer in ``[lo, hi]`` (integral floats and numpy integers as every other integer)."""
        try:
            value = check.integer(self._name(name), getattr(self, name))
        except ConfigError:
            value = None
        if value is None or not lo <= value <= hi:
            raise self._err(name, f"an integer in [{lo}, {hi}]")
        setattr(self, name, value)

    def _float(self, name: str, lo: float, hi: float, lo_open: bool = False) -> None:
        setattr(self, name, check.real(self._name(name), getattr(self, name), lo=lo, hi=hi, lo_open=lo_open))

    def _bools(self, *names: str) -> None:
        for name in names:
            if not isinstance(getattr(self, name), bool):
                raise self._err(name, "true or false")

    def _validate(self) -> None:
        self._validate_env()

    def _validate_env(self) -> None:
        """Validate the env and filter fields."""
        if not isinstance(self.scenario, str) or self.scenario not in SCENARIOS:
            raise self._err("scenario", f"one of {sorted(SCENARIOS)}")
        self._int("num_robots", 1, LIMITS["slots"])
        self._int("decision_interval", 1, 10_000)
        for name in ("num_neighbors", "num_obstacles"):
            self._int(name, 0, 256)
        if self.max_steps is not None:
            self._int("max_steps", 1, 10**7)
        self._float("dt", 0.0, 1.0, lo_open=True)
        if self.action_mode not in _ACTION_MODES:
            raise self._err("action_mode", f"one of {list(_ACTION_MODES)}")
        self._bools("terminate_on_collision", "filter")
        for name in ("scenario_kwargs", "reward", "filter_kwargs"):
            if not isinstance(getattr(self, name), dict):
                raise self._err(name, "a table/dict")
        try:
            RewardConfig.coerce(self.reward)
        except TypeError:
            known = [f.name for f in fields(RewardConfig)]
            unknown = sorted(set(self.reward) - set(known))
            raise ConfigError(f"{self._name('reward')}: got unknown key(s) {unknown}, expected keys among "
                              f"{known}") from None
        self._validate_filter()
        if self.reward.get("correction", 0.0) and not self.filter:
            raise ConfigError(f"{self._name('reward')}: got correction={self.reward['correction']!r} with "
                              "filter=False, expected filter=True (the correction penalty needs the filter)")

    def _validate_filter(self) -> None:
        """``filter_kwargs``: a valid filter at the env's ``dt``, ``neural_iterations`` bounded for training."""
        where = self._name("filter_kwargs")
        fk = self.filter_kwargs
        if "dt" in fk and fk["dt"] != self.dt:
            raise ConfigError(f"{where}.dt: got {check.short_repr(fk['dt'])}, expected the env's dt = {self.dt!r} (the "
                              "filter runs at every physics step; set dt instead)")
        try:
            fc = self.filter_config()
        except (TypeError, ConfigError) as exc:
            raise ConfigError(f"{where}: {exc}") from None
        if fc.neural_iterations > LIMITS["neural_iterations"]:
            raise ConfigError(f"{where}.neural_iterations: got {fc.neural_iterations}, expected at most "
                              f"{LIMITS['neural_iterations']} while training (each iteration is paid at every "
                              "physics step)")

    def _validate_run_folder(self) -> None:
        self.out_dir = check_path(self.out_dir, self._name("out_dir"))  # type: ignore[attr-defined]
        if self.run_name is not None:  # type: ignore[attr-defined]
            check_name(self.run_name, self._name("run_name"))  # type: ignore[attr-defined]

    # ------------------------------------------------------------------ helpers
    def env_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of :class:`~aasoatt_env.sim.env.AASOATTParallelEnv` for this run."""
        kw: dict[str, Any] = dict(
            scenario=self.scenario, dt=self.dt, decision_interval=self.decision_interval,
            action_mode=self.action_mode, num_neighbors=self.num_neighbors, num_obstacles=self.num_obstacles,
            reward=dict(self.reward), terminate_on_collision=self.terminate_on_collision,
            max_steps=self.max_steps, num_robots=self.num_robots, **self.scenario_kwargs,
        )
        return kw

    def filter_config(self) -> FilterConfig:
        """The safety filter's configuration (``filter_kwargs`` at this run's ``dt``)."""
        return FilterConfig.merged({**self.filter_kwargs, "dt": self.dt})

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON dict of every field."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Any:
        """Build from a dict, rejecting unknown keys."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(str(k) for k in set(data) - known)
        if unknown:
            raise ConfigError(f"{cls.__name__}: got unknown key(s) {unknown}, expected keys among {sorted(known)}")
        return cls(**data)

    @classmethod
    def from_file(cls, path: str | os.PathLike[str], **overrides: Any) -> Any:
        """Load a ``.toml`` or ``.json`` file; ``overrides`` win over the file."""
        return cls.from_dict({**load_config_file(path), **overrides})


@dataclass
class TrainConfig(EnvConfig):
    """Configuration of one PPO training run with Stable-Baselines3 (see the module docstring).

    The env and filter fields are those of :class:`EnvConfig`.  Bounds: :data:`LIMITS`.

    Attributes
    ----------
    reward : dict
        Reward weights laid over :data:`TRAIN_REWARD` key by key (the env's
        :class:`~aasoatt_env.sim.rewards.RewardConfig` fields).
    velocity_tracking : float
        Weight in ``[0, 100]`` of the training-only shaping term ``-|v_i - v_d_i|``
        (:class:`train.vec_env.VelocityTrackingShaping`; 0: off).
    total_timesteps : int
        Agent-steps (one per robot per decision) of the whole run; a resumed run continues to it.
    n_envs : int
        Teams (envs) stepped together (``n_envs * num_robots`` slots).
    num_workers : int
        Processes stepping the teams: 1 (default) steps them in the training process; more split
        them into shards stepped at the same time (:class:`~aasoatt_env.sim.sharded.ShardedBatchedEnv`).
    seed : int
        Seed of PPO, torch and the envs, in ``[0, 2**31 - 1]``.
    learning_rate, gamma, gae_lambda, clip_range, ent_coef, vf_coef, max_grad_norm : float
        PPO hyper-parameters (``ent_coef`` in ``[0, 10]``, ``vf_coef`` in ``[0, 100]``,
        ``max_grad_norm`` in ``(0, 1000]``).
    n_steps : int
        Rollout length per slot (buffer = ``n_steps * n_envs * num_robots``).
    batch_size, n_epochs : int
        PPO minibatch size and epochs per update.
    net_arch : list of int
        Hidden layers of the policy and value MLPs.
    log_std_init : float
        Initial log standard deviation of the Gaussian policy.
    policy_prior : {"none", "tracking"}
        ``"none"`` (default): SB3's ``MlpPolicy``, learned from scratch.  ``"tracking"``:
        :class:`agents.prior.TrackingPriorPolicy` (needs ``action_mode="point"`` and
        ``normalize_obs=False``): it starts as the paper's tracking law and stays close to it.
    prior_gains : list of two floats
        ``[k3, k4]`` of the tracking-law prior.
    normalize_obs : bool
        Normalise observations with ``VecNormalize`` (statistics saved with the model).
    normalize_reward : bool
        Scale rewards by ``VecNormalize``'s running return std (training only).
    init_from : str or None
        A run folder (or model ``.zip``) whose policy weights and observation statistics start
        this run (fine-tuning); the settings its policy depends on must be as in that run
        (:func:`train.setup.check_init_from`, before a run folder is made).
    resume : str or None
        A run folder or checkpoint to continue (``aasoatt train --resume RUN``): its weights,
        optimiser state, step counter and normalisation statistics; the new run folder holds
        the whole curve (:mod:`train.resume`).
    eval_every : int
        Agent-steps between held-out evaluations during training (0: none); one more at the end.
    eval_episodes : int
        Episodes per held-out evaluation (seeds ``HELDOUT_SEED + j``, never used for training).
    out_dir : str
        Parent folder of runs.
    run_name : str or None
        Run folder name (default: a name from scenario, filter and seed).
    checkpoint_freq : int
        Agent-steps between checkpoints (0: none).
    tensorboard : bool
        Write tensorboard logs under ``<run>/tb``.
    progress_bar : bool
        Print a progress line about every 5% of the run.
    device : str
        Torch device: ``"cpu"``, ``"auto"``, ``"cuda"``, ``"cuda:<i>"`` or ``"mps"``; it must exist
        here (:func:`train.setup.check_device`).
    torch_threads : int
        ``torch.set_num_threads`` (1 is fastest for small MLPs on few cores).
    verbose : int
        SB3 verbosity (0-2).
    """

    velocity_tracking: float = 0.0
    total_timesteps: int = 1_228_800
    n_envs: int = 32
    num_workers: int = 1
    seed: int = 0
    learning_rate: float = 3e-4
    n_steps: int = 64
    batch_size: int = 1024
    n_epochs: int = 10
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_range: float = 0.2
    ent_coef: float = 0.0
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    net_arch: list[int] = field(default_factory=lambda: [64, 64])
    log_std_init: float = -1.0
    policy_prior: str = "none"
    prior_gains: list[float] = field(default_factory=lambda: [1.0, 4.0])
    normalize_obs: bool = True
    normalize_reward: bool = True
    init_from: str | None = None
    resume: str | None = None
    eval_every: int = 122_880
    eval_episodes: int = 10
    out_dir: str = "runs"
    run_name: str | None = None
    checkpoint_freq: int = 250_000
    tensorboard: bool = True
    progress_bar: bool = True
    device: str = "cpu"
    torch_threads: int = 1
    verbose: int = 0

    def _validate(self) -> None:
        if isinstance(self.reward, dict):
            self.reward = {**TRAIN_REWARD, **self.reward}
        self._validate_env()
        self._validate_sizes()
        self._float("learning_rate", 0.0, 1.0, lo_open=True)
        for name in ("gamma", "gae_lambda"):
            self._float(name, 0.0, 1.0)
        self._float("clip_range", 0.0, 10.0, lo_open=True)
        self._float("ent_coef", 0.0, 10.0)
        self._float("vf_coef", 0.0, 100.0)
        self._float("velocity_tracking", 0.0, 100.0)
        self._float("max_grad_norm", 0.0, 1000.0, lo_open=True)
        self._float("log_std_init", -20.0, 5.0)
        if self.policy_prior not in ("none", "tracking"):
            raise self._err("policy_prior", "one of ['none', 'tracking']")
        if not (isinstance(self.prior_gains, (list, tuple)) and len(self.prior_gains) == 2):
            raise self._err("prior_gains", "two positive numbers [k3, k4]")
        self.prior_gains = [check.positive(f"{self._name('prior_gains')}[{i}]", g, hi=1e4)
                            for i, g in enumerate(self.prior_gains)]
        if self.policy_prior == "tracking" and (self.action_mode != "point" or self.normalize_obs):
            raise ConfigError(
                f"TrainConfig.policy_prior: got 'tracking' with action_mode={self.action_mode!r}, "
                f"normalize_obs={self.normalize_obs!r}, expected action_mode='point' and normalize_obs=false"
            )
        self._bools("normalize_obs", "normalize_reward", "tensorboard", "progress_bar")
        self._net_arch()
        for name in ("init_from", "resume"):
            if getattr(self, name) is not None:
                setattr(self, name, check_path(getattr(self, name), self._name(name)))
        if self.init_from is not None and self.resume is not None:
            raise ConfigError(f"TrainConfig.init_from: got {self.init_from!r} with resume={self.resume!r}, expected "
                              "one of them (resume continues a run; init_from starts a new one from its weights)")
        if not isinstance(self.device, str):
            raise self._err("device", "a torch device name")
        self._validate_run_folder()

    def _validate_sizes(self) -> None:
        """Every size against :data:`LIMITS` (the products too), before anything is allocated."""
        lim = LIMITS
        self._int("seed", 0, lim["seed"])
        self._int("n_envs", 1, lim["teams"])
        slots = self.n_envs * self.num_robots
        if slots > lim["slots"]:
            raise self._err("n_envs", f"at most {lim['slots'] // self.num_robots} with {self.num_robots} robots "
                            f"(n_envs * num_robots <= {lim['slots']} robots stepped together)")
        self._int("num_workers", 1, lim["workers"])
        if self.num_workers > self.n_envs:
            raise self._err("num_workers", f"at most n_envs = {self.n_envs} (one team per worker at least)")
        self._int("total_timesteps", 1, lim["agent_steps"])
        self._int("n_steps", 1, lim["n_steps"])
        if self.n_steps * slots > lim["rollout"]:
            raise self._err("n_steps", f"at most {lim['rollout'] // slots} with {slots} slots (the rollout buffer "
                            f"n_steps * n_envs * num_robots holds at most {lim['rollout']:,} transitions)")
        self._int("batch_size", 2, lim["rollout"])
        if self.batch_size > self.n_steps * slots:
            raise self._err("batch_size", f"at most n_steps * n_envs * num_robots = {self.n_steps * slots}")
        self._int("n_epochs", 1, lim["epochs"])
        self._int("torch_threads", 1, lim["workers"])
        for name in ("checkpoint_freq", "eval_every"):
            self._int(name, 0, lim["agent_steps"])
        self._int("eval_episodes", 1, lim["episodes"])
        self._int("verbose", 0, 2)


# the command line and config files (train.options) and the run folders (train.runs), from here as before
from train.options import (  # noqa: E402
    add_config_arguments,
    config_from_args,
    load_config_file,
    parse_config,
    split_backend,
)
