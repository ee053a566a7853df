"""Benchmark the safety-filter step along short closed-loop sequences, against Robotarium-style whole-team QPs.

Scenes (each a sequence of consecutive physics steps, so warm starts carry from
step to step as they do in use; every variant sees the same states):

  circle   the circle swap (R = 6) around the centre crossing (steps 1100-1119 of
           the tracking controller behind the default filter with ``kernel="numpy"``), N = 10 and 39
  packed   a jittered grid 1.1 m apart, robots moving at 0.5-1 m/s in random
           directions, held random nominals of up to 30 rad/s^2 (a congested
           moment: every robot has many neighbours within D = 3 m and most
           nominals violate a row), N = 39 ... 3,000
  spread   the same grid 2 m apart with gentle nominals (rows present, few bind),
           N = 39 ... 10,000

Columns (median ms per whole ``SafetyFilter.step``: neighbours, rows, QP, backup layer, result):

  ours          the default filter (decomposition, warm active set, the solver route, backup layer;
                the stages' compiled forms where numba is installed, ``kernel="auto"``)
  numpy         the same with every part's numpy reference (``kernel="numpy"``)
  layer off     the same without the backup layer (the paper's filter)
  whole QP      one QP for the whole team, proxsuite (``decompose=False``, no warm start)
  cvxopt        Robotarium-style: the whole team in one ``cvxopt.solvers.qp`` call
  osqp          OSQP, whole team, eps 1e-7 with polishing
  daqp          the default pipeline with DAQP instead of proxsuite (layer off)
  decentral     ``mode="decentralized"``: every robot's own 2-variable QP, then the backup layer
  dec. off      the same without the backup layer

Ratios are against ``ours`` in the same run.  Exactness: the largest
``|du - du_ref|`` of ``layer off`` over every step, ``du_ref`` from an
independent solver: quadprog up to 300 robots; above, Clarabel (an interior-point
method, 1e-10), whose answer is then polished on its own active set (the KKT
equalities of the rows its multipliers mark, solved with scipy's sparse LU and
iterative refinement, here, not with the filter's code) and kept only where the
polished point meets the KKT conditions (:func:`_kkt_polish`); ``err*`` marks a
scene where some step's polish failed and Clarabel's raw answer (off by up to
~1e-4 rad/s^2 at these sizes) was the reference.

``--calls`` adds, per scene, the Python-level function calls and the C-level
calls (numpy and scipy functions and methods; operators such as ``a + b`` are not
counted) of one ``ours`` and one ``layer off`` step, averaged over the sequence
(counted in a separate pass, not in the timed one), and the timed median divided by
them: where that is near the cost of one small numpy call (about a microsecond), the
step's time is the overhead of its calls rather than arithmetic, and only fewer calls
(a compiled kernel) make it faster.

Usage: python benchmarks/bench_filter.py [--quick] [--sizes 39,100] [--steps 20] [--calls] [--page docs/...]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402
import scipy.sparse.linalg as spla  # noqa: E402
from page import add_page_options, check_page, write_page  # noqa: E402

from aasoatt_env import compiled, make_env  # noqa: E402
from aasoatt_env.errors import ConfigError  # noqa: E402
from aasoatt_env.model.dynamics import DT, input_bounds, integrate, kinematics, pose_from_point  # noqa: E402
from aasoatt_env.model.params import make_team  # noqa: E402
from aasoatt_env.safety import SafetyFilter  # noqa: E402
from aasoatt_env.safety.solvers import available_solvers, policy  # noqa: E402
from aasoatt_env.safety.solvers.backends import SOLVERS, Backend, RawAnswer  # noqa: E402
from agents import TrackingController  # noqa: E402

VARIANTS = {
    "ours": {},
    "numpy": {"kernel": "numpy"},
    "layer off": {"backup": False},
    "whole QP": {"decompose": False, "active_set": False, "backup": False},
    "cvxopt": {"solver": "cvxopt", "decompose": False, "active_set": False, "backup": False},
    "osqp": {"solver": "osqp", "decompose": False, "active_set": False, "backup": False},
    "daqp": {"solver": "daqp", "backup": False},
    "decentral": {"mode": "decentralized"},
    "dec. off": {"mode": "decentralized", "backup": False},
}
SLOW = {"cvxopt": 1000, "osqp": 1000, "whole QP": 1000, "daqp": 300}
"""Largest team a slow variant is run on."""


class _Capture:
    """A control filter that runs the default ``SafetyFilter`` and keeps its inputs at physics steps ``[a, b)``."""

    keeps_input_bounds = True

    def __init__(self, a: int, b: int) -> None:
        # recorded behind the numpy reference: the scene is the same whether numba is installed or not
        # (the kernels' last-bit differences would move the chaotic crossing)
        self.inner, self.a, self.b, self.k, self.seq = SafetyFilter(kernel="numpy"), a, b, 0, []

    def reset(self, team) -> None:
        self.inner.reset(team)

    def __call__(self, inp, du_nominal):
        if self.a <= self.k < self.b:
            p_d, v_d, _ = inp.reference
            self.seq.append((inp.kin, inp.u.copy(), inp.theta.copy(), du_nominal.copy(), inp.lo, inp.hi,
                             (p_d, v_d)))
        self.k += 1
        return self.inner(inp, du_nominal)


def circle_sequence(n: int, steps: int):
    """Filter inputs at physics steps 1100.. of the circle swap (the centre crossing)."""
    env = make_env("circle_swap", num_robots=n, settle_time=0.0)
    cap = _Capture(1100, 1100 + steps)
    env.set_control_filter(cap)
    obs, _ = env.reset(seed=0)
    agent = TrackingController()
    while len(cap.seq) < steps:
        obs, *_ = env.step(agent.act(obs, env))
    return env.team, cap.seq, "auxiliary_velocity"


def grid_sequence(n: int, steps: int, spacing: float, nominal: float, seed: int = 0):
    """A jittered grid moving under held random nominals, advanced by the default filter."""
    rng = np.random.default_rng(seed)
    team = make_team("paper", n)
    side = int(np.ceil(np.sqrt(n)))
    g = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)[:n] * spacing
    p = g + rng.uniform(-0.02, 0.02, g.shape)
    theta = rng.uniform(-np.pi, np.pi, n)
    pose = pose_from_point(team, p, theta)
    u = rng.uniform(2, 8, (n, 1)) * np.ones((1, 2)) + rng.normal(0, 0.5, (n, 2))
    nom = rng.uniform(-nominal, nominal, (n, 2))
    f = SafetyFilter(team, deadlock="none")
    seq = []
    for _ in range(steps):
        kin = kinematics(team, pose, u)
        lo, hi = input_bounds(team, u, DT)
        seq.append((kin, u.copy(), pose[:, 2].copy(), nom, lo, hi, None))
        du, _ = f.step(kin, u, pose[:, 2], nom, lo, hi)
        pose, u = integrate(team, pose, u, du, DT)
    return team, seq, "none"


KKT_TOL = 1e-10
"""Largest row or bound violation and negative multiplier of a polished reference (scaled problem)."""
KKT_STATIONARY = 1e-9
"""Largest entry of the polished reference's Lagrangian gradient ``H x + g + A' z``."""


def _kkt_polish(prob, x: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """An interior-point answer ``(x, z)`` of ``prob`` made exact on its active set, or None where it does not verify.

    The working set is the rows whose multiplier ``z`` exceeds a fraction of the largest and the bounds ``x``
    lies within a distance of (a few of each are tried); ``[[H, A_W'], [A_W, 0]]`` is solved by a sparse LU of
    its copy with a 1e-12 proximal shift and ten rounds of iterative refinement on the unshifted system; the
    point is returned only where every row and bound holds within :data:`KKT_TOL`, the working ones as
    equalities (complementarity: only they carry multipliers), every working multiplier is ``>= -KKT_TOL``
    and the Lagrangian gradient is within :data:`KKT_STATIONARY`: the KKT conditions, which make it the QP's
    optimum (a convex QP) to those tolerances.  ``x`` is not used beyond choosing the working set: the
    polished point comes from the equalities alone.
    """
    n, m = prob.n, prob.m
    H = prob.H_sparse().tocsc()
    A = sp.vstack((prob.C, sp.identity(n), -sp.identity(n)), format="csr")
    b = np.concatenate((prob.u, prob.ub, -prob.lb))
    finite = np.abs(b) < 1e19
    top = max(float(z.max(initial=0.0)), 1e-300)
    for frac, near in ((1e-7, 1e-8), (1e-9, 1e-10), (1e-5, 1e-6), (1e-11, 1e-12)):
        on = np.concatenate((z > frac * top, x >= prob.ub - near, x <= prob.lb + near)) & finite
        idx = np.flatnonzero(on)
        k = idx.size
        K = sp.bmat([[H, A[idx].T], [A[idx], None]], format="csc") if k else H
        shift = sp.diags(np.concatenate((np.full(n, 1e-12), np.full(k, -1e-12))))
        try:
            lu = spla.splu((K + shift).tocsc())
        except RuntimeError:  # singular even shifted
            continue
        rhs = np.concatenate((-prob.g, b[idx]))
        sol = lu.solve(rhs)
        for _ in range(10):
            sol = sol + lu.solve(rhs - K @ sol)
        xp, zw = sol[:n], sol[n:]
        zall = np.zeros(A.shape[0])
        zall[idx] = zw
        r = A @ xp - b
        if (np.all(np.isfinite(sol)) and float(np.max(r[finite], initial=0.0)) <= KKT_TOL
                and float(np.abs(r[idx]).max(initial=0.0)) <= KKT_TOL  # the working set met as equalities
                and float(zw.min(initial=0.0)) >= -KKT_TOL
                and float(np.abs(H @ xp + prob.g + A.T @ zall).max(initial=0.0)) <= KKT_STATIONARY):
            return xp, np.maximum(zall[:m], 0.0)
    return None


_POLISH_FAILED: list[int] = []  # steps whose reference is Clarabel's raw answer (the current scene's)


def _clarabel_kkt(prob, x0, z0, opts: dict) -> RawAnswer:
    """The registered Clarabel back-end's answer, polished by :func:`_kkt_polish` where that verifies."""
    raw = SOLVERS["clarabel"](prob, x0, z0, opts)
    polished = _kkt_polish(prob, raw.x, raw.z) if raw.ok else None
    if polished is None:
        _POLISH_FAILED.append(1)
        return raw
    return RawAnswer(polished[0], polished[1], True, raw.iterations, "clarabel, KKT-polished")


def _reference(team, seq, deadlock) -> tuple[list[np.ndarray], bool] | None:
    """Independent solver's answers of the QP (layer off) at every step, and whether all were exact.

    quadprog (an exact dual active-set method) up to 300 robots; above, Clarabel polished by
    :func:`_kkt_polish` (False where some step's polish did not verify).
    """
    solver = "quadprog" if team.n <= 300 and "quadprog" in available_solvers() else "clarabel"
    if solver not in available_solvers():
        return None
    if solver == "clarabel":
        solver = "clarabel+kkt"
        SOLVERS[solver] = Backend(_clarabel_kkt, "clarabel")  # the registry: one function, one line
    _POLISH_FAILED.clear()
    f = SafetyFilter(team, deadlock=deadlock, backup=False, solver=solver, decompose=False, active_set=False)
    preferred, policy.PHASE1_ROUTE = policy.PHASE1_ROUTE, ()  # phase 1 (relaxed steps) by the reference too,
    try:  # not by the filter's route
        answers = [f.step(kin, u, th, nom, lo, hi, reference=ref)[0] for kin, u, th, nom, lo, hi, ref in seq]
    finally:
        policy.PHASE1_ROUTE = preferred
    return answers, not _POLISH_FAILED


def calls_per_step(team, seq, deadlock: str, **kw) -> tuple[float, float]:
    """Python-level and C-level calls per filter step along ``seq`` (``sys.setprofile``; operators not counted)."""
    f = SafetyFilter(team, deadlock=deadlock, **kw)
    f.reset()
    count = {"call": 0, "c_call": 0}

    def tally(frame, event, arg):
        if event in count:
            count[event] += 1

    sys.setprofile(tally)
    try:
        for kin, u, th, nom, lo, hi, r in seq:
            f.step(kin, u, th, nom, lo, hi, reference=r)
    finally:
        sys.setprofile(None)
    return count["call"] / len(seq), count["c_call"] / len(seq)


def bench(label: str, team, seq, deadlock: str, reps: int, calls: bool = False) -> dict:
    out = {"scene": label, "N": team.n}
    if calls:
        out["calls"] = (calls_per_step(team, seq, deadlock), calls_per_step(team, seq, deadlock, backup=False))
    ref = _reference(team, seq, deadlock)
    if ref is not None:
        ref, out["exact ref"] = ref
    for name, kw in VARIANTS.items():
        if kw.get("solver", "proxsuite") not in available_solvers() or team.n > SLOW.get(name, 10**9):
            out[name] = float("nan")
            continue
        try:
            f = SafetyFilter(team, deadlock=deadlock, **kw)
        except (ConfigError, TypeError):  # e.g. mode="decentralized" not in this version
            out[name] = float("nan")
            continue
        times, err, backup_steps = [], 0.0, 0
        for _ in range(reps):
            f.reset()
            for k, (kin, u, th, nom, lo, hi, r) in enumerate(seq):
                t = time.perf_counter()
                du, res = f.step(kin, u, th, nom, lo, hi, reference=r)
                times.append(time.perf_counter() - t)
                if name == "layer off" and ref is not None:
                    err = max(err, float(np.abs(du - ref[k]).max(initial=0.0)))
                backup_steps += bool(res.backup.any())
        out[name] = float(np.median(times))
        if name == "ours":
            out["rows"], out["qp rows"], out["backup steps"] = res.n_rows, res.n_qp_rows, backup_steps // reps
        if name == "layer off":
            out["err"] = err if ref is not None else float("nan")
    return out


def _fmt(v: float, width: int, digits: int) -> str:
    return f"{v:{width}.{digits}f}" if np.isfinite(v) else f"{'-':>{width}s}"  # '-': not run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="N <= 300, 8 steps per scene")
    ap.add_argument("--steps", type=int, default=20, help="consecutive physics steps per scene")
    ap.add_argument("--sizes", default=None, help="comma-separated grid sizes (default 39,100,300,1000,3000,10000)")
    ap.add_argument("--calls", action="store_true", help="also count the Python and C calls of a step (own pass)")
    add_page_options(ap)
    args = ap.parse_args()
    check_page(args)
    steps = 8 if args.quick else args.steps
    sizes = [int(s) for s in args.sizes.split(",")] if args.sizes else (
        [39, 100, 300] if args.quick else [39, 100, 300, 1000, 3000, 10000])
    rows = []
    for n in (10, 39):
        rows.append(bench("circle", *circle_sequence(n, steps), reps=3, calls=args.calls))
        print(f"  done circle N={n}", flush=True)
    for n in sizes:
        if n <= 3000:
            k = steps if n <= 300 else max(4, steps // 4)
            rows.append(bench("packed", *grid_sequence(n, k, 1.1, 30.0), reps=3 if n <= 300 else 1, calls=args.calls))
            print(f"  done packed N={n}", flush=True)
    for n in sizes:
        k = steps if n <= 300 else max(4, steps // 4)
        rows.append(bench("spread", *grid_sequence(n, k, 2.0, 3.0), reps=3 if n <= 300 else 1, calls=args.calls))
        print(f"  done spread N={n}", flush=True)
    lines = _table(rows, args.calls)
    print("\n".join(lines))
    write_page(args, "Filter step times", "```\n" + "\n".join(lines) + "\n```\n\n" + (__doc__ or "").split("Usage")[0])


def _table(rows: list[dict], calls: bool) -> list[str]:
    """The results as text lines (printed, and the page's body)."""
    names = list(VARIANTS)
    kernel = "compiled (numba)" if compiled.available() else "numpy (numba not installed)"
    out = [f"median ms per filter step along the sequence; ratio = variant / ours; ours' kernels: {kernel}", "",
           f"{'scene':7s} {'N':>6s} {'rows':>6s} {'qp rows':>8s} {'backup':>7s} "
           + " ".join(f"{k:>10s}" for k in names) + " " + " ".join(f"{k + '/ours':>14s}" for k in names[1:])
           + f" {'err':>8s}"]
    for r in rows:
        out.append(f"{r['scene']:7s} {r['N']:6d} {r.get('rows', 0):6d} {r.get('qp rows', 0):8d} "
                   f"{r.get('backup steps', 0):7d} "
                   + " ".join(_fmt(r[k] * 1e3, 10, 2) for k in names) + " "
                   + " ".join(_fmt(r[k] / r['ours'], 14, 2) for k in names[1:])
                   + f" {r.get('err', float('nan')):8.1e}" + ("" if r.get("exact ref", True) else "*"))
    out += ["", "err: largest |du - du_ref| [rad/s^2] of 'layer off' over every step against an independent solver "
            "(quadprog up to 300 robots, above Clarabel polished on its active set and KKT-verified; *: some step's "
            "polish failed, Clarabel's raw answer there)"]
    if calls:
        out += ["", "calls per filter step (Python-level function calls + C-level calls; operators not counted), "
                "and the timed median per call", "",
                f"{'scene':7s} {'N':>6s} {'ours calls':>11s} {'us/call':>8s} {'layer off calls':>16s} "
                f"{'us/call':>8s} {'backup layer calls':>19s}"]
        for r in rows:
            (po, co), (pl, cl) = r["calls"]
            out.append(f"{r['scene']:7s} {r['N']:6d} {po + co:11.0f} {1e6 * r['ours'] / (po + co):8.2f} "
                       f"{pl + cl:16.0f} {1e6 * r['layer off'] / (pl + cl):8.2f} {po + co - pl - cl:19.0f}")
    return out


if __name__ == "__main__":
    main()
