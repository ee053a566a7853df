"""What every ``aasoatt`` command shares: one-line errors, option types, output paths, atomic writes, progress.

Options and paths are checked before any work; a user error prints one line and exits 2.  Files are written
under a temporary name, then renamed, so an interrupted command leaves the earlier file or the whole new one.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, NoReturn

from aasoatt_env.errors import AASOATTError, ConfigError
from aasoatt_env.validation import short_repr

__all__ = ["OutputPlan", "Parser", "add_common_options", "atomic_write", "int_option", "path_option", "progress",
           "real_option", "run_guarded", "staged"]

#: Marks the temporary files of :func:`staged`: never taken for results.
PARTIAL = ".partial"


class Parser(argparse.ArgumentParser):
    """An :class:`argparse.ArgumentParser` whose usage errors are one line (exit status 2)."""

    def error(self, message: str) -> NoReturn:
        """Print ``prog: error: message (see prog --help)`` and exit with status 2."""
        self.exit(2, f"{self.prog}: error: {_one_line(message)} (see {self.prog} --help)\n")


def add_common_options(parser: argparse.ArgumentParser, overwrite: bool = True) -> None:
    """Add ``--debug`` (and ``--overwrite`` for commands that write results)."""
    parser.add_argument("--debug", action="store_true", help="on an error, show the full traceback")
    if overwrite:
        parser.add_argument("--overwrite", action="store_true",
                            help="replace results already at the output path (refused otherwise)")


def _one_line(exc: BaseException | str) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def run_guarded(prog: str, argv: Sequence[str], body: Callable[[list[str]], int]) -> int:
    """Run ``body(argv)``: a user error prints one line and returns 2, an OSError 1, Ctrl-C 130 (``--debug``: raise)."""
    argv = list(argv)
    try:
        return int(body(argv) or 0)
    except (AASOATTError, OSError, KeyboardInterrupt) as exc:
        if "--debug" in argv:
            raise
        if isinstance(exc, KeyboardInterrupt):
            print(f"{prog}: interrupted", file=sys.stderr)
            return 130
        print(f"{prog}: error: {_one_line(exc)}", file=sys.stderr)
        return 2 if isinstance(exc, AASOATTError) else 1


def _number_option(kind: type, expected: str, ok: Callable[[Any], bool]) -> Callable[[str], Any]:
    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"got {short_repr(text)}, expected {expected}") from None
        if not ok(value):
            raise argparse.ArgumentTypeError(f"got {short_repr(value, 40)}, expected {expected}")
        return value

    parse.__name__ = "integer" if kind is int else "number"  # argparse's word when it cannot say more
    return parse


def int_option(lo: int, hi: int | None = None) -> Callable[[str], int]:
    """An argparse ``type=`` for integers in ``[lo, hi]`` (the message states the range)."""
    expected = f"an integer >= {lo}" if hi is None else f"an integer in [{lo}, {hi}]"
    return _number_option(int, expected, lambda v: lo <= v and (hi is None or v <= hi))


def real_option(lo: float, hi: float | None = None, lo_open: bool = False) -> Callable[[str], float]:
    """An argparse ``type=`` for finite numbers ``> lo`` (``lo_open``) or ``>= lo``, and ``<= hi``."""
    expected = f"a finite number {'>' if lo_open else '>='} {lo:g}" + ("" if hi is None else f" and <= {hi:g}")
    return _number_option(float, expected, lambda v: math.isfinite(v) and (v > lo if lo_open else v >= lo)
                          and (hi is None or v <= hi))


def path_option(text: str) -> str:
    """An argparse ``type=`` for output paths: not empty, no NUL, within the system's name-length limits."""
    raw = os.fsencode(text)
    if not raw or b"\0" in raw:
        raise argparse.ArgumentTypeError(f"got {short_repr(text)}, expected a path")
    if len(raw) >= 4096 or any(len(part) > 255 for part in raw.split(b"/")):
        raise argparse.ArgumentTypeError(f"got a path of {len(raw)} bytes, expected at most 4095 bytes and names of "
                                         "at most 255 bytes")
    return text


class OutputPlan:
    """Output paths of one command, checked and made before the work; on a failure its new folders go again."""

    def __init__(self, overwrite: bool) -> None:
        self.overwrite = bool(overwrite)
        self._created: list[Path] = []

    def _prepare(self, path: str | os.PathLike[str], flag: str, check: Callable[[Path], Path]) -> Path:
        """``path`` checked by ``check`` (which returns its folder); the folder made and test-written."""
        try:
            target = Path(path_option(os.fspath(path)))
            folder = probe = check(target)
            missing = []
            while not probe.exists() and probe.parent != probe:
                missing.append(probe)
                probe = probe.parent
            if probe.exists() and not probe.is_dir():
                raise ConfigError(f"{flag}: {probe} is a file, not a folder; cannot write {folder}")
            folder.mkdir(parents=True, exist_ok=True)
            self._created += reversed(missing)
            with tempfile.TemporaryFile(dir=folder):
                pass
        except argparse.ArgumentTypeError as exc:
            raise ConfigError(f"{flag}: {exc}") from None
        except OSError as exc:
            raise ConfigError(f"{flag}: cannot write to {path} ({exc.strerror or exc})") from None
        return target

    def folder(self, path: str | os.PathLike[str], flag: str, *, entries: Sequence[str] | None = None) -> Path:
        """A results folder, created and test-written now; ``entries``: the names written (None: any content)."""

        def check(folder: Path) -> Path:
            if folder.exists() and not folder.is_dir():
                raise ConfigError(f"{flag}: {folder} exists and is not a folder")
            if folder.is_dir() and not self.overwrite:
                present = sorted(p.name for p in folder.iterdir() if PARTIAL not in p.name)
                clash = present if entries is None else [e for e in entries if e in present]
                if clash:
                    shown = ", ".join(clash[:4]) + (", ..." if len(clash) > 4 else "")
                    raise ConfigError(f"{flag}: {folder} already holds results ({shown}); pass --overwrite to "
                                      "replace them, or choose another path")
            return folder

        return self._prepare(path, flag, check)

    def file(self, path: str | os.PathLike[str], flag: str, *, suffixes: Sequence[str] | None = None) -> Path:
        """An output file: its folder is created and test-written now; an existing file needs ``overwrite``."""

        def check(target: Path) -> Path:
            if suffixes is not None and target.suffix.lower() not in suffixes:
                raise ConfigError(f"{flag}: got {str(target)!r}, expected a file name ending in one of "
                                  f"{list(suffixes)}")
            if target.exists() or target.is_symlink():
                if not target.is_file():
                    raise ConfigError(f"{flag}: {target} exists and is not a regular file")
                if not self.overwrite:
                    raise ConfigError(f"{flag}: {target} already exists; pass --overwrite to replace it, "
                                      "or choose another path")
            return target.parent

        return self._prepare(path, flag, check)

    def discard(self) -> None:
        """Remove the folders this plan created that are still empty."""
        for folder in reversed(self._created):
            with contextlib.suppress(OSError):
                folder.rmdir()
        self._created.clear()

    def __enter__(self) -> OutputPlan:
        return self

    def __exit__(self, kind: type[BaseException] | None, *_: object) -> None:
        if kind is not None:
            self.discard()


@contextlib.contextmanager
def staged(*paths: str | os.PathLike[str]) -> Iterator[list[Path]]:
    """Temporary paths beside ``paths`` (same suffix) to write: all renamed into place if the block succeeds."""
    targets = [Path(p) for p in paths]
    temps = [t.with_name(f".{t.stem}.{os.getpid()}{PARTIAL}{t.suffix}") for t in targets]
    try:
        yield temps
        for temp, target in zip(temps, targets):
            os.replace(temp, target)
    finally:
        for temp in temps:
            with contextlib.suppress(FileNotFoundError):
                temp.unlink()


def atomic_write(path: str | os.PathLike[str], write: Callable[[Path], Any]) -> Path:
    """Call ``write(temporary_path)``, then rename the complete file to ``path`` (see :func:`staged`)."""
    with staged(path) as (temp,):
        write(temp)
    return Path(path)


def progress(total: int, desc: str, unit: str = "step", enabled: bool = True, leave: bool = True) -> Any:
    """A progress bar on stderr (tqdm's ``update``, ``set_postfix_str``, ``close``); without tqdm a line per tenth."""
    try:
        from tqdm import tqdm
    except ImportError:
        return _Lines(total, desc, unit, enabled)
    return tqdm(total=total, desc=desc, unit=unit, disable=not enabled, leave=leave)


class _Lines:
    """The plain fallback of :func:`progress`: done, rate and time left every tenth of the work."""

    def __init__(self, total: int, desc: str, unit: str, enabled: bool) -> None:
        self.total, self.desc, self.unit, self.enabled = max(int(total), 1), desc, unit, enabled
        self.n, self.shown, self.t0 = 0, 0, time.perf_counter()
        self.set_postfix_str = self.close = lambda *_: None

    def update(self, n: int = 1) -> None:
        self.n += n
        if self.enabled and 10 * self.n // self.total > self.shown:
            self.shown, rate = 10 * self.n // self.total, self.n / max(time.perf_counter() - self.t0, 1e-9)
            print(f"{self.desc}: {self.n}/{self.total} {self.unit}s, {rate:.1f} {self.unit}/s, "
                  f"{(self.total - self.n) / rate:.0f} s left", file=sys.stderr, flush=True)
