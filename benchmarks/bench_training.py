"""PPO training throughput (agent-steps/s), bare and behind the safety filter, in one run.

    python benchmarks/bench_training.py [--timesteps 36864] [--rounds 3] [--robots 6] [--n-envs 32] [--model RUN]
                                        [--workers W] [--rllib]

Each row trains PPO with the default recipe (``TrainConfig`` defaults: 32 teams x N
robots stepped by one batched physics call, decision_interval 20; behind the filter one
filter call per physics step for all teams, or, for comparison, one per team) with rollouts
of ``--n-steps`` (the recipe's 64) per slot, for ``--timesteps`` agent-steps after one warm-up
update, and reports what a training run sees: rollout collection plus PPO
updates, one torch thread.  The rows take turns: each trains ``--timesteps / --rounds``
agent-steps per round (one PPO update by default), so a drift of the machine's speed
hits every row alike; each row's rate is its median over the rounds, and the filtered /
bare ratio is also printed per round (the two rows run back to back).  The filter's share
of the filtered row is measured by timing its calls; the third row steps the same teams
one by one (:class:`train.vec_env.ParallelVecEnv`), for comparison.  ``--workers W`` adds a bare and a
filtered row with the teams split over ``W`` processes (``TrainConfig.num_workers``,
:class:`~aasoatt_env.sim.sharded.ShardedBatchedEnv`; the filter's calls are then not timed):
they show what more cores buy, so compare them only with idle cores.

``--rllib`` (in the virtual environment of the ``rllib`` extra) adds the same training with Ray
RLlib (:mod:`train.rllib`, the same batch of ``--n-envs`` teams x ``--robots`` robots x
``--n-steps`` decisions per iteration, minibatch and epochs), bare and behind the filter, sampled
in the driver (``num_env_runners=0``: one process, like ``aasoatt train``), taking turns with the
Stable-Baselines3 rows; it reports each row's agent-steps/s end to end (sampling and updates, one
env runner: the driver) and the ratio to ``aasoatt train``'s (one process, one core) in the same rounds.

``--model RUN`` starts every row from a trained policy (``init_from``): the
filter's cost depends on how often it has to act, which is far more often for
the random actions of a fresh policy than for a trained one.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from page import add_page_options, check_page, printed_page

from train.config import TrainConfig
from train.train import build_model, init_policy, make_vec_env


def separate_vec_env(cfg: TrainConfig):
    """The same stack with the teams stepped one by one (``ParallelVecEnv``), for comparison."""
    from train.train import make_env
    from train.vec_env import ParallelVecEnv, SlotMonitor, SlotNormalize

    venv = SlotMonitor(ParallelVecEnv([lambda: make_env(cfg) for _ in range(cfg.n_envs)]))
    return SlotNormalize(venv, norm_obs=cfg.normalize_obs, norm_reward=cfg.normalize_reward, gamma=cfg.gamma,
                         clip_obs=10.0)


class Row:
    """One loop of the table: its vec env and PPO model, built once and warmed up, then timed in chunks."""

    def __init__(self, filtered: bool, robots: int, n_envs: int, solver: str | None, model: str | None,
                 n_steps: int, batched: bool = True, grouped: bool = True, workers: int = 1) -> None:
        kw = {"filter_kwargs": {"solver": solver}} if (filtered and solver) else {}
        cfg = TrainConfig(num_robots=robots, n_envs=n_envs, filter=filtered, progress_bar=False, tensorboard=False,
                          checkpoint_freq=0, n_steps=n_steps, batch_size=min(1024, n_steps * n_envs * robots),
                          init_from=model, num_workers=workers, **kw)
        self.venv = make_vec_env(cfg, group_filter=grouped) if batched else separate_vec_env(cfg)
        self.ppo = build_model(cfg, self.venv)
        if model:
            init_policy(self.ppo, self.venv, cfg)
        self.filter_time = [0.0]
        self.calls: list[float] = []
        self.timed = filtered and workers == 1
        if self.timed:  # time every filter call (the grouped one, or one per team and physics step)
            batch = self.venv.unwrapped.batch  # (batched only)
            filter_time, calls = self.filter_time, self.calls

            def timed(f: Any) -> _Timed:
                call = f.__call__

                def run(inp: Any, du: np.ndarray) -> Any:
                    t = time.perf_counter()
                    out = call(inp, du)
                    dt = time.perf_counter() - t
                    filter_time[0] += dt
                    calls.append(dt)
                    return out

                return _Timed(f, run)

            if batch.grouped_filter is not None:
                batch._grouped = timed(batch.grouped_filter)
            else:
                for base in batch._bases:
                    base._control_filter = timed(base.control_filter)
        self.per_update = cfg.n_steps * self.venv.num_envs
        self.ppo.learn(self.per_update)  # warm-up
        self.filter_time[0] = 0.0
        self.calls.clear()
        self.steps, self.wall, self.rates = 0, 0.0, []

    def run(self, timesteps: int) -> None:
        """Train ``timesteps`` more agent-steps (whole updates), timed."""
        start = self.ppo.num_timesteps
        t0 = time.perf_counter()
        self.ppo.learn(max(timesteps, self.per_update), reset_num_timesteps=False)
        dt = time.perf_counter() - t0
        steps = self.ppo.num_timesteps - start
        self.steps += steps
        self.wall += dt
        self.rates.append(steps / dt)

    def close(self) -> None:
        self.venv.close()


def stepping_rate(robots: int, n_envs: int, workers: int, decisions: int = 40) -> float:
    """Agent-steps/s of the filtered batch alone (no policy, no PPO): uniform random actions, after 5 decisions."""
    from aasoatt_env.sim.batched import BatchedAASOATTEnv
    from aasoatt_env.sim.sharded import ShardedBatchedEnv
    from train.train import make_env

    cfg = TrainConfig(num_robots=robots, n_envs=n_envs, filter=True, progress_bar=False, tensorboard=False,
                      checkpoint_freq=0)
    fns = [lambda: make_env(cfg) for _ in range(n_envs)]
    batch = ShardedBatchedEnv(fns, workers) if workers > 1 else BatchedAASOATTEnv(fns)
    try:
        batch.reset(seed=0)
        rng = np.random.default_rng(0)
        for _ in range(5):
            batch.step(rng.uniform(-1.0, 1.0, (n_envs, robots, 2)))
        t = time.perf_counter()
        for _ in range(decisions):
            batch.step(rng.uniform(-1.0, 1.0, (n_envs, robots, 2)))
        return decisions * n_envs * robots / (time.perf_counter() - t)
    finally:
        batch.close()


class RLlibRow:
    """RLlib PPO on the same teams and batch, sampled in the driver; timed per ``Algorithm.train()`` call."""

    def __init__(self, filtered: bool, robots: int, n_envs: int, n_steps: int) -> None:
        from ray.tune.registry import register_env

        from train.rllib import ENV_NAME, RLlibConfig, build_algorithm_config
        from train.rllib_env import make_rllib_env

        cfg = RLlibConfig(num_robots=robots, filter=filtered, num_envs_per_env_runner=n_envs,
                          train_batch_size=n_steps * n_envs * robots, verbose=0)
        register_env(ENV_NAME, make_rllib_env)
        self.algo = build_algorithm_config(cfg).build_algo()
        self.algo.train()  # warm-up
        self.steps, self.wall, self.rates = 0, 0.0, []

    def run(self, timesteps: int) -> None:
        """Train whole iterations until ``timesteps`` more agent-steps are done."""
        done, wall = 0, 0.0
        while done < timesteps:
            t0 = time.perf_counter()
            result = self.algo.train()
            wall += time.perf_counter() - t0
            done += int(result["env_runners"]["num_env_steps_sampled"])
        self.steps += done
        self.wall += wall
        self.rates.append(done / wall)

    def close(self) -> None:
        self.algo.stop()


def rllib_rows(args: argparse.Namespace, sb3: dict[bool, Row]) -> None:
    """Time RLlib bare and behind the filter, taking turns with the Stable-Baselines3 rows ``sb3``."""
    import ray

    ray.init(num_cpus=2, include_dashboard=False, logging_level="ERROR")
    try:
        rows = {f: RLlibRow(f, args.robots, args.n_envs, args.n_steps) for f in (False, True)}
        chunk = max(args.timesteps // args.rounds, 1)
        for _ in range(args.rounds):
            for f in (False, True):
                sb3[f].run(chunk)
                rows[f].run(chunk)
        print("\n| loop | agent-steps | RLlib agent-steps/s per env runner | aasoatt train agent-steps/s per core "
              "(same rounds) | RLlib / aasoatt train | per round |")
        print("|---|---:|---:|---:|---:|---|")
        for f, row in rows.items():
            mine = sb3[f].rates[-args.rounds:]
            rate, theirs = float(np.median(row.rates)), float(np.median(mine))
            rounds = ", ".join(f"{100 * a / b:.0f}%" for a, b in zip(row.rates, mine))
            name = "RLlib, behind the filter" if f else "RLlib, bare"
            print(f"| {name} | {row.steps} | {rate:,.0f} | {theirs:,.0f} | {100 * rate / theirs:.0f}% | {rounds} |",
                  flush=True)
            row.close()
    finally:
        ray.shutdown()


class _Timed:
    """A control filter whose calls are timed (protocol attributes passed through)."""

    def __init__(self, inner: Any, call: Callable[[Any, np.ndarray], Any]) -> None:
        self._inner, self._call = inner, call
        self.keeps_input_bounds = inner.keeps_input_bounds

    def reset(self, team: Any) -> None:
        self._inner.reset(team)

    def reset_rows(self, rows: np.ndarray, team: Any) -> None:
        self._inner.reset_rows(rows, team)

    def __call__(self, inp: Any, du: np.ndarray) -> Any:
        return self._call(inp, du)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--timesteps", type=int, default=36_864, help="agent-steps per row, over all rounds")
    p.add_argument("--rounds", type=int, default=3,
                   help="each row is timed in this many chunks, the rows taking turns (rates: medians)")
    p.add_argument("--robots", type=int, default=6)
    p.add_argument("--n-envs", type=int, default=TrainConfig.n_envs,
                   help="teams in all (the recipe's; split over the processes with --workers)")
    p.add_argument("--n-steps", type=int, default=TrainConfig.n_steps, help="rollout length per slot (the recipe's)")
    p.add_argument("--solver", default=None, help="filter QP solver (default: the filter's default)")
    p.add_argument("--model", default=None, help="start from this trained run (init_from)")
    p.add_argument("--workers", type=int, default=1,
                   help="also rows with the teams stepped in this many processes (num_workers; 1: no such rows)")
    p.add_argument("--rllib", action="store_true", help="also Ray RLlib rows (needs the rllib extra)")
    add_page_options(p)
    args = p.parse_args()
    check_page(args)
    if args.rounds < 1 or args.timesteps < 1:
        p.error(f"--rounds and --timesteps: got {args.rounds} and {args.timesteps}, expected positive numbers")
    with printed_page(args, "Training throughput", __doc__.split("Usage")[0] if __doc__ else ""):
        _run(args)


def _run(args: argparse.Namespace) -> None:
    torch.set_num_threads(1)
    print(f"PPO throughput, {args.n_envs} envs x {args.robots} robots (batched), decision_interval 20 (dt 0.005), "
          f"policy: {args.model or 'fresh (random actions)'}\n")
    print("| loop | agent-steps | agent-steps/s | physics steps/s (per team) | filter share of wall time | "
          "ms per filter call (median) |")
    print("|---|---:|---:|---:|---:|---:|")
    rates = {}
    solver = args.solver or "default solver"
    rows = [("bare", False, True, True),
            (f"behind the filter ({solver}), one filter call for all teams", True, True, True),
            ("bare, teams stepped one by one (ParallelVecEnv)", False, False, True),
            (f"behind the filter ({solver}), one filter call per team", True, True, False)]
    rows = [(*r, 1) for r in rows]
    if args.workers > 1:
        w = args.workers
        rows += [(f"bare, {w} worker processes", False, True, True, w),
                 (f"behind the filter ({solver}), one filter call per worker, {w} worker processes", True, True, True,
                  w)]
    built = [(name, filtered, batched, grouped, workers,
              Row(filtered, args.robots, args.n_envs, args.solver, args.model, args.n_steps, batched, grouped,
                  workers)) for name, filtered, batched, grouped, workers in rows]
    chunk = max(args.timesteps // args.rounds, 1)
    for _ in range(args.rounds):  # every row a chunk per round: the machine's drifts hit every row alike
        for *_, row in built:
            row.run(chunk)
    if args.rllib:
        rllib_rows(args, {f: row for _, f, batched, grouped, workers, row in built if batched and grouped
                          and workers == 1})
    ratios: dict[tuple, list[float]] = {}
    for name, filtered, batched, grouped, workers, row in built:
        rate = float(np.median(row.rates))
        if batched:
            rates[filtered, grouped, workers] = rate
            ratios[filtered, grouped, workers] = row.rates
        share = f"{100 * row.filter_time[0] / row.wall:.0f}%" if row.timed else "-"
        call = f"{1e3 * float(np.median(row.calls)):.3f}" if row.timed else "-"
        print(f"| {name} | {row.steps} | {rate:,.0f} | {rate / args.robots * 20:,.0f} | {share} | {call} |", flush=True)
        row.close()
    rounds_pct = [100 * f / b for f, b in zip(ratios[True, True, 1], ratios[False, True, 1])]
    print("\nper round, behind the filter (one call for all teams) / bare: "
          + ", ".join(f"{r:.1f}%" for r in rounds_pct))
    bare = rates[False, True, 1]
    print(f"\nbehind the filter / bare: {100 * rates[True, True, 1] / bare:.1f}% (one call for all teams), "
          f"{100 * rates[True, False, 1] / bare:.1f}% (one call per team)")
    if args.workers > 1:
        w = args.workers
        one, many = (stepping_rate(args.robots, args.n_envs, k) for k in (1, w))
        print(f"stepping alone behind the filter (no policy, no PPO; uniform random actions): {one:,.0f} "
              f"agent-steps/s in one process, {many:,.0f} with {w} workers ({many / one:.2f}x)")
        print(f"with {w} worker processes: behind the filter {100 * rates[True, True, w] / bare:.1f}% of the "
              f"one-process bare rate, {100 * rates[True, True, w] / rates[False, True, w]:.1f}% of bare with "
              f"{w} workers; {rates[True, True, w] / rates[True, True, 1]:.2f}x the one-process filtered rate")


if __name__ == "__main__":
    main()
