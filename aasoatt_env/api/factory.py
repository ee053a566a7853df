"""``make_env``, ``make_batched_env``: the one constructor of every env (CLI, reproduction, training, benchmarks)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from aasoatt_env import validation as check
from aasoatt_env.errors import ConfigError
from aasoatt_env.safety.config import FilterConfig
from aasoatt_env.safety.wrapper import AASOATTFilter
from aasoatt_env.sim.batched import BatchedAASOATTEnv
from aasoatt_env.sim.env import AASOATTParallelEnv
from aasoatt_env.sim.scenarios import Scenario
from aasoatt_env.sim.sharded import ShardedBatchedEnv

__all__ = ["make_batched_env", "make_env"]


def make_env(scenario: str | Scenario = "circle_swap", *, filter: FilterConfig | Mapping[str, Any] | bool | None = None,
             infos: str = "nested", **env_kwargs: Any) -> AASOATTParallelEnv | AASOATTFilter:
    """A PettingZoo parallel env of ``scenario``, behind :class:`~aasoatt_env.safety.wrapper.AASOATTFilter` if asked.

    ``filter``: None/False (bare), True (defaults), a :class:`FilterConfig` or a mapping of its fields; ``infos``:
    the filter's info layout; ``**env_kwargs``: :class:`~aasoatt_env.sim.env.AASOATTParallelEnv`'s and the scenario's.
    """
    check.choice("infos", infos, ("nested", "flat"))  # checked without a filter too
    env = AASOATTParallelEnv(scenario, **env_kwargs)
    if filter is None or filter is False:
        return env
    if filter is not True and not isinstance(filter, (FilterConfig, Mapping)):
        raise ConfigError(f"filter: got {filter!r}, expected None, True/False, a FilterConfig or a mapping of "
                          "its fields")
    return AASOATTFilter(env, None if filter is True else filter, infos=infos)


def make_batched_env(num_envs: int, scenario: str | Scenario = "circle_swap", *,
                     filter: FilterConfig | Mapping[str, Any] | bool | None = None, autoreset: bool = True,
                     group_filter: bool = True, num_workers: int = 1,
                     **env_kwargs: Any) -> BatchedAASOATTEnv | ShardedBatchedEnv:
    """``num_envs`` :func:`make_env` teams stepped together (:class:`~aasoatt_env.sim.batched.BatchedAASOATTEnv`).

    ``num_workers > 1``: that many shards in worker processes (:class:`~aasoatt_env.sim.sharded.ShardedBatchedEnv`).
    """
    num_envs = check.integer("num_envs", num_envs, lo=1)
    fns = [lambda: make_env(scenario, filter=filter, **env_kwargs) for _ in range(num_envs)]
    if isinstance(num_workers, bool) or not isinstance(num_workers, (int, np.integer)) or not (
            1 <= num_workers <= num_envs):
        raise ConfigError(f"num_workers: got {num_workers!r}, expected an integer in [1, num_envs = {num_envs}]")
    if num_workers > 1:
        make_env(scenario, filter=filter, **env_kwargs).close()  # bad arguments fail here, not in a worker
        return ShardedBatchedEnv(fns, num_workers, autoreset=autoreset, group_filter=group_filter)
    return BatchedAASOATTEnv(fns, autoreset=autoreset, group_filter=group_filter)
