r"""The safe-RL comparison: trained bare vs trained behind the filter vs with a correction penalty.

Usage::

    python -m train.compare                      # what the README shows (see "Budget" below)
    python -m train.compare --full               # the full set: every variant from scratch, 3 seeds, 2 scenes
    python -m train.compare --scenes random_goals_6r --seeds 0 --episodes 5 --out-dir results/try

Variants (one policy per seed):

=====================  ====================================================================
``bare``               (a) the default recipe, trained bare (``TrainConfig`` defaults)
``filter``             (b) trained behind ``AASOATTFilter`` (correction penalty 0)
``filter+correction``  (c) trained behind the filter with ``reward.correction`` (``--correction``)
=====================  ====================================================================

Each policy is evaluated bare and behind the filter on the same ``--episodes``
seeded episodes (seeds 10000, 10001, ...; :func:`train.evaluate.evaluate_agent`):
success (within 0.1 m of the goal at the end), RMSE, collisions, safe rate,
filter intervention rate and mean correction; plus the training wall time.
The table gives the mean over seeds and, after ``±``, the spread (half the
range, lowest to highest).  A learning-curve figure per scene is drawn from the
runs' ``metrics.csv``.

Scenes: ``random_goals_6r`` (the default: 6 robots, 6.25 m arena) and
``crowded_12r`` (12 robots in a 6.5 m arena: 1.9x the density).

Budget: training behind the filter costs several times more per agent-step than
bare training, with one filter call per physics step for all teams (README,
"Batched stepping").  By default (b) and (c) therefore *fine-tune* each
seed's bare policy (a) behind the filter for ``--filter-steps`` agent-steps
(``init_from``; rollouts of ``--filter-n-steps`` 64 per slot: with the
recipe's 32 envs x 6 robots 12,288 agent-steps per update, so the default
61,440 make 5 updates);
``--filter-start scratch`` (implied by ``--full``) trains them from
scratch for ``--bare-steps`` like (a).  Finished runs and evaluations are
reused (``--out-dir`` is a cache): rerunning after an interruption continues;
a finished run trained with other settings stops the command.

Outputs in ``--out-dir``: ``runs/<scene>/<variant>_s<seed>/`` (training runs),
``evals/*.json``, ``compare.md`` (the tables), ``compare.json`` (every number),
``learning_curves_<scene>.png``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from aasoatt_env.api.factory import make_env
from aasoatt_env.cli_support import OutputPlan, Parser, int_option, real_option, run_guarded
from aasoatt_env.errors import ConfigError, DataFileError
from agents.run_files import read_json
from train.config import TrainConfig
from train.runs import write_json, write_text

__all__ = ["SCENES", "VARIANTS", "main", "run_comparison"]

SCENES: dict[str, dict[str, Any]] = {
    "random_goals_6r": {"scenario": "random_goals", "num_robots": 6},
    "crowded_12r": {"scenario": "random_goals", "num_robots": 12, "scenario_kwargs": {"arena_size": 6.5}},
}
"""Scene name -> :class:`TrainConfig` fields."""

VARIANTS: tuple[str, ...] = ("bare", "filter", "filter+correction")
_EVALS = ("bare", "filter")


def _scene_config(scene: str, **fields: Any) -> TrainConfig:
    return TrainConfig(**{**SCENES[scene], **fields})


def _finished(run: Path) -> bool:
    return (run / "model.zip").is_file() and (run / "train_stats.json").is_file()


_BOOKKEEPING = ("out_dir", "run_name", "progress_bar", "tensorboard", "checkpoint_freq", "verbose", "device",
                "torch_threads", "num_workers")
"""Config fields that do not change what a run learns: a cached run may differ in these."""


def _check_cached(run: Path, cfg: TrainConfig) -> None:
    """Raise :class:`ConfigError` if the finished ``run`` was trained with other settings than ``cfg``.

    A finished run is reused, so it must be the run these settings would train (a
    changed default recipe, a different ``--correction``, ...): otherwise one table
    would mix runs of different settings without saying so.
    """
    try:
        done = read_json(run / "config.json")
    except DataFileError as err:
        raise ConfigError(f"{run}: a finished run without a readable config.json is in the way ({err}); remove "
                          "it to retrain it") from None
    want = json.loads(json.dumps(cfg.to_dict()))  # the types config.json holds (lists, not tuples)
    if done.get("init_from") and want.get("init_from"):  # the same folder, however it was written
        done["init_from"], want["init_from"] = (str(Path(v).resolve()) for v in (done["init_from"], want["init_from"]))
    shown = []
    for k in sorted(k for k in want if k not in _BOOKKEEPING and done.get(k) != want[k]):
        old, new = done.get(k), want[k]
        if isinstance(old, dict) and isinstance(new, dict):  # name the entries: reward.correction 1.0 (asked 2.0)
            shown += [f"{k}.{e} {old.get(e)!r} (asked {new.get(e)!r})" for e in sorted(set(old) | set(new))
                      if old.get(e) != new.get(e)]
        else:
            shown.append(f"{k} {old!r} (asked {new!r})")
    if shown:
        raise ConfigError(f"{run}: a finished run with other settings is in the way: {', '.join(shown)}; use "
                          "another --out-dir, or remove the run to retrain it")


def _check_options(scenes: Sequence[str], seeds: Sequence[int], variants: Sequence[str], bare_steps: int,
                   filter_steps: int, filter_start: str, filter_n_steps: int, correction: float, episodes: int,
                   eval_seed: int) -> None:
    """Raise :class:`ConfigError` naming the first bad option of :func:`run_comparison` (before anything runs)."""
    def is_int(v: Any) -> bool:
        return isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))

    for name, values, known in (("scenes", scenes, list(SCENES)), ("variants", variants, list(VARIANTS))):
        if isinstance(values, str) or not list(values):
            raise ConfigError(f"--{name}: got {values!r}, expected one or more names among {known}")
        bad = [v for v in values if v not in known]
        if bad:
            raise ConfigError(f"--{name}: got {bad}, expected names among {known}")
    for name, values in (("scenes", scenes), ("seeds", seeds), ("variants", variants)):
        dup = sorted({str(v) for v in values if list(values).count(v) > 1})
        if dup:
            raise ConfigError(f"--{name}: got {', '.join(dup)} more than once, expected each at most once")
    if isinstance(seeds, str) or not list(seeds) or not all(is_int(s) and s >= 0 for s in seeds):
        raise ConfigError(f"--seeds: got {list(seeds) if not isinstance(seeds, str) else seeds!r}, expected one or "
                          "more integers >= 0")
    for name, value in (("bare-steps", bare_steps), ("filter-steps", filter_steps),
                        ("filter-n-steps", filter_n_steps), ("episodes", episodes)):
        if not is_int(value) or value < 1:
            raise ConfigError(f"--{name}: got {value!r}, expected an integer >= 1")
    if not is_int(eval_seed) or eval_seed < 0:
        raise ConfigError(f"eval_seed: got {eval_seed!r}, expected an integer >= 0")
    if filter_start not in ("bare", "scratch"):
        raise ConfigError(f"--filter-start: got {filter_start!r}, expected 'bare' or 'scratch'")
    ok = isinstance(correction, (int, float, np.integer, np.floating)) and not isinstance(correction, bool)
    if not (ok and math.isfinite(correction) and correction >= 0):
        raise ConfigError(f"--correction: got {correction!r}, expected a finite number >= 0")


def _model_digest(run: Path) -> str:
    """SHA-256 of the run's ``model.zip``: an evaluation cache belongs to one trained model."""
    return hashlib.sha256((run / "model.zip").read_bytes()).hexdigest()


def _train(run: Path, cfg: TrainConfig, log: Any) -> dict[str, Any]:
    """Train ``cfg`` into ``run`` unless a finished run of the same settings is there; its ``train_stats.json``."""
    from train.train import train

    if _finished(run):
        _check_cached(run, cfg)
    else:
        if run.exists() and any(run.iterdir()):
            raise ConfigError(f"{run}: an unfinished run is in the way (no train_stats.json); remove it first")
        print(f"[compare] training {run}", file=log, flush=True)
        train(cfg)
    return read_json(run / "train_stats.json")


def _evaluate(run: Path, scene_cfg: TrainConfig, filtered: bool, episodes: int, seed: int, cache: Path,
              log: Any) -> dict[str, Any]:
    """Evaluate the policy of ``run`` on ``scene_cfg``'s env, bare or behind the filter (cached in ``cache``).

    The cache holds the SHA-256 of the ``model.zip`` it evaluated: after a run
    was removed and retrained, its evaluations are made again, not reused.
    """
    from agents.learned import LearnedAgent
    from train.evaluate import evaluate_agent

    digest = _model_digest(run)
    if cache.is_file():
        data = read_json(cache)
        if data.get("episodes") == episodes and data.get("seed") == seed and data.get("model_sha256") == digest:
            return data
    print(f"[compare] evaluating {run} {'behind the filter' if filtered else 'bare'} ({episodes} episodes)",
          file=log, flush=True)
    agent = LearnedAgent.load(run)
    kw = {**scene_cfg.env_kwargs(), "terminate_on_collision": False, "reward": {}}
    fc = scene_cfg.filter_config() if filtered else None
    row = evaluate_agent(run.name, agent, lambda: make_env(**kw, filter=fc), episodes, seed)
    data = {**row.as_dict(), "seed": seed, "model_sha256": digest}
    cache.parent.mkdir(parents=True, exist_ok=True)
    write_json(cache, data)
    return data


def _plan(out: Path, scenes: Sequence[str], seeds: Sequence[int], variants: Sequence[str], bare_steps: int,
          filter_steps: int, filter_start: str, filter_n_steps: int, correction: float) -> dict[tuple, TrainConfig]:
    """The :class:`TrainConfig` of every run, keyed ``(scene, seed, variant)``: all validated before any trains."""
    plan: dict[tuple, TrainConfig] = {}
    fine = filter_start == "bare"
    for scene in scenes:
        for seed in seeds:
            bare_run = out / "runs" / scene / f"bare_s{seed}"
            common = dict(out_dir=str(out / "runs" / scene), seed=seed, progress_bar=True, tensorboard=False,
                          checkpoint_freq=0)
            plan[scene, seed, "bare"] = _scene_config(scene, total_timesteps=bare_steps, run_name=bare_run.name,
                                                      **common)
            for variant in variants:
                if variant == "bare":
                    continue
                reward = {"correction": correction} if variant == "filter+correction" else {}
                tune = {"n_steps": filter_n_steps} if fine else {}
                plan[scene, seed, variant] = _scene_config(
                    scene, filter=True, reward=reward, run_name=f"{variant.replace('+', '_')}_s{seed}", **tune,
                    total_timesteps=filter_steps if fine else bare_steps, init_from=str(bare_run) if fine else None,
                    **common)
    return plan


def _entry(out: Path, scene: str, seed: int, variant: str, plan: dict[tuple, TrainConfig], bare_stats: Any,
           settings: dict[str, Any], log: Any) -> dict[str, Any] | None:
    """One run's row of ``compare.json``: trained (or reused) and evaluated bare and behind the filter.

    With ``settings["table_only"]`` nothing is trained or evaluated: None where the run or an
    evaluation is missing.
    """
    table_only, filter_start = settings["table_only"], settings["filter_start"]
    run = out / "runs" / scene / f"{variant.replace('+', '_')}_s{seed}"
    caches = [out / "evals" / f"{scene}_{run.name}_{mode}.json" for mode in _EVALS]
    if table_only and not (_finished(run) and all(c.is_file() for c in caches)):
        return None
    config = read_json(run / "config.json") if table_only else None
    if table_only:
        stats = read_json(run / "train_stats.json")
        start = Path(config["init_from"]).name if config and config.get("init_from") else None
    elif variant == "bare":
        stats, start = bare_stats, None
    else:
        stats = _train(run, plan[scene, seed, variant], log)
        start = (out / "runs" / scene / f"bare_s{seed}").name if filter_start == "bare" else None
    config = config or read_json(run / "config.json")
    entry: dict[str, Any] = {
        "scene": scene, "variant": variant, "seed": seed, "run": str(run), "init_from": start,
        "train_wall_s": stats["wall_time_s"], "train_agent_steps": stats["agent_steps"],
        "train_agent_steps_per_s": stats["agent_steps_per_s"],
        "total_wall_s": stats["wall_time_s"] + (bare_stats["wall_time_s"] if start and bare_stats else 0),
        "correction_weight": config["reward"].get("correction", 0.0),
    }
    digest = _model_digest(run) if table_only else None
    for mode, cache in zip(_EVALS, caches):
        if table_only:
            ev = read_json(cache)
            if ev.get("model_sha256", digest) != digest:
                raise ConfigError(f"{cache}: the evaluation of another model than {run}/model.zip "
                                  "(retrained since); run without --table-only to evaluate it")
            entry[f"eval_{mode}"] = ev
        else:
            entry[f"eval_{mode}"] = _evaluate(run, _scene_config(scene), mode == "filter", settings["episodes"],
                                              settings["eval_seed"], cache, log)
    return entry


def run_comparison(
    out_dir: str | Path = "results/compare",
    *,
    scenes: Sequence[str] = tuple(SCENES),
    seeds: Sequence[int] = (0, 1, 2),
    variants: Sequence[str] = VARIANTS,
    bare_steps: int = 1_228_800,
    filter_steps: int = 61_440,
    filter_start: str = "bare",
    filter_n_steps: int = 64,
    correction: float = 1.0,
    episodes: int = 20,
    eval_seed: int = 10_000,
    table_only: bool = False,
    log: Any = None,
) -> dict[str, Any]:
    """Train, evaluate and tabulate (module docstring); returns what ``compare.json`` holds.

    ``table_only``: train and evaluate nothing; tabulate the finished runs and evaluations found
    in ``out_dir`` among those asked for (the others are left out).

    Raises
    ------
    ConfigError
        A bad option or a run whose :class:`TrainConfig` is invalid: all checked before anything
        is trained, evaluated or written; with ``table_only``, nothing to tabulate.
    """
    log = log or sys.stdout
    _check_options(scenes, seeds, variants, bare_steps, filter_steps, filter_start, filter_n_steps, correction,
                   episodes, eval_seed)
    scenes, seeds, variants = list(scenes), [int(s) for s in seeds], list(variants)
    out = Path(out_dir)
    plan = {} if table_only else _plan(out, scenes, seeds, variants, bare_steps, filter_steps, filter_start,
                                       filter_n_steps, float(correction))  # every run's settings checked up front
    if not table_only:
        OutputPlan(overwrite=True).folder(out, "--out-dir")  # a cache: reused, so existing content is fine
    t_start = time.perf_counter()
    settings = {"scenes": {s: SCENES[s] for s in scenes}, "seeds": list(seeds), "variants": list(variants),
                "bare_steps": bare_steps, "filter_steps": filter_steps, "filter_start": filter_start,
                "filter_n_steps": filter_n_steps, "correction": float(correction), "episodes": episodes,
                "eval_seed": eval_seed}
    results: dict[str, Any] = {"settings": settings, "runs": []}
    for scene in scenes:
        for seed in seeds:
            bare_run = out / "runs" / scene / f"bare_s{seed}"
            if table_only:
                bare_stats = read_json(bare_run / "train_stats.json") if _finished(bare_run) else None
            elif "bare" in variants or filter_start == "bare":
                bare_stats = _train(bare_run, plan[scene, seed, "bare"], log)
            else:
                bare_stats = None
            for variant in variants:
                entry = _entry(out, scene, seed, variant, plan, bare_stats, {**settings, "table_only": table_only},
                               log)
                if entry is not None:
                    results["runs"].append(entry)
    if table_only and not results["runs"]:  # an empty table would replace the one there
        raise ConfigError(f"--table-only: {out} holds no finished, evaluated run among those asked for (scenes "
                          f"{scenes}, seeds {seeds}, variants {variants}); run without --table-only first")
    results["wall_time_s"] = time.perf_counter() - t_start
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "compare.json", results)
    write_text(out / "compare.md", to_markdown(results))
    for scene in scenes:
        _figure(results, scene, out / f"learning_curves_{scene}.png")
    return results


# ---------------------------------------------------------------------- tables and figures
def _agg(values: list[float], pct: bool = False, digits: int = 3) -> str:
    vals = [v for v in values if v is not None and v == v]
    if not vals:
        return "-"
    scale = 100.0 if pct else 1.0
    mean, half = scale * float(np.mean(vals)), scale * (max(vals) - min(vals)) / 2
    d = 1 if pct else digits
    text = f"{mean:.{d}f}" + ("%" if pct else "")
    return text + (f" ± {half:.{d}f}" if len(vals) > 1 else "")


_LABEL = {"bare": "(a) trained bare", "filter": "(b) trained behind the filter",
          "filter+correction": "(c) behind the filter + correction penalty"}


def to_markdown(results: dict[str, Any]) -> str:
    """The comparison tables (one per scene), mean ± half-range over seeds."""
    st = results["settings"]
    lines = []
    for scene in st["scenes"]:
        runs = [r for r in results["runs"] if r["scene"] == scene]
        if not runs:
            continue
        cfg = SCENES[scene]
        lines += [f"### {scene}: {cfg['num_robots']} robots"
                  + (f", arena {cfg['scenario_kwargs']['arena_size']} m" if "scenario_kwargs" in cfg else ""), "",
                  "| policy | deployed | success | RMSE [m] | collisions, all seeds (episodes) | safe rate "
                  "| intervention | correction [rad/s^2] | training wall [s] |",
                  "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
        for variant in st["variants"]:
            rs = [r for r in runs if r["variant"] == variant]
            if not rs:
                continue
            for mode in _EVALS:
                ev = [r[f"eval_{mode}"] for r in rs]
                col = sum(int(e["collisions"]) for e in ev)
                col_ep = sum(int(e["collision_episodes"]) for e in ev)
                wall = _agg([r["total_wall_s"] for r in rs], digits=0)
                lines.append(
                    f"| {_LABEL[variant]} | {'behind the filter' if mode == 'filter' else 'bare'} "
                    f"| {_agg([e['success_rate'] for e in ev], pct=True)} | {_agg([e['rmse'] for e in ev])} "
                    f"| {col} ({col_ep}) | {_agg([e['safe_rate'] for e in ev], pct=True)} "
                    f"| {_agg([e['intervention_rate'] for e in ev], pct=True)} "
                    f"| {_agg([e['mean_correction'] for e in ev])} | {wall} |")
        lines.append("")
        both = ({r["seed"] for r in runs if r["variant"] == "filter+correction"}
                & {r["seed"] for r in runs if r["variant"] == "bare"})
        base = [r["eval_filter"]["mean_correction"] for r in runs if r["variant"] == "bare" and r["seed"] in both]
        pen = [r["eval_filter"]["mean_correction"] for r in runs
               if r["variant"] == "filter+correction" and r["seed"] in both]
        if base and pen and None not in base + pen:  # (null: not measured, written so by write_json)
            cut = 100 * (1 - np.mean(pen) / np.mean(base))
            lines += [f"Mean filter correction behind the filter, (c) vs (a) on the same seeds: {np.mean(pen):.3f} vs "
                      f"{np.mean(base):.3f} rad/s^2 ({f'{cut:.1f}% less' if cut >= 0 else f'{-cut:.1f}% more'}).",
                      ""]
        lines += [_settings_note(runs), ""]
    return "\n".join(lines) + "\n"


def _settings_note(runs: list[dict[str, Any]]) -> str:
    """What was run for one scene, read from the runs themselves."""
    parts = []
    for variant in VARIANTS:
        rs = [r for r in runs if r["variant"] == variant]
        if not rs:
            continue
        steps = sorted({int(r["train_agent_steps"]) for r in rs})
        text = f"{_LABEL[variant].split(' ', 1)[0]} seeds {', '.join(str(r['seed']) for r in rs)}: " + (
            f"fine-tuned from (a) of the same seed for {'/'.join(f'{x:,}' for x in steps)} agent-steps"
            if rs[0].get("init_from") else f"{'/'.join(f'{x:,}' for x in steps)} agent-steps")
        weights = sorted({float(r.get("correction_weight", 0.0)) for r in rs})
        if variant == "filter+correction":
            text += f", correction weight {'/'.join(f'{w:g}' for w in weights)}"
        parts.append(text)
    ev = runs[0]["eval_filter"]
    first = int(ev.get("seed", 10_000))
    tuned = any(r.get("init_from") for r in runs)
    return ("; ".join(parts) + f". {ev['episodes']} evaluation episodes per row (seeds {first}-"
            f"{first + int(ev['episodes']) - 1}); mean ± half the range over seeds; collisions summed over "
            "seeds" + ("; training wall time of (b)/(c) includes the bare run they start from." if tuned else "."))


def _figure(results: dict[str, Any], scene: str, path: Path) -> None:
    from train.telemetry import plot_learning_curve, read_metrics

    curves: dict[str, list[list[dict[str, float]]]] = {}
    for r in results["runs"]:
        if r["scene"] != scene:
            continue
        rows = read_metrics(Path(r["run"]) / "metrics.csv")
        if r["init_from"]:  # a fine-tuned run continues its bare run's curve
            offset = read_metrics(Path(r["run"]).parent / r["init_from"] / "metrics.csv")[-1]["agent_steps"]
            rows = [{**row, "agent_steps": row["agent_steps"] + offset} for row in rows]
        curves.setdefault(_LABEL[r["variant"]], []).append(rows)
    if curves:
        try:
            plot_learning_curve(curves, path, title=f"{scene}: training telemetry (rollouts of the training runs)")
        except ImportError:  # matplotlib is optional
            pass


# ---------------------------------------------------------------------- command line
def build_parser(prog: str = "python -m train.compare") -> argparse.ArgumentParser:
    """Command-line parser."""
    p = Parser(prog=prog, description="Safe-RL comparison: trained bare / behind the filter / with a correction "
               "penalty, each evaluated bare and behind the filter.")
    p.add_argument("--out-dir", default="results/compare", help="runs, evaluations and tables (reused when rerun)")
    p.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    p.add_argument("--seeds", nargs="+", type=int_option(0), default=[0, 1, 2], help="training seeds (>= 0)")
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    p.add_argument("--bare-steps", type=int_option(1), default=1_228_800, help="agent-steps of (a)")
    p.add_argument("--filter-steps", type=int_option(1), default=61_440,
                   help="agent-steps of (b)/(c) fine-tuning behind the filter (with --filter-start bare)")
    p.add_argument("--filter-n-steps", type=int_option(1), default=64,
                   help="rollout length per slot of the fine-tuning runs (more updates for few agent-steps)")
    p.add_argument("--filter-start", choices=("bare", "scratch"), default="bare",
                   help="(b)/(c) fine-tune each seed's (a) (bare, default) or train from scratch for --bare-steps")
    p.add_argument("--correction", type=real_option(0.0), default=1.0,
                   help="reward.correction of (c) (a finite number >= 0)")
    p.add_argument("--episodes", type=int_option(1), default=20, help="evaluation episodes per policy and mode")
    p.add_argument("--table-only", action="store_true",
                   help="train and evaluate nothing: tabulate the finished runs and evaluations in --out-dir")
    p.add_argument("--full", action="store_true",
                   help="the full set: every variant from scratch (--filter-start scratch), 3 seeds, both scenes")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point."""
    argv = list(sys.argv[1:] if argv is None else argv)
    return run_guarded("train.compare", argv, _main)


def _main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    start = "scratch" if args.full else args.filter_start
    results = run_comparison(args.out_dir, scenes=args.scenes, seeds=args.seeds, variants=args.variants,
                             bare_steps=args.bare_steps, filter_steps=args.filter_steps, filter_start=start,
                             filter_n_steps=args.filter_n_steps, table_only=args.table_only,
                             correction=args.correction, episodes=args.episodes)
    print((Path(args.out_dir) / "compare.md").read_text())
    print(f"wall time {results['wall_time_s']:.0f} s (runs and evaluations already in {args.out_dir} are reused)")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
