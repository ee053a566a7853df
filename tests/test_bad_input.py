"""Every bad input gets a clear error.

Each case either works or raises the documented error type with the parameter's
name in the message; no raw numpy / pickle / zip / JSON error escapes; a crafted
pickle is never executed.  Groups (the issue's): numeric and choice keywords of the
env, the scenarios, ``FilterConfig``, ``RewardConfig`` and ``RobotParams``;
``reset`` seeds and calls before ``reset``; actions; obstacles and custom
scenarios; size bounds; wrapper misuse; corrupted rollout files; model folders
(crafted pickles, crafted SB3 zips, corrupted files).
"""

from __future__ import annotations

import base64
import io
import json
import math
import os
import pickle
import re
import shutil
import time
import warnings
import zipfile
from dataclasses import fields
from pathlib import Path

import gymnasium
import numpy as np
import pytest
from helpers import tiny_train_config
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pettingzoo import ParallelEnv

import aasoatt_env
from aasoatt_env import validation as check
from aasoatt_env.analysis.recording import run_episode
from aasoatt_env.analysis.rollout import Rollout
from aasoatt_env.api.factory import make_env
from aasoatt_env.errors import (
    ActionError,
    ConfigError,
    DataFileError,
    ResetNeeded,
    ScenarioError,
    UnknownKeywordError,
    UsageError,
)
from aasoatt_env.model.params import RobotParams
from aasoatt_env.safety.config import FilterConfig
from aasoatt_env.safety.wrapper import AASOATTFilter
from aasoatt_env.sim.env import AASOATTParallelEnv
from aasoatt_env.sim.rewards import RewardConfig
from aasoatt_env.sim.scenarios import CircleSwap, RandomGoals
from agents import TrackingController

# --------------------------------------------------------------------------- junk for every keyword
JUNK: dict[str, object] = {
    "nan": float("nan"), "inf": float("inf"), "-inf": float("-inf"), "-1": -1, "1e308": 1e308, "True": True,
    "'2'": "2", "2+0j": 2 + 0j, "None": None, "[]": [], "10**400": 10**400,
}
"""The issue's junk (NaN, inf, -1, 1e308, True, "2", 2+0j, None, []) plus -inf and an int beyond the float range."""

# (owner, keyword) -> the junk labels that are valid values for it (documented: None = default/none,
# True for flags, inf = no limit, -1 within a signed range); every other junk value must be rejected.
_OPTIONAL = {"None"}
ACCEPTS: dict[tuple[str, str], set[str]] = {
    ("env", "max_steps"): _OPTIONAL, ("env", "render_mode"): _OPTIONAL, ("env", "reward"): _OPTIONAL,
    ("env", "terminate_on_collision"): {"True"}, ("env", "clip_actions"): {"True"},
    ("random_goals", "arena_size"): _OPTIONAL, ("random_goals", "min_spacing"): _OPTIONAL,
    ("random_goals", "robots"): _OPTIONAL, ("circle_swap", "robots"): _OPTIONAL,
    ("circle_swap", "obstacles"): _OPTIONAL, ("circle_obstacles", "obstacles"): _OPTIONAL,
    ("tracking", "robots"): _OPTIONAL, ("tracking", "reference"): _OPTIONAL,
    ("position_swap", "robots"): _OPTIONAL, ("custom", "headings"): _OPTIONAL, ("custom", "duration"): _OPTIONAL,
    ("custom", "obstacles"): _OPTIONAL, ("custom", "robots"): _OPTIONAL,
    ("filter", "sigma"): {"-1"}, ("filter", "rotation_deg"): {"-1"}, ("filter", "gate_range"): _OPTIONAL,
    ("filter", "safety_margin"): _OPTIONAL, ("filter", "max_wheel_speed"): _OPTIONAL,
    ("filter", "active_set"): {"True"}, ("filter", "decompose"): {"True"}, ("filter", "backup"): {"True"},
    ("filter", "backup_repair"): {"True"}, ("filter", "negotiate"): {"True"},
    ("robot", "max_wheel_speed"): {"inf"},
}

ENV_KEYWORDS = ["dt", "decision_interval", "action_mode", "sensing_range", "num_neighbors", "num_obstacles", "reward",
                "terminate_on_collision", "collision_tolerance", "max_steps", "clip_actions", "render_mode"]
SCENARIO_KEYWORDS = {
    "circle_swap": ["num_robots", "radius", "duration", "settle_time", "robots", "profile", "obstacles"],
    "circle_obstacles": ["num_robots", "radius", "duration", "settle_time", "obstacles"],
    "tracking": ["trajectory", "speed", "amplitude", "frequency", "circle_radius", "duration", "robots", "reference"],
    "position_swap": ["distance", "speed", "settle_time", "robots"],
    "random_goals": ["num_robots", "arena_size", "min_spacing", "speed", "settle_time", "robots", "random_obstacles"],
    "custom": ["starts", "reference", "duration", "headings", "obstacles", "robots", "settle_time"],
}
CUSTOM_BASE = {"starts": [[0.0, 0.0], [3.0, 0.0]],
               "reference": {"waypoints": [[[0.0, 0.0], [0.0, 3.0]], [[3.0, 0.0], [3.0, 3.0]]], "times": [0.0, 5.0]}}


def _build_and_step(**kw: object) -> None:
    """Construct, reset and step once (an accepted value must not fail later)."""
    env = make_env(**kw)
    env.reset(seed=0)
    env.step({a: np.zeros(2) for a in env.agents})
    env.close()


def _cases() -> list[tuple[str, str]]:
    out = [("env", k) for k in ENV_KEYWORDS]
    out += [(sc, k) for sc, ks in SCENARIO_KEYWORDS.items() for k in ks]
    out += [("filter", f.name) for f in fields(FilterConfig) if f.name != "dt"]
    out += [("reward", f.name) for f in fields(RewardConfig)]
    out += [("robot", f.name) for f in fields(RobotParams)]
    return out


def _attempt(owner: str, name: str, value: object) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if owner == "env":
            _build_and_step(scenario="circle_swap", num_robots=3, **{name: value})
        elif owner == "custom":
            _build_and_step(scenario="custom", **{**CUSTOM_BASE, name: value})
        elif owner == "filter":
            _build_and_step(scenario="circle_swap", num_robots=3, filter={"solver": "ldp", name: value})
        elif owner == "reward":
            _build_and_step(scenario="circle_swap", num_robots=3, reward={name: value})
        elif owner == "robot":
            _build_and_step(scenario="circle_swap", num_robots=3, robots=RobotParams(**{name: value}))
        else:
            _build_and_step(scenario=owner, **{name: value})


@pytest.mark.parametrize(("owner", "name"), _cases(), ids=lambda x: str(x))
def test_junk_for_every_keyword_is_rejected_with_its_name(owner: str, name: str) -> None:
    accepted = ACCEPTS.get((owner, name), set())
    for label, value in JUNK.items():
        try:
            _attempt(owner, name, value)
        except (ConfigError, TypeError) as exc:
            assert name in str(exc), f"{owner}.{name}={label}: message does not name it: {exc}"
            assert label not in accepted, f"{owner}.{name}={label} is documented as valid but raised {exc}"
        else:
            assert label in accepted, f"{owner}.{name}={label} was accepted silently"


@settings(max_examples=200, deadline=None)
@given(st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(), st.booleans(), st.text(max_size=3),
                 st.complex_numbers(), st.none(), st.lists(st.integers(), max_size=2), st.decimals()))
def test_validation_layer_never_lets_anything_else_escape(value: object) -> None:
    for fn, kwargs, ok in (
        (check.real, {"lo": 0.0, "hi": 10.0}, lambda v: 0.0 <= v <= 10.0),
        (check.positive, {}, lambda v: 0.0 < v <= check.MAGNITUDE_MAX),
        (check.positive, {"allow_inf": True}, lambda v: v == math.inf or 0.0 < v <= check.MAGNITUDE_MAX),
        (check.integer, {"lo": 1, "hi": 100}, lambda v: isinstance(v, int) and 1 <= v <= 100),
        (check.real, {}, lambda v: abs(v) <= check.MAGNITUDE_MAX),
    ):
        try:
            out = fn("param", value, **kwargs)
        except ConfigError as exc:
            assert str(exc).startswith("param: got ")
        else:
            assert not isinstance(value, (bool, str, complex)) and ok(out)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(name=st.sampled_from([f.name for f in fields(RobotParams) if f.name != "model"]),
       value=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(min_value=-10**30,
                                                                                   max_value=10**30)))
def test_robot_params_are_in_range_or_named(name: str, value: float) -> None:
    try:
        p = RobotParams(**{name: value})
    except ConfigError as exc:
        assert f"RobotParams.{name}" in str(exc)
    else:
        v = getattr(p, name)
        assert (1e-6 <= v <= 1e9) or (name == "max_wheel_speed" and v == math.inf)


@settings(max_examples=60, deadline=None)
@given(name=st.sampled_from([f.name for f in fields(RewardConfig)]),
       value=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(min_value=-10**30,
                                                                                   max_value=10**30)))
def test_reward_weights_are_finite_and_bounded(name: str, value: float) -> None:
    try:
        cfg = RewardConfig(**{name: value})
    except ConfigError as exc:
        assert name in str(exc)
    else:
        assert 0.0 <= getattr(cfg, name) <= check.MAGNITUDE_MAX


def test_unknown_keywords_are_type_errors_naming_them() -> None:
    with pytest.raises(TypeError, match="unexpected keyword argument 'frameskip'"):
        AASOATTParallelEnv("circle_swap", frameskip=4)
    with pytest.raises(UnknownKeywordError, match="'k9'"):
        FilterConfig.merged({"k9": 1})
    with pytest.raises(TypeError, match="'colision'"):
        RewardConfig.coerce({"colision": 1.0})
    with pytest.raises(TypeError, match="'frameskip'"):
        gymnasium.make("aasoatt/CircleSwap-v0", frameskip=4)


def test_issue_examples_of_silently_wrong_values() -> None:
    with pytest.raises(ConfigError, match="collision_tolerance"):
        AASOATTParallelEnv(collision_tolerance=float("nan"))
    with pytest.raises(ConfigError, match="num_robots"):
        AASOATTParallelEnv(num_robots=True)
    for dt in (100, 1e-300):
        with pytest.raises(ConfigError, match="dt"):
            AASOATTParallelEnv(dt=dt)
    with pytest.raises(ConfigError, match="settle_time"):
        RandomGoals(settle_time=-5)
    with pytest.raises(ConfigError, match="reward"):
        AASOATTParallelEnv(reward="x")
    with pytest.raises(ConfigError, match="reward"):
        AASOATTParallelEnv(reward=5)
    with pytest.raises(ConfigError, match="k1"):
        FilterConfig(k1="2")
    with pytest.raises(ConfigError, match="arena_size"):
        RandomGoals(arena_size=1e308)
    with pytest.raises(ConfigError, match="speed"):  # a derived duration beyond range names the input
        aasoatt_env.get_scenario("position_swap", speed=1e-300)


# --------------------------------------------------------------------------- reset, calls before reset
@pytest.mark.parametrize("seed", [-1, "abc", True, float("nan"), 2.5, [1]])
def test_bad_seeds(seed: object) -> None:
    for env in (AASOATTParallelEnv(num_robots=2), make_env("circle_swap", num_robots=2, filter=True)):
        with pytest.raises(ConfigError, match="seed"):
            env.reset(seed=seed)
    with pytest.raises(ConfigError, match="seed"):
        gymnasium.make("aasoatt/CircleSwap-v0", num_robots=2).reset(seed=seed)


def test_integral_seeds_work() -> None:
    env = AASOATTParallelEnv("random_goals", num_robots=3)
    a = env.reset(seed=3)[0]
    b = env.reset(seed=3.0)[0]
    c = env.reset(seed=np.int64(3))[0]
    assert all(np.array_equal(a[k], b[k]) and np.array_equal(a[k], c[k]) for k in a)
    with pytest.raises(ConfigError, match="options"):
        env.reset(seed=0, options=5)


@pytest.mark.parametrize("what", ["positions", "velocities", "headings", "wheel_speeds", "radii", "goals", "time",
                                  "reference", "obstacles", "kinematics", "layout", "max_steps", "state", "render",
                                  "step"])
def test_calls_before_reset_say_reset(what: str) -> None:
    env = AASOATTParallelEnv(render_mode="rgb_array", num_robots=2)
    with pytest.raises(ResetNeeded, match="reset"):
        attr = getattr(env, what)
        if callable(attr):
            attr({}) if what == "step" else attr()


# --------------------------------------------------------------------------- actions
BAD_ACTIONS = {
    "nan": [float("nan"), 0.0], "inf": [float("inf"), 0.0], "complex": [1 + 0j, 0.0], "numeric strings": ["1", "2"],
    "string": "ab", "None": None, "shape (1, 2)": [[1.0, 2.0]], "shape (3,)": [1.0, 2.0, 3.0], "object": {"a": 1},
    "huge int": [10**400, 0],
}


@pytest.mark.parametrize("label", list(BAD_ACTIONS))
@pytest.mark.parametrize("filtered", [False, True])
def test_bad_actions_name_the_agent(label: str, filtered: bool) -> None:
    env = make_env("circle_swap", num_robots=3, filter=filtered)
    env.reset(seed=0)
    acts = {a: np.zeros(2) for a in env.agents}
    acts["robot_1"] = BAD_ACTIONS[label]
    with pytest.raises(ActionError, match="robot_1"):
        env.step(acts)


def test_huge_nominal_behind_the_filter_is_refused_not_turned_into_inf() -> None:
    env = make_env("circle_swap", num_robots=3, filter=True)
    env.reset(seed=0)
    acts = {a: np.zeros(2) for a in env.agents}
    acts["robot_0"] = np.array([1e160, -1e160])
    with pytest.raises(ActionError, match=r"robot_0.*1e\+06"):
        env.step(acts)
    acts["robot_0"] = np.array([50.0, -50.0])  # a large but sane nominal: the filter keeps the bounds
    _, rew, _, _, infos = env.step(acts)
    assert all(math.isfinite(r) for r in rew.values())
    assert math.isfinite(infos["robot_0"]["filter"]["correction"]) and infos["robot_0"]["filter"]["status"] == "solved"


@pytest.mark.parametrize("actions", [[np.zeros(2)] * 3, None, "x", {"robot_0": np.zeros(2)}, {0: np.zeros(2)}])
def test_bad_action_dicts(actions: object) -> None:
    env = AASOATTParallelEnv(num_robots=3)
    env.reset(seed=0)
    with pytest.raises(ActionError, match="actions"):
        env.step(actions)


# --------------------------------------------------------------------------- obstacles, custom
@pytest.mark.parametrize(("obstacles", "match"), [
    (([[1.0, 2.0, 3.0]], [0.5]), r"obstacles: got centres of shape \(1, 3\), expected \(M, 2\)"),
    (([[5.0, 5.0]], [[0.5, 0.6]]), "obstacles: got 1 centres and 2 radii"),
    (([[5.0, 5.0]], [-0.5]), r"obstacles \(radii\)"),
    (([[5.0, float("nan")]], [0.5]), r"obstacles \(centres\)"),
    (([["a", "b"]], [0.5]), r"obstacles \(centres\)"),
    ("disc", "obstacles: got 'disc', expected a pair"),
    ((1, 2, 3), "obstacles: got"),
    (([[0.0, 6.0]], [0.5]), "obstacles: robot .* overlaps obstacle 0"),  # on a start of the circle
])
def test_obstacles_of_the_wrong_shape_or_place(obstacles: object, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        AASOATTParallelEnv("circle_swap", num_robots=4, obstacles=obstacles)


def test_obstacle_on_a_goal_is_refused() -> None:
    with pytest.raises(ScenarioError, match="overlaps obstacle"):
        AASOATTParallelEnv("circle_obstacles", num_robots=4, obstacles=([[-6.0, 0.0]], [0.5]))  # robot 0's goal
    with pytest.raises(ScenarioError, match="overlaps obstacle"):
        AASOATTParallelEnv("custom", **CUSTOM_BASE, obstacles=([[0.0, 3.0]], [0.4]))


def test_position_swap_too_small_to_hold_the_robots_is_refused() -> None:
    """Neighbouring corners are distance / sqrt(2) apart: below 2 r sqrt(2) the robots would start overlapping."""
    with pytest.raises(ScenarioError, match=r"distance: got 0.2 m, whose start corners do not hold the robots: "
                       r"robots 0 and 1 overlap \(0.141421356 m apart < 0.21 m"):
        AASOATTParallelEnv("position_swap", distance=0.2)
    _, infos = AASOATTParallelEnv("position_swap", distance=0.3).reset()  # just enough room
    assert min(info["clearance"] for info in infos.values()) == pytest.approx(0.3 / np.sqrt(2) - 0.21, abs=1e-9)
    # mixed radii: only neighbouring pairs count (0.707 m apart holds 0.48 + 0.105 m)
    AASOATTParallelEnv("position_swap", distance=1.0, robots=["paper", "turtlebot3_burger"] * 2).reset()


@pytest.mark.parametrize("n", [3, 6, 12, 39])
def test_robots_that_exactly_touch_at_the_start_are_accepted(n: int) -> None:
    """The circle holds N robots when neighbours touch (chord = d_s): the constructor and reset agree."""
    env = AASOATTParallelEnv("circle_swap", num_robots=n, radius=0.48 / np.sin(np.pi / n))
    _, infos = env.reset()
    assert min(info["clearance"] for info in infos.values()) == pytest.approx(0.0, abs=1e-9)
    _, infos = AASOATTParallelEnv("position_swap", distance=0.3).reset()  # just enough room
    assert min(info["clearance"] for info in infos.values()) == pytest.approx(0.3 / np.sqrt(2) - 0.21, abs=1e-9)


def test_a_user_scenario_that_starts_overlapping_is_refused_at_reset() -> None:
    """The env checks every layout, so a user's own Scenario subclass cannot start the filter inside a collision."""
    from aasoatt_env.sim.scenarios import PositionSwap

    class Overlapping(PositionSwap):
        name = "overlapping"

        def build(self, rng):
            layout = super().build(rng)
            layout.starts[1] = layout.starts[0] + 0.05
            return layout

    env = AASOATTParallelEnv(Overlapping())
    with pytest.raises(ScenarioError, match=r"scenario 'overlapping': starts: robots 0 and 1 overlap "
                       r"\(0.0707106781 m apart"):
        env.reset(seed=0)

    class NotFinite(PositionSwap):
        name = "not_finite"

        def build(self, rng):
            layout = super().build(rng)
            layout.starts[2] = np.nan
            return layout

    with pytest.raises(ScenarioError, match=r"scenario 'not_finite': starts: robot 2 at \[nan, nan\], expected "
                       r"finite coordinates"):
        AASOATTParallelEnv(NotFinite()).reset(seed=0)


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"starts": []}, r"starts: got shape \(0,\)"),
    ({"starts": [[0, 0, 0]]}, r"starts: got shape \(1, 3\)"),
    ({"starts": [["1", "2"]]}, "starts: got"),
    ({"starts": [[0.0, 0.0], [0.5, 0.0]]}, "starts: robots 0 and 1 overlap"),
    ({"reference": {"waypoints": [[[0, 0], [0, 3]], [[3, 0], [3, 3]]]}}, "waypoints without 'times'"),
    ({"reference": {"waypoints": [[[0, 0], [0, 3]], [[3, 0], [3, 3]]], "times": [1.0, 0.0]}}, "times: got"),
    ({"reference": {"waypoints": [[[0, 0], [0, 3]], [[3, 0], [3, 3]]], "times": [0.0, 1.0, 2.0]}}, "times: got"),
    ({"reference": 5}, "reference: got int"),
    ({"reference": lambda t: np.zeros((2, 2))}, "callable reference needs duration"),
    ({"duration": 5.0}, "duration: got 5 with a dict reference"),
    ({"headings": [0.0]}, r"headings: got shape \(1,\), expected \(2,\)"),
])
def test_custom_scenario_inputs(kwargs: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        AASOATTParallelEnv("custom", **{**CUSTOM_BASE, **kwargs})


# --------------------------------------------------------------------------- size bounds
@pytest.mark.parametrize(("build", "match"), [
    (lambda: RandomGoals(num_robots=10**6), r"num_robots: got 1000000, expected an integer in \[1, 100000\]"),
    (lambda: CircleSwap(num_robots=10**6), r"num_robots: got 1000000, expected an integer in \[1, 100000\]"),
    (lambda: AASOATTParallelEnv(num_neighbors=10**6), r"num_neighbors: got 1000000, expected an integer in \[0, 256\]"),
    (lambda: AASOATTParallelEnv(num_obstacles=10**7),
     r"num_obstacles: got 10000000, expected an integer in \[0, 256\]"),
    (lambda: AASOATTParallelEnv(decision_interval=10**9), r"decision_interval: .*\[1, 10000\]"),
])
def test_unreasonable_sizes_are_rejected_at_once(build, match: str) -> None:
    t0 = time.perf_counter()
    with pytest.raises(ConfigError, match=match):
        build()
    assert time.perf_counter() - t0 < 0.5


def test_twenty_thousand_random_robots_build_quickly() -> None:
    t0 = time.perf_counter()
    layout = RandomGoals(num_robots=20_000).build(np.random.default_rng(0))
    assert time.perf_counter() - t0 < 5.0
    from scipy.spatial import cKDTree

    d, _ = cKDTree(layout.starts).query(layout.starts, k=2)
    assert d[:, 1].min() >= RandomGoals(num_robots=20_000).min_spacing


def test_random_goals_near_the_cover_limit_places_every_robot_and_keeps_the_spacing() -> None:
    """12 robots 0.96 m apart in a 4.4 m arena (cover 0.449, inside the check): one try of the one-by-one sampler
    fails on some seeds; whole-set retries place them all on every seed."""
    scen = RandomGoals(num_robots=12, min_spacing=0.96, arena_size=4.4)
    for seed in range(10):
        layout = scen.build(np.random.default_rng(seed))
        for pts in (layout.starts, np.asarray(layout.reference.goals)):
            d = np.hypot(*(pts[:, None, :] - pts[None, :, :]).transpose(2, 0, 1))
            assert d[np.triu_indices(12, 1)].min() >= 0.96


# --------------------------------------------------------------------------- wrapper misuse
class _OtherEnv(ParallelEnv):  # a PettingZoo ParallelEnv that is not ours
    possible_agents = ["a"]


@pytest.mark.parametrize(("make", "error", "match"), [
    (lambda: AASOATTFilter(None), ConfigError, "env: got NoneType"),
    (lambda: AASOATTFilter(_OtherEnv()), ConfigError, "env: got _OtherEnv"),
    (lambda: AASOATTFilter(AASOATTParallelEnv(), config="x"), ConfigError, "config: got str"),
    (lambda: AASOATTFilter(AASOATTParallelEnv(), dt=0.01), ConfigError, "dt: got 0.01"),
    (lambda: AASOATTFilter(AASOATTParallelEnv(), k9=1.0), TypeError, "unexpected keyword argument 'k9'"),
    (lambda: AASOATTFilter(AASOATTParallelEnv(), barrier=[]), ConfigError, "barrier: got"),
    (lambda: AASOATTFilter(AASOATTParallelEnv(), barrier={}), ConfigError, "barrier: got"),
    (lambda: AASOATTFilter(AASOATTParallelEnv(), solver=["ldp"]), ConfigError, "solver: got"),
    (lambda: AASOATTFilter(AASOATTParallelEnv(), infos="table"), ConfigError, "infos: got 'table'"),
    (lambda: AASOATTFilter(AASOATTFilter(AASOATTParallelEnv())), UsageError, "already has a control filter"),
    (lambda: gymnasium.make("aasoatt/CircleSwap-v0", safety_filter="aasoatt"), ConfigError, "safety_filter"),
    (lambda: gymnasium.make("aasoatt/CircleSwap-v0", safety_filter={"k9": 1}), TypeError, "'k9'"),
])
def test_wrapper_misuse(make, error: type, match: str) -> None:
    with pytest.raises(error, match=match):
        make()


def test_wrapping_after_reset_works() -> None:
    env = AASOATTParallelEnv("circle_swap", num_robots=4)
    obs, _ = env.reset(seed=0)
    filt = AASOATTFilter(env, solver="ldp")
    _, _, _, _, infos = filt.step({a: np.zeros(2) for a in filt.agents})
    assert infos["robot_0"]["filter"]["status"] == "solved"
    with pytest.raises(UsageError, match="already has a control filter"):
        AASOATTFilter(env)


# --------------------------------------------------------------------------- corrupted rollout files
@pytest.fixture(scope="module")
def rollout_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    env = make_env("circle_swap", num_robots=3, max_steps=25)
    rollout, _ = run_episode(env, TrackingController(), seed=0)
    path = tmp_path_factory.mktemp("rollout") / "rollout.npz"
    rollout.save(path)
    return path


def _expect_load_error(path: Path, match: str | None = None) -> None:
    with pytest.raises(DataFileError, match=match) as exc:
        Rollout.load(path)
    assert str(path) in str(exc.value)


def test_rollout_text_file_is_refused_without_advice_to_unpickle(tmp_path: Path) -> None:
    """numpy's own message suggests ``allow_pickle=True``: ours says the file is not a rollout, and never unpickles."""
    path = tmp_path / "notes.txt"
    path.write_text("hello\n")
    match = r"not a readable rollout file \(not an .npz archive of plain arrays; files are never unpickled\)"
    with pytest.raises(DataFileError, match=match) as exc:
        Rollout.load(path)
    assert "allow_pickle" not in str(exc.value)


def test_make_env_checks_infos_without_a_filter() -> None:
    with pytest.raises(ConfigError, match=r"infos: got 'garbage', expected one of \['flat', 'nested'\]"):
        make_env("circle_swap", infos="garbage")


def test_rollout_truncated_empty_garbage(rollout_file: Path, tmp_path: Path) -> None:
    raw = rollout_file.read_bytes()
    bad = tmp_path / "bad.npz"
    for k in range(0, len(raw), max(1, len(raw) // 40)):
        bad.write_bytes(raw[:k])
        _expect_load_error(bad)
    bad.write_bytes(b"")
    _expect_load_error(bad)
    bad.write_bytes(os.urandom(2000))
    _expect_load_error(bad)
    _expect_load_error(tmp_path / "missing.npz", "no such rollout file")
    _expect_load_error(tmp_path)  # a folder
    np.save(tmp_path / "plain.npy", np.zeros(3))
    _expect_load_error(tmp_path / "plain.npy")


def test_rollout_flipped_bytes(rollout_file: Path, tmp_path: Path) -> None:
    raw = rollout_file.read_bytes()
    good = Rollout.load(rollout_file)
    bad = tmp_path / "flip.npz"
    for k in range(0, len(raw), max(1, len(raw) // 150)):
        b = bytearray(raw)
        b[k] ^= 0xFF
        bad.write_bytes(bytes(b))
        try:
            r = Rollout.load(bad)
        except DataFileError as exc:
            assert str(bad) in str(exc)
        else:  # a flip in zip metadata that no reader uses: the data are intact (CRC-checked)
            np.testing.assert_array_equal(r.positions, good.positions)


@pytest.mark.parametrize(("change", "match"), [
    ({"metadata": np.array("{not json")}, "not a readable rollout file"),
    ({"metadata": np.array("[1, 2]")}, "metadata"),
    ({"metadata": np.array("[" * 100_000 + "]" * 100_000)}, "not a readable rollout file"),
    ({"metadata": np.array([{"a": 1}], dtype=object)}, "not a readable rollout file"),  # would need pickle
    ({"dt": np.array("abc")}, "dt"),
    ({"dt": np.array(float("nan"))}, "dt"),
    ({"format_version": np.array(99)}, "format_version 99"),
    ({"positions": None}, "missing field 'positions'"),
    ({"positions": "nan"}, "positions: got a non-finite value"),
    ({"positions": "complex"}, "positions: got dtype complex"),
    ({"radii": np.array([-1.0, 1.0, 1.0])}, "radii"),
])
def test_rollout_bad_fields(rollout_file: Path, tmp_path: Path, change: dict, match: str) -> None:
    with np.load(rollout_file) as z:
        arrays = dict(z)
    for k, v in change.items():
        if v is None:
            del arrays[k]
        elif isinstance(v, str):
            arrays[k] = np.full(arrays[k].shape, np.nan) if v == "nan" else arrays[k].astype(complex)
        else:
            arrays[k] = v
    bad = tmp_path / "bad.npz"
    np.savez(bad, **arrays)
    _expect_load_error(bad, match)


def test_rollout_header_claiming_a_huge_array(rollout_file: Path, tmp_path: Path) -> None:
    bad = tmp_path / "huge.npz"
    with np.load(rollout_file) as z, zipfile.ZipFile(bad, "w") as out:
        for k, v in z.items():
            if k == "positions":
                continue
            buf = io.BytesIO()
            np.lib.format.write_array(buf, v)
            out.writestr(k + ".npy", buf.getvalue())
        hdr = io.BytesIO()
        np.lib.format.write_array_header_1_0(hdr, {"descr": "<f8", "fortran_order": False,
                                                   "shape": (10**7, 10**6, 2)})
        out.writestr("positions.npy", hdr.getvalue())
    _expect_load_error(bad, "too large")


def test_nan_positions_never_reach_the_metrics() -> None:
    with pytest.raises(ConfigError, match="positions: got a non-finite value"):
        Rollout(dt=0.1, times=[0.0, 0.1], positions=[[[0.0, 0.0]], [[np.nan, 0.0]]], velocities=np.zeros((2, 1, 2)),
                headings=np.zeros((2, 1)), references=np.zeros((2, 1, 2)), reference_velocities=np.zeros((2, 1, 2)),
                goals=[[0.0, 0.0]], radii=[0.5])


# --------------------------------------------------------------------------- model folders: nothing is unpickled


class _Evil:
    """Unpickling this creates ``marker``: the proof that a pickle was executed."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):  # noqa: ANN204
        return (Path.touch, (self.marker,))


@pytest.fixture(scope="module")
def model_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    pytest.importorskip("stable_baselines3")
    torch = pytest.importorskip("torch")

    from train.train import train

    torch.set_num_threads(1)
    return train(tiny_train_config(tmp_path_factory.mktemp("runs"), run_name="m")).parent


def _clone(run: Path, dest: Path) -> Path:
    shutil.copytree(run, dest)
    return dest


def _rewrite_data(model_zip: Path, edit, extra: dict[str, bytes] | None = None) -> None:
    tmp = model_zip.with_suffix(".tmp")
    with zipfile.ZipFile(model_zip) as src, zipfile.ZipFile(tmp, "w") as dst:
        for info in src.infolist():
            content = src.read(info.filename)
            if info.filename == "data" and edit is not None:
                content = json.dumps(edit(json.loads(content))).encode()
            if extra and info.filename in extra:
                content = extra[info.filename]
            dst.writestr(info.filename, content)
    tmp.replace(model_zip)


def _payload(marker: Path) -> str:
    return base64.b64encode(pickle.dumps(_Evil(marker))).decode()


def test_vecnormalize_pickle_is_never_opened(model_run: Path, tmp_path: Path) -> None:
    from agents.learned import LearnedAgent

    marker = tmp_path / "PWNED"
    run = _clone(model_run, tmp_path / "run")
    (run / "vecnormalize.pkl").write_bytes(pickle.dumps(_Evil(marker)))
    LearnedAgent.load(run)
    (run / "normalization.npz").unlink()
    with pytest.raises(DataFileError, match=r"normalization.npz: missing.*vecnormalize.pkl is there, but pickles "
                                            "are never loaded"):
        LearnedAgent.load(run)
    assert not marker.exists()


@pytest.mark.parametrize("key", ["policy_class", "_last_obs", "observation_space", "lr_schedule", "env", "new_key"])
def test_serialized_entries_of_a_model_zip_are_never_executed(model_run: Path, tmp_path: Path, key: str) -> None:
    from agents.learned import LearnedAgent

    marker = tmp_path / "PWNED"
    run = _clone(model_run, tmp_path / "run")
    _rewrite_data(run / "model.zip", lambda d: {**d, key: {":type:": "x", ":serialized:": _payload(marker)}})
    agent = LearnedAgent.load(run)
    env = agent.make_env()
    obs, _ = env.reset(seed=0)
    agent.reset(env)
    assert set(agent.act(obs, env)) == set(env.agents)
    assert not marker.exists()


@pytest.mark.parametrize(("edit", "match"), [
    (lambda m: lambda d: {**d, "policy_kwargs": {":type:": "x", ":serialized:": _payload(m)}}, "not plain JSON"),
    (lambda m: lambda d: {**d, "policy_kwargs": {**d["policy_kwargs"], "activation_fn": {":serialized:": _payload(m)}}},
     "unexpected keys"),
    (lambda m: lambda d: {**d, "policy_kwargs": {"net_arch": [10**8]}}, "net_arch"),
])
def test_crafted_policy_kwargs_are_refused(model_run: Path, tmp_path: Path, edit, match: str) -> None:
    from agents.learned import LearnedAgent

    marker = tmp_path / "PWNED"
    run = _clone(model_run, tmp_path / "run")
    _rewrite_data(run / "model.zip", edit(marker))
    with pytest.raises(DataFileError, match=match):
        LearnedAgent.load(run)
    assert not marker.exists()


@pytest.mark.parametrize("entry", ["pytorch_variables.pth", "policy.pth"])
def test_pickled_tensors_files_are_not_executed(model_run: Path, tmp_path: Path, entry: str) -> None:
    import torch

    from agents.learned import LearnedAgent

    marker = tmp_path / "PWNED"
    run = _clone(model_run, tmp_path / "run")
    buf = io.BytesIO()
    torch.save({"x": _Evil(marker)}, buf)
    _rewrite_data(run / "model.zip", None, extra={entry: buf.getvalue()})
    with pytest.raises(DataFileError, match="model.zip: cannot load the model"):
        LearnedAgent.load(run)
    assert not marker.exists()


def test_crafted_pickles_not_executed_by_the_cli(model_run: Path, tmp_path: Path) -> None:
    from aasoatt_env.apps.cli import main

    marker = tmp_path / "PWNED"
    run = _clone(model_run, tmp_path / "run")
    (run / "vecnormalize.pkl").write_bytes(pickle.dumps(_Evil(marker)))
    _rewrite_data(run / "model.zip", lambda d: {**d, "_last_obs": {":serialized:": _payload(marker)}})
    assert main(["evaluate", "--bare", str(run), "--episodes", "1", "--rows", "learned (bare)", "-q"]) == 0
    assert main(["run", "--scenario", "random_goals", "--robots", "3", "-p", "max_steps=5", "-p", "action_mode=point",
                 "--controller", "learned",
                 "--model", str(run), "--filter", "none", "-q"]) == 0
    assert not marker.exists()


@pytest.mark.parametrize("name", ["model.zip", "normalization.npz", "policy.json"])
def test_missing_or_empty_model_files_name_the_file(model_run: Path, tmp_path: Path, name: str) -> None:
    from agents.learned import LearnedAgent

    run = _clone(model_run, tmp_path / "run")
    (run / name).write_bytes(b"")
    with pytest.raises(DataFileError, match=name):
        LearnedAgent.load(run)
    (run / name).unlink()
    with pytest.raises(DataFileError, match="model here" if name == "model.zip" else name):
        LearnedAgent.load(run)


@pytest.mark.parametrize(("name", "content", "match"), [
    ("policy.json", "[1, 2]", "expected an object"),
    ("policy.json", '{"env": {"scenario": "random_goals", "num_robots": 3}, "policy": "MlpPolicy"}',
     "missing key 'normalize_obs'"),
    ("policy.json", '{"env": {"num_robots": -3}, "policy": "MlpPolicy", "normalize_obs": true}', "env settings"),
    ("policy.json", '{"env": {}, "policy": "EvilPolicy", "normalize_obs": false}', "policy 'EvilPolicy' is unknown"),
    ("policy.json", '{"env": {}, "policy": "MlpPolicy", "normalize_obs": false, "filter": {"k9": 1}}',
     "filter settings"),
    ("policy.json", "[" * 100_000, "not a readable JSON file"),
])
def test_corrupted_policy_json(model_run: Path, tmp_path: Path, name: str, content: str, match: str) -> None:
    from agents.learned import LearnedAgent

    run = _clone(model_run, tmp_path / "run")
    (run / name).write_text(content)
    with pytest.raises(DataFileError, match=match) as exc:
        LearnedAgent.load(run)
    assert name in str(exc.value)


def test_bad_normalisation_statistics(model_run: Path, tmp_path: Path) -> None:
    from agents.learned import LearnedAgent

    run = _clone(model_run, tmp_path / "run")
    with np.load(run / "normalization.npz") as z:
        stats = dict(z)
    for change in ({"mean": stats["mean"] * np.nan}, {"var": -stats["var"]}, {"clip_obs": np.array([1.0, 2.0])},
                   {"epsilon": np.array("x")}, {"mean": stats["mean"][:-1]}, {"mean": stats["mean"].astype(complex)}):
        np.savez(run / "normalization.npz", **{**stats, **change})
        with pytest.raises(DataFileError, match="normalization.npz"):
            LearnedAgent.load(run)


def test_config_json_is_not_needed(model_run: Path, tmp_path: Path) -> None:
    from agents.learned import LearnedAgent

    run = _clone(model_run, tmp_path / "run")
    (run / "config.json").write_text("{corrupted")
    LearnedAgent.load(run)  # the agent reads policy.json; config.json is a record of the training run


@pytest.mark.slow
@pytest.mark.parametrize("name", ["model.zip", "normalization.npz", "policy.json"])
def test_every_flipped_or_truncated_model_file_names_itself(model_run: Path, tmp_path: Path, name: str) -> None:
    from agents.learned import LearnedAgent

    raw = (model_run / name).read_bytes()
    run = _clone(model_run, tmp_path / "run")
    step = max(1, len(raw) // 40)
    for mode in ("flip", "truncate"):
        for k in range(0, len(raw), step):
            b = bytearray(raw)
            if mode == "flip":
                b[k] ^= 0xFF
            else:
                b = b[:k]
            (run / name).write_bytes(bytes(b))
            try:
                LearnedAgent.load(run)
            except DataFileError as exc:
                assert name in str(exc)
    (run / name).write_bytes(raw)


@pytest.mark.parametrize("action", [np.zeros(4, complex), ["1"] * 4, np.full(4, np.nan), None, np.zeros(3)])
def test_bad_joint_actions_of_the_gymnasium_view(action: object) -> None:
    env = gymnasium.make("aasoatt/CircleSwap-v0", num_robots=2)
    env.reset(seed=0)
    with pytest.raises(ActionError, match="action"):
        env.step(action)


# --------------------------------------------------------------------------- training and evaluation options
TRAIN_CONFIGS = {
    "seed 2**32": ({"seed": 2**32}, r"TrainConfig.seed: got 4294967296, expected an integer in \[0, 2147483647\]"),
    "seed 2**63-1": ({"seed": 2**63 - 1}, r"TrainConfig.seed: got 9223372036854775807"),
    "NUL in run_name": ({"run_name": "a\x00b"}, r"TrainConfig.run_name: got 'a\\x00b', expected a path without NUL"),
    "NUL in out_dir": ({"out_dir": "o\x00d"}, r"TrainConfig.out_dir: got 'o\\x00d', expected a path without NUL"),
    "n_steps 1e9": ({"n_steps": 10**9}, r"TrainConfig.n_steps: got 1000000000, expected an integer in \[1, 65536\]"),
    "n_steps * slots": ({"n_steps": 60_000}, r"TrainConfig.n_steps: got 60000, expected at most 10922 with 192 slots"),
    "ent_coef 1e300": ({"ent_coef": 1e300}, r"TrainConfig.ent_coef: got 1e\+300, expected a finite number in \[0, 10"),
    "vf_coef 1e300": ({"vf_coef": 1e300}, r"TrainConfig.vf_coef: got 1e\+300, expected a finite number in \[0, 100\]"),
    "velocity_tracking 1e300": ({"velocity_tracking": 1e300}, r"TrainConfig.velocity_tracking: got 1e\+300"),
    "max_grad_norm inf": ({"max_grad_norm": 1e300}, r"TrainConfig.max_grad_norm: got 1e\+300"),
    "run_name '.'": ({"run_name": "."}, r"TrainConfig.run_name: got '.', expected a folder name \(no path separators"),
    "run_name '..'": ({"run_name": ".."}, r"TrainConfig.run_name: got '..', expected a folder name"),
    "run_name a/b": ({"run_name": "a/b"}, r"TrainConfig.run_name: got 'a/b', expected a folder name"),
    "filter dt replaced": ({"filter": True, "filter_kwargs": {"dt": 0.01}},
                           r"TrainConfig.filter_kwargs.dt: got 0.01, expected the env's dt = 0.005"),
    "300-character out_dir": ({"out_dir": "x" * 300}, r"TrainConfig.out_dir: got a path whose part 'x+'... has 300 "
                                                       r"bytes, expected names of at most 200"),
    "300-character run_name": ({"run_name": "y" * 300}, r"TrainConfig.run_name: got a path whose part"),
    "empty out_dir": ({"out_dir": ""}, r"TrainConfig.out_dir: got '', expected a non-empty path"),
    "n_envs 1e6": ({"n_envs": 10**6}, r"TrainConfig.n_envs: got 1000000, expected an integer in \[1, 4096\]"),
    "n_envs x robots": ({"n_envs": 4096, "num_robots": 20}, r"TrainConfig.n_envs: got 4096, expected at most 3276 "
                                                             r"with 20 robots"),
    "total_timesteps 1e15": ({"total_timesteps": 10**15}, r"TrainConfig.total_timesteps: got 1000000000000000"),
    "n_epochs 1e6": ({"n_epochs": 10**6}, r"TrainConfig.n_epochs: got 1000000, expected an integer in \[1, 1000\]"),
    "neural_iterations": ({"filter": True, "filter_kwargs": {"solver": "neural", "neural_iterations": 10**4}},
                          r"TrainConfig.filter_kwargs.neural_iterations: got 10000, expected at most 1000"),
    "eval_episodes 1e9": ({"eval_episodes": 10**9}, r"TrainConfig.eval_episodes: got 1000000000"),
    "resume with init_from": ({"resume": "a", "init_from": "b"}, r"TrainConfig.init_from: got 'b' with resume='a'"),
    "NUL in resume": ({"resume": "r\x00"}, r"TrainConfig.resume: got 'r\\x00', expected a path without NUL"),
}


@pytest.mark.parametrize("case", list(TRAIN_CONFIGS))
def test_training_configs_are_refused_with_status_2_before_any_folder(tmp_path: Path, capsys, case: str) -> None:
    """Each bad config (from a JSON file: NUL and huge integers pass through it) is one line, exit 2, no folder."""
    pytest.importorskip("stable_baselines3")
    from train.train import main

    change, match = TRAIN_CONFIGS[case]
    out = tmp_path / "runs"
    data = {"out_dir": str(out), **change}
    (tmp_path / "run.json").write_text(json.dumps(data))
    t0 = time.perf_counter()
    assert main(["--config", str(tmp_path / "run.json")]) == 2
    assert time.perf_counter() - t0 < 2.0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and re.search(match, err), err
    assert "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.json"]  # no folder made


@pytest.mark.parametrize("value", [np.int64(2), 2.0, np.int32(2)])
def test_integral_sizes_are_integers_whatever_their_type(tmp_path: Path, value: object) -> None:
    from train.config import TrainConfig
    from train.rllib import RLlibConfig

    cfg = tiny_train_config(tmp_path, n_envs=value, seed=value, n_steps=value * 8)
    assert (cfg.n_envs, cfg.seed, cfg.n_steps) == (2, 2, 16) and type(cfg.n_envs) is int
    assert RLlibConfig(num_envs_per_env_runner=value, iterations=value).num_envs_per_env_runner == 2
    assert TrainConfig(out_dir=str(tmp_path), n_envs=value, batch_size=value * 64).n_envs == 2
    with pytest.raises(ConfigError, match=r"TrainConfig.n_envs: got 2.5"):
        TrainConfig(n_envs=2.5)


RLLIB_CONFIGS = {
    "iterations 1e9": ({"iterations": 10**9}, r"RLlibConfig.iterations: got 1000000000, expected an integer in"),
    "teams 1e6": ({"num_envs_per_env_runner": 10**6}, r"RLlibConfig.num_envs_per_env_runner: got 1000000"),
    "batch 1e9": ({"train_batch_size": 10**9}, r"RLlibConfig.train_batch_size: got 1000000000"),
    "seed 2**32": ({"seed": 2**32}, r"RLlibConfig.seed: got 4294967296"),
    "runners 1e5": ({"num_env_runners": 10**5}, r"RLlibConfig.num_env_runners: got 100000"),
    "timeout 1e300": ({"sample_timeout_s": 1e300}, r"RLlibConfig.sample_timeout_s: got 1e\+300"),
    "terminate_on_collision": ({"terminate_on_collision": True}, r"RLlibConfig.terminate_on_collision: got True"),
    "NUL in run_name": ({"run_name": "x\x00"}, r"RLlibConfig.run_name: got 'x\\x00'"),
    "filter dt": ({"filter_kwargs": {"dt": 0.01}}, r"RLlibConfig.filter_kwargs.dt: got 0.01"),
}


@pytest.mark.parametrize("case", list(RLLIB_CONFIGS))
def test_rllib_configs_are_refused_with_status_2(tmp_path: Path, capsys, case: str) -> None:
    from aasoatt_env.apps.cli import main

    change, match = RLLIB_CONFIGS[case]
    (tmp_path / "run.json").write_text(json.dumps({"out_dir": str(tmp_path / "runs"), **change}))
    assert main(["train", "--backend", "rllib", "--config", str(tmp_path / "run.json")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and re.search(match, err), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.json"]


@pytest.mark.parametrize(("out", "match"), [
    ("", r"--out: got '', expected a non-empty path"),
    ("z" * 300 + ".md", r"--out: got a path whose part 'z+'... has 303 bytes, expected names of at most 200"),
    ("dir/", r"--out: got '.*dir/', expected a file path such as results.md"),
])
def test_evaluate_out_is_checked_before_any_episode(tmp_path: Path, capsys, no_work, out: str, match: str) -> None:
    from aasoatt_env.apps.cli import main

    assert main(["evaluate", "--rows", "random", "--episodes", "1", "--out", f"{tmp_path}/{out}" if out else ""]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and re.search(match, err), err
    assert list(tmp_path.iterdir()) == []
