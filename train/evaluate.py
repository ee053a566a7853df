r"""Evaluate baselines and learned policies over K seeded episodes; one Markdown table.

Usage::

    python -m train.evaluate --bare runs/ppo_bare/model.zip --filtered runs/ppo_filter/model.zip \\
        --episodes 100 --out results.md
    aasoatt evaluate ...          # the same flags

A learned policy is a Stable-Baselines3 run (:mod:`train.train`) or a Ray RLlib run
(:mod:`train.rllib`, recognised by the ``"backend": "rllib"`` of its ``policy.json``; evaluated
without starting Ray), see :func:`agents.learned.load_learned`.

Rows (a row is skipped when its model is not given):

=======================================  ==========================================
row                                      agent / env
=======================================  ==========================================
``random``                               uniform random actions, bare env
``tracking``                             the paper's tracking law, bare env
``tracking + filter``                    tracking law behind ``AASOATTFilter``
``learned (bare)``                       policy trained bare, bare env
``learned (bare) + filter``              the same policy behind the filter
``learned (filter)``                     policy trained behind the filter, bare env
``learned (filter) + filter``            policy trained behind the filter, behind it
=======================================  ==========================================

Every row runs the same episodes: episode ``j`` is reset with ``seed + j``, on
the env of the (first) learned policy's ``config.json`` (scenario, robots,
``dt``, ``decision_interval``, action mode), or of the given
:class:`~train.config.TrainConfig`; ``terminate_on_collision`` is off.

Columns (means over episodes; per episode from :func:`aasoatt_env.analysis.metrics.summarize`
on the rollout recorded at the decision rate, and from ``infos[agent]["filter"]``):

* **safe rate**: fraction of robots that never collide (robot or obstacle);
* **success**: fraction of robots within ``goal_tolerance`` of their goal at the end;
* **RMSE**: tracking error ``|p - p_d|`` [m], pooled over robots and steps;
* **intervention**: fraction of robot-decisions where the filter changed the
  nominal at some physics step;
* **correction**: mean over robot-decisions of the largest
  ``|du_safe - du_nominal|`` in the decision [rad/s^2];
* **collisions**: total colliding robot pairs plus robot-obstacle hits over
  all episodes, and the number of episodes with any.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from aasoatt_env.analysis.metrics import summarize
from aasoatt_env.analysis.recording import RecordEpisode
from aasoatt_env.api.factory import make_env
from aasoatt_env.cli_support import OutputPlan, Parser, add_common_options, int_option, real_option, run_guarded
from aasoatt_env.errors import ConfigError, UnknownKeywordError
from aasoatt_env.safety.config import FilterConfig
from aasoatt_env.validation import parse_assignments
from agents import RandomAgent, TrackingController
from agents.learned import load_learned
from train.config import TrainConfig

__all__ = ["EvalRow", "evaluate", "evaluate_agent", "main", "to_markdown"]


@dataclass
class EvalRow:
    """Aggregated metrics of one agent/env combination over the episodes."""

    name: str
    episodes: int
    safe_rate: float
    success_rate: float
    rmse: float
    intervention_rate: float | None
    mean_correction: float | None
    collisions: int
    collision_episodes: int
    wall_time_s: float
    extra: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """JSON-friendly dict."""
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


class _PointModeAdapter:
    """Run an analytic controller (``point_accel(env)``) on a ``action_mode="point"`` env.

    ``action = a / max_point_accel``, clipped to ``[-1, 1]`` on a bare env,
    unclipped (the nominal) behind the filter.
    """

    def __init__(self, controller: Any, saturate: bool) -> None:
        self.controller = controller
        self.saturate = saturate

    def reset(self, env: Any) -> None:
        self.controller.reset(env)

    def act(self, observations: dict[str, np.ndarray], env: Any) -> dict[str, np.ndarray]:
        base = env.unwrapped
        act = self.controller.point_accel(env) / base.team.max_point_accel[:, None]
        if self.saturate:
            act = np.clip(act, -1.0, 1.0)
        act = act.astype(np.float32)
        idx = base.agent_index
        return {a: act[idx[a]] for a in env.agents}


def _tracking(action_mode: str, filtered: bool) -> Any:
    if action_mode == "wheel":
        return TrackingController(saturate=not filtered)
    return _PointModeAdapter(TrackingController(), saturate=not filtered)


def evaluate_agent(
    name: str,
    agent: Any,
    env_fn: Callable[[], Any],
    episodes: int,
    seed: int = 10_000,
    goal_tolerance: float = 0.1,
    progress: bool = False,
) -> EvalRow:
    """Run ``agent`` for ``episodes`` seeded episodes of ``env_fn()`` and aggregate the metrics.

    Parameters
    ----------
    name : str
        Row label.
    agent : Agent
        ``reset(env)`` / ``act(observations, env)``.
    env_fn : callable
        Builds the (bare or filtered) parallel env (called once).
    episodes : int
        Number of episodes; episode ``j`` is reset with ``seed + j``.
    seed : int
        First episode seed.
    goal_tolerance : float
        Success radius [m].
    progress : bool
        Show a tqdm bar.
    """
    if episodes < 1:
        raise ConfigError(f"episodes: got {episodes!r}, expected an integer >= 1")
    env = RecordEpisode(env_fn())
    safe, succ, rmse, n_col, col_eps = [], [], [], 0, 0
    interv: list[float] = []
    corr: list[float] = []
    statuses: dict[str, int] = {}
    has_filter = False
    it = range(episodes)
    if progress:
        from tqdm import tqdm

        it = tqdm(it, desc=name, unit="episode")
    t0 = time.perf_counter()
    for j in it:
        obs, _ = env.reset(seed=seed + j)
        agent.reset(env)
        while env.agents:
            obs, _, _, _, infos = env.step(agent.act(obs, env))
            for info in infos.values():
                f = info.get("filter")
                if f is not None:
                    has_filter = True
                    interv.append(float(f["intervened"]))
                    corr.append(float(f["correction"]))
                    statuses[f["status"]] = statuses.get(f["status"], 0) + 1
        s = summarize(env.rollout, goal_tolerance=goal_tolerance)
        safe.append(s["safe_rate"])
        succ.append(s["reach_rate"])
        rmse.append(s["rmse"])
        c = int(s["n_collision_pairs"]) + int(s["n_obstacle_collisions"])
        n_col += c
        col_eps += c > 0
    env.close()
    return EvalRow(
        name=name, episodes=episodes, safe_rate=float(np.mean(safe)), success_rate=float(np.mean(succ)),
        rmse=float(np.mean(rmse)),
        intervention_rate=float(np.mean(interv)) if has_filter else None,
        mean_correction=float(np.mean(corr)) if has_filter else None,
        collisions=n_col, collision_episodes=int(col_eps), wall_time_s=time.perf_counter() - t0,
        extra={"filter_status": statuses} if has_filter else {},
    )


ROWS = ("random", "tracking", "tracking + filter", "learned (bare)", "learned (bare) + filter",
        "learned (filter)", "learned (filter) + filter")
"""Row names, in table order (``learned (filter)``: the policy trained behind the filter, run bare)."""


def evaluate(
    bare_model: str | Path | None = None,
    filtered_model: str | Path | None = None,
    *,
    episodes: int = 100,
    seed: int = 10_000,
    config: TrainConfig | None = None,
    filter_kwargs: dict[str, Any] | None = None,
    rows: Sequence[str] | None = None,
    goal_tolerance: float = 0.1,
    progress: bool = False,
    jobs: int = 1,
) -> list[EvalRow]:
    """Evaluate the table's rows (see the module docstring) and return them.

    Parameters
    ----------
    bare_model, filtered_model : path, optional
        Policies trained bare and behind the filter: a Stable-Baselines3 run (folder or ``model.zip``)
        or a Ray RLlib run of :mod:`train.rllib` (folder or checkpoint), see :func:`agents.learned.load_learned`.
    episodes : int
        Episodes per row (``K``).
    seed : int
        Seed of the first episode (``seed + j`` for episode ``j``).
    config : TrainConfig, optional
        Env settings; default: the first given model's ``config.json``, else
        :class:`TrainConfig` defaults.
    filter_kwargs : dict, optional
        Filter arguments for the ``+ filter`` rows (default: the config's).
    rows : sequence of str, optional
        Subset of :data:`ROWS` (default all whose model is given).
    goal_tolerance : float
        Success radius [m].
    progress : bool
        Progress bars.
    jobs : int
        Rows evaluated in parallel processes (same numbers as ``jobs=1``: every
        row runs its own seeded episodes).

    Returns
    -------
    list of EvalRow
        Format with :func:`to_markdown`.
    """
    wanted = list(rows) if rows is not None else list(ROWS)
    bad = [r for r in wanted if r not in ROWS]
    if bad:
        raise ConfigError(f"rows: got {bad}, expected names among {list(ROWS)}")
    if not isinstance(jobs, int) or jobs < 1:
        raise ConfigError(f"jobs: got {jobs!r}, expected an integer >= 1")
    if jobs > 1:
        return _evaluate_parallel(bare_model, filtered_model, wanted, jobs, episodes=episodes, seed=seed,
                                  config=config, filter_kwargs=filter_kwargs, goal_tolerance=goal_tolerance)
    learned = {
        "bare": load_learned(bare_model) if bare_model is not None else None,
        "filter": load_learned(filtered_model) if filtered_model is not None else None,
    }
    first = learned["bare"] or learned["filter"]
    if config is not None:
        env_kwargs, fc = config.env_kwargs(), config.filter_config()
    elif first is not None:
        env_kwargs, fc = dict(first.spec["env"]), FilterConfig.merged(first.spec.get("filter") or {})
    else:
        default = TrainConfig(progress_bar=False)
        env_kwargs, fc = default.env_kwargs(), default.filter_config()
    if filter_kwargs is not None:
        fc = FilterConfig.merged(fc, **filter_kwargs)
    env_kwargs.update(terminate_on_collision=False, reward={})

    def env_fn(filtered: bool) -> Callable[[], Any]:
        return lambda: make_env(**env_kwargs, filter=fc if filtered else None)

    mode = env_kwargs.get("action_mode", "wheel")
    plan: list[tuple[str, Callable[[], Any], bool]] = [
        ("random", lambda: RandomAgent(seed=seed), False),
        ("tracking", lambda: _tracking(mode, False), False),
        ("tracking + filter", lambda: _tracking(mode, True), True),
    ]
    if learned["bare"] is not None:
        plan += [("learned (bare)", lambda: learned["bare"], False),
                 ("learned (bare) + filter", lambda: learned["bare"], True)]
    if learned["filter"] is not None:
        plan += [("learned (filter)", lambda: learned["filter"], False),
                 ("learned (filter) + filter", lambda: learned["filter"], True)]
    out = []
    for name, agent_fn, filtered in plan:
        if name in wanted:
            out.append(evaluate_agent(name, agent_fn(), env_fn(filtered), episodes, seed, goal_tolerance, progress))
    return out


def _evaluate_parallel(
    bare_model: str | Path | None, filtered_model: str | Path | None, wanted: list[str], jobs: int, **kw: Any
) -> list[EvalRow]:
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    given = {"learned (bare)": bare_model, "learned (bare) + filter": bare_model,
             "learned (filter)": filtered_model, "learned (filter) + filter": filtered_model}
    todo = [r for r in ROWS if r in wanted and given.get(r, True) is not None]
    with ProcessPoolExecutor(max_workers=min(jobs, max(len(todo), 1)), mp_context=mp.get_context("spawn")) as ex:
        futures = [ex.submit(evaluate, bare_model, filtered_model, rows=[r], **kw) for r in todo]
        return [row for f in futures for row in f.result()]


def _fmt(x: float | None, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def to_markdown(rows: Sequence[EvalRow], title: str | None = None) -> str:
    """One Markdown table of the rows (rates in percent)."""
    lines = []
    if title:
        lines += [f"### {title}", ""]
    lines += [
        "| agent | episodes | safe rate | success | RMSE [m] | intervention "
        "| correction [rad/s^2] | collisions (episodes) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        iv = None if r.intervention_rate is None else 100 * r.intervention_rate
        lines.append(
            f"| {r.name} | {r.episodes} | {100 * r.safe_rate:.1f}% | {100 * r.success_rate:.1f}% | {r.rmse:.3f} "
            f"| {_fmt(iv, '.1f')}{'%' if iv is not None else ''} | {_fmt(r.mean_correction, '.3f')} "
            f"| {r.collisions} ({r.collision_episodes}) |"
        )
    return "\n".join(lines)


def build_parser(prog: str = "aasoatt evaluate") -> argparse.ArgumentParser:
    """Command-line parser."""
    p = Parser(prog=prog, description="Evaluate baselines and learned policies (Markdown table).")
    p.add_argument("--bare", default=None, help="model trained bare (run folder or model.zip; SB3 or RLlib run)")
    p.add_argument("--filtered", default=None, help="model trained behind the filter")
    p.add_argument("--episodes", type=int_option(1, 10**7), default=100)
    p.add_argument("--seed", type=int_option(0), default=10_000)
    p.add_argument("--config", default=None, help="TOML/JSON TrainConfig for the env (default: the model's)")
    p.add_argument("--rows", nargs="+", default=None, choices=ROWS, metavar="ROW", help=f"subset of {list(ROWS)}")
    p.add_argument("--filter-arg", action="append", default=None, metavar="KEY=VALUE", help="filter argument")
    p.add_argument("--goal-tolerance", type=real_option(0.0, lo_open=True), default=0.1)
    p.add_argument("--out", default=None,
                   help="write the Markdown table to this file (and a .json beside it); "
                   "existing files need --overwrite")
    p.add_argument("--jobs", type=int_option(1, 256), default=1, help="rows evaluated in parallel processes")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    add_common_options(p)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point; prints the Markdown table.

    Options, the models, the config file and the output files are checked before
    the first episode; an existing table is replaced only with ``--overwrite``.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    return run_guarded("aasoatt evaluate", argv, _main)


def _main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    plan = OutputPlan(args.overwrite)
    out = json_out = None
    if args.out:
        if Path(args.out).suffix.lower() == ".json":
            raise ConfigError(f"--out: got {args.out!r}; the table is Markdown and its .json goes beside it, "
                              "expected e.g. results.md")
        out = plan.file(args.out, "--out")
        json_out = plan.file(out.with_suffix(".json"), "--out (its .json)")
    try:
        config = TrainConfig.from_file(args.config) if args.config else None
        fk = parse_assignments(args.filter_arg, "--filter-arg") if args.filter_arg else None
        if fk is not None:
            try:
                FilterConfig.merged(fk)
            except UnknownKeywordError as exc:
                raise UnknownKeywordError(f"--filter-arg: {exc}") from None
        if args.jobs > 1:  # with jobs=1, evaluate() loads the models before the first episode
            for model in (args.bare, args.filtered):
                if model is not None:
                    load_learned(model)  # every model file checked before any worker starts
        rows = evaluate(args.bare, args.filtered, episodes=args.episodes, seed=args.seed, config=config,
                        filter_kwargs=fk, rows=args.rows, goal_tolerance=args.goal_tolerance,
                        progress=not args.quiet and args.jobs == 1, jobs=args.jobs)
    except BaseException:
        plan.discard()
        raise
    table = to_markdown(rows)
    print(table)
    if out is not None and json_out is not None:
        out.write_text(table + "\n")
        json_out.write_text(json.dumps([r.as_dict() for r in rows], indent=2))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
