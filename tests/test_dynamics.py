import math

import numpy as np
import pytest

from aasoatt_env import ConfigError, RobotParams, make_team
from aasoatt_env.model import dynamics as dyn


def test_constant_wheel_speeds_trace_the_closed_form_circle():
    team = make_team("paper", 1)
    wr, wl = 6.0, 4.0
    b = team.half_track[0]
    radius = b * (wr + wl) / (wr - wl)
    pose, u = np.zeros((1, 3)), np.array([[wr, wl]])
    dt, steps = 0.005, 2000  # 10 s
    err = 0.0
    for _ in range(steps):
        pose, u = dyn.integrate(team, pose, u, np.zeros((1, 2)), dt)
        err = max(err, abs(math.hypot(pose[0, 0], pose[0, 1] - radius) - radius))
    assert err < 1e-9
    omega = team.wheel_radius[0] * (wr - wl) / (2 * b)
    assert pose[0, 2] == pytest.approx(omega * steps * dt, abs=1e-9)


def test_straight_line_when_wheels_are_equal():
    team = make_team("paper", 1)
    pose, u = np.zeros((1, 3)), np.array([[5.0, 5.0]])
    pose, u = dyn.integrate(team, pose, u, np.zeros((1, 2)), 1.0)
    assert pose[0] == pytest.approx([0.5, 0.0, 0.0])


def _random_state(rng, n):
    pose = np.column_stack([rng.normal(size=(n, 2)), rng.uniform(-np.pi, np.pi, n)])
    u = rng.normal(scale=5.0, size=(n, 2))
    return pose, u


@pytest.mark.parametrize("preset", ["paper", "turtlebot3_burger"])
def test_point_velocity_is_A_u_and_acceleration_is_A_du_plus_Adot_u(preset):
    rng = np.random.default_rng(1)
    n = 5
    team = make_team(preset, n)
    pose, u = _random_state(rng, n)
    du = rng.uniform(-1, 1, size=(n, 2)) * team.du_max
    kin = dyn.kinematics(team, pose, u)
    h = 1e-5
    # central differences of the exact integrator
    pose_f, u_f = dyn.integrate(team, pose, u, du, h)
    pose_b, u_b = dyn.integrate(team, pose, u, du, -h)
    p_dot = (dyn.control_point(team, pose_f) - dyn.control_point(team, pose_b)) / (2 * h)
    np.testing.assert_allclose(p_dot, np.einsum("nij,nj->ni", kin.A, u), rtol=1e-6, atol=1e-7)
    v_f = dyn.kinematics(team, pose_f, u_f).v
    v_b = dyn.kinematics(team, pose_b, u_b).v
    a_fd = (v_f - v_b) / (2 * h)
    a = np.einsum("nij,nj->ni", kin.A, du) + kin.adot_u
    np.testing.assert_allclose(a_fd, a, rtol=1e-5, atol=1e-6)


def test_A_matches_closed_form_and_determinant():
    team = make_team("paper", 3)
    theta = np.array([0.0, 0.7, -2.0])
    A = dyn.jacobian(team, theta)
    rho, b, offset = 0.1, 0.2, 0.2
    np.testing.assert_allclose(np.linalg.det(A), -(rho**2) * offset / (2 * b))
    k = offset / b
    c, s = math.cos(0.7), math.sin(0.7)
    np.testing.assert_allclose(A[1], rho / 2 * np.array([[c - k * s, c + k * s], [s + k * c, s - k * c]]))


def test_double_integrator_is_exact():
    team = make_team("double_integrator", 2)
    pose = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.3]])
    u = np.array([[1.0, 0.0], [0.0, 0.0]])
    du = np.array([[0.0, 2.0], [0.0, 0.0]])
    pose2, u2 = dyn.integrate(team, pose, u, du, 0.5)
    assert pose2[0, :2] == pytest.approx([0.5, 0.25])
    assert u2[0] == pytest.approx([1.0, 1.0])
    assert pose2[1, 2] == pytest.approx(0.3)  # at rest: heading kept
    kin = dyn.kinematics(team, pose2, u2)
    np.testing.assert_allclose(kin.A, np.broadcast_to(np.eye(2), (2, 2, 2)))
    np.testing.assert_allclose(kin.adot_u, 0.0)


def test_input_bounds_respect_speed_limit_and_never_empty():
    p = RobotParams(max_wheel_accel=10.0, max_wheel_speed=5.0)
    team = make_team(p, 3)
    u = np.array([[0.0, 4.99], [5.0, -5.0], [7.0, 0.0]])
    lo, hi = dyn.input_bounds(team, u, 0.01)
    assert np.all(lo <= hi)
    within = np.abs(u[:2]) <= 5.0
    assert np.all(np.abs(u[:2] + hi[:2] * 0.01)[within] <= 5.0 + 1e-12)
    assert np.all(np.abs(u[:2] + lo[:2] * 0.01)[within] <= 5.0 + 1e-12)
    assert hi[0, 1] == pytest.approx(1.0)  # (5 - 4.99) / 0.01
    assert hi[2, 0] == pytest.approx(-10.0)  # over the limit: must brake at full rate
    assert lo[0, 0] == pytest.approx(-10.0)


def test_speed_box_matches_input_bounds_and_is_never_empty():
    rng = np.random.default_rng(3)
    team = make_team(RobotParams(max_wheel_accel=10.0, max_wheel_speed=5.0), 50)
    u = rng.uniform(-8.0, 8.0, (50, 2))
    lo, hi = dyn.input_bounds(team, u, 0.01)
    lo2, hi2 = dyn.speed_box(-team.du_max, team.du_max, u, 5.0, 0.01)
    np.testing.assert_array_equal(lo, lo2)
    np.testing.assert_array_equal(hi, hi2)
    assert np.all(lo <= hi)
    assert np.all(np.abs(lo) <= 10.0) and np.all(np.abs(hi) <= 10.0)
    inside = np.abs(u) <= 5.0
    assert np.all(np.abs(u + lo * 0.01)[inside] <= 5.0 + 1e-12)
    assert np.all(np.abs(u + hi * 0.01)[inside] <= 5.0 + 1e-12)


def test_heterogeneous_team_arrays():
    team = make_team(["paper", RobotParams(radius=0.3, max_wheel_accel=20.0), "paper"], 3)
    np.testing.assert_allclose(team.radius, [0.48, 0.3, 0.48])
    np.testing.assert_allclose(team.du_max[:, 0], [60.0, 20.0, 60.0])


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"radius": 0.0}, r"RobotParams.radius: got 0.0, expected a finite number in \[1e-06, 1e\+06\]"),
        ({"radius": -1.0}, r"RobotParams.radius"),
        ({"offset": float("nan")}, r"RobotParams.offset"),
        ({"max_wheel_accel": float("inf")}, r"max_wheel_accel"),
        ({"model": "tank"}, r"model: got 'tank', expected one of"),
    ],
)
def test_robot_params_validation(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        RobotParams(**kwargs)


def test_unknown_preset_lists_known():
    known = r"\['double_integrator', 'paper', 'paper_small', 'turtlebot3_burger', 'turtlebot3_waffle_pi'\]"
    with pytest.raises(ConfigError, match=r"known presets: " + known):
        RobotParams.preset("roomba")


def test_max_point_accel_is_inscribed_radius():
    p = RobotParams()
    team = make_team(p, 1)
    A = dyn.jacobian(team, np.array([0.4]))[0]
    # the reachable parallelogram contains the disc of radius max_point_accel, and touches it
    ang = np.linspace(0, 2 * np.pi, 721)
    dirs = np.stack([np.cos(ang), np.sin(ang)], 1)
    du = np.linalg.solve(A, (p.max_point_accel * dirs).T).T
    assert np.abs(du).max() == pytest.approx(p.max_wheel_accel, rel=1e-4)
