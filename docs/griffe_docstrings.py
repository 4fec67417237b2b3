"""A griffe extension for the API pages (``extensions:`` in ``mkdocs.yml``).

The docstrings give units in brackets (``[Pa]``, ``[–]``) and ranges as ``[0, 1/3]``; two
bracket groups in a row (``κ ∈ [0, 1/3] [–]``) read to Markdown as a reference link
``[text][id]``, which mkdocs-autorefs then fails to resolve (a warning, so an error under
``mkdocs build --strict``). The first group of such a pair is escaped, outside code spans.
"""

from __future__ import annotations

import re

import griffe

_PAIR = re.compile(r"\[([^\[\]`\n]*)\](\s?)(?=\[)")
_CODE = re.compile(r"(``?[^`]*``?)")


def escape_reference_pairs(text: str) -> str:
    """``[a] [b]`` → ``\\[a\\] [b]`` outside backtick code spans."""
    parts = _CODE.split(text)
    return "".join(p if i % 2 else _PAIR.sub(r"\\[\1\\]\2", p) for i, p in enumerate(parts))


class EscapeReferencePairs(griffe.Extension):
    """Escape ``[a] [b]`` in every docstring (see the module docstring)."""

    def on_instance(self, *, obj: griffe.Object, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = escape_reference_pairs(obj.docstring.value)
