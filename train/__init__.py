"""Reinforcement learning on the AA-SOATT env: PPO with parameter sharing (SB3, or Ray RLlib).

==========================  ===================================================
module                      contents
==========================  ===================================================
:mod:`train.config`         ``TrainConfig`` and its bounds (``LIMITS``); its
                            defaults are the recipe that learns from scratch
:mod:`train.options`        the command line and config files of both backends
:mod:`train.runs`           run folders, atomic writes, path checks
:mod:`train.build`          the envs, model and checks a run is built from
:mod:`train.vec_env`        ``BatchedVecEnv`` (teams stepped together) and
                            ``ParallelVecEnv``: SB3 VecEnvs, one slot per robot;
                            ``SlotMonitor``, ``SlotNormalize``
:mod:`train.ppo`            ``SlotPPO``: PPO that never trains on dead-slot padding
:mod:`train.telemetry`      per-rollout metrics, progress line, learning curves
:mod:`train.heldout`        held-out evaluation during training
:mod:`train.resume`         ``aasoatt train --resume``
:mod:`train.seeds`          ``aasoatt train --seeds``: mean and spread over seeds
:mod:`train.train`          ``train(config) -> Path`` and ``python -m train.train``
:mod:`train.policies`       loading a trained policy for a command
:mod:`train.intervals`      Wilson intervals, mean and spread
:mod:`train.evaluate`       ``evaluate(...) -> list[EvalRow]``, ``to_markdown``,
                            ``python -m train.evaluate``
:mod:`train.compare`        the safe-RL comparison, ``python -m train.compare``
:mod:`train.rllib`          the Ray RLlib backend (``aasoatt train --backend rllib``)
:mod:`train.rllib_env`      its env: the robots of many teams as one vector env
==========================  ===================================================

Nothing heavy is imported here (torch and SB3 load with the submodules).
"""
