"""Exact values of the pieces the redesign made explicit: the env-filter protocol, barrier rows by hand,
the reward terms, ``state()``, and the one rule for combining a configuration with explicit options."""

from __future__ import annotations

import numpy as np
import pytest

from aasoatt_env import AASOATTFilter, AASOATTParallelEnv, ConfigError, FilterConfig, UsageError, make_env
from aasoatt_env.model.dynamics import DT, input_bounds, kinematics, pose_from_point
from aasoatt_env.model.params import make_team
from aasoatt_env.safety import SafetyFilter
from aasoatt_env.safety.barriers import PairGeometry, barrier_rows
from aasoatt_env.sim.protocol import ControlFilter, FilterInput


class Spy:
    """A control filter that records its calls and returns a fixed fraction of the nominal."""

    keeps_input_bounds = False

    def __init__(self, scale: float = 0.5) -> None:
        self.scale, self.calls, self.resets = scale, [], []

    def reset(self, team) -> None:
        self.resets.append(team.n)

    def __call__(self, inp: FilterInput, nominal_du: np.ndarray):
        self.calls.append((inp, nominal_du.copy()))
        du = self.scale * nominal_du

        class Out:
            pass

        out = Out()
        out.du, out.correction = du, np.linalg.norm(du - nominal_du, axis=1)
        out.avoiding = np.zeros(du.shape[0], dtype=bool)
        return out


def test_filter_is_called_once_per_physics_step_with_the_state_and_its_output_is_applied():
    env = AASOATTParallelEnv("circle_swap", num_robots=3, radius=3.0, decision_interval=4,
                             reward={"correction": 2.0, "effort": 0.0, "tracking": 0.0})
    spy = Spy(0.5)
    env.set_control_filter(spy)
    env.reset(seed=0)
    assert spy.resets == [3] and isinstance(spy, ControlFilter)
    pose0, u0, t0 = env.poses, env.wheel_speeds, env.time
    act = {a: np.array([0.8, -0.4], np.float32) for a in env.agents}
    _, rew, *_ = env.step(act)
    assert len(spy.calls) == 4 and len(env.filter_outputs) == 4  # one call per physics step
    inp, nom = spy.calls[0]
    np.testing.assert_array_equal(inp.pose, pose0)
    np.testing.assert_array_equal(inp.u, u0)
    assert inp.time == t0 and inp.dt == DT
    np.testing.assert_allclose(nom, np.tile([0.8 * 60.0, -0.4 * 60.0], (3, 1)), rtol=1e-6)
    np.testing.assert_allclose(inp.reference[0], env.layout.reference(0.0)[0])
    assert [c[0].time for c in spy.calls] == pytest.approx([t0 + k * DT for k in range(4)])
    # the env applied the filter's du (0.5 of the nominal) at every step: wheel speeds grow by 0.5 * a * dt each
    np.testing.assert_allclose(env.wheel_speeds, u0 + 4 * DT * 0.5 * np.tile([48.0, -24.0], (3, 1)), rtol=1e-6)
    # the reward's correction term: -2 * max |du - du_nom| / max_wheel_accel
    corr = np.linalg.norm([24.0, -12.0]) / 60.0
    assert rew["robot_0"] == pytest.approx(-2.0 * corr, rel=1e-6)


def test_an_env_takes_one_filter_and_rejects_non_filters():
    env = AASOATTParallelEnv("circle_swap", num_robots=2)
    with pytest.raises(ConfigError, match="ControlFilter"):
        env.set_control_filter(object())
    wrapped = AASOATTFilter(env)
    with pytest.raises(UsageError, match="already has a control filter"):
        AASOATTFilter(wrapped)
    env.set_control_filter(None)
    assert env.control_filter is None
    AASOATTFilter(env)  # after removing the first, a new one is accepted


def test_filter_installed_after_reset_is_reset_with_the_team():
    env = AASOATTParallelEnv("circle_swap", num_robots=3)
    env.reset(seed=0)
    wrapped = AASOATTFilter(env)
    assert wrapped.filter.team is env.team
    _, _, _, _, infos = wrapped.step({a: np.zeros(2) for a in env.agents})
    assert infos["robot_0"]["filter"]["status"] == "solved"


def test_config_and_explicit_options_combine_by_one_rule():
    base = FilterConfig(barrier="braking", solver="ldp", k1=3.0)
    env = AASOATTFilter(AASOATTParallelEnv("circle_swap", num_robots=2), base, solver="quadprog", k2=5.0)
    assert (env.config.barrier, env.config.solver, env.config.k1, env.config.k2) == ("braking", "quadprog", 3.0, 5.0)
    env2 = make_env("circle_swap", filter={"barrier": "distance"}, num_robots=2)
    assert env2.config.barrier == "distance" and env2.config.solver == "proxsuite"
    with pytest.raises(TypeError, match="unexpected keyword argument 'k9'"):
        FilterConfig.merged(base, k9=1.0)
    with pytest.raises(ConfigError, match="dt"):
        AASOATTFilter(AASOATTParallelEnv("circle_swap", num_robots=2), dt=0.01)


def test_aasoatt_rows_of_a_head_on_pair_by_hand():
    """eqn.7-8 for two robots on the x axis approaching each other (hand algebra)."""
    r, v, d_s, k1, k2 = 2.0, 0.5, 0.96, 2.0, 3.0
    p = np.array([[-r / 2, 0.0], [r / 2, 0.0]])
    vel = np.array([[v, 0.0], [-v, 0.0]])
    adot = np.array([[0.0, 0.1], [0.0, -0.2]])
    g = PairGeometry(np.array([0]), np.array([1]), p[:1] - p[1:], vel[:1] - vel[1:], adot[:1] - adot[1:],
                     np.array([d_s]), np.array([d_s]), np.array([8.0]))
    c, rhs, keep = barrier_rows("aasoatt", g, FilterConfig(k1=k1, k2=k2))
    # p_ij = (-2, 0), v_ij = (1, 0): |v|^2 - (p.v)^2/r^2 = 1 - 4/4 = 0; p.v = -2; p.adot_ij = (-2)*0 + 0 * 0.3 = 0
    expected = 0.0 + (k1 + k2) * (-2.0) + k1 * k2 * r * (r - d_s) + 0.0
    np.testing.assert_allclose(c, [[2.0, 0.0]])  # c = -p_ij
    assert rhs[0] == pytest.approx(expected) and list(keep) == [0]
    # the row is h_dot + k2 h >= 0 with h = r_dot + k1 (r - d_s): check it against finite differences
    h = lambda rr, rd: rd + k1 * (rr - d_s)  # noqa: E731
    rd = -2 * v  # closing at 1 m/s
    for a_rel in (-3.0, 0.0, 3.0):  # relative acceleration along p_ij (w_i - w_j = a_rel * e_x)
        r_dd = -a_rel  # r = x_j - x_i, so r_dd = -(a_i - a_j)
        hdot = r_dd + k1 * rd
        lhs = c[0] @ np.array([a_rel, 0.0])  # c^T (w_i - w_j)
        # the row c^T w <= rhs holds exactly when h_dot + k2 h >= 0 scaled by r (and A_dot terms are 0 here)
        assert (lhs <= rhs[0] + 1e-12) == (r * (hdot + k2 * h(r, rd)) >= -1e-12)


def test_state_holds_poses_wheel_speeds_reference_and_time():
    env = AASOATTParallelEnv("circle_swap", num_robots=3, radius=3.0)
    env.reset(seed=0)
    env.step({a: np.array([1.0, 0.5], np.float32) for a in env.agents})
    s = env.state()
    n = 3
    np.testing.assert_array_equal(s[: 3 * n], env.poses.ravel())
    np.testing.assert_array_equal(s[3 * n : 5 * n], env.wheel_speeds.ravel())
    p_d, v_d, _ = env.reference
    np.testing.assert_array_equal(s[5 * n : 7 * n], p_d.ravel())
    np.testing.assert_array_equal(s[7 * n : 9 * n], v_d.ravel())
    assert s[-1] == env.time == pytest.approx(DT)
    assert s.shape == env.state_space.shape


def test_reward_terms_by_value():
    env = AASOATTParallelEnv("random_goals", num_robots=2, reward={"tracking": 2.0, "collision": 0.0, "effort": 0.5,
                                                                   "goal_bonus": 3.0, "goal_tolerance": 100.0})
    env.reset(seed=0)
    act = {"robot_0": np.array([0.6, -0.8], np.float32), "robot_1": np.zeros(2, np.float32)}
    _, rew, _, _, infos = env.step(act)
    for a, action in act.items():
        expected = -2.0 * infos[a]["tracking_error"] - 0.5 * 0.5 * float(np.sum(np.square(action))) + 3.0
        assert rew[a] == pytest.approx(expected, rel=1e-6)
    # collision: robots placed overlapping get -collision per step
    env2 = AASOATTParallelEnv("custom", starts=[[0.0, 0.0], [3.0, 0.0]], reference={"waypoints": [[[0, 0], [0, 0]],
                              [[3, 0], [3, 0]]], "times": [0.0, 1.0]}, reward={"tracking": 0.0, "effort": 0.0,
                              "collision": 7.0})
    env2.reset(seed=0)
    _, rew2, _, _, _ = env2.step({a: np.zeros(2) for a in env2.agents})
    assert rew2 == {"robot_0": 0.0, "robot_1": 0.0}


def test_safety_filter_result_is_a_filter_output():
    team = make_team("paper", 2)
    pose = pose_from_point(team, np.array([[0.0, 0.0], [5.0, 0.0]]), np.zeros(2))
    u = np.zeros((2, 2))
    f = SafetyFilter(team, deadlock="none")
    kin = kinematics(team, pose, u)
    lo, hi = input_bounds(team, u, DT)
    du, res = f.step(kin, u, pose[:, 2], np.ones((2, 2)), lo, hi)
    np.testing.assert_array_equal(res.du, du)
    assert res.correction.shape == (2,) and res.avoiding.dtype == bool
