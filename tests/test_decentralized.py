"""The decentralised filter: the exact per-robot 2-variable QP solver and the authority split of the pair rows.

Every answer is checked against an independent dense solver (quadprog) on the robot's own QP.
"""

from __future__ import annotations

import inspect

import numpy as np
import pytest
from helpers import needs_numba

from aasoatt_env.model.dynamics import input_bounds, kinematics, pose_from_point
from aasoatt_env.model.geometry import robot_pairs
from aasoatt_env.model.params import make_team
from aasoatt_env.safety.barriers import PairGeometry, barrier_rows
from aasoatt_env.safety.config import FilterConfig
from aasoatt_env.safety.decentralized import decentralized_step, negotiation_rows, split_rows
from aasoatt_env.safety.problem import box_least_squares, build_problem
from aasoatt_env.safety.solvers import local, polygons
from aasoatt_env.safety.solvers.local import RELAX_TOL, solve_local_qps

quadprog = pytest.importorskip("quadprog")

both = pytest.mark.parametrize("compiled", [False, pytest.param(True, marks=needs_numba)])
"""Run a test on the numpy solver and on its compiled kernel."""


# ----------------------------------------------------------------------------- references
def _qp_ref(H, g, lb, ub, G, h):
    """quadprog on one robot: ``(x, row multipliers)`` or None when it reports the constraints inconsistent."""
    C = np.vstack([-np.eye(2), np.eye(2), -G.reshape(-1, 2)])
    b = np.concatenate([-ub, lb, -h])
    try:
        x, _, _, _, lag, _ = quadprog.solve_qp(H, -g, C.T, b, 0)
    except ValueError:
        return None
    return x, lag[4:]


def _phase1_ref(lb, ub, G, h):
    """Least violations of the rows normalised by ``|G_r|`` (bounds hard), by quadprog on the lifted QP."""
    nrm = np.linalg.norm(G, axis=1)
    Gn, hn = G / nrm[:, None], h / nrm
    m = G.shape[0]
    Hq = np.eye(2 + m)
    Hq[:2, :2] *= 1e-9
    C = np.zeros((2 * m + 4, 2 + m))
    b = np.zeros(2 * m + 4)
    C[:m, :2], C[:m, 2:], b[:m] = -Gn, np.eye(m), -hn  # G x - s <= h
    C[m:2 * m, 2:] = np.eye(m)  # s >= 0
    C[2 * m:2 * m + 2, :2], b[2 * m:2 * m + 2] = np.eye(2), lb
    C[2 * m + 2:, :2], b[2 * m + 2:] = -np.eye(2), -ub
    xs = quadprog.solve_qp(Hq, np.zeros(2 + m), C.T, b, 0)[0]
    return np.maximum(Gn @ xs[:2] - hn, 0.0)


# ----------------------------------------------------------------------------- random robots
def _random_robots(n, seed):
    """Random 2-variable QPs with 0-12 rows; kinds: generic, parallel/duplicate rows, rows through the
    optimum, infeasible (opposite parallel rows with a gap, an empty triangle, a row beyond the box)."""
    rng = np.random.default_rng(seed)
    H = np.empty((n, 2, 2))
    g = rng.normal(0.0, 3.0, (n, 2))
    lb = -rng.uniform(0.5, 2.0, (n, 2))
    ub = rng.uniform(0.5, 2.0, (n, 2))
    owners, Gs, hs = [], [], []
    for k in range(n):
        B = rng.normal(size=(2, 2))
        H[k] = B @ B.T + 0.3 * np.eye(2)
        m = int(rng.integers(0, 13))
        G = rng.normal(size=(m, 2))
        h = rng.normal(0.8, 0.6, m)
        kind = int(rng.integers(0, 7))
        if kind == 1 and m >= 2:  # parallel and duplicate rows
            G[1] = G[0] * rng.uniform(0.5, 2.0)
            h[1] = h[0] * G[1, 0] / G[0, 0] + rng.choice([0.0, 0.2, -0.2])
            if m >= 3:
                G[2], h[2] = G[0], h[0]
        elif kind == 2 and m >= 2:  # opposite rows with a clear gap: infeasible
            G[1] = -G[0] * rng.uniform(0.5, 2.0)
            c = abs(G[1, 0] / G[0, 0])
            h[1] = -h[0] * c - rng.uniform(0.3, 1.0) * c
        elif kind == 3:  # an empty triangle: n_k' x <= -c with normals 120 degrees apart
            ang = rng.uniform(0, 2 * np.pi) + np.array([0.0, 2 * np.pi / 3, 4 * np.pi / 3])
            T = np.stack((np.cos(ang), np.sin(ang)), axis=1) * rng.uniform(0.5, 2.0, (3, 1))
            G = np.vstack((G, T))
            h = np.concatenate((h, -rng.uniform(0.05, 0.5, 3) * np.linalg.norm(T, axis=1)))
        elif kind == 4:  # a row beyond the box
            G = np.vstack((G, [[1.0, 0.0]]))
            h = np.concatenate((h, [lb[k, 0] - rng.uniform(0.1, 1.0)]))
        elif kind == 5:  # rows through the optimum of the robot's QP (degenerate vertices, polygon kept)
            ref = _qp_ref(H[k], g[k], lb[k], ub[k], G, h)
            if ref is not None:
                xs = ref[0]
                act = [G[i] for i in np.flatnonzero(np.abs(G @ xs - h) < 1e-9)]
                act += [np.eye(2)[i] for i in range(2) if xs[i] >= ub[k, i] - 1e-9]
                act += [-np.eye(2)[i] for i in range(2) if xs[i] <= lb[k, i] + 1e-9]
                if act:  # normals in the normal cone at the optimum: the rows contain the polygon
                    cone = np.array(act)
                    extra = rng.uniform(0.1, 1.0, (3, len(act))) @ cone
                    extra[0] = cone[0] * 2.0
                else:  # an interior optimum: two cuts through it leave an interior
                    extra = rng.normal(size=(2, 2))
                G = np.vstack((G, extra))
                h = np.concatenate((h, extra @ xs))
        owners.append(np.full(G.shape[0], k))
        Gs.append(G.reshape(-1, 2))
        hs.append(h)
    return H, g, lb, ub, np.concatenate(owners).astype(np.intp), np.vstack(Gs), np.concatenate(hs)


@both
def test_local_solver_matches_dense_solver_on_random_robots(compiled):
    n = 1500
    H, g, lb, ub, owner, G, h = _random_robots(n, seed=7)
    sol = solve_local_qps(H, g, lb, ub, owner, G, h, compiled=compiled)
    n_inf = 0
    for k in range(n):
        r = owner == k
        ref = _qp_ref(H[k], g[k], lb[k], ub[k], G[r], h[r])
        assert sol.feasible[k] == (ref is not None), k
        if ref is None:
            n_inf += 1
            assert np.all(sol.lam[r] == 0.0)
            assert np.all((sol.x[k] >= lb[k]) & (sol.x[k] <= ub[k]))
            continue
        assert np.max(np.abs(sol.x[k] - ref[0])) <= 1e-6, k
        # KKT with the returned multipliers: stationarity, signs, complementarity
        lam, lb_k = sol.lam[r], sol.lam_box[k]
        grad = H[k] @ sol.x[k] + g[k] + G[r].T @ lam + lb_k[0] - lb_k[1]
        assert np.max(np.abs(grad)) <= 1e-7 * (1 + np.abs(g[k]).max()), k
        assert np.all(lam >= 0) and np.all(lb_k >= 0)
        assert np.all(lam * (G[r] @ sol.x[k] - h[r]) >= -1e-8)
    # the set holds every kind of case
    assert 100 <= n_inf <= n - 500
    assert int((np.bincount(owner, minlength=n) == 0).sum()) > 50


@needs_numba
def test_local_solver_enumeration_path_agrees():
    """The compiled kernel's enumeration fallback alone (no active-set iteration) gives the same answers."""
    H, g, lb, ub, owner, G, h = _random_robots(300, seed=3)
    fast = solve_local_qps(H, g, lb, ub, owner, G, h, compiled=True)
    enum = solve_local_qps(H, g, lb, ub, owner, G, h, max_iter=0, compiled=True)
    assert enum.n_enumerated > 0
    np.testing.assert_array_equal(fast.feasible, enum.feasible)
    assert np.max(np.abs(fast.x - enum.x)) <= 1e-8


@both
def test_relaxed_robots_get_their_least_violation_answer(compiled):
    H, g, lb, ub, owner, G, h = _random_robots(400, seed=5)
    sol = solve_local_qps(H, g, lb, ub, owner, G, h, relax=True, compiled=compiled)
    bad = np.flatnonzero(~sol.feasible)
    assert bad.size > 30
    nrm = np.linalg.norm(G, axis=1)
    for k in bad:
        r = owner == k
        s_ref = _phase1_ref(lb[k], ub[k], G[r], h[r])
        loosen = s_ref * nrm[r] * (1 + 1e-6) + RELAX_TOL * nrm[r]
        np.testing.assert_allclose(sol.loosened[r], loosen, atol=1e-6 * (1 + nrm[r].max()))
        ref = _qp_ref(H[k], g[k], lb[k], ub[k], G[r], h[r] + sol.loosened[r])
        assert ref is not None
        assert np.max(np.abs(sol.x[k] - ref[0])) <= 1e-6, k
    assert np.all(sol.loosened[~np.isin(owner, bad)] == 0.0)


@both
def test_local_solver_edge_cases(compiled):
    H = np.broadcast_to(np.eye(2), (3, 2, 2)).copy()
    g = np.array([[-5.0, 0.0], [0.0, 0.0], [1.0, 1.0]])
    lb, ub = -np.ones((3, 2)), np.ones((3, 2))
    # robot 0: no rows (box only); robot 1: a zero row 0 <= -1 (infeasible); robot 2: a zero row 0 <= 1
    rows = (np.array([1, 2]), np.zeros((2, 2)), np.array([-1.0, 1.0]))
    sol = solve_local_qps(H, g, lb, ub, *rows, compiled=compiled)
    np.testing.assert_allclose(sol.x[0], [1.0, 0.0])
    assert sol.lam_box[0, 0, 0] == pytest.approx(4.0)
    assert list(sol.feasible) == [True, False, True]
    np.testing.assert_allclose(sol.x[2], [-1.0, -1.0])
    relaxed = solve_local_qps(H, g, lb, ub, *rows, relax=True, compiled=compiled)
    assert relaxed.loosened.tolist() == [1.0 + 1e-6, 0.0]  # the zero row is met by loosening it to 0 <= 0
    empty = solve_local_qps(np.zeros((0, 2, 2)), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 2)),
                            np.zeros(0, int), np.zeros((0, 2)), np.zeros(0), compiled=compiled)
    assert empty.x.shape == (0, 2)
    for bad in (np.zeros((2, 2, 2)), np.array([[[1.0, 0.0], [0.0, 1.0]], [[1.0, 2.0], [2.0, 1.0]]])):
        with pytest.raises(ValueError, match=r"H: block\(s\) \[.*1\] not symmetric positive definite"):
            solve_local_qps(bad, np.zeros((2, 2)), -np.ones((2, 2)), np.ones((2, 2)), np.zeros(0, int),
                            np.zeros((0, 2)), np.zeros(0), compiled=compiled)
    # a row that never binds (h = +inf) is no row, relaxed or not
    G = np.array([[2.0, 1.0], [-3.0, 0.0], [1.0, -2.0], [2.0, 2.0], [1.0, 1.0]])
    h = np.array([-1.0, -2.0, 2.0, 1.0, np.inf])
    one = (np.eye(2)[None], np.array([[-3.0, -2.0]]), -np.ones((1, 2)), np.ones((1, 2)), np.zeros(5, int), G)
    for relax in (False, True):
        with_inf = solve_local_qps(*one, h, relax=relax, compiled=compiled)
        without = solve_local_qps(*one[:4], np.zeros(4, int), G[:4], h[:4], relax=relax, compiled=compiled)
        np.testing.assert_array_equal(with_inf.x, without.x)
        assert np.all(np.isfinite(with_inf.loosened)) and with_inf.loosened[4] == 0.0


@pytest.mark.parametrize(("kw", "match"), [
    ({"H": np.full((1, 2, 2), np.nan)}, "H: expected finite"), ({"g": np.array([[np.inf, 0.0]])}, "g: expected"),
    ({"lb": np.array([[np.nan, -1.0]])}, "lb: expected finite"), ({"G": np.array([[np.nan, 1.0]])}, "G: expected"),
    ({"h": np.array([np.nan])}, "h: expected finite values or \\+inf"), ({"h": np.array([-np.inf])}, "h: expected"),
    ({"tol": 0.0}, "tol: expected a finite tolerance > 0"), ({"tol": np.nan}, "tol: expected"),
    ({"max_iter": 2.7}, "max_iter: expected an integer >= 0"), ({"max_iter": -1}, "max_iter"),
    ({"relax_tol": -1.0}, "relax_tol: expected finite values >= 0"),
    ({"relax_tol": np.ones(3)}, r"relax_tol: got shape \(3,\), expected one value or one per robot \(1,\)"),
])
@both
def test_local_solver_refuses_bad_input_naming_it(kw, match, compiled):
    args = {"H": np.eye(2)[None], "g": np.zeros((1, 2)), "lb": -np.ones((1, 2)), "ub": np.ones((1, 2)),
            "owner": np.zeros(1, int), "G": np.array([[1.0, 0.0]]), "h": np.array([0.5])}
    opts = {k: v for k, v in kw.items() if k in ("tol", "max_iter", "relax_tol")}
    args.update({k: v for k, v in kw.items() if k not in opts})
    with pytest.raises(ValueError, match=match):
        solve_local_qps(**args, **opts, relax=True, compiled=compiled)


def test_the_phase1_line_minimiser_is_exact_and_each_robots_own():
    """Robot 0's slope at 0 is exactly 0 (beside a padding row); robot 1's minimiser is a kink, robot 2's inside a
    piece.  Each answer is exact and the one it gets alone."""
    res = np.array([[0.0, -polygons.FAR], [-1.0, 0.5], [1.0, 0.5]])
    delta = np.array([[1.0, 0.0], [2.0, -1.0], [-4.0, 0.0]])
    t = polygons._line_min(np, res, delta)
    assert t[0] == 0.0 and t[1] == pytest.approx(0.5) and t[2] == pytest.approx(0.25)
    for k in range(3):
        assert polygons._line_min(np, res[k:k + 1], delta[k:k + 1])[0] == t[k]


@both
def test_a_robot_answers_the_same_alone_and_in_a_batch(compiled):
    """A robot infeasible only by a zero row (``0 <= h < 0``), relaxed beside robots whose phase 1 needs several
    line-search steps: its answer is finite and the one it gets alone, and theirs are theirs."""
    H, g, lb, ub, owner, G, h = _random_robots(400, seed=5)
    n = H.shape[0]
    one = (np.eye(2)[None] * 2.0, np.array([[1.0, -0.5]]), -np.ones((1, 2)), np.ones((1, 2)))
    zero_row = (np.zeros((1, 2)), np.array([-1.0]))
    batch = solve_local_qps(np.concatenate((H, one[0])), np.concatenate((g, one[1])), np.concatenate((lb, one[2])),
                            np.concatenate((ub, one[3])), np.concatenate((owner, [n])), np.vstack((G, zero_row[0])),
                            np.concatenate((h, zero_row[1])), relax=True, compiled=compiled)
    alone = solve_local_qps(*one, np.zeros(1, int), *zero_row, relax=True, compiled=compiled)
    assert np.all(np.isfinite(batch.x)) and np.all(np.isfinite(batch.loosened))
    np.testing.assert_array_equal(batch.x[n], alone.x[0])
    assert batch.loosened[-1] == alone.loosened[0] == pytest.approx(1.0 + 1e-6)
    ref = solve_local_qps(H, g, lb, ub, owner, G, h, relax=True, compiled=compiled)
    np.testing.assert_array_equal(batch.x[:n], ref.x)  # and the others their own


def _unique_multipliers(H, g, lb, ub, owner, G, h, sol):
    """``(N,)`` bool: the robot's multipliers are unique (at most two constraints active, their normals independent);
    elsewhere (duplicate rows, rows through a vertex) any valid ones are an answer."""
    n = H.shape[0]
    x, hh = sol.x, h + sol.loosened
    act = np.abs((G * x[owner]).sum(axis=1) - hh) <= 1e-9 * (1 + np.abs(hh))
    at_box = (np.abs(x - lb) <= 1e-12) | (np.abs(x - ub) <= 1e-12)
    unique = np.bincount(owner[act], minlength=n) + at_box.sum(axis=1) <= 2
    for k in np.flatnonzero(unique):
        normals = [G[r] / np.linalg.norm(G[r]) for r in np.flatnonzero(act & (owner == k))]
        normals += [np.eye(2)[i] for i in np.flatnonzero(at_box[k])]
        if len(normals) == 2 and abs(normals[0][0] * normals[1][1] - normals[0][1] * normals[1][0]) < 1e-6:
            unique[k] = False
    return unique


@needs_numba
@pytest.mark.parametrize("relax", [False, True])
def test_the_compiled_local_solver_makes_the_numpy_solvers_decisions(relax):
    """Same feasibility and loosened rows; the answers and their multipliers, where unique, to rounding (3,000 robots).

    The kernel projects by a dual active set, the reference line by line (:mod:`~aasoatt_env.safety.solvers.polygons`):
    without relaxation their answers agree to rounding.  A relaxation loosens the rows by the least violation, which
    the kernel's phase 1 (regula falsi, from its active set's last point) reaches to its stopping tolerance (about
    ``1e-7`` here) and the reference's (exact line minimiser, from the minimiser over the bounds) closer: to 1e-6.
    """
    for seed in (21, 22):
        args = _random_robots(1500, seed=seed)
        ref = solve_local_qps(*args, relax=relax)
        com = solve_local_qps(*args, relax=relax, compiled=True)
        np.testing.assert_array_equal(com.feasible, ref.feasible)
        assert (ref.iterations, ref.n_enumerated) == (0, 0)  # (the numpy path has neither)
        np.testing.assert_array_equal(com.loosened > 0, ref.loosened > 0)
        unique = _unique_multipliers(*args, ref)
        assert unique.sum() >= 1200
        if not relax:  # loosened rows may meet at one point, where which of them is active is arbitrary
            np.testing.assert_array_equal(com.lam[unique[args[4]]] > 0, ref.lam[unique[args[4]]] > 0)
            np.testing.assert_array_equal(com.lam_box[unique] > 0, ref.lam_box[unique] > 0)
        tol = 1e-6 if relax else 1e-12
        for a, b in ((com.x, ref.x), (com.lam[unique[args[4]]], ref.lam[unique[args[4]]]),
                     (com.lam_box[unique], ref.lam_box[unique]), (com.loosened, ref.loosened)):
            np.testing.assert_allclose(a, b, rtol=tol if relax else 0, atol=tol)


def test_the_kernels_constants_are_the_reference_solvers():
    kern = pytest.importorskip("aasoatt_env.safety.solvers.local_kernel")
    assert kern._PAD_B == local.PAD_B
    default = inspect.signature(polygons.least_violation).parameters["max_iter"].default
    assert kern._LV_ITERS == polygons.LV_ITERS == default


# ----------------------------------------------------------------------------- the decentralised step
def _scene(n, spacing=1.1, nominal=30.0, seed=0, obstacles=False):
    """A jittered grid moving in random directions (as ``benchmarks/bench_filter.py``), rows as the filter builds
    them (no deadlock strategy); optional disc obstacles between the robots."""
    rng = np.random.default_rng(seed)
    team = make_team("paper", n)
    side = int(np.ceil(np.sqrt(n)))
    grid = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)[:n] * spacing
    p = grid + rng.uniform(-0.02, 0.02, grid.shape)
    theta = rng.uniform(-np.pi, np.pi, n)
    pose = pose_from_point(team, p, theta)
    u = rng.uniform(2, 8, (n, 1)) * np.ones((1, 2)) + rng.normal(0, 0.5, (n, 2))
    kin = kinematics(team, pose, u)
    lo, hi = input_bounds(team, u, 0.005)
    nom = rng.uniform(-nominal, nominal, (n, 2))
    cfg = FilterConfig(deadlock="none")
    pv, v, A, adot = kin.p, kin.v, kin.A, kin.adot_u
    pr = robot_pairs(pv, cfg.sensing_range)
    ri, rj = pr[:, 0], pr[:, 1]
    rad, amax = team.radius, team.max_point_accel
    gp, gv, ga = pv[ri] - pv[rj], v[ri] - v[rj], adot[ri] - adot[rj]
    ds, ap = rad[ri] + rad[rj], amax[ri] + amax[rj]
    if obstacles:
        oc = grid[: max(1, n // 10)] + spacing / 2
        d = np.linalg.norm(pv[:, None] - oc[None], axis=2) - 0.2
        oi, ok = np.nonzero(d <= cfg.sensing_range)
        gp = np.concatenate((gp, pv[oi] - oc[ok]))
        gv, ga = np.concatenate((gv, v[oi])), np.concatenate((ga, adot[oi]))
        ds = np.concatenate((ds, rad[oi] + 0.2))
        ap = np.concatenate((ap, amax[oi]))
        ri, rj = np.concatenate((ri, oi)), np.concatenate((rj, np.full(oi.size, -1)))
    sp2 = np.einsum("ij,ij->i", v, v)
    margin = cfg.pair_margin(gv) + cfg.speed_margin * (sp2[ri] + np.where(rj >= 0, sp2[np.maximum(rj, 0)], 0.0))
    c, rhs, keep = barrier_rows(cfg.barrier, PairGeometry(ri, rj, gp, gv, ga, ds + margin, ds, ap), cfg)
    ri, rj = ri[keep], rj[keep]
    Gi = np.einsum("pki,pk->pi", A[ri], c)
    Gj = -np.einsum("pki,pk->pi", A[np.maximum(rj, 0)], c)
    target = np.einsum("nij,nj->ni", A, nom)
    return team, A, target, lo, hi, ri, rj, Gi, Gj, rhs


@pytest.mark.parametrize("split", ["authority", "reciprocal"])
def test_split_rows_add_up_to_the_pair_rows(split):
    team, A, target, lo, hi, ri, rj, Gi, Gj, rhs = _scene(60, obstacles=True)
    auth = team.max_point_accel * np.linspace(0.5, 2.0, team.n)  # unequal authorities
    du0 = box_least_squares(A, target, lo, hi) if split == "reciprocal" else None
    sp = split_rows(ri, rj, Gi, Gj, rhs, auth, du0)
    m = rhs.size
    obs = rj < 0
    assert obs.any() and (~obs).any()
    assert sp.owner.size == m + int((~obs).sum())
    hs = np.zeros(m)
    np.add.at(hs, sp.row_side(np.arange(sp.owner.size))[0], sp.h)
    np.testing.assert_allclose(hs, rhs, rtol=1e-12, atol=1e-12)
    row, side = sp.row_side(np.arange(sp.owner.size))
    np.testing.assert_array_equal(sp.owner, np.where(side == 0, ri[row], rj[row]))
    np.testing.assert_array_equal(sp.G, np.where(side[:, None] == 0, Gi[row], Gj[row]))
    # shares follow authority; obstacle rows whole
    i_half = side == 0
    rr = i_half & ~obs[row]
    share = auth[ri[row[rr]]] / (auth[ri[row[rr]]] + auth[rj[row[rr]]])
    if du0 is None:  # rhs split
        np.testing.assert_allclose(sp.h[rr], rhs[row[rr]] * share)
    else:  # the nominal pair's correction split: h_i = Gi du0_i - share * (Gi du0_i + Gj du0_j - rhs)
        gi0 = np.einsum("pi,pi->p", Gi, du0[ri])
        gj0 = np.einsum("pi,pi->p", Gj, du0[np.maximum(rj, 0)])
        v = gi0 + gj0 - rhs
        np.testing.assert_allclose(sp.h[rr], gi0[row[rr]] - share * v[row[rr]],
                                   rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(sp.h[i_half & obs[row]], rhs[row[i_half & obs[row]]], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("split", ["authority", "reciprocal"])
@pytest.mark.parametrize(("n", "spacing", "nominal"), [(64, 1.1, 30.0), (100, 2.0, 3.0)])
def test_each_robot_answer_equals_dense_solver_on_its_own_qp(n, spacing, nominal, split):
    team, A, target, lo, hi, ri, rj, Gi, Gj, rhs = _scene(n, spacing, nominal, obstacles=True)
    auth = team.max_point_accel
    res = decentralized_step(A, target, lo, hi, ri, rj, Gi, Gj, rhs, auth, split=split)
    du0 = box_least_squares(A, target, lo, hi) if split == "reciprocal" else None
    sp = split_rows(ri, rj, Gi, Gj, rhs, auth, du0)
    scale = np.max(np.maximum(np.abs(lo), np.abs(hi)), axis=1)
    rows_k = [np.flatnonzero(sp.owner == k) for k in range(n)]
    for k in range(n):
        r = rows_k[k]
        Hk, gk = 2 * A[k].T @ A[k], -2 * A[k].T @ target[k]
        ref = _qp_ref(Hk, gk, lo[k], hi[k], sp.G[r], sp.h[r])
        assert res.infeasible[k] == (ref is None), k
        if ref is None:  # least violation of its own rows, then its QP over the loosened rows
            nrm = np.linalg.norm(sp.G[r], axis=1)
            s = _phase1_ref(lo[k] / scale[k], hi[k] / scale[k], sp.G[r] * scale[k], sp.h[r])
            ref = _qp_ref(Hk, gk, lo[k], hi[k], sp.G[r], sp.h[r] + s * nrm * scale[k] * (1 + 1e-6)
                          + RELAX_TOL * nrm * scale[k])
            assert ref is not None
        assert np.max(np.abs(res.du[k] - ref[0])) <= 1e-6 * scale[k], k
        # multipliers in the centralised filter's units (du, objective |A du - target|^2)
        row, side = sp.row_side(r)
        np.testing.assert_allclose(res.eta_half[row, side], ref[1], atol=1e-6 * (1 + np.abs(ref[1]).max()))
    assert res.n_relaxed == int(res.infeasible.sum())
    if spacing > 1.5:
        assert res.n_relaxed == 0 and res.slack == 0.0
        # every pair row holds: the halves add up
        du = res.du
        lhs = np.einsum("pi,pi->p", Gi, du[ri]) + np.where(rj >= 0, np.einsum("pi,pi->p", Gj, du[np.maximum(rj, 0)]),
                                                            0.0)
        assert np.all(lhs <= rhs + 1e-9 * (1 + np.abs(rhs)))
    else:
        assert res.n_relaxed > 0 and res.slack > 0.0  # the packed grid: halving rows boxes robots in
    assert np.all((res.du >= lo) & (res.du <= hi))


@pytest.mark.parametrize("split", ["authority", "reciprocal"])
def test_infeasible_robot_reported_and_relaxed(split):
    """A robot squeezed between two neighbours that both demand it back off: its own QP is empty."""
    A = np.broadcast_to(0.05 * np.array([[1.0, 1.0], [1.0, -1.0]]), (3, 2, 2)).copy()
    lo, hi = -60 * np.ones((3, 2)), 60 * np.ones((3, 2))
    target = np.zeros((3, 2))
    # rows c'(w_i - w_j) <= rhs: robot 1 in the middle, c = -p_ij along x
    ri, rj = np.array([0, 1]), np.array([1, 2])
    c = np.array([[1.0, 0.0], [1.0, 0.0]])
    Gi, Gj = np.einsum("pki,pk->pi", A[ri], c), -np.einsum("pki,pk->pi", A[rj], c)
    rhs = np.array([-8.0, -8.0])  # each pair must open at 8 m/s^2 (each robot reaches 6 m/s^2 along x)
    res = decentralized_step(A, target, lo, hi, ri, rj, Gi, Gj, rhs, np.ones(3), split=split)
    assert list(res.infeasible) == [False, True, False]
    assert res.n_relaxed == 1 and res.slack > 0
    assert np.all((res.du >= lo) & (res.du <= hi))
    assert res.eta[0] > 0 and res.eta[1] > 0
    # the outer robots take their own halves exactly
    w = np.einsum("nij,nj->ni", A, res.du)
    assert w[0, 0] == pytest.approx(-4.0) and w[2, 0] == pytest.approx(4.0)
    # robot 1 is pulled both ways: its least-violation answer splits the difference
    assert w[1, 0] == pytest.approx(0.0, abs=1e-6)


def test_eta_in_centralised_units_for_a_lone_robot():
    """One robot and an obstacle row: the local QP is the centralised QP, so the multipliers agree."""
    A = np.array([[[0.05, 0.05], [0.1, -0.1]]])
    target = np.array([[3.0, 1.0]])
    lo, hi = -60 * np.ones((1, 2)), 60 * np.ones((1, 2))
    Gi = np.array([[0.05, 0.1]]) @ A[0]
    rhs = np.array([0.2])
    res = decentralized_step(A, target, lo, hi, np.array([0]), np.array([-1]), Gi, np.zeros((1, 2)), rhs,
                             np.ones(1))
    scale = np.array([60.0])
    prob = build_problem(A, target, lo, hi, scale, np.array([0]), np.array([-1]), Gi, np.zeros((1, 2)), rhs)
    x, _, _, _, lag, _ = quadprog.solve_qp(prob.H_dense(), -prob.g, -prob.C.toarray().T, -prob.u, 0)
    np.testing.assert_allclose(res.du[0], x * scale, atol=1e-8)
    eta_c = prob.obj_scale * lag / prob.row_norm
    assert eta_c[0] > 0
    np.testing.assert_allclose(res.eta, eta_c, rtol=1e-6)
    np.testing.assert_allclose(res.z, lag, rtol=1e-6)  # normalised as the filter's z


# ----------------------------------------------------------------------------- negotiation groups
def test_negotiation_rows_are_the_rows_among_the_triggered_robots_and_those_they_touch():
    # a row of robots 1.01 m apart (gap 0.05) but 3-4 (gap 0.3); robots 6-7 touch far away
    x = np.array([0.0, 1.01, 2.02, 3.03, 4.34, 10.0, 20.0, 21.01])
    p = np.stack((x, np.zeros(8)), axis=1)
    radius = np.full(8, 0.48)
    ri = np.array([0, 1, 0, 2, 3, 6, 1, 0, 1])
    rj = np.array([1, 2, 2, 3, 4, 7, -1, 3, 3])  # (an obstacle row, 1 -1, is never whole)
    triggered = np.zeros(8, bool)
    triggered[1] = True
    # robot 1 and the robots it touches (0, 2) negotiate: rows 0-1, 1-2 and 0-2 (not touching) whole; robot 3
    # touches robot 2, which is not triggered: 2-3, 0-3 and 1-3 stay split; 3-4, 6-7 have no triggered robot
    want = [True, True, True, False, False, False, False, False, False]
    assert list(negotiation_rows(triggered, p, radius, ri, rj, 0.1)) == want
    # with a 0.4 m touching gap robot 1 touches nobody new; with 1.2 m it touches 3 (gap 1.06): 2-3, 0-3, 1-3 too
    assert list(negotiation_rows(triggered, p, radius, ri, rj, 0.4)) == want
    with_3 = [True, True, True, True, False, False, False, True, True]
    assert list(negotiation_rows(triggered, p, radius, ri, rj, 1.2)) == with_3
    triggered[3] = True  # 3 negotiates itself; 3-4 (gap 0.35) still not
    assert list(negotiation_rows(triggered, p, radius, ri, rj, 0.1)) == with_3
    assert not negotiation_rows(np.zeros(8, bool), p, radius, ri, rj, 5.0).any()


def _group_reference(A, target, lo, hi, ri, rj, Gi, Gj, rhs, auth, whole):
    """The negotiation groups' answer by quadprog: the ``whole`` rows whole, the grouped robots' halves of the rest."""
    du0 = box_least_squares(A, target, lo, hi)
    sp = split_rows(ri, rj, Gi, Gj, rhs, auth, du0)
    m = rhs.size
    grouped = np.zeros(A.shape[0], bool)
    grouped[ri[whole]] = grouped[rj[whole]] = True
    sub = np.flatnonzero(grouped)
    at = {r: k for k, r in enumerate(sub)}
    nv = 2 * sub.size
    H = np.zeros((nv, nv))
    q = np.zeros(nv)
    for k, r in enumerate(sub):
        H[2 * k:2 * k + 2, 2 * k:2 * k + 2] = 2 * A[r].T @ A[r]
        q[2 * k:2 * k + 2] = 2 * A[r].T @ target[r]
    C, b = [], []
    for r in np.flatnonzero(whole):
        row = np.zeros(nv)
        row[2 * at[ri[r]]:2 * at[ri[r]] + 2] -= Gi[r]
        row[2 * at[rj[r]]:2 * at[rj[r]] + 2] -= Gj[r]
        C.append(row)
        b.append(-rhs[r])
    row_of, _ = sp.row_side(np.arange(sp.owner.size))
    for h in np.flatnonzero(grouped[sp.owner] & ~whole[row_of]):
        row = np.zeros(nv)
        row[2 * at[sp.owner[h]]:2 * at[sp.owner[h]] + 2] = -sp.G[h]
        C.append(row)
        b.append(-sp.h[h])
    for k, r in enumerate(sub):
        for d in range(2):
            e = np.zeros(nv)
            e[2 * k + d] = 1.0
            C += [e, -e]
            b += [lo[r, d], -hi[r, d]]
    x = quadprog.solve_qp(H, q, np.array(C).T, np.array(b), 0)[0]
    assert m == rhs.size
    return grouped, sub, x.reshape(-1, 2), whole


@both
def test_negotiation_groups_answer_their_rows_whole_as_a_dense_solver_does(compiled):
    from aasoatt_env.model.geometry import pair_components
    from aasoatt_env.safety.solvers import SolverPolicy

    # a grid 1.4 m apart under large nominals: rows bind, some lone robots' own QPs are infeasible
    team, A, target, lo, hi, ri, rj, Gi, Gj, rhs = _scene(100, 1.4, 30.0, seed=1, obstacles=True)
    auth = team.max_point_accel
    # three patches of the grid negotiate: every robot row among robots 0-2 and 10-12 (one group), 55-56, and
    # an obstacle row of robot 99 (never whole)
    patch = np.zeros(100, bool)
    patch[[0, 1, 2, 10, 11, 12, 55, 56, 99]] = True
    whole = patch[ri] & patch[np.maximum(rj, 0)]
    assert (whole & (rj < 0)).any()
    # the filter's settings for its groups
    policy = SolverPolicy("proxsuite", active_set=True, compiled=compiled)
    res = decentralized_step(A, target, lo, hi, ri, rj, Gi, Gj, rhs, auth, compiled=compiled, whole=whole,
                             policy=policy)
    alone = decentralized_step(A, target, lo, hi, ri, rj, Gi, Gj, rhs, auth, compiled=compiled)
    grouped, sub, ref, whole = _group_reference(A, target, lo, hi, ri, rj, Gi, Gj, rhs, auth, whole & (rj >= 0))
    assert whole.any() and grouped.sum() == 8
    np.testing.assert_array_equal(res.grouped, grouped)
    assert res.group_status == "solved"
    assert (res.z_half[whole] > 1e-6).any()  # the group's rows bind: its QP is solved, not its robots' box answers
    scale = np.max(np.maximum(np.abs(lo), np.abs(hi)), axis=1)
    assert np.max(np.abs(res.du[sub] - ref) / scale[sub, None]) <= 1e-6
    # every other robot: its own QP's answer, as without groups (some of them relaxed)
    np.testing.assert_array_equal(res.du[~grouped], alone.du[~grouped])
    assert res.n_relaxed == int((alone.infeasible & ~grouped).sum()) > 0
    assert not res.infeasible[grouped].any()
    # the groups: components of the whole rows
    lab = pair_components(sub.size, np.searchsorted(sub, ri[whole]), np.searchsorted(sub, rj[whole]))
    sizes = np.bincount(lab)
    assert res.n_groups == int((sizes >= 2).sum()) and res.largest_group == int(sizes.max())
    # the whole rows hold jointly; a binding whole row marks both of its robots (the deadlock memory reads z_half)
    du = res.du
    lhs = np.einsum("pi,pi->p", Gi, du[ri]) + np.where(rj >= 0, np.einsum("pi,pi->p", Gj, du[np.maximum(rj, 0)]),
                                                        0.0)
    assert np.all(lhs[whole] <= rhs[whole] + 1e-7 * (1 + np.abs(rhs[whole])))
    np.testing.assert_array_equal(res.z_half[whole, 0], res.z_half[whole, 1])
    # warm-started from this answer (as the filter does at the next step): the same optimum
    warm = decentralized_step(A, target, lo, hi, ri, rj, Gi, Gj, rhs, auth, compiled=compiled, whole=whole | (
        patch[ri] & (rj < 0)), policy=policy, x_warm=res.du / scale[:, None], z_warm=res.z)
    assert np.max(np.abs(warm.du[sub] - ref) / scale[sub, None]) <= 1e-6


def test_negotiation_needs_its_solver():
    team, A, target, lo, hi, ri, rj, Gi, Gj, rhs = _scene(9, 2.0, 3.0)
    with pytest.raises(ValueError, match="policy"):
        decentralized_step(A, target, lo, hi, ri, rj, Gi, Gj, rhs, team.max_point_accel, whole=rj >= 0)


def test_without_triggered_robots_negotiation_changes_nothing():
    """The default deadlock strategy, a step where nobody is triggered yet (the first): the step is the per-robot
    one, bit for bit, every field; a later step of the same crowd with robots triggered does negotiate."""
    from aasoatt_env.safety.core import SafetyFilter

    rng = np.random.default_rng(4)
    team = make_team("paper", 30)
    p = np.stack(np.meshgrid(np.arange(6), np.arange(5)), -1).reshape(-1, 2)[:30] * 1.05
    pose = pose_from_point(team, p + rng.uniform(-0.02, 0.02, p.shape), rng.uniform(-np.pi, np.pi, 30))
    u = rng.uniform(2, 8, (30, 2))
    kin = kinematics(team, pose, u)
    lo, hi = input_bounds(team, u, 0.005)
    nom = rng.uniform(-30, 30, (30, 2))
    ref = (kin.p + rng.uniform(-3, 3, (30, 2)), rng.uniform(-1, 1, (30, 2)))
    filters = [SafetyFilter(team, mode="decentralized", negotiate=negotiate) for negotiate in (True, False)]
    outs = [f.step(kin, u, pose[:, 2], nom, lo, hi, reference=ref)[1] for f in filters]
    assert not outs[0].triggered.any()
    for name in ("du", "eta", "avoiding", "backup", "correction", "pairs"):
        np.testing.assert_array_equal(getattr(outs[0], name), getattr(outs[1], name), err_msg=name)
    for name in ("status", "message", "slack", "margin", "iterations", "n_rows", "n_qp_rows"):
        assert getattr(outs[0], name) == getattr(outs[1], name), name
    second = filters[0].step(kin, u, pose[:, 2], nom, lo, hi, reference=ref)[1]
    assert second.triggered.any() and "negotiation group" in second.message


@pytest.mark.parametrize(("kw", "match"), [({"negotiate_gap": -0.1}, "negotiate_gap"),
                                           ({"negotiate_gap": 5.0}, "negotiate_gap"),
                                           ({"negotiate": "yes"}, "negotiate")])
def test_negotiation_options_are_validated(kw, match):
    from aasoatt_env.errors import ConfigError

    with pytest.raises(ConfigError, match=match):
        FilterConfig(mode="decentralized", **kw)


# ----------------------------------------------------------------------------- the filter's decentralised mode
def test_mode_is_validated():
    from aasoatt_env.errors import ConfigError

    with pytest.raises(ConfigError, match="mode.*decentralized"):
        FilterConfig(mode="distributed")


def _run(n: int, agent, steps: int, seed: int = 0, scenario: str = "circle_swap", **kw):
    from aasoatt_env import make_env
    from aasoatt_env.analysis.metrics import pairwise_min_distance
    from aasoatt_env.analysis.recording import run_episode

    env = make_env(scenario=scenario, num_robots=n, filter=FilterConfig(mode="decentralized"), max_steps=steps, **kw)
    ro, _ = run_episode(env, agent, seed=seed)
    return ro, pairwise_min_distance(ro).overall_min_robot_gap


def test_wrapper_runs_the_local_qps_and_reports_them():
    from aasoatt_env import make_env
    from agents import TrackingController

    env = make_env(scenario="circle_swap", num_robots=8, filter={"mode": "decentralized"}, infos="nested")
    obs, _ = env.reset(seed=0)
    ctrl = TrackingController()
    ctrl.reset(env)
    for _ in range(5):
        obs, _, _, _, infos = env.step(ctrl.act(obs, env))
    f = infos["robot_0"]["filter"]
    assert f["status"] in ("solved", "relaxed", "backup")
    assert env.unwrapped.positions.shape == (8, 2)


@pytest.mark.slow
def test_closed_loop_circle_home_without_collision():
    """Radius-6 circle, 20 robots, the paper's tracking controller: everyone home, no pair closer than d_s."""
    from agents import TrackingController

    ro, gap = _run(20, TrackingController(), steps=3000, settle_time=3.0)
    err = np.linalg.norm(ro.positions[-1] - ro.goals, axis=1)
    assert gap >= -1e-9
    assert err.max() <= 0.05, err.max()


def _home(negotiate: bool, seed: int = 0, **kw):
    """Robots home (within 5 cm) and the closest pair gap of one tracking-controller episode, decentralised."""
    from aasoatt_env import make_env
    from aasoatt_env.analysis.metrics import pairwise_min_distance
    from aasoatt_env.analysis.recording import run_episode
    from agents import TrackingController

    env = make_env(filter=FilterConfig(mode="decentralized", negotiate=negotiate), **kw)
    ro, _ = run_episode(env, TrackingController(), seed=seed)
    err = np.linalg.norm(ro.positions[-1] - ro.goals, axis=1)
    return int((err <= 0.05).sum()), pairwise_min_distance(ro).overall_min_robot_gap


def test_negotiation_frees_a_crowd_the_split_rows_stop():
    """8 robots in a 4.5 m arena with 2 obstacles: with split rows alone robots stop against each other short of
    their goals; the negotiation groups get every robot home, and no pair comes closer than d_s either way."""
    scene = dict(scenario="random_goals", num_robots=8, arena_size=4.5, random_obstacles=2, settle_time=6.0)
    home, gap = _home(True, **scene)
    alone, gap_alone = _home(False, **scene)
    assert home == 8 and alone < 8, (home, alone)
    assert gap >= -1e-9 and gap_alone >= -1e-9


def test_the_groups_solver_gets_their_budget(monkeypatch):
    """The decentralised mode's policy (its negotiation groups') has GROUP_ONE_CHANGE_ITER, the centralised mode's
    the default; along a crowded episode with groups every warm active set of a group runs with that budget
    (compiled decomposition or policy)."""
    from aasoatt_env import make_env
    from aasoatt_env.safety import centralized, core
    from aasoatt_env.safety.decentralized import GROUP_ONE_CHANGE_ITER
    from aasoatt_env.safety.solvers import active_set, policy
    from agents import TrackingController

    made = []

    class Spy(policy.SolverPolicy):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            made.append(self.one_change_iter)

    monkeypatch.setattr(core, "SolverPolicy", Spy)
    budgets = []
    real_budget, real_parts = active_set.one_change_budget, policy.solve_active_set_parts
    monkeypatch.setattr(centralized.aset, "one_change_budget", lambda v: budgets.append(v) or real_budget(v))
    monkeypatch.setattr(policy, "solve_active_set_parts",
                        lambda *a, **k: budgets.append(k.get("one_change_iter")) or real_parts(*a, **k))
    env = make_env("random_goals", num_robots=8, arena_size=4.5, random_obstacles=2,
                   filter=FilterConfig(mode="decentralized"), max_steps=600)
    obs, _ = env.reset(seed=0)
    agent, grouped = TrackingController(), 0
    for _ in range(600):
        obs, *_ = env.step(agent.act(obs, env))
        grouped += "negotiation group" in env.unwrapped.filter_outputs[-1].message
    assert made[-1] == GROUP_ONE_CHANGE_ITER
    assert grouped > 10 and budgets and set(budgets) == {GROUP_ONE_CHANGE_ITER}, (grouped, set(budgets))
    make_env("random_goals", num_robots=4, filter=FilterConfig(mode="centralized"))
    assert made[-1] is None


@pytest.mark.slow
@pytest.mark.parametrize(("n", "radius", "duration"), [(39, 6.0, 12.0), (60, 10.0, 20.0)])
def test_the_paper_circles_get_home_decentralised(n, radius, duration):
    """The paper's circle swaps (radius 6 m with 39 robots, radius 10 m with 60), 3 s of settling: every robot home."""
    home, gap = _home(True, scenario="circle_swap", num_robots=n, radius=radius, duration=duration, settle_time=3.0)
    assert home == n and gap >= -1e-9


@pytest.mark.slow
@pytest.mark.parametrize("adversary", ["spin_up", "burst", "chase_nearest"])
def test_adversaries_do_not_collide(adversary):
    from agents import ADVERSARIES

    cls = ADVERSARIES[adversary]
    try:
        agent = cls(seed=3)
    except TypeError:
        agent = cls()
    ro, gap = _run(12, agent, steps=600, seed=3, scenario="random_goals")
    assert np.all(np.isfinite(ro.positions))
    assert gap >= -1e-9, gap


@needs_numba
def test_the_groups_compiled_solve_waits_for_a_warm_answer_and_changes_no_bit(monkeypatch):
    """The negotiation groups' compiled solve is tried only after a step the warm active set answered whole (after one
    the solvers' route answered it fails again); spin-up robots' infeasible groups give the same steps bit for bit as
    when it is tried at every step."""
    from aasoatt_env import make_env
    from aasoatt_env.compiled import kernels
    from aasoatt_env.safety import decentralized as dec
    from agents import ADVERSARIES

    kernel, step = kernels("centralized"), dec.decentralized_step

    def run(always: bool) -> tuple[list, list]:
        real, codes, out = kernel.solve_decomposed, [], []

        def counted(*args):
            codes.append((len(out), int(real(*args)[0])))
            return real(*args)

        def stepped(*args, **kw):
            kw["try_compiled"] = kw["try_compiled"] or always
            return step(*args, **kw)

        monkeypatch.setattr(kernel, "solve_decomposed", counted)
        monkeypatch.setattr(dec, "decentralized_step", stepped)
        env = make_env("random_goals", num_robots=8, max_steps=300, decision_interval=1,
                       filter={"mode": "decentralized"})
        agent = ADVERSARIES["spin_up"]()
        obs, _ = env.reset(seed=5158)
        for _ in range(env.max_steps):
            obs, *_ = env.step(agent.act(obs, env))
            out.append((env.last_result.du.copy(), env.last_result.message, env.last_result.eta.copy()))
        monkeypatch.undo()
        return out, codes

    ref, ref_codes = run(always=True)
    out, codes = run(always=False)
    for (du_a, msg_a, eta_a), (du_b, msg_b, eta_b) in zip(out, ref):
        assert msg_a == msg_b
        np.testing.assert_array_equal(du_a.view(np.int64), du_b.view(np.int64))
        np.testing.assert_array_equal(eta_a.view(np.int64), eta_b.view(np.int64))
    failed = [k for k, code in ref_codes if code < 0]
    assert len(failed) > 100 and len(codes) < len(ref_codes) - 100
    tried = {k for k, _ in codes}
    assert not [k for k, code in codes if code < 0 and k + 1 in tried]  # (after a failure the route answered)
