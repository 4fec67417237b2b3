"""Names that moved keep resolving for one release, with a ``DeprecationWarning``.

A package whose names moved binds ``__getattr__ = moved_attributes(...)``: Python calls it
only for attributes the module does not have (PEP 562), so the forward costs nothing on
the names that live there, and each target is imported when it is first asked for (a
forward is not a dependency: :mod:`jaxelastic.loads` forwards to the post-processing
layer above it).
"""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable, Mapping

__all__ = ["moved_attributes"]


def moved_attributes(
    module: str, shown_as: str, moved: Mapping[str, tuple[str, str]]
) -> Callable[[str], object]:
    """A module ``__getattr__`` that resolves the names of ``moved`` with a warning.

    Args:
        module: the module's ``__name__`` (for the AttributeError of other names).
        shown_as: how users write the module (``"je"``, ``"jaxelastic.io"``), for the warning.
        moved: old name → ``(where, instead)``: ``where`` is ``"package.module"`` or
            ``"package.module:attribute"``, what the old name now returns; ``instead`` what
            to write, quoted in the warning.
    """

    def __getattr__(name: str):
        if name not in moved:
            raise AttributeError(f"module {module!r} has no attribute {name!r}")
        where, instead = moved[name]
        warnings.warn(
            f"{shown_as}.{name} is deprecated and will be removed: use {instead}",
            DeprecationWarning,
            stacklevel=2,
        )
        path, _, attribute = where.partition(":")
        target = importlib.import_module(path)
        return getattr(target, attribute) if attribute else target

    return __getattr__
