"""Reading a run's files without trusting them: bounded sizes, plain data, fixed names and shapes.

Every reader here checks what it can before it allocates or deserialises anything:

* JSON (:func:`read_json`, :func:`parse_json`): at most :data:`MAX_JSON_BYTES`, nested at most
  :data:`MAX_JSON_DEPTH` levels (counted without recursion, so ``[`` x 100,000 is refused, never
  a ``RecursionError``), an object at the top;
* zip members (:func:`zip_member`): the size the archive declares is bounded before reading;
* ``.npz`` archives (:func:`read_npz`): only the expected names, each array's header (dtype,
  shape) checked against the expected shape before its data is read, real finite numbers;
* torch files (:func:`read_tensors`): ``torch.load(weights_only=True)`` (no code runs), then a
  flat mapping of exactly the expected names to finite float tensors of the expected shapes.

Every refusal is a :class:`~aasoatt_env.errors.DataFileError` naming the file (and entry).
"""

from __future__ import annotations

import io
import json
import math
import re
import zipfile
import zlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from aasoatt_env.errors import DataFileError

__all__ = ["MAX_JSON_BYTES", "MAX_JSON_DEPTH", "READ_ERRORS", "load_tensor_file", "parse_json", "read_json", "read_npz",
           "read_tensors", "zip_member"]

MAX_JSON_BYTES: int = 1 << 20
"""Largest JSON file a run may hold (``policy.json``, ``config.json``, a model zip's ``data``): 1 MiB."""
MAX_JSON_DEPTH: int = 32
"""Deepest nesting a run's JSON may have (what training writes is at most 4 levels deep)."""
MAX_MEMBERS: int = 64
"""Most entries a model zip or ``.npz`` archive may have."""

READ_ERRORS: tuple[type[BaseException], ...] = (
    OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile, zlib.error, NotImplementedError,
    MemoryError, UnicodeDecodeError, RuntimeError, AttributeError, IndexError,
)
"""What reading a corrupted or crafted file can raise (bad zip or deflate data, an unsupported zip
feature, a torch file that is no tensor archive)."""

_STRING = re.compile(r'"(?:[^"\\]|\\.)*"')


def _why(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {str(exc)[:200]}"


def json_depth(text: str) -> int:
    """How deeply ``[`` and ``{`` nest in ``text`` (outside strings), counted without recursion."""
    code = np.frombuffer(_STRING.sub('""', text).encode("utf-8", "replace"), dtype=np.uint8)
    step = (np.isin(code, (ord("["), ord("{"))).astype(np.int64)
            - np.isin(code, (ord("]"), ord("}"))).astype(np.int64))
    return int(np.cumsum(step).max(initial=0))


def parse_json(raw: bytes | str, where: str, max_bytes: int = MAX_JSON_BYTES) -> dict[str, Any]:
    """A JSON object from ``raw`` (at most ``max_bytes``, :data:`MAX_JSON_DEPTH` levels, finite numbers).

    Parameters
    ----------
    raw : bytes or str
        The file's content.
    where : str
        The file (and entry) for the message.
    max_bytes : int
        Size bound.

    Raises
    ------
    DataFileError
        Too large, too deep, not JSON, NaN/Infinity constants, or not an object at the top.
    """
    if len(raw) > max_bytes:
        raise DataFileError(f"{where}: {len(raw):,} bytes, expected a JSON file of at most {max_bytes:,} bytes")
    try:
        text = raw.decode("utf-8") if isinstance(raw, bytes) else raw
    except UnicodeDecodeError as exc:
        raise DataFileError(f"{where}: not a readable JSON file ({_why(exc)})") from None
    depth = json_depth(text)
    if depth > MAX_JSON_DEPTH:
        raise DataFileError(f"{where}: not a readable JSON file (nested {depth} levels deep, expected at most "
                            f"{MAX_JSON_DEPTH})")

    def constant(name: str) -> Any:
        raise ValueError(f"non-standard constant {name}")

    try:
        data = json.loads(text, parse_constant=constant)
    except (ValueError, RecursionError) as exc:
        raise DataFileError(f"{where}: not a readable JSON file ({_why(exc)})") from None
    if not isinstance(data, dict):
        raise DataFileError(f"{where}: got a JSON {type(data).__name__}, expected an object")
    return data


def read_json(path: Path, max_bytes: int = MAX_JSON_BYTES) -> dict[str, Any]:
    """:func:`parse_json` of the file ``path`` (its size checked before it is read)."""
    try:
        size = path.stat().st_size
        if size > max_bytes:
            raise DataFileError(f"{path}: {size:,} bytes, expected a JSON file of at most {max_bytes:,} bytes")
        raw = path.read_bytes()
    except OSError as exc:
        raise DataFileError(f"{path}: not a readable JSON file ({_why(exc)})") from None
    return parse_json(raw, str(path), max_bytes)


def zip_member(archive: zipfile.ZipFile, name: str, max_bytes: int, where: str) -> bytes:
    """The entry ``name`` of ``archive``, refused when its declared size exceeds ``max_bytes``."""
    infos = archive.infolist()
    if len(infos) > MAX_MEMBERS:
        raise DataFileError(f"{where}: {len(infos)} entries, expected at most {MAX_MEMBERS}")
    info = next((i for i in infos if i.filename == name), None)
    if info is None:
        raise DataFileError(f"{where}: no entry {name!r}")
    if info.file_size > max_bytes:
        raise DataFileError(f"{where}: entry {name!r} declares {info.file_size:,} bytes, expected at most "
                            f"{max_bytes:,}")
    try:
        return archive.read(info)
    except READ_ERRORS as exc:
        raise DataFileError(f"{where}: entry {name!r} is not readable ({_why(exc)})") from None


def _npz_array(archive: zipfile.ZipFile, name: str, shape: tuple[int, ...] | None, where: str) -> np.ndarray:
    """One ``.npy`` entry: header checked (real dtype, ``shape`` or a scalar) before the data is read."""
    fmt = np.lib.format
    info = archive.getinfo(name + ".npy")
    want = shape if shape is not None else ()
    bound = 256 + 8 * max(1, math.prod(want))
    if info.file_size > bound:
        raise DataFileError(f"{where}: {name!r} declares {info.file_size:,} bytes, expected at most {bound:,} "
                            f"(shape {want})")
    with archive.open(info) as fh:
        version = fmt.read_magic(fh)
        header = fmt.read_array_header_1_0(fh) if version == (1, 0) else fmt.read_array_header_2_0(fh)
        got, _, dtype = header
        if dtype.kind not in "fiu" or dtype.hasobject:
            raise DataFileError(f"{where}: {name!r} has dtype {dtype}, expected real numbers")
        if tuple(got) != want:
            raise DataFileError(f"{where}: {name!r} has shape {tuple(got)}, expected {want}")
        fh.seek(0)
        arr = fmt.read_array(fh, allow_pickle=False)
    if not np.isfinite(arr).all():
        raise DataFileError(f"{where}: {name!r} holds non-finite values, expected finite numbers")
    return np.asarray(arr, dtype=np.float64)


def read_npz(path: Path, expected: Mapping[str, tuple[int, ...] | None],
             optional: Mapping[str, tuple[int, ...] | None] | None = None) -> dict[str, np.ndarray]:
    """The arrays of an ``.npz`` file: exactly the ``expected`` names (plus any of ``optional``).

    Parameters
    ----------
    path : Path
        The file.
    expected, optional : mapping
        Array name -> expected shape (``None``: a scalar).

    Returns
    -------
    dict
        Name -> float64 array (finite).

    Raises
    ------
    DataFileError
        Not a zip of ``.npy`` entries, unexpected or missing names, a header with another dtype or
        shape (checked before the data is read), non-finite values.
    """
    optional = dict(optional or {})
    allowed = {**optional, **expected}
    try:
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
            if len(names) > MAX_MEMBERS or not all(n.endswith(".npy") for n in names):
                raise DataFileError(f"{path}: expected an .npz archive of at most {MAX_MEMBERS} .npy arrays")
            found = {n[:-4] for n in names}
            unknown = sorted(found - set(allowed))
            missing = sorted(set(expected) - found)
            if unknown or missing:
                raise DataFileError(f"{path}: got arrays {sorted(found)}, expected {sorted(expected)}"
                                    + (f" (and optionally {sorted(optional)})" if optional else ""))
            return {n: _npz_array(archive, n, allowed[n], str(path)) for n in sorted(found)}
    except DataFileError:
        raise
    except READ_ERRORS as exc:
        raise DataFileError(f"{path}: not a readable .npz file of plain arrays ({_why(exc)}); files are never "
                            "unpickled") from None


def load_tensor_file(raw: bytes, where: str) -> Any:
    """``torch.load(weights_only=True)`` of ``raw``: tensors and plain containers only, no code runs."""
    import torch

    try:
        return torch.load(io.BytesIO(raw), map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - whatever torch's safe unpickler raises on a crafted file
        why = ("it holds objects other than tensors (refused: files are never unpickled)"
               if "Weights only load failed" in str(exc) else _why(exc))
        raise DataFileError(f"{where}: not a readable tensor file ({why})") from None


def read_tensors(raw: bytes, where: str, expected: Mapping[str, tuple[int, ...]]) -> dict[str, Any]:
    """Torch tensors by a fixed list of names and shapes from a ``torch.save`` file (nothing else is set).

    ``torch.load(weights_only=True)`` runs no code; the result must map exactly the ``expected``
    names to finite floating-point tensors of the expected shapes.  Nothing in the process
    changes here: the caller copies the checked tensors into a module it built.

    Raises
    ------
    DataFileError
        Not a tensor file, other names (a dotted or dunder name is just another name), another
        shape or dtype, non-finite values.
    """
    import torch

    state = load_tensor_file(raw, where)
    if not isinstance(state, Mapping):
        raise DataFileError(f"{where}: got a {type(state).__name__}, expected a mapping of tensor names")
    names = [str(k) for k in state]
    unknown = sorted(n for n in names if n not in expected)
    missing = sorted(set(expected) - set(names))
    if unknown or missing or not all(isinstance(k, str) for k in state):
        shown = ", ".join(repr(n[:80]) for n in (unknown or missing)[:4])
        listed = f"{sorted(expected)[:6]}{'...' if len(expected) > 6 else ''}"
        raise DataFileError(f"{where}: {'unexpected' if unknown else 'missing'} entries {shown}; expected exactly "
                            f"{len(expected)} named parameters {listed}")
    for name, want in expected.items():
        t = state[name]
        if not isinstance(t, torch.Tensor) or not t.dtype.is_floating_point or tuple(t.shape) != tuple(want):
            got = f"{t.dtype} {tuple(t.shape)}" if isinstance(t, torch.Tensor) else type(t).__name__
            raise DataFileError(f"{where}: {name!r} is {got}, expected a float tensor of shape {tuple(want)}")
        if not bool(torch.isfinite(t).all()):
            raise DataFileError(f"{where}: {name!r} holds non-finite values (NaN or inf), expected finite weights")
    return dict(state)
