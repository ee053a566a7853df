"""Experiment scaffolding: declare an :class:`Experiment`; :func:`run` tabulates it beside the paper's numbers."""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from aasoatt_env.analysis.metrics import format_value as fmt
from aasoatt_env.apps.reproduce.runner import RunResult, RunSpec, run_many
from aasoatt_env.cli_support import OutputPlan, staged

__all__ = ["Experiment", "Report", "Settings", "fmt", "fmt_rel", "md_table", "rel_diff", "run"]

Column = tuple[str, Callable[[dict[str, Any]], str]]  # a table column: its header and the cell of a CSV row
Results = dict[str, RunResult]  # the runs of an experiment by key

#: The CSV columns of a run's metrics, in this order (then the ``*_end`` goal metrics).
CSV_METRICS = ("intervention_time", "rmse", "mae", "std", "max_tracking_error", "min_center_distance_full",
               "min_robot_gap_full", "min_obstacle_gap", "n_collision_pairs", "n_obstacle_collisions",
               "final_error_mean", "final_error_max", "reach_rate", "n_deadlocked", "triggered_fraction",
               "relaxed_fraction", "unsafe_fraction", "failed_fraction", "slack_max", "solve_time_median", "wall_time")

SHORT_NAMES = {"intervention_time": "IT [s]", "rmse": "RMSE", "mae": "MAE", "std": "std"}


@dataclass(frozen=True)
class Settings:
    """The options of ``aasoatt reproduce`` shared by all experiments (``command`` heads the Markdown)."""

    quick: bool = False
    out: Path = Path("results")
    jobs: int = 1
    solver: str = "daqp"
    safety_margin: float = 0.0
    backup: bool = False
    progress: bool = True
    command: str = "aasoatt reproduce"


def rel_diff(ours: float | None, paper: float | None) -> float | None:
    """Relative difference ``(ours - paper) / |paper|`` (None when either is missing)."""
    if ours is None or paper is None or paper == 0 or not math.isfinite(ours):
        return None
    return (ours - paper) / abs(paper)


def fmt_rel(x: float | None) -> str:
    """A relative difference as a signed percentage."""
    return "-" if x is None else f"{100 * x:+.1f}%"


def md_table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A GitHub Markdown table; cells are formatted with :func:`fmt` unless already strings."""
    out = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    out += ["| " + " | ".join(c if isinstance(c, str) else fmt(c) for c in row) + " |" for row in rows]
    return "\n".join(out)


def col(header: str, key: str | Callable[[dict[str, Any]], Any], digits: int = 4) -> Column:
    """A column showing the CSV row's ``key`` (or ``key(row)``) with ``digits`` decimals."""
    return header, lambda row: fmt(key(row) if callable(key) else row.get(key), digits)


def compared(metrics: Sequence[str]) -> list[Column]:
    """The paper | ours | relative-difference columns of ``metrics``."""
    return [c for k in metrics for c in (col(f"{SHORT_NAMES[k]} paper", f"paper_{k}"), col(f"{SHORT_NAMES[k]} ours", k),
                                         ("rel.", lambda row, k=k: fmt_rel(row[f"rel_{k}"])))]


class Experiment:
    """One experiment of the paper, declared by overriding the hooks that apply.

    ``_specs``: the runs in table order; ``_paper``: a run's numbers in the paper; ``_extra``: more CSV fields;
    ``_columns``, ``_notes``, ``_sections``, ``_findings``: the Markdown; ``_figures``: ``(figure, file, caption)``.
    """

    name: ClassVar[str]
    title: ClassVar[str]
    metrics: ClassVar[tuple[str, ...]] = ()
    heading: ClassVar[str] = "## Results (paper | ours | relative difference)"
    sizes: ClassVar[dict[bool, Any]] = {}
    columns: ClassVar[list[Column]] = []  # the results table, unless it depends on the settings (_columns)

    def size(self, s: Settings) -> Any:
        """The scenario sizes for ``s``."""
        return self.sizes[s.quick]

    def _specs(self, s: Settings) -> list[RunSpec]:
        raise NotImplementedError

    def _columns(self, s: Settings) -> list[Column]:
        return self.columns

    def _paper(self, spec: RunSpec) -> dict[str, Any] | None:
        return None

    def _extra(self, s: Settings, spec: RunSpec, result: RunResult) -> dict[str, Any]:
        return {}

    def _notes(self, s: Settings) -> list[str]:
        return []

    def _sections(self, s: Settings, res: Results) -> list[Any]:
        return []

    _findings = _figures = _sections  # no findings, no figures unless overridden


def result_row(exp: str, res: RunResult, ref: dict[str, Any] | None, metrics: Sequence[str]) -> dict[str, Any]:
    """One CSV row: the run's labels, metrics, the paper's numbers and the relative differences."""
    row: dict[str, Any] = {"experiment": exp, "key": res.spec.key, **res.spec.meta}
    row.update({k: res.metrics[k] for k in CSV_METRICS if k in res.metrics})
    row.update({k: v for k, v in res.metrics.items() if k.endswith("_end")})
    for k in metrics:
        p = None if ref is None else ref.get(k)
        row[f"paper_{k}"], row[f"rel_{k}"] = p, rel_diff(res.metrics.get(k), p)
    return row


def run(exp: Experiment, s: Settings) -> Report:
    """Run ``exp`` and tabulate its results."""
    specs = exp._specs(s)
    res = {r.spec.key: r for r in run_many(specs, jobs=s.jobs, desc=exp.name, show=s.progress)}
    rows = [{**result_row(exp.name, res[sp.key], exp._paper(sp), exp.metrics), **exp._extra(s, sp, res[sp.key])}
            for sp in specs]
    cols = exp._columns(s)
    table = md_table([h for h, _ in cols], [[cell(row) for _, cell in cols] for row in rows])
    findings = "\n".join(f"- {line}" for line in exp._findings(s, res))
    sections = [f"{exp.heading}\n\n{table}", *exp._sections(s, res), *([f"## Findings\n\n{findings}"] * bool(findings))]
    return Report(exp.name, exp.title, s.out, rows, exp._notes(s), sections, exp._figures(s, res))


@dataclass
class Report:
    """One experiment's rows, settings, Markdown sections and figures, ready to write."""

    name: str
    title: str
    out: Path
    rows: list[dict[str, Any]]
    settings: list[str]
    sections: list[str]
    figures: list[tuple[Any, str, str]]

    @property
    def dir(self) -> Path:
        """The experiment's folder, ``<out>/<name>``."""
        return Path(self.out) / self.name

    def body(self) -> list[str]:
        """The Markdown of the settings and sections (what a results page shows of this experiment)."""
        return (["## Settings", "", *(f"- {s}" for s in self.settings), ""] if self.settings else []) + [
            line for s in self.sections for line in (s.strip(), "")]

    def write(self, wall_time: float, command: str) -> tuple[Path, Path]:
        """Write ``<name>.csv``, ``README.md`` and the figures (all or none); return the CSV and README paths."""
        csv_path, md_path = self.dir / f"{self.name}.csv", self.dir / "README.md"
        md = [f"# {self.title}", "", f"Command: `{command}`", "", *self.body()]
        if self.figures:
            md += ["## Figures", "", *(f"- `{name}`: {caption}" for _, name, caption in self.figures), ""]
        md += [f"CSV: `{csv_path.name}`.", "", f"Wall time of this experiment: {wall_time:.1f} s.", ""]
        with OutputPlan(overwrite=True) as plan:  # a failure leaves no empty folder to be taken for results
            plan.folder(self.dir, self.name)
            with staged(csv_path, md_path, *(self.dir / name for _, name, _ in self.figures)) as temps:
                self._write_csv(temps[0])
                temps[1].write_text("\n".join(md))
                for (fig, _, _), temp in zip(self.figures, temps[2:]):
                    fig.savefig(temp, dpi=110, format="png")
        return csv_path, md_path

    def _write_csv(self, path: Path) -> None:
        keys = list(dict.fromkeys(k for row in self.rows for k in row))
        with path.open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=keys)
            w.writeheader()
            w.writerows({k: _csv_cell(row.get(k)) for k in keys} for row in self.rows)


def _csv_cell(v: Any) -> Any:
    if v is None:
        return ""
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    return v.item() if isinstance(v, (np.integer, np.bool_)) else v
