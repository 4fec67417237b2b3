"""The one atomic file writer of the package and the JSON sanitiser.

:func:`write_atomic` is the atomic writer every output goes through (temporary file in the
target directory, then ``os.replace``: a reader never sees a half-written file and a crash
leaves no partial output); :func:`to_jsonable` turns numpy/JAX values, NamedTuples, enums
and paths into plain JSON values (NaN/inf → ``null``) and :func:`write_json` writes them
atomically.
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import json
import math
import os
import secrets
from typing import Any, cast

import jax
import numpy as np

__all__ = ["write_atomic", "write_json", "to_jsonable"]


def write_atomic(path, write_fn) -> None:
    """Write a file atomically: ``write_fn(tmp)`` fills a temporary file, which replaces
    ``path`` only once it is complete.

    The temporary file lies in the directory of ``path`` (so ``os.replace`` is atomic on
    POSIX and Windows), is flushed to disk with ``fsync`` before the rename and is removed
    if anything fails, ``KeyboardInterrupt`` included: ``path`` then keeps its old content
    (or stays absent) and no temporary file is left behind. The new file gets mode 0644.

    Args:
        path: the destination file (``str`` or path-like); its directory must exist.
        write_fn: called once as ``write_fn(tmp)`` with the temporary path (a ``str``
            ending in ``.tmp``); it must write the whole content to that path (pass an
            explicit format to writers that guess it from the extension).
    """
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    if os.path.isdir(path):
        raise IsADirectoryError(f"cannot write {path!r}: it is a directory; give a file name")
    if not os.path.isdir(directory):
        raise FileNotFoundError(
            f"cannot write {path!r}: the directory {directory!r} does not exist (create it "
            "first, e.g. os.makedirs(..., exist_ok=True))"
        )
    tmp = None
    try:
        for _ in range(100):
            # the name is bound before the file exists (unlike tempfile.mkstemp), so an
            # interrupt landing at any instant leaves nothing the cleanup below cannot see
            tmp = os.path.join(directory, f".{os.path.basename(path)}.{secrets.token_hex(8)}.tmp")
            try:
                os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
                break
            except FileExistsError:  # someone else's file: never remove it
                tmp = None
        else:
            raise FileExistsError(f"cannot create a temporary file for {path!r}")
        write_fn(tmp)
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)  # created 0600; outputs are meant to be read
        os.replace(tmp, path)
    except BaseException:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.remove(tmp)
        raise


def to_jsonable(obj, *, nonfinite: str = "null"):
    """Convert ``obj`` recursively into plain JSON values (dict, list, str, int, float,
    bool, None).

    Handles dicts (keys become ``str``; enum keys their name), lists, tuples and sets,
    NamedTuples (a dict of their fields), dataclass instances (a dict of their fields),
    enums (their ``name``, also for ``IntEnum`` such as ``Status``), paths (``os.fspath``),
    numpy and JAX scalars and arrays (nested lists), Python and numpy numbers.

    Args:
        obj: the object to convert (not a traced JAX value).
        nonfinite: how NaN and ±inf floats are written: ``"null"`` (default, ``None``) or
            ``"string"`` (``"nan"``, ``"inf"``, ``"-inf"``).

    Returns:
        A value that ``json.dumps(..., allow_nan=False)`` accepts.

    Raises:
        TypeError: an object of another type (the message names its position).
        ValueError: an unknown ``nonfinite``.
    """
    if nonfinite not in ("null", "string"):
        raise ValueError(f"nonfinite must be 'null' or 'string', got {nonfinite!r}")
    return _jsonable(obj, nonfinite, "obj")


def _json_float(x: float, nonfinite: str):
    if math.isfinite(x):
        return x
    if nonfinite == "null":
        return None
    return "nan" if math.isnan(x) else ("inf" if x > 0 else "-inf")


def _json_key(k) -> str:
    return k.name if isinstance(k, enum.Enum) else str(k)


def _jsonable(x, nonfinite: str, where: str):
    """:func:`to_jsonable` of ``x`` found at ``where`` (for the error message)."""
    if x is None or isinstance(x, bool):
        return x
    if isinstance(x, str):
        return str(x)  # np.str_ too
    if isinstance(x, enum.Enum):
        return x.name
    if isinstance(x, int):
        return int(x)
    if isinstance(x, float):
        return _json_float(float(x), nonfinite)
    if isinstance(x, (np.ndarray, np.generic, jax.Array)):
        a = np.asarray(x)
        if a.dtype.kind in "biu":
            return a.tolist()
        if a.dtype.kind == "f":
            if a.ndim == 0:
                return _json_float(float(a), nonfinite)
            return [_jsonable(v, nonfinite, f"{where}[{i}]") for i, v in enumerate(a)]
        if a.dtype.kind in "OUS":
            return _jsonable(a.tolist(), nonfinite, where)
        raise TypeError(f"to_jsonable: {where} is an array of dtype {a.dtype}")
    if isinstance(x, dict):
        return {_json_key(k): _jsonable(v, nonfinite, f"{where}[{k!r}]") for k, v in x.items()}
    if isinstance(x, tuple) and hasattr(x, "_asdict"):  # NamedTuple
        fields: dict = cast(Any, x)._asdict()
        return {k: _jsonable(v, nonfinite, f"{where}.{k}") for k, v in fields.items()}
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return {
            f.name: _jsonable(getattr(x, f.name), nonfinite, f"{where}.{f.name}")
            for f in dataclasses.fields(x)
        }
    if isinstance(x, (list, tuple)):
        return [_jsonable(v, nonfinite, f"{where}[{i}]") for i, v in enumerate(x)]
    if isinstance(x, (set, frozenset)):
        items = [_jsonable(v, nonfinite, f"{where}{{...}}") for v in x]
        return sorted(items, key=repr)
    if isinstance(x, os.PathLike):
        return os.fspath(x)
    raise TypeError(f"to_jsonable: {where} has type {type(x).__name__}, not JSON-serialisable")


def write_json(path, obj, *, indent: int | None = 1, nonfinite: str = "null") -> None:
    """Write ``to_jsonable(obj)`` as JSON (UTF-8, trailing newline) atomically to ``path``.

    Args:
        path: the destination file; see :func:`write_atomic`.
        obj: anything :func:`to_jsonable` accepts.
        indent: ``json.dumps`` indentation (``None``: one line).
        nonfinite: how NaN/inf are written, see :func:`to_jsonable`.
    """
    text = json.dumps(to_jsonable(obj, nonfinite=nonfinite), indent=indent, allow_nan=False)

    def write(tmp: str) -> None:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text + "\n")

    write_atomic(path, write)
