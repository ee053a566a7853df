"""Liveness campaign: scenes x seeds x filter modes x deadlock strategies -> robots home, makespan, collisions.

The tracking controller (the paper's method) drives every robot behind the filter with its defaults but
``mode`` and ``deadlock``.  Scenes (``--scenes``, all by default):

* ``fig5``: the paper's Fig. 5 (20 robots, three discs), 12 s + ``settle``;
* ``corridor22`` / ``corridor16``: the ``corridor`` scenario, paper robots, 2.2 m wide 4 against 4 and 1.6 m
  wide (one robot at a time) 3 against 3; ``tb3corridor22`` / ``tb3corridor16``: TurtleBot3 Burger teams in the
  same corridors scaled by their size (0.21 / 0.96); 40 s + 90 s settle;
* ``doorway``: the ``doorway`` scenario, 2 against 2 through a 1.6 m door between 5 m rooms, seeded places,
  15 s + 60 s settle;
* ``field``: the ``obstacle_field`` scenario, 5 robots in a 9 m arena, density 0.1, radii 0.3-0.8 m, seeded,
  straight-line references at 0.8 m/s + 30 s settle;
* ``circle6`` / ``circle10`` / ``random30``: the open scenes (radius 6, N = 20 and 39; radius 10, N = 60;
  30 random goals), to show they stay home.

Every episode runs the scenario's whole horizon (its duration plus the stated settle time), except that a scene
marked ``stop`` ends once every robot has been within ``--tol`` of its goal for 2 s (nothing moves after
that).  A robot is home when within ``--tol`` (0.05 m) of its goal at the end.  Each robot not home is
classified: ``no path`` when its goal is not reachable from where it ended in the free space of its centre (the
obstacles grown by its radius, on a 2 cm grid; robots ignored), else ``stuck``.  Results are appended to a JSONL
file as they finish; a run with the same ``--out`` resumes where it stopped.

Usage::

    python benchmarks/liveness_campaign.py run --out results/liveness.jsonl --jobs 2
    python benchmarks/liveness_campaign.py summary --out results/liveness.jsonl \
        --page docs/benchmarks/liveness_campaign.md
"""

from __future__ import annotations

import argparse
import json
import time
from multiprocessing import Pool
from pathlib import Path

import numpy as np
from page import add_page_options, check_page, command_line, write_page

TB3 = 0.21 / 0.96  # TurtleBot3 Burger diameter over the paper robot's


def _corridor(width: float, n: int, scale: float = 1.0, robots: str = "paper") -> dict:
    s = scale
    return dict(scenario="corridor", width=width * s, left=n, right=n, robots=robots, length=10.0 * s,
                spacing=1.2 * s, approach=4.0 * s, wall_radius=0.3 * s, wall_pitch=0.5 * s, flange=6.0 * s,
                duration=40.0, settle_time=90.0)


#: name -> (scenario keywords, seeds, stop early once all are home)
SCENES: dict[str, tuple[dict, int, bool]] = {
    "fig5": (dict(scenario="circle_obstacles", num_robots=20, settle_time=10.0), 1, False),
    "corridor22": (_corridor(2.2, 4), 1, True),
    "corridor16": (_corridor(1.6, 3), 1, True),
    "tb3corridor22": (_corridor(2.2, 4, TB3, "turtlebot3_burger"), 1, True),
    "tb3corridor16": (_corridor(1.6, 3, TB3, "turtlebot3_burger"), 1, True),
    "doorway": (dict(scenario="doorway", left=2, right=2, door=1.6, room=5.0, duration=15.0, settle_time=60.0),
                200, True),
    "field": (dict(scenario="obstacle_field", num_robots=5, density=0.1, arena_size=9.0, settle_time=30.0), 200,
              True),
    "circle6": (dict(scenario="circle_swap", num_robots=39, radius=6.0, duration=12.0, settle_time=10.0), 1, False),
    "circle6n20": (dict(scenario="circle_swap", num_robots=20, radius=6.0, duration=12.0, settle_time=10.0), 1,
                   False),
    "circle10": (dict(scenario="circle_swap", num_robots=60, radius=10.0, duration=20.0, settle_time=10.0), 1,
                 False),
    "random30": (dict(scenario="random_goals", num_robots=30, settle_time=10.0), 1, False),
}


def _unreachable(ro, p_end: np.ndarray, k: int) -> bool:
    """Whether robot ``k``'s goal lies outside the free-space component of ``p_end`` (obstacles only).

    Free space: centres farther than the robot's radius + an obstacle's radius - 2 cm (a robot touching a wall is
    in it) from every obstacle, on a 2 cm grid; each end snaps to the nearest free cell within 10 cm (none:
    the point is walled in, no path).
    """
    from scipy import ndimage

    if not ro.n_obstacles:
        return False
    pts = np.concatenate((p_end[None], ro.goals[k][None], ro.obstacle_centers))
    lo, hi, h = pts.min(axis=0) - 2.0, pts.max(axis=0) + 2.0, 0.02
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0], h), np.arange(lo[1], hi[1], h), indexing="ij")
    free = np.ones(gx.shape, dtype=bool)
    for c, r in zip(ro.obstacle_centers, ro.obstacle_radii):
        free &= (gx - c[0]) ** 2 + (gy - c[1]) ** 2 >= (r + ro.radii[k] - h) ** 2
    lab, _ = ndimage.label(free)

    def label_at(q: np.ndarray) -> int:
        i, j = np.round((q - lo) / h).astype(int)
        if lab[i, j]:
            return int(lab[i, j])
        win = lab[max(i - 5, 0):i + 6, max(j - 5, 0):j + 6]  # else the nearest free cell within 10 cm
        if not win.any():
            return 0
        ci, cj = np.nonzero(win)
        near = np.argmin((ci + max(i - 5, 0) - i) ** 2 + (cj + max(j - 5, 0) - j) ** 2)
        return int(win[ci[near], cj[near]])

    a, b = label_at(p_end), label_at(ro.goals[k])
    return a == 0 or b == 0 or a != b


def _episode(key: dict) -> dict:
    from aasoatt_env import FilterConfig, make_env
    from aasoatt_env.analysis.metrics import liveness, pairwise_min_distance, tracking_stats
    from aasoatt_env.analysis.recording import RecordEpisode
    from agents import TrackingController

    kw, _, stop = SCENES[key["scene"]]
    env = RecordEpisode(make_env(filter=FilterConfig(mode=key["mode"], deadlock=key["deadlock"]), **kw))
    agent = TrackingController()
    t0 = time.perf_counter()
    obs, _ = env.reset(seed=key["seed"])
    agent.reset(env)
    base = env.unwrapped
    dt, home_for = base.dt, 0
    while env.agents:
        obs, *_ = env.step(agent.act(obs, env))
        if stop:
            d = np.linalg.norm(base.kinematics.p - base.reference[0], axis=1)
            home_for = home_for + 1 if bool(np.all(d <= key["tol"])) and base.time >= base.layout.reference.duration \
                else 0
            if home_for * dt >= 2.0:
                break
    ro = env.rollout
    wall = time.perf_counter() - t0
    live = liveness(ro, goal_tolerance=key["tol"])
    sep = pairwise_min_distance(ro)
    fe = np.linalg.norm(ro.positions[-1] - ro.goals, axis=1)
    out = [int(k) for k in np.flatnonzero(fe > key["tol"])]
    why = ["no path" if _unreachable(ro, ro.positions[-1, k], k) else "stuck" for k in out]
    gaps = [g for g in (sep.overall_min_robot_gap, sep.overall_min_obstacle_gap) if np.isfinite(g)]
    return {**key, **live, "min_gap": float(min(gaps)) if gaps else None,
            "min_robot_gap": float(sep.overall_min_robot_gap) if np.isfinite(sep.overall_min_robot_gap) else None,
            "rmse": tracking_stats(ro)["rmse"], "not_home": out, "why": why, "t_end": float(ro.times[-1]),
            "wall_s": wall}


def _key_id(k: dict) -> str:
    return f"{k['scene']}/seed={k['seed']}/{k['mode']}/{k['deadlock']}/tol={k['tol']}"


def _records(path: Path) -> list[dict]:
    if not path.is_file():
        return []
    out = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError as exc:
            raise SystemExit(f"error: --out {path}: line {n} is not a JSON record ({exc})") from None
    return out


def run(args: argparse.Namespace) -> None:
    path = Path(args.out)
    done = {_key_id(r) for r in _records(path)}
    keys = [dict(scene=s, seed=seed, mode=m, deadlock=d, tol=args.tol) for s in args.scenes for d in args.deadlock
            for m in args.modes for seed in range(args.first_seed, args.first_seed + min(args.seeds, SCENES[s][1]))]
    keys = sorted((k for k in keys if _key_id(k) not in done), key=lambda k: k["seed"])  # (seeds interleaved)
    path.parent.mkdir(parents=True, exist_ok=True)
    print(f"{len(keys)} episodes to run ({len(done)} done)", flush=True)
    with path.open("a") as fh, Pool(args.jobs) as pool:
        for rec in pool.imap_unordered(_episode, keys):
            fh.write(json.dumps(rec | {"command": command_line()}) + "\n")
            fh.flush()
            print(f"{_key_id(rec)}: home {rec['home']}/{rec['n_robots']} makespan {rec['makespan']} "
                  f"gap {rec['min_gap']} {rec['why']} {rec['wall_s']:.0f}s", flush=True)


def _row(scene: str, mode: str, dl: str, rs: list[dict]) -> str:
    home, n = sum(r["home"] for r in rs), sum(r["n_robots"] for r in rs)
    ratios = [r["makespan_ratio"] for r in rs if r["makespan_ratio"] is not None]
    spans = [r["makespan"] for r in rs if r["makespan"] is not None]
    gaps = [r["min_gap"] for r in rs if r["min_gap"] is not None]
    col = sum(1 for r in rs if r["min_gap"] is not None and r["min_gap"] < -1e-3)
    nopath = sum(w == "no path" for r in rs for w in r["why"])
    span = f"{np.median(spans):.1f}" if spans else "-"
    ratio = f"{np.median(ratios):.2f} / {max(ratios):.2f}" if ratios else "-"
    return (f"| {scene} | {mode} | {dl} | {len(rs)} | {home}/{n} ({home / n:.1%}) | {nopath} | "
            f"{sum(len(r['not_home']) for r in rs) - nopath} | {span} | {ratio} | "
            f"{np.mean([r['stalled_time_mean'] for r in rs]):.2f} | {min(gaps):+.4f} | {col} | "
            f"{np.mean([r['rmse'] for r in rs]):.4f} |")


def summary(args: argparse.Namespace) -> None:
    recs = [r for path in args.out.split(",") for r in _records(Path(path))]
    if not recs:
        raise SystemExit(f"error: --out {args.out}: no results")
    last = {_key_id(r): r for r in recs}
    out = ["| scene | mode | deadlock | episodes | robots home | not home: no path | not home: stuck | "
           "makespan [s] (median) | makespan / straight-line bound (median / max) | stalled time per robot [s] | "
           "closest gap [m] | episodes with a collision | RMSE [m] |",
           "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    groups: dict[tuple, list[dict]] = {}
    for r in last.values():
        groups.setdefault((r["scene"], r["mode"], r["deadlock"]), []).append(r)
    for (scene, mode, dl) in sorted(groups, key=lambda g: (list(SCENES).index(g[0]), g[1], g[2])):
        out.append(_row(scene, mode, dl, groups[(scene, mode, dl)]))
    bad = [r for r in last.values() if r["not_home"]]
    if bad:
        out.append("\nEpisodes with a robot not home (robot: why):\n")
        out += [f"- {_key_id(r)}: " + ", ".join(f"{k}: {w}" for k, w in zip(r["not_home"], r["why"]))
                for r in sorted(bad, key=_key_id)]
    text = "\n".join(out)
    print(text)
    write_page(args, "Liveness campaign", text + "\n\n" + __doc__.split("Usage")[0], recs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=("run", "summary"))
    ap.add_argument("--scenes", type=lambda v: tuple(v.split(",")), default=tuple(SCENES),
                    help=f"comma-separated, among {list(SCENES)}")
    ap.add_argument("--modes", type=lambda v: tuple(v.split(",")), default=("centralized", "decentralized"))
    ap.add_argument("--deadlock", type=lambda v: tuple(v.split(",")), default=("yield",),
                    help="deadlock strategies, comma-separated (FilterConfig.deadlock)")
    ap.add_argument("--seeds", type=int, default=200, help="seeds per scene at most (a scene's own count caps it)")
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--tol", type=float, default=0.05, help="goal tolerance [m]")
    ap.add_argument("--jobs", type=int, default=1, help="episodes in parallel processes")
    ap.add_argument("--out", default="results/liveness.jsonl",
                    help="JSONL results (appended; resumable); summary: several, comma-separated")
    add_page_options(ap)
    args = ap.parse_args()
    check_page(args)
    unknown = [s for s in args.scenes if s not in SCENES]
    if unknown:
        ap.error(f"--scenes: got {unknown}, expected names among {list(SCENES)}")
    if args.seeds < 1 or args.jobs < 1 or args.first_seed < 0 or not args.tol > 0:
        ap.error("--seeds/--jobs: expected integers >= 1; --first-seed >= 0; --tol > 0")
    {"run": run, "summary": summary}[args.what](args)


if __name__ == "__main__":
    main()
