"""Benchmark the safety-filter step (rows + solve) against Robotarium-style cvxopt and OSQP filters.

Congested moment: a random packed layout (jittered grid, spacing 1.1 m, robots
moving at ~0.5-1 m/s in random directions, nominal = random accelerations of up
to 30 rad/s^2), so every robot has many neighbours inside D = 3 m and most
nominals violate a row.  "sparse": the same grid 2 m apart with gentle
nominals (rows present, few bind: the typical step of a spread-out team).
For N <= 39 the circle swap (R = 6) snapshot near the centre crossing is
timed as well.

Every column is a whole ``SafetyFilter.step`` (neighbour search, rows, QP
assembly, solve, result) on the same state and the same rows; medians over
repeated calls, one core:

  ours        the default filter (exact decomposition + proxsuite)
  whole QP    the same without decomposition (``decompose=False``): one QP for the team
  cvxopt      Robotarium-style: the whole team in one ``cvxopt.solvers.qp`` call
              (``solver="cvxopt", decompose=False``)
  osqp        OSQP, whole team, eps 1e-7 with polishing (``solver="osqp", decompose=False``)
  daqp        the default filter with DAQP instead of proxsuite (``solver="daqp"``)
  ldp         the default filter with the exact NNLS solver (``solver="ldp"``, proxsuite's
              fallback; dense, so only up to ``ldp.MAX_VARS`` variables: N <= 250)
  active set  ``active_set=True`` repeated on the same state: the warm active-set
              path's best case (opt-in; slower than the default in the 39-robot closed loop)
  qp rows     rows the QP saw after decomposition / all rows

Ratios are against ``ours`` in the same run.

Usage: python benchmarks/bench_filter.py [--quick]
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from aasoatt_env import make_env  # noqa: E402
from aasoatt_env.model.dynamics import input_bounds, kinematics, pose_from_point  # noqa: E402
from aasoatt_env.model.params import make_team  # noqa: E402
from aasoatt_env.safety import SafetyFilter  # noqa: E402
from aasoatt_env.safety.solvers import available_solvers  # noqa: E402
from aasoatt_env.safety.solvers.ldp import MAX_VARS as LDP_MAX_VARS  # noqa: E402
from agents import TrackingController  # noqa: E402


def packed(n: int, seed: int = 0, spacing: float = 1.1, nominal: float = 30.0):
    rng = np.random.default_rng(seed)
    team = make_team("paper", n)
    side = int(np.ceil(np.sqrt(n)))
    g = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)[:n] * spacing
    p = g + rng.uniform(-0.02, 0.02, g.shape)
    theta = rng.uniform(-np.pi, np.pi, n)
    pose = pose_from_point(team, p, theta)
    u = rng.uniform(2, 8, (n, 1)) * np.ones((1, 2)) + rng.normal(0, 0.5, (n, 2))
    kin = kinematics(team, pose, u)
    lo, hi = input_bounds(team, u, 0.005)
    nom = rng.uniform(-nominal, nominal, (n, 2))
    return team, (kin, u, theta, nom, lo, hi, None)


class _Capture:
    """A control filter that runs the default ``SafetyFilter`` and keeps its inputs at one physics step."""

    keeps_input_bounds = True

    def __init__(self, at_step: int) -> None:
        self.inner, self.at, self.k, self.snapshot = SafetyFilter(), at_step, 0, None

    def reset(self, team) -> None:
        self.inner.reset(team)

    def __call__(self, inp, du_nominal):
        if self.k == self.at:
            p_d, v_d, _ = inp.reference
            self.snapshot = (inp.kin, inp.u.copy(), inp.theta.copy(), du_nominal.copy(), inp.lo, inp.hi, (p_d, v_d))
        self.k += 1
        return self.inner(inp, du_nominal)


def circle_snapshot(n: int):
    """The filter's inputs at physics step 1100 (5.5 s, the centre crossing) of the circle swap (R = 6, 12 s)."""
    env = make_env("circle_swap", num_robots=n, settle_time=0.0)
    cap = _Capture(1100)
    env.set_control_filter(cap)
    obs, _ = env.reset(seed=0)
    agent = TrackingController()
    while cap.snapshot is None:
        obs, *_ = env.step(agent.act(obs, env))
    return env.team, cap.snapshot


def timed(fn, reps: int) -> float:
    ts = []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts))


VARIANTS = {
    "ours": {},
    "whole QP": {"decompose": False},
    "cvxopt": {"solver": "cvxopt", "decompose": False},
    "osqp": {"solver": "osqp", "decompose": False},
    "daqp": {"solver": "daqp"},
    "ldp": {"solver": "ldp"},
    "active set": {"active_set": True},
}


def bench(label: str, team, snap, reps: int, slow_reps: int) -> dict:
    kin, u, theta, nom, lo, hi, ref = snap
    deadlock = "none" if ref is None else "auxiliary_velocity"
    out = {"scene": label, "N": team.n}
    for name, kw in VARIANTS.items():
        too_big = kw.get("solver") == "ldp" and 2 * team.n > LDP_MAX_VARS
        if kw.get("solver", "proxsuite") not in available_solvers() or too_big:
            out[name] = float("nan")
            continue
        f = SafetyFilter(team, deadlock=deadlock, **kw)
        du, res = f.step(kin, u, theta, nom, lo, hi, reference=ref)  # warm-up (and warm start)
        if name == "ours":
            out["rows"], out["qp rows"], out["status"], du_ref = res.n_rows, res.n_qp_rows, res.status, du
        else:
            out[name + " err"] = float(np.max(np.abs(du - du_ref), initial=0.0))
        r = reps if name in ("ours", "active set", "whole QP", "daqp", "ldp") else slow_reps
        out[name] = timed(lambda f=f: f.step(kin, u, theta, nom, lo, hi, reference=ref), r)
    return out


def _fmt(v: float, width: int, digits: int) -> str:
    return f"{v:{width}.{digits}f}" if np.isfinite(v) else f"{'-':>{width}s}"  # '-': not run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="N <= 300 and fewer repetitions")
    args = ap.parse_args()
    sizes = [10, 39, 100, 300] if args.quick else [10, 39, 100, 300, 1000]
    reps = 5 if args.quick else 21
    rows = [bench("circle", *circle_snapshot(n), reps, max(3, reps // 3)) for n in (10, 39)]
    for n in sizes:
        rows.append(bench("packed", *packed(n), reps if n <= 300 else 5, max(3, reps // 3) if n <= 300 else 3))
    for n in sizes:  # the same grid, 2 m apart, gentle nominals: rows present, few bind
        rows.append(bench("sparse", *packed(n, spacing=2.0, nominal=3.0), reps if n <= 300 else 5,
                          max(3, reps // 3) if n <= 300 else 3))
    names = list(VARIANTS)
    print("median ms per filter step (rows + solve); ratio = variant / ours\n")
    print(f"{'scene':7s} {'N':>5s} {'rows':>6s} {'qp rows':>8s} {'status':>8s} "
          + " ".join(f"{k:>10s}" for k in names) + " " + " ".join(f"{k + '/ours':>12s}" for k in names[1:]))
    for r in rows:
        print(f"{r['scene']:7s} {r['N']:5d} {r['rows']:6d} {r['qp rows']:8d} {r['status']:>8s} "
              + " ".join(_fmt(r[k] * 1e3, 10, 2) for k in names) + " "
              + " ".join(_fmt(r[k] / r['ours'], 12, 1) for k in names[1:]))
    errs = ", ".join(
        f"{k} {max((r.get(k + ' err', 0.0) for r in rows if np.isfinite(r[k])), default=0.0):.1e}" for k in names[1:]
    )
    print(f"\nlargest |du - du_ours| [rad/s^2] (same QP; cvxopt and OSQP at their own tolerances): {errs}")

if __name__ == "__main__":
    main()
