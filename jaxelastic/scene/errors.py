"""Scene errors: :class:`SceneError` and the translation of pydantic's ``ValidationError``.

Every message names the scene, the key as it is written in the file (``[material].nu``,
``[dirichlet][0].nodes.plane.axis``, ``[fit.case][1].weight``), the bad value and the valid
choices or range, e.g. ``scene 'beam.toml': [material].nu must be < 0.5, got 0.7``.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

from pydantic import ValidationError
from pydantic_core import PydanticCustomError

__all__ = ["SceneError", "fail", "key_path", "type_name", "describe", "from_validation_error"]

AT = "{at}"
"""Placeholder for the key path in the text of :func:`fail` errors."""


class SceneError(ValueError):
    """An invalid scene; the message names the scene and the offending key."""


def fail(text: str) -> PydanticCustomError:
    """A validation error with our own text; ``{at}`` in ``text`` becomes the key path of the
    value being validated (raise it inside a pydantic validator)."""
    return PydanticCustomError("scene", "{text}", {"text": text})


def type_name(x) -> str:
    """The TOML name of a value's type (``boolean``, ``integer``, ``float``, ``string``,
    ``array``, ``table``)."""
    for t, name in (
        (bool, "boolean"),
        (int, "integer"),
        (float, "float"),
        (str, "string"),
        (list, "array"),
        (tuple, "array"),
        (Mapping, "table"),
    ):
        if isinstance(x, t):
            return name
    return type(x).__name__


def key_path(loc) -> str:
    """The key as written in a scene file, from a pydantic error location.

    ``("material", "nu")`` → ``[material].nu``; ``("dirichlet", 0, "nodes")`` →
    ``[dirichlet][0].nodes``; ``("fit", "case", 1, "weight")`` → ``[fit.case][1].weight``;
    ``("name",)`` → ``name``. Union tags (strings starting with ``~``) are dropped.
    """
    parts = [p for p in loc if not (isinstance(p, str) and p.startswith("~"))]
    if not parts:
        return ""
    if parts[0] in ("name", "description"):
        head, rest = str(parts[0]), parts[1:]
    elif parts[:2] == ["fit", "case"]:
        head, rest = "[fit.case]", parts[2:]
    else:
        head, rest = f"[{parts[0]}]", parts[1:]
    return head + "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in rest)


_TYPE_WORDS = {
    "float_type": "a number",
    "float_parsing": "a number",
    "int_type": "an integer",
    "int_parsing": "an integer",
    "int_from_float": "an integer",
    "bool_type": "true or false",
    "bool_parsing": "true or false",
    "string_type": "a string",
    "list_type": "an array",
    "tuple_type": "an array",
    "dict_type": "a table",
    "model_type": "a table",
    "model_attributes_type": "a table",
}
_BOUNDS = {
    "greater_than": ("gt", ">"),
    "greater_than_equal": ("ge", ">="),
    "less_than": ("lt", "<"),
    "less_than_equal": ("le", "<="),
}


def _choices(expected: str) -> str:
    """``"'a', 'b' or 'c'"`` (pydantic's wording) → ``"'a', 'b', 'c'"`` (tags lose ``~``)."""
    items = re.findall(r"'[^']*'|[^\s,']+", expected.replace(" or ", ", "))
    return ", ".join(i.replace("'~", "'") for i in items)


def describe(err: Mapping[str, Any]) -> str:
    """One pydantic error (an item of ``ValidationError.errors()``) as a scene message."""
    kind, ctx, x = err["type"], err.get("ctx") or {}, err.get("input")
    at = key_path(err["loc"])
    got = f"got {type_name(x)} {x!r}"
    if kind == "scene":
        return ctx["text"].replace(AT, at)
    if kind == "missing":
        return f"{at} is required"
    if kind in _TYPE_WORDS:
        return f"{at} must be {_TYPE_WORDS[kind]}, {got}"
    if kind in _BOUNDS:
        name, op = _BOUNDS[kind]
        return f"{at} must be {op} {ctx[name]:g}, got {x!r}"
    if kind == "finite_number":
        return f"{at} must be finite, got {x!r}"
    if kind == "too_short":
        return f"{at} must be a non-empty array, got {x!r}"
    if kind == "literal_error":
        if "'" not in ctx["expected"]:  # numbers: "1 or 2"
            return f"{at} must be {ctx['expected']}, got {x!r}"
        return f"{at} must be one of {_choices(ctx['expected'])}, got {x!r}"
    if kind == "union_tag_invalid":  # the integrator's type
        return f"{at}.type must be one of {_choices(ctx['expected_tags'])}, got {ctx['tag']!r}"
    if kind == "extra_forbidden":
        return f"unknown key {at}"
    return f"{at}: {err['msg']}"


def from_validation_error(label: str, e: ValidationError, limit: int = 5) -> SceneError:
    """A :class:`SceneError` for scene ``label`` naming the first problem (and up to
    ``limit - 1`` more, one per line)."""
    msgs = list(dict.fromkeys(describe(err) for err in e.errors()))
    text = f"scene {label!r}: {msgs[0]}"
    for m in msgs[1:limit]:
        text += f"\n  and: {m}"
    if len(msgs) > limit:
        text += f"\n  ({len(msgs) - limit} more)"
    return SceneError(text)
