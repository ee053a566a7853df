"""Every registered id through the checkers of the RL libraries users already have.

For each id of :data:`aasoatt_env.ENV_IDS`, bare and behind :class:`AASOATTFilter`:

* PettingZoo: ``parallel_api_test``, ``parallel_seed_test``, ``api_test`` on ``parallel_to_aec``;
* Gymnasium ``check_env`` and Stable-Baselines3 ``check_env`` on the centralised view
  (``gymnasium.make(id)`` and ``gymnasium.make(id, safety_filter={})``);
* TorchRL: ``GymEnv(id)`` and ``PettingZooWrapper`` (filter infos ``"flat"``), each with
  ``check_env_specs`` and a 50-step rollout (skipped, with the reason, when torchrl is not installed).

Ray RLlib has its own test (``tests/test_rllib.py``, in the venv of the ``rllib`` extra).
"""

from __future__ import annotations

import warnings

import gymnasium
import numpy as np
import pettingzoo
import pytest
from pettingzoo.test import api_test, parallel_api_test, parallel_seed_test
from pettingzoo.utils.conversions import parallel_to_aec

import aasoatt_env
from aasoatt_env import ENV_IDS, AASOATTFilter

pytestmark = pytest.mark.filterwarnings("ignore:PettingZoo in TorchRL is tested:UserWarning")

# Small teams where the scenario has a size (Tracking and PositionSwap have fixed teams), a policy
# at 10 Hz and a short horizon: every check crosses at least one episode end.
SMALL: dict[str, dict] = {
    "aasoatt/CircleSwap-v0": dict(num_robots=4),
    "aasoatt/CircleSwapObstacles-v0": dict(num_robots=4),
    "aasoatt/Tracking-v0": {},
    "aasoatt/PositionSwap-v0": {},
    "aasoatt/RandomGoals-v0": dict(num_robots=3),
}
FAST = dict(decision_interval=20, max_steps=30)
IDS = sorted(ENV_IDS)
MODES = ["bare", "filter"]


def test_every_registered_id_is_covered():
    assert set(SMALL) == set(ENV_IDS)


def make_parallel(env_id: str, mode: str, infos: str = "nested", **kw):
    env = pettingzoo.make("parallel", env_id, **{**SMALL[env_id], **FAST, **kw})
    return env if mode == "bare" else AASOATTFilter(env, infos=infos)


def make_gym(env_id: str, mode: str, **kw):
    extra = {} if mode == "bare" else {"safety_filter": {}}
    return gymnasium.make(env_id, **{**SMALL[env_id], **FAST, **kw}, **extra)


# ---------------------------------------------------------------------------------------------- PettingZoo
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("env_id", IDS)
def test_pettingzoo_parallel_api_test(env_id, mode):
    parallel_api_test(make_parallel(env_id, mode), num_cycles=40)


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("env_id", IDS)
def test_pettingzoo_parallel_seed_test(env_id, mode):
    # compares the first step's observations, rewards, dones and infos of two same-seeded envs:
    # the filter's infos must be deterministic (no wall-clock times)
    parallel_seed_test(lambda: make_parallel(env_id, mode))


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("env_id", IDS)
def test_pettingzoo_api_test_on_parallel_to_aec(env_id, mode):
    api_test(parallel_to_aec(make_parallel(env_id, mode)), num_cycles=40)


@pytest.mark.parametrize("infos", ["nested", "flat"])
def test_filtered_env_is_deterministic_over_a_whole_episode(infos):
    # parallel_seed_test compares one step only (docs/technical_brief.md section 8). Exact equality over many
    # steps needs an exact solver: proxsuite can differ in the last bit between identical runs (docs/design.md,
    # "Which solver answers").
    pytest.importorskip("daqp")
    from gymnasium.utils.env_checker import data_equivalence

    def roll():
        env = AASOATTFilter(pettingzoo.make("parallel", "aasoatt/RandomGoals-v0", num_robots=4, max_steps=20,
                                            decision_interval=20), infos=infos, solver="daqp")
        rng = np.random.default_rng(0)
        out = [env.reset(seed=3)]
        while env.agents:
            out.append(env.step({a: rng.uniform(-1, 1, 2).astype(np.float32) for a in env.agents}))
        return out

    a, b = roll(), roll()
    assert len(a) == 21
    assert all(data_equivalence(x, y) for x, y in zip(a, b))


# ---------------------------------------------------------------------------------------------- Gymnasium, SB3
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("env_id", IDS)
def test_gymnasium_check_env_on_the_centralised_view(env_id, mode):
    from gymnasium.utils.env_checker import check_env

    env = make_gym(env_id, mode)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a checker warning is a failure too
        check_env(env.unwrapped, skip_render_check=True)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    if mode == "filter":
        first = next(iter(info["agents"].values()))
        assert {"filter_intervened", "filter_correction", "filter_status_code"} <= set(first)


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("env_id", IDS)
def test_sb3_check_env_on_the_centralised_view(env_id, mode):
    pytest.importorskip("stable_baselines3", reason="stable-baselines3 is in the train extra")
    from stable_baselines3.common.env_checker import check_env

    check_env(make_gym(env_id, mode).unwrapped, warn=True, skip_render_check=True)


# ---------------------------------------------------------------------------------------------- TorchRL
def _torchrl():
    return pytest.importorskip("torchrl", reason="torchrl is not installed (it is in the dev extra)")


def _rollout_50(env):
    import torch

    torch.manual_seed(0)
    td = env.rollout(50, break_when_any_done=False)  # crosses episode ends (auto-reset)
    assert td.batch_size == torch.Size([50])
    return td


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("env_id", IDS)
def test_torchrl_gymenv(env_id, mode):
    _torchrl()
    from torchrl.envs import GymEnv
    from torchrl.envs.utils import check_env_specs

    # GymEnv probes the constructor with frameskip= and retries without it only on Python's TypeError wording
    extra = {} if mode == "bare" else {"safety_filter": {}}
    env = GymEnv(env_id, **SMALL[env_id], **FAST, **extra)
    check_env_specs(env, seed=0)
    td = _rollout_50(env)
    n = len(env._env.unwrapped.par.possible_agents)
    assert td["action"].shape == (50, 2 * n)
    assert td["next", "done"].any()  # max_steps=30: the rollout crossed an episode end


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("env_id", IDS)
def test_torchrl_pettingzoo_wrapper(env_id, mode):
    _torchrl()
    from torchrl.envs.libs.pettingzoo import PettingZooWrapper
    from torchrl.envs.utils import check_env_specs

    par = make_parallel(env_id, mode, infos="flat")  # TorchRL makes a tensor of every info value
    env = PettingZooWrapper(env=par, use_mask=True, done_on_any=False, seed=0)
    assert list(env.group_map) == ["robot"]
    check_env_specs(env, seed=0)
    td = _rollout_50(env)
    n = len(par.possible_agents)
    assert td["robot", "action"].shape == (50, n, 2)
    info = td["next", "robot", "info"]
    assert "clearance" in info.keys()
    if mode == "filter":
        assert {"filter_intervened", "filter_correction", "filter_status_code"} <= set(info.keys())


@pytest.mark.parametrize("mode", MODES)
def test_torchrl_pettingzoo_wrapper_with_agents_that_leave(mode):
    # TorchRL sends an action for every robot of the group, also for robots that are done: the env
    # ignores those (with one warning) like PettingZoo's own conversion wrappers do
    _torchrl()
    from torchrl.envs.libs.pettingzoo import PettingZooWrapper
    from torchrl.envs.utils import check_env_specs

    par = make_parallel("aasoatt/RandomGoals-v0", mode, infos="flat", num_robots=8, terminate_on_collision=True)
    env = PettingZooWrapper(env=par, use_mask=True, done_on_any=False, seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        check_env_specs(env, seed=0)
        td = _rollout_50(env)
    terminated = td["next", "robot", "terminated"]
    if mode == "bare":
        assert terminated.any()  # random actions collide: some robots left their episode mid-rollout
    else:
        assert not terminated.any()  # behind the filter nobody collides


def test_torchrl_rejects_nothing_but_the_nested_filter_infos():
    # the default nested infos hold a dict with a string: TorchRL cannot batch them, hence infos="flat"
    _torchrl()
    from torchrl.envs.libs.pettingzoo import PettingZooWrapper

    with pytest.raises(RuntimeError, match="infer dtype of dict"):
        PettingZooWrapper(env=make_parallel("aasoatt/CircleSwap-v0", "filter"), use_mask=True, seed=0)


def test_unknown_keyword_is_a_type_error_with_pythons_wording():
    # what TorchRL's GymEnv (and any caller probing optional keywords) matches on
    with pytest.raises(TypeError, match="unexpected keyword argument 'frameskip'"):
        aasoatt_env.make_env("circle_swap", frameskip=1)
    with pytest.raises(TypeError, match="unexpected keyword argument 'frameskip'"):
        gymnasium.make("aasoatt/CircleSwap-v0", frameskip=1)
