"""CSV, Markdown and figure output of the reproduction experiments.

Every experiment writes ``<out>/<experiment>/``:

* ``<experiment>.csv`` - one row per run (labels, our metrics, the paper's
  numbers ``paper_<metric>`` and relative differences ``rel_<metric>``);
* ``README.md`` - the settings, Markdown tables with the paper's numbers beside
  ours and the relative difference ``(ours - paper) / |paper|``, findings and
  the wall time;
* ``*.png`` - figures.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["Report", "fmt", "md_table", "rel_diff", "fmt_rel", "new_figure", "save_figure"]


def rel_diff(ours: float | None, paper: float | None) -> float | None:
    """Relative difference ``(ours - paper) / |paper|`` (None when either is missing)."""
    if ours is None or paper is None or paper == 0 or not math.isfinite(ours):
        return None
    return (ours - paper) / abs(paper)


def fmt(x: Any, digits: int = 4) -> str:
    """Format a number for a table (``-`` for None)."""
    if x is None:
        return "-"
    if isinstance(x, (bool, np.bool_)):
        return "yes" if x else "no"
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    if isinstance(x, (float, np.floating)):
        if not math.isfinite(x):
            return str(x)
        return f"{x:.{digits}f}"
    return str(x)


def fmt_rel(x: float | None) -> str:
    """Format a relative difference as a signed percentage."""
    return "-" if x is None else f"{100 * x:+.1f}%"


def md_table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A GitHub Markdown table; cells are formatted with :func:`fmt` unless already strings."""
    out = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    for row in rows:
        out.append("| " + " | ".join(c if isinstance(c, str) else fmt(c) for c in row) + " |")
    return "\n".join(out)


def new_figure(nrows: int = 1, ncols: int = 1, size: tuple[float, float] = (6.0, 4.0)) -> tuple[Any, Any]:
    """A matplotlib figure (Agg, no pyplot state) and its axes array."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False)
    return fig, axes


def save_figure(fig: Any, path: Path, dpi: int = 110) -> None:
    """Save ``fig`` as PNG."""
    fig.savefig(path, dpi=dpi)


class Report:
    """Collects one experiment's rows, tables and notes and writes them out.

    Parameters
    ----------
    name : str
        Experiment name (directory and file stem).
    title : str
        Markdown title.
    out : Path
        Results root; files go to ``out / name``.
    """

    def __init__(self, name: str, title: str, out: Path) -> None:
        self.name = name
        self.title = title
        self.dir = Path(out) / name
        self.dir.mkdir(parents=True, exist_ok=True)
        self.rows: list[dict[str, Any]] = []
        self.sections: list[str] = []
        self.figures: list[str] = []
        self.settings: list[str] = []

    def add_row(self, row: dict[str, Any]) -> None:
        """Append a CSV row (a flat dict)."""
        self.rows.append(row)

    def section(self, text: str) -> None:
        """Append a Markdown block (tables, findings)."""
        self.sections.append(text.strip())

    def setting(self, text: str) -> None:
        """Append a bullet to the settings list."""
        self.settings.append(text)

    def figure(self, fig: Any, filename: str, caption: str) -> Path:
        """Save a figure into the experiment directory and reference it from the Markdown."""
        path = self.dir / filename
        save_figure(fig, path)
        self.figures.append(f"- `{filename}`: {caption}")
        return path

    def write(self, wall_time: float, command: str) -> tuple[Path, Path]:
        """Write ``<name>.csv`` and ``README.md``; return their paths."""
        csv_path = self.dir / f"{self.name}.csv"
        keys: list[str] = []
        for row in self.rows:
            for k in row:
                if k not in keys:
                    keys.append(k)
        with csv_path.open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=keys)
            w.writeheader()
            for row in self.rows:
                w.writerow({k: _csv_cell(row.get(k)) for k in keys})
        md = [f"# {self.title}", "", f"Command: `{command}`", ""]
        if self.settings:
            md += ["## Settings", ""] + [f"- {s}" for s in self.settings] + [""]
        for s in self.sections:
            md += [s, ""]
        if self.figures:
            md += ["## Figures", ""] + self.figures + [""]
        md += [f"CSV: `{csv_path.name}`.", "", f"Wall time of this experiment: {wall_time:.1f} s.", ""]
        md_path = self.dir / "README.md"
        md_path.write_text("\n".join(md))
        return csv_path, md_path


def _csv_cell(v: Any) -> Any:
    if v is None:
        return ""
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, (np.integer, np.bool_)):
        return v.item()
    return v
