"""The solver policy: which solver answers which QP is a function of the problem and the configuration alone."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers import circle_layout, closed_loop

import aasoatt_env.safety.solvers.backends as backends
import aasoatt_env.safety.solvers.policy as pol
from aasoatt_env.model.dynamics import kinematics, pose_from_point
from aasoatt_env.model.params import make_team
from aasoatt_env.safety import SafetyFilter
from aasoatt_env.safety.problem import build_problem

HAS_DAQP = "daqp" in backends.available_solvers()


def _contradiction(n: int, upper: float = -1.0):
    """``n`` robots, each with the rows ``du_x <= upper`` and ``du_x >= 1``: with the default ``upper`` infeasible,
    every row's least violation 1; with ``upper = 2`` feasible, the target (0.5, 0.25) -> du = (1, 0.25)."""
    idx = np.repeat(np.arange(n), 2)
    Gi = np.tile([[1.0, 0.0], [-1.0, 0.0]], (n, 1))
    return build_problem(np.tile(np.eye(2), (n, 1, 1)), np.tile([0.5, 0.25], (n, 1)), -3 * np.ones((n, 2)),
                         3 * np.ones((n, 2)), np.ones(n), idx, -np.ones(2 * n, int), Gi, np.zeros((2 * n, 2)),
                         np.tile([upper, -1.0], n))


def _spy(monkeypatch):
    """Record the name of every back-end the policy calls."""
    asked = []

    def spied(real, k):
        return None if real is None else lambda *a: asked.append(k) or real(*a)

    for name, backend in list(backends.SOLVERS.items()):
        monkeypatch.setitem(backends.SOLVERS, name, dataclasses.replace(
            backend, solve=spied(backend.solve, name), least_violation=spied(backend.least_violation, name)))
    return asked


def test_the_route_is_a_table_of_sizes_and_back_ends():
    daqp = ["daqp"] if HAS_DAQP else []
    assert [k for k, _ in pol.route("proxsuite", 40)] == [*daqp, "ldp", "proxsuite"]
    assert [k for k, _ in pol.route("proxsuite", 500)] == [*daqp, "ldp", "proxsuite"]
    assert [k for k, _ in pol.route("proxsuite", 501)] == ["proxsuite"]
    assert [k for k, _ in pol.route("ldp", 40)] == ["ldp"]
    if HAS_DAQP:
        assert pol.route("daqp", 40) == [("daqp", {})]  # as configured: the box as rows
        assert pol.route("proxsuite", 40)[0] == ("daqp", {"simple_bounds": True, "warm_start": True})


def test_a_stalling_back_end_is_not_asked_where_the_exact_route_answers(monkeypatch):
    """proxsuite starved of iterations changes nothing on a problem the exact solvers take."""
    monkeypatch.setitem(backends.ITER_LIMIT, "proxsuite", 2)
    asked = _spy(monkeypatch)
    ok = _contradiction(3, upper=2.0)
    sol = pol.solve_qp(ok, "proxsuite")
    assert sol.status == "solved" and "proxsuite" not in asked
    np.testing.assert_allclose(sol.x.reshape(3, 2), [[1.0, 0.25]] * 3, atol=1e-12)


def test_a_stall_beyond_the_exact_route_goes_to_phase_one_and_never_returns_nan(monkeypatch):
    monkeypatch.setitem(backends.ITER_LIMIT, "proxsuite", 1)
    monkeypatch.setattr(pol, "EXACT_ROUTE", ())
    sol = pol.solve_qp(_contradiction(3, upper=2.0), "proxsuite")
    assert "MAX_ITER" in sol.message and np.all(np.isfinite(sol.x)) and np.all(np.isfinite(sol.z))
    assert sol.status in ("solved", "relaxed")


@pytest.mark.parametrize("n", [5, 40])
def test_phase_one_finds_every_rows_least_violation(monkeypatch, n):
    """The phase-1 problem goes to the first installed solver of PHASE1_ROUTE for its size (before a back-end that
    may stall), then ``ldp``; each row's least violation is found exactly (1 here) and the loosened rows hold."""
    prob = _contradiction(n)
    asked = _spy(monkeypatch)
    sol = pol.solve_qp(prob, "proxsuite")
    assert sol.status == "relaxed" and sol.slack == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(sol.x.reshape(n, 2), [[0.0, 0.25]] * n, atol=2e-6)  # (rows loosened by 1 + 1.1e-6)
    p1 = prob.n + prob.m
    expected = pol._phase1_order("proxsuite", p1)[0]
    first_infeasible = asked.index("daqp" if HAS_DAQP else "ldp")
    assert asked[first_infeasible + 1] == expected  # the route proved it infeasible, then phase 1 asked this one
    assert "phase 1: largest row violation 1" in sol.message


@pytest.mark.skipif(not HAS_DAQP, reason="needs daqp")
def test_daqps_soft_rows_answer_phase_one_as_the_slack_variables_do(monkeypatch):
    """DAQP's own phase 1 (soft rows, no slack variables) finds the same least violations and point as the
    phase-1 problem with a slack per row, on rows of every kind: met, violated, hopeless."""
    for n in (3, 12):
        prob = _contradiction(n)
        prob.u[0] += 3.5  # robot 0: du_x <= 2.5 and >= 1, met
        prob.u[2] += 1.0  # robot 1: du_x <= 0 and >= 1, each row violated by 0.5 at least; the others by 1
        soft = backends.SOLVERS["daqp"].least_violation(prob, pol.PHASE1_REG, {})
        slacked = backends.SOLVERS["daqp"](pol._slacked(prob), None, None, {})
        assert soft.ok and slacked.ok and soft.x.shape == (prob.n,)
        np.testing.assert_allclose(soft.x, slacked.x[:prob.n], atol=1e-8)
        viol = np.maximum(prob.C @ soft.x - prob.u, 0.0)
        np.testing.assert_allclose(viol, [0.0, 0.0, 0.5, 0.5] + [1.0] * (2 * n - 4), atol=1e-7)
    asked = _spy(monkeypatch)
    monkeypatch.setitem(backends.SOLVERS, "daqp", dataclasses.replace(backends.SOLVERS["daqp"], solve=lambda *a: (
        backends.RawAnswer(None, None, False, 0, "daqp: not asked for phase 1", infeasible=True))))
    sol = pol.solve_qp(_contradiction(3), "proxsuite")
    assert sol.status == "relaxed" and sol.slack == pytest.approx(1.0, abs=1e-6)
    assert asked == ["daqp"]  # (its soft rows: neither its QP with slack variables nor ldp)


@pytest.mark.skipif(not HAS_DAQP, reason="needs daqp")
def test_daqps_answers_are_taken_only_verified_and_its_proofs_end_the_route(monkeypatch):
    ok, bad = _contradiction(3, upper=2.0), _contradiction(3)
    sol = pol.solve_qp(ok, "proxsuite")
    assert sol.status == "solved" and sol.message.startswith("daqp exitflag 1 (KKT verified)")
    with monkeypatch.context() as mp:  # an answer the warm active set does not verify is not taken
        mp.setattr(pol, "solve_active_set", lambda *a, **k: None)
        sol = pol.solve_qp(ok, "proxsuite")
        assert sol.message.startswith("daqp exitflag 1, KKT check failed, then ldp")
    asked = _spy(monkeypatch)
    sol = pol.solve_qp(bad, "proxsuite")
    assert sol.status == "relaxed" and "daqp exitflag -1; phase 1" in sol.message
    assert asked[0] == "daqp" and "ldp" not in asked[:2]  # the proof ended the route: phase 1 next


def test_the_loosened_problem_gets_one_exact_attempt_then_the_phase_one_point(monkeypatch):
    """The loosened problem (feasible at the phase-1 point by construction) goes to the route's first solver alone:
    where it fails, the phase-1 point answers, and neither ldp's dense NNLS nor proxsuite is asked."""
    first = "daqp" if HAS_DAQP else "ldp"
    real = backends.SOLVERS[first]

    qp_calls = []

    def fails_when_loosened(prob, x0, z0, opts):  # (the QP's size, asked a second time: the loosened problem)
        qp_calls.append(prob.n == 6)
        if sum(qp_calls) == 2 and qp_calls[-1]:
            return backends.RawAnswer(None, None, False, 3, f"{first}: failed")
        return real.solve(prob, x0, z0, opts)

    monkeypatch.setitem(backends.SOLVERS, first, backends.Backend(
        fails_when_loosened, real.module, real.exact, real.verified, real.deterministic, real.may_stall,
        real.route_options))
    asked = _spy(monkeypatch)
    sol = pol.solve_qp(_contradiction(3), "proxsuite")
    assert sol.status == "relaxed" and sol.slack == pytest.approx(1.0, abs=1e-6)
    assert sol.message.endswith("the loosened problem failed, the phase-1 point returned")
    assert asked[-1] == first and "proxsuite" not in asked and (first == "ldp" or "ldp" not in asked)
    np.testing.assert_allclose(sol.x.reshape(3, 2)[:, 0], 0.0, atol=1e-5)  # (each row violated by 1 at most)
    assert np.all(np.isfinite(sol.x)) and np.all(sol.z == 0.0)
    monkeypatch.setattr(pol, "EXACT_ROUTE", ())
    asked.clear()
    pol.solve_qp(_contradiction(3), "proxsuite")
    assert asked.count("proxsuite") == 2  # (the QP and the loosened QP: proxsuite is the whole route)


@pytest.mark.skipif(not HAS_DAQP, reason="needs daqp")
def test_daqp_warm_started_from_the_working_set_answers_as_cold(monkeypatch):
    """With ``warm_start`` DAQP starts from the warm working set (bounds first: the upper ones +1, the lower ones -1,
    then the rows whose multiplier was positive) and reaches the cold start's optimum; without it, no start."""
    import daqp

    prob = _contradiction(3, upper=2.0)
    starts = []
    real = daqp.solve
    monkeypatch.setattr(daqp, "solve", lambda *a, **k: starts.append(k.get("dual_start")) or real(*a, **k))
    x0 = np.array([3.0, 0.0, -3.0, 0.0, 0.5, 0.25])  # robot 0 at its upper bound in x, robot 1 at its lower one
    z0 = np.array([0.0, 2.0, 1e-12, 0.0, 0.0, 0.5])  # (1e-12: a solver's rest on a slack row, below the cut)
    opts = dict(backends.SOLVERS["daqp"].route_options)
    assert opts["warm_start"]  # (the route asks for it)
    cold = backends.SOLVERS["daqp"](prob, x0, z0, {**opts, "warm_start": False})
    warm = backends.SOLVERS["daqp"](prob, x0, z0, opts)
    assert starts[0] is None
    np.testing.assert_array_equal(starts[1], [1, 0, -1, 0, 0, 0, 0, 1, 0, 0, 0, 1])
    assert cold.ok and warm.ok
    np.testing.assert_allclose(warm.x, cold.x, atol=1e-12)
    np.testing.assert_allclose(warm.x.reshape(3, 2), np.tile([1.0, 0.25], (3, 1)), atol=1e-12)


@pytest.mark.skipif(not HAS_DAQP, reason="needs daqp")
def test_daqp_as_configured_keeps_the_box_as_rows(monkeypatch):
    """``solver="daqp"`` (aasoatt reproduce's) passes the box as rows; on the route, as DAQP's simple bounds."""
    import daqp

    prob = _contradiction(3, upper=2.0)
    rows = []
    real = daqp.solve
    monkeypatch.setattr(daqp, "solve", lambda H, f, A, *a, **k: rows.append(A.shape[0]) or real(H, f, A, *a, **k))
    plain = backends.SOLVERS["daqp"](prob, None, None, {})
    routed = backends.SOLVERS["daqp"](prob, None, None, dict(backends.SOLVERS["daqp"].route_options))
    assert rows == [prob.n + prob.m, prob.m]
    np.testing.assert_allclose(routed.x, plain.x, atol=1e-12)


def test_proofs_of_infeasibility_on_a_packed_team_skip_proxsuite(monkeypatch):
    """An infeasible team (a packed ring with tiny bounds) is proved so by the exact route and relaxed."""
    asked = _spy(monkeypatch)
    n = 6
    team = make_team("paper", n)
    ang = 2 * np.pi * np.arange(n) / n
    pose = pose_from_point(team, 0.6 * np.stack((np.cos(ang), np.sin(ang)), axis=1), ang + np.pi)
    u = np.full((n, 2), 8.0)
    lo, hi = -np.full((n, 2), 0.1), np.full((n, 2), 0.1)
    du, res = SafetyFilter(team, deadlock="none", backup=False).step(kinematics(team, pose, u), u, ang + np.pi,
                                                                      np.zeros((n, 2)), lo, hi)
    assert res.slack > 0 and "phase 1" in res.message and "proxsuite" not in asked


def test_the_policy_keeps_no_state_between_calls():
    """The same problem twice gives the same bits, whatever was solved in between."""
    ok, bad = _contradiction(4, upper=2.0), _contradiction(4)
    policy = pol.SolverPolicy("proxsuite")
    first = policy.solve(ok, None, None)
    policy.solve(bad, None, None)
    again = policy.solve(ok, None, None)
    assert first.x.tobytes() == again.x.tobytes() and first.message == again.message


def test_a_closed_loop_never_reads_the_clock(monkeypatch):
    """A clock that jumps a minute at every reading (a very slow machine) changes no decision of the filter."""
    import time

    scen = circle_layout(10, radius=6.0, duration=12.0)
    normal = closed_loop(scen, SafetyFilter(scen.team), 8.0)
    ticks = iter(range(10**9))
    monkeypatch.setattr(time, "perf_counter", lambda: 60.0 * next(ticks))
    slow = closed_loop(scen, SafetyFilter(scen.team), 8.0)
    assert slow.min_distance < 1.0  # (the robots met: the QP had rows to solve)
    assert slow.p.tobytes() == normal.p.tobytes()


def test_training_stacks_behind_the_filter_on_a_slow_machine(monkeypatch):
    """The grouped filter of a training stack (32 teams) steps on a clock where every solve looks slow."""
    import time

    from aasoatt_env import make_batched_env

    def run() -> np.ndarray:
        env = make_batched_env(32, "random_goals", num_robots=6, decision_interval=20, action_mode="point",
                               filter=True)
        env.reset(seed=3)
        rng = np.random.default_rng(3)
        for _ in range(6):
            env.step(rng.uniform(-1, 1, (32, 6, 2)))
        env.sync()
        return np.concatenate([e.unwrapped.positions for e in env.envs])

    normal = run()
    ticks = iter(range(10**9))
    monkeypatch.setattr(time, "perf_counter", lambda: 60.0 * next(ticks))
    assert run().tobytes() == normal.tobytes()


@pytest.mark.parametrize("upper", [None, 2.0])  # inconsistent rows; consistent ones
def test_after_a_relaxed_step_phase_one_goes_first_with_the_same_answer(monkeypatch, upper):
    """``relaxed=True`` (the previous step's rows were inconsistent): phase 1 before the route, which is asked only
    where phase 1 finds the rows consistent; the answer is bit for bit the route-first one."""
    prob = _contradiction(3) if upper is None else _contradiction(3, upper=upper)
    policy = pol.SolverPolicy("proxsuite", active_set=False)
    asked = _spy(monkeypatch)
    first = policy.solve(prob, None, None)
    route_first = list(asked)
    asked.clear()
    again = policy.solve(prob, None, None, relaxed=True)
    assert (again.status, again.slack) == (first.status, first.slack)
    np.testing.assert_array_equal(again.x, first.x)
    np.testing.assert_array_equal(again.z, first.z)
    if upper is None:
        assert first.status == "relaxed" and len(asked) == len(route_first) - 1  # (no proof of infeasibility)
        assert again.message.startswith("phase 1 first (the previous step was relaxed); phase 1: largest row")
    else:
        assert first.status == "solved" and len(asked) == len(route_first) + 1  # (phase 1, then the route)
        assert again.message == first.message


@pytest.mark.skipif(not HAS_DAQP, reason="needs daqp")
def test_a_starved_solver_keeps_its_iteration_limit_and_the_team_stays_apart(monkeypatch):
    """Every back-end call is bounded by its iteration count (``ITER_LIMIT``), never by the clock: DAQP starved to
    5 iterations reports at most 5 on every call of a packed 12-robot team driven at nominals of 1e6 (infeasible
    steps included), the route goes on to the next solver, and no two robots ever touch."""
    from aasoatt_env import make_env
    from agents import ADVERSARIES

    monkeypatch.setitem(backends.ITER_LIMIT, "daqp", 5)
    calls = []
    real = backends.SOLVERS["daqp"]
    monkeypatch.setitem(backends.SOLVERS, "daqp", dataclasses.replace(
        real, solve=lambda *a: (lambda r: calls.append(r.iterations) or r)(real.solve(*a))))
    env = make_env("random_goals", num_robots=12, filter=True, max_steps=10**9)
    obs, _ = env.reset(seed=5158)
    agent = ADVERSARIES["spin_up"]()
    agent.reset(env)
    base, statuses, gap = env.unwrapped, set(), np.inf
    radius = base.team.radius
    for _ in range(200):
        obs, *_ = env.step({a: v * np.float32(1e6) for a, v in agent.act(obs, env).items()})
        statuses.add(base.filter_outputs[-1].status)
        d = np.linalg.norm(base.positions[:, None] - base.positions[None], axis=2) - radius[:, None] - radius[None]
        gap = min(gap, float(d[np.triu_indices(12, 1)].min()))
    assert "relaxed" in statuses and len(calls) > 100
    assert max(calls) == 5 and min(calls) >= 0  # (at its limit on many calls: the count is DAQP's own)
    assert gap > 0.0
