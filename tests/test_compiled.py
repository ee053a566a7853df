"""The compiled kernels (backup layer, decentralised local solver) against the numpy reference, and their selection.

The kernels (:mod:`aasoatt_env.compiled`) must make the numpy code's
decisions on every state: which robots brake, which pairs are broken, the share
each robot takes, the rounds and the pairs checked; the inputs and margins may
differ by floating-point rounding only.  The local solver's kernel against its
reference and a dense solver: ``tests/test_decentralized.py``.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import needs_numba

from aasoatt_env import FilterConfig, compiled, make_env
from aasoatt_env.analysis.metrics import pairwise_min_distance
from aasoatt_env.analysis.recording import run_episode
from aasoatt_env.api.factory import make_batched_env
from aasoatt_env.errors import ConfigError
from aasoatt_env.model.dynamics import DT, input_bounds, integrate, kinematics
from aasoatt_env.model.geometry import robot_pairs
from aasoatt_env.model.params import RobotParams, Team, make_team, stack_teams
from aasoatt_env.safety import SafetyFilter, warm_up
from aasoatt_env.safety.backup.gate import gatekeeper, repair
from aasoatt_env.safety.backup.paths import point as _point
from aasoatt_env.safety.problem import build_problem
from aasoatt_env.safety.solvers import active_set, policy
from aasoatt_env.safety.solvers.local import solve_local_qps
from agents import ADVERSARIES, HostileAgent, TrackingController

F = 2.0 / 3.0
D = 3.0


def _teams() -> dict:
    mixed = ["paper", "turtlebot3_burger", "paper", RobotParams(radius=0.3, offset=0.1)] * 3
    return {
        "paper": make_team("paper", 12),
        "mixed": make_team(mixed, 12),
        "double_integrator": make_team("double_integrator", 12),
        "grouped": stack_teams([make_team("paper", 6), make_team("paper", 6)]),
    }


def _state(team, rng, side: float):
    """A crowded random state: speeds up to spinning, candidates anywhere in the box (some at its corners)."""
    pose = np.column_stack((rng.uniform(0, side, (team.n, 2)), rng.uniform(-np.pi, np.pi, team.n)))
    u = rng.normal(0, 8.0 if team.is_diff_drive else 1.5, (team.n, 2))
    u[0] = [12.0, -12.0] if team.is_diff_drive else [0.0, 0.0]
    u[1] = [1e-7, 2e-7]
    lo, hi = input_bounds(team, u, DT)
    cand = rng.uniform(lo, hi)
    cand[:3] = np.where(rng.random((3, 2)) < 0.5, lo[:3], hi[:3])
    return pose, u, cand, lo, hi


def _obstacles(team, rng, side: float, grouped: bool):
    c = rng.uniform(0, side, (3, 2))
    r = rng.uniform(0.1, 0.5, 3)
    return (c, r, np.array([0, 1, 0])) if grouped else (c, r)


def _assert_same_decisions(g0, g1) -> None:
    for name in ("braking", "broken", "share", "out_of_range"):
        np.testing.assert_array_equal(getattr(g1, name), getattr(g0, name), err_msg=name)
    assert (g1.safe, g1.rounds, g1.n_pairs) == (g0.safe, g0.rounds, g0.n_pairs)
    np.testing.assert_allclose(g1.du, g0.du, rtol=0, atol=1e-11)
    finite = np.isfinite(g0.robot_margin)
    np.testing.assert_array_equal(np.isfinite(g1.robot_margin), finite)
    np.testing.assert_allclose(g1.robot_margin[finite], g0.robot_margin[finite], rtol=0, atol=1e-11)
    assert g1.margin == pytest.approx(g0.margin, abs=1e-11)


@needs_numba
@pytest.mark.parametrize("kind", ["paper", "mixed", "double_integrator", "grouped"])
def test_the_compiled_gatekeeper_makes_the_numpy_gatekeepers_decisions(kind):
    """Random crowded states, every option of the check: the same decisions, inputs and margins to 1e-9."""
    team = _teams()[kind]
    rng = np.random.default_rng(20261201)
    checked = braked = 0
    for trial in range(40):
        side = rng.uniform(2.0, 5.0)
        pose, u, cand, _, _ = _state(team, rng, side)
        obstacles = _obstacles(team, rng, side, kind == "grouped") if trial % 2 else None
        p0 = _point(team, pose)
        near = (None, robot_pairs(np.stack((p0.real, p0.imag), axis=1), D, groups=team.group),
                np.argwhere(np.triu(np.ones((team.n, team.n), dtype=bool), 1)))[trial % 3]  # a superset: all pairs
        kw = dict(sensing_range=D, brake_fraction=F, obstacles=obstacles, tol=1e-9, near_pairs=near,
                  quick=bool(trial % 4 == 1), hold_violations=bool(trial % 5 == 2),
                  blend_levels=((0.5,), (), (0.75, 0.25))[trial % 3])
        g0 = gatekeeper(team, pose, u, cand, DT, **kw)
        g1 = gatekeeper(team, pose, u, cand, DT, compiled=True, **kw)
        _assert_same_decisions(g0, g1)
        checked += g0.n_pairs
        braked += int(g0.braking.sum())
    assert checked > 100 and braked > 20  # the states were crowded enough to test the rounds



@needs_numba
def test_the_gatekeepers_braking_samples_by_recurrence_match_the_sines_and_cosines():
    """The gate's rows rotate by recurrence (``fast``): the same deviations, samples within 1e-12 of the path length.

    Short and long brakes (1 to 5,000 steps, several resynchronisations), turns from none
    (omega 0 and 1e-12) to spinning, both row starts, point masses (bulge) too.
    """
    from aasoatt_env.safety.backup import kernels as k

    rng = np.random.default_rng(11)
    worst = 0.0
    for trial in range(300):
        steps = int(rng.choice([1, 2, 3, 15, 16, 17, 40, 333, 5000]))
        ratio = steps - rng.uniform(0.0, 0.999)
        rate = 1.0 / max(ratio, 1.0)
        omega = float(rng.choice([0.0, 1e-12, -3e-4, rng.normal(0, 3.0), rng.normal(0, 60.0)]))
        pdot = complex(*rng.normal(0, 2.0, 2))
        p_start = complex(*rng.uniform(-50, 50, 2))
        start, bulge, has_bulge = int(trial % 2), float(rng.uniform(0, 1e-4)), bool(trial % 3 == 0)
        length = steps + 1 + start + int(rng.integers(0, 3))  # past the rest too
        rows = []
        for fast in (False, True):
            p, d = np.full(length, np.nan, dtype=complex), np.full(length - 1, np.nan)
            k.fill_brake(p, d, start, p_start, pdot, omega, rate, bulge, has_bulge, DT, length, fast)
            rows.append((p, d))
        (p0, d0), (p1, d1) = rows
        np.testing.assert_array_equal(d1[start:], d0[start:])
        path = abs(pdot) * DT * steps
        err = float(np.max(np.abs(p1[start:] - p0[start:])))
        assert err <= 1e-12 * (1.0 + path), (trial, steps, omega, err)
        worst = max(worst, err / (1.0 + path))
    assert worst > 0.0  # the recurrence ran (it is not the same arithmetic)


def _spread_state(team, rng):
    """A state without overlaps (a jittered grid, obstacles between the robots): the repair's domain.

    (Where a robot already overlaps, the margin's finite-difference gradient at the first step is
    ~1e-6 and the least-norm lift divides by its square, so rounding is amplified a million-fold.)
    """
    pose, u, cand, lo, hi = _state(team, rng, 1.0)
    spacing = 2.0 * float(team.radius.max()) + rng.uniform(0.02, 0.3)
    grid = np.stack(np.meshgrid(np.arange(4), np.arange(3)), -1).reshape(-1, 2)[: team.n] * spacing
    pose[:, :2] = grid + rng.uniform(-0.01, 0.01, grid.shape) - _point(team, pose[:, :3] * [0, 0, 1]).view(
        np.float64).reshape(-1, 2)  # control points on the grid
    c = grid[:3] + 0.5 * spacing
    r = np.full(3, 0.5 * spacing * np.sqrt(2.0) - float(team.radius.max()) - 0.01)
    obstacles = (c, r, np.array([0, 1, 0])) if team.group is not None else (c, r)
    return pose, u, cand, lo, hi, obstacles


@needs_numba
@pytest.mark.parametrize("kind", ["paper", "mixed", "double_integrator", "grouped"])
def test_the_compiled_repair_gives_the_numpy_repairs_answer(kind):
    team = _teams()[kind]
    rng = np.random.default_rng(7)
    moved = 0
    for trial in range(30):
        pose, u, cand, lo, hi, obstacles = _spread_state(team, rng)
        kw = dict(sensing_range=D, brake_fraction=F, obstacles=obstacles if trial % 2 else None)
        r0 = repair(team, pose, u, cand, DT, lo, hi, **kw)
        r1 = repair(team, pose, u, cand, DT, lo, hi, compiled=True, **kw)
        np.testing.assert_allclose(r1, r0, rtol=0, atol=1e-6)
        moved += int((r0 != np.clip(cand, lo, hi)).any(axis=1).sum())
    assert moved > 10  # the repair acted


class _BothKernels:
    """A control filter that runs the numpy and the compiled filter on every physics step and applies numpy's."""

    keeps_input_bounds = True

    def __init__(self, **options) -> None:
        self.f = {k: SafetyFilter(kernel=k, **options) for k in ("numpy", "numba")}
        self.steps = self.acted = self.relaxed = self.grouped = 0

    def reset(self, team) -> None:
        for f in self.f.values():
            f.reset(team)

    def __call__(self, inp, du_nominal):
        out = {k: f(inp, du_nominal) for k, f in self.f.items()}
        np.testing.assert_array_equal(out["numba"].backup, out["numpy"].backup)
        np.testing.assert_allclose(out["numba"].du, out["numpy"].du, rtol=0, atol=1e-5)  # (the repair's)
        assert out["numba"].status == out["numpy"].status
        self.steps += 1
        self.acted += out["numpy"].status == "backup"  # the layer braked or repaired someone
        self.relaxed += "infeasible (relaxed)" in out["numpy"].message  # a robot's own QP was relaxed
        self.grouped += "negotiation group" in out["numpy"].message
        return out["numpy"]


@needs_numba
@pytest.mark.parametrize(("mode", "negotiate"), [("centralized", True), ("decentralized", False),
                                                 ("decentralized", True)])
def test_filters_with_either_kernel_give_the_same_steps_along_a_hostile_episode(mode, negotiate):
    """Full-throttle bursts: at every physics step the same braking robots and status, inputs to rounding
    (decentralised: the robots' own QPs, relaxed ones included, by the local solver's kernel too; with the
    negotiation groups, theirs by the centralised parts)."""
    env = make_env("random_goals", num_robots=12, max_steps=300)
    both = _BothKernels(mode=mode, negotiate=negotiate)
    env.set_control_filter(both)
    agent = ADVERSARIES["burst"](rest_steps=20)
    obs, _ = env.reset(seed=3)
    for _ in range(300):
        obs, *_ = env.step(agent.act(obs, env))
    assert both.steps == 300 * env.decision_interval and both.acted > 20
    if mode == "decentralized":
        assert both.relaxed > 20 if not negotiate else both.grouped > 20


class _BothActiveSets:
    """Runs the compiled warm active set beside the numpy one on every problem the filter gives it.

    Tallies, from the filter's warm start and from a cold one (an empty working set, where parts often need
    dependent working sets), the parts each verifies and the worst difference where both do.
    """

    def __init__(self, monkeypatch) -> None:
        self.parts = {"warm": [0, 0, 0, 0], "cold": [0, 0, 0, 0]}  # parts, numpy verified, compiled verified, differ
        self.problems = 0
        self.worst = 0.0
        ref = policy.solve_active_set_parts

        def both(prob, x0, z0, groups, max_iter=6, compiled=False, one_change_iter=active_set.ONE_CHANGE_ITER):
            kw = {"one_change_iter": one_change_iter}
            out = ref(prob, x0, z0, groups, max_iter, **kw)
            self.check("warm", out, ref(prob, x0, z0, groups, max_iter, compiled=True, **kw), groups)
            cold = (np.zeros_like(x0), np.zeros_like(z0), groups, max_iter)
            self.check("cold", ref(prob, *cold, **kw), ref(prob, *cold, compiled=True, **kw), groups)
            self.problems += 1
            return out

        monkeypatch.setattr(policy, "solve_active_set_parts", both)
        monkeypatch.setattr(active_set, "solve_active_set_parts", both)  # solve_active_set's

    def check(self, start, out, com, groups) -> None:
        assert (out is None) == (com is None)
        if out is None:
            return
        np.testing.assert_array_equal(com.row_group, out.row_group)
        tally = self.parts[start]
        tally[0] += out.ok.shape[0]
        tally[1] += int(out.ok.sum())
        tally[2] += int(com.ok.sum())
        tally[3] += int((out.ok != com.ok).sum())
        ok = out.ok & com.ok
        v = np.repeat(ok[np.zeros(out.x.shape[0] // 2, int) if groups is None else groups], 2)
        rows = ok[out.row_group]
        np.testing.assert_array_equal(com.z[rows] > 1e-9, out.z[rows] > 1e-9)  # the same active rows
        self.worst = max(self.worst, float(np.abs(com.x[v] - out.x[v]).max(initial=0.0)),
                         float(np.abs(com.z[rows] - out.z[rows]).max(initial=0.0)))


@needs_numba
def test_the_compiled_active_set_verifies_the_numpy_ones_parts(monkeypatch):
    """Along closed loops (a small circle swap's crossing, one team; a stack of teams under random actions, one
    part each): where both verify a part, the same active rows and points to rounding; from the filter's warm
    starts the same parts verified.  From cold starts the two may verify different parts: a dependent working set
    makes the regularised Schur solve ill-conditioned (multipliers ~1e9), where the last bits of BLAS and of the
    kernel's sums decide the next working set (the unverified part goes to the general solver, whose answer is
    the same optimum)."""
    both = _BothActiveSets(monkeypatch)
    env = make_env("circle_swap", num_robots=12, radius=2.0, duration=4.0, settle_time=0.0,
                   filter={"kernel": "numpy"}, max_steps=500)
    for agent in (TrackingController(), ADVERSARIES["burst"](rest_steps=10)):
        obs, _ = env.reset(seed=4)
        for _ in range(500):
            obs, *_ = env.step(agent.act(obs, env))
    batch = make_batched_env(8, "random_goals", num_robots=6, filter={"kernel": "numpy"})
    batch.reset(seed=5)
    rng = np.random.default_rng(5)
    for _ in range(400):
        batch.step(rng.uniform(-1.0, 1.0, (8, 6, 2)))
    warm, cold = both.parts["warm"], both.parts["cold"]
    assert both.problems > 900 and warm[0] > 2 * both.problems
    assert warm[1] > 0.9 * warm[0] and warm[3] == 0
    # cold starts: some parts unverified in the budget; the two rarely differ, and not one-sidedly
    assert cold[1] < cold[0] and cold[3] <= 0.05 * cold[0] and cold[2] >= cold[1] - 0.01 * cold[0]
    assert both.worst <= 1e-8


def test_the_primal_dual_rule_leaves_an_inconsistent_working_set(monkeypatch):
    """Warm-started with two parallel rows ``x <= 0`` and ``x <= 1`` (a dependent, inconsistent set): the primal-dual
    rule is not applied to its point; the one-change rule starts from that point without solving it again, drops
    the slack row and verifies: two equality solves in all."""
    prob = build_problem(np.eye(2)[None], np.array([[2.0, 0.0]]), -3 * np.ones((1, 2)), 3 * np.ones((1, 2)),
                         np.ones(1), np.array([0, 0]), np.array([-1, -1]), np.array([[1.0, 0.0], [1.0, 0.0]]),
                         np.zeros((2, 2)), np.array([0.0, 1.0]))
    last, applied = {}, []
    eq, pdas = active_set._equality_point, active_set._pdas_rule

    def spy_eq(*args):
        out = last["point"] = eq(*args)
        last["W"] = args[-1].copy()
        return out

    def spy_pdas(W, lam, r, *rest):
        applied.append(bool(np.all(np.abs(r[W]) <= active_set.TOL)))  # was the point's working set consistent?
        return pdas(W, lam, r, *rest)

    monkeypatch.setattr(active_set, "_equality_point", spy_eq)
    monkeypatch.setattr(active_set, "_pdas_rule", spy_pdas)
    out = active_set.solve_active_set_parts(prob, np.zeros(2), np.array([1.0, 1.0]), None)
    assert out.ok.all() and out.iterations == 2 and np.allclose(out.x, [0.0, 0.0])
    assert all(applied)  # never applied to an inconsistent set
    assert last["W"].tolist()[:2] == [True, False]  # verified with x <= 0 alone
    if compiled.available():
        com = active_set.solve_active_set_parts(prob, np.zeros(2), np.array([1.0, 1.0]), None, compiled=True)
        assert com.ok.all() and com.iterations == 2 and np.allclose(com.x, out.x)


@pytest.mark.parametrize("use_kernel", [False, pytest.param(True, marks=needs_numba)])
def test_the_one_change_budget_bounds_the_rows_the_warm_active_set_adds(use_kernel, monkeypatch):
    """Eight robots, each pushed against its own row, warm-started with none of them (and no primal-dual
    iteration): the one-change rule adds one row per iteration, so it verifies the optimum in nine equality solves
    and gives up with eight or fewer; ``SolverPolicy`` hands its budget (the negotiation groups' larger one,
    :data:`~aasoatt_env.safety.decentralized.GROUP_ONE_CHANGE_ITER`) to every warm active set it runs."""
    from aasoatt_env.safety.decentralized import GROUP_ONE_CHANGE_ITER

    n = 8
    A = np.tile(np.eye(2), (n, 1, 1))
    idx = np.arange(n)
    prob = build_problem(A, np.tile([2.0, 0.0], (n, 1)), -3 * np.ones((n, 2)), 3 * np.ones((n, 2)), np.ones(n), idx,
                         -np.ones(n, int), np.tile([1.0, 0.0], (n, 1)), np.zeros((n, 2)), np.ones(n))
    x0, z0 = np.tile([2.0, 0.0], n), np.zeros(n)  # the unconstrained optimum, no row active
    for budget, verified in ((8, False), (9, True), (GROUP_ONE_CHANGE_ITER, True)):
        out = active_set.solve_active_set(prob, x0, z0, max_iter=0, compiled=use_kernel, one_change_iter=budget)
        assert (out is not None) == verified, budget
        if verified:
            assert out[2] == n + 1 and np.allclose(out[0].reshape(n, 2), [[1.0, 0.0]] * n)
    seen = []
    real_one, real_parts = policy.solve_active_set, policy.solve_active_set_parts
    monkeypatch.setattr(policy, "solve_active_set",
                        lambda *a, **k: seen.append(k["one_change_iter"]) or real_one(*a, **k))
    monkeypatch.setattr(policy, "solve_active_set_parts",
                        lambda *a, **k: seen.append(k["one_change_iter"]) or real_parts(*a, **k))
    pol = policy.SolverPolicy("proxsuite", active_set=True, compiled=use_kernel, one_change_iter=GROUP_ONE_CHANGE_ITER)
    sol = pol.solve(prob, x0, z0)
    sol2 = pol.solve(prob, x0, z0, groups=idx)
    assert sol.status == sol2.status == "solved" and np.allclose(sol2.x.reshape(n, 2), [[1.0, 0.0]] * n)
    assert seen == [GROUP_ONE_CHANGE_ITER, GROUP_ONE_CHANGE_ITER]


@pytest.mark.parametrize("use_kernel", [False, pytest.param(True, marks=needs_numba)])
def test_the_active_set_refuses_groups_that_are_not_labels(use_kernel):
    """Negative labels (the kernel would index by them) or a wrong length: not a labelling, so None."""
    A = np.tile(np.eye(2), (3, 1, 1))
    target = np.array([[1.0, 0.0], [-1.0, 0.0], [0.5, 0.5]])
    prob = build_problem(A, target, -np.ones((3, 2)), np.ones((3, 2)), np.ones(3), np.array([0]), np.array([1]),
                         np.array([[1.0, 0.0]]), np.array([[-1.0, 0.0]]), np.array([0.1]))
    for groups in ([-1, -1, 0], [0, 0, -1], [-1, -1], [0, 0, 1, 1]):
        assert active_set.solve_active_set_parts(prob, np.zeros(6), np.ones(1), np.array(groups),
                                                 compiled=use_kernel) is None
    ok = active_set.solve_active_set_parts(prob, np.zeros(6), np.ones(1), np.array([0, 0, 1]), compiled=use_kernel)
    assert ok.ok.all() and np.allclose(ok.x.reshape(3, 2)[2], [0.5, 0.5])


def _run_stack(seed: int) -> None:
    """600 physics steps of a training stack: 8 teams of 6 behind the filter, the training recipe's point actions
    held for 20 physics steps, a fresh policy's (Gaussian, std 0.37, clipped): with seed 0 some teams' QPs are
    infeasible on 13 steps, the others verified."""
    batch = make_batched_env(8, "random_goals", num_robots=6, filter=True, decision_interval=20, action_mode="point")
    batch.reset(seed=seed)
    rng = np.random.default_rng(seed)
    for _ in range(30):
        batch.step(rng.normal(0.0, 0.37, (8, 6, 2)).clip(-1.0, 1.0))


def _central_answers(monkeypatch, compiled_stage: bool, scene: str) -> tuple[list, int]:
    """Every centralised QP stage's answer along a closed loop, with the compiled stage tried or not (the numpy
    stage, with the compiled active set), and how many QP steps the compiled stage answered."""
    from aasoatt_env.safety import centralized, core

    answers, by_kernel = [], [0]
    call, post = centralized.Centralized.__call__, centralized.Centralized.__post_init__
    k = compiled.kernels("centralized")
    real = k.solve_decomposed

    def counted(*args):
        out = real(*args)
        by_kernel[0] += out[0] == k.VERIFIED
        return out

    def record(self, *args):
        out = call(self, *args)
        answers.append(out)
        return out

    def set_up(self):
        post(self)
        if not compiled_stage:
            object.__setattr__(self, "settings", None)

    monkeypatch.setattr(k, "solve_decomposed", counted)
    monkeypatch.setattr(core, "fusable", lambda *args: False)  # (the centralised stage itself, every step)
    monkeypatch.setattr(centralized.Centralized, "__call__", record)
    monkeypatch.setattr(centralized.Centralized, "__post_init__", set_up)
    if scene == "stack":
        _run_stack(0)
    else:  # a small circle swap's crossing under the tracking law; circles among obstacles under bursts
        env = (make_env("circle_swap", num_robots=12, radius=2.0, duration=4.0, settle_time=0.0, max_steps=400,
                        filter=True)
               if scene == "crossing" else make_env("circle_obstacles", num_robots=10, max_steps=600, filter=True))
        agent = TrackingController() if scene == "crossing" else ADVERSARIES["burst"](rest_steps=10)
        obs, _ = env.reset(seed=12)
        for _ in range(env.max_steps):
            obs, *_ = env.step(agent.act(obs, env))
    monkeypatch.undo()
    return answers, by_kernel[0]


def _bits(a: np.ndarray) -> np.ndarray:
    """The float64 array's bit patterns (``-0.0`` and ``0.0`` differ, NaN equals only the same NaN)."""
    return np.ascontiguousarray(a, dtype=np.float64).view(np.int64)


@needs_numba
@pytest.mark.parametrize("scene", ["stack", "crossing", "obstacles"])
def test_the_compiled_centralised_stage_answers_as_the_numpy_stage(monkeypatch, scene):
    """Along closed loops every step's answer with the compiled centralised stage equals the numpy stage's (with
    the compiled active set) bit for bit: wheel accelerations, scaled points, multipliers, avoidance, status,
    message, iterations; the compiled stage answers most QP steps, the numpy stage the others (the training
    stack's infeasible teams)."""
    ref, ref_kernel = _central_answers(monkeypatch, False, scene)
    out, by_kernel = _central_answers(monkeypatch, True, scene)
    assert ref_kernel == 0 and len(out) == len(ref) >= 300
    for a, b in zip(out, ref):
        for field in ("du", "x", "z", "eta"):
            np.testing.assert_array_equal(_bits(getattr(a, field)), _bits(getattr(b, field)))
        np.testing.assert_array_equal(a.avoiding, b.avoiding)
        assert (a.status, a.message, a.iterations, a.n_qp, a.slack) == (b.status, b.message, b.iterations, b.n_qp,
                                                                        b.slack)
    qp_steps = sum(a.n_qp > 0 for a in out)
    assert qp_steps > 50 and by_kernel > 0.8 * qp_steps
    assert scene != "stack" or by_kernel < qp_steps  # (some steps the numpy stage answered)


@needs_numba
@pytest.mark.parametrize("margin", [None, 0.01])
def test_the_rows_kernel_gives_the_numpy_rows_bit_for_bit(margin):
    """The compiled pairs and rows against the numpy stage on random robots, coincident ones (``r`` clamped at
    1e-9), singular input matrices, obstacles and a speed margin: the pairs, rows in wheel coordinates,
    right-hand sides, keys and the smallest barrier value and gap, bit for bit."""
    import dataclasses

    from aasoatt_env.model.dynamics import Kinematics
    from aasoatt_env.safety.inputs import check_step
    from aasoatt_env.safety.rows import CompiledRows, find_pairs, numpy_rows

    cfg = FilterConfig(k1=1.3, k2=2.9, safety_margin=margin, speed_margin=0.07)
    rng = np.random.default_rng(21)
    n = 60
    p = rng.uniform(0.0, 6.0, (n, 2))
    p[5] = p[4]  # coincident robots
    p[7] = p[6] + 1e-12
    v, adot = rng.normal(0.0, 1.0, (n, 2)), rng.normal(0.0, 3.0, (n, 2))
    v[9] = v[8]
    A = rng.normal(0.0, 1.0, (n, 2, 2))
    A[3] = 0.0  # singular
    A[11, :, 1] = 0.0
    team = dataclasses.replace(make_team("paper", n), radius=rng.uniform(0.05, 0.2, n))
    obstacles = (rng.uniform(0.0, 6.0, (4, 2)), rng.uniform(0.1, 0.5, 4))
    zeros = np.zeros((n, 2))
    s = check_step(team, cfg, Kinematics(p, v, A, adot), zeros, np.zeros(n), zeros, -np.ones((n, 2)),
                   np.ones((n, 2)), obstacles=obstacles)
    pairs = find_pairs(team, s.p, cfg.sensing_range, s.obstacles, compiled=False)
    assert pairs.robots.shape[0] > 200 and pairs.obstacles.shape[0] > 10
    np.testing.assert_array_equal(find_pairs(team, s.p, cfg.sensing_range, s.obstacles, compiled=True).robots,
                                  pairs.robots)
    want = numpy_rows(cfg, s, pairs, np.zeros(n, dtype=bool))
    got = CompiledRows(cfg)(cfg, s, pairs, np.zeros(n, dtype=bool))
    for field in ("ri", "rj", "pairs", "keys"):
        np.testing.assert_array_equal(getattr(got, field), getattr(want, field))
    for field in ("Gi", "Gj", "rhs", "barrier_min", "gap_min"):
        np.testing.assert_array_equal(_bits(np.asarray(getattr(got, field))), _bits(np.asarray(getattr(want, field))))


@pytest.mark.parametrize("kernel", ["numpy", pytest.param("numba", marks=needs_numba)])
def test_a_float32_state_is_filtered_as_its_float64_values(kernel):
    """The state arrays are taken as float64 on every path: a float32 state gives the answer of the same values in
    float64 (before, the numpy rows computed in float32 and the compiled ones in float64)."""
    team = make_team("paper", 8)
    rng = np.random.default_rng(5)
    pose = np.column_stack((rng.uniform(0.0, 2.0, (8, 2)), rng.uniform(-np.pi, np.pi, 8))).astype(np.float32)
    u = rng.normal(0.0, 4.0, (8, 2)).astype(np.float32)
    kin32 = type(kinematics(team, pose, u))(*(a.astype(np.float32) for a in kinematics(team, pose, u)))
    kin64 = type(kin32)(*(a.astype(np.float64) for a in kin32))
    lo, hi = input_bounds(team, u.astype(np.float64), DT)
    nominal = rng.normal(0.0, 20.0, (8, 2))
    answers = []
    for kin, uu, th in ((kin64, u.astype(np.float64), pose[:, 2].astype(np.float64)), (kin32, u, pose[:, 2])):
        f = SafetyFilter(team, kernel=kernel, deadlock="none")
        answers.append(f.step(kin, uu, th, nominal, lo, hi)[1])
    assert answers[0].n_rows > 5
    np.testing.assert_array_equal(answers[0].du, answers[1].du)
    assert answers[0].barrier_min == answers[1].barrier_min


def _filter_results(monkeypatch, scene: str, rows_kernel: bool, fused: bool = False,
                    deadlock_kernel: bool = True) -> tuple[list, list]:
    """Every filter step's result and wheel accelerations along a closed loop, with the compiled rows or the numpy
    rows, the fused step or not, the compiled deadlock stage or not, and per step ``(rows kernel called from
    Python, fused step's answer or None)``."""
    from aasoatt_env.safety import core
    from aasoatt_env.safety.rows import numpy_rows

    warm_up()  # (the kernels compiled before the rows kernel is wrapped below: they call the real one)
    results, calls, seen = [], [0], []
    init, step = core.SafetyFilter.__init__, core.SafetyFilter.step
    rows = compiled.kernels("rows")
    real_rows = rows.aasoatt_rows

    def set_up(self, *args, **kw):
        init(self, *args, **kw)
        if not rows_kernel:
            self._rows = numpy_rows
        if not deadlock_kernel:
            assert self._multiplier is not None
            self._multiplier = None
        if not fused:
            self._fused = None
        elif self._fused is not None:
            real = self._fused
            self._fused = lambda *a: seen.append(real(*a)) or seen[-1]

    def record(self, *args, **kw):
        calls[0], seen[:] = 0, []
        du, res = step(self, *args, **kw)
        results.append((du, res))
        steps.append((calls[0], seen[0] if seen else "not tried"))
        return du, res

    def counted(*args):
        calls[0] += 1
        return real_rows(*args)

    steps: list = []
    monkeypatch.setattr(core.SafetyFilter, "__init__", set_up)
    monkeypatch.setattr(core.SafetyFilter, "step", record)
    monkeypatch.setattr(rows, "aasoatt_rows", counted)
    _drive(13 if scene == "stack" else 0, scene)
    monkeypatch.undo()
    return results, steps


def _assert_same_steps(out: list, ref: list) -> None:
    """Every step's ``(du, FilterResult)`` equal bit for bit: inputs, multipliers, margins, flags, status, message."""
    for (du_a, a), (du_b, b) in zip(out, ref):
        np.testing.assert_array_equal(_bits(du_a), _bits(du_b))
        for field in ("eta", "correction", "slack", "margin", "barrier_min"):
            np.testing.assert_array_equal(_bits(np.asarray(getattr(a, field))), _bits(np.asarray(getattr(b, field))))
        for field in ("pairs", "avoiding", "triggered", "backup", "intervened"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
        assert (a.status, a.safe, a.message, a.iterations, a.n_rows, a.n_qp_rows) == (
            b.status, b.safe, b.message, b.iterations, b.n_rows, b.n_qp_rows)


def _drive(stack_seed: int, scene: str) -> None:
    """A closed loop behind the filter: a training stack (``stack_seed``), 20 robots under uniform random actions,
    250 robots under a hostile policy, or a 12-robot circle swap's crossing (``crossing``; ``margins``: with fixed
    and speed margins, without the layer, gains whose product is not a power of two)."""
    if scene in ("stack", "infeasible"):
        _run_stack(0 if scene == "infeasible" else stack_seed)
    elif scene == "random":  # uniform random actions at every physics step: robots spin up past the range limit
        env = make_env("random_goals", num_robots=20, max_steps=700, filter=True)
        rng = np.random.default_rng(5)
        env.reset(seed=5)
        for _ in range(env.max_steps):
            env.step({a: rng.uniform(-1.0, 1.0, 2) for a in env.agents})
    elif scene == "large":  # beyond the brute force's size: the grid of cells' pairs, keys not in order
        env = make_env("random_goals", num_robots=250, max_steps=60, filter=True)
        agent = HostileAgent()
        obs, _ = env.reset(seed=14)
        for _ in range(env.max_steps):
            obs, *_ = env.step(agent.act(obs, env))
    else:
        options = {} if scene == "crossing" else {"safety_margin": 0.01, "speed_margin": 0.05, "backup": False,
                                                  "k1": 1.3, "k2": 2.9}
        env = make_env("circle_swap", num_robots=12, radius=2.0, duration=4.0, settle_time=0.0, max_steps=400,
                       filter=options)
        agent = TrackingController()
        obs, _ = env.reset(seed=12)
        for _ in range(env.max_steps):
            obs, *_ = env.step(agent.act(obs, env))


@needs_numba
@pytest.mark.parametrize("scene", ["stack", "crossing", "margins", "large"])
def test_the_compiled_rows_give_the_numpy_rows_steps_bit_for_bit(monkeypatch, scene):
    """Along closed loops every filter step with the compiled pairs and barrier rows (rows_kernel) equals the numpy
    step bit for bit: wheel accelerations, multipliers, rows, margins, the smallest barrier value, status, message,
    the deadlock and avoidance flags (a training stack and a crossing, whose pairs the brute force's candidates
    give; fixed and speed margins without the backup layer, where the margin is the smallest gap; 250 robots under
    a hostile policy, whose pairs the grid of cells finds)."""
    ref, ref_steps = _filter_results(monkeypatch, scene, rows_kernel=False)
    out, steps = _filter_results(monkeypatch, scene, rows_kernel=True)
    assert all(k == 0 for k, _ in ref_steps) and all(k == 1 for k, _ in steps)
    assert len(out) == len(ref) >= (60 if scene == "large" else 400)
    assert sum(res.n_rows for _, res in out) > 1000
    assert scene == "large" or sum(res.triggered.any() for _, res in out) > 10
    _assert_same_steps(out, ref)


@needs_numba
@pytest.mark.parametrize("scene", ["infeasible", "crossing", "random", "large"])
def test_the_fused_step_gives_the_pipelines_steps_bit_for_bit(monkeypatch, scene):
    """Along closed loops every filter step with the fused step equals the pipeline's bit for bit; the fused step
    answers most steps whole (robots braking for their range limit included), and on some only the rows and the QP
    (the backup stage then runs: robots held or repaired), or nothing (the QP not verified: a training stack's
    infeasible teams)."""
    ref, _ = _filter_results(monkeypatch, scene, rows_kernel=True)
    out, steps = _filter_results(monkeypatch, scene, rows_kernel=True, fused=True)
    assert len(out) == len(ref) >= (60 if scene == "large" else 400)
    _assert_same_steps(out, ref)
    answers = [a for _, a in steps if not isinstance(a, str)]
    tried = [k for k, (_, a) in enumerate(steps) if not isinstance(a, str)]
    answered_before = [out[k - 1][1].message.split(";")[0] in ("closed form: no row binds",
                                                               "active set (warm, KKT verified)")
                       for k in range(1, len(out))]
    assert tried == [k for k, yes in enumerate(answered_before, start=1) if yes]  # (after a step the kernels answered)
    whole = sum(a is not None and a[2] is not None for a in answers)
    rows_and_qp = sum(a is not None and a[2] is None for a in answers)
    if scene != "large":  # (250 robots under a hostile policy: the pipeline answers every step)
        assert whole > len(answers) // 2
    if scene in ("infeasible", "random"):
        assert rows_and_qp > 10
    if scene == "infeasible":  # a training stack: robots braking for their range limit (the quick check answers)
        assert sum(a is not None and a[2] is not None and a[2].braking.any() for a in answers) > 10
    if scene == "infeasible":
        assert sum(a is None for a in answers) > 0


@needs_numba
@pytest.mark.parametrize("scene", ["stack", "crossing", "random"])
def test_the_compiled_deadlock_stage_gives_the_numpy_stages_steps_bit_for_bit(monkeypatch, scene):
    """The ``multiplier`` trigger and ``A du_nom`` compiled (``rows_kernel.multiplier_target``) give the numpy
    stage's steps bit for bit along closed loops where robots are triggered."""
    ref, _ = _filter_results(monkeypatch, scene, rows_kernel=True, deadlock_kernel=False)
    out, _ = _filter_results(monkeypatch, scene, rows_kernel=True)
    assert len(out) == len(ref) >= 400 and sum(res.triggered.sum() for _, res in out) > 100
    _assert_same_steps(out, ref)


@needs_numba
def test_the_compiled_deadlock_stage_without_a_reference_keeps_the_avoiding_robots_triggered():
    """Without a reference no robot is done: the compiled trigger flags exactly the robots that were avoiding, as
    the numpy trigger does, along a crowded team's steps."""
    team = make_team("paper", 12)
    rng = np.random.default_rng(4)
    pose = np.column_stack((rng.uniform(0.0, 2.5, (12, 2)), rng.uniform(-np.pi, np.pi, 12)))
    u = rng.normal(0.0, 4.0, (12, 2))
    filters = [SafetyFilter(team, deadlock="rotate_nominal") for _ in range(2)]
    filters[1]._multiplier = None
    triggered = 0
    for _ in range(30):
        nominal = rng.normal(0.0, 40.0, (12, 2))
        (du, res), (du_ref, res_ref) = (f.from_state(pose, u, nominal) for f in filters)
        np.testing.assert_array_equal(_bits(du), _bits(du_ref))
        np.testing.assert_array_equal(res.triggered, res_ref.triggered)
        triggered += int(res.triggered.sum())
        pose, u = integrate(team, pose, u, du, DT)
    assert triggered > 10


def test_a_trigger_or_strategy_registered_in_place_of_the_defaults_is_the_one_called(monkeypatch):
    """A function registered under the default trigger's name, or a strategy of a subclass, is called as registered."""
    from aasoatt_env.safety import core, deadlock

    seen = []

    def mine(state, context):
        seen.append(context.p.shape[0])
        return np.ones(context.p.shape[0], dtype=bool)

    class Loud(deadlock.Strategy):
        def correct_target(self, target, zeta, Q, ctx):
            seen.append("strategy")
            return super().correct_target(target, zeta, Q, ctx)

    loud = Loud("eqn.13", deadlock.STRATEGIES["auxiliary_velocity"].target, needs_reference=True)
    monkeypatch.setitem(core.TRIGGERS, "multiplier", mine)
    monkeypatch.setitem(core.STRATEGIES, "auxiliary_velocity", loud)
    env = make_env("random_goals", num_robots=6, filter=True, max_steps=5)
    env.reset(seed=1)
    for _ in range(3):
        env.step({a: np.zeros(2) for a in env.agents})
    assert seen.count(6) >= 3 and seen.count("strategy") >= 3


@pytest.mark.parametrize("grouped", [False, True])
def test_a_subsets_backup_constants_are_the_whole_teams_indexed(grouped):
    """The backup layer's per-robot constants of a team's subset (its checks of a group of robots) are taken
    from the whole team's by indexing: the same numbers as made for that subset alone, for mixed robots, in
    stacks of teams, for index arrays and masks (the caller's array changed afterwards), and for a subset of a
    subset; a pickled subset leaves its whole team behind."""
    import pickle

    from aasoatt_env.model.params import SUBSET_OF
    from aasoatt_env.safety.backup.gate import team_block as _team_block

    team = make_team(["paper", "turtlebot3_burger", RobotParams(radius=0.3, offset=0.1), "paper_small"] * 6, 24)
    if grouped:
        team = stack_teams([team.subset(np.arange(12)), team.subset(np.arange(12, 24))])
    rng = np.random.default_rng(2)
    picks = [rng.choice(24, 7, replace=False), rng.uniform(size=24) < 0.4, np.arange(24)[::-1]]
    for idx in picks:
        sub = team.subset(idx)
        assert sub.derived[SUBSET_OF][0] is team
        if idx.dtype != bool:
            idx[:] = idx[::-1].copy()  # the caller's index array reused: the subset keeps its own robots
        nested = sub.subset(np.array([0, 2]))
        for t in (sub, nested):
            alone = Team(t.radius, t.wheel_radius, t.half_track, t.offset, t.max_wheel_accel, t.max_wheel_speed,
                         t.max_point_accel, t.model, t.group)
            got, want = _team_block(t, 2.0 / 3.0, 3.0), _team_block(alone, 2.0 / 3.0, 3.0)
            assert SUBSET_OF not in alone.derived
            for a, b in zip((*got[0], got[1]), (*want[0], want[1])):
                if isinstance(a, np.ndarray):
                    assert a.dtype == b.dtype and a.flags.c_contiguous
                    np.testing.assert_array_equal(a, b)
                else:
                    assert a == b
        copy = pickle.loads(pickle.dumps(sub))
        assert SUBSET_OF not in copy.derived and len(pickle.dumps(sub)) < len(pickle.dumps(team))
        np.testing.assert_array_equal(_team_block(copy, 2.0 / 3.0, 3.0)[1], _team_block(sub, 2.0 / 3.0, 3.0)[1])


@needs_numba
def test_the_compiled_box_least_squares_is_the_numpy_one():
    """Every robot's closed form, inside and outside its box, on every edge and corner, and robots whose
    numbers are not finite (a singular ``A``, a NaN or infinite target): the same numbers (a zero's or a NaN's
    sign may differ: numpy's own clip gives ``0.0`` or ``-0.0`` on a tie with a signed zero bound depending on
    the array's length)."""
    from aasoatt_env.safety.problem import box_least_squares

    rng = np.random.default_rng(13)
    team = make_team(["paper", "turtlebot3_burger", RobotParams(radius=0.3, offset=0.1)] * 1000, 3000)
    u = rng.uniform(-8.0, 8.0, (team.n, 2))
    kin = kinematics(team, np.column_stack((rng.uniform(-5, 5, (team.n, 2)), rng.uniform(-np.pi, np.pi, team.n))), u)
    lo, hi = input_bounds(team, u, DT)
    target = rng.normal(0.0, 3.0, (team.n, 2)) * rng.choice([0.01, 1.0, 100.0], (team.n, 1))
    A = kin.A.copy()
    A[:5] = 0.0  # singular
    target[5:10] = np.nan
    target[10:15, 0] = np.inf
    A[15:20, 0, 0] = np.nan
    with np.errstate(all="ignore"):
        ref = box_least_squares(A, target, lo, hi)
    np.testing.assert_array_equal(box_least_squares(A, target, lo, hi, compiled=True), ref)  # (NaN == NaN here)
    inside = ((ref > lo) & (ref < hi)).all(axis=1)
    assert 0.05 * team.n < inside.sum() < 0.95 * team.n and not np.isfinite(ref[:20]).all()
    with pytest.raises(ValueError, match=r"lo: got shape \(3, 2\), expected \(3000, 2\)"):
        box_least_squares(A, target, lo[:3], hi, compiled=True)


_AFTER_WARM_UP = """
import numpy as np
from aasoatt_env import compiled, make_batched_env, make_env
from aasoatt_env.model.dynamics import DT, input_bounds, kinematics
from aasoatt_env.model.params import make_team
from aasoatt_env.safety import SafetyFilter, warm_up
from agents import HostileAgent, TrackingController

ENTRIES = {"backup": ("gate_full", "repair_full"), "local": ("solve_all",), "active_set": ("solve_parts",),
           "geometry": ("cell_pairs", "components"), "centralized": ("solve_decomposed", "box_least_squares"),
           "rows": ("aasoatt_rows", "pairs_within"), "fused": ("fused_step",), "inputs": ("numbers",),
           "deadlock": ("multiplier_target",)}


def signatures():
    return {f"{p}.{n}": sorted(map(str, getattr(compiled.kernels(p), n).signatures)) for p, names in ENTRIES.items()
            for n in names}


names = []
assert warm_up("auto", progress=names.append) is True and names
before = signatures()
assert all(before.values()), before
for mode in ("centralized", "decentralized"):
    for scenario, kw, agent in (("random_goals", {"num_robots": 250}, HostileAgent()),
                                ("circle_obstacles", {"num_robots": 10}, HostileAgent()),
                                ("circle_swap", {"num_robots": 20}, TrackingController())):
        env = make_env(scenario, filter={"mode": mode}, max_steps=400, **kw)
        obs, _ = env.reset(seed=2)
        for _ in range(400 if scenario == "circle_swap" else 25):
            obs, *_ = env.step(agent.act(obs, env))
batch = make_batched_env(4, "random_goals", num_robots=6, filter=True)
batch.reset(seed=3)
for _ in range(10):
    batch.step(np.random.default_rng(3).uniform(-1.0, 1.0, (4, 6, 2)))
# the core called directly: Fortran-ordered or read-only arrays, with and without a reference
team = make_team(["paper", "turtlebot3_burger"] * 4, 8)
rng = np.random.default_rng(6)
pose = np.column_stack((rng.uniform(0.0, 3.0, (8, 2)), rng.uniform(-np.pi, np.pi, 8)))
u = rng.normal(0.0, 5.0, (8, 2))
kin, (lo, hi) = kinematics(team, pose, u), input_bounds(team, u, DT)
ref = (kin.p.copy(), np.zeros((8, 2)))
ref[0].flags.writeable = False
for u_in, reference in ((u, ref), (np.asfortranarray(u), None)):
    filt = SafetyFilter(team, deadlock="auxiliary_velocity" if reference else "rotate_nominal")
    for _ in range(2):
        filt.step(kin, u_in, pose[:, 2], rng.normal(0.0, 30.0, (8, 2)), lo, hi, reference=reference)
after = signatures()
print([k for k in after if after[k] != before[k]])
"""


@needs_numba
@pytest.mark.slow
def test_warm_up_compiles_what_the_filter_runs():
    """In a fresh process, after ``warm_up`` nothing compiles any more: hostile runs of both modes, with obstacles,
    the paper's circle swap (braking and repairs), a stack of teams, 250 robots (the cells), the core called
    directly with other layouts."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _AFTER_WARM_UP], capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "[]"


def test_warm_up_without_kernels(monkeypatch):
    def refuse(part):
        raise AssertionError(f"the {part} kernels were asked for")

    monkeypatch.setattr(compiled, "kernels", refuse)
    assert warm_up("numpy") is False
    with pytest.raises(ConfigError, match=r"kernel: got 'fast', expected one of \['auto', 'numpy', 'numba'\]"):
        warm_up("fast")
    monkeypatch.setattr(compiled, "_load", lambda name: None)  # numba missing
    assert warm_up("auto") is False
    with pytest.raises(ConfigError, match=r"kernel: .*pip install \"aasoatt\[fast\]\""):
        warm_up("numba")


def test_kernel_option_is_validated():
    with pytest.raises(ConfigError, match="kernel"):
        FilterConfig(kernel="fortran")
    assert FilterConfig(kernel="numpy").compiled is False
    assert FilterConfig().compiled is compiled.available()


def test_kernel_numba_without_numba_says_how_to_install_it(monkeypatch):
    monkeypatch.setattr(compiled, "_load", lambda name: None)
    cfg = FilterConfig(kernel="numba")  # a saved configuration still loads
    with pytest.raises(ConfigError, match=r"kernel: .*pip install \"aasoatt\[fast\]\""):
        SafetyFilter(config=cfg)
    for mode in ("centralized", "decentralized"):  # the active set's, the local solver's kernel
        with pytest.raises(ConfigError, match=r"kernel: .*pip install \"aasoatt\[fast\]\""):
            SafetyFilter(kernel="numba", mode=mode, backup=False)
    with pytest.raises(ConfigError, match=r"kernel: .*pip install \"aasoatt\[fast\]\""):
        make_env("random_goals", num_robots=2, filter={"kernel": "numba"})
    assert FilterConfig(kernel="auto").compiled is False  # falls back to the numpy reference


@pytest.mark.slow
@pytest.mark.parametrize("kernel", ["numpy", "numba"])
def test_hostile_policy_behind_either_kernel_never_collides(kernel):
    if kernel == "numba" and not compiled.available():
        pytest.skip("numba not installed")
    env = make_env("random_goals", filter={"kernel": kernel}, num_robots=20, max_steps=1200)
    rollout, _ = run_episode(env, HostileAgent(), seed=6)
    assert pairwise_min_distance(rollout).overall_min_robot_gap >= -1e-3
    assert not np.any(rollout.solver_status == "unsafe")
    assert rollout.backup.any()


@pytest.mark.parametrize("use_kernel", [False, pytest.param(True, marks=needs_numba)])
@pytest.mark.parametrize("kind", ["paper", "double_integrator"])
def test_a_nan_speed_is_never_verified_safe(kind, use_kernel):
    """A NaN wheel speed makes the robot's reach NaN (unbounded): broken, and the state is not called safe."""
    team = make_team(kind, 2)
    u = np.array([[np.nan, np.nan], [0.0, 0.0]])
    for gap in (1.0, 50.0):  # a pair within range, and the robot alone
        pose = np.array([[0.0, 0.0, 0.0], [gap, 0.0, 0.0]])
        with np.errstate(invalid="ignore"):
            g = gatekeeper(team, pose, u, np.zeros((2, 2)), DT, sensing_range=D, brake_fraction=F,
                           compiled=use_kernel)
        assert not g.safe and g.broken[0]


@pytest.mark.parametrize("use_kernel", [False, pytest.param(True, marks=needs_numba)])
def test_gatekeeper_refuses_bad_pairs_and_blend_levels(use_kernel):
    team = make_team("paper", 2)
    pose, u = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]), np.zeros((2, 2))
    kw = dict(sensing_range=D, brake_fraction=F, compiled=use_kernel)
    for bad in (np.array([[0, 7]]), np.array([[-1, 0]]), np.array([0, 1]), np.array([[0.0, 1.0]])):
        with pytest.raises(ValueError, match=r"near_pairs: .*expected \(P, 2\) integer robot indices in \[0, 2\)"):
            gatekeeper(team, pose, u, u, DT, near_pairs=bad, **kw)
    for bad in ((1.5,), (float("nan"),), (-0.5,)):
        with pytest.raises(ValueError, match=r"blend_levels: .*expected shares in \(0, 1\]"):
            gatekeeper(team, pose, u, u, DT, blend_levels=bad, **kw)


def test_compiled_calls_without_numba_say_how_to_install_it(monkeypatch):
    monkeypatch.setattr(compiled, "_load", lambda name: None)
    team = make_team("paper", 2)
    pose, u = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]), np.zeros((2, 2))
    with pytest.raises(ImportError, match=r"pip install \"aasoatt\[fast\]\""):
        gatekeeper(team, pose, u, u, DT, sensing_range=D, brake_fraction=F, compiled=True)
    with pytest.raises(ImportError, match=r"pip install \"aasoatt\[fast\]\""):
        repair(team, pose, u, u, DT, u - 1.0, u + 1.0, sensing_range=D, brake_fraction=F, compiled=True)
    with pytest.raises(ImportError, match=r"pip install \"aasoatt\[fast\]\""):
        solve_local_qps(np.eye(2)[None], np.zeros((1, 2)), -np.ones((1, 2)), np.ones((1, 2)), np.zeros(0, int),
                        np.zeros((0, 2)), np.zeros(0), compiled=True)


def test_a_point_mass_rests_past_its_braking_horizon():
    """Past the last braking step a point mass is at rest: no parabola bulge on the padding steps.

    Braking from exactly 1 m/s, ``T / dt`` rounds one ulp above an integer, so the speed scale of the step after
    the horizon is 1e-16 > 0: that step must carry no bulge (12.5 um), as the kernels' rows, at rest past their
    horizon, carry none.
    """
    from aasoatt_env.safety.backup import braking_du, candidate_paths, candidate_samples_at

    t1 = make_team("double_integrator", 1)
    u = np.array([[np.cos(np.pi / 6), np.sin(np.pi / 6)]])
    for _ in range(8):
        du = braking_du(t1, u, DT, F)
        cp = candidate_paths(t1, np.zeros((1, 3)), u, du, DT, F, length=200)
        n = int(cp.length[0])
        assert (cp.delta[0, n - 1:] == 0.0).all() and cp.delta[0, n - 2] > 0.0
        s = np.arange(n - 3, n + 3)[None, :]
        _, d = candidate_samples_at(t1, np.zeros((1, 3)), u, du, DT, F, s)
        assert (d[0, 2:] == 0.0).all()  # steps n-1 .. : at rest
        u = u + du * DT


def test_absurd_wheel_speeds_are_never_called_brake_safe():
    """A braking longer than MAX_BRAKE_STEPS is not sampled: its reach is unbounded, the robot broken."""
    from aasoatt_env.safety.backup import MAX_BRAKE_STEPS

    team = make_team("paper", 2)
    pose = np.array([[0.0, 0.0, 0.0], [50.0, 0.0, 0.0]])
    for speed in (1e9, 1e20):
        u = np.array([[speed, speed], [0.0, 0.0]])
        for use_kernel in (False, True) if compiled.available() else (False,):
            g = gatekeeper(team, pose, u, np.zeros((2, 2)), DT, sensing_range=D, brake_fraction=F,
                           compiled=use_kernel)
            assert not g.safe and g.broken[0] and not g.broken[1]
    assert MAX_BRAKE_STEPS * DT > 100.0  # (the kernels read the same constant)


@needs_numba
def test_the_compiled_kernels_check_every_shape():
    team = make_team("paper", 3)
    pose, u = np.zeros((3, 3)), np.zeros((3, 2))
    pose[:, 0] = [0.0, 1.0, 2.0]
    kw = dict(sensing_range=D, brake_fraction=F, compiled=True)
    with pytest.raises(ValueError, match=r"du_c: got shape \(2, 2\), expected \(3, 2\) for a team of 3 robots"):
        gatekeeper(team, pose, u, u[:2], DT, **kw)
    with pytest.raises(ValueError, match=r"pose: got shape \(3, 2\), expected \(3, 3\)"):
        gatekeeper(team, pose[:, :2], u, u, DT, **kw)
    with pytest.raises(ValueError, match=r"obstacles: got centres \(2, 2\), radii \(1,\)"):
        gatekeeper(team, pose, u, u, DT, obstacles=(np.zeros((2, 2)), np.ones(1)), **kw)
    with pytest.raises(ValueError, match=r"hi: got shape \(3, 1\), expected \(3, 2\)"):
        repair(team, pose, u, u, DT, u - 1.0, u[:, :1], **kw)


@needs_numba
def test_describe_says_which_form_runs_each_stage():
    """The default filter names its compiled stages and the fused step; a barrier without a kernel, a strategy
    that rotates the rows, the decentralised mode and the numpy kernel say where the numpy reference runs."""
    team = make_team("paper", 4)
    lines = SafetyFilter(team).describe().splitlines()
    assert "  rows      compiled (aasoatt)" in lines and lines[-1].startswith("  fused ")
    assert "  rows      numpy (distance: no compiled form)" in SafetyFilter(team, barrier="distance").describe()
    with pytest.warns(UserWarning, match="rotates the relative positions"):
        rotating = SafetyFilter(team, deadlock="rotate_relative_position").describe()
    assert "  rows      numpy (aasoatt: the strategy rotates the rows)" in rotating and "fused" not in rotating
    assert "fused" not in SafetyFilter(team, mode="decentralized").describe()
    plain = SafetyFilter(team, kernel="numpy")
    assert "compiled" not in repr(plain) and "fused" not in repr(plain) and "  backup    numpy" in repr(plain)


def _bits(a: np.ndarray) -> np.ndarray:
    """The array's bytes as integers: signed zeros and NaN payloads count."""
    a = np.ascontiguousarray(a)
    return a.view(np.uint32 if a.dtype == np.float32 else np.uint64)


@needs_numba
def test_the_compiled_kinematics_and_step_give_the_numpy_numbers_bit_for_bit():
    """``kinematics`` and ``integrate`` with ``compiled=True`` (:mod:`~aasoatt_env.model.dynamics_kernel`) on 1,800
    random states of mixed teams of 1-64 robots (straight lines, wheels at rest, fast spins): the same bits as the
    numpy reference (numpy's complex products, signed zeros included)."""
    rng = np.random.default_rng(0)
    for n in (1, 3, 7, 20, 21, 64):
        team = make_team((["paper", "turtlebot3_burger"] * 32)[:n], n)
        for t in range(300):
            pose = np.column_stack((rng.uniform(-10.0, 10.0, (n, 2)), rng.uniform(-50.0, 50.0, n)))
            u = rng.normal(0.0, rng.choice([1e-3, 1.0, 20.0]), (n, 2)) * (t % 7 != 0)
            if t % 5 == 0:
                u[:, 1] = u[:, 0]
            du = rng.normal(0.0, 30.0, (n, 2))
            for a, b in zip(kinematics(team, pose, u), kinematics(team, pose, u, compiled=True)):
                assert np.array_equal(_bits(a), _bits(b))
            for a, b in zip(integrate(team, pose, u, du, DT), integrate(team, pose, u, du, DT, compiled=True)):
                assert np.array_equal(_bits(a), _bits(b))


@needs_numba
@pytest.mark.parametrize(("scenario", "options"), [
    ("random_goals", dict(num_robots=20, random_obstacles=6)), ("circle_swap", dict(num_robots=39)),
    ("doorway", {}), ("random_goals", dict(num_robots=3, num_neighbors=6, num_obstacles=3)),
    ("random_goals", dict(num_robots=150)), ("batched", dict(num_robots=6, random_obstacles=3))])
def test_the_compiled_observations_give_the_numpy_observations_bit_for_bit(monkeypatch, scenario, options):
    """Every observation along 60 steps of uniform random actions, built by the compiled kernel
    (:mod:`~aasoatt_env.sim.observations_kernel`) and by the numpy reference: the same float32 bits (obstacles, more
    neighbour slots than robots, the k-d tree's neighbours, stacked teams with obstacle offsets)."""
    import aasoatt_env.sim.observations as obs_mod
    import aasoatt_env.sim.stack as stack_mod

    calls = []

    def both(**kw):
        ref = obs_mod.build_observations(**kw, compiled=False)
        calls.append(np.array_equal(_bits(ref), _bits(obs_mod.build_observations(**kw, compiled=True))))
        return ref

    monkeypatch.setattr(stack_mod, "build_observations", lambda compiled, **kw: both(**kw))
    rng = np.random.default_rng(0)
    if scenario == "batched":
        env = make_batched_env(4, "random_goals", **options)
        env.reset(seed=0)
        for _ in range(60):
            env.step(rng.uniform(-1.0, 1.0, (4, 6, 2)).astype(np.float32))
    else:
        env = make_env(scenario, **options)
        env.reset(seed=1)
        for _ in range(60):
            env.step({a: rng.uniform(-1.0, 1.0, 2).astype(np.float32) for a in env.agents})
            if not env.agents:
                break
    assert len(calls) >= 40 and all(calls)


@needs_numba
def test_the_compiled_neighbourhood_gives_the_numpy_ones_bit_for_bit(monkeypatch):
    """:func:`~aasoatt_env.model.geometry.neighbourhood` by the kernel and by the numpy reference: the same nearest
    (the lower index first on a tie), distances, gaps and clearance, on 200 random stacks (equal and unequal radii,
    positions on a 0.1 m grid: many ties; fewer robots than slots; lone robots) and along a batched episode."""
    import aasoatt_env.sim.stack as stack_mod
    from aasoatt_env.model.geometry import neighbourhood

    rng = np.random.default_rng(0)
    for trial in range(200):
        teams, n, k, m = (int(rng.integers(1, 9)), int(rng.integers(1, 40)), int(rng.integers(0, 7)),
                          int(rng.integers(0, 4)))
        p = rng.uniform(-3.0, 3.0, (teams * n, 2))
        p = np.round(p, 1) if trial % 3 == 0 else p
        radii = np.full(teams * n, 0.3) if trial % 2 else rng.uniform(0.1, 0.4, teams * n)
        args = (p, radii, rng.uniform(-3.0, 3.0, (teams, m, 2)), rng.uniform(0.1, 0.5, (teams, m)), k, teams)
        for ref, new in zip(neighbourhood(*args), neighbourhood(*args, compiled=True)):
            assert ref.shape == new.shape and np.array_equal(_bits(ref), _bits(new)), (trial, teams, n, k)
    calls = []

    def both(*args, compiled, **kw):
        ref = neighbourhood(*args, **kw)
        calls.append(all(np.array_equal(_bits(a), _bits(b)) for a, b in zip(ref, neighbourhood(*args, **kw,
                                                                                             compiled=True))))
        return ref

    monkeypatch.setattr(stack_mod, "neighbourhood", both)
    env = make_batched_env(4, "circle_swap", num_robots=12)  # (a circle: neighbours at equal distances)
    env.reset(seed=0)
    for _ in range(40):
        env.step(rng.uniform(-1.0, 1.0, (4, 12, 2)).astype(np.float32))
    assert len(calls) >= 40 and all(calls)


@needs_numba
def test_the_compiled_active_set_answers_a_large_problem_of_small_parts(monkeypatch):
    """A stack of 48 teams of 6 behind one centralised filter under random actions: its QPs (576 variables, too many
    for dense algebra as one) are answered part by part by the kernel, every part verified, and the positions agree
    with the numpy reference's (sparse algebra on the whole problem) to 1e-9 m over 60 steps."""
    from aasoatt_env.safety.solvers import active_set as mod

    answered, kernel = [], mod._solve_compiled

    def counted(prob, *args):
        out = kernel(prob, *args)
        answered.append(prob.n if out is not None and out.ok.all() else 0)
        return out

    monkeypatch.setattr(mod, "_solve_compiled", counted)
    rng = np.random.default_rng(2)
    acts = rng.uniform(-1.0, 1.0, (60, 48, 6, 2))
    paths = []
    for name in ("numba", "numpy"):
        env = make_batched_env(48, "random_goals", num_robots=6, filter={"kernel": name})
        env.reset(seed=0)
        for a in acts:
            env.step(a)
        paths.append(env._kin.p.copy())
    assert max(answered) > mod.DENSE_MAX_VARS and not mod._dense(max(answered), 0)  # (every part verified)
    assert np.abs(paths[0] - paths[1]).max() <= 1e-9
