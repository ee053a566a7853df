"""Reproduce the paper's Sec. V: ``aasoatt reproduce EXPERIMENT [--quick] [--out DIR] [--jobs N]``.

Experiments (see :mod:`aasoatt_env.apps.reproduce.experiments`): ``table1``,
``compare-ca``, ``table2``, ``deadlock-triggers``, ``table3``, ``swarm100``,
``obstacles`` and ``all``.  Each writes ``<out>/<experiment>/`` with a CSV, a
Markdown ``README.md`` putting the paper's numbers beside ours (relative
difference), PNG figures and the experiment's wall time; ``all`` also writes
``<out>/SUMMARY.md`` with the wall time of each experiment and the total.

Every run is deterministic: the same command gives the same numbers whatever
``--jobs`` is.  ``--quick`` runs small variants (seconds, for CI) whose numbers
are *not* comparable to the paper; they go to ``results/quick/`` unless ``--out``
says otherwise, so they never replace the full tables.  Existing results are
replaced only with ``--overwrite``; every option and the output folder are
checked before the first run.

Python use::

    from aasoatt_env.apps.reproduce import run_experiment, Settings
    report = run_experiment("compare-ca", Settings(out=Path("results")))
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from aasoatt_env.apps.reproduce.experiments import EXPERIMENTS, Settings
from aasoatt_env.apps.reproduce.report import Report
from aasoatt_env.cli_support import (
    OutputPlan,
    Parser,
    add_common_options,
    guarded_outputs,
    int_option,
    real_option,
    run_guarded,
)
from aasoatt_env.errors import ConfigError
from aasoatt_env.safety import available_solvers

__all__ = ["EXPERIMENTS", "Settings", "main", "run_experiment"]


def run_experiment(name: str, settings: Settings) -> tuple[Report, float]:
    """Run experiment ``name`` and write its files.

    Parameters
    ----------
    name : str
        A key of :data:`EXPERIMENTS`.
    settings : Settings
        Shared options.

    Returns
    -------
    report : Report
        The written report (``report.dir`` holds the files).
    wall_time : float
        Seconds spent, recorded in the Markdown.
    """
    if name not in EXPERIMENTS:
        raise ConfigError(f"experiment: got {name!r}, expected one of {sorted(EXPERIMENTS)} or 'all'")
    t0 = time.perf_counter()
    report = EXPERIMENTS[name](settings)
    wall = time.perf_counter() - t0
    report.write(wall, f"{settings.command}")
    return report, wall


QUICK_SUBDIR = "quick"
"""``--quick`` results go to ``<out>/quick/`` by default, so they never replace the full tables."""


def _parser() -> argparse.ArgumentParser:
    p = Parser(
        prog="aasoatt reproduce",
        description="Reproduce the paper's Sec. V experiments; writes CSV, Markdown and PNG per experiment.",
    )
    p.add_argument("experiment", choices=[*EXPERIMENTS, "all"], help="experiment to run")
    p.add_argument("--quick", action="store_true",
                   help=f"small, fast variants (CI); not comparable to the paper; default --out results/{QUICK_SUBDIR}")
    p.add_argument("--out", default=None,
                   help=f"results root directory (default: results, or results/{QUICK_SUBDIR} with --quick)")
    p.add_argument("--jobs", type=int_option(1, 256), default=1,
                   help="worker processes for independent runs (default: 1)")
    p.add_argument(
        "--solver",
        default=None,
        help="QP solver of the safety filter (default: daqp if installed, else proxsuite; the paper's is 'neural')",
    )
    p.add_argument(
        "--safety-margin",
        type=real_option(0.0, 1.0),
        default=0.0,
        help="margin added to d_s [m] in the paper-comparison runs, in [0, 1] (default 0: the paper's barrier)",
    )
    p.add_argument(
        "--backup",
        action="store_true",
        help="turn the braking backup layer on (default off: the paper's method as published)",
    )
    p.add_argument("--no-progress", action="store_true", help="hide progress bars")
    add_common_options(p)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point (``aasoatt reproduce ...``); returns the exit status.

    Options and output folders are checked before the first run; existing results
    (``<out>/<experiment>/``, ``<out>/SUMMARY.md``) are replaced only with ``--overwrite``.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    return run_guarded("aasoatt reproduce", argv, _main)


def _main(argv: list[str]) -> int:
    args = _parser().parse_args(argv)
    if args.solver is None:
        args.solver = "daqp" if "daqp" in available_solvers() else "proxsuite"
        if args.solver != "daqp":
            print(
                'note: DAQP is not installed (pip install "aasoatt[repro]"); using proxsuite (same '
                "results, about 5x slower)",
                file=sys.stderr,
            )
    if args.solver not in available_solvers():
        raise ConfigError(f"--solver: got {args.solver!r}, expected one of {available_solvers()}")
    names = list(EXPERIMENTS) if args.experiment == "all" else [args.experiment]
    cmd = "aasoatt reproduce {name}" + (" --quick" if args.quick else "")
    if args.solver != "daqp":
        cmd += f" --solver {args.solver}"
    if args.safety_margin:
        cmd += f" --safety-margin {args.safety_margin:g}"
    if args.backup:
        cmd += " --backup"
    out = Path(args.out) if args.out is not None else Path("results") / (QUICK_SUBDIR if args.quick else "")
    plan = OutputPlan(args.overwrite)
    plan.folder(out, "--out", entries=[*names, *(["SUMMARY.md"] if len(names) > 1 else [])])
    walls: dict[str, float] = {}
    t0 = time.perf_counter()
    for k, name in enumerate(names):
        settings = Settings(
            quick=args.quick,
            out=out,
            jobs=args.jobs,
            solver=args.solver,
            safety_margin=args.safety_margin,
            backup=args.backup,
            progress=not args.no_progress,
            command=cmd.format(name=name),
        )
        report, wall = (guarded_outputs(plan, lambda s=settings, n=name: run_experiment(n, s)) if k == 0
                        else run_experiment(name, settings))
        walls[name] = wall
        print(f"{name}: {wall:.1f} s -> {report.dir / 'README.md'}", flush=True)
    total = time.perf_counter() - t0
    if len(names) > 1:
        lines = [
            "# Reproduction summary",
            "",
            f"Command: `{cmd.format(name=args.experiment)}`{f' --jobs {args.jobs}' if args.jobs > 1 else ''}",
            "",
            "| experiment | wall time [s] | report |",
            "|---|---|---|",
        ]
        lines += [f"| {n} | {w:.1f} | [{n}/README.md]({n}/README.md) |" for n, w in walls.items()]
        lines += ["", f"Total wall time: {total:.1f} s ({total / 60:.1f} min).", ""]
        (out / "SUMMARY.md").write_text("\n".join(lines))
        print(f"all: {total:.1f} s -> {out / 'SUMMARY.md'}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
