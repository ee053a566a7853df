"""Entry points: :func:`make_env` (env behind a filter or not), the Gymnasium view and the registered ids.

This layer sits on top of the simulation and the safety filter.
"""

from aasoatt_env.api.factory import make_batched_env, make_env
from aasoatt_env.api.gym_env import AASOATTGymEnv
from aasoatt_env.api.registration import ENV_IDS, env, parallel_env, register_all

__all__ = ["ENV_IDS", "AASOATTGymEnv", "env", "make_batched_env", "make_env", "parallel_env", "register_all"]
