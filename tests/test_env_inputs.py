"""Inputs the envs refuse: booleans among actions, references that are not finite (named, nothing stepped)."""

from __future__ import annotations

import numpy as np
import pytest

from aasoatt_env import make_batched_env, make_env
from aasoatt_env.errors import ActionError, ResetNeeded, ScenarioError
from aasoatt_env.sim.sharded import ShardedBatchedEnv

torch = pytest.importorskip("torch")

_BOOL = r"\(a float or integer dtype\)"


@pytest.mark.parametrize("bad", [[True, True], np.array([True, False]), torch.tensor([True, True]), [0.5, True]],
                         ids=["list", "numpy", "torch", "mixed"])
@pytest.mark.parametrize("filtered", [False, True])
def test_one_robots_boolean_action_among_numbers_is_refused_naming_it(bad: object, filtered: bool) -> None:
    env = make_env("circle_swap", num_robots=3, filter=filtered)
    env.reset(seed=0)
    before = env.positions
    acts: dict[str, object] = {a: np.full(2, 0.5, np.float32) for a in env.agents}
    acts["robot_1"] = bad
    with pytest.raises(ActionError, match=r"actions\['robot_1'\]: got .*" + _BOOL):
        env.step(acts)
    np.testing.assert_array_equal(env.positions, before)  # nothing stepped
    acts = {a: torch.full((2,), 0.5) for a in env.agents}  # float tensors are numbers
    env.step(acts)


@pytest.mark.parametrize("make", [
    lambda: [[[0.1, 0.2], [0.0, 0.0], [0.0, 0.0]], [[0.0, 0.0], [True, True], [0.0, 0.0]]],
    lambda: [torch.zeros(3, 2), torch.tensor([[0.0, 0.0], [True, True], [0.0, 0.0]]).bool()],
    lambda: [np.zeros((3, 2)), np.ones((3, 2), dtype=bool)],
], ids=["nested lists", "torch per team", "numpy per team"])
def test_a_boolean_entry_of_batched_actions_is_refused_naming_the_team(make) -> None:
    batch = make_batched_env(2, "random_goals", num_robots=3)
    batch.reset(seed=0)
    with pytest.raises(ActionError, match=r"actions\[1(, 1)?\]: got booleans, expected real numbers of shape "
                                          r"\(2, 3, 2\) " + _BOOL):
        batch.step(make())
    with pytest.raises(ActionError, match=r"actions: got shape \(2, 3, 2\) \(dtype bool\)"):
        batch.step(torch.zeros((2, 3, 2), dtype=torch.bool))
    assert (batch.elapsed_steps == 0).all()


def test_the_sharded_env_refuses_a_boolean_entry_with_the_same_check() -> None:
    fns = [lambda: make_env("random_goals", num_robots=3) for _ in range(4)]
    sharded = ShardedBatchedEnv(fns, 2)
    try:
        sharded.reset(seed=0)
        acts = [[[0.0, 0.0]] * 3 for _ in range(4)]
        acts[3][2] = [True, False]
        with pytest.raises(ActionError, match=r"actions\[3, 2\]: got booleans"):
            sharded.step(acts)
        assert (sharded.elapsed_steps == 0).all()
    finally:
        sharded.close()


class _Reference:
    """A user's reference whose velocity is NaN for ``0.05 < t < 1`` (or from the start)."""

    goals = np.array([[5.0, 0.0], [3.0, 5.0]])
    duration = 5.0

    def __init__(self, bad_from: float = 0.05) -> None:
        self.bad_from = bad_from

    def __call__(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        starts = np.array([[0.0, 0.0], [3.0, 0.0]])
        p = starts + (self.goals - starts) * min(max(t, 0.0) / 5.0, 1.0)
        v = np.zeros((2, 2))
        v[1, 0] = np.nan if self.bad_from < t < 1.0 or (self.bad_from < 0 and t < 1.0) else 0.0
        return p, v, np.zeros((2, 2))


@pytest.mark.parametrize("filtered", [False, True])
def test_a_reference_that_is_nan_at_reset_is_refused_and_leaves_no_episode(filtered: bool) -> None:
    # sqrt(t) differentiated by central differences: NaN at t = 0 - h
    env = make_env("custom", starts=[[0.0, 0.0], [3.0, 0.0]], duration=5.0, filter=filtered,
                   reference=lambda t: np.array([[np.sqrt(t), 0.0], [3.0, np.sqrt(t)]]))
    with pytest.warns(RuntimeWarning), pytest.raises(
            ScenarioError, match=r"reference \(FunctionReference\) v_d at t = 0 s: got a non-finite value \[nan, "
                                 r"0\.0\] for robot 0, expected finite values"):
        env.reset(seed=0)
    with pytest.raises(ResetNeeded, match="reset"):
        env.step({a: np.zeros(2) for a in env.possible_agents})


@pytest.mark.parametrize("filtered", [False, True])
def test_a_reference_that_turns_nan_during_the_episode_is_refused_at_that_step(filtered: bool) -> None:
    env = make_env("custom", starts=[[0.0, 0.0], [3.0, 0.0]], reference=_Reference(), filter=filtered)
    env.reset(seed=0)
    for _ in range(10):  # t = 0.05 s
        env.step({a: np.zeros(2) for a in env.agents})
    time, poses = env.time, env.poses
    with pytest.raises(ScenarioError, match=r"reference \(_Reference\) v_d at t = 0\.055 s: got a non-finite "
                                            r"value \[nan, 0\.0\] for robot 1, expected finite values"):
        env.step({a: np.zeros(2) for a in env.agents})
    assert env.time == time  # the step that met it left the state as it was
    np.testing.assert_array_equal(env.poses, poses)


def test_the_batched_env_names_the_team_of_a_nan_reference() -> None:
    batch = make_batched_env(2, "custom", starts=[[0.0, 0.0], [3.0, 0.0]], reference=_Reference(-1.0))
    with pytest.raises(ScenarioError, match=r"v_d at t = 0 s: got a non-finite value \[nan, 0\.0\] for robot 1"):
        batch.reset(seed=0)
    batch = make_batched_env(2, "custom", starts=[[0.0, 0.0], [3.0, 0.0]], reference=_Reference(),
                             decision_interval=20)
    batch.reset(seed=0)
    with pytest.raises(ScenarioError, match=r"v_d at t = 0\.1 s: got a non-finite value \[nan, 0\.0\] for robot 1 "
                                            r"of team 0"):
        batch.step(np.zeros((2, 2, 2)))
    assert (batch.elapsed_steps == 0).all()


def test_the_gymnasium_view_refuses_a_boolean_entry_of_the_joint_action() -> None:
    import gymnasium

    env = gymnasium.make("aasoatt/CircleSwap-v0", num_robots=2)
    env.reset(seed=0)
    with pytest.raises(ActionError, match=r"action\[1\]: got booleans, expected \(4,\) real numbers " + _BOOL):
        env.step([0.1, True, 0.0, 0.0])
    env.step(np.zeros(4))
