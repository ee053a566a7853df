"""The simulation layer on :mod:`aasoatt_env.model`: env, scenarios, references, rendering, the filter protocol."""

from aasoatt_env.sim.batched import BatchedAASOATTEnv
from aasoatt_env.sim.env import AASOATTParallelEnv
from aasoatt_env.sim.protocol import ControlFilter, FilterInput, FilterOutput
from aasoatt_env.sim.rewards import RewardConfig
from aasoatt_env.sim.scenarios import SCENARIOS, Layout, Scenario, get_scenario
from aasoatt_env.sim.sharded import ShardedBatchedEnv

__all__ = ["SCENARIOS", "AASOATTParallelEnv", "BatchedAASOATTEnv", "ControlFilter", "FilterInput", "FilterOutput",
           "Layout", "RewardConfig", "Scenario", "ShardedBatchedEnv", "get_scenario"]
