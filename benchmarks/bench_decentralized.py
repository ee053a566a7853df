"""Benchmark the decentralised filter step (every robot its own 2-variable QP) at 1,000-10,000 robots.

Scenes (as ``benchmarks/bench_filter.py``): "packed", a jittered grid 1.1 m apart
whose robots move at 0.2-0.8 m/s in random directions with random nominals of up
to 30 rad/s^2 (every robot has ~20 rows, most bind, and about half of the
robots' own QPs are infeasible once the pair rows are halved); "spread", the
same grid 2 m apart with gentle nominals (3 rad/s^2): rows present, few bind.

Columns (medians over repeated calls on the same state, one core, ms; a second table gives the
minima, which other processes on a shared machine disturb least):

  pairs     the neighbour search alone (``aasoatt_env.model.geometry.robot_pairs``, D = 3 m)
  rows      the barrier rows from the pairs, as ``SafetyFilter.step`` builds them (no deadlock strategy)
  solve     ``decentralized_step``: split the rows, solve every robot's QP exactly, relax the infeasible ones
            (``split="reciprocal"``, the default)
  total     pairs + rows + solve: the decentralised filter step without the backup layer
  auth      ``solve`` with ``split="authority"`` (rhs split by authority)
  step      a whole ``SafetyFilter.step(mode="decentralized", backup=False)`` (validation, barrier values,
            result) where the core has the ``mode`` option (PROPOSED_core_patch.diff), else '-'
  +backup   the same with the backup layer (the default filter)

Targets (issue 13): packed N = 1,000 <= 5 ms and spread N = 10,000 <= 50 ms per decentralised step.

Usage: python benchmarks/bench_decentralized.py [--quick] [--reps K]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from bench_filter import packed  # noqa: E402

from aasoatt_env.model.geometry import robot_pairs  # noqa: E402
from aasoatt_env.safety import SafetyFilter  # noqa: E402
from aasoatt_env.safety.barriers import PairGeometry, barrier_rows  # noqa: E402
from aasoatt_env.safety.config import FilterConfig  # noqa: E402
from aasoatt_env.safety.decentralized import decentralized_step  # noqa: E402

CFG = FilterConfig(deadlock="none")
HAS_MODE = "mode" in FilterConfig.__dataclass_fields__


def rows(team, kin, pr, nom):
    """The filter's rows for pairs ``pr`` (the lines of ``SafetyFilter.step`` between the search and the QP)."""
    p, v, A, adot = kin.p, kin.v, kin.A, kin.adot_u
    ri, rj = pr[:, 0], pr[:, 1]
    rad, amax = team.radius, team.max_point_accel
    geo_p, geo_v, geo_a = p[ri] - p[rj], v[ri] - v[rj], adot[ri] - adot[rj]
    ds, ap = rad[ri] + rad[rj], amax[ri] + amax[rj]
    sp2 = np.einsum("ij,ij->i", v, v)
    margin = CFG.pair_margin(geo_v) + CFG.speed_margin_coefficient * (sp2[ri] + sp2[rj])
    c, rhs, keep = barrier_rows(CFG.barrier, PairGeometry(ri, rj, geo_p, geo_v, geo_a, ds + margin, ds, ap), CFG)
    ri, rj = ri[keep], rj[keep]
    Gi = np.einsum("pki,pk->pi", A[ri], c)
    Gj = -np.einsum("pki,pk->pi", A[rj], c)
    target = np.einsum("nij,nj->ni", A, nom)
    return target, ri, rj, Gi, Gj, rhs


MINIMA: dict[tuple[str, int, str], float] = {}


def timed(fn, reps: int, key: tuple[str, int, str] | None = None) -> float:
    """Median wall time [ms] of ``reps`` calls (the minimum is kept in ``MINIMA[key]``)."""
    fn()  # warm-up
    ts = []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    if key is not None:
        MINIMA[key] = float(np.min(ts)) * 1e3
    return float(np.median(ts)) * 1e3


def bench(label: str, n: int, spacing: float, nominal: float, reps: int) -> dict:
    team, (kin, u, theta, nom, lo, hi, _) = packed(n, spacing=spacing, nominal=nominal)
    pr = robot_pairs(kin.p, CFG.sensing_range)
    target, ri, rj, Gi, Gj, rhs = rows(team, kin, pr, nom)
    amax = team.max_point_accel
    out = {"scene": label, "N": n, "rows": int(rhs.size)}
    res = decentralized_step(kin.A, target, lo, hi, ri, rj, Gi, Gj, rhs, amax)
    out["relaxed"] = res.n_relaxed
    out["relaxed auth"] = decentralized_step(kin.A, target, lo, hi, ri, rj, Gi, Gj, rhs, amax,
                                             split="authority").n_relaxed
    k = (label, n)
    out["pairs"] = timed(lambda: robot_pairs(kin.p, CFG.sensing_range), reps, (*k, "pairs"))
    out["rows ms"] = timed(lambda: rows(team, kin, pr, nom), reps, (*k, "rows ms"))
    out["solve"] = timed(lambda: decentralized_step(kin.A, target, lo, hi, ri, rj, Gi, Gj, rhs, amax), reps,
                         (*k, "solve"))
    out["total"] = out["pairs"] + out["rows ms"] + out["solve"]
    MINIMA[(*k, "total")] = sum(MINIMA[(*k, c)] for c in ("pairs", "rows ms", "solve"))
    out["auth"] = timed(lambda: decentralized_step(kin.A, target, lo, hi, ri, rj, Gi, Gj, rhs, amax,
                                                   split="authority"), reps, (*k, "auth"))
    out["step"] = out["+backup"] = MINIMA[(*k, "step")] = MINIMA[(*k, "+backup")] = float("nan")
    if HAS_MODE:
        for key, backup in (("step", False), ("+backup", True)):
            f = SafetyFilter(team, deadlock="none", mode="decentralized", backup=backup)
            out[key] = timed(lambda f=f: f.step(kin, u, theta, nom, lo, hi), reps, (*k, key))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="N <= 1,000")
    ap.add_argument("--reps", type=int, default=21, help="timed calls per cell (median)")
    args = ap.parse_args()
    scenes = [("packed", 100, 1.1, 30.0), ("packed", 1000, 1.1, 30.0), ("spread", 1000, 2.0, 3.0)]
    if not args.quick:
        scenes += [("packed", 3000, 1.1, 30.0), ("spread", 10000, 2.0, 3.0)]
    rows_out = [bench(*s, reps=args.reps) for s in scenes]
    cols = ["pairs", "rows ms", "solve", "total", "auth", "step", "+backup"]
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    for what, get in (("median", lambda r, c: r[c]), ("minimum", lambda r, c: MINIMA[(r["scene"], r["N"], c)])):
        print(f"{what} ms per decentralised filter step, one core, {args.reps} calls; total = pairs + rows + solve"
              f" (load average {load:.1f})\n")
        print(f"{'scene':7s} {'N':>6s} {'rows':>7s} {'relaxed':>8s} {'(auth)':>7s} "
              + " ".join(f"{c.replace(' ms', ''):>8s}" for c in cols))
        for r in rows_out:
            vals = [get(r, c) for c in cols]
            print(f"{r['scene']:7s} {r['N']:6d} {r['rows']:7d} {r['relaxed']:8d} {r['relaxed auth']:7d} "
                  + " ".join(f"{v:8.2f}" if np.isfinite(v) else f"{'-':>8s}" for v in vals))
        print()
    print("relaxed: robots whose own QP was infeasible (reciprocal split; '(auth)': authority split)")
    print("targets (issue 13): packed N = 1,000 total <= 5 ms; spread N = 10,000 total <= 50 ms")


if __name__ == "__main__":
    main()
