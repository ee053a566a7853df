"""Thousands of teams in one call: the robot model, the decentralised filter and the env in torch (``docs/tensor.md``).

Imports torch; :mod:`aasoatt_env` itself never imports this package (``aasoatt_env.make_tensor_env`` loads it on use).
"""

from aasoatt_env.tensor.env import TensorEnv, make_tensor_env
from aasoatt_env.tensor.filter import BACKUP, GROUPED, RELAXED, FilterOut, SafetyLayer, filter_step

__all__ = ["BACKUP", "GROUPED", "RELAXED", "FilterOut", "SafetyLayer", "TensorEnv", "filter_step", "make_tensor_env"]
