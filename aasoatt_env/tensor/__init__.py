"""Thousands of teams in one call: the robot model, the decentralised filter and the env in torch (``docs/tensor.md``).

Imports torch; :mod:`aasoatt_env` itself never imports this package (``aasoatt_env.make_tensor_env`` loads it on use).
"""
