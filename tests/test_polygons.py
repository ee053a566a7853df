"""The 2-variable QPs of both decentralised filters (:mod:`aasoatt_env.safety.solvers.polygons`), on numpy and torch.

Projections onto polygons of unit half-planes against a brute-force enumeration of every candidate (the point, its
projections onto each line, each pair of lines' vertex), empty polygons, parallel and duplicate lines, absent slots
(zero normals); the least violation of an empty polygon's rows against a dense solver.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from aasoatt_env.safety.solvers.polygons import FAR, least_violation, solve_polygons

TOL = 1e-10


def _random_polygons(n, seed):
    """``(t, nx, ny, b)``: random polygons of up to 7 lines (slots beyond a robot's count absent); kinds: generic,
    duplicate and parallel lines, lines through one vertex, empty (a gap between opposite lines, a triangle)."""
    rng = np.random.default_rng(seed)
    C = 7
    nx, ny, b = np.zeros((n, C)), np.zeros((n, C)), np.full((n, C), FAR)
    t = rng.normal(0.0, 2.0, (n, 2))
    for k in range(n):
        m = int(rng.integers(1, C + 1))
        ang = rng.uniform(0, 2 * np.pi, m)
        off = rng.normal(0.5, 0.8, m)
        kind = int(rng.integers(0, 5))
        if kind == 1 and m >= 3:  # a duplicate (scaled before normalising: rounding) and a parallel line
            ang[1], off[1] = ang[0], off[0]
            ang[2], off[2] = ang[0], off[0] + rng.choice([-0.3, 0.3])
        elif kind == 2 and m >= 3:  # three lines through one point
            p = rng.normal(0.0, 1.0, 2)
            off[:3] = np.cos(ang[:3]) * p[0] + np.sin(ang[:3]) * p[1]
        elif kind == 3 and m >= 2:  # opposite lines with a gap: empty
            ang[1], off[1] = ang[0] + np.pi, -off[0] - rng.uniform(0.2, 1.0)
        elif kind == 4 and m >= 3:  # an empty triangle
            ang[:3] = rng.uniform(0, 2 * np.pi) + np.array([0.0, 2 * np.pi / 3, 4 * np.pi / 3])
            off[:3] = -rng.uniform(0.05, 0.5, 3)
        g = np.stack((np.cos(ang), np.sin(ang)), axis=1) * rng.uniform(0.5, 2.0, (m, 1))
        nrm = np.linalg.norm(g, axis=1)
        slots = rng.permutation(C)[:m]  # (absent slots between the lines)
        nx[k, slots], ny[k, slots], b[k, slots] = g[:, 0] / nrm, g[:, 1] / nrm, off * nrm / nrm
    return t, nx, ny, b


def _brute_force(t, nx, ny, b):
    """Per robot the nearest feasible candidate (None: the polygon is empty)."""
    out = []
    for k in range(t.shape[0]):
        real = np.flatnonzero(b[k] < FAR)
        N, h, tk = np.stack((nx[k, real], ny[k, real]), axis=1), b[k, real], t[k]
        tol = TOL * (1.0 + np.abs(tk).max())
        cands = [tk] + [tk - (N[i] @ tk - h[i]) * N[i] for i in range(len(real))]
        for i, j in itertools.combinations(range(len(real)), 2):
            M = N[[i, j]]
            if abs(np.linalg.det(M)) > 1e-9:
                cands.append(np.linalg.solve(M, h[[i, j]]))
        feas = [c for c in cands if np.all(N @ c - h <= 10 * tol)]
        out.append(min(feas, key=lambda c: np.sum((c - tk) ** 2)) if feas else None)
    return out


def test_projections_are_the_brute_force_optima_with_valid_multipliers():
    t, nx, ny, b = _random_polygons(1500, seed=1)
    ans = solve_polygons(t, nx, ny, b)
    ref = _brute_force(t, nx, ny, b)
    empty = np.array([r is None for r in ref])
    np.testing.assert_array_equal(ans.feasible, ~empty)
    assert 100 <= empty.sum() <= 700
    w, mu = ans.w[~empty], ans.mu[~empty]
    np.testing.assert_allclose(w, np.stack([r for r in ref if r is not None]), rtol=0, atol=1e-9)
    # KKT: 2 (t - w) = sum mu_c n_c, mu >= 0, only on constraints through w, none on absent slots
    resid = 2 * (t[~empty] - w) - np.stack(((mu * nx[~empty]).sum(1), (mu * ny[~empty]).sum(1)), axis=1)
    assert np.abs(resid).max() <= 1e-9
    assert mu.min() >= -1e-12
    slack = nx[~empty] * w[:, 0:1] + ny[~empty] * w[:, 1:2] - b[~empty]
    assert np.all((mu == 0) | (np.abs(slack) <= 1e-9))
    assert np.all(ans.mu[empty] == 0) and np.all(mu[b[~empty] == FAR] == 0)


def test_duplicate_and_parallel_lines_and_absent_slots():
    """The same line four times (normals equal to rounding), a parallel one beyond it, absent slots between:
    the projection onto the line, its multiplier on one of the copies."""
    scale = np.array([1.0, 2.0, 0.3824, 0.1502, 1.0])
    g = np.array([0.81830053, 0.88874897]) * scale[:, None]
    h = 0.61273785 * scale
    h[4] = 2.0
    nrm = np.linalg.norm(g, axis=1)
    C = 8
    nx, ny, b = np.zeros((1, C)), np.zeros((1, C)), np.full((1, C), FAR)
    slots = [0, 2, 3, 5, 7]
    nx[0, slots], ny[0, slots], b[0, slots] = g[:, 0] / nrm, g[:, 1] / nrm, h / nrm
    t = np.array([[2.0, 1.0]])
    ans = solve_polygons(t, nx, ny, b)
    n0 = g[0] / nrm[0]
    expect = t[0] - (n0 @ t[0] - h[0] / nrm[0]) * n0
    assert ans.feasible[0]
    np.testing.assert_allclose(ans.w[0], expect, atol=1e-12)
    np.testing.assert_allclose(ans.mu[0].sum(), 2 * (n0 @ t[0] - h[0] / nrm[0]), rtol=1e-12)
    assert ans.mu[0, 7] == 0.0 and np.count_nonzero(ans.mu[0]) == 1
    # the parallel line moved inside the copies: the polygon is the half-plane beyond it
    b2 = b.copy()
    b2[0, 7] = h[0] / nrm[0] - 0.5
    np.testing.assert_allclose(solve_polygons(t, nx, ny, b2).w[0], expect - 0.5 * n0, atol=1e-12)
    # and facing the other way with a gap: empty
    nx2, ny2 = nx.copy(), ny.copy()
    nx2[0, 7], ny2[0, 7], b2[0, 7] = -n0[0], -n0[1], -h[0] / nrm[0] - 0.5
    bad = solve_polygons(t, nx2, ny2, b2)
    assert not bad.feasible[0] and np.all(bad.mu == 0)


def _phase1_ref(gx, gy, hh, lb, ub):
    """Least violations of unit rows over a box, by quadprog on the lifted QP (``x`` and a slack per row)."""
    quadprog = pytest.importorskip("quadprog")
    G = np.stack((gx, gy), axis=1)
    m = G.shape[0]
    Hq = np.eye(2 + m)
    Hq[:2, :2] *= 1e-9
    C = np.zeros((2 * m + 4, 2 + m))
    rhs = np.zeros(2 * m + 4)
    C[:m, :2], C[:m, 2:], rhs[:m] = -G, np.eye(m), -hh
    C[m:2 * m, 2:] = np.eye(m)
    C[2 * m:2 * m + 2, :2], rhs[2 * m:2 * m + 2] = np.eye(2), lb
    C[2 * m + 2:, :2], rhs[2 * m + 2:] = -np.eye(2), -ub
    xs = quadprog.solve_qp(Hq, np.zeros(2 + m), C.T, rhs, 0)[0]
    return np.maximum(G @ xs[:2] - hh, 0.0)


def test_least_violation_is_the_dense_solvers_from_any_start():
    rng = np.random.default_rng(4)
    P, K = 200, 6
    ang = rng.uniform(0, 2 * np.pi, (P, K))
    gx, gy, hh = np.cos(ang), np.sin(ang), rng.normal(-0.3, 0.5, (P, K))
    gx[:, -1], gy[:, -1], hh[:, -1] = 0.0, 0.0, FAR  # an absent slot
    lb, ub = -rng.uniform(0.2, 1.0, (P, 2)), rng.uniform(0.2, 1.0, (P, 2))
    starts = (np.zeros((P, 2)), lb, np.clip(rng.normal(0.0, 1.0, (P, 2)), lb, ub))
    answers = [least_violation(gx, gy, hh, lb, ub, x0) for x0 in starts]
    for x, viol in answers:
        assert np.all((x >= lb) & (x <= ub)) and viol[:, -1].max() == 0.0
        np.testing.assert_allclose(viol, answers[0][1], rtol=0, atol=1e-7)  # (its stopping tolerance)
    assert (answers[0][1].max(axis=1) > 1e-3).sum() > 50  # most are infeasible
    for k in range(0, P, 10):
        np.testing.assert_allclose(answers[0][1][k, :-1], _phase1_ref(gx[k, :-1], gy[k, :-1], hh[k, :-1], lb[k],
                                                                         ub[k]), rtol=0, atol=1e-7)


def test_torch_runs_the_same_code_to_rounding():
    torch = pytest.importorskip("torch")
    t, nx, ny, b = _random_polygons(600, seed=2)
    ref = solve_polygons(t, nx, ny, b)
    tt = torch.as_tensor(t, dtype=torch.float64).requires_grad_(True)
    out = solve_polygons(tt, *(torch.as_tensor(a) for a in (nx, ny, b)))
    np.testing.assert_array_equal(out.feasible.numpy(), ref.feasible)
    np.testing.assert_allclose(out.w.detach().numpy(), ref.w, rtol=0, atol=1e-12)
    np.testing.assert_allclose(out.mu.numpy(), ref.mu, rtol=0, atol=1e-12)
    # the projection's derivative: 1 inside, 0 across a vertex, the line's direction along a line
    out.w.sum().backward()
    assert torch.isfinite(tt.grad).all()
    inside = np.all(nx * t[:, 0:1] + ny * t[:, 1:2] - b <= 0, axis=1)
    np.testing.assert_array_equal(tt.grad.numpy()[inside], 1.0)
    rng = np.random.default_rng(3)
    P, K = 50, 5
    args = [rng.normal(size=(P, K)) for _ in range(3)]
    nrm = np.hypot(args[0], args[1])
    gx, gy, hh = args[0] / nrm, args[1] / nrm, args[2] - 1.0
    lb, ub, x0 = -np.ones((P, 2)), np.ones((P, 2)), np.zeros((P, 2))
    x, viol = least_violation(gx, gy, hh, lb, ub, x0)
    xt, vt = least_violation(*(torch.as_tensor(a) for a in (gx, gy, hh, lb, ub, x0)))
    np.testing.assert_allclose(vt.numpy(), viol, rtol=0, atol=1e-12)
    np.testing.assert_allclose(xt.numpy(), x, rtol=0, atol=1e-12)
