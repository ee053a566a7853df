"""The AASOATTFilter wrapper on the PettingZoo env: contract, infos, bounds, safety under bad policies."""

import gymnasium
import numpy as np
import pettingzoo
import pytest
from pettingzoo.test import parallel_api_test

import aasoatt_env  # noqa: F401
from aasoatt_env import AASOATTGymEnv, AASOATTParallelEnv, ConfigError, SolverError
from aasoatt_env.analysis.recording import run_episode
from aasoatt_env.safety import SafetyFilter
from aasoatt_env.safety.wrapper import AASOATTFilter
from agents import HostileAgent, RandomAgent, TrackingController

FILTER_KEYS = {
    "intervened",
    "avoiding",
    "triggered",
    "correction",
    "status",
    "slack",
    "iterations",
    "n_rows",
    "n_qp_rows",
}


@pytest.mark.parametrize(
    "env_id", ["aasoatt/CircleSwap-v0", "aasoatt/CircleSwapObstacles-v0", "aasoatt/RandomGoals-v0"]
)
def test_wrapped_env_keeps_the_pettingzoo_contract(env_id):
    env = AASOATTFilter(pettingzoo.make("parallel", env_id, max_steps=40, decision_interval=2))
    parallel_api_test(env, num_cycles=60)


def test_infos_carry_filter_report_and_bounds_hold_for_unbounded_nominal():
    env = AASOATTFilter(AASOATTParallelEnv("circle_swap", num_robots=6, radius=2.0, duration=3.0))
    obs, infos = env.reset(seed=0)
    assert FILTER_KEYS <= set(infos["robot_0"]["filter"])
    team = env.unwrapped.team
    for _ in range(200):
        u0 = env.unwrapped.wheel_speeds
        obs, _, _, _, infos = env.step({a: np.array([7.0, -9.0], np.float32) for a in env.agents})
        du = (env.unwrapped.wheel_speeds - u0) / env.unwrapped.dt
        assert np.all(np.abs(du) <= team.max_wheel_accel[:, None] + 1e-6)
    f = infos["robot_0"]["filter"]
    assert f["status"] in ("solved", "relaxed") and f["intervened"]
    assert f["correction"] > 0


@pytest.mark.parametrize("mode", ["nested", "flat"])
def test_each_agents_filter_info_is_its_own_robots_report_in_python_types(mode):
    env = AASOATTFilter(AASOATTParallelEnv("circle_swap", num_robots=8, radius=1.6, duration=2.0), infos=mode)
    env.reset(seed=0)
    rng = np.random.default_rng(1)
    seen = 0
    for _ in range(30):
        _, _, _, _, infos = env.step({a: rng.uniform(-1, 1, 2).astype(np.float32) for a in env.agents})
        rep = env.report
        for agent, info in infos.items():
            i = env.unwrapped.agent_index[agent]
            f = info["filter"] if mode == "nested" else {k[len("filter_"):]: v for k, v in info.items()
                                                         if k.startswith("filter_")}
            assert type(f["correction"]) is float and f["correction"] == float(rep.correction[i]), agent
            want = (bool, "intervened") if mode == "nested" else (float, "intervened")
            assert type(f[want[1]]) is want[0] and bool(f["intervened"]) == bool(rep.intervened[i]), agent
            assert bool(f["backup"]) == bool(rep.backup[i]) and bool(f["avoiding"]) == bool(rep.avoiding[i]), agent
            seen += int(bool(f["intervened"]))
    assert seen > 0  # the check above saw robots the filter corrected, not only idle ones


def test_filter_is_applied_at_every_physics_step_of_a_decision_interval():
    env = AASOATTFilter(
        AASOATTParallelEnv("circle_swap", num_robots=4, radius=1.5, duration=2.0, decision_interval=10)
    )
    obs, _ = env.reset(seed=0)
    ctrl = TrackingController()
    clearance, qp_steps = np.inf, 0
    while env.agents:
        obs, _, _, _, infos = env.step(ctrl.act(obs, env))
        clearance = min(clearance, min(i["clearance"] for i in infos.values()))
        assert len(env.unwrapped.filter_outputs) == 10  # every physics step of the decision was filtered
        f = infos["robot_0"]["filter"]
        assert 0 <= f["n_qp_rows"] <= f["n_rows"] <= 6
        qp_steps += f["iterations"] > 0
    assert clearance >= -1e-3
    assert qp_steps > 0  # the crossing needed the QP at some decision


def test_paper_method_circle_swap_10_robots_safe_and_home():
    env = AASOATTFilter(
        AASOATTParallelEnv("circle_swap", num_robots=10, radius=6.0, duration=12.0, settle_time=3.0)
    )
    rollout, _ = run_episode(env, TrackingController(), seed=0)
    d = np.linalg.norm(rollout.positions[:, :, None] - rollout.positions[:, None], axis=-1)
    d[:, np.arange(10), np.arange(10)] = np.inf
    assert d.min() >= 0.96 - 1e-3
    assert not np.any(rollout.solver_status == "failed")
    assert np.linalg.norm(rollout.positions[-1] - rollout.goals, axis=1).max() <= 0.05
    assert rollout.avoiding.any()


@pytest.mark.parametrize("agent", [RandomAgent(seed=0), HostileAgent()], ids=["random", "hostile"])
def test_bad_policies_behind_the_filter_never_collide(agent):
    env = AASOATTFilter(AASOATTParallelEnv("random_goals", num_robots=20, max_steps=600))
    for seed in (0, 1):
        obs, infos = env.reset(seed=seed)
        agent.reset(env)
        worst = np.inf
        while env.agents:
            obs, _, _, _, infos = env.step(agent.act(obs, env))
            worst = min(worst, min(i["clearance"] for i in infos.values()))
            assert not any(i["collision"] for i in infos.values())
            assert all(i["filter"]["status"] != "failed" for i in infos.values())
        assert worst >= -1e-3


def _hostile_worst_clearance(env, seed):
    obs, _ = env.reset(seed=seed)
    agent = HostileAgent()
    worst = np.inf
    while env.agents:
        obs, _, _, _, infos = env.step(agent.act(obs, env))
        worst = min(worst, min(i["clearance"] for i in infos.values()))
    return worst


@pytest.mark.slow
@pytest.mark.parametrize("bound", ["robots", "filter"])
def test_hostile_policy_with_a_wheel_speed_bound_full_length(bound):
    """The two seeds (of 10) where unlimited paper robots spin up and collide (README: known limits).

    With a 20 rad/s wheel-speed bound, either the robots' own or the filter's
    ``max_wheel_speed`` on unlimited robots, the hostile policy never collides.
    """
    from aasoatt_env.model.params import RobotParams

    if bound == "robots":
        robots = RobotParams(max_wheel_speed=20.0)
        env = AASOATTFilter(AASOATTParallelEnv("random_goals", num_robots=20, max_steps=2000, robots=robots))
    else:
        env = AASOATTFilter(AASOATTParallelEnv("random_goals", num_robots=20, max_steps=2000), max_wheel_speed=20.0)
    for seed in (2, 6):
        assert _hostile_worst_clearance(env, seed) >= -1e-3, seed
        assert np.abs(env.unwrapped.wheel_speeds).max() <= 20.0 + 1e-9


@pytest.mark.slow
def test_hostile_policy_on_unlimited_robots_needs_the_backup_layer():
    """Seed 6 without any wheel-speed bound: the paper's QP alone ends in an overlap,
    the default filter (braking backup layer on) keeps every pair apart."""
    base = dict(num_robots=20, max_steps=2000)
    qp_only = AASOATTFilter(AASOATTParallelEnv("random_goals", **base), backup=False)
    assert _hostile_worst_clearance(qp_only, 6) < -1e-3
    default = AASOATTFilter(AASOATTParallelEnv("random_goals", **base))
    assert _hostile_worst_clearance(default, 6) >= 0.0


def test_terminate_on_collision_below_the_rounding_allowance_is_refused_behind_the_filter():
    """At tolerance 0 a rounding overlap (1e-16 m) 'terminates' a moving robot, which the env stops in place: an
    input the filter did not return, and the robot behind it would run into it (by -0.5 mm)."""
    starts = np.array([[0.0, 0.0], [-0.96, 0.0], [-1.9201, 0.0]])  # a convoy: 0 and 1 touch, 2 is 0.1 mm behind
    kw = {"starts": starts, "reference": {"waypoints": np.repeat(starts[:, None], 2, axis=1), "times": [0.0, 1.0]},
          "headings": [0.0, 0.0, 0.0], "terminate_on_collision": True}
    match = r"collision_tolerance: got 0 with terminate_on_collision=True, expected >= 1e-09 m behind a control filter"
    with pytest.raises(ConfigError, match=match):
        AASOATTFilter(AASOATTParallelEnv("custom", collision_tolerance=0.0, **kw))
    with pytest.raises(ConfigError, match=match):  # the env-free filter installed by hand: the same check
        AASOATTParallelEnv("custom", collision_tolerance=0.0, **kw).set_control_filter(SafetyFilter())
    env = AASOATTFilter(AASOATTParallelEnv("custom", collision_tolerance=1e-9, max_steps=300, **kw))
    env.reset(seed=0)
    worst = np.inf
    for _ in range(300):  # everyone full throttle forward
        _, _, term, _, _ = env.step({a: np.ones(2) for a in env.agents})
        p = env.unwrapped.kinematics.p
        worst = min(worst, float(np.hypot(*(p[1:] - p[:-1]).T).min()) - 0.96)
        assert not any(term.values())
    assert worst >= -1e-9


def test_bare_hostile_policy_does_collide():
    env = AASOATTParallelEnv("random_goals", num_robots=20, max_steps=600)
    obs, _ = env.reset(seed=0)
    agent = HostileAgent()
    collided = False
    while env.agents:
        obs, _, _, _, infos = env.step(agent.act(obs, env))
        collided |= any(i["collision"] for i in infos.values())
    assert collided


def test_gymnasium_view_with_filter():
    env = gymnasium.make(
        "aasoatt/CircleSwap-v0", num_robots=4, radius=2.0, safety_filter={"deadlock": "none"}
    )
    obs, info = env.reset(seed=0)
    obs, r, term, trunc, info = env.step(env.action_space.sample())
    assert info["agents"]["robot_0"]["filter_status_code"] in (0.0, 1.0)
    assert isinstance(env.unwrapped, AASOATTGymEnv)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"barrier": "magic"}, r"barrier.*'magic'.*aasoatt"),
        ({"deadlock": "wiggle"}, r"deadlock.*'wiggle'"),
        ({"solver": "gurobi"}, r"solver: got 'gurobi', expected one of \['proxsuite', 'neural'"),
        ({"trigger": "vibes"}, r"trigger.*'vibes'"),
        ({"zeta": 5.0}, r"k4 > zeta"),
        ({"k1": -1.0}, r"k1"),
    ],
)
def test_wrapper_rejects_bad_options_at_construction(kwargs, match):
    with pytest.raises((ConfigError, SolverError), match=match):
        AASOATTFilter(AASOATTParallelEnv("circle_swap", num_robots=4, radius=2.0), **kwargs)


def test_filter_is_exported_at_top_level():
    assert aasoatt_env.AASOATTFilter is AASOATTFilter
    assert {"AASOATTFilter", "SafetyFilter", "FilterConfig", "FilterResult"} <= set(aasoatt_env.__all__)
