"""Entry points: :func:`make_env` (bare or behind the safety filter), the Gymnasium view, the registered ids."""

from aasoatt_env.api.factory import make_batched_env, make_env
from aasoatt_env.api.gym_env import AASOATTGymEnv
from aasoatt_env.api.registration import ENV_IDS, env, parallel_env, register_all

__all__ = ["ENV_IDS", "AASOATTGymEnv", "env", "make_batched_env", "make_env", "parallel_env", "register_all"]
