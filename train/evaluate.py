r"""Evaluate baselines and learned policies over K seeded episodes; one Markdown table.

Usage::

    python -m train.evaluate --bare runs/ppo_bare/model.zip --filtered runs/ppo_filter/model.zip \\
        --episodes 100 --out results.md
    aasoatt evaluate ...          # the same flags

A learned policy is a Stable-Baselines3 run (:mod:`train.train`) or a Ray RLlib run
(:mod:`train.rllib`, recognised by the ``"backend": "rllib"`` of its ``policy.json``; evaluated
without starting Ray), see :func:`agents.learned.load_learned`.

Rows (by default every row whose model is given; a row asked for with ``--rows`` whose
model is not given is an error naming the missing option):

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
:class:`~train.config.TrainConfig`; ``terminate_on_collision`` is off.  The settings a
policy depends on (:data:`POLICY_ENV_KEYS`) must be those it was trained with: a config or
a second policy that differs in one of them is refused before the first episode
(:func:`policy_env_kwargs`, which ``aasoatt run --controller learned`` uses too).

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

Each rate comes with its 95% Wilson score interval (:func:`train.intervals.wilson`): success over
robot-episodes (each robot of each episode one trial), and the share of episodes with a collision
over episodes.  Intervals assume independent trials; robots of one episode interact, so the
success interval is a lower bound on the uncertainty.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import time
from collections.abc import Callable, Mapping, Sequence
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
from train.config import TrainConfig
from train.intervals import wilson
from train.policies import POLICY_ENV_KEYS, load_policy, policy_env_kwargs
from train.runs import check_path, write_json, write_text

__all__ = ["POLICY_ENV_KEYS", "EvalRow", "evaluate", "evaluate_agent", "load_policy", "main", "policy_env_kwargs",
           "to_markdown"]

_PARAM_NAMES = {"rows": "rows", "bare": "bare_model", "filter": "filtered_model", "config": "config"}
"""How errors name evaluate()'s inputs by default (the command line passes its option names instead)."""


@dataclass
class EvalRow:
    """Aggregated metrics of one agent/env combination over the episodes (rates with 95% Wilson intervals)."""

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
    robot_episodes: int = 0
    success_ci: tuple[float, float] = (float("nan"), float("nan"))
    collision_episode_ci: tuple[float, float] = (float("nan"), float("nan"))
    extra: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """JSON-friendly dict."""
        return {k: list(v) if isinstance(v, tuple) else v
                for k, v in ((k, getattr(self, k)) for k in self.__dataclass_fields__)}


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
    per_episode: list[dict[str, Any]] = []
    filter_infos: list[dict[str, Any]] = []
    it: Any = range(episodes)
    if progress:
        from tqdm import tqdm

        it = tqdm(it, desc=name, unit="episode")
    t0 = time.perf_counter()
    for j in it:
        obs, _ = env.reset(seed=seed + j)
        agent.reset(env)
        while env.agents:
            obs, _, _, _, infos = env.step(agent.act(obs, env))
            filter_infos += [info["filter"] for info in infos.values() if info.get("filter") is not None]
        per_episode.append(summarize(env.rollout, goal_tolerance=goal_tolerance))
    env.close()
    return _row(name, per_episode, filter_infos, time.perf_counter() - t0)


def _row(name: str, per_episode: list[dict[str, Any]], filter_infos: list[dict[str, Any]], wall: float) -> EvalRow:
    """Aggregate the episodes' :func:`summarize` dicts and the filter's per-decision infos into a row."""
    hits = [int(s["n_collision_pairs"]) + int(s["n_obstacle_collisions"]) for s in per_episode]
    robot_episodes = sum(int(s["n_robots"]) for s in per_episode)
    reached = sum(s["reach_rate"] * s["n_robots"] for s in per_episode)
    collided = sum(h > 0 for h in hits)
    statuses: dict[str, int] = {}
    for f in filter_infos:
        statuses[f["status"]] = statuses.get(f["status"], 0) + 1
    has_filter = bool(filter_infos)
    return EvalRow(
        name=name, episodes=len(per_episode), safe_rate=float(np.mean([s["safe_rate"] for s in per_episode])),
        success_rate=float(np.mean([s["reach_rate"] for s in per_episode])),
        rmse=float(np.mean([s["rmse"] for s in per_episode])),
        intervention_rate=float(np.mean([float(f["intervened"]) for f in filter_infos])) if has_filter else None,
        mean_correction=float(np.mean([float(f["correction"]) for f in filter_infos])) if has_filter else None,
        collisions=sum(hits), collision_episodes=int(collided), wall_time_s=wall, robot_episodes=robot_episodes,
        success_ci=wilson(round(reached), robot_episodes), collision_episode_ci=wilson(collided, len(per_episode)),
        extra={"filter_status": statuses} if has_filter else {},
    )


ROWS = ("random", "tracking", "tracking + filter", "learned (bare)", "learned (bare) + filter",
        "learned (filter)", "learned (filter) + filter")
"""Row names, in table order (``learned (filter)``: the policy trained behind the filter, run bare)."""


def _env_of(learned: dict[str, Any], labels: dict[str, str], config: TrainConfig | None,
            names: Mapping[str, str]) -> tuple[dict[str, Any], FilterConfig]:
    """The env keywords and filter of the table: the config's, else the first policy's; every policy's settings."""
    first = "bare" if learned["bare"] is not None else "filter" if learned["filter"] is not None else None
    if config is not None:
        env_kwargs, fc = config.env_kwargs(), config.filter_config()
    elif first is not None:
        spec = learned[first].spec
        env_kwargs, fc = dict(spec["env"]), FilterConfig.merged(spec.get("filter") or {})
    else:
        default = TrainConfig(progress_bar=False)
        env_kwargs, fc = default.env_kwargs(), default.filter_config()
    for key, policy in learned.items():  # each policy runs on the env it was trained for: checked now
        if policy is not None:
            if config is not None:
                source, hint = names["config"], " (give a config with the run's env settings)"
            else:
                source, hint = f"the env of {labels[first]}", " (evaluate the two policies separately)"
            env_kwargs = policy_env_kwargs(policy, env_kwargs, model=labels[key], default_option=source, hint=hint)
    return env_kwargs, fc


def _load_models(models: dict[str, Any], names: Mapping[str, str], jobs: int) -> tuple[dict[str, Any], dict[str, str]]:
    """The policies (loaded from paths, or given loaded) and how errors name each."""
    if not isinstance(jobs, int) or not 1 <= jobs <= 256:
        raise ConfigError(f"jobs: got {jobs!r}, expected an integer in [1, 256]")
    is_path = {k: isinstance(m, (str, os.PathLike)) for k, m in models.items()}
    if jobs > 1:
        loaded = [names[k] for k, m in models.items() if m is not None and not is_path[k]]
        if loaded:
            raise ConfigError(f"jobs: got {jobs} with a loaded policy ({loaded[0]}), expected model paths "
                              "(the worker processes load them) or jobs=1")
    learned = {k: None if m is None else load_policy(m, names[k]) if is_path[k] else m for k, m in models.items()}
    labels = {k: f"{names[k]} {str(m)!r}" if is_path[k] else names[k] for k, m in models.items()}
    return learned, labels


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
    option_names: Mapping[str, str] | None = None,
) -> list[EvalRow]:
    """Evaluate the table's rows (see the module docstring) and return them.

    Parameters
    ----------
    bare_model, filtered_model : path or policy, optional
        Policies trained bare and behind the filter: a run folder, model ``.zip`` or checkpoint of
        either backend (:func:`train.policies.load_policy`), or a loaded policy (only with ``jobs=1``).
    episodes : int
        Episodes per row (``K``); episode ``j`` is reset with ``seed + j``.
    seed : int
        Seed of the first episode.
    config : TrainConfig, optional
        Env settings; default: the first given model's, else :class:`TrainConfig` defaults.
    filter_kwargs : dict, optional
        Filter arguments for the ``+ filter`` rows (default: the config's).
    rows : sequence of str, optional
        Subset of :data:`ROWS` (default all whose model is given); a ``learned (...)`` row needs its model.
    goal_tolerance : float
        Success radius [m].
    progress : bool
        Progress bars.
    jobs : int
        Rows evaluated in parallel processes (the same numbers as ``jobs=1``).
    option_names : mapping, optional
        How errors name ``"rows"``, ``"bare"``, ``"filter"`` and ``"config"`` (default the parameter names).

    Raises
    ------
    ConfigError
        An unknown row, a ``learned (...)`` row without its model, or a config (or second
        policy) whose env differs from a policy's training in a :data:`POLICY_ENV_KEYS` setting.
    """
    wanted = list(rows) if rows is not None else list(ROWS)
    bad = [r for r in wanted if r not in ROWS]
    if bad:
        raise ConfigError(f"rows: got {bad}, expected names among {list(ROWS)}")
    names = {**_PARAM_NAMES, **(option_names or {})}
    if rows is not None:  # rows asked for must be made; by default the rows whose model is given
        check_rows(wanted, bare_model is not None, filtered_model is not None, names)
    learned, labels = _load_models({"bare": bare_model, "filter": filtered_model}, names, jobs)
    env_kwargs, fc = _env_of(learned, labels, config, names)
    if filter_kwargs is not None:
        fc = FilterConfig.merged(fc, **filter_kwargs)
    if jobs > 1:
        return _evaluate_parallel(bare_model, filtered_model, wanted, jobs, episodes=episodes, seed=seed,
                                  config=config, filter_kwargs=filter_kwargs, goal_tolerance=goal_tolerance)
    env_kwargs.update(terminate_on_collision=False, reward={})
    mode = env_kwargs.get("action_mode", "wheel")
    plan: list[tuple[str, Callable[[], Any], bool]] = [
        ("random", lambda: RandomAgent(seed=seed), False),
        ("tracking", lambda: _tracking(mode, False), False),
        ("tracking + filter", lambda: _tracking(mode, True), True),
    ]
    for key, label in (("bare", "learned (bare)"), ("filter", "learned (filter)")):
        if learned[key] is not None:
            plan += [(label, lambda k=key: learned[k], False), (f"{label} + filter", lambda k=key: learned[k], True)]
    return [evaluate_agent(name, agent_fn(), lambda f=filtered: make_env(**env_kwargs, filter=fc if f else None),
                           episodes, seed, goal_tolerance, progress)
            for name, agent_fn, filtered in plan if name in wanted]


def check_rows(rows: Sequence[str], bare: bool, filtered: bool, names: Mapping[str, str] | None = None) -> None:
    """Refuse a ``learned (...)`` row whose model is not given (errors name ``names``' options)."""
    n = {**_PARAM_NAMES, **(names or {})}
    for row in rows:
        for prefix, given, key, what in (("learned (bare)", bare, "bare", "a policy trained bare"),
                                         ("learned (filter)", filtered, "filter", "a policy trained behind the "
                                          "filter")):
            if row.startswith(prefix) and not given:
                raise ConfigError(f"{n['rows']}: got {row!r}, which needs {n[key]} ({what}); expected {n[key]} "
                                  "or other rows")


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


def _pct(x: float | None, ci: tuple[float, float] | None = None) -> str:
    if x is None:
        return "-"
    out = f"{100 * x:.1f}%"
    if ci is not None and all(np.isfinite(ci)):
        out += f" [{100 * ci[0]:.1f}, {100 * ci[1]:.1f}]"
    return out


def to_markdown(rows: Sequence[EvalRow], title: str | None = None) -> str:
    """One Markdown table of the rows (rates in percent, 95% Wilson intervals in brackets)."""
    lines = [f"### {title}", ""] if title else []
    lines += [
        "| agent | episodes | safe rate | success [95% CI] | RMSE [m] | intervention "
        "| correction [rad/s^2] | collisions (episodes) | episodes with a collision [95% CI] |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        corr = "-" if r.mean_correction is None else f"{r.mean_correction:.3f}"
        lines.append(
            f"| {r.name} | {r.episodes} | {_pct(r.safe_rate)} | {_pct(r.success_rate, r.success_ci)} | {r.rmse:.3f} "
            f"| {_pct(r.intervention_rate)} | {corr} | {r.collisions} ({r.collision_episodes}) "
            f"| {_pct(r.collision_episodes / max(r.episodes, 1), r.collision_episode_ci)} |"
        )
    return "\n".join(lines)


def build_parser(prog: str = "aasoatt evaluate") -> argparse.ArgumentParser:
    """Command-line parser."""
    p = Parser(prog=prog, description="Evaluate baselines and learned policies (Markdown table, 95% intervals).")
    p.add_argument("--bare", default=None, help="model trained bare (run folder or model.zip; SB3 or RLlib run)")
    p.add_argument("--filtered", default=None, help="model trained behind the filter")
    p.add_argument("--episodes", type=int_option(1, 10**6), default=100)
    p.add_argument("--seed", type=int_option(0, 2**62), default=10_000)
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


_OPTIONS = {"rows": "--rows", "bare": "--bare", "filter": "--filtered", "config": "--config"}


def _outputs(args: argparse.Namespace, plan: OutputPlan) -> tuple[Path | None, Path | None]:
    """The table and its ``.json`` (``--out``), checked and their folder made writable before any episode."""
    if args.out is None:
        return None, None
    out = Path(check_path(args.out, "--out"))
    if out.suffix.lower() == ".json":
        raise ConfigError(f"--out: got {args.out!r}; the table is Markdown and its .json goes beside it, "
                          "expected e.g. results.md")
    if out.name in ("", ".", "..") or args.out.endswith(os.sep):
        raise ConfigError(f"--out: got {args.out!r}, expected a file path such as results.md")
    return plan.file(out, "--out"), plan.file(out.with_suffix(".json"), "--out (its .json)")


def _main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    check_rows(args.rows or (), args.bare is not None, args.filtered is not None, _OPTIONS)
    plan = OutputPlan(args.overwrite)
    out, json_out = _outputs(args, plan)
    try:
        config = TrainConfig.from_file(args.config) if args.config else None
        fk = parse_assignments(args.filter_arg, "--filter-arg") if args.filter_arg else None
        if fk is not None:
            try:
                FilterConfig.merged(fk)
            except UnknownKeywordError as exc:
                raise UnknownKeywordError(f"--filter-arg: {exc}") from None
        # evaluate() loads the models (every file checked, before any episode or worker starts)
        rows = evaluate(args.bare, args.filtered, episodes=args.episodes, seed=args.seed, config=config,
                        filter_kwargs=fk, rows=args.rows, goal_tolerance=args.goal_tolerance,
                        progress=not args.quiet and args.jobs == 1, jobs=args.jobs, option_names=_OPTIONS)
    except BaseException:
        plan.discard()
        raise
    table = to_markdown(rows)
    print(table)
    if out is not None and json_out is not None:
        write_text(out, f"```bash\n{shlex.join(['aasoatt', 'evaluate', *argv])}\n```\n\n{table}\n")  # (its command)
        write_json(json_out, [r.as_dict() for r in rows])
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
