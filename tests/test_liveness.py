"""The ``yield`` deadlock strategy's rules on hand-built states, the liveness scenarios and metrics, a closed loop."""

from __future__ import annotations

import numpy as np
import pytest

from aasoatt_env import FilterConfig, make_env
from aasoatt_env.analysis.metrics import arrival_times, liveness, pairwise_min_distance
from aasoatt_env.analysis.recording import run_episode
from aasoatt_env.errors import ConfigError, ScenarioError
from aasoatt_env.safety import liveness as L
from aasoatt_env.safety.deadlock import STRATEGIES, DeadlockState, TargetContext
from aasoatt_env.safety.detour import ROUTE_CLEARANCE, ROUTE_STEP, plan_route
from aasoatt_env.sim.scenarios import SCENARIOS, get_scenario
from tests.test_metrics import make_rollout

CFG = FilterConfig(deadlock="yield")
STALLED = int(round(L.STALL_TIME / CFG.dt))


def _step(p, p_d, memory, *, v=None, obstacles=None, obstacle_pairs=None, radius=0.48):
    """One call of the strategy on robots at rest: every robot pair in range, the tracking law's target, no trigger."""
    p, p_d = np.asarray(p, float), np.asarray(p_d, float)
    n = p.shape[0]
    pairs = np.array([(i, j) for i in range(n) for j in range(i + 1, n)], dtype=np.intp).reshape(-1, 2)
    ctx = TargetContext(np.zeros((n, 2)) if v is None else v, p, (p_d, np.zeros((n, 2))), CFG.k3, CFG.k4, memory,
                        pairs, np.zeros((0, 2), np.intp) if obstacle_pairs is None else obstacle_pairs, obstacles,
                        np.full(n, radius), np.zeros((n, 2)), CFG)
    nominal = -CFG.k3 * CFG.k4 * (p - p_d)  # the tracking law at rest (eqn.11): what the target is corrected from
    return STRATEGIES["yield"].correct_target(nominal, np.zeros(n), np.eye(2), ctx)


def _stalled_memory(p):
    state = DeadlockState()
    state.liveness = L.YieldMemory.empty(np.asarray(p, float))
    state.liveness.still[:] = STALLED
    return state


@pytest.fixture
def no_route(monkeypatch):
    """Rule 5 (boundary following) where the detour's grid has no way (rule 5b falls back on it)."""
    monkeypatch.setattr(L, "plan_route", lambda *args: None)


def test_registered_opt_in_and_the_default_unchanged():
    assert FilterConfig().deadlock == "auxiliary_velocity"
    s = STRATEGIES["yield"]
    assert s.stateful and s.needs_reference and not s.rotates_rows


def test_lower_priority_of_two_facing_stalled_robots_yields():
    p = [[0.0, 0.0], [1.2, 0.0]]  # gap 0.24 m, facing: robot 0 wants +x, robot 1 wants -x
    state = _stalled_memory(p)
    _step(p, [[9.0, 0.0], [-9.0, 0.0]], state)
    m = state.liveness
    assert m.hold[0] == 0 and m.hold[1] > 0 and m.rank[1] == 0.0
    np.testing.assert_allclose(m.away[1], [1.0, 0.0])


def test_a_queue_in_one_direction_does_not_yield():
    p = [[0.0, 0.0], [1.2, 0.0]]
    state = _stalled_memory(p)
    _step(p, [[9.0, 0.0], [9.0, 0.2]], state)
    assert not (state.liveness.hold > 0).any()


def test_priority_is_inherited_down_a_chain():
    # robot 1 yields to robot 0 and retreats along its trail toward robot 2, which wants to go where 1 came from
    p = [[0.0, 0.0], [1.2, 0.0], [2.4, 0.0]]
    state = _stalled_memory(p)
    m = state.liveness
    m.trail[1, :3] = [[3.0, 0.0], [2.0, 0.0], [1.5, 0.0]]
    m.count[1] = m.cursor[1] = 3
    m.hold[1], m.rank[1] = 10, 0.0
    m.still[2] = 0  # robot 2 moves: it is pushed by the yielder, not stalled
    target = _step(p, [[9.0, 0.0], [-9.0, 0.0], [-9.0, 0.0]], state)
    assert m.hold[2] > 0 and m.rank[2] == 0.0
    assert target[1, 0] > 0.0  # the yielder accelerates back along its trail (+x)


def test_in_a_passage_the_pusher_keeps_its_yielder_yielding_while_it_comes_on():
    # robot 1 yields with robot 0's priority (inherited: equal to its pusher's own); robot 0, not yielding, comes on
    # behind it within KEEP_GAP.  Between walls (no room to step aside) robot 1 keeps yielding, so a whole one-lane
    # corridor backs out; in the open, or once robot 0 heads elsewhere, its hold runs down
    p = [[0.0, 0.0], [1.2, 0.0]]
    x = np.arange(-1.0, 3.01, 0.5)
    walls = np.concatenate([np.stack((x, np.full_like(x, y)), axis=1) for y in (-1.1, 1.1)])
    radii = np.full(walls.shape[0], 0.3)
    pairs = np.array([(r, o) for r in range(2) for o in range(walls.shape[0])], dtype=np.intp)
    full = int(round(L.HOLD_TIME / CFG.dt))
    for goal0, obstacles, expected in (([9.0, 0.0], (walls, radii), full), ([9.0, 0.0], None, 2),
                                       ([-9.0, 0.0], (walls, radii), 2)):
        state = DeadlockState()
        m = state.liveness = L.YieldMemory.empty(np.asarray(p, float))
        m.hold[1], m.rank[1] = 3, 0.0
        _step(p, [goal0, [-9.0, 0.0]], state, obstacles=obstacles,
              obstacle_pairs=pairs if obstacles is not None else None)
        assert m.hold[1] == expected
        assert m.rank[1] == 0.0


def test_a_done_robot_in_the_way_is_pushed_only_on_contact():
    goal = [[9.0, 0.0], [1.2, 0.0]]
    for x, pushed in ((1.2, True), (2.0, False)):  # gaps 0.24 m and 1.04 m
        p = [[0.0, 0.0], [x, 0.0]]
        state = _stalled_memory(p)
        _step(p, [goal[0], [x, 0.0]], state)
        assert (state.liveness.hold[1] > 0) == pushed


def test_the_yielder_at_the_end_of_its_trail_steps_to_the_right_of_the_push():
    p = [[0.0, 0.0], [1.2, 0.0]]
    state = _stalled_memory(p)
    target = _step(p, [[9.0, 0.0], [-9.0, 0.0]], state)  # robot 1: no trail
    assert target[1, 1] < 0.0 and abs(target[1, 0]) < 1e-9  # pushed toward +x: its right is -y


def test_a_robot_stalled_at_an_obstacle_slides_along_it_toward_its_goal(no_route):
    p = [[0.0, 0.0]]
    state = _stalled_memory(p)
    obstacles = (np.array([[1.0, 0.1]]), np.array([0.3]))  # gap 0.225 m, centre slightly left of the way
    target = _step(p, [[5.0, 0.0]], state, obstacles=obstacles, obstacle_pairs=np.array([[0, 0]]))
    assert state.liveness.escape[0] > 0
    assert target[0, 1] < 0.0  # around the obstacle on the side nearer the goal


def test_a_robot_home_in_the_way_steps_aside_even_for_a_robot_that_is_not_stalled():
    p = [[0.0, 0.0], [1.2, 0.3]]  # robot 1 home 0.2 m from its goal, gap 0.28 m, a little left of robot 0's way
    state = DeadlockState()  # (no stall: robot 0 just arrives)
    target = _step(p, [[9.0, 0.0], [1.2, 0.5]], state)
    m = state.liveness
    assert m.hold[1] > 0 and m.rank[1] == 0.0 and m.aside[1]
    np.testing.assert_allclose(m.spot[1], [1.2, 0.48 + 0.48 + 0.3])  # off robot 0's line (y = 0) on its own side
    assert target[1, 1] > 0.0 and abs(target[1, 0]) < 1e-9  # sideways, not back along a trail toward robot 0
    assert target[0, 0] > 0.0  # robot 0 keeps its way


def test_a_robot_home_steps_aside_to_the_other_side_where_an_obstacle_takes_its_own():
    p = [[0.0, 0.0], [1.2, 0.3]]
    state = DeadlockState()
    obstacles = (np.array([[1.2, 1.6]]), np.array([0.5])), np.array([[1, 0]])  # on robot 1's spot (y = 1.26)
    _step(p, [[9.0, 0.0], [1.2, 0.5]], state, obstacles=obstacles[0], obstacle_pairs=obstacles[1])
    m = state.liveness
    assert m.aside[1]
    np.testing.assert_allclose(m.spot[1], [1.2, -1.26])  # across robot 0's line instead


def test_a_robot_home_beside_the_lane_is_not_pushed():
    for angle, pushed in ((45.0, True), (55.0, False)):  # gap 0.24 m, 0.85 m and 0.98 m off robot 0's line
        q = 1.2 * np.array([np.cos(np.radians(angle)), np.sin(np.radians(angle))])
        state = DeadlockState()
        _step([[0.0, 0.0], q], [[9.0, 0.0], q], state)  # (the lane: 0.96 m either side of the line)
        assert (state.liveness.hold[1] > 0) == pushed


def test_a_robot_stepping_aside_makes_nobody_yield():
    p = [[0.0, 0.0], [1.2, 0.0]]  # robot 0 stepping aside (it was home), facing robot 1 of lower priority
    state = _stalled_memory(p)
    m = state.liveness
    m.hold[0], m.rank[0], m.aside[0], m.spot[0] = 10, 0.0, True, [0.0, 1.3]
    _step(p, [[9.0, 0.0], [-9.0, 0.0]], state)
    assert m.hold[1] == 0


def test_a_robot_beside_the_lane_does_not_keep_one_from_following_an_obstacle(no_route):
    q = 1.2 * np.array([np.cos(np.radians(55.0)), np.sin(np.radians(55.0))])  # gap 0.24 m, 0.98 m off the line
    p = [[0.0, 0.0], q]
    state = _stalled_memory(p)
    obstacles = (np.array([[1.0, -0.1]]), np.array([0.3]))  # in robot 0's way, in contact
    _step(p, [[5.0, 0.0], q], state, obstacles=obstacles, obstacle_pairs=np.array([[0, 0]]))
    assert state.liveness.escape[0] > 0


def test_boundary_following_turns_at_an_inner_corner(no_route):
    # two discs close together ahead and to the right: the tangent of the first runs into the second
    p = [[0.0, 0.0]]
    state = _stalled_memory(p)
    obstacles = (np.array([[1.0, 0.1], [0.3, -0.95]]), np.array([0.3, 0.3]))  # gaps 0.225 m and 0.216 m
    target = _step(p, [[5.0, 0.0]], state, obstacles=obstacles, obstacle_pairs=np.array([[0, 0], [0, 1]]))
    m = state.liveness
    u = np.array([0.3, -0.95]) / np.hypot(0.3, -0.95)  # toward the second disc: follow its tangent, same hand
    np.testing.assert_allclose(m.slide[0], (np.array([u[1], -u[0]]) + 0.3 * u) / np.hypot(1.0, 0.3))
    assert target[0, 0] < 0.0 and target[0, 1] < 0.0  # out of the corner, not into the second disc


def test_boundary_following_ends_once_nearer_the_goal_with_the_way_clear(no_route):
    p = [[0.0, 0.0]]
    state = _stalled_memory(p)
    m = state.liveness
    m.escape[0], m.hit[0], m.slide[0], m.hand[0] = 500, 6.0, [0.0, -1.0], 1.0  # began 6 m from its goal
    obstacles = (np.array([[-1.0, 0.5]]), np.array([0.3]))  # behind it, in contact: not in its way
    _step(p, [[5.0, 0.0]], state, obstacles=obstacles, obstacle_pairs=np.array([[0, 0]]))
    assert m.escape[0] == 0  # 5 m < 6 m - STALL_ERROR: it leaves the boundary
    state = _stalled_memory(p)
    m = state.liveness
    m.escape[0], m.hit[0], m.slide[0], m.hand[0] = 500, 5.2, [0.0, -1.0], 1.0  # not nearer by STALL_ERROR
    _step(p, [[5.0, 0.0]], state, obstacles=obstacles, obstacle_pairs=np.array([[0, 0]]))
    assert m.escape[0] == 499


PINCH = (np.array([[0.9, 0.55], [0.9, -0.55]]), np.array([0.4, 0.4]))  # a gap of 0.3 m ahead, 0.96 m robots


def _clearance(pts, obstacles, radius=0.48):
    d = np.linalg.norm(pts[:, None] - obstacles[0][None], axis=2) - obstacles[1][None] - radius
    return d.min(axis=1)


def test_detour_goes_round_a_gap_narrower_than_the_robot():
    pts = plan_route(np.zeros(2), np.array([5.0, 0.0]), 0.48, *PINCH, 0, 1.0, np.array([1.0, 0.0]))
    np.testing.assert_allclose(pts[-1], [5.0, 0.0])
    assert np.linalg.norm(pts[0]) <= ROUTE_STEP + 1e-9
    assert np.all(np.linalg.norm(np.diff(pts, axis=0), axis=1) <= ROUTE_STEP + 1e-9)
    assert _clearance(pts, PINCH).min() >= ROUTE_CLEARANCE  # never through the gap: round a disc
    assert np.abs(pts[:, 1]).max() > 0.55 + 0.4 + 0.48


def test_detour_is_none_when_the_goal_is_walled_in():
    a = np.linspace(0.0, 2.0 * np.pi, 12, endpoint=False)
    ring = (np.stack((4.0 + 1.5 * np.cos(a), 1.5 * np.sin(a)), axis=1), np.full(12, 0.35))  # gaps 0.08 m
    assert plan_route(np.zeros(2), np.array([4.0, 0.0]), 0.48, *ring, 0, 1.0, np.array([1.0, 0.0])) is None


def test_a_robot_stalled_at_a_gap_narrower_than_itself_takes_a_detour_round_it():
    p = [[0.0, 0.0]]  # gaps 0.175 m to both discs, both ahead: boundary following would slide into the gap
    state = _stalled_memory(p)
    target = _step(p, [[5.0, 0.0]], state, obstacles=PINCH, obstacle_pairs=np.array([[0, 0], [0, 1]]))
    m = state.liveness
    assert m.stop[0] > 0 and m.escape[0] == 0 and m.still[0] == 0  # a route, not the boundary; the clock restarts
    route = m.route[0, :m.stop[0]]
    np.testing.assert_allclose(route[-1], [5.0, 0.0])
    assert _clearance(route[2:], PINCH).min() >= ROUTE_CLEARANCE
    target = _step(p, [[5.0, 0.0]], state, obstacles=PINCH, obstacle_pairs=np.array([[0, 0], [0, 1]]))
    assert abs(target[0, 1]) > abs(target[0, 0])  # sideways, out of the mouth of the gap, not on into it


def test_a_robot_on_a_detour_leaves_it_while_it_yields():
    p = [[0.0, 0.0]]
    state = _stalled_memory(p)
    _step(p, [[5.0, 0.0]], state, obstacles=PINCH, obstacle_pairs=np.array([[0, 0], [0, 1]]))
    m = state.liveness
    stop = m.stop[0]
    m.hold[0], m.rank[0], m.away[0] = 10, 0.0, [1.0, 0.0]  # pushed toward +x, no trail: it steps to its right
    target = _step(p, [[5.0, 0.0]], state, obstacles=PINCH, obstacle_pairs=np.array([[0, 0], [0, 1]]))
    assert m.stop[0] == stop and target[0, 1] < 0.0 and abs(target[0, 0]) < 1e-9


def test_lone_robot_on_its_reference_is_untouched():
    state = DeadlockState()
    target = _step([[0.0, 0.0]], [[0.5, 0.0]], state)
    np.testing.assert_array_equal(target, [[CFG.k3 * CFG.k4 * 0.5, 0.0]])


@pytest.mark.parametrize("name", ["corridor", "doorway", "obstacle_field"])
def test_scenarios_registered_and_seeded(name):
    assert name in SCENARIOS
    sc = get_scenario(name)
    a, b, c = (sc.build(np.random.default_rng(s)) for s in (1, 1, 2))
    np.testing.assert_array_equal(a.starts, b.starts)
    np.testing.assert_array_equal(a.obstacle_centers, b.obstacle_centers)
    assert a.obstacle_radii.size > 0
    if name != "corridor":  # (the corridor is the same for every seed)
        assert not np.array_equal(a.starts, c.starts)


def test_corridor_walls_leave_the_stated_width():
    c, r = get_scenario("corridor", width=1.6, flange=0.0).obstacles()
    inner = np.abs(c[:, 1]) - r
    np.testing.assert_allclose(inner.min(), 0.8)


@pytest.mark.parametrize("name, kwargs, match", [
    ("corridor", dict(width=0.9), "width: got 0.9 m, but a robot is 0.96 m across"),
    ("corridor", dict(left=0, right=0), "left, right: got 0 and 0 robots"),
    ("corridor", dict(flange=-1.0), "flange"),
    ("doorway", dict(door=0.5), "door: got 0.5 m"),
    ("doorway", dict(left=40, room=3.0), "do not fit in a room"),
    ("obstacle_field", dict(density=0.9), "density"),
    ("obstacle_field", dict(radii=(0.8, 0.3)), "radii: got"),
])
def test_scenario_errors(name, kwargs, match):
    with pytest.raises((ConfigError, ScenarioError), match=match):
        get_scenario(name, **kwargs)


def test_arrival_times_and_makespan():
    x = np.array([0.0, 0.5, 1.0, 1.0, 0.9, 1.0, 1.0])  # robot 0 home at step 5 (it left once); robot 1 never
    pos = np.stack([np.stack((x, np.zeros(7)), axis=1), np.zeros((7, 2))], axis=1)
    ref = pos.copy()
    ref[:, 0, 0] = np.minimum(np.arange(7) * 0.5, 1.0)
    ro = make_rollout(pos, references=ref, goals=np.array([[1.0, 0.0], [3.0, 0.0]]))
    np.testing.assert_allclose(arrival_times(ro, 0.05), [0.5, np.nan])
    live = liveness(ro, goal_tolerance=0.05)
    assert live["home"] == 1 and live["makespan"] is None and live["makespan_ratio"] is None
    ro1 = make_rollout(pos[:, :1], references=ref[:, :1], goals=np.array([[1.0, 0.0]]))
    live = liveness(ro1, goal_tolerance=0.05)
    assert live["makespan"] == pytest.approx(0.5)
    assert live["lower_bound"] == pytest.approx(0.2)  # 1 m at the reference's 5 m/s
    assert live["makespan_ratio"] == pytest.approx(2.5)


@pytest.mark.parametrize("mode", ["centralized", pytest.param("decentralized", marks=pytest.mark.slow)])
def test_one_lane_corridor_closed_loop_all_home(mode):
    from agents import TrackingController

    env = make_env(filter=FilterConfig(mode=mode, deadlock="yield"), scenario="corridor", width=1.6, left=1,
                   right=1, length=4.0, approach=2.0, flange=3.0, duration=15.0, settle_time=35.0)
    ro, _ = run_episode(env, TrackingController(), seed=0)
    live = liveness(ro, goal_tolerance=0.05)
    assert live["home"] == 2 and live["makespan_ratio"] >= 1.0
    sep = pairwise_min_distance(ro)
    assert min(sep.overall_min_robot_gap, sep.overall_min_obstacle_gap) > -1e-3


@pytest.mark.slow
@pytest.mark.parametrize("scene, seed", [
    # a robot home by the door in the way of one coming through it (two robots stuck without rule 3b)
    (dict(scenario="doorway", left=2, right=2, door=1.6, room=5.0, duration=15.0, settle_time=60.0), 12),
    # a robot home by the door: a detour round it (as round an obstacle) led along the wall, far off
    (dict(scenario="doorway", left=2, right=2, door=1.6, room=5.0, duration=15.0, settle_time=60.0), 48),
    # a robot stalled between two discs close together (stuck without the inner-corner turn and the Bug2 exit)
    (dict(scenario="obstacle_field", num_robots=5, density=0.1, arena_size=9.0, settle_time=30.0), 11),
])
def test_campaign_scenes_that_got_stuck_get_home(scene, seed):
    from agents import TrackingController

    env = make_env(filter=FilterConfig(deadlock="yield"), **scene)
    ro, _ = run_episode(env, TrackingController(), seed=seed)
    live = liveness(ro, goal_tolerance=0.05)
    assert live["home"] == live["n_robots"]
    sep = pairwise_min_distance(ro)
    assert min(sep.overall_min_robot_gap, sep.overall_min_obstacle_gap) > -1e-3


def test_field_robots_wedged_in_gaps_narrower_than_themselves_get_home():
    # the campaign's obstacle_field seed 159: three robots stalled in gaps between discs narrower than they are,
    # boundary following sliding each from one disc into the next (stuck without the detour, rule 5b)
    from agents import TrackingController

    env = make_env(filter=FilterConfig(deadlock="yield"), scenario="obstacle_field", num_robots=5, density=0.1,
                   arena_size=9.0, settle_time=30.0)
    ro, _ = run_episode(env, TrackingController(), seed=159)
    assert liveness(ro, goal_tolerance=0.05)["home"] == 5
    sep = pairwise_min_distance(ro)
    assert min(sep.overall_min_robot_gap, sep.overall_min_obstacle_gap) > -1e-3
