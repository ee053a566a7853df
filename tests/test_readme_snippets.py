"""The code snippets of README.md (minimal example, safety filter, RL libraries), run as written.

Only the training budgets are shrunk (the replaced texts must be there exactly once).
The RLlib commands are run by ``tests/test_rllib.py`` (in the virtual environment of the ``rllib`` extra).
"""

from __future__ import annotations

import warnings

import pytest
from readme_blocks import readme_block, shrink


def _run(code: str) -> dict:
    torch = pytest.importorskip("torch")
    torch.set_num_threads(1)
    namespace: dict = {"__name__": "readme_snippet"}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # TorchRL: "tested with PettingZoo 1.24.3"
        exec(compile(code, "README.md", "exec"), namespace)
    return namespace


@pytest.mark.slow
def test_readme_sb3_parameter_sharing_snippet():
    pytest.importorskip("stable_baselines3", reason="stable-baselines3 is in the train extra")
    ns = _run(shrink(readme_block("sb3-shared"), {"[make] * 4": "[make] * 1",
                                                   "total_timesteps=6_144": "total_timesteps=1"}))
    assert ns["model"].num_timesteps == 256 * 6  # one rollout: n_steps per robot slot


def test_readme_sb3_centralised_snippet():
    pytest.importorskip("stable_baselines3", reason="stable-baselines3 is in the train extra")
    ns = _run(shrink(readme_block("sb3-centralised"), {"n_steps=512": "n_steps=64",
                                                        "total_timesteps=1_024": "total_timesteps=1"}))
    assert ns["model"].num_timesteps == 64


def test_readme_torchrl_snippet():
    pytest.importorskip("torchrl", reason="torchrl is not installed (it is in the dev extra)")
    ns = _run(readme_block("torchrl"))
    td = ns["td"]
    assert td.batch_size[0] == 100
    assert td["next", "robot", "info", "filter_intervened"].shape == (100, 6)


def test_readme_batched_snippet():
    ns = _run(readme_block("batched"))
    envs = ns["envs"]
    assert ns["obs"].shape == (8, 6, envs.agent_observation_space.shape[0])
    assert ns["rewards"].shape == (8, 6) and envs.live.shape == (8, 6)


def test_readme_filter_snippet():
    ns: dict = {"__name__": "readme_snippet"}  # (core dependencies only: no torch)
    exec(compile(readme_block("filter"), "README.md", "exec"), ns)
    assert ns["result"].status == "solved" and ns["result"].intervened.all()
    assert (ns["du_safe"] < ns["du_nominal"]).all() and (ns["du_safe"] <= ns["hi"]).all()


def test_readme_torch_snippet():
    ns = _run(readme_block("torch"))
    assert ns["obs"].shape == (256, 6, ns["envs"].obs_dim) and ns["rewards"].shape == (256, 6)
    assert float(ns["infos"]["clearance"].min()) >= -1e-3


@pytest.mark.slow
def test_readme_minimal_example():
    code = readme_block("minimal")
    namespace: dict = {"__name__": "readme_snippet"}
    exec(compile(code, "README.md", "exec"), namespace)
    env = namespace["env"]
    assert not env.agents  # the episode ran to its end
    gaps = [i["clearance"] for i in namespace["infos"].values()]
    assert min(gaps) > -1e-3 and "SafetyFilter(mode=centralized" in repr(env.filter)
