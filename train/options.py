"""The command line and config files of the training commands (both backends).

Every field of the configuration class (:class:`train.config.TrainConfig` or
:class:`train.rllib.RLlibConfig`) is a flag.  Precedence: defaults < the resumed run's
``config.json`` (``--resume RUN``) < ``--config FILE`` < flags.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Sequence
from dataclasses import MISSING, fields
from pathlib import Path
from typing import Any

import tomllib

from aasoatt_env.errors import ConfigError, DataFileError
from aasoatt_env.validation import parse_value
from agents.run_files import MAX_JSON_BYTES, read_json
from train.runs import check_path

__all__ = ["add_config_arguments", "config_from_args", "load_config_file", "parse_config", "run_config",
           "split_backend"]

_DICT_FIELDS = {"scenario_kwargs": "scenario-arg", "reward": "reward", "filter_kwargs": "filter-arg"}
_OPTIONAL_INTS = {"num_cpus"}  # int fields whose default is None


def load_config_file(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a TOML (``.toml``) or JSON (``.json``) config file into a dict (bounded size and nesting)."""
    p = Path(check_path(path, "config file"))
    if p.suffix not in (".toml", ".json"):
        raise ConfigError(f"config file: got suffix {p.suffix!r}, expected '.toml' or '.json' (file {str(p)!r})")
    if not p.is_file():
        raise DataFileError(f"{p}: no such config file, expected an existing .toml or .json file")
    if p.suffix == ".json":
        return read_json(p)
    try:
        if p.stat().st_size > MAX_JSON_BYTES:
            raise DataFileError(f"{p}: larger than {MAX_JSON_BYTES:,} bytes, expected a config file")
        return tomllib.loads(p.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError, RecursionError) as exc:
        raise DataFileError(f"{p}: not a readable TOML file ({type(exc).__name__}: {str(exc)[:200]})") from None


def run_config(path: str | os.PathLike[str], flag: str) -> dict[str, Any]:
    """The ``config.json`` of the run ``path`` (a run folder, a file in it, or a checkpoint of it)."""
    p = Path(check_path(path, flag))
    if not p.exists():
        raise ConfigError(f"{flag}: got {str(path)!r}, expected a run folder or checkpoint (no such path)")
    base = p if p.is_dir() else p.parent
    for folder in (base, base.parent, base.parent.parent):
        if (folder / "config.json").is_file():
            return read_json(folder / "config.json")
    raise ConfigError(f"{flag}: {str(path)!r} holds no config.json here or above; expected a run folder of "
                      "aasoatt train")


def _int_arg(text: str) -> int | str:
    """``"1e6"`` -> 1000000; anything else is passed on for the config to reject with its range."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"got {text!r}, expected an integer") from None
    if value.is_integer():
        try:
            return int(text)
        except ValueError:
            return int(value)
    return text


_int_arg.__name__ = "integer"


def _bool(text: str) -> bool:
    low = text.lower()
    if low in ("1", "true", "yes", "on"):
        return True
    if low in ("0", "false", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"got {text!r}, expected true or false")


def add_config_arguments(parser: argparse.ArgumentParser, cls: type | None = None) -> None:
    """Add ``--config`` and one ``--field-name`` flag per field of ``cls`` (default :class:`TrainConfig`).

    Dict fields take repeated ``KEY=VALUE``: ``--reward collision=20``,
    ``--filter-arg solver=proxsuite``, ``--scenario-arg speed=1.0``;
    ``--net-arch 64 64``.  Unset flags leave the file/default value.
    """
    from train.config import TrainConfig

    cls = TrainConfig if cls is None else cls
    parser.add_argument("--config", default=None, help=f"TOML or JSON file of {cls.__name__} fields")
    for f in fields(cls):
        default = f.default if f.default is not MISSING else f.default_factory()  # type: ignore[misc]
        if f.name in _DICT_FIELDS:
            parser.add_argument(f"--{_DICT_FIELDS[f.name]}", dest=f.name, action="append", default=None,
                                metavar="KEY=VALUE", help=f"{f.name} entry (repeatable)")
            continue
        flag = "--" + f.name.replace("_", "-")
        kw: dict[str, Any] = {"dest": f.name, "default": None, "help": f"default {default}"}
        if f.name == "net_arch":
            kw.update(type=int, nargs="+")
        elif f.name == "prior_gains":
            kw.update(type=float, nargs=2)
        elif isinstance(default, bool):
            kw.update(type=_bool, metavar="BOOL")
        elif isinstance(default, int) or f.name in _OPTIONAL_INTS or f.name == "max_steps":
            kw.update(type=_int_arg)
        elif isinstance(default, float):
            kw.update(type=float)
        if f.name == "resume":
            kw["help"] = "continue this run (folder or checkpoint): its config.json is the base of this one"
        parser.add_argument(flag, **kw)


def config_from_args(args: argparse.Namespace, cls: type | None = None) -> Any:
    """Merge defaults, the resumed run's config, ``args.config`` and the flags set in ``args`` into a ``cls``."""
    from train.config import TrainConfig

    cls = TrainConfig if cls is None else cls
    data: dict[str, Any] = {}
    if getattr(args, "resume", None) is not None:
        data = run_config(args.resume, "--resume")
        data["init_from"] = None  # (what it was started from is in its weights now)
        data = {k: v for k, v in data.items() if k in {f.name for f in fields(cls)}}
    if getattr(args, "config", None):
        data.update(load_config_file(args.config))
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


def parse_config(argv: Sequence[str] | None = None, prog: str = "train") -> Any:
    """Parse a command line into a :class:`TrainConfig` (for tests and scripts)."""
    parser = argparse.ArgumentParser(prog=prog)
    add_config_arguments(parser)
    return config_from_args(parser.parse_args(argv))


def split_backend(argv: Sequence[str]) -> tuple[str, list[str]]:
    """The ``--backend`` of a training command line (default ``"sb3"``) and the command line without it."""
    from train.config import BACKENDS

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
