"""Unit tests of the safety filter: inputs, relaxation, registries, triggers, neighbours."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from helpers import circle_layout, closed_loop, needs_numba

import aasoatt_env.safety.solvers.backends as backends
from aasoatt_env import compiled as compiled_module
from aasoatt_env import make_env
from aasoatt_env.errors import ConfigError, SolverError, StateError
from aasoatt_env.model.dynamics import input_bounds, kinematics, pose_from_point
from aasoatt_env.model.geometry import pair_components, robot_pairs
from aasoatt_env.model.params import make_team
from aasoatt_env.safety import BARRIERS, STRATEGIES, TRIGGERS, FilterConfig, SafetyFilter
from aasoatt_env.safety import centralized as centralized_module
from aasoatt_env.safety import problem as problem_module
from aasoatt_env.safety import rows as rows_module
from aasoatt_env.safety.backup import gate as gatekeeper_module
from aasoatt_env.safety.solvers import active_set as active_set_module
from aasoatt_env.safety.solvers import local as local_module


def _state(n=4, spacing=1.2, seed=0, speed=0.5):
    rng = np.random.default_rng(seed)
    team = make_team("paper", n)
    p = np.stack((np.arange(n) * spacing, np.zeros(n)), axis=1)
    theta = rng.uniform(-np.pi, np.pi, n)
    pose = pose_from_point(team, p, theta)
    u = rng.normal(0, speed, (n, 2))
    return team, pose, u


def _inputs(team, pose, u, dt=0.005):
    kin = kinematics(team, pose, u)
    lo, hi = input_bounds(team, u, dt)
    return kin, lo, hi


def test_nan_nominal_names_robot():
    team, pose, u = _state()
    kin, lo, hi = _inputs(team, pose, u)
    nom = np.zeros((4, 2))
    nom[2, 1] = np.nan
    with pytest.raises(StateError, match="robot index 2"):
        SafetyFilter(team, deadlock="none").step(kin, u, pose[:, 2], nom, lo, hi)


def test_bad_shape_nominal():
    team, pose, u = _state()
    kin, lo, hi = _inputs(team, pose, u)
    with pytest.raises(StateError, match=r"expected \(4, 2\)"):
        SafetyFilter(team, deadlock="none").step(kin, u, pose[:, 2], np.zeros((3, 2)), lo, hi)


def _from_state(**kw):
    team, pose, u = _state(n=2, spacing=3.0, speed=0.0)
    args = {"pose": pose, "u": u, "nominal_du": np.zeros((2, 2)),
            "reference": (pose[:, :2].copy(), np.zeros((2, 2)))}
    args.update(kw)
    return SafetyFilter(team).from_state(args.pop("pose"), args.pop("u"), args.pop("nominal_du"), **args)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"nominal_du": np.full((2, 2), 1e300)}, r"nominal_du: got a value beyond \+-1e\+09 .*\(robot index 0\)"),
        ({"u": np.full((2, 2), 1e200)}, r"u: got a value beyond \+-1e\+09 \[1e\+200, 1e\+200\] .*\(robot index 0\)"),
        ({"pose": np.full((2, 3), np.inf)}, r"pose: got a non-finite value \[inf, inf, inf\] .*\(robot index 0\)"),
        ({"pose": np.zeros((2, 2))}, r"pose: got shape \(2, 2\), expected \(2, 3\)"),
        ({"reference": (np.full((2, 2), np.nan), np.zeros((2, 2)))}, r"reference p_d: got a non-finite value"),
        ({"reference": (np.zeros((3, 2)), np.zeros((2, 2)))}, r"reference p_d: got shape \(3, 2\), expected \(2, 2\)"),
        ({"reference": 1.0}, r"reference: got float, expected \(p_d, v_d\) or \(p_d, v_d, a_d\)"),
        ({"obstacles": (np.array([[1.5, 0.0]]), np.array([np.nan]))},
         r"obstacles radii: got a non-finite value \[nan\] for obstacle\(s\) \[0\]"),
        ({"obstacles": (np.array([[1.5, 0.0]]), np.array([-1.0]))}, r"obstacles radii: got -1.0 for obstacle 0, "
         r"expected a radius >= 0"),
        ({"obstacles": (np.array([[1.5, 3.0], [5.0, 5.0]]), np.array([0.5]))},
         r"obstacles centres: got shape \(2, 2\), expected \(1, 2\)"),
        ({"obstacles": (np.array([[1.5, 3.0]]), np.array([0.5]), np.array([np.nan]))},
         r"obstacles groups: got float64 array of shape \(1,\), expected finite group labels"),
        ({"obstacles": (np.array([[1.5, 3.0]]), np.array([0.5]), np.array(["a"]))},
         r"obstacles groups: got <U1 array of shape \(1,\), expected finite group labels"),
    ],
)
def test_env_free_core_refuses_bad_state(kwargs, match):
    """The core refuses what the env would: NaN, |x| > 1e9, wrong shapes (a NaN radius must not drop an obstacle)."""
    with pytest.raises(StateError, match=match):
        _from_state(**kwargs)


def test_env_free_core_takes_every_form_of_a_valid_input_alike():
    """The forms the core has always taken give the same answer: references as tuple, list, 3-tuple (with a_d, as a
    reference returns it) or flat (2N,) arrays; obstacles as lists or arrays, with or without groups, radius 0."""
    team, pose, u = _state(n=2, spacing=1.5, speed=0.8)
    nom = np.array([[30.0, 30.0], [-20.0, 25.0]])
    p_d, v_d = pose[:, :2] + 0.3, np.ones((2, 2))
    obst = (np.array([[0.7, 1.5]]), np.array([0.3]))

    def du(**kw):
        return SafetyFilter(team).from_state(pose, u, nom, **kw)[0]

    ref = du(reference=(p_d, v_d), obstacles=obst)
    for kw in ({"reference": [p_d.tolist(), v_d.tolist()], "obstacles": (obst[0].tolist(), obst[1].tolist())},
               {"reference": (p_d, v_d, np.zeros((2, 2))), "obstacles": (*obst, None)},
               {"reference": (p_d.ravel(), v_d.ravel()), "obstacles": (*obst, np.array([0]))},
               {"reference": (p_d.reshape(1, -1), v_d), "obstacles": (*obst, np.array([0.0]))}):
        np.testing.assert_array_equal(du(**kw), ref)
    point = du(reference=(p_d, v_d), obstacles=(obst[0], np.array([0.0])))  # a point obstacle is an obstacle
    assert np.isfinite(point).all()


def test_env_free_core_keeps_a_valid_obstacle():
    """Control for the NaN-radius case: the same obstacle with a real radius binds (a robot driving at it brakes)."""
    team = make_team("paper", 1)
    pose, u = np.array([[0.0, 0.0, 0.0]]), np.full((1, 2), 3.0 / team.wheel_radius[0])
    du, res = SafetyFilter(team, deadlock="none").from_state(pose, u, np.full((1, 2), 60.0),
                                            obstacles=(np.array([[1.3, 0.0]]), np.array([0.5])))
    assert res.n_rows == 1 and (du < 0).all()


@pytest.mark.parametrize(
    ("kwargs", "exc", "match"),
    [
        ({"barrier": "nope"}, ConfigError, "aasoatt"),
        ({"deadlock": "nope"}, ConfigError, "auxiliary_velocity"),
        ({"trigger": "nope"}, ConfigError, "multiplier"),
        ({"solver": "nope"}, SolverError, "proxsuite"),
        ({"k4": 2.0, "zeta": 2.0}, ConfigError, "Theorem 2"),
        ({"k1": -1.0}, ConfigError, r"k1: got -1.0, expected"),
        ({"zeta": -0.5}, ConfigError, r"zeta: got -0.5"),
        ({"rotation_deg": 270}, ConfigError, "rotation_deg"),
        ({"safety_margin": -0.1}, ConfigError, "safety_margin"),
        ({"max_wheel_speed": 0.0}, ConfigError, r"max_wheel_speed: got 0.0, expected a finite positive"),
        ({"nonexistent": 1}, TypeError, "nonexistent"),
    ],
)
def test_config_errors(kwargs, exc, match):
    team = make_team("paper", 2)
    with pytest.raises(exc, match=match):
        SafetyFilter(team, **kwargs)


def test_filter_side_wheel_speed_bound():
    """``max_wheel_speed`` keeps |u + du dt| <= w; a wheel beyond it is braked at full rate."""
    team, pose, u = _state(spacing=2.5)  # far enough apart that the spinning robot is brake-safe
    u = np.array([[0.0, 19.99], [25.0, -25.0], [3.0, 3.0], [-19.0, 0.0]])
    kin, lo, hi = _inputs(team, pose, u)
    nominal = np.stack((team.max_wheel_accel, -team.max_wheel_accel), axis=1)  # push the wheels apart
    du, res = SafetyFilter(team, deadlock="none", max_wheel_speed=20.0).step(kin, u, pose[:, 2], nominal, lo, hi)
    after = u + du * 0.005
    a = team.max_wheel_accel[:, None]
    assert res.status in ("solved", "relaxed")
    assert np.all(np.abs(du) <= a + 1e-9)
    assert np.all(np.abs(after[[0, 2, 3]]) <= 20.0 + 1e-9)
    np.testing.assert_allclose(du[1], [-a[1, 0], a[1, 0]])  # over the limit: full braking both wheels
    free, _ = SafetyFilter(team, deadlock="none").step(kin, u, pose[:, 2], nominal, lo, hi)
    assert np.abs(u + free * 0.005).max() > 20.0  # without the option the nominal is allowed


def test_uninstalled_solver_lists_available(monkeypatch):
    monkeypatch.setitem(backends.SOLVERS, "ghost", backends.Backend(backends._osqp, "ghost_module_xyz"))
    with pytest.raises(SolverError, match="not installed.*available"):
        FilterConfig(solver="ghost")


def test_missing_reference_is_explained():
    team, pose, u = _state()
    kin, lo, hi = _inputs(team, pose, u)
    with pytest.raises(ConfigError, match="needs reference"):
        SafetyFilter(team).step(kin, u, pose[:, 2], np.zeros((4, 2)), lo, hi)


def test_packed_team_with_tiny_bounds_is_relaxed():
    n = 6
    team = make_team("paper", n)
    ang = 2 * np.pi * np.arange(n) / n
    p = 0.6 * np.stack((np.cos(ang), np.sin(ang)), axis=1)  # neighbours 0.6 apart < d_s
    theta = ang + np.pi
    pose = pose_from_point(team, p, theta)
    u = np.full((n, 2), 8.0)  # all driving towards the centre
    kin = kinematics(team, pose, u)
    lo, hi = -np.full((n, 2), 0.1), np.full((n, 2), 0.1)
    f = SafetyFilter(team, deadlock="none")
    du, res = f.step(kin, u, theta, np.zeros((n, 2)), lo, hi)
    assert res.status == "unsafe" and not res.safe  # the start overlaps: no status may say otherwise
    assert res.slack > 0 and "phase 1" in res.message  # the rows it cannot meet were relaxed
    assert np.all(np.isfinite(du)) and np.all(np.isfinite(res.eta))
    assert np.all(du >= lo) and np.all(du <= hi)


def test_far_apart_robots_pass_nominal_through():
    team, pose, u = _state(spacing=5.0)
    kin, lo, hi = _inputs(team, pose, u)
    nom = np.random.default_rng(1).uniform(-10, 10, (4, 2))
    du, res = SafetyFilter(team, deadlock="none").step(kin, u, pose[:, 2], nom, lo, hi)
    assert res.n_rows == 0 and res.status == "solved"
    np.testing.assert_allclose(du, nom, atol=1e-9)
    assert not res.intervened.any() and not res.avoiding.any()


@pytest.mark.parametrize("barrier", sorted(BARRIERS))
def test_every_barrier_gives_finite_rows_and_a_solution(barrier):
    team, pose, u = _state(n=5, spacing=1.1, speed=3.0)
    kin, lo, hi = _inputs(team, pose, u)
    nom = np.zeros((5, 2))
    obstacles = (np.array([[2.0, 1.2]]), np.array([0.3]))
    f = SafetyFilter(team, barrier=barrier, deadlock="none")
    du, res = f.step(kin, u, pose[:, 2], nom, lo, hi, obstacles=obstacles)
    assert res.status in ("solved", "relaxed")
    assert np.all(np.isfinite(du)) and np.all(np.isfinite(res.eta))
    assert res.eta.shape == (res.n_rows,) and res.pairs.shape == (res.n_rows, 2)
    if barrier != "gated_distance":
        assert res.obstacle_rows.any()
        assert np.all(res.pairs[res.obstacle_rows, 1] == -1)


def test_obstacle_row_keeps_robot_off_the_obstacle():
    team = make_team("paper", 1)
    theta = np.array([0.0])
    pose = pose_from_point(team, np.array([[0.0, 0.0]]), theta)
    u = np.full((1, 2), 10.0)  # 1 m/s towards +x
    obstacles = (np.array([[1.5, 0.0]]), np.array([0.3]))
    f = SafetyFilter(team, deadlock="none")
    dmin = np.inf
    for _ in range(600):
        kin, lo, hi = _inputs(team, pose, u)
        nom = np.linalg.solve(kin.A, (np.array([[1.0, 0.0]]) * 2 - kin.v * 2 - kin.adot_u)[..., None])[..., 0]
        du, res = f.step(kin, u, pose[:, 2], np.clip(nom, lo, hi), lo, hi, obstacles=obstacles)
        from aasoatt_env.model.dynamics import integrate

        pose, u = integrate(team, pose, u, du, 0.005)
        dmin = min(dmin, float(np.linalg.norm(kinematics(team, pose, u).p[0] - obstacles[0][0])))
    assert dmin >= 0.48 + 0.3 - 1e-3


_COMBOS = [(s, "multiplier") for s in STRATEGIES if s != "none"] + [
    ("auxiliary_velocity", t) for t in TRIGGERS if t != "multiplier"
]


@pytest.mark.parametrize(("strategy", "trig"), _COMBOS)
def test_strategies_and_triggers_run(strategy, trig):
    # on a symmetric 6-robot circle the nearest neighbour is never ahead: use a head-on pair
    scen = circle_layout(2 if trig == "heading" else 6, radius=2.5, duration=4.0)
    extra = {"stall_time": 0.2, "stall_distance": 0.05} if trig == "stalled" else {}
    f = SafetyFilter(scen.team, deadlock=strategy, trigger=trig, **extra)
    triggered = []
    orig = f.step

    def step(*a, **k):
        du, res = orig(*a, **k)
        triggered.append(res.triggered.any())
        assert np.all(np.isfinite(du))
        return du, res

    f.step = step  # type: ignore[method-assign]
    out = closed_loop(scen, f, 3.0)
    assert out.statuses.get("failed", 0) == 0
    assert any(triggered), "trigger never fired in a head-on swap"
    if strategy != "rotate_relative_position":
        # eqn.12c rotates p_ij inside the barrier itself and gives up the guarantee (documented)
        assert out.min_distance >= 0.96 - 1e-3


def test_multiplier_trigger_follows_previous_avoidance():
    scen = circle_layout(6, radius=3.0, duration=6.0)
    f = SafetyFilter(scen.team)
    seen = []
    orig = f.step

    def step(*a, **k):
        du, res = orig(*a, **k)
        seen.append((res.avoiding.copy(), res.triggered.copy()))
        return du, res

    f.step = step  # type: ignore[method-assign]
    closed_loop(scen, f, 3.0)
    assert any(a.any() for a, _ in seen)
    for (a_prev, _), (_, t_now) in zip(seen[:-1], seen[1:]):
        np.testing.assert_array_equal(a_prev, t_now)


def test_multiplier_trigger_is_off_for_robots_that_are_done():
    # robot 0 is at rest at its goal (reference at rest, 5 cm away): no deadlock, whatever its rows
    from aasoatt_env.safety.deadlock import DeadlockState, TriggerContext

    cfg = FilterConfig()
    p = np.array([[0.0, 0.0], [2.0, 0.0], [4.0, 0.0]])
    p_d = p + np.array([[0.05, 0.0], [0.5, 0.0], [0.05, 0.0]])  # robot 1 is 0.5 m from its reference
    v_d = np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0]])  # robot 2's reference still moves
    ctx = TriggerContext(p, np.zeros((3, 2)), np.zeros(3), (p_d, v_d), np.empty((0, 2), int), np.empty((0, 2)), cfg)
    state = DeadlockState(avoiding=np.array([True, True, True]))
    assert TRIGGERS["multiplier"](state, ctx).tolist() == [False, True, True]
    state = DeadlockState(avoiding=np.array([False, False, True]))
    assert TRIGGERS["multiplier"](state, ctx).tolist() == [False, False, True]
    assert TRIGGERS["multiplier"](state, ctx._replace(reference=None)).tolist() == [False, False, True]


def test_neural_solver_never_fails_and_approaches_optimum():
    scen = circle_layout(6, radius=3.0, duration=6.0)
    out = closed_loop(scen, SafetyFilter(scen.team, solver="neural", neural_iterations=5), 3.0)
    assert out.statuses == {"solved": 600}
    team, pose, u = _state(n=3, spacing=1.0, speed=4.0)
    kin, lo, hi = _inputs(team, pose, u)
    exact, _ = SafetyFilter(team, deadlock="none").step(kin, u, pose[:, 2], np.zeros((3, 2)), lo, hi)
    approx, res = SafetyFilter(team, deadlock="none", solver="neural", neural_iterations=20000).step(
        kin, u, pose[:, 2], np.zeros((3, 2)), lo, hi
    )
    assert np.all(np.isfinite(approx))
    np.testing.assert_allclose(approx, exact, atol=0.5)


@pytest.mark.parametrize("n", [5, 40, 200, 400])
def test_kdtree_and_brute_pairs_agree(n):
    rng = np.random.default_rng(n)
    p = rng.uniform(0, np.sqrt(n) * 1.5, (n, 2))
    a = robot_pairs(p, 3.0, method="brute")
    b = robot_pairs(p, 3.0, method="kdtree")
    np.testing.assert_array_equal(a, b)
    assert np.all(a[:, 0] < a[:, 1])


@needs_numba
def test_the_compiled_cells_give_the_brute_forces_pairs_and_components():
    """Every back-end the same pairs in the same order, and both component labellings equal: dense and sparse
    grids, pairs at exactly the radius (a lattice of spacing 1, radius 1), groups, points without a position."""
    rng = np.random.default_rng(3)
    lattice = np.stack(np.meshgrid(np.arange(12.0), np.arange(12.0)), -1).reshape(-1, 2)
    cases = [(lattice, 1.0, None), (lattice * 0.1, 0.1, None)]
    for k in range(60):
        n = int(rng.integers(2, 600))
        p = rng.uniform(-1.0, 1.0, (n, 2)) * rng.choice([2.0, 30.0, 1e4])
        if k % 4 == 0:
            p = np.round(p, 0)  # coincident points and distances of exactly the radius
        if k % 5 == 0:
            p[rng.integers(0, n, 3)] = np.nan  # no position: no pair
        labels = rng.integers(0, 3, n) * (0.25 if k % 2 else 1)  # integer labels, or fractional ones
        cases.append((p, float(rng.choice([0.5, 3.0, 7.0])), labels if k % 3 == 0 else None))
    total = 0
    for p, r, g in cases:
        ref = robot_pairs(p, r, method="brute", groups=g)
        np.testing.assert_array_equal(robot_pairs(p, r, method="cells", groups=g), ref)
        if np.all(np.isfinite(p)) and np.abs(p).max() < 1e3:  # (scipy's tree refuses NaN, overflows at 1e4)
            np.testing.assert_array_equal(robot_pairs(p, r, method="kdtree", groups=g), ref)
        n = p.shape[0]
        np.testing.assert_array_equal(pair_components(n, ref[:, 0], ref[:, 1], compiled=True),
                                      pair_components(n, ref[:, 0], ref[:, 1], compiled=False))
        total += ref.shape[0]
    assert robot_pairs(lattice, 1.0, method="cells").shape[0] == 2 * 12 * 11  # exactly at the radius: in
    assert total > 10_000
    assert robot_pairs(np.array([[0.0, 0.0], [1e300, 0.0], [0.5, 0.0]]), 1.0, method="cells").tolist() == [[0, 2]]


@pytest.mark.parametrize("compiled", [False, pytest.param(True, marks=needs_numba)])
def test_geometry_refuses_indices_and_labels_that_do_not_fit(compiled):
    """The kernels index by these without bounds checks: a wrong one is refused, naming it."""
    with pytest.raises(ValueError, match=r"ri/rj: edge ends must be robot indices in \[0, 3\)"):
        pair_components(3, np.array([0, 1]), np.array([5, 2]), compiled=compiled)
    with pytest.raises(ValueError, match=r"ri/rj"):
        pair_components(3, np.array([-2]), np.array([1]), compiled=compiled)
    with pytest.raises(ValueError, match=r"ri/rj: edge ends must be integer robot indices"):
        pair_components(3, np.array([0.5]), np.array([1.0]), compiled=compiled)
    assert pair_components(3, np.array([0]), np.array([-1]), compiled=compiled).tolist() == [0, 1, 2]  # obstacle
    p = np.random.default_rng(0).uniform(0, 20, (250, 2))
    for method in ("brute", "kdtree", "cells" if compiled else "brute"):
        with pytest.raises(ValueError, match=r"groups: got shape \(10,\), expected one label per point \(250,\)"):
            robot_pairs(p, 3.0, method=method, groups=np.zeros(10, int))


def test_a_numpy_filter_runs_no_kernel(monkeypatch):
    """``kernel="numpy"``: the neighbour search and the components too stay numpy (the env's own stages, its
    neighbour table among them, are the env's: compiled wherever numba imports)."""
    real = compiled_module.kernels

    def refuse(part):
        if part == "geometry":  # (the env's neighbour table only)
            return SimpleNamespace(nearest=real(part).nearest)
        raise AssertionError(f"the {part} kernels were asked for")

    monkeypatch.setattr(compiled_module, "kernels", refuse)
    for mod in (gatekeeper_module, local_module, active_set_module, rows_module, centralized_module,
                problem_module):  # (their own names for it)
        monkeypatch.setattr(mod, "kernels", refuse)
    for mode in ("centralized", "decentralized"):
        env = make_env("random_goals", num_robots=12, filter={"kernel": "numpy", "mode": mode}, max_steps=50)
        obs, _ = env.reset(seed=1)
        rng = np.random.default_rng(1)
        for _ in range(50):
            obs, *_ = env.step({a: rng.uniform(-1, 1, 2).astype(np.float32) for a in env.agents})
    team = make_team("paper", 300)
    p = np.random.default_rng(2).uniform(0, 30, (300, 2))
    pose = pose_from_point(team, p, np.zeros(300))
    u = np.zeros((300, 2))
    kin = kinematics(team, pose, u)
    lo, hi = input_bounds(team, u, 0.005)
    SafetyFilter(team, kernel="numpy", deadlock="none").step(kin, u, pose[:, 2], np.ones((300, 2)), lo, hi)


def test_reset_clears_memory():
    scen = circle_layout(4, radius=2.0, duration=4.0)
    f = SafetyFilter(scen.team, trigger="stalled")
    closed_loop(scen, f, 0.5)
    f.reset()
    assert f._x is None and f._dl.history == []


def test_box_least_squares_matches_quadprog():
    quadprog = pytest.importorskip("quadprog")
    from aasoatt_env.model.dynamics import jacobian
    from aasoatt_env.safety.problem import box_least_squares

    rng = np.random.default_rng(3)
    k = 400
    team = make_team("paper", k)
    A = jacobian(team, rng.uniform(-np.pi, np.pi, k))
    target = rng.normal(0, 8, (k, 2))  # often outside what the box allows
    lo = -rng.uniform(0.5, 60, (k, 2))
    hi = rng.uniform(0.5, 60, (k, 2))
    du = box_least_squares(A, target, lo, hi)
    assert np.all(du >= lo) and np.all(du <= hi)
    outside = 0
    for i in range(k):
        H = 2 * A[i].T @ A[i]
        Ct = np.hstack((np.eye(2), -np.eye(2)))
        ref = quadprog.solve_qp(H, 2 * A[i].T @ target[i], Ct, np.concatenate((lo[i], -hi[i])), 0)[0]
        np.testing.assert_allclose(np.sum((A[i] @ du[i] - target[i]) ** 2),
                                   np.sum((A[i] @ ref - target[i]) ** 2), rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(du[i], ref, atol=1e-7)
        outside += not np.allclose(du[i], np.linalg.solve(A[i], target[i]))
    assert outside > k // 4  # the edge cases were exercised


class _Twin(SafetyFilter):
    """Decomposed filter that solves every step again without decomposition."""

    def __init__(self, team):
        super().__init__(team)
        self.twin = SafetyFilter(team, decompose=False)
        self.diffs, self.qp_rows, self.rows = [], [], []

    def step(self, *args, **kwargs):
        du, res = super().step(*args, **kwargs)
        du_full, res_full = self.twin.step(*args, **kwargs)
        assert res.status == res_full.status
        self.diffs.append(float(np.max(np.abs(du - du_full), initial=0.0)))
        self.qp_rows.append(res.n_qp_rows)
        self.rows.append(res.n_rows)
        return du, res


def test_decomposition_gives_the_full_qp_answer():
    scen = circle_layout(10, radius=6.0, duration=12.0)
    filt = _Twin(scen.team)
    out = closed_loop(scen, filt, 9.0)
    rows, qp_rows = np.array(filt.rows), np.array(filt.qp_rows)
    # both paths were exercised: rows present but no QP needed, and real QPs
    assert np.sum((rows > 0) & (qp_rows == 0)) > 50
    assert np.sum(qp_rows > 0) > 50
    assert max(filt.diffs) < 1e-5 * 60.0  # rad/s^2, the solver tolerance on the scaled problem
    assert out.min_distance >= 0.96 - 1e-3


@pytest.mark.parametrize("seed", range(5))
def test_component_labels_match_scipy(seed):
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from aasoatt_env.model.geometry import pair_components

    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 200))
    m = int(rng.integers(0, 2 * n))
    ri = rng.integers(0, n, m)
    rj = np.where(rng.random(m) < 0.2, -1, rng.integers(0, n, m))  # -1: obstacle rows, no edge
    ours = pair_components(n, ri, rj)
    e = rj >= 0
    ref = connected_components(coo_matrix((np.ones(e.sum()), (ri[e], rj[e])), shape=(n, n)), directed=False)[1]
    # same partition: labels map one-to-one
    pairs = set(zip(ours.tolist(), ref.tolist()))
    assert len(pairs) == len(set(ours.tolist())) == len(set(ref.tolist()))


def test_a_registered_strategys_target_of_the_wrong_shape_is_refused(monkeypatch):
    """A deadlock strategy's target is checked before the QP (the compiled parts read it without bounds checks)."""
    import dataclasses

    from aasoatt_env.safety import deadlock

    bad = dataclasses.replace(STRATEGIES["auxiliary_velocity"], target=lambda target, zeta, Q, c: target[:1])
    monkeypatch.setitem(deadlock.STRATEGIES, "short", bad)
    scen = circle_layout(6, radius=2.5, duration=4.0)
    with pytest.raises(ConfigError, match=r"deadlock strategy 'short': its target has shape \(1, 2\).*\(6, 2\)"):
        closed_loop(scen, SafetyFilter(scen.team, deadlock="short"), 3.0)  # (it acts once a robot is triggered)


def test_a_team_with_a_short_parameter_array_is_refused():
    """One value per robot for every parameter array of a Team built by hand (the kernels read without checks)."""
    import dataclasses

    team = make_team("paper", 4)
    short = dataclasses.replace(team, max_wheel_accel=team.max_wheel_accel[:2])
    with pytest.raises(ConfigError, match=r"team.max_wheel_accel: got ndarray of shape \(2,\), expected .*\(4,\)"):
        SafetyFilter(short)


def test_a_trigger_you_register_gets_the_pairs(monkeypatch):
    """Only the triggers known to read no pairs run before the rows, with empty pairs; any other sees them."""
    from aasoatt_env.safety import deadlock

    seen = []
    monkeypatch.setitem(deadlock.TRIGGERS, "mine", lambda memory, c: seen.append(c.pair_idx.shape[0]) or
                        np.zeros(c.p.shape[0], dtype=bool))
    scen = circle_layout(6, radius=2.5, duration=4.0)
    closed_loop(scen, SafetyFilter(scen.team, trigger="mine"), 0.5)
    assert len(seen) == 100 and min(seen[1:]) > 0


def test_a_far_nominal_is_pulled_in_radially_and_filtered_as_its_projection():
    """A nominal of 1e6 (an untrained network, a units mistake) is filtered as the nominal pulled in to
    NOMINAL_RANGE times the wheel bound from the box's centre, in the same direction; nearer nominals are
    the QP's own (the array itself is passed on)."""
    from aasoatt_env.safety.inputs import NOMINAL_RANGE, bound_nominal

    n = 6
    team = make_team("paper", n)
    ang = 2 * np.pi * np.arange(n) / n
    pose = pose_from_point(team, 1.7 * np.stack((np.cos(ang), np.sin(ang)), axis=1), ang + np.pi)
    u = np.full((n, 2), 2.0)
    kin, lo, hi = _inputs(team, pose, u)
    rng = np.random.default_rng(4)
    far = rng.normal(0.0, 1e6, (n, 2))
    near = rng.uniform(-100.0, 100.0, (n, 2))
    scale = np.full(n, 60.0)
    assert bound_nominal(near, lo, hi, scale, team.max_wheel_accel) is near
    pulled = bound_nominal(far, lo, hi, scale, team.max_wheel_accel)
    centre = 0.5 * (lo + hi)
    np.testing.assert_allclose(np.linalg.norm(pulled - centre, axis=1), NOMINAL_RANGE * 60.0, rtol=1e-12)
    cos = np.sum((pulled - centre) * (far - centre), axis=1) / (
        np.linalg.norm(pulled - centre, axis=1) * np.linalg.norm(far - centre, axis=1))
    np.testing.assert_allclose(cos, 1.0, atol=1e-12)
    for backup in (False, True):
        du_far, res = SafetyFilter(team, deadlock="none", backup=backup).step(kin, u, pose[:, 2], far, lo, hi)
        du_pulled, _ = SafetyFilter(team, deadlock="none", backup=backup).step(kin, u, pose[:, 2], pulled, lo, hi)
        np.testing.assert_array_equal(du_far, du_pulled)
        assert res.n_qp_rows > 0 and res.status in ("solved", "backup") and res.iterations <= 100


def test_brute_force_candidates_of_labelled_points_are_each_labels_upper_triangle():
    """``brute_candidates`` with labels: every pair ``i < j`` of one label, sorted, as the filter of the whole upper
    triangle (200 random labellings, contiguous or not); a stack of 4,096 teams of 20 in memory of its pairs."""
    from aasoatt_env.model.geometry import brute_candidates

    rng = np.random.default_rng(0)
    for trial in range(200):
        n = int(rng.integers(1, 60))
        groups = rng.integers(0, int(rng.integers(1, 8)), n)
        groups = np.sort(groups) if trial % 3 == 0 else groups
        iu, ju = np.triu_indices(n, k=1)
        same = groups[iu] == groups[ju]
        got = brute_candidates(n, groups)
        assert np.array_equal(got[0], iu[same]) and np.array_equal(got[1], ju[same]), trial
    iu, ju = brute_candidates(81920, np.repeat(np.arange(4096), 20))  # (the whole triangle: 3.4e9 pairs)
    assert iu.shape == (4096 * 190,) and (ju // 20 == iu // 20).all() and (iu < ju).all()


@pytest.mark.parametrize("mode", ["decentralized", "centralized"])
def test_the_per_robot_flags_say_what_answered_each_robot(mode):
    """``FilterResult.flags`` along 16 robots resting and then at full throttle among obstacles (the defaults): the
    ``BACKUP`` bit is exactly ``backup``; ``RELAXED`` only at relaxed steps, ``GROUPED`` and ``RELAXED`` only in the
    decentralised mode, where both occur; ``UNSAFE`` only at unsafe steps."""
    from aasoatt_env.safety.result import BACKUP, GROUPED, RELAXED, UNSAFE
    from agents import ADVERSARIES

    env = make_env("random_goals", num_robots=16, random_obstacles=4, filter={"mode": mode}, max_steps=400)
    obs, _ = env.reset(seed=2)
    agent, seen = ADVERSARIES["burst"](), 0
    for _ in range(400):
        obs, *_ = env.step(agent.act(obs, env))
        if not env.agents:
            break
        for res in env.unwrapped.filter_outputs:
            f = res.flags
            assert f.shape == (16,) and np.array_equal((f & BACKUP) > 0, res.backup)
            assert not (f & UNSAFE).any() or res.status == "unsafe"
            assert not (f & RELAXED).any() or res.status in ("relaxed", "backup", "failed", "unsafe")
            seen |= int(np.bitwise_or.reduce(f))
    assert seen & BACKUP
    both = RELAXED | GROUPED
    assert (seen & both == both) if mode == "decentralized" else not seen & both
