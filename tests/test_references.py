"""Reference trajectories: per-robot durations and the batched env's stacked evaluation."""

from __future__ import annotations

import numpy as np
import pytest

from aasoatt_env.errors import ConfigError
from aasoatt_env.sim.references import FunctionReference, LinearReference, ReferenceStack


def _line(rng: np.random.Generator, n: int, duration, profile: str = "linear") -> LinearReference:
    starts = rng.uniform(-3, 3, (n, 2))
    return LinearReference(starts, starts + rng.uniform(-2, 2, (n, 2)), duration, profile=profile)


def test_per_robot_durations_travel_and_rest() -> None:
    starts = np.array([[0.0, 0.0], [1.0, 1.0]])
    goals = np.array([[2.0, 0.0], [1.0, 4.0]])
    ref = LinearReference(starts, goals, np.array([2.0, 3.0]))
    assert ref.duration == 3.0
    p, v, a = ref(1.0)
    np.testing.assert_allclose(p, [[1.0, 0.0], [1.0, 2.0]])
    np.testing.assert_allclose(v, [[1.0, 0.0], [0.0, 1.0]])
    p, v, a = ref(2.5)  # robot 0 rests at its goal, robot 1 still travels
    np.testing.assert_array_equal(p[0], goals[0])
    np.testing.assert_array_equal(v[0], [0.0, 0.0])
    np.testing.assert_allclose(p[1], [1.0, 3.5])
    np.testing.assert_array_equal(a, 0.0)
    p, v, _ = ref(-1.0)  # before the start: at the start, moving off
    np.testing.assert_array_equal(p, starts)


@pytest.mark.parametrize("duration", [np.array([1.0, -2.0]), np.array([1.0, 2.0, 3.0]), np.array([1.0, np.nan])])
def test_bad_durations_are_named(duration) -> None:
    with pytest.raises(ConfigError, match="duration"):
        LinearReference(np.zeros((2, 2)), np.ones((2, 2)), duration)


@pytest.mark.parametrize("profile", ["linear", "smooth"])
def test_stack_equals_each_reference_exactly(profile: str) -> None:
    rng = np.random.default_rng(3)
    refs = [_line(rng, 4, rng.uniform(1, 5, 4), profile), _line(rng, 4, 2.5, profile), _line(rng, 4, 0.7, profile)]
    stack = ReferenceStack(refs)
    for times in ([0.0, 0.0, 0.0], [0.3, 2.4, 0.69], [1.7, 7.0, 0.7], [-0.1, 2.5, 10.0]):
        got = stack(times)
        for i in range(3):
            want = np.concatenate([r(t)[i] for r, t in zip(refs, times)])
            np.testing.assert_array_equal(got[i], want)


def test_stack_of_other_references_calls_each() -> None:
    rng = np.random.default_rng(4)
    lin = _line(rng, 3, 2.0)
    fn = FunctionReference(lambda t: np.full((3, 2), t), 4.0)
    stack = ReferenceStack([lin, fn])
    got = stack([1.0, 2.0])
    np.testing.assert_array_equal(got[0], np.concatenate((lin(1.0)[0], np.full((3, 2), 2.0))))
    with pytest.raises(ConfigError, match="times: got 1 times, expected one per team"):
        stack([1.0])
