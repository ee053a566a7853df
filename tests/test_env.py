import gymnasium
import numpy as np
import pettingzoo
import pytest
from pettingzoo.test import parallel_api_test

import aasoatt_env
from aasoatt_env import ENV_IDS, AASOATTParallelEnv, ActionError, ConfigError, ScenarioError
from aasoatt_env.sim.observations import SELF_DIM, SLOT_DIM
from agents import RandomAgent, TrackingController


@pytest.mark.parametrize("env_id", sorted(ENV_IDS))
def test_parallel_api_for_every_registered_id(env_id):
    env = pettingzoo.make("parallel", env_id, max_steps=60)
    parallel_api_test(env, num_cycles=100)


@pytest.mark.parametrize("env_id", sorted(ENV_IDS))
def test_gymnasium_view_passes_env_checker(env_id):
    from gymnasium.utils.env_checker import check_env

    env = gymnasium.make(env_id, max_steps=20)
    check_env(env.unwrapped, skip_render_check=True)


def test_gymnasium_make_with_module_prefix_and_pettingzoo_make_kwargs():
    env = gymnasium.make("aasoatt_env:aasoatt/CircleSwap-v0", num_robots=8)
    obs, info = env.reset(seed=0)
    assert obs.shape == env.observation_space.shape == (8 * (SELF_DIM + SLOT_DIM * 6),)
    par = pettingzoo.make("parallel", "aasoatt/CircleSwap-v0", num_robots=20)
    assert len(par.possible_agents) == 20
    aec = aasoatt_env.env("position_swap")
    aec.reset(seed=0)
    assert aec.agents == [f"robot_{i}" for i in range(4)]


def _rollout(env, agent, seed, steps):
    obs, _ = env.reset(seed=seed)
    agent.reset(env)
    traj = [env.unwrapped.positions.copy()]
    obs_hist = []
    for _ in range(steps):
        if not env.agents:
            break
        obs, rew, term, trunc, info = env.step(agent.act(obs, env))
        traj.append(env.unwrapped.positions.copy())
        obs_hist.append(np.concatenate([obs[a] for a in sorted(obs)]))
    return np.array(traj), np.array(obs_hist)


def test_same_seed_gives_bit_identical_300_step_rollouts():
    make = lambda: AASOATTParallelEnv("random_goals", num_robots=6, decision_interval=2)  # noqa: E731
    t1, o1 = _rollout(make(), RandomAgent(seed=3), seed=7, steps=300)
    t2, o2 = _rollout(make(), RandomAgent(seed=3), seed=7, steps=300)
    assert t1.shape[0] == 301
    assert np.array_equal(t1, t2) and np.array_equal(o1, o2)
    t3, _ = _rollout(make(), RandomAgent(seed=3), seed=8, steps=300)
    assert not np.allclose(t1[0], t3[0])  # random scenario: different layout


def test_deterministic_scenario_same_layout_for_any_seed():
    env = AASOATTParallelEnv("circle_swap", num_robots=6)
    env.reset(seed=1)
    a = env.positions
    env.reset(seed=2)
    np.testing.assert_array_equal(a, env.positions)


def test_circle_swap_layout_and_reference():
    env = AASOATTParallelEnv("circle_swap", num_robots=10, radius=6.0, duration=12.0)
    env.reset(seed=0)
    np.testing.assert_allclose(np.linalg.norm(env.positions, axis=1), 6.0)
    np.testing.assert_allclose(env.goals, -env.positions, atol=1e-12)
    p_d, v_d, a_d = env.reference
    np.testing.assert_allclose(np.linalg.norm(v_d, axis=1), 1.0)  # 12 m in 12 s
    assert env.velocities == pytest.approx(np.zeros((10, 2)))
    # the robots face their goals
    np.testing.assert_allclose(np.cos(env.headings), -env.positions[:, 0] / 6.0, atol=1e-12)


def test_too_many_robots_says_at_most_39():
    with pytest.raises(ScenarioError, match="at most 39 robots of radius 0.48 fit on a circle of radius 6"):
        AASOATTParallelEnv("circle_swap", num_robots=40, radius=6.0)
    AASOATTParallelEnv("circle_swap", num_robots=39, radius=6.0)


def test_unknown_scenario_lists_known():
    with pytest.raises(ScenarioError, match=r"known scenarios: \['circle_obstacles', 'circle_swap'"):
        AASOATTParallelEnv("swirl")


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"dt": 0.0}, r"dt: got 0.0, expected a finite number in \[1e-06, 0.1\]"),
        ({"dt": -0.01}, "dt: got -0.01"),
        ({"radius": -6.0}, "radius: got -6.0"),
        ({"decision_interval": 0}, r"decision_interval: got 0, expected an integer in \[1, 10000\]"),
        ({"action_mode": "torque"}, "action_mode: got 'torque'"),
        ({"robots": "roomba"}, "unknown robot preset 'roomba'"),
        ({"reward": {"collision": -1.0}}, r"RewardConfig.collision: got -1.0"),
    ],
)
def test_bad_configuration_names_the_argument(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        AASOATTParallelEnv("circle_swap", **kwargs)


@pytest.fixture
def env4():
    env = AASOATTParallelEnv("position_swap")
    env.reset(seed=0)
    return env


def _zeros(env):
    return {a: np.zeros(2, np.float32) for a in env.agents}


@pytest.mark.parametrize(
    "mutate,match",
    [
        (lambda a: a.update(robot_0=np.zeros(3)), r"actions\['robot_0'\]: got shape \(3,\), expected \(2,\)"),
        (lambda a: a.update(robot_1=np.array([np.nan, 0.0])), r"actions\['robot_1'\]: got non-finite"),
        (lambda a: a.update(robot_2=np.array([np.inf, 0.0])), r"actions\['robot_2'\]: got non-finite"),
        (lambda a: a.update(robot_9=np.zeros(2)), r"unknown agent\(s\) \['robot_9'\]"),
        (lambda a: a.pop("robot_3"), r"missing action for live agent\(s\) \['robot_3'\]"),
        (lambda a: a.update(robot_0=np.array([1.5, 0.0])), r"expected values in \[-1, 1\]"),
    ],
)
def test_bad_actions_raise_action_error_naming_the_agent(env4, mutate, match):
    acts = _zeros(env4)
    mutate(acts)
    with pytest.raises(ActionError, match=match):
        env4.step(acts)


def test_clip_actions_option_accepts_out_of_range():
    env = AASOATTParallelEnv("position_swap", clip_actions=True)
    env.reset(seed=0)
    acts = {a: np.array([5.0, -5.0], np.float32) for a in env.agents}
    env.step(acts)
    u = env.wheel_speeds  # clipped to the bound: du = +-max_wheel_accel
    np.testing.assert_allclose(u, np.tile([20.0 * 0.005, -20.0 * 0.005], (4, 1)))


def test_decision_interval_holds_action_and_advances_time():
    env = AASOATTParallelEnv("position_swap", decision_interval=10)
    env.reset(seed=0)
    acts = {a: np.array([1.0, 1.0], np.float32) for a in env.agents}
    env.step(acts)
    assert env.time == pytest.approx(0.05)
    np.testing.assert_allclose(env.wheel_speeds, 20.0 * 0.05)


def test_speed_limit_saturates_and_is_reported():
    env = AASOATTParallelEnv("position_swap")  # burger: 6.67 rad/s
    env.reset(seed=0)
    acts = {a: np.array([1.0, 1.0], np.float32) for a in env.agents}
    saturated = False
    for _ in range(100):
        _, _, _, _, infos = env.step(acts)
        saturated |= infos["robot_0"]["saturated"]
    assert np.all(env.wheel_speeds <= 0.22 / 0.033 + 1e-9)
    assert saturated


def test_truncation_at_horizon_and_agents_leave():
    env = AASOATTParallelEnv("tracking", duration=0.05)  # 10 steps
    env.reset(seed=0)
    n = 0
    while env.agents:
        _, _, term, trunc, _ = env.step(_zeros(env))
        n += 1
    assert n == 10 and trunc == {"robot_0": True} and term == {"robot_0": False}


def test_terminate_on_collision_removes_robots_and_freezes_them():
    env = AASOATTParallelEnv("circle_swap", num_robots=4, radius=2.0, duration=2.0, terminate_on_collision=True)
    obs, _ = env.reset(seed=0)
    ctrl = TrackingController(saturate=True)
    terminated = set()
    while env.agents:
        obs, _, term, trunc, infos = env.step(ctrl.act(obs, env))
        for a, t in term.items():
            if t:
                assert infos[a]["collision"]
                terminated.add(a)
    assert terminated  # bare tracking through the centre collides
    frozen = env.positions.copy()
    assert not env.agents
    np.testing.assert_array_equal(frozen, env.positions)


def test_infos_and_state_and_properties():
    env = AASOATTParallelEnv("circle_obstacles", num_robots=20)
    obs, infos = env.reset(seed=0)
    assert set(infos["robot_0"]) >= {"tracking_error", "clearance", "collision"}
    # neighbours on the radius-6 circle with 20 robots are 1.877 m apart: gap 0.917
    gap = 2 * 6 * np.sin(np.pi / 20) - 0.96
    assert infos["robot_0"]["clearance"] == pytest.approx(gap)
    assert env.state().shape == env.state_space.shape
    assert env.radii.shape == (20,) and env.goals.shape == (20, 2) and env.wheel_speeds.shape == (20, 2)
    assert env.obstacles[0].shape == (3, 2)


def test_observation_contents():
    env = AASOATTParallelEnv("circle_swap", num_robots=20, sensing_range=3.0, num_neighbors=4)
    obs, _ = env.reset(seed=0)
    o = obs["robot_0"]
    assert o.dtype == np.float32 and env.observation_space("robot_0").contains(o)
    np.testing.assert_allclose(o[0:2], 0.0, atol=1e-6)  # on its reference
    np.testing.assert_allclose(o[2:4], env.goals[0] - env.positions[0], atol=1e-5)
    slots = o[SELF_DIM : SELF_DIM + 4 * SLOT_DIM].reshape(4, SLOT_DIM)
    d = 2 * 6 * np.sin(np.pi / 20)
    # two neighbours at chord distance d, the next two at 2 sin(2 pi / 20) 6 = 3.708 > 3: masked
    np.testing.assert_allclose(np.linalg.norm(slots[:2, :2], axis=1), d, rtol=1e-5)
    np.testing.assert_allclose(slots[:2, 5], 1.0)
    np.testing.assert_array_equal(slots[2:], 0.0)
    assert env.observation_space("robot_0") is env.observation_space("robot_0")


def test_heterogeneous_team_runs():
    from aasoatt_env import RobotParams

    robots = [RobotParams(radius=0.3 + 0.05 * i, max_wheel_accel=30 + 5 * i) for i in range(6)]
    env = AASOATTParallelEnv("random_goals", num_robots=6, robots=robots)
    obs, _ = env.reset(seed=1)
    np.testing.assert_allclose(env.radii, [0.3, 0.35, 0.4, 0.45, 0.5, 0.55])
    for _ in range(20):
        obs, *_ = env.step({a: np.ones(2, np.float32) for a in env.agents})
    np.testing.assert_allclose(env.wheel_speeds[:, 0], [(30 + 5 * i) * 0.1 for i in range(6)])


def test_point_action_mode_gives_requested_point_acceleration():
    env = AASOATTParallelEnv("tracking", action_mode="point")
    env.reset(seed=0)
    v0 = env.velocities
    env.step({"robot_0": np.array([0.5, 0.0], np.float32)})
    a = (env.velocities - v0) / env.dt
    amax = env.team.max_point_accel[0]
    np.testing.assert_allclose(a[0], [0.5 * amax, 0.0], atol=1e-2 * amax)


def test_rgb_array_render():
    env = AASOATTParallelEnv("position_swap", render_mode="rgb_array")
    env.reset(seed=0)
    img = env.render()
    assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
    assert img.std() > 0
    env.close()


def test_tracking_controller_tracks_a_circle():
    env = AASOATTParallelEnv("tracking", trajectory="circle")
    obs, _ = env.reset(seed=0)
    ctrl = TrackingController(saturate=True)
    errs = []
    while env.agents:
        obs, _, _, _, infos = env.step(ctrl.act(obs, env))
        errs.append(infos["robot_0"]["tracking_error"])
    assert max(errs[-200:]) < 1e-3  # converged
    assert np.sqrt(np.mean(np.square(errs))) < 0.05


def test_custom_scenario_with_waypoints_callable_and_obstacles():
    from aasoatt_env.sim.references import LinearReference

    starts = np.array([[0.0, 0.0], [3.0, 0.0]])
    wp = {"waypoints": np.array([[[0, 0], [1, 1], [2, 0]], [[3, 0], [3, 2], [3, 4]]], float), "times": [0, 2, 4]}
    env = AASOATTParallelEnv("custom", starts=starts, reference=wp, obstacles=([[1.5, -2.0]], [0.3]))
    env.reset(seed=0)
    np.testing.assert_allclose(env.goals, [[2, 0], [3, 4]])
    p_d, v_d, _ = env.reference
    np.testing.assert_allclose(v_d, [[0.5, 0.5], [0.0, 1.0]])
    assert env.headings == pytest.approx([np.pi / 4, np.pi / 2])
    assert env.obstacles[1].tolist() == [0.3]

    def circle(t):
        return np.array([[np.cos(t), np.sin(t)], [3 + np.cos(t), np.sin(t)]])

    env = AASOATTParallelEnv("custom", starts=circle(0.0), reference=circle, duration=2.0)
    env.reset()
    np.testing.assert_allclose(env.reference[1], [[0, 1], [0, 1]], atol=1e-6)  # finite differences
    env = AASOATTParallelEnv("custom", starts=starts, reference=LinearReference(starts, starts + 1, 1.0))
    env.reset()
    with pytest.raises(ScenarioError, match="robots 0 and 1 overlap"):
        AASOATTParallelEnv("custom", starts=[[0, 0], [0.5, 0]], reference=wp)
    with pytest.raises(ConfigError, match="callable reference needs duration"):
        AASOATTParallelEnv("custom", starts=starts, reference=circle)


def test_every_adversary_acts_before_its_reset_as_after_it():
    """Each of ``ADVERSARIES`` called without ``reset``: the same actions as after ``reset`` (not an AttributeError)."""
    from agents import ADVERSARIES

    env = aasoatt_env.make_env("random_goals", num_robots=4)
    obs, _ = env.reset(seed=0)
    for name, cls in ADVERSARIES.items():
        fresh, reset = cls(), cls()
        reset.reset(env)
        a, b = fresh.act(obs, env), reset.act(obs, env)
        assert all(np.array_equal(a[k], b[k]) for k in a), name
