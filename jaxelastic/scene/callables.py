"""User functions named in a scene as ``"module:function"`` (materials, displacements,
initial velocities), imported with the scene file's directory first on ``sys.path``."""

from __future__ import annotations

import contextlib
import importlib
import inspect
import sys
from collections.abc import Callable

__all__ = ["CallableSpecError", "import_callable", "n_positional"]


class CallableSpecError(ValueError):
    """A ``"module:function"`` that cannot be resolved (the message says why)."""


@contextlib.contextmanager
def _on_path(directory: str):
    sys.path.insert(0, directory)
    try:
        yield
    finally:
        with contextlib.suppress(ValueError):
            sys.path.remove(directory)


def import_callable(spec: str, base_dir: str) -> Callable:
    """Resolve ``"module:function"`` (dotted attribute paths allowed after the colon).

    Args:
        spec: ``"package.module:function"`` or ``"module:Class.method"``.
        base_dir: directory searched first for ``module`` (restored afterwards).
    Raises:
        CallableSpecError: a malformed spec, a failed import, a missing attribute, or an
            object that is not callable.
    """
    mod_name, _, attr = spec.partition(":")
    if not mod_name or not attr:
        raise CallableSpecError(f"{spec!r} is not of the form 'module:function'")
    try:
        with _on_path(base_dir):
            obj = importlib.import_module(mod_name)
    except Exception as e:  # noqa: BLE001 — any import failure is reported with the key
        raise CallableSpecError(
            f"cannot import module {mod_name!r} ({type(e).__name__}: {e})"
        ) from None
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise CallableSpecError(f"module {mod_name!r} has no attribute {attr!r}")
        obj = getattr(obj, part)
    if not callable(obj):
        raise CallableSpecError(f"{spec!r} is not callable")
    return obj


def n_positional(fn) -> int:
    """Number of positional parameters ``fn`` accepts (99 for ``*args``)."""
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        return 1
    n = 0
    for p in sig.parameters.values():
        if p.kind == p.VAR_POSITIONAL:
            return 99
        if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD):
            n += 1
    return n
