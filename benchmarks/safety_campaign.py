"""Closed-loop safety campaign of the default filter: adversarial nominals, and the paper's scenarios.

``adversarial`` (the guarantee): every adversary of :data:`agents.ADVERSARIES`
drives every robot of a team behind ``AASOATTFilter`` with its defaults, for
``--steps`` physics steps (``decision_interval=1``), over

* teams: N = 2, 8, 16 on RandomGoals (arena by default), and N = 39 on the
  radius-6 circle (the paper's largest crowd);
* presets: ``paper`` (no wheel-speed limit), ``turtlebot3`` (TurtleBot3 Burger,
  6.67 rad/s) and ``mixed`` (the two alternating); ``--presets`` also offers
  ``double_integrator`` (point masses);
* static obstacles: none, or 4 random discs (RandomGoals; the circle's Fig. 5
  obstacles on the circle);
* seeds 0 .. ``--seeds - 1``.

Each episode reports the smallest robot-robot and robot-obstacle surface gaps
(``d_s`` met when ``>= -1e-3``), NaN anywhere, the steps where the backup layer
braked and where a status said ``unsafe``, and the wall time.  Results are
appended to a JSONL file as they finish; a run with the same ``--out`` resumes
where it stopped.

``paper`` (liveness): the paper's method (tracking controller) on the radius-6
circle, N = 10, 20, 30, 35, 39 (+3 s to settle), the radius-10 circle N = 60
(+3 s) and the 20-robot Fig. 5 obstacle scene, with the layer on and off: gaps,
every robot's final distance to its goal (must be <= 0.05 m), tracking RMSE.

Usage::

    python benchmarks/safety_campaign.py adversarial --teams 2,8,16 --seeds 7 --steps 800 --jobs 2 \
        --out results/campaign.jsonl
    python benchmarks/safety_campaign.py adversarial --teams 39 --seeds 2 --steps 400 --jobs 2 \
        --out results/campaign.jsonl
    python benchmarks/safety_campaign.py paper --out results/paper_liveness.jsonl
    python benchmarks/safety_campaign.py summary --out results/campaign.jsonl --page docs/safety_campaign.md
"""

from __future__ import annotations

import argparse
import inspect
import itertools
import json
import os
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from page import add_page_options, check_page, command_line, write_page  # noqa: E402

PRESETS = {"paper": "paper", "turtlebot3": "turtlebot3_burger", "mixed": None, "double_integrator": "double_integrator"}
DEFAULT_PRESETS = ("paper", "turtlebot3", "mixed")
TEAMS = (2, 8, 16, 39)
TOL = 1e-3


def _robots(preset: str, n: int):
    spec = PRESETS[preset]
    return spec if spec is not None else ["paper" if i % 2 == 0 else "turtlebot3_burger" for i in range(n)]


def _episode(key: dict) -> dict:
    from aasoatt_env import make_env
    from aasoatt_env.analysis.metrics import pairwise_min_distance
    from aasoatt_env.analysis.recording import run_episode
    from agents import ADVERSARIES

    n, preset, obst, adv, seed, steps = key["n"], key["preset"], key["obstacles"], key["adversary"], key["seed"], \
        key["steps"]
    robots = _robots(preset, n)
    if n == 39:  # the radius-6 circle, with the Fig. 5 obstacles inside it or without
        kw = dict(scenario="circle_obstacles" if obst else "circle_swap", num_robots=39, robots=robots)
    else:
        kw = dict(scenario="random_goals", num_robots=n, robots=robots, random_obstacles=4 if obst else 0)
    env = make_env(filter={"mode": key.get("mode", "centralized"), "backup": key.get("backup", True)},
                   max_steps=steps, **kw)
    cls = ADVERSARIES[adv]
    agent = cls(seed=seed) if "seed" in inspect.signature(cls).parameters else cls()
    t = time.perf_counter()
    rollout, _ = run_episode(env, agent, seed=seed)
    wall = time.perf_counter() - t
    sep = pairwise_min_distance(rollout)
    finite = all(np.all(np.isfinite(getattr(rollout, f))) for f in ("positions", "velocities", "headings"))
    return {**key, "min_robot_gap": float(sep.overall_min_robot_gap) if n > 1 else None,
            "min_obstacle_gap": float(sep.overall_min_obstacle_gap) if rollout.n_obstacles else None,
            "finite": bool(finite), "backup_steps": int(rollout.backup.any(axis=1).sum()),
            "unsafe_steps": int(np.sum(rollout.solver_status == "unsafe")), "steps": int(rollout.n_steps - 1),
            "wall_s": wall}


def _key_id(k: dict) -> str:
    mode = "" if k.get("mode", "centralized") == "centralized" else f"/{k['mode']}"
    mode += "" if k.get("backup", True) else "/layer-off"
    return f"{k['adversary']}/N={k['n']}/{k['preset']}/obst={int(k['obstacles'])}/seed={k['seed']}{mode}"


def _key_steps(k: dict) -> str:
    """The record's identity including its length (a longer run of the same episode is another record)."""
    return f"{_key_id(k)}/steps={k['steps']}"


_EPISODE_KEYS = ("adversary", "n", "preset", "obstacles", "seed", "steps", "min_robot_gap", "min_obstacle_gap",
                 "finite", "wall_s")
_SCENE_KEYS = ("scene", "n", "layer")


def _records(path: Path, keys: tuple[str, ...] | None = None) -> list[dict]:
    """The JSON records of a results file; a line that is not one (or lacks ``keys``) is a one-line error."""
    if not path.is_file():
        return []
    out = []
    for k, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except ValueError as exc:
            raise SystemExit(f"error: --out {path}: line {k} is not JSON ({exc}); expected this script's "
                             "results file (one JSON record per line)") from None
        missing = [key for key in (keys or ()) if not isinstance(rec, dict) or key not in rec]
        if not isinstance(rec, dict) or missing:
            raise SystemExit(f"error: --out {path}: line {k} is not a record of this kind (missing {missing}); "
                             "expected a results file this script wrote")
        out.append(rec)
    return out


def _done(path: Path) -> dict[str, dict]:
    return {_key_steps(rec): rec for rec in _records(path, _EPISODE_KEYS)}


def _longest(recs: list[dict]) -> list[dict]:
    """One record per episode (adversary, team, preset, obstacles, seed, mode): the longest run."""
    best: dict[str, dict] = {}
    for r in recs:
        k = _key_id(r)
        if k not in best or r["steps"] > best[k]["steps"]:
            best[k] = r
    return list(best.values())


def adversarial(args: argparse.Namespace) -> None:
    from agents import ADVERSARIES

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    done = _done(out)
    keys = [dict(adversary=a, n=n, preset=p, obstacles=o, seed=s, steps=args.steps, mode=args.mode,
                 backup=not args.layer_off)
            for s, a, n, p, o in itertools.product(range(args.first_seed, args.first_seed + args.seeds), ADVERSARIES,
                                                   args.teams, args.presets, (False, True))]
    todo = [k for k in keys if _key_steps(k) not in done]
    print(f"{len(keys)} episodes, {len(keys) - len(todo)} already in {out}, {len(todo)} to run", flush=True)
    t0 = time.perf_counter()
    with out.open("a") as fh:
        if args.jobs > 1:
            import multiprocessing as mp

            with mp.get_context("spawn").Pool(args.jobs) as pool:
                for rec in pool.imap_unordered(_episode, todo):
                    fh.write(json.dumps(rec | {"command": command_line()}) + "\n")
                    fh.flush()
                    _progress(rec)
        else:
            for k in todo:
                rec = _episode(k)
                fh.write(json.dumps(rec | {"command": command_line()}) + "\n")
                fh.flush()
                _progress(rec)
    print(f"wall {time.perf_counter() - t0:.0f} s this run", flush=True)
    summary(args)


def _progress(rec: dict) -> None:
    gap = rec["min_robot_gap"]
    og = rec["min_obstacle_gap"]
    print(f"{_key_id(rec):45s} gap {gap if gap is None else f'{gap:+.4f}'} obst {og if og is None else f'{og:+.4f}'} "
          f"backup {rec['backup_steps']:4d} unsafe {rec['unsafe_steps']} {rec['wall_s']:.1f}s", flush=True)


_PAPER_HEADER = ("| scene | N | layer | closest gap [m] | worst final error [m] | robots home | RMSE [m] | "
                 "backup steps | wall [s] |\n|---|---:|---|---:|---:|---:|---:|---:|---:|")


def _paper_row(rec: dict) -> str:
    return (f"| {rec['scene']} | {rec['n']} | {'on' if rec['layer'] else 'off'} | {rec['min_gap']:+.4f} | "
            f"{rec['final_max']:.4f} | {rec['home']}/{rec['n']} | {rec['rmse']:.4f} | {rec['backup_steps']} | "
            f"{rec['wall_s']:.0f} |")


def _paper_summary(path: Path, mode: str, out: list[str]) -> None:
    """The liveness table of a ``paper`` results file (the last record of each scene, N and layer)."""
    last = {}
    for rec in _records(path, _SCENE_KEYS):
        if rec.get("mode", "centralized") == mode:
            last[(rec["scene"], rec["n"], rec["layer"])] = rec
    out.append(f"\nmode={mode}: the paper's scenes, tracking controller, +3 s settle\n")
    out.append(_PAPER_HEADER)
    for rec in last.values():
        out.append(_paper_row(rec))


def summary(args: argparse.Namespace) -> None:
    out: list[str] = []
    _summary(args, out)
    print("\n".join(out))
    kind = "Safety campaign" if "episodes" in "\n".join(out) else "Liveness of the paper's scenes"
    shown = [r for r in _records(Path(args.out)) if r.get("mode", "centralized") == args.mode
             and ("scene" in r or r.get("backup", True) != args.layer_off)]  # (the records the tables show)
    write_page(args, f"{kind} ({args.mode})", "\n".join(out) + "\n\n" + __doc__.split("Usage")[0], shown)


def _summary(args: argparse.Namespace, out: list[str]) -> None:
    path = Path(args.out)
    if not path.is_file():
        raise SystemExit(f"error: --out {path}: no such results file")
    recs = _records(path)
    if recs and "scene" in recs[0]:
        _paper_summary(path, args.mode, out)
        return
    recs = _longest([r for r in _done(path).values()
                     if r.get("mode", "centralized") == args.mode and r.get("backup", True) != args.layer_off])
    if not recs:
        out.append("no results yet")
        return
    def bad(r: dict) -> bool:
        gaps = [g for g in (r["min_robot_gap"], r["min_obstacle_gap"]) if g is not None]
        return (not r["finite"]) or any(g < -TOL for g in gaps)

    steps = sorted({r["steps"] for r in recs})
    out.append(f"\nmode={args.mode}, backup layer {'off' if args.layer_off else 'on'}: "
          f"{len(recs)} episodes x {'/'.join(map(str, steps))} physics steps; "
          f"wall {sum(r['wall_s'] for r in recs):.0f} s "
          f"(sum over episodes)\n")
    out.append("| adversary | episodes | closest robot pair gap [mm] | closest obstacle gap [mm] | "
          "episodes with a pair closer than d_s - 1 mm | NaN | backup steps (share) | unsafe steps |")
    out.append("|---|---:|---:|---:|---:|---:|---:|---:|")
    for adv in sorted({r["adversary"] for r in recs}) + ["all"]:
        rs = [r for r in recs if adv in ("all", r["adversary"])]
        g = [r["min_robot_gap"] for r in rs if r["min_robot_gap"] is not None]
        o = [r["min_obstacle_gap"] for r in rs if r["min_obstacle_gap"] is not None]
        steps = sum(r["steps"] for r in rs)
        out.append(f"| {adv} | {len(rs)} | {1e3 * min(g):+.4f} | {1e3 * min(o) if o else float('nan'):+.4f} | "
              f"{sum(bad(r) for r in rs)} | {sum(not r['finite'] for r in rs)} | "
              f"{sum(r['backup_steps'] for r in rs)} ({sum(r['backup_steps'] for r in rs) / max(steps, 1):.1%}) | "
              f"{sum(r['unsafe_steps'] for r in rs)} |")
    out.append("\n| team | preset | episodes | closest robot pair gap [mm] | closest obstacle gap [mm] | "
          "backup steps (share) |")
    out.append("|---:|---|---:|---:|---:|---:|")
    for n, p in sorted({(r["n"], r["preset"]) for r in recs}):
        rs = [r for r in recs if (r["n"], r["preset"]) == (n, p)]
        g = [r["min_robot_gap"] for r in rs if r["min_robot_gap"] is not None]
        o = [r["min_obstacle_gap"] for r in rs if r["min_obstacle_gap"] is not None]
        steps = sum(r["steps"] for r in rs)
        out.append(f"| {n} | {p} | {len(rs)} | {1e3 * min(g):+.4f} | {1e3 * min(o) if o else float('nan'):+.4f} | "
              f"{sum(r['backup_steps'] for r in rs)} ({sum(r['backup_steps'] for r in rs) / max(steps, 1):.1%}) |")


def paper(args: argparse.Namespace) -> None:
    from aasoatt_env import FilterConfig, make_env
    from aasoatt_env.analysis.metrics import summarize
    from aasoatt_env.analysis.recording import run_episode
    from agents import TrackingController

    runs = [("circle R=6", dict(scenario="circle_swap", num_robots=n, radius=6.0, duration=12.0)) for n in
            (10, 20, 30, 35, 39)]
    runs += [("circle R=10", dict(scenario="circle_swap", num_robots=60, radius=10.0, duration=20.0)),
             ("Fig. 5 obstacles", dict(scenario="circle_obstacles", num_robots=20))]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    print(_PAPER_HEADER)
    with out.open("a") as fh:
        for label, kw in runs:
            for layer in (True, False) if args.mode == "centralized" else (True,):
                env = make_env(filter=FilterConfig(backup=layer, mode=args.mode), settle_time=3.0, **kw)
                t = time.perf_counter()
                ro, _ = run_episode(env, TrackingController(), seed=0)
                wall = time.perf_counter() - t
                s = summarize(ro, goal_tolerance=0.05)
                gap = min(v for v in (s["min_robot_gap"], s["min_obstacle_gap"]) if v is not None)
                fe = np.linalg.norm(ro.positions[-1] - ro.goals, axis=1)
                rec = dict(scene=label, n=kw["num_robots"], layer=layer, mode=args.mode, min_gap=gap,
                           final_max=float(fe.max()),
                           home=int(np.sum(fe <= 0.05)), rmse=s["rmse"], backup_steps=int(ro.backup.any(axis=1).sum()),
                           wall_s=wall, command=command_line())
                fh.write(json.dumps(rec) + "\n")
                fh.flush()
                print(_paper_row(rec), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=("adversarial", "paper", "summary"))
    ap.add_argument("--seeds", type=int, default=7, help="seeds per combination (adversarial)")
    ap.add_argument("--first-seed", type=int, default=0, help="first seed (adversarial): seeds first .. first+seeds-1")
    ap.add_argument("--steps", type=int, default=800, help="physics steps per episode (adversarial)")
    ap.add_argument("--teams", type=lambda v: tuple(int(x) for x in v.split(",")), default=TEAMS,
                    help="team sizes, comma-separated (39 = the radius-6 circle)")
    ap.add_argument("--presets", type=lambda v: tuple(v.split(",")), default=DEFAULT_PRESETS,
                    help=f"robot presets, comma-separated, among {list(PRESETS)} (default: "
                    f"{','.join(DEFAULT_PRESETS)})")
    ap.add_argument("--mode", choices=("centralized", "decentralized"), default="centralized",
                    help="the filter's mode (FilterConfig.mode)")
    ap.add_argument("--layer-off", action="store_true",
                    help="adversarial: the paper's filter alone (backup=False), for comparison")
    ap.add_argument("--jobs", type=int, default=1, help="episodes in parallel processes")
    ap.add_argument("--out", default="results/safety_campaign.jsonl", help="JSONL results (appended; resumable)")
    add_page_options(ap)
    args = ap.parse_args()
    check_page(args)
    for name, value in (("--seeds", args.seeds), ("--steps", args.steps), ("--jobs", args.jobs)):
        if value < 1:
            ap.error(f"{name}: got {value}, expected an integer >= 1")
    if args.first_seed < 0 or any(n < 1 for n in args.teams):
        ap.error(f"--first-seed/--teams: got {args.first_seed}/{list(args.teams)}, expected a seed >= 0 and team "
                 "sizes >= 1")
    unknown = [p for p in args.presets if p not in PRESETS]
    if unknown:
        ap.error(f"--presets: got {unknown}, expected names among {list(PRESETS)}")
    {"adversarial": adversarial, "paper": paper, "summary": summary}[args.what](args)


if __name__ == "__main__":
    main()
