"""Scenes: a simulation described in a TOML file, validated, built and run.

A scene names a mesh, a material, boundary conditions, loads, solver settings, an
integrator and outputs (reference: ``docs/scenes.md``, generated from the schema).
:func:`load_scene` validates it (unknown keys, wrong types and impossible values are
refused with a :class:`SceneError` naming the key, the value and what is valid),
:func:`build` turns it into arrays and a :class:`~jaxelastic.mechanics.potential.Potential`,
:func:`run_scene` solves it and writes the outputs (``jaxelastic run SCENE --out DIR``),
and :func:`run_fit` identifies E and ν as its ``[fit]`` table says (``jaxelastic fit``).
:func:`json_schema` is the JSON Schema of a scene file (``jaxelastic schema``).

Modules, in import order: :mod:`~jaxelastic.scene.errors`, :mod:`~jaxelastic.scene.where`
(selection expressions), :mod:`~jaxelastic.scene.callables` (``"module:function"``),
:mod:`~jaxelastic.scene.schema` (the pydantic models), :mod:`~jaxelastic.scene.docs` (the
generated reference), :mod:`~jaxelastic.scene.load`, :mod:`~jaxelastic.scene.problem`,
:mod:`~jaxelastic.scene.outputs`, :mod:`~jaxelastic.scene.run`, :mod:`~jaxelastic.scene.fit`.
Shipped scenes (``scene/data/*.toml``, :func:`shipped_scenes`; a test keeps this list
complete): ``balloon`` (an inflated thick sphere and its pressure–volume curve),
``cook``, ``default`` (a neo-Hookean beam released under gravity), ``drop``,
``fibre_block``, ``fit_cantilever``, ``fit_plate_hole`` (Mooney–Rivlin constants from a
force curve and DIC points), ``fold``, ``press``, ``swing2d``, ``twist``, ``ventricle`` (an
idealised left ventricle inflated to 10 kPa: Land et al. 2015, problem 2),
``ventricle_active`` (the same ventricle contracting: an active fibre tension of 60 kPa
against 15 kPa, helix fibres at the quadrature points; problem 3).
"""

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the names as the type checker and the API docs see them
    from .docs import reference_markdown as reference_markdown
    from .errors import SceneError as SceneError
    from .fit import run_fit as run_fit
    from .load import Scene as Scene
    from .load import apply_overrides as apply_overrides
    from .load import load_scene as load_scene
    from .load import shipped_scenes as shipped_scenes
    from .problem import Built as Built
    from .problem import build as build
    from .run import run_scene as run_scene
    from .schema import SceneSpec as SceneSpec
    from .schema import json_schema as json_schema
    from .where import where_mask as where_mask

__all__ = [
    "SceneError",
    "Scene",
    "SceneSpec",
    "Built",
    "load_scene",
    "apply_overrides",
    "shipped_scenes",
    "build",
    "run_scene",
    "run_fit",
    "where_mask",
    "json_schema",
    "reference_markdown",
]

_LAZY = {
    # name: (module, attribute)
    "reference_markdown": (".docs", "reference_markdown"),
    "SceneError": (".errors", "SceneError"),
    "run_fit": (".fit", "run_fit"),
    "Scene": (".load", "Scene"),
    "apply_overrides": (".load", "apply_overrides"),
    "load_scene": (".load", "load_scene"),
    "shipped_scenes": (".load", "shipped_scenes"),
    "Built": (".problem", "Built"),
    "build": (".problem", "build"),
    "run_scene": (".run", "run_scene"),
    "SceneSpec": (".schema", "SceneSpec"),
    "json_schema": (".schema", "json_schema"),
    "where_mask": (".where", "where_mask"),
}


def __getattr__(name: str):
    """The package's names, each imported when first used (PEP 562): a static scene run
    imports neither the fitting modules nor the reference generator, and
    ``jaxelastic.scene.interrupt`` (the command's signal handling) loads on its own."""
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    where, attribute = _LAZY[name]
    value = getattr(importlib.import_module(where, __name__), attribute)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
