"""Closed-loop circle swap with the safety filter, plus a cross-check of the QP solver."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import circle_layout, closed_loop

import aasoatt_env.safety.solvers.policy as core
from aasoatt_env.model.dynamics import jacobian
from aasoatt_env.model.params import make_team
from aasoatt_env.safety import SafetyFilter, build_problem, solve_qp

D_S = 0.96


def _full_objective(prob, x):
    """Objective shifted so the unconstrained optimum is 0 (>= 0, scale-free comparison)."""
    gb = prob.g.reshape(-1, 2)
    c = 0.5 * np.einsum("ni,ni->", gb, np.linalg.solve(prob.H_blocks, gb[..., None])[..., 0])
    return prob.objective(x) + c


@pytest.fixture(scope="module")
def swap10(request):
    recorded = []
    real = core.SolverPolicy.solve

    def spy(self, prob, *a, **k):
        sol = real(self, prob, *a, **k)
        if prob.m > 0 and len(recorded) < 400:
            recorded.append(prob)
        return sol

    core.SolverPolicy.solve = spy
    try:  # (the numpy stages: every QP through the policy, none answered by the compiled centralised stage)
        scen = circle_layout(10, radius=6.0, duration=12.0)
        out = closed_loop(scen, SafetyFilter(scen.team, kernel="numpy"), 15.0)
    finally:
        core.SolverPolicy.solve = real
    return out, recorded


@pytest.mark.slow
def test_circle_swap_safe_and_converges(swap10):
    out, _ = swap10
    assert out.min_distance >= D_S - 1e-3
    assert out.statuses.get("failed", 0) == 0
    assert np.all(out.final_error < 0.05), out.final_error


@pytest.mark.slow
def test_without_deadlock_resolution_robots_get_stuck():
    scen = circle_layout(10)
    out = closed_loop(scen, SafetyFilter(scen.team, deadlock="none"), 15.0)
    assert out.min_distance >= D_S - 1e-3
    assert np.max(out.final_error) > 0.5


@pytest.mark.parametrize("other", ["quadprog", "clarabel"])
def test_warm_started_active_set_path_matches_independent_solver(swap10, other):
    # FilterConfig(active_set=True) first tries a warm-started active-set method (KKT-verified);
    # warm-start each recorded problem from the optimum of a perturbed copy, as the
    # previous control step would, and compare with an independent solver
    import dataclasses

    _, recorded = swap10
    rng = np.random.default_rng(1)
    took_fast = 0
    for prob in recorded[:250]:
        prev = dataclasses.replace(prob, g=prob.g + rng.normal(0, 0.02, prob.n))
        warm = solve_qp(prev, "proxsuite")
        ours = solve_qp(prob, "proxsuite", warm.x, warm.z, active_set=True)
        ref = solve_qp(prob, other)
        took_fast += ours.message.startswith("active set")
        assert ours.status == ref.status == "solved"
        f1, f2 = _full_objective(prob, ours.x), _full_objective(prob, ref.x)
        assert abs(f1 - f2) <= 1e-6 * max(1.0, abs(f2)), (f1, f2)
        assert np.all(prob.C @ ours.x <= prob.u + 1e-8)
    assert took_fast >= 200  # the warm path, not the fallback, was exercised


@pytest.mark.slow
@pytest.mark.parametrize("strategy", ["rotate_nominal", "rotate_reference_velocity", "auxiliary_velocity"])
def test_deadlock_strategies_bring_every_robot_home(strategy):
    scen = circle_layout(10, radius=6.0, duration=12.0)
    out = closed_loop(scen, SafetyFilter(scen.team, deadlock=strategy), 15.0)
    assert out.min_distance >= D_S - 1e-3
    assert out.statuses.get("failed", 0) == 0
    assert np.all(out.final_error < 0.05), out.final_error


def _random_problems(rng, count):
    probs = []
    team = make_team("paper", 8)
    for _ in range(count):
        n = int(rng.integers(2, 9))
        A = jacobian(team, rng.uniform(-np.pi, np.pi, 8))[:n]
        target = rng.normal(0, 3, (n, 2))
        lo, hi = -np.full((n, 2), 60.0), np.full((n, 2), 60.0)
        m = int(rng.integers(1, 3 * n))
        ri = rng.integers(0, n, m)
        rj = (ri + rng.integers(1, n, m)) % n
        rj = np.where(rng.random(m) < 0.2, -1, rj)
        c = rng.normal(0, 1, (m, 2))
        Gi = np.einsum("pki,pk->pi", A[ri], c)
        Gj = -np.einsum("pki,pk->pi", A[np.maximum(rj, 0)], c)
        rhs = rng.normal(0, 2, m)
        probs.append(build_problem(A, target, lo, hi, np.full(n, 60.0), ri, rj, Gi, Gj, rhs))
    return probs


@pytest.mark.parametrize(("solver", "other"), [("proxsuite", "quadprog"), ("proxsuite", "clarabel"),
                                               ("ldp", "quadprog")])
def test_cross_check_against_independent_solver(swap10, solver, other):
    _, recorded = swap10
    rng = np.random.default_rng(0)
    probs = recorded[:300] + _random_problems(rng, 250)
    assert len(probs) >= 500
    compared = 0
    for prob in probs:
        ours = solve_qp(prob, solver)
        ref = solve_qp(prob, other)
        assert ours.status != "failed"
        assert np.all(np.isfinite(ours.x))
        assert np.all(ours.x >= prob.lb - 1e-9) and np.all(ours.x <= prob.ub + 1e-9)
        if ref.status == "solved":
            # the independent solver solves it: we must not call it infeasible
            assert ours.status == "solved", ours.message
            f1, f2 = _full_objective(prob, ours.x), _full_objective(prob, ref.x)
            assert abs(f1 - f2) <= 1e-6 * max(1.0, abs(f2)), (f1, f2)
            compared += 1
    assert compared >= 450


@pytest.mark.slow
def test_full_circle_of_39_robots_is_safe_and_reaches_the_packed_goals():
    # the goals are only 6 mm further apart than d_s: a constant discrete-time
    # margin would make them unreachable; the velocity-faded margin does not
    scen = circle_layout(39, radius=6.0, duration=12.0)
    out = closed_loop(scen, SafetyFilter(scen.team), 15.0)
    assert out.min_distance >= D_S - 1e-3
    assert out.statuses.get("failed", 0) == 0
    assert np.all(out.final_error < 0.05), out.final_error.max()


def test_ldp_alone_relaxes_infeasible_problems_like_quadprog(monkeypatch):
    # core dependencies only (no Clarabel to fall back on): ldp answers the phase-1
    # problem too, so an infeasible QP is relaxed, never "failed"
    import aasoatt_env.safety.solvers.backends as backends

    real = backends._installed
    monkeypatch.setattr(backends, "_installed", lambda mod: mod != "clarabel" and real(mod))
    relaxed = 0
    for prob in _random_problems(np.random.default_rng(0), 250):
        ours, ref = solve_qp(prob, "ldp"), solve_qp(prob, "quadprog")
        assert ours.status == ref.status, ours.message
        assert np.all(ours.x >= prob.lb - 1e-9) and np.all(ours.x <= prob.ub + 1e-9)
        if ref.status == "relaxed":
            relaxed += 1
            assert abs(ours.slack - ref.slack) <= 1e-6 * max(1.0, ref.slack)
            # rows were loosened by their least violation (1 + 1e-6) + 1e-7 (qp.solve_qp)
            assert np.all(prob.C @ ours.x - prob.u <= ours.slack * (1 + 2e-6) + 2e-7)
    assert relaxed >= 30


def test_stacked_teams_take_the_dense_active_set_and_match_quadprog(swap10, monkeypatch):
    # a stack of small teams behind one filter call (the batched env's grouped filter) gives
    # problems with many variables and few rows each: the warm active set solves them with
    # dense algebra (DENSE_MAX_CELLS); its answer must still be the exact optimum
    import dataclasses

    import scipy.sparse as sp

    import aasoatt_env.safety.solvers.active_set as AS

    _, recorded = swap10
    dense_calls = []
    real_rows = AS._dense_rows
    monkeypatch.setattr(AS, "_dense_rows", lambda prob, L: dense_calls.append(prob.n) or real_rows(prob, L))
    rng = np.random.default_rng(2)
    groups = [recorded[k:k + 5] for k in range(0, 200, 40)]
    for group in groups:
        stack = dataclasses.replace(
            group[0], H_blocks=np.concatenate([p.H_blocks for p in group]), g=np.concatenate([p.g for p in group]),
            C=sp.block_diag([p.C for p in group], format="csr"), u=np.concatenate([p.u for p in group]),
            lb=np.concatenate([p.lb for p in group]), ub=np.concatenate([p.ub for p in group]),
            scale=np.concatenate([p.scale for p in group]), row_norm=np.concatenate([p.row_norm for p in group]))
        assert stack.n > AS.DENSE_MAX_VARS and stack.n * (stack.m + 2 * stack.n) <= AS.DENSE_MAX_CELLS
        prev = dataclasses.replace(stack, g=stack.g + rng.normal(0, 0.02, stack.n))
        warm = solve_qp(prev, "proxsuite")
        ours = solve_qp(stack, "proxsuite", warm.x, warm.z, active_set=True)
        ref = solve_qp(stack, "quadprog")
        assert ours.message.startswith("active set"), ours.message
        f1, f2 = _full_objective(stack, ours.x), _full_objective(stack, ref.x)
        assert abs(f1 - f2) <= 1e-6 * max(1.0, abs(f2)), (f1, f2)
        assert np.all(stack.C @ ours.x <= stack.u + 1e-8)
        np.testing.assert_allclose(ours.x, ref.x, atol=1e-6)
    assert dense_calls and min(dense_calls) > AS.DENSE_MAX_VARS


def _stacked(parts: list) -> object:
    """One QP of independent ``parts`` (a stack of teams): block-diagonal rows, the parts' variables in order."""
    import dataclasses

    import scipy.sparse as sp

    return dataclasses.replace(
        parts[0], H_blocks=np.concatenate([p.H_blocks for p in parts]), g=np.concatenate([p.g for p in parts]),
        C=sp.block_diag([p.C for p in parts], format="csr"), u=np.concatenate([p.u for p in parts]),
        lb=np.concatenate([p.lb for p in parts]), ub=np.concatenate([p.ub for p in parts]),
        scale=np.concatenate([p.scale for p in parts]), row_norm=np.concatenate([p.row_norm for p in parts]))


def test_a_stack_s_parts_are_verified_one_by_one_and_only_the_rest_goes_to_the_back_end(swap10):
    # four independent parts in one QP (a stack of teams), one of them infeasible: the warm
    # active set answers the three it verifies, only the infeasible one goes to the back-end and
    # phase 1, and every part's answer is its own exact optimum
    import dataclasses

    import aasoatt_env.safety.solvers.active_set as AS
    from aasoatt_env.safety.solvers.policy import SolverPolicy

    _, recorded = swap10
    parts = [recorded[k] for k in (10, 60, 110, 160)]
    parts[2] = dataclasses.replace(parts[2], u=parts[2].u - 5.0)  # unit rows, |x| <= 1: no point meets these
    stack = _stacked(parts)
    groups = np.repeat(np.arange(4), [p.n // 2 for p in parts])
    warm = [solve_qp(recorded[k - 1], "quadprog") for k in (10, 60, 110, 160)]
    x0, z0 = np.concatenate([w.x for w in warm]), np.concatenate([w.z for w in warm])
    assert x0.shape == (stack.n,) and z0.shape == (stack.m,)
    sol = SolverPolicy("proxsuite", active_set=True).solve(stack, x0, z0, groups)
    assert "active set (warm, KKT verified) on 3 of 4 parts" in sol.message, sol.message
    assert sol.status == "relaxed"
    xs = np.split(sol.x, np.cumsum([p.n for p in parts])[:-1])
    zs = np.split(sol.z, np.cumsum([p.m for p in parts])[:-1])
    for k, p in enumerate(parts):
        ref = solve_qp(p, "quadprog")
        np.testing.assert_allclose(xs[k], ref.x, atol=1e-6)
        if k == 2:
            assert ref.status == "relaxed" and abs(sol.slack - ref.slack) <= 1e-6 * max(1.0, ref.slack)
        else:
            np.testing.assert_allclose(zs[k], ref.z, atol=1e-6)
    # one group: the whole problem is one part, answered as without groups
    one = AS.solve_active_set_parts(parts[0], warm[0].x, warm[0].z, np.zeros(parts[0].n // 2, int))
    none = AS.solve_active_set_parts(parts[0], warm[0].x, warm[0].z, None)
    assert one.ok.shape == (1,) and one.ok[0] and one.iterations == none.iterations
    np.testing.assert_array_equal(one.x, none.x)
    # groups that a row joins are refused (None: the caller solves the whole problem)
    split = np.arange(stack.n // 2) % 2
    assert AS.solve_active_set_parts(stack, x0, z0, split) is None
    stack_ok = SolverPolicy("proxsuite", active_set=True).solve(stack, x0, z0, split)
    np.testing.assert_allclose(stack_ok.x, sol.x, atol=1e-6)


def test_the_active_set_never_verifies_a_nan(swap10):
    # a NaN in the bounds or the linear term fails the KKT check of its part: no "solved" NaN
    import dataclasses

    import aasoatt_env.safety.solvers.active_set as AS

    _, recorded = swap10
    prob = recorded[40]
    warm = solve_qp(recorded[39], "quadprog")
    u = prob.u.copy()
    u[0] = np.nan
    g = prob.g.copy()
    g[:] = np.nan
    for bad in (dataclasses.replace(prob, u=u), dataclasses.replace(prob, g=g)):
        assert AS.solve_active_set(bad, warm.x, warm.z) is None
        part = AS.solve_active_set_parts(bad, warm.x, warm.z, np.zeros(prob.n // 2, int))
        assert part is None or not part.ok.any()


def test_group_argmin_picks_the_first_smallest_finite_value_per_group():
    from aasoatt_env.safety.solvers.active_set import _group_argmin

    val = np.array([3.0, 1.0, np.inf, 1.0, 2.0, np.inf, 5.0, 0.5])
    rg = np.array([0, 0, 1, 0, 2, 1, 2, 3])
    # group 0: ties at 1.0 -> the first index; group 1: only inf -> -1; group 4 has no rows -> -1
    np.testing.assert_array_equal(_group_argmin(val, rg, 5), [1, -1, 4, 7, -1])
    np.testing.assert_array_equal(_group_argmin(np.array([np.inf, np.inf]), np.zeros(2, int), 1), [-1])
    np.testing.assert_array_equal(_group_argmin(np.array([2.0, 1.0, 1.0]), np.zeros(3, int), 1), [1])


def test_a_row_without_entries_belongs_to_group_zero():
    import scipy.sparse as sp

    import aasoatt_env.safety.solvers.active_set as AS
    from aasoatt_env.safety.problem import QPProblem

    # two robots in two groups; rows: robot 1's, an empty one (0 <= 1), robot 0's
    C = sp.csr_matrix(np.array([[0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]]))
    prob = QPProblem(H_blocks=np.broadcast_to(np.eye(2), (2, 2, 2)).copy(), g=np.array([-2.0, 0.0, -2.0, 0.0]),
                     C=C, u=np.array([0.5, 1.0, 0.25]), lb=-np.ones(4), ub=np.ones(4), scale=np.ones(4),
                     obj_scale=1.0, row_norm=np.ones(3), diagonal=True)
    out = AS.solve_active_set_parts(prob, np.zeros(4), np.array([1.0, 0.0, 1.0]), np.array([0, 1]))
    np.testing.assert_array_equal(out.row_group, [1, 0, 0])
    assert out.ok.all()
    np.testing.assert_allclose(out.x, [0.25, 0.0, 0.5, 0.0], atol=1e-12)
    np.testing.assert_allclose(out.z, [1.5, 0.0, 1.75], atol=1e-12)


def test_one_change_rule_rescues_warm_starts_the_primal_dual_rule_cannot_finish(swap10, monkeypatch):
    # warm starts a few rows off (the optimum of a perturbed copy): where the primal-dual
    # rule fails, the one-change rule finishes from the same warm start, and the answer is exact
    import dataclasses

    import aasoatt_env.safety.solvers.active_set as AS

    _, recorded = swap10
    rng = np.random.default_rng(3)
    cases = []
    for prob in recorded[:300]:
        prev = dataclasses.replace(prob, g=prob.g + rng.normal(0, 1.0, prob.n))
        warm = solve_qp(prev, "quadprog")
        cases.append((prob, warm.x, warm.z))
    monkeypatch.setattr(AS, "ONE_CHANGE_ITER", 0)
    pdas = [AS.solve_active_set(dataclasses.replace(p), x, z, max_iter=6) is not None for p, x, z in cases]
    monkeypatch.setattr(AS, "ONE_CHANGE_ITER", 4)
    rescued = 0
    for (prob, x, z), before in zip(cases, pdas):
        out = AS.solve_active_set(dataclasses.replace(prob), x, z, max_iter=6)  # (the budgets the count was made with)
        if out is None:
            continue
        rescued += not before
        if not before:  # the iterations count both rules' equality solves
            assert out[2] >= 2
        ref = solve_qp(prob, "quadprog")
        np.testing.assert_allclose(out[0], ref.x, atol=1e-8)
    assert rescued >= 5, (sum(pdas), rescued, len(cases))  # measured: 272 -> 282 of 300


@pytest.mark.parametrize("kind", ["csr", "unsorted", "duplicates", "csc", "coo", "no rows", "cached"])
def test_ldp_dense_rows_are_the_sparse_forms(kind):
    """``dense_least_distance_form`` (``ldp``'s rows) has the bits of ``least_distance_form(...).Mt.toarray()``:
    CSR rows in order or not, repeated entries (the sparse product adds their products), other formats, no rows,
    signed zeros stored, and with the sparse form already cached on the problem."""
    import scipy.sparse as sp

    from aasoatt_env.safety.problem import QPProblem
    from aasoatt_env.safety.solvers.active_set import (
        _least_distance_form,
        dense_least_distance_form,
        least_distance_form,
    )

    rng = np.random.default_rng(["csr", "unsorted", "duplicates", "csc", "coo", "no rows", "cached"].index(kind))
    for _ in range(40):
        nb, m = int(rng.integers(1, 10)), 0 if kind == "no rows" else int(rng.integers(1, 12))
        n = 2 * nb
        L = rng.normal(size=(nb, 2, 2))
        H = L @ L.transpose(0, 2, 1) + 0.1 * np.eye(2)
        C = sp.random(m, n, density=0.4, random_state=int(rng.integers(1 << 30)), format="coo")
        C.data = rng.normal(size=C.data.shape)
        C.data[::4] = -0.0
        if kind == "duplicates" and C.nnz:
            C = sp.coo_matrix((np.concatenate((C.data, C.data[:2])), (np.concatenate((C.row, C.row[:2])),
                               np.concatenate((C.col, C.col[:2])))), shape=(m, n))
        C = C.asformat("csr" if kind in ("csr", "unsorted", "duplicates", "no rows", "cached") else kind)
        if kind == "unsorted":
            for r in range(m):
                a, b = C.indptr[r], C.indptr[r + 1]
                C.indices[a:b], C.data[a:b] = C.indices[a:b][::-1].copy(), C.data[a:b][::-1].copy()
            C.has_sorted_indices = False
        prob = QPProblem(H, rng.normal(size=n), C, rng.normal(size=m), -np.ones(n), np.ones(n), np.ones(n), 1.0,
                         np.ones(m), False)
        if kind == "cached":
            least_distance_form(prob)
        dense = dense_least_distance_form(prob)
        ref = _least_distance_form(prob)
        np.testing.assert_array_equal(dense.Mt.view(np.int64), ref.Mt.toarray().view(np.int64))
        np.testing.assert_array_equal(dense.b, ref.b)
        np.testing.assert_array_equal(dense.gt, ref.gt)


def test_the_parts_the_active_set_leaves_go_to_the_back_end_in_chunks_of_whole_parts(swap10, monkeypatch):
    # eight independent parts in one QP, two of them infeasible, with no warm start the active set verifies: the
    # route answers them in chunks of whole parts of at most REST_CHUNK variables (a larger part alone), each part
    # its own exact optimum, as when they go as one problem
    import dataclasses

    import aasoatt_env.safety.solvers.policy as pol

    _, recorded = swap10
    parts = [recorded[k] for k in (10, 35, 60, 85, 110, 135, 160, 185)]
    for k in (2, 5):
        parts[k] = dataclasses.replace(parts[k], u=parts[k].u - 5.0)  # (no point meets these rows)
    stack = _stacked(parts)
    groups = np.repeat(np.arange(8), [p.n // 2 for p in parts])
    x0, z0 = np.zeros(stack.n), np.zeros(stack.m)
    sizes, routed = [], pol.SolverPolicy._routed
    monkeypatch.setattr(pol.SolverPolicy, "_routed",
                        lambda self, prob, *a: sizes.append(prob.n) or routed(self, prob, *a))
    answers = {}
    for most in (10**9, 2 * parts[0].n):
        sizes.clear()
        monkeypatch.setattr(pol, "REST_CHUNK", most)
        answers[most] = pol.SolverPolicy("proxsuite", active_set=True, one_change_iter=0).solve(stack, x0, z0, groups)
        assert answers[most].status == "relaxed" and max(sizes) <= max(most, max(p.n for p in parts))
    one, chunked = answers[10**9], answers[2 * parts[0].n]
    assert "chunks" not in one.message and len(sizes) >= 3 and "chunks" in chunked.message, chunked.message
    np.testing.assert_allclose(chunked.x, one.x, atol=1e-6)
    assert abs(chunked.slack - one.slack) <= 1e-6 * max(1.0, one.slack)
