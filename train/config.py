"""``TrainConfig``: every knob of a PPO run, from a TOML/JSON file and the command line.

Precedence: dataclass defaults < config file (``--config run.toml`` or
``.json``) < command-line flags.  The configuration is validated once, in
``__post_init__``; every error is a :class:`~aasoatt_env.errors.ConfigError`
of the form ``"TrainConfig.<field>: got X, expected Y"``.

The defaults of :class:`TrainConfig` are the recipe that learns from scratch
(``train/configs/random_goals_6r.toml``, measured in the README): a plain MLP,
observations and rewards normalised, point actions, 32 envs x 6 robots, 1.23M
agent-steps.  ``reward`` entries are laid over the recipe's reward
(:data:`TRAIN_REWARD`), key by key, wherever they come from.

:class:`EnvConfig` holds the env and filter fields that every training backend
shares: :class:`TrainConfig` (Stable-Baselines3) and
:class:`train.rllib.RLlibConfig` (Ray RLlib) extend it, and
:func:`add_config_arguments` / :func:`config_from_args` serve either.

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

import argparse
import contextlib
import json
import math
import os
import shutil
from collections.abc import Sequence
from dataclasses import MISSING, asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import tomllib

from aasoatt_env.errors import ConfigError, DataFileError
from aasoatt_env.safety.config import FilterConfig
from aasoatt_env.sim.rewards import RewardConfig
from aasoatt_env.sim.scenarios import SCENARIOS
from aasoatt_env.validation import parse_value
from agents.learned import MAX_LAYER_SIZE, MAX_LAYERS

__all__ = ["BACKENDS", "INCOMPLETE_FILE", "TRAIN_REWARD", "EnvConfig", "TrainConfig", "abandon_run",
           "add_config_arguments", "claim_run_dir", "config_from_args", "load_config_file", "split_backend",
           "unique_run_dir"]

_ACTION_MODES = ("wheel", "point")

TRAIN_REWARD: dict[str, float] = {"tracking": 1.0, "collision": 1.0, "effort": 0.01, "goal_bonus": 0.5,
                                   "goal_tolerance": 0.1}
"""The reward of the default recipe (:class:`TrainConfig`); ``reward`` entries replace these key by key.

``collision`` 1 rather than the env's 10: with 10, collisions a robot cannot avoid alone (others drive
into it) drown the tracking signal and a plain MLP does not learn (``docs/technical_brief.md`` section 10).
``goal_tolerance`` 0.1 m is the evaluation's success radius."""

BACKENDS = ("sb3", "rllib")
"""``aasoatt train --backend``: ``sb3`` (:mod:`train.train`, the default) or ``rllib`` (:mod:`train.rllib`)."""


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
        Physics step [s] (0.005: the 200 Hz of the filter).
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
        Arguments of the filter (``barrier``, ``deadlock``, ``solver``, gains).
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
    def _err(self, name: str, expected: str) -> ConfigError:
        return ConfigError(f"{type(self).__name__}.{name}: got {getattr(self, name)!r}, expected {expected}")

    def _net_arch(self) -> None:
        """``net_arch``: 1 to ``MAX_LAYERS`` sizes in ``[1, MAX_LAYER_SIZE]`` (what the loaders accept)."""
        arch = self.net_arch
        if not (isinstance(arch, (list, tuple)) and 1 <= len(arch) <= MAX_LAYERS
                and all(isinstance(h, int) and not isinstance(h, bool) and 1 <= h <= MAX_LAYER_SIZE for h in arch)):
            raise self._err("net_arch", f"a list of 1 to {MAX_LAYERS} layer sizes in [1, {MAX_LAYER_SIZE}] (a run "
                            "must be loadable)")
        self.net_arch = list(arch)

    def _int(self, name: str, lo: int) -> None:
        v = getattr(self, name)
        if isinstance(v, bool) or not isinstance(v, int) or v < lo:
            raise self._err(name, f"an integer >= {lo}")

    def _float(self, name: str, lo: float, hi: float = math.inf, lo_open: bool = False) -> None:
        v = getattr(self, name)
        ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
        ok = ok and (v > lo if lo_open else v >= lo) and v <= hi
        if not ok:
            lb = "(" if lo_open else "["
            raise self._err(name, f"a number in {lb}{lo:g}, {hi:g}]")
        setattr(self, name, float(v))

    def _bools(self, *names: str) -> None:
        for name in names:
            if not isinstance(getattr(self, name), bool):
                raise self._err(name, "true or false")

    def _validate(self) -> None:
        self._validate_env()

    def _validate_env(self) -> None:
        """Validate the env and filter fields."""
        if self.scenario not in SCENARIOS:
            raise self._err("scenario", f"one of {sorted(SCENARIOS)}")
        for name in ("num_robots", "decision_interval"):
            self._int(name, 1)
        for name in ("num_neighbors", "num_obstacles"):
            self._int(name, 0)
        if self.max_steps is not None:
            self._int("max_steps", 1)
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
            raise ConfigError(f"{type(self).__name__}.reward: got unknown key(s) {unknown}, expected keys among "
                              f"{known}") from None
        try:
            self.filter_config()
        except TypeError as exc:
            raise ConfigError(f"{type(self).__name__}.filter_kwargs: {exc}") from None
        except ConfigError as exc:
            raise ConfigError(f"{type(self).__name__}.filter_kwargs: {exc}") from None
        if self.reward.get("correction", 0.0) and not self.filter:
            raise ConfigError(
                f"{type(self).__name__}.reward: got correction={self.reward['correction']!r} with filter=False, "
                "expected filter=True (the correction penalty needs the filter)"
            )

    def _validate_run_folder(self) -> None:
        if not isinstance(self.out_dir, str) or not self.out_dir:  # type: ignore[attr-defined]
            raise self._err("out_dir", "a non-empty folder path")
        name = self.run_name  # type: ignore[attr-defined]
        if name is not None and (not isinstance(name, str) or not name or os.sep in name):
            raise self._err("run_name", "a non-empty folder name or None")

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
        """The safety filter's configuration (``filter_kwargs`` converted at this edge)."""
        return FilterConfig.merged(self.filter_kwargs, dt=self.dt)

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON dict of every field."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Any:
        """Build from a dict, rejecting unknown keys."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
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

    The env and filter fields are those of :class:`EnvConfig`.

    Attributes
    ----------
    reward : dict
        Reward weights laid over :data:`TRAIN_REWARD` key by key (the env's
        :class:`~aasoatt_env.sim.rewards.RewardConfig` fields).
    velocity_tracking : float
        Weight of the training-only shaping term ``-|v_i - v_d_i|``
        (:class:`train.vec_env.VelocityTrackingShaping`; 0: off).
    total_timesteps : int
        Agent-steps (one per robot per decision) to train for.
    n_envs : int
        Teams (envs) stepped together (``n_envs * num_robots`` slots).
    num_workers : int
        Processes stepping the teams: 1 (default) steps them in the training
        process; more split them into that many shards stepped at the same time
        (:class:`~aasoatt_env.sim.sharded.ShardedBatchedEnv`), so filtered
        training uses more cores.  Trajectories agree with one process bit for bit
        without a filter, to rounding behind the grouped filter (its QP is
        solved per shard).
    seed : int
        Seed of PPO, torch and the envs.
    learning_rate, gamma, gae_lambda, clip_range, ent_coef, vf_coef, max_grad_norm : float
        PPO hyper-parameters.
    n_steps : int
        Rollout length per slot (buffer = ``n_steps * n_envs * num_robots``).
    batch_size, n_epochs : int
        PPO minibatch size and epochs per update.
    net_arch : list of int
        Hidden layers of the policy and value MLPs.
    log_std_init : float
        Initial log standard deviation of the Gaussian policy.
    policy_prior : {"none", "tracking"}
        ``"none"`` (default): SB3's ``MlpPolicy``, learned from scratch.
        ``"tracking"``: :class:`agents.prior.TrackingPriorPolicy`, whose action
        mean is a trainable linear layer on the raw observation initialised to
        the paper's tracking law plus the MLP (needs ``action_mode="point"`` and
        ``normalize_obs=False``): it starts as the tracking law and stays close
        to it.
    prior_gains : list of two floats
        ``[k3, k4]`` of the tracking-law prior.
    normalize_obs : bool
        Normalise observations with ``VecNormalize`` (running statistics are
        saved with the model and used by :class:`agents.learned.LearnedAgent`).
    normalize_reward : bool
        Scale rewards by ``VecNormalize``'s running return std (training only).
    init_from : str or None
        A run folder (or model ``.zip``) of ``aasoatt train`` whose policy
        weights and observation statistics start this run (fine-tuning, e.g.
        a policy trained bare, now behind the filter).  Every setting the loaded
        policy depends on must be as in that run: ``action_mode``, the observation
        layout (``num_neighbors``, ``num_obstacles``, ``sensing_range``),
        ``decision_interval``, ``dt``, ``policy_prior``, ``net_arch`` and
        ``normalize_obs`` (:func:`train.train.check_init_from`, before a run folder is made).
    out_dir : str
        Parent folder of runs.
    run_name : str or None
        Run folder name (default: a name from scenario, filter and seed).
    checkpoint_freq : int
        Agent-steps between checkpoints (0: none).
    tensorboard : bool
        Write tensorboard logs under ``<run>/tb``.
    progress_bar : bool
        Print a progress line (throughput, ETA, success, tracking error,
        collisions, filter intervention) about every 5% of the run.
    device : str
        Torch device: ``"cpu"``, ``"auto"`` (the GPU if there is one), ``"cuda"``,
        ``"cuda:<i>"`` or ``"mps"``; it must exist on this machine
        (:func:`train.train.check_device`, before a run folder is made).
    torch_threads : int
        ``torch.set_num_threads`` (1 is fastest for small MLPs on few cores).
    verbose : int
        SB3 verbosity.
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
        for name in ("total_timesteps", "n_envs", "n_steps", "n_epochs", "torch_threads", "num_workers"):
            self._int(name, 1)
        if self.num_workers > self.n_envs:
            raise self._err("num_workers", f"at most n_envs = {self.n_envs} (one team per worker at least)")
        for name in ("checkpoint_freq", "seed", "verbose"):
            self._int(name, 0)
        self._int("batch_size", 2)
        self._float("learning_rate", 0.0, 1.0, lo_open=True)
        self._float("gamma", 0.0, 1.0)
        self._float("gae_lambda", 0.0, 1.0)
        self._float("clip_range", 0.0, 10.0, lo_open=True)
        self._float("ent_coef", 0.0)
        self._float("vf_coef", 0.0)
        self._float("velocity_tracking", 0.0)
        self._float("max_grad_norm", 0.0, lo_open=True)
        self._float("log_std_init", -20.0, 5.0)
        if self.policy_prior not in ("none", "tracking"):
            raise self._err("policy_prior", "one of ['none', 'tracking']")
        if not (isinstance(self.prior_gains, (list, tuple)) and len(self.prior_gains) == 2
                and all(isinstance(g, (int, float)) and not isinstance(g, bool) and math.isfinite(g) and g > 0
                        for g in self.prior_gains)):
            raise self._err("prior_gains", "two positive numbers [k3, k4]")
        self.prior_gains = [float(g) for g in self.prior_gains]
        if self.policy_prior == "tracking" and (self.action_mode != "point" or self.normalize_obs):
            raise ConfigError(
                f"TrainConfig.policy_prior: got 'tracking' with action_mode={self.action_mode!r}, "
                f"normalize_obs={self.normalize_obs!r}, expected action_mode='point' and normalize_obs=false"
            )
        self._bools("normalize_obs", "normalize_reward", "tensorboard", "progress_bar")
        self._net_arch()
        if self.init_from is not None and (not isinstance(self.init_from, str) or not self.init_from):
            raise self._err("init_from", "a run folder or model .zip path, or None")
        rollout = self.n_steps * self.n_envs * self.num_robots
        if self.batch_size > rollout:
            raise self._err("batch_size", f"at most n_steps * n_envs * num_robots = {rollout}")
        self._validate_run_folder()


def claim_run_dir(out_dir: str | os.PathLike[str], name: str, marker: bool = True) -> tuple[Path, bool]:
    """Create (or take an empty) ``<out_dir>/<name>``, or ``<name>_2``, ``<name>_3``, ...; and whether it was created.

    A run never writes into the folder of another run; an existing empty folder is used.  With
    ``marker`` the folder is claimed by creating its :data:`INCOMPLETE_FILE` exclusively, so two
    runs started at once never share a folder; the caller removes the marker when the run is done.
    The flag says whether this call created the folder (:func:`abandon_run` removes only such).
    """
    base = Path(out_dir) / name
    path, k = base, 1
    while True:
        created = False
        try:
            path.mkdir(parents=True)
            created = True
        except FileExistsError:
            if not (path.exists() or path.is_symlink()):  # a parent is a dangling link: no name will do
                raise
        if path.is_dir() and (created or not any(path.iterdir())):
            if not marker:
                return path, created
            try:
                with (path / INCOMPLETE_FILE).open("x") as fh:
                    fh.write("training in progress or failed: this is not a finished run\n")
                return path, created
            except FileExistsError:  # another run claimed it first
                pass
        k += 1
        path = base.with_name(f"{base.name}_{k}")


def unique_run_dir(out_dir: str | os.PathLike[str], name: str) -> Path:
    """Create and return ``<out_dir>/<name>``, or ``<name>_2``, ``<name>_3``, ... if it holds files.

    A run never writes into the folder of another run; an existing empty folder is used
    (:func:`claim_run_dir` without a marker).
    """
    return claim_run_dir(out_dir, name, marker=False)[0]


INCOMPLETE_FILE = "INCOMPLETE"
"""A run folder holds this file while its training runs, and keeps it if training failed after a checkpoint."""


def abandon_run(run: Path, keep: bool, created: bool) -> None:
    """After a failed training: empty ``run`` (removed if this run created it), or mark it incomplete.

    With ``keep`` (it holds a model or checkpoint) it stays with an :data:`INCOMPLETE_FILE` and no
    ``train_stats.json`` (what marks a finished run).  A folder that existed before the run (an empty
    folder it was given, or a link to one) stays, emptied.
    """
    if keep:
        try:
            (run / "train_stats.json").unlink(missing_ok=True)
            (run / INCOMPLETE_FILE).write_text("training did not finish: keep the checkpoints you need, then "
                                               "remove this folder\n")
        except OSError:
            pass
        return
    for child in list(run.iterdir()) if run.is_dir() else []:
        if child.is_dir() and not child.is_symlink():
            shutil.rmtree(child, ignore_errors=True)
        else:
            child.unlink(missing_ok=True)
    if created and not run.is_symlink():
        with contextlib.suppress(OSError):
            run.rmdir()


def load_config_file(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a TOML (``.toml``) or JSON (``.json``) config file into a dict."""
    p = Path(path)
    if p.suffix not in (".toml", ".json"):
        raise ConfigError(f"config file: got suffix {p.suffix!r}, expected '.toml' or '.json' (file {str(p)!r})")
    if not p.is_file():
        raise DataFileError(f"{p}: no such config file, expected an existing .toml or .json file")
    try:
        text = p.read_text()
        data = tomllib.loads(text) if p.suffix == ".toml" else json.loads(text)
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError, json.JSONDecodeError, RecursionError) as exc:
        kind = "TOML" if p.suffix == ".toml" else "JSON"
        raise DataFileError(f"{p}: not a readable {kind} file ({type(exc).__name__}: {str(exc)[:200]})") from None
    if not isinstance(data, dict):
        raise DataFileError(f"{p}: got a JSON {type(data).__name__}, expected an object of TrainConfig fields")
    return data


# ---------------------------------------------------------------------- command line
_DICT_FIELDS = {"scenario_kwargs": "scenario-arg", "reward": "reward", "filter_kwargs": "filter-arg"}
_OPTIONAL_INTS = {"num_cpus"}  # int fields whose default is None


def _int_arg(text: str) -> int | str:
    """``"1e6"`` -> 1000000; anything else is passed on for :class:`TrainConfig` to reject with its range."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"got {text!r}, expected an integer") from None
    return int(value) if value.is_integer() else text


_int_arg.__name__ = "integer"


def _bool(text: str) -> bool:
    low = text.lower()
    if low in ("1", "true", "yes", "on"):
        return True
    if low in ("0", "false", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"got {text!r}, expected true or false")


def add_config_arguments(parser: argparse.ArgumentParser, cls: type[EnvConfig] | None = None) -> None:
    """Add ``--config`` and one ``--field-name`` flag per field of ``cls`` (default :class:`TrainConfig`).

    Dict fields take repeated ``KEY=VALUE``: ``--reward collision=20``,
    ``--filter-arg solver=proxsuite``, ``--scenario-arg speed=1.0``;
    ``--net-arch 64 64``.  Unset flags leave the file/default value.
    """
    cls = TrainConfig if cls is None else cls
    parser.add_argument("--config", default=None, help=f"TOML or JSON file of {cls.__name__} fields")
    for f in fields(cls):
        default = f.default if f.default is not MISSING else f.default_factory()  # type: ignore[misc]
        if f.name in _DICT_FIELDS:
            parser.add_argument(f"--{_DICT_FIELDS[f.name]}", dest=f.name, action="append", default=None,
                                metavar="KEY=VALUE", help=f"{f.name} entry (repeatable)")
            continue
        flag = "--" + f.name.replace("_", "-")
        if f.name == "net_arch":
            parser.add_argument(flag, dest=f.name, type=int, nargs="+", default=None, help=f"default {default}")
        elif f.name == "prior_gains":
            parser.add_argument(flag, dest=f.name, type=float, nargs=2, default=None, help=f"default {default}")
        elif isinstance(default, bool):
            parser.add_argument(flag, dest=f.name, type=_bool, default=None, metavar="BOOL", help=f"default {default}")
        elif isinstance(default, int):
            parser.add_argument(flag, dest=f.name, type=_int_arg, default=None, help=f"default {default}")
        elif isinstance(default, float):
            parser.add_argument(flag, dest=f.name, type=float, default=None, help=f"default {default}")
        elif f.name == "max_steps":
            parser.add_argument(flag, dest=f.name, type=int, default=None, help="default: scenario horizon")
        elif f.name in _OPTIONAL_INTS:
            parser.add_argument(flag, dest=f.name, type=int, default=None, help=f"default {default}")
        else:
            parser.add_argument(flag, dest=f.name, default=None, help=f"default {default}")


def config_from_args(args: argparse.Namespace, cls: type[EnvConfig] | None = None) -> Any:
    """Merge defaults, ``args.config`` and the flags set in ``args`` into a validated ``cls`` (:class:`TrainConfig`)."""
    cls = TrainConfig if cls is None else cls
    data: dict[str, Any] = load_config_file(args.config) if getattr(args, "config", None) else {}
    for f in fields(cls):
        val = getattr(args, f.name, None)
        if val is None:
            continue
        if f.name in _DICT_FIELDS:
            merged = dict(data.get(f.name, {}))
            for item in val:
                if "=" not in item:
                    raise ConfigError(f"--{_DICT_FIELDS[f.name]}: got {item!r}, expected KEY=VALUE")
                k, v = item.split("=", 1)
                merged[k.strip()] = parse_value(v.strip())
            data[f.name] = merged
        else:
            data[f.name] = val
    return cls.from_dict(data)


def parse_config(argv: Sequence[str] | None = None, prog: str = "train") -> TrainConfig:
    """Parse a command line into a :class:`TrainConfig` (for tests and scripts)."""
    parser = argparse.ArgumentParser(prog=prog)
    add_config_arguments(parser)
    return config_from_args(parser.parse_args(argv))


def split_backend(argv: Sequence[str]) -> tuple[str, list[str]]:
    """The ``--backend`` of a training command line (default ``"sb3"``) and the command line without it."""
    pre = argparse.ArgumentParser(prog="aasoatt train", add_help=False)
    pre.add_argument("--backend", choices=BACKENDS, default="sb3")
    known, _ = pre.parse_known_args(argv)
    rest: list[str] = []
    skip = False
    for a in argv:
        if skip:
            skip = False
        elif a == "--backend":
            skip = True
        elif not a.startswith("--backend="):
            rest.append(a)
    return known.backend, rest
