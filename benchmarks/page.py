"""The benchmarks' result pages: a markdown file headed by the exact command that made it (``--page FILE``).

Measured tables live in ``docs/`` pages that the benchmark commands write themselves, so they are
regenerated, not hand-edited.  A page records the command, the machine and the library versions;
an existing page is replaced only with ``--overwrite``, and every page is written atomically.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import platform
import shlex
import sys
from collections.abc import Iterator
from pathlib import Path

from aasoatt_env.cli_support import atomic_write


def add_page_options(parser: argparse.ArgumentParser) -> None:
    """``--page FILE`` and ``--overwrite``."""
    parser.add_argument("--page", default=None, help="also write the results as a markdown page (docs/...)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --page")


def check_page(args: argparse.Namespace) -> None:
    """Refuse (exit 2) an existing page without ``--overwrite`` before any work starts."""
    if args.page and Path(args.page).exists() and not args.overwrite:
        sys.exit(f"--page: {args.page} exists; add --overwrite to replace it")


def machine() -> str:
    """The machine and the versions a page's numbers were measured with."""
    import numpy as np
    import scipy

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), cpu)
    except OSError:
        pass
    try:
        import numba
        fast = f", numba {numba.__version__}"
    except ImportError:
        fast = ", numba not installed"
    return (f"{cpu}, {os.cpu_count()} cores; Python {platform.python_version()}, numpy {np.__version__}, "
            f"scipy {scipy.__version__}{fast}")


def command_line() -> str:
    """This process's command line as a shell command (``cd DIR && ...`` where run from a subfolder)."""
    command = "python " + " ".join(shlex.quote(a) for a in sys.argv)
    root = Path(__file__).resolve().parent.parent  # the repository
    cwd = Path.cwd().resolve()
    if cwd != root and cwd.is_relative_to(root):  # (run from a subfolder: the command's paths are relative to it)
        command = f"cd {shlex.quote(str(cwd.relative_to(root)))} && {command}"
    return command


def write_page(args: argparse.Namespace, title: str, body: str, records: list[dict] | None = None) -> None:
    """Write ``body`` under ``title``, the command line and the machine to ``args.page`` (if given).

    ``records``: the results the page summarises; the commands that wrote them (their ``command``) head it too.
    """
    if not args.page:
        return
    made = list(dict.fromkeys(r["command"] for r in records or () if r.get("command")))
    command = "\n".join([*made, command_line()])
    text = f"# {title}\n\n```bash\n{command}\n```\n\nMeasured on {machine()}.\n\n{body.rstrip()}\n"
    Path(args.page).parent.mkdir(parents=True, exist_ok=True)
    atomic_write(args.page, lambda p: p.write_text(text))
    print(f"wrote {args.page}")


class _Tee(io.TextIOBase):
    def __init__(self, out: io.TextIOBase) -> None:
        self.out, self.kept = out, io.StringIO()

    def write(self, text: str) -> int:
        self.kept.write(text)
        return self.out.write(text)

    def flush(self) -> None:
        self.out.flush()


@contextlib.contextmanager
def printed_page(args: argparse.Namespace, title: str, notes: str = "") -> Iterator[None]:
    """Everything printed inside the block also becomes the page's body (when ``--page`` is given)."""
    tee = _Tee(sys.stdout)
    with contextlib.redirect_stdout(tee):
        yield
    write_page(args, title, tee.kept.getvalue() + ("\n" + notes if notes else ""))
