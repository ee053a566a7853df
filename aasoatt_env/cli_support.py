"""What every ``aasoatt`` command shares: one-line errors, ``--debug``, option types and output checks.

Contract of every command (``run``, ``list``, ``reproduce``, ``train``, ``evaluate``):

* options and output paths are checked **before** any simulation or training
  starts, so a typo never costs a run;
* a user error (a bad option, a bad or unwritable output path, a corrupted input
  file: any :class:`~aasoatt_env.errors.AASOATTError`) prints **one line**,
  ``aasoatt <command>: error: <what is wrong>``, and exits with status 2;
  ``--debug`` shows the full traceback instead;
* earlier results are never overwritten unless ``--overwrite`` is given
  (``train`` makes a new numbered run folder instead).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NoReturn

from aasoatt_env.errors import AASOATTError, ConfigError

__all__ = [
    "OutputPlan",
    "guarded_outputs",
    "Parser",
    "add_common_options",
    "int_option",
    "real_option",
    "run_guarded",
]


class Parser(argparse.ArgumentParser):
    """An :class:`argparse.ArgumentParser` whose usage errors are one line (exit status 2)."""

    def error(self, message: str) -> NoReturn:
        """Print ``prog: error: message (see prog --help)`` and exit with status 2."""
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def add_common_options(parser: argparse.ArgumentParser, overwrite: bool = True) -> None:
    """``--debug`` (and ``--overwrite`` for commands that write results)."""
    parser.add_argument("--debug", action="store_true", help="on an error, show the full traceback")
    if overwrite:
        parser.add_argument("--overwrite", action="store_true",
                            help="replace results already at the output path (refused otherwise)")


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def run_guarded(prog: str, argv: Sequence[str], body: Callable[[list[str]], int]) -> int:
    """Run ``body(argv)``; a user error becomes one line on stderr and status 2 (``--debug``: re-raise).

    :class:`~aasoatt_env.errors.AASOATTError` (bad options, bad files, unknown
    keywords) is a user error (status 2); an :class:`OSError` while writing
    (disk full, a path that vanished) prints one line with status 1; Ctrl-C
    status 130.
    """
    argv = list(argv)
    debug = "--debug" in argv
    try:
        return int(body(argv) or 0)
    except AASOATTError as exc:
        if debug:
            raise
        print(f"{prog}: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except OSError as exc:
        if debug:
            raise
        print(f"{prog}: error: {_one_line(exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        if debug:
            raise
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130


# ---------------------------------------------------------------------------------------- option types
def int_option(lo: int, hi: int | None = None) -> Callable[[str], int]:
    """An argparse ``type=`` for integers in ``[lo, hi]`` (the message states the range)."""
    expected = f"an integer >= {lo}" if hi is None else f"an integer in [{lo}, {hi}]"

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"got {text!r}, expected {expected}") from None
        if value < lo or (hi is not None and value > hi):
            raise argparse.ArgumentTypeError(f"got {value}, expected {expected}")
        return value

    parse.__name__ = "integer"
    return parse


def real_option(lo: float, hi: float | None = None, lo_open: bool = False) -> Callable[[str], float]:
    """An argparse ``type=`` for finite numbers ``> lo`` (``lo_open``) or ``>= lo``, and ``<= hi``."""
    bound = f"{'>' if lo_open else '>='} {lo:g}"
    expected = f"a finite number {bound}" + ("" if hi is None else f" and <= {hi:g}")

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"got {text!r}, expected {expected}") from None
        ok = math.isfinite(value) and (value > lo if lo_open else value >= lo) and (hi is None or value <= hi)
        if not ok:
            raise argparse.ArgumentTypeError(f"got {text}, expected {expected}")
        return value

    parse.__name__ = "number"
    return parse


# ---------------------------------------------------------------------------------------- output paths
class OutputPlan:
    """Output paths of one command, checked and prepared before the work starts.

    :meth:`folder` and :meth:`file` raise :class:`~aasoatt_env.errors.ConfigError`
    naming the option when a path cannot be written or would replace earlier
    results without ``overwrite``; folders they had to create are removed again
    by :meth:`discard` if the command fails before writing anything into them.

    Parameters
    ----------
    overwrite : bool
        The command's ``--overwrite``.
    """

    def __init__(self, overwrite: bool) -> None:
        self.overwrite = bool(overwrite)
        self._created: list[Path] = []

    def _make_writable_dir(self, folder: Path, flag: str) -> None:
        missing = []
        probe = folder
        while not probe.exists():
            missing.append(probe)
            if probe.parent == probe:
                break
            probe = probe.parent
        if probe.exists() and not probe.is_dir():
            raise ConfigError(f"{flag}: {probe} is a file, not a folder; cannot write {folder}")
        try:
            folder.mkdir(parents=True, exist_ok=True)
            self._created += reversed(missing)
            with tempfile.TemporaryFile(dir=folder):
                pass
        except OSError as exc:
            raise ConfigError(f"{flag}: cannot write to {folder} ({exc.strerror or exc})") from None

    def folder(self, path: str | os.PathLike[str], flag: str, *, entries: Sequence[str] | None = None) -> Path:
        """A results folder: created (with its parents) and test-written now.

        ``entries``: the names the command will write into it; ``None`` means the
        whole folder is the result, so any existing content counts as earlier
        results.  Existing results are refused unless ``overwrite``.
        """
        folder = Path(path)
        if folder.exists() and not folder.is_dir():
            raise ConfigError(f"{flag}: {folder} exists and is not a folder")
        if folder.is_dir() and not self.overwrite:
            try:
                present = sorted(p.name for p in folder.iterdir())
            except OSError as exc:
                raise ConfigError(f"{flag}: cannot read {folder} ({exc.strerror or exc})") from None
            clash = present if entries is None else [e for e in entries if e in present]
            if clash:
                shown = ", ".join(clash[:4]) + (", ..." if len(clash) > 4 else "")
                raise ConfigError(
                    f"{flag}: {folder} already holds results ({shown}); pass --overwrite to replace them, "
                    "or choose another path"
                )
        self._make_writable_dir(folder, flag)
        return folder

    def file(self, path: str | os.PathLike[str], flag: str, *, suffixes: Sequence[str] | None = None) -> Path:
        """An output file: its folder is created and test-written now; an existing file needs ``overwrite``."""
        target = Path(path)
        if suffixes is not None and target.suffix.lower() not in suffixes:
            raise ConfigError(f"{flag}: got {str(target)!r}, expected a file name ending in one of {list(suffixes)}")
        if target.exists() or target.is_symlink():
            if not target.is_file():
                raise ConfigError(f"{flag}: {target} exists and is not a regular file")
            if not self.overwrite:
                raise ConfigError(f"{flag}: {target} already exists; pass --overwrite to replace it, "
                                  "or choose another path")
        self._make_writable_dir(target.parent if str(target.parent) else Path("."), flag)
        return target

    def discard(self) -> None:
        """Remove the folders this plan created that are still empty (the command failed)."""
        for folder in reversed(self._created):
            try:
                folder.rmdir()
            except OSError:
                pass
        self._created.clear()


def guarded_outputs(plan: OutputPlan, work: Callable[[], Any]) -> Any:
    """Run ``work()``; on any failure remove the empty folders ``plan`` created, then re-raise."""
    try:
        return work()
    except BaseException:
        plan.discard()
        raise
