"""Benchmark the safety-filter step (rows + solve) against cvxopt and OSQP on the same rows.

Congested moment: a random packed layout (jittered grid, spacing 1.1 m, robots
moving at ~0.5-1 m/s in random directions, nominal = random accelerations), so
every robot has many neighbours inside D = 3 m.  For N <= 39 the circle swap
(R = 6) snapshot near the centre crossing is timed as well.

Columns (medians, one core):
  step      SafetyFilter.step with FilterConfig(active_set=True), repeated on the same
            state: the warm active-set path (qp.solve_active_set) is taken; this is its
            best case (in the 39-robot closed loop it was 2.3x *slower* than no-AS,
            which is why it is off by default)
  no-AS     the default SafetyFilter.step (proxsuite, cold each step)
  prox      proxsuite solve only (same canonical QP)
  cvxopt    Robotarium-style cvxopt.solvers.qp on the same QP (solve only)
  osqp      OSQP on the same QP (solve only, polished, eps 1e-7)

Usage: python benchmarks/bench_filter.py [--quick]
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402

import aasoatt_env.safety.core as core  # noqa: E402
from aasoatt_env.dynamics import input_bounds, kinematics, pose_from_point  # noqa: E402
from aasoatt_env.params import make_team  # noqa: E402
from aasoatt_env.safety import SafetyFilter, solve_qp  # noqa: E402
from aasoatt_env.safety.scenario import CircleSwap, rollout  # noqa: E402


def packed(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    team = make_team("paper", n)
    side = int(np.ceil(np.sqrt(n)))
    g = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)[:n] * 1.1
    p = g + rng.uniform(-0.02, 0.02, g.shape)
    theta = rng.uniform(-np.pi, np.pi, n)
    pose = pose_from_point(team, p, theta)
    u = rng.uniform(2, 8, (n, 1)) * np.ones((1, 2)) + rng.normal(0, 0.5, (n, 2))
    kin = kinematics(team, pose, u)
    lo, hi = input_bounds(team, u, 0.005)
    nom = rng.uniform(-30, 30, (n, 2))
    return team, (kin, u, theta, nom, lo, hi, None)


def circle_snapshot(n: int):
    scen = CircleSwap(n)
    out = rollout(scen, SafetyFilter(scen.team), 5.6, record=lambda k: k == 1100)
    return scen.team, out.snapshots[0]


def cvxopt_solve(prob):
    import cvxopt

    cvxopt.solvers.options["show_progress"] = False
    n = prob.n
    H = prob.H_sparse().tocoo()
    P = cvxopt.spmatrix(H.data, H.row.astype(int), H.col.astype(int), (n, n))
    G = sp.vstack((prob.C, sp.identity(n), -sp.identity(n))).tocoo()
    Gm = cvxopt.spmatrix(G.data, G.row.astype(int), G.col.astype(int), G.shape)
    h = cvxopt.matrix(np.concatenate((prob.u, prob.ub, -prob.lb)))
    return cvxopt.solvers.qp(P, cvxopt.matrix(prob.g), Gm, h)


def timed(fn, reps):
    ts = []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts))


def bench(label, team, snap, reps, with_cvxopt):
    kin, u, theta, nom, lo, hi, ref = snap
    f = SafetyFilter(team, deadlock="none" if ref is None else "auxiliary_velocity")
    probs = []
    real = core.solve_qp

    def spy(prob, *a, **k):
        probs.append(prob)
        return real(prob, *a, **k)

    core.solve_qp = spy
    _, res = f.step(kin, u, theta, nom, lo, hi, reference=ref)
    core.solve_qp = real
    prob = probs[-1]
    f_as = SafetyFilter(team, deadlock=f.config.deadlock, active_set=True)
    f_as.step(kin, u, theta, nom, lo, hi, reference=ref)
    t_step = timed(lambda: f_as.step(kin, u, theta, nom, lo, hi, reference=ref), reps)
    t_old = timed(lambda: f.step(kin, u, theta, nom, lo, hi, reference=ref), max(1, reps // 3))
    t_prox = timed(lambda: solve_qp(prob, "proxsuite"), reps)
    t_cvx = timed(lambda: cvxopt_solve(prob), max(1, reps // 3)) if with_cvxopt else float("nan")
    t_osqp = timed(lambda: solve_qp(prob, "osqp"), max(1, reps // 3))
    return label, team.n, res.n_rows, res.status, t_step, t_old, t_prox, t_cvx, t_osqp


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer sizes and repetitions")
    args = ap.parse_args()
    sizes = [10, 39, 100, 300] if args.quick else [10, 39, 100, 300, 1000]
    reps = 5 if args.quick else 21
    rows = []
    for n in (10, 39):
        rows.append(bench("circle", *circle_snapshot(n), reps, True))
    for n in sizes:
        rows.append(bench("packed", *packed(n), reps if n <= 300 else max(3, reps // 4), n <= 300 or not args.quick))
    ms = 1e3
    print(f"{'scene':7s} {'N':>5s} {'rows':>6s} {'status':>8s} {'step ms':>9s} {'no-AS ms':>9s} {'noAS/step':>9s} "
          f"{'prox ms':>9s} {'cvxopt ms':>10s} {'osqp ms':>9s} {'cvx/step':>9s} {'osqp/step':>10s}")
    for lab, n, m, st, a, o, b, c, d in rows:
        print(f"{lab:7s} {n:5d} {m:6d} {st:>8s} {a * ms:9.2f} {o * ms:9.2f} {o / a:9.1f} {b * ms:9.2f} {c * ms:10.2f} "
              f"{d * ms:9.2f} {c / a:9.1f} {d / a:10.1f}")


if __name__ == "__main__":
    main()
