"""Reinforcement learning on the AA-SOATT env: PPO with parameter sharing (SB3).

==========================  ===================================================
module                      contents
==========================  ===================================================
:mod:`train.config`         ``TrainConfig`` (TOML/JSON file + command line)
:mod:`train.vec_env`        ``ParallelVecEnv``: SB3 VecEnv, one slot per robot
:mod:`train.train`          ``train(config) -> Path`` and ``python -m train.train``
:mod:`train.evaluate`       ``evaluate(...) -> list[EvalRow]``, ``to_markdown``,
                            ``python -m train.evaluate``
==========================  ===================================================

Nothing heavy is imported here (torch and SB3 load with the submodules).
"""
