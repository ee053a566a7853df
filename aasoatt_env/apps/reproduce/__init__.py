"""Reproduce the paper's Sec. V: ``aasoatt reproduce EXPERIMENT [--quick] [--out DIR] [--jobs N] [--page FILE]``.

Each experiment writes ``<out>/<experiment>/`` (CSV, README with the paper's numbers beside ours, figures);
``--page`` puts every table on one page headed by its command.  From Python:
``report, seconds = run_experiment("compare-ca", Settings(out=Path("results")))``.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from aasoatt_env import cli_support
from aasoatt_env.apps.reproduce.experiments import EXPERIMENTS
from aasoatt_env.apps.reproduce.report import Report, Settings, md_table, run
from aasoatt_env.errors import ConfigError
from aasoatt_env.safety import available_solvers

__all__ = ["EXPERIMENTS", "Settings", "main", "run_experiment"]

QUICK_SUBDIR = "quick"  # --quick writes to results/quick by default: never over the full tables


def run_experiment(name: str, settings: Settings) -> tuple[Report, float]:
    """Run experiment ``name`` and write its files; return the report and the seconds it took."""
    if name not in EXPERIMENTS:
        raise ConfigError(f"experiment: got {name!r}, expected one of {sorted(EXPERIMENTS)} or 'all'")
    t0 = time.perf_counter()
    report = run(EXPERIMENTS[name], settings)
    wall = time.perf_counter() - t0
    report.write(wall, settings.command)
    return report, wall


def _parser() -> argparse.ArgumentParser:
    p = cli_support.Parser(prog="aasoatt reproduce",
               description="Reproduce the paper's Sec. V experiments; writes CSV, Markdown and PNG per experiment.")
    p.add_argument("experiment", choices=[*EXPERIMENTS, "all"], help="experiment to run")
    p.add_argument("--quick", action="store_true",
                   help=f"small, fast variants (CI); not comparable to the paper; default --out results/{QUICK_SUBDIR}")
    p.add_argument("--out", type=cli_support.path_option, default=None,
                   help=f"results root directory (default: results, or results/{QUICK_SUBDIR} with --quick)")
    p.add_argument("--page", type=cli_support.path_option, default=None,
                   help="also write every result table to this Markdown page, headed by the command (e.g. "
                        "docs/paper_results.md)")
    p.add_argument("--jobs", type=cli_support.int_option(1, 256), default=1,
                   help="worker processes for independent runs")
    p.add_argument("--solver", default=None, help="QP solver of the safety filter (default: daqp if installed, "
                                                  "else proxsuite; the paper's is 'neural')")
    p.add_argument("--safety-margin", type=cli_support.real_option(0.0, 1.0), default=0.0,
                   help="margin added to d_s [m] in the paper-comparison runs, in [0, 1] (default 0: the paper's)")
    p.add_argument("--backup", action="store_true",
                   help="turn the braking backup layer on (default off: the paper's method as published)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    cli_support.add_common_options(p)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point (``aasoatt reproduce ...``); returns the exit status."""
    return cli_support.run_guarded("aasoatt reproduce", sys.argv[1:] if argv is None else argv, _main)


def _main(argv: list[str]) -> int:
    args = _parser().parse_args(argv)
    solver = args.solver or ("daqp" if "daqp" in available_solvers() else "proxsuite")
    if args.solver is None and solver != "daqp":
        print('note: DAQP is not installed (pip install "aasoatt[repro]"); using proxsuite (same results, '
              "about 5x slower)", file=sys.stderr)
    if solver not in available_solvers():
        raise ConfigError(f"--solver: got {solver!r}, expected one of {available_solvers()}")
    names = list(EXPERIMENTS) if args.experiment == "all" else [args.experiment]
    cmd = "aasoatt reproduce {name}" + " --quick" * args.quick + f" --solver {solver}" * (solver != "daqp")
    cmd += f" --safety-margin {args.safety_margin:g}" * bool(args.safety_margin) + " --backup" * args.backup
    out = Path(args.out) if args.out is not None else Path("results") / (QUICK_SUBDIR if args.quick else "")
    walls: dict[str, float] = {}
    reports = []
    with cli_support.OutputPlan(args.overwrite) as plan:  # a refusal or failure before any results: no folder left
        plan.folder(out, "--out", entries=[*names, *(["SUMMARY.md"] if len(names) > 1 else [])])
        page = plan.file(args.page, "--page", suffixes=(".md",)) if args.page is not None else None
        for name in names:
            s = Settings(quick=args.quick, out=out, jobs=args.jobs, solver=solver, safety_margin=args.safety_margin,
                         backup=args.backup, progress=not args.no_progress, command=cmd.format(name=name))
            report, walls[name] = run_experiment(name, s)
            reports.append(report)
            print(f"{name}: {walls[name]:.1f} s -> {report.dir / 'README.md'}", flush=True)
        if len(names) > 1:
            _write_summary(out, cmd.format(name=args.experiment) + f" --jobs {args.jobs}" * (args.jobs > 1), walls)
        if page is not None:
            _write_page(page, ["aasoatt", "reproduce", *argv], reports)
            print(f"page -> {page}")
    return 0


def _write_summary(out: Path, command: str, walls: dict[str, float]) -> None:
    """``<out>/SUMMARY.md``: the wall time of each experiment and their total."""
    total = sum(walls.values())
    table = md_table(["experiment", "wall time [s]", "report"],
                     [[n, f"{w:.1f}", f"[{n}/README.md]({n}/README.md)"] for n, w in walls.items()])
    lines = ["# Reproduction summary", "", f"Command: `{command}`", "", table, "",
             f"Total wall time: {total:.1f} s ({total / 60:.1f} min).", ""]
    cli_support.atomic_write(out / "SUMMARY.md", lambda tmp: tmp.write_text("\n".join(lines)))
    print(f"all: {total:.1f} s -> {out / 'SUMMARY.md'}")


def _write_page(path: Path, argv: list[str], reports: list[Report]) -> None:
    """One Markdown page of every report's settings and tables, headed by the command line that made it."""
    lines = ["# Reproduction of the paper's experiments", "", "Written by this command (run it again to regenerate "
             "this page; do not edit it by hand):", "", "```", shlex.join(argv), "```", ""]
    for report in reports:
        lines += [f"## {report.title}", "", *("#" + line if line.startswith("#") else line for line in report.body())]
    cli_support.atomic_write(path, lambda tmp: tmp.write_text("\n".join(lines)))


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
