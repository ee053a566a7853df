"""The ``aasoatt`` command line.

``list``, ``run``, ``warm-up`` here; ``reproduce``, ``train``, ``evaluate`` in their modules.  Heavy libraries
(torch, Stable-Baselines3, Ray, matplotlib) are imported only by the commands that use them.
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import json
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from aasoatt_env import cli_support
from aasoatt_env.analysis.metrics import format_summary, summarize
from aasoatt_env.analysis.plotting import plot_trajectories
from aasoatt_env.analysis.recording import run_episode
from aasoatt_env.analysis.rollout import Rollout
from aasoatt_env.api.factory import make_env
from aasoatt_env.api.registration import ENV_IDS
from aasoatt_env.errors import AASOATTError, ConfigError, UnknownKeywordError
from aasoatt_env.safety import BARRIERS, STRATEGIES, TRIGGERS, available_solvers
from aasoatt_env.safety.config import FilterConfig
from aasoatt_env.sim.rendering import ANIMATION_SUFFIXES, animation_writer_missing, save_animation
from aasoatt_env.sim.scenarios import SCENARIOS
from aasoatt_env.sim.scenarios.base import MAX_ROBOTS
from aasoatt_env.validation import parse_assignments
from agents.base import agent_accepts, agent_names, get_agent

__all__ = ["main"]

RUN_OUTPUTS = ("metrics.json", "rollout.npz", "trajectories.png")  # what ``aasoatt run --out DIR`` writes

# commands whose module's main() parses their own options (--help included) and guards their own errors
_FORWARDED = {"reproduce": "aasoatt_env.apps.reproduce", "train": "train.train", "evaluate": "train.evaluate"}


def _parameters(scenario: str) -> dict[str, inspect.Parameter]:
    return {name: p for name, p in inspect.signature(SCENARIOS[scenario].__init__).parameters.items()
            if name != "self" and p.kind not in (inspect.Parameter.VAR_POSITIONAL, inspect.Parameter.VAR_KEYWORD)}


def _required_parameters(scenario: str) -> list[str]:
    """Parameters of ``scenario`` without a default (``custom``: ``starts`` and ``reference``)."""
    return [name for name, p in _parameters(scenario).items() if p.default is inspect.Parameter.empty]


def cmd_list(args: argparse.Namespace) -> int:
    """Print scenarios, controllers and filter options."""
    ids = {v: k for k, v in ENV_IDS.items()}
    print("Scenarios (--scenario NAME, parameters with -p KEY=VALUE):")
    for name, cls in SCENARIOS.items():
        doc = re.sub(r":\w+:`(~[\w.]*\.|\.)?([^`]+)`", r"\2", (cls.__doc__ or "").strip().splitlines()[0])  # (no roles)
        print(f"  {name:18s} id {ids.get(name, '-')}\n      {doc.replace('``', '')}")
        for pname, p in _parameters(name).items():
            print(f"      {pname}{'' if p.default is inspect.Parameter.empty else f' = {p.default!r}'}")
    for title, names in (("\nControllers (--controller NAME):", agent_names()), ("Barriers (--filter NAME):", BARRIERS),
                         ("Deadlock strategies (--deadlock):", STRATEGIES),
                         ("Deadlock triggers (--trigger):", TRIGGERS), ("QP solvers (--solver):", available_solvers())):
        print(title, ", ".join(names))
    return 0


def _filter_config(args: argparse.Namespace) -> FilterConfig | None:
    """The filter options of the command line as a :class:`FilterConfig` (None for ``--filter none``)."""
    if args.filter == "none":
        for flag, value, default in (("--deadlock", args.deadlock, "auxiliary_velocity"),
                                     ("--trigger", args.trigger, "multiplier"), ("--solver", args.solver, "proxsuite")):
            if value != default:
                raise ConfigError(f"{flag}: got {value!r} with --filter none, expected no filter options")
        if args.gain:
            raise ConfigError(f"-g/--gain: got {args.gain} with --filter none, expected no filter gains")
        return None
    if args.solver not in available_solvers():
        raise ConfigError(f"--solver: got {args.solver!r}, expected one of {available_solvers()}")
    gains = parse_assignments(args.gain, "-g/--gain")
    for key, flag in (("barrier", "--filter"), ("deadlock", "--deadlock"), ("trigger", "--trigger"),
                      ("solver", "--solver")):
        if key in gains:
            raise ConfigError(f"-g/--gain: got {key}={gains[key]!r}, expected {flag} for that")
    if "dt" in gains:
        raise ConfigError(f"-g/--gain: got dt={gains['dt']!r}; the filter runs at the env's physics step "
                          "(use -p dt=...)")
    try:
        return FilterConfig.merged(gains, barrier=args.filter, deadlock=args.deadlock, trigger=args.trigger,
                                   solver=args.solver)
    except UnknownKeywordError as exc:
        raise UnknownKeywordError(f"-g/--gain: {exc}") from None


def _env_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """The env keywords of ``-p``, ``--robots`` and ``--decision-interval``; required parameters must be given."""
    kwargs = parse_assignments(args.param, "-p/--param")
    if args.robots is not None:
        if "num_robots" in kwargs:
            raise ConfigError("--robots: given together with -p num_robots=..., expected one of them")
        kwargs["num_robots"] = args.robots
    for key in ("filter", "infos", "render_mode", "decision_interval"):
        if key in kwargs:
            raise ConfigError(f"-p/--param: got {key}=..., expected the command-line option for it")
    missing = [name for name in _required_parameters(args.scenario) if name not in kwargs]
    if missing:
        raise ConfigError(f"--scenario {args.scenario}: missing required parameter(s) {', '.join(missing)}; "
                          f"expected {' '.join(f'-p {name}=...' for name in missing)} (aasoatt list shows them)")
    if args.decision_interval is not None:
        kwargs["decision_interval"] = args.decision_interval
    return kwargs


def _env_and_agent(args: argparse.Namespace, kwargs: dict[str, Any], filter_config: FilterConfig | None
                   ) -> tuple[Any, Any]:
    """The env and controller of ``aasoatt run``; ``--controller learned``: the env settings of its run."""
    agent = None
    if args.controller == "learned":
        from train.evaluate import load_policy, policy_env_kwargs

        agent = load_policy(args.model, "--model")
        kwargs = policy_env_kwargs(agent, kwargs, model=f"--model {args.model!r}",
                                   options={"decision_interval": "--decision-interval"}, default_option="-p/--param")
    kwargs.setdefault("decision_interval", 1)
    try:
        env = make_env(args.scenario, filter=filter_config, render_mode="rgb_array" if args.gif else None, **kwargs)
    except UnknownKeywordError as exc:
        raise UnknownKeywordError(f"-p/--param: {exc}") from None
    if agent is not None:
        agent.reset(env)  # observation layout and action mode checked before the episode
        return env, agent
    ctrl_kwargs: dict[str, Any] = {"saturate": filter_config is None} if args.controller in ("tracking", "pd") else {}
    if agent_accepts(args.controller, "seed"):
        ctrl_kwargs["seed"] = args.seed
    return env, get_agent(args.controller, **ctrl_kwargs)


def _write_results(out: Path, summary: dict[str, Any], rollout: Rollout, title: str) -> None:
    """``metrics.json``, ``rollout.npz`` and ``trajectories.png`` (without matplotlib: no plot), all or none."""
    try:
        fig = plot_trajectories(rollout.positions, radii=rollout.radii, references=rollout.references,
                                goals=rollout.goals, obstacles=(rollout.obstacle_centers, rollout.obstacle_radii),
                                title=title)
    except ImportError as exc:
        fig = None
        print(f"(no trajectory plot: {exc})", file=sys.stderr)
    with cli_support.staged(*(out / name for name in RUN_OUTPUTS[: 3 if fig is not None else 2])) as temps:
        temps[0].write_text(json.dumps(summary, indent=2))
        rollout.save(temps[1])
        if fig is not None:
            fig.savefig(temps[2], dpi=150, format="png")
    print(f"wrote {out}/{', '.join(RUN_OUTPUTS[: 3 if fig is not None else 2])}")


def cmd_run(args: argparse.Namespace) -> int:
    """Run one episode and report its metrics (options, then output paths, then the env are checked first)."""
    if args.model is not None and args.controller != "learned":
        raise ConfigError(f"--model: given with --controller {args.controller!r}, expected --controller learned")
    if args.model is None and args.controller == "learned":
        raise ConfigError("controller 'learned': got no model path, expected --model PATH (a run folder or .zip)")
    kwargs, filter_config = _env_kwargs(args), _filter_config(args)
    with cli_support.OutputPlan(args.overwrite) as plan:
        out = plan.folder(args.out, "--out", entries=RUN_OUTPUTS) if args.out is not None else None
        gif = plan.file(args.gif, "--gif", suffixes=ANIMATION_SUFFIXES) if args.gif is not None else None
        if gif is not None and animation_writer_missing(gif.suffix):
            extra = ", ".join(animation_writer_missing(gif.suffix))
            raise ConfigError(f"--gif: got {str(gif)!r}, but writing {gif.suffix!r} needs {extra}, which is not "
                              f"installed; expected a suffix among {list(ANIMATION_SUFFIXES)} whose writer is "
                              f"installed (or install {extra})")
        env, agent = _env_and_agent(args, kwargs, filter_config)
        if filter_config is not None:  # (the kernels loaded before the first step: solve times are the steps')
            from aasoatt_env.safety import warm_up

            warm_up(filter_config.kernel)
        rollout, frames = run_episode(env, agent, seed=args.seed, render_every=args.frame_every if gif else None,
                                      progress=not args.quiet, metadata={"controller": args.controller,
                                                                         "filter": args.filter, "seed": args.seed})
        summary = summarize(rollout, goal_tolerance=args.goal_tolerance)
        print(format_summary(summary))
        if out is not None:
            _write_results(out, summary, rollout, f"{args.scenario}: {args.controller} / {args.filter}")
        if gif is not None:  # save_animation and atomic_write: a failed writer leaves no partial file at --gif
            try:
                cli_support.atomic_write(gif, lambda tmp: save_animation(frames, tmp, fps=args.fps))
            except AASOATTError:
                raise
            except (ValueError, RuntimeError, OSError) as exc:  # the writer failed: one line, status 1
                raise OSError(f"--gif: could not write {gif} ({' '.join(str(exc).split())[:300]})") from exc
            print(f"wrote {gif} ({len(frames)} frames)")
    env.close()
    return 1 if args.fail_on_collision and summary.get("n_collision_pairs") else 0


def _run_parser(sub: Any) -> None:
    p = sub.add_parser("run", help="run a controller on a scenario")

    def choice(flag: str, default: str, options: Sequence[str]) -> None:
        p.add_argument(flag, default=default, choices=options, metavar="NAME", help=f"one of {', '.join(options)}")

    choice("--scenario", "circle_swap", sorted(SCENARIOS))
    p.add_argument("--robots", type=cli_support.int_option(1, MAX_ROBOTS), default=None,
                   help="number of robots (num_robots)")
    p.add_argument("-p", "--param", action="append", help="scenario/env parameter KEY=VALUE")
    choice("--controller", "tracking", agent_names())
    p.add_argument("--model", default=None, help="saved model for --controller learned")
    p.add_argument("--filter", default="aasoatt", choices=[*BARRIERS, "none"], metavar="NAME",
                   help=f"barrier: one of {', '.join(BARRIERS)}; or 'none' for the bare env")
    choice("--deadlock", "auxiliary_velocity", list(STRATEGIES))
    choice("--trigger", "multiplier", list(TRIGGERS))
    p.add_argument("--solver", default="proxsuite", help="QP solver (aasoatt list shows the installed ones)")
    p.add_argument("-g", "--gain", action="append", help="filter gain KEY=VALUE (k1, k2, zeta, ...)")
    p.add_argument("--decision-interval", type=cli_support.int_option(1, 10_000), default=None,
                   help="physics steps per action (default 1; --controller learned: the run's)")
    p.add_argument("--seed", type=cli_support.int_option(0), default=0)
    p.add_argument("--gif", type=cli_support.path_option, default=None,
                   help=f"write an animation ({', '.join(ANIMATION_SUFFIXES)}; video needs imageio-ffmpeg)")
    p.add_argument("--frame-every", type=cli_support.int_option(1), default=20, help="env steps between GIF frames")
    p.add_argument("--fps", type=cli_support.int_option(1, 1000), default=20)
    p.add_argument("--out", type=cli_support.path_option, default=None, help=f"folder for {', '.join(RUN_OUTPUTS)}")
    p.add_argument("--goal-tolerance", type=cli_support.real_option(0.0, lo_open=True), default=0.05)
    p.add_argument("--fail-on-collision", action="store_true", help="exit 1 if any pair collided")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    cli_support.add_common_options(p)
    p.set_defaults(func=cmd_run)


def cmd_warm_up(args: argparse.Namespace) -> int:
    """Compile the safety filter's kernels now (:func:`aasoatt_env.safety.warm_up`), one line per part."""
    import time

    from aasoatt_env.safety import warm_up

    t0 = time.perf_counter()

    def show(part: str) -> None:
        print(f"[{time.perf_counter() - t0:5.1f} s] {part} (compiled once, then loaded from the cache) ...", flush=True)

    if warm_up(args.kernel, progress=show):
        print(f"[{time.perf_counter() - t0:5.1f} s] compiled kernels ready (cached for later runs)")
    else:
        print("no compiled kernels to prepare: the numpy reference runs (pip install \"aasoatt[fast]\" for them)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``aasoatt``."""
    parser = cli_support.Parser(prog="aasoatt", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, parser_class=cli_support.Parser)
    p_list = sub.add_parser("list", help="scenarios, controllers, filter options")
    cli_support.add_common_options(p_list, overwrite=False)
    p_list.set_defaults(func=cmd_list)
    _run_parser(sub)
    p_warm = sub.add_parser("warm-up", help="compile the filter's kernels once (numba caches them)")
    p_warm.add_argument("--kernel", choices=("auto", "numba"), default="auto",
                        help="auto: where numba is installed; numba: or an error")
    p_warm.set_defaults(func=cmd_warm_up)
    for name, module in _FORWARDED.items():
        p = sub.add_parser(name, help=f"see {module} (aasoatt {name} --help)", add_help=False)
        p.add_argument("rest", nargs=argparse.REMAINDER)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``aasoatt`` console script (see :mod:`aasoatt_env.cli_support` for the contract)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in _FORWARDED:
        if argv[0] == "train":  # --backend rllib: train.rllib (Ray RLlib's venv has no Stable-Baselines3)
            from train.config import split_backend

            backend, rest = split_backend(argv[1:])
            if backend == "rllib":
                from train.rllib import main as rllib_main

                return int(rllib_main(rest, prog="aasoatt train --backend rllib") or 0)
        return int(importlib.import_module(_FORWARDED[argv[0]]).main(argv[1:]) or 0)

    def body(args_list: list[str]) -> int:
        args = build_parser().parse_args(args_list)
        return int(args.func(args))

    prog = f"aasoatt {argv[0]}" if argv and not argv[0].startswith("-") else "aasoatt"
    return cli_support.run_guarded(prog, argv, body)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
