"""Run folders and the files in them: claimed exclusively, written atomically, paths checked first.

* :func:`claim_run_dir`: a new folder per run (``<name>_2``, ``<name>_3``, ... when taken), claimed
  with its :data:`INCOMPLETE_FILE`; :func:`abandon_run` after a failure.
* :func:`atomic_write` and its helpers: every file training and evaluation write goes to a
  temporary file in the same folder and is renamed over the target (``os.replace``) once complete,
  so an interrupted write (Ctrl-C, a full disk, a crash) leaves the old file or the new one, never
  part of one; the temporary file is removed on every way out.
* :func:`check_path`, :func:`check_name`: a path or folder name from a user or config (no NUL,
  each component at most :data:`MAX_NAME_BYTES`, the whole at most :data:`MAX_PATH_BYTES`),
  checked before any folder is made.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np

from aasoatt_env.errors import ConfigError

__all__ = ["INCOMPLETE_FILE", "MAX_NAME_BYTES", "MAX_PATH_BYTES", "abandon_run", "atomic_path", "atomic_write",
           "check_name", "check_path", "claim_run_dir", "finite_json", "save_npz", "unique_run_dir", "write_json",
           "write_text"]

INCOMPLETE_FILE = "INCOMPLETE"
"""A run folder holds this file while its training runs, and keeps it if training failed after a checkpoint."""
MAX_NAME_BYTES = 200
"""Longest file or folder name accepted (bytes; file systems allow 255, and run folders get suffixes)."""
MAX_PATH_BYTES = 3000
"""Longest path accepted (bytes; below the 4096 of ``PATH_MAX``, leaving room for a run's own files)."""


def check_path(value: Any, name: str) -> str:
    """``value`` as a path string, or a :class:`ConfigError` naming ``name`` (empty, NUL, too long)."""
    if isinstance(value, os.PathLike):
        value = os.fspath(value)
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{name}: got {value!r}, expected a non-empty path")
    if "\x00" in value:
        raise ConfigError(f"{name}: got {value[:80]!r}, expected a path without NUL characters")
    size = len(os.fsencode(value))
    if size > MAX_PATH_BYTES:
        raise ConfigError(f"{name}: got a path of {size} bytes, expected at most {MAX_PATH_BYTES}")
    long = [part for part in Path(value).parts if len(os.fsencode(part)) > MAX_NAME_BYTES]
    if long:
        raise ConfigError(f"{name}: got a path whose part {long[0][:40]!r}... has {len(os.fsencode(long[0]))} bytes, "
                          f"expected names of at most {MAX_NAME_BYTES}")
    return value


def check_name(value: Any, name: str) -> str:
    """``value`` as a folder name (one path component, not ``.`` or ``..``), or a :class:`ConfigError`."""
    check_path(value, name)
    if value in (".", "..") or os.sep in value or (os.altsep and os.altsep in value) or "/" in value:
        raise ConfigError(f"{name}: got {value!r}, expected a folder name (no path separators, not '.' or '..')")
    return value


# ---------------------------------------------------------------------------------------- atomic writes
@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str], suffix: str = "") -> Iterator[Path]:
    """A temporary path in ``path``'s folder; renamed to ``path`` when the block ends without an error.

    On any error (including ``KeyboardInterrupt``) the temporary file is removed and ``path`` is
    left as it was.  ``suffix`` is kept at the end of the temporary name (writers that add one).
    """
    target = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=f".tmp{suffix}", dir=target.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def atomic_write(path: str | os.PathLike[str], write: Callable[[IO[bytes]], Any]) -> Path:
    """Write ``path`` atomically: ``write(fh)`` fills a temporary file, flushed to disk, then renamed."""
    with atomic_path(path) as tmp, tmp.open("wb") as fh:
        write(fh)
        fh.flush()
        os.fsync(fh.fileno())
    return Path(path)


def write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Write ``text`` (UTF-8) atomically."""
    return atomic_write(path, lambda fh: fh.write(text.encode()))


def finite_json(obj: Any) -> Any:
    """``obj`` with every non-finite number (NaN, inf; numpy scalars too) replaced by None."""
    if isinstance(obj, dict):
        return {k: finite_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_json(v) for v in obj]
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj


def write_json(path: str | os.PathLike[str], data: Any) -> Path:
    """Write ``data`` as strict JSON atomically (non-finite numbers become null, never a bare NaN)."""
    return write_text(path, json.dumps(finite_json(data), indent=2, allow_nan=False))


def save_npz(path: str | os.PathLike[str], **arrays: Any) -> Path:
    """``np.savez`` of ``arrays`` to ``path`` atomically."""
    return atomic_write(path, lambda fh: np.savez(fh, **arrays))


# ---------------------------------------------------------------------------------------- run folders
def claim_run_dir(out_dir: str | os.PathLike[str], name: str, marker: bool = True) -> tuple[Path, bool]:
    """Create (or take an empty) ``<out_dir>/<name>``, or ``<name>_2``, ``<name>_3``, ...; and whether it was created.

    A run never writes into the folder of another run; an existing empty folder is used.  With
    ``marker`` the folder is claimed by creating its :data:`INCOMPLETE_FILE` exclusively, so two
    runs started at once never share a folder; the caller removes the marker when the run is done.
    The flag says whether this call created the folder (:func:`abandon_run` removes only such).
    """
    base = Path(out_dir) / name
    path, k = base, 1
    while True:
        created = False
        try:
            path.mkdir(parents=True)
            created = True
        except FileExistsError:
            if not (path.exists() or path.is_symlink()):  # a parent is a dangling link: no name will do
                raise
        if path.is_dir() and (created or not any(path.iterdir())):
            if not marker:
                return path, created
            try:
                with (path / INCOMPLETE_FILE).open("x") as fh:
                    fh.write("training in progress or failed: this is not a finished run\n")
                return path, created
            except FileExistsError:  # another run claimed it first
                pass
        k += 1
        path = base.with_name(f"{base.name}_{k}")


def unique_run_dir(out_dir: str | os.PathLike[str], name: str) -> Path:
    """Create and return ``<out_dir>/<name>``, or ``<name>_2``, ``<name>_3``, ... if it holds files.

    A run never writes into the folder of another run; an existing empty folder is used
    (:func:`claim_run_dir` without a marker).
    """
    return claim_run_dir(out_dir, name, marker=False)[0]


def abandon_run(run: Path, keep: bool, created: bool) -> None:
    """After a failed training: empty ``run`` (removed if this run created it), or mark it incomplete.

    With ``keep`` (it holds a model or checkpoint) it stays with an :data:`INCOMPLETE_FILE` and no
    ``train_stats.json`` (what marks a finished run).  A folder that existed before the run (an empty
    folder it was given, or a link to one) stays, emptied.
    """
    if keep:
        with contextlib.suppress(OSError):
            (run / "train_stats.json").unlink(missing_ok=True)
            write_text(run / INCOMPLETE_FILE, "training did not finish: resume it (aasoatt train --resume), or keep "
                                              "the checkpoints you need and remove this folder\n")
        return
    for child in list(run.iterdir()) if run.is_dir() else []:
        if child.is_dir() and not child.is_symlink():
            shutil.rmtree(child, ignore_errors=True)
        else:
            child.unlink(missing_ok=True)
    if created and not run.is_symlink():
        with contextlib.suppress(OSError):
            run.rmdir()
