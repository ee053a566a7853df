"""Unit tests of aasoatt_env.analysis.rollout and aasoatt_env.analysis.metrics on tiny hand-computed rollouts."""

from __future__ import annotations

import json

import numpy as np
import pytest

from aasoatt_env.analysis.metrics import (
    collisions,
    deadlocked_robots,
    final_errors,
    format_summary,
    intervention_time,
    intervention_times,
    longest_stall,
    pairwise_min_distance,
    reach_rate,
    safe_rate,
    solver_stats,
    summarize,
    tracking_errors,
    tracking_stats,
)
from aasoatt_env.analysis.rollout import Rollout, RolloutBuilder
from aasoatt_env.errors import ConfigError


def make_rollout(positions, *, dt=0.1, references=None, velocities=None, goals=None, radii=None, **kw):
    p = np.asarray(positions, dtype=float)
    T, N, _ = p.shape
    return Rollout(
        dt=dt,
        times=np.arange(T) * dt,
        positions=p,
        velocities=np.zeros_like(p) if velocities is None else velocities,
        headings=np.zeros((T, N)),
        references=p.copy() if references is None else references,
        reference_velocities=np.zeros_like(p),
        goals=p[-1].copy() if goals is None else goals,
        radii=np.full(N, 0.5) if radii is None else radii,
        **kw,
    )


# --------------------------------------------------------------------------- tracking
def test_tracking_errors_345():
    # Robot 0 is off by (3, 4) -> 5 at every step; robot 1 by (0.6, 0.8) -> 1 at step 1 only.
    refs = np.zeros((2, 2, 2))
    refs[:, 1] = [10.0, 0.0]
    pos = refs.copy()
    pos[:, 0] += [3.0, 4.0]
    pos[1, 1] += [0.6, 0.8]
    ro = make_rollout(pos, references=refs)
    e = tracking_errors(ro)
    np.testing.assert_allclose(e, [[5.0, 0.0], [5.0, 1.0]])
    st = tracking_stats(ro)
    # samples 5, 5, 0, 1
    assert st["mae"] == pytest.approx(11 / 4)
    assert st["rmse"] == pytest.approx(np.sqrt(51 / 4))
    assert st["std"] == pytest.approx(np.sqrt(51 / 4 - (11 / 4) ** 2))  # population std
    assert st["std"] == pytest.approx(np.std([5, 5, 0, 1]))
    assert st["max"] == 5.0


def test_final_errors_and_reach_rate():
    pos = np.array([[[0.0, 0.0], [5.0, 0.0], [0.0, 5.0]]] * 2)
    goals = np.array([[3.0, 4.0], [5.0, 0.05], [0.0, 5.0]])
    ro = make_rollout(pos, goals=goals, radii=np.full(3, 0.1))
    np.testing.assert_allclose(final_errors(ro), [5.0, 0.05, 0.0])
    assert reach_rate(ro, goal_tolerance=0.1) == pytest.approx(2 / 3)
    assert reach_rate(ro, goal_tolerance=0.01) == pytest.approx(1 / 3)
    assert reach_rate(ro, goal_tolerance=5.0) == 1.0
    with pytest.raises(ConfigError, match="goal_tolerance"):
        reach_rate(ro, goal_tolerance=-1)


# ----------------------------------------------------------------- intervention time
def test_intervention_time_known_window():
    T, N = 10, 3
    avoiding = np.zeros((T, N), dtype=bool)
    avoiding[2:7, 0] = True  # first 2, last 6 -> 4 steps
    avoiding[[1, 3, 9], 1] = True  # gaps inside the window still count: 1..9 -> 8 steps
    # robot 2 never avoids -> 0
    pos = np.zeros((T, N, 2))
    pos[:, :, 0] = [0.0, 5.0, 10.0]
    ro = make_rollout(pos, dt=0.005, avoiding=avoiding)
    np.testing.assert_allclose(intervention_times(ro), [4 * 0.005, 8 * 0.005, 0.0])
    assert intervention_time(ro) == pytest.approx(12 * 0.005 / 3)


def test_intervention_time_requires_avoiding():
    ro = make_rollout(np.zeros((2, 1, 2)))
    with pytest.raises(ConfigError, match="avoiding"):
        intervention_time(ro)
    assert summarize(ro)["intervention_time"] is None


# ------------------------------------------------------------- separation / collisions
def approaching_pair():
    # Robots 0 and 1 on the x axis approach: centre distances 3, 2, 1, 0.5, 1;
    # robot 2 far away.  Radii 0.5 and 0.25 -> safety distance 0.75.
    x1 = np.array([3.0, 2.0, 1.0, 0.5, 1.0])
    pos = np.zeros((5, 3, 2))
    pos[:, 1, 0] = x1
    pos[:, 2] = [20.0, 20.0]
    return make_rollout(pos, radii=np.array([0.5, 0.25, 0.5]))


def test_pairwise_min_distance():
    sep = pairwise_min_distance(approaching_pair())
    np.testing.assert_allclose(sep.min_center_distance, [3.0, 2.0, 1.0, 0.5, 1.0])
    np.testing.assert_allclose(sep.min_robot_gap, [2.25, 1.25, 0.25, -0.25, 0.25])
    np.testing.assert_array_equal(sep.closest_pair, [[0, 1]] * 5)
    assert sep.overall_min_center_distance == 0.5
    assert sep.overall_min_robot_gap == pytest.approx(-0.25)
    assert np.isinf(sep.overall_min_obstacle_gap)
    assert sep.overall_min_gap == pytest.approx(-0.25)


def test_pairwise_gap_uses_each_pairs_radii():
    # Pair (0,1) closer in centre distance, pair (1,2) smaller gap due to big radius.
    pos = np.array([[[0.0, 0.0], [1.0, 0.0], [2.5, 0.0]]])
    ro = make_rollout(pos, radii=np.array([0.1, 0.1, 1.5]))
    sep = pairwise_min_distance(ro)
    assert sep.min_center_distance[0] == pytest.approx(1.0)
    assert sep.min_robot_gap[0] == pytest.approx(1.5 - 1.6)
    np.testing.assert_array_equal(sep.closest_pair[0], [1, 2])


def test_collision_known_step():
    ro = approaching_pair()
    rep = collisions(ro)
    assert rep.robot_pairs == [(0, 1, 3)]
    assert rep.obstacle_hits == []
    assert rep.n_robot_pairs == 1
    np.testing.assert_array_equal(rep.colliding_robots, [True, True, False])
    assert safe_rate(ro) == pytest.approx(1 / 3)
    # A tolerance larger than the overlap (0.25) forgives it.
    assert collisions(ro, tolerance=0.3).robot_pairs == []
    assert safe_rate(ro, tolerance=0.3) == 1.0


def test_collision_tolerance_boundary():
    # Distance 0.9995 with d_s = 1: overlap 5e-4 < default tolerance 1e-3 -> no collision.
    pos = np.array([[[0.0, 0.0], [0.9995, 0.0]]])
    ro = make_rollout(pos)
    assert not collisions(ro).any
    assert collisions(ro, tolerance=1e-4).robot_pairs == [(0, 1, 0)]


def test_obstacle_collision_and_gap():
    # Obstacle at (0, 3), radius 1; robot 0 moves up the y axis with radius 0.5.
    pos = np.zeros((4, 2, 2))
    pos[:, 0, 1] = [0.0, 1.0, 1.8, 1.0]
    pos[:, 1] = [10.0, 0.0]
    ro = make_rollout(pos, obstacle_centers=[[0.0, 3.0]], obstacle_radii=[1.0])
    sep = pairwise_min_distance(ro)
    np.testing.assert_allclose(sep.min_obstacle_gap, [1.5, 0.5, -0.3, 0.5])
    rep = collisions(ro)
    assert rep.obstacle_hits == [(0, 0, 2)]
    assert rep.robot_pairs == []
    assert safe_rate(ro) == 0.5


def test_collisions_chunked_matches_bruteforce(monkeypatch):
    import aasoatt_env.analysis.metrics as m

    monkeypatch.setattr(m, "_CHUNK_ELEMENTS", 50)  # forces 1-step chunks for N = 6
    rng = np.random.default_rng(1)
    T, N = 30, 6
    pos = np.cumsum(rng.normal(scale=0.3, size=(T, N, 2)), axis=0) + rng.uniform(-2, 2, (1, N, 2))
    radii = rng.uniform(0.2, 0.5, N)
    ro = make_rollout(pos, radii=radii)
    d = np.linalg.norm(pos[:, :, None] - pos[:, None], axis=-1)
    rs = radii[:, None] + radii[None]
    hit = d < rs - 1e-3
    expected = sorted(
        (i, j, int(np.argmax(hit[:, i, j]))) for i in range(N) for j in range(i + 1, N) if hit[:, i, j].any()
    )
    got = collisions(ro).robot_pairs
    assert sorted(got) == expected
    gap = np.where(np.eye(N, dtype=bool), np.inf, d - rs)
    np.testing.assert_allclose(pairwise_min_distance(ro).min_robot_gap, gap.min(axis=(1, 2)))


# -------------------------------------------------------------------------- deadlock
def test_deadlocked_robot():
    T, N, dt = 10, 3, 0.1
    pos = np.zeros((T, N, 2))
    pos[:, 0, 0] = [0, 1, 2, 2, 2, 2, 2, 2, 2, 2]  # stops at x = 2 from step 2 to 9, goal at 5
    pos[:, 1, 0] = np.arange(T) + 20.0  # keeps moving
    pos[:, 2, 0] = [40, 41, 42, 43, 44, 45, 45, 45, 45, 45]  # parks on its goal at 45
    vel = np.zeros((T, N, 2))
    vel[:, 1, 0] = 1.0
    vel[:2, 0, 0] = 1.0
    vel[:5, 2, 0] = 1.0
    goals = np.array([[5.0, 0.0], [100.0, 0.0], [45.0, 0.0]])
    ro = make_rollout(pos, dt=dt, velocities=vel, goals=goals)
    stall = longest_stall(ro, speed_threshold=0.05, goal_tolerance=0.1)
    assert stall[0] == pytest.approx(0.7)  # steps 2..9
    assert stall[1] < 0  # never stalled
    assert stall[2] < 0  # slow only at its goal
    np.testing.assert_array_equal(
        deadlocked_robots(ro, speed_threshold=0.05, dwell_time=0.5, goal_tolerance=0.1), [True, False, False]
    )
    np.testing.assert_array_equal(
        deadlocked_robots(ro, speed_threshold=0.05, dwell_time=0.7, goal_tolerance=0.1), [True, False, False]
    )
    np.testing.assert_array_equal(
        deadlocked_robots(ro, speed_threshold=0.05, dwell_time=0.8, goal_tolerance=0.1), [False, False, False]
    )


def test_stall_runs_are_uninterrupted():
    T = 8
    vel = np.zeros((T, 1, 2))
    vel[3, 0, 0] = 1.0  # one fast step splits the stall into 0..2 and 4..7
    ro = make_rollout(np.zeros((T, 1, 2)), dt=1.0, velocities=vel, goals=[[9.0, 0.0]])
    assert longest_stall(ro)[0] == pytest.approx(3.0)


# ---------------------------------------------------------------------------- solver
def test_solver_stats():
    status = ["optimal", "optimal", "relaxed", "PRIMAL_INFEASIBLE", "optimal"]
    ro = make_rollout(
        np.zeros((5, 1, 2)),
        solver_status=status,
        solve_time=[1e-3, 2e-3, 3e-3, 4e-3, 10e-3],
        slack=[0, 0, 0.2, 0, 0],
    )
    st = solver_stats(ro)
    assert st["relaxed_fraction"] == pytest.approx(0.2)
    assert st["failed_fraction"] == pytest.approx(0.2)
    assert st["status_counts"] == {"optimal": 3, "relaxed": 1, "PRIMAL_INFEASIBLE": 1}
    assert st["solve_time_median"] == pytest.approx(3e-3)
    assert st["solve_time_mean"] == pytest.approx(4e-3)
    assert st["solve_time_max"] == pytest.approx(10e-3)
    assert st["slack_max"] == pytest.approx(0.2)
    empty = solver_stats(make_rollout(np.zeros((2, 1, 2))))
    assert all(v is None for v in empty.values())


# --------------------------------------------------------------------------- summary
def test_summarize_json_and_format():
    ro = approaching_pair()
    ro.avoiding = np.zeros((5, 3), dtype=bool)
    ro.avoiding[1:4, :2] = True
    s = summarize(ro)
    json.dumps(s)  # JSON-friendly
    assert s["n_robots"] == 3 and s["n_steps"] == 5
    assert s["intervention_time"] == pytest.approx(2 * 0.2 / 3)
    assert s["n_collision_pairs"] == 1
    assert s["n_colliding_robots"] == 2
    assert s["safe_rate"] == pytest.approx(1 / 3)
    assert s["min_robot_gap"] == pytest.approx(-0.25)
    assert s["min_obstacle_gap"] is None
    assert s["rmse"] == 0.0
    text = format_summary(s)
    lines = text.splitlines()
    assert len(lines) == len(s)
    assert lines[0].split() == ["n_robots", "3"]
    assert any(line.split() == ["min_obstacle_gap", "-"] for line in lines)
    assert len({len(line) for line in lines}) == 1  # aligned
    assert any(line.split() == ["solve_time_max", "-"] for line in lines)  # no solver: no unit either


def test_format_summary_solve_times_carry_their_unit():
    lines = format_summary({"solve_time_median": 1.25e-3, "solve_time_max": 0.0123, "duration": 2.0}).splitlines()
    assert [line.split() for line in lines] == [["solve_time_median", "1.2500", "ms"],
                                                ["solve_time_max", "12.3000", "ms"], ["duration", "2.0000"]]


# ---------------------------------------------------------------- rollout container
def full_rollout():
    rng = np.random.default_rng(0)
    T, N = 4, 2
    return Rollout(
        dt=0.005,
        times=np.arange(T) * 0.005,
        positions=rng.normal(size=(T, N, 2)),
        velocities=rng.normal(size=(T, N, 2)),
        headings=rng.normal(size=(T, N)),
        references=rng.normal(size=(T, N, 2)),
        reference_velocities=rng.normal(size=(T, N, 2)),
        goals=rng.normal(size=(N, 2)),
        radii=[0.48, 0.3],
        obstacle_centers=[[1.0, 2.0]],
        obstacle_radii=[0.5],
        nominal_actions=rng.normal(size=(T, N, 2)),
        actions=rng.normal(size=(T, N, 2)),
        avoiding=rng.random((T, N)) < 0.5,
        triggered=rng.random((T, N)) < 0.5,
        backup=rng.random((T, N)) < 0.5,
        solver_status=["optimal", "relaxed", "optimal", "failed"],
        slack=[0.0, 0.1, 0.0, 0.0],
        solve_time=[1e-4, 2e-4, 3e-4, 4e-4],
        metadata={"scenario": "circle", "method": "aa-soatt", "params": {"N": 2, "q_deg": -60}},
    )


def test_save_load_round_trip(tmp_path):
    ro = full_rollout()
    path = tmp_path / "ep.npz"
    ro.save(path)
    back = Rollout.load(path)
    assert back.dt == ro.dt
    assert back.metadata == ro.metadata
    for name in Rollout.ARRAY_FIELDS:
        a, b = getattr(ro, name), getattr(back, name)
        assert a.dtype == b.dtype, name
        np.testing.assert_array_equal(a, b, err_msg=name)


def test_save_load_minimal(tmp_path):
    ro = make_rollout(np.zeros((3, 2, 2)) + [[0.0, 0.0], [3.0, 0.0]])
    ro.save(tmp_path / "m.npz")
    back = Rollout.load(tmp_path / "m.npz")
    assert back.avoiding is None and back.solver_status is None
    assert back.obstacle_centers.shape == (0, 2)
    assert back.metadata == {}


def test_shape_validation_messages():
    ro = full_rollout()
    kwargs = {name: getattr(ro, name) for name in ("dt", *Rollout.ARRAY_FIELDS)}
    with pytest.raises(
        ConfigError,
        match=r"velocities: got shape \(4, 3, 2\), expected \(T, N, 2\) = \(4, 2, 2\)",
    ):
        Rollout(**{**kwargs, "velocities": np.zeros((4, 3, 2))})
    with pytest.raises(ConfigError, match=r"headings: got shape \(4, 2, 1\), expected \(T, N\)"):
        Rollout(**{**kwargs, "headings": np.zeros((4, 2, 1))})
    with pytest.raises(ConfigError, match=r"radii: got shape \(3,\), expected \(N,\) = \(2,\)"):
        Rollout(**{**kwargs, "radii": [0.5, 0.5, 0.5]})
    with pytest.raises(ConfigError, match=r"obstacle_radii: got shape \(2,\), expected \(M,\) = \(1,\)"):
        Rollout(**{**kwargs, "obstacle_radii": [0.5, 0.5]})
    with pytest.raises(ConfigError, match=r"solver_status: got shape \(3,\), expected \(T,\) = \(4,\)"):
        Rollout(**{**kwargs, "solver_status": ["a", "b", "c"]})
    with pytest.raises(ConfigError, match="avoiding: got non-boolean"):
        Rollout(**{**kwargs, "avoiding": np.full((4, 2), 0.5)})
    with pytest.raises(ConfigError, match="dt: got"):
        Rollout(**{**kwargs, "dt": 0.0})
    with pytest.raises(ConfigError, match="radii: got .* expected positive"):
        Rollout(**{**kwargs, "radii": [0.5, -1.0]})
    with pytest.raises(ConfigError, match="times: got decreasing"):
        Rollout(**{**kwargs, "times": [0.0, 0.2, 0.1, 0.3]})
    with pytest.raises(ConfigError, match="metadata: not JSON"):
        Rollout(**{**kwargs, "metadata": {"x": object()}})


def test_builder_matches_direct_construction():
    ro = full_rollout()
    b = RolloutBuilder(ro.dt, goals=ro.goals, radii=ro.radii, metadata={"scenario": "circle"})
    for k in range(ro.n_steps):
        b.append(
            time=ro.times[k],
            positions=ro.positions[k],
            velocities=ro.velocities[k],
            headings=ro.headings[k],
            references=ro.references[k],
            reference_velocities=ro.reference_velocities[k],
            avoiding=ro.avoiding[k],
            solver_status=ro.solver_status[k],
            solve_time=ro.solve_time[k],
        )
    assert len(b) == ro.n_steps
    built = b.build(
        obstacle_centers=ro.obstacle_centers, obstacle_radii=ro.obstacle_radii, metadata={"method": "x"}
    )
    assert built.metadata == {"scenario": "circle", "method": "x"}
    for name in (
        "times",
        "positions",
        "headings",
        "avoiding",
        "solver_status",
        "solve_time",
        "obstacle_radii",
    ):
        np.testing.assert_array_equal(getattr(built, name), getattr(ro, name), err_msg=name)
    assert built.avoiding.dtype == bool
    assert built.actions is None


def test_builder_copies_buffers_and_rejects_inconsistency():
    b = RolloutBuilder(0.1, goals=[[0.0, 0.0]], radii=[0.5])
    buf = np.zeros((1, 2))
    step = dict(velocities=buf, headings=[0.0], references=buf, reference_velocities=buf)
    b.append(time=0.0, positions=buf, avoiding=[True], **step)
    buf[:] = 7.0  # caller reuses its buffer
    with pytest.raises(ConfigError, match="avoiding: given at 1 of the 1 previous steps"):
        b.append(time=0.1, positions=buf, **step)
    b.append(time=0.1, positions=buf, avoiding=[False], **step)
    ro = b.build()
    np.testing.assert_array_equal(ro.positions[:, 0, 0], [0.0, 7.0])
    with pytest.raises(ConfigError, match="unknown field"):
        b.append(time=0.2, positions=buf, bogus=1, **step)
    with pytest.raises(ConfigError, match="no step recorded"):
        RolloutBuilder(0.1, goals=[[0.0, 0.0]], radii=[0.5]).build()
    with pytest.raises(ConfigError, match="radii: missing"):
        nb = RolloutBuilder(0.1, goals=[[0.0, 0.0]])
        nb.append(time=0.0, positions=buf, **step)
        nb.build()
