"""Reinforcement learning on the AA-SOATT env: PPO with parameter sharing (SB3).

==========================  ===================================================
module                      contents
==========================  ===================================================
:mod:`train.config`         ``TrainConfig`` (TOML/JSON file + command line); its
                            defaults are the recipe that learns from scratch
:mod:`train.vec_env`        ``BatchedVecEnv`` (teams stepped together) and
                            ``ParallelVecEnv``: SB3 VecEnvs, one slot per robot;
                            ``SlotMonitor``, ``SlotNormalize``
:mod:`train.ppo`            ``SlotPPO``: PPO that never trains on dead-slot padding
:mod:`train.telemetry`      per-rollout metrics, progress line, learning curves
:mod:`train.train`          ``train(config) -> Path`` and ``python -m train.train``
:mod:`train.evaluate`       ``evaluate(...) -> list[EvalRow]``, ``to_markdown``,
                            ``python -m train.evaluate``
:mod:`train.compare`        the safe-RL comparison, ``python -m train.compare``
:mod:`train.rllib`          the Ray RLlib backend (``aasoatt train --backend rllib``)
==========================  ===================================================

Nothing heavy is imported here (torch and SB3 load with the submodules).
"""
