"""Reading scenes: :func:`load_scene` (a TOML file, a shipped name or a dict) → :class:`Scene`.

:func:`apply_overrides` applies dotted-path replacements (``--set mesh.n=[6,2,2]``) to a
raw scene before validation; :func:`shipped_scenes` lists the scene files shipped in
``jaxelastic/scene/data``.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import os
import sys
import types
from collections.abc import Mapping
from typing import Any

from .errors import SceneError
from .schema import SceneSpec, validate

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python < 3.11
    import tomli as tomllib

__all__ = ["Scene", "load_scene", "apply_overrides", "shipped_scenes", "SCENE_DIR"]

SCENE_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "data")
"""Directory of the shipped scene files."""


def freeze(obj: Any) -> Any:
    """Nested mappings and sequences as read-only mappings and tuples."""
    if isinstance(obj, Mapping):
        return types.MappingProxyType({k: freeze(v) for k, v in obj.items()})
    if isinstance(obj, (list, tuple)):
        return tuple(freeze(v) for v in obj)
    return obj


def thaw(obj: Any) -> Any:
    """Nested mappings and sequences as plain dicts and lists (a deep copy)."""
    if isinstance(obj, Mapping):
        return {k: thaw(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [thaw(v) for v in obj]
    return obj


@dataclasses.dataclass(frozen=True)
class Scene:
    """A validated scene (read-only).

    Attributes:
        spec: the typed, validated scene (:class:`~jaxelastic.scene.schema.SceneSpec`).
        label: how messages name the scene (the file name, or ``"<dict>"``).
        source: absolute path of the scene file, or None.
        base_dir: directory that relative paths and ``module:function`` imports resolve
            against.
    """

    spec: SceneSpec
    label: str
    source: str | None
    base_dir: str

    @functools.cached_property
    def data(self) -> Mapping:
        """The scene as nested read-only mappings and tuples, with defaults filled in (a
        valid scene itself: ``load_scene(scene.to_dict())`` round-trips)."""
        return freeze(self.spec.model_dump(mode="python", exclude_none=True))

    def __getitem__(self, key):
        return self.data[key]

    def get(self, key, default=None):
        return self.data.get(key, default)

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def static(self) -> bool:
        return self.spec.static

    @property
    def dim(self) -> int | None:
        """Spatial dimension when known before reading a mesh file, else None."""
        return self.spec.known_dim

    def to_dict(self) -> dict:
        """A plain, JSON-serialisable deep copy of :attr:`data`."""
        return thaw(self.data)

    def error(self, msg: str) -> SceneError:
        """A :class:`SceneError` ``scene '<label>': <msg>``."""
        return SceneError(f"scene {self.label!r}: {msg}")


def shipped_scenes() -> dict[str, str]:
    """Name → path of the scene files shipped with jaxelastic (``default``, ``twist``, …)."""
    if not os.path.isdir(SCENE_DIR):
        return {}
    names = sorted(f for f in os.listdir(SCENE_DIR) if f.endswith(".toml"))
    return {f[: -len(".toml")]: os.path.join(SCENE_DIR, f) for f in names}


def apply_overrides(data: Mapping, overrides: Mapping[str, Any]) -> dict:
    """A deep copy of a raw scene dict with dotted-path overrides applied.

    ``{"mesh.n": [6, 2, 2], "integrator.duration": 0.5, "dirichlet.0.displacement": [..]}``;
    an integer path component indexes an array of tables. Missing tables are created.
    """
    out = thaw(data)
    for path, value in overrides.items():
        parts = str(path).split(".")
        node: Any = out
        for i, p in enumerate(parts):
            last = i == len(parts) - 1
            if isinstance(node, list):
                if not p.lstrip("-").isdigit() or not -len(node) <= int(p) < len(node):
                    raise SceneError(f"override {path!r}: {p!r} is not an index of the array")
                if last:
                    node[int(p)] = copy.deepcopy(value)
                else:
                    node = node[int(p)]
            elif isinstance(node, dict):
                if last:
                    node[p] = copy.deepcopy(value)
                else:
                    node = node.setdefault(p, {})
            else:
                raise SceneError(f"override {path!r}: {'.'.join(parts[:i])!r} is not a table")
    return out


def read_toml(source) -> tuple[dict, str]:
    """``(raw dict, absolute path)`` of a scene file or shipped scene name.

    Raises:
        SceneError: no such file, a directory, not UTF-8, or invalid TOML.
    """
    path = os.fspath(source)
    shipped = shipped_scenes()
    if not os.path.exists(path) and path.removesuffix(".toml") in shipped:
        path = shipped[path.removesuffix(".toml")]
    path = os.path.abspath(path)
    label = os.path.basename(path)
    if os.path.isdir(path):
        inside = sorted(f for f in os.listdir(path) if f.endswith(".toml"))[:5]
        hint = f" (scene files in it: {', '.join(inside)})" if inside else ""
        raise SceneError(
            f"scene {os.fspath(source)!r}: is a directory, not a scene file; give a scene "
            f"TOML file{hint}"
        )
    if not os.path.isfile(path):
        raise SceneError(
            f"scene {os.fspath(source)!r}: no such file (shipped scenes: "
            f"{', '.join(shipped) or 'none'})"
        )
    try:
        with open(path, "rb") as f:
            return tomllib.load(f), path
    except tomllib.TOMLDecodeError as e:
        raise SceneError(f"scene {label!r}: invalid TOML: {e}") from None
    except UnicodeDecodeError as e:
        raise SceneError(f"scene {label!r}: not a UTF-8 text file ({e})") from None
    except RecursionError:
        raise SceneError(_too_deep(label)) from None


def _too_deep(label: str) -> str:
    return (
        f"scene {label!r}: arrays or tables nested too deeply to read (a scene needs at most "
        "a few levels: tables, arrays of tables, vectors)"
    )


def load_scene(
    source, *, overrides: Mapping[str, Any] | None = None, base_dir: str | None = None
) -> Scene:
    """Read and validate a scene.

    Args:
        source: a TOML file path, the name of a shipped scene (``"default"``, ``"twist"``,
            …, see :func:`shipped_scenes`), a dict with the same structure as the TOML,
            or a :class:`Scene` (returned as is unless ``overrides`` are given).
        overrides: dotted-path replacements applied before validation (see
            :func:`apply_overrides`), e.g. ``{"mesh.n": [6, 2, 2]}``.
        base_dir: directory for relative mesh paths and ``module:function`` imports of a
            dict scene (default: the current directory; for a file, its directory).

    Raises:
        SceneError: the file is missing or not TOML, or the scene is invalid (the message
            names the scene, the key, the bad value and what is valid).
    """
    if isinstance(source, Scene):
        if not overrides:
            return source
        return load_scene(source.to_dict(), overrides=overrides, base_dir=source.base_dir)
    path = None
    if isinstance(source, Mapping):
        raw, label = source, "<dict>"
        bdir = os.path.abspath(base_dir or os.getcwd())
    elif isinstance(source, (str, os.PathLike)):
        raw, path = read_toml(source)
        label = os.path.basename(path)
        bdir = os.path.abspath(base_dir or os.path.dirname(path))
    else:
        raise TypeError(f"load_scene() takes a path, a dict or a Scene, got {type(source)}")
    try:
        raw = apply_overrides(raw, overrides or {})
        return Scene(validate(raw, label, bdir), label, path, bdir)
    except RecursionError:
        raise SceneError(_too_deep(label)) from None
