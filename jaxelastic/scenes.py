"""Scenes: a simulation described in a TOML file, validated, built and run.

A scene names a mesh, a material, boundary conditions, loads, solver settings, an
integrator and outputs. :func:`load_scene` validates it (unknown keys, wrong types and
impossible values are refused with a :class:`SceneError` naming the key), :func:`build`
turns it into arrays and a :class:`~jaxelastic.potential.Potential`, and
:func:`run_scene` solves it and writes the outputs (``jaxelastic run SCENE --out DIR``).
Shipped scenes: ``default`` (a neo-Hookean beam released under gravity), ``twist``,
``cook`` and ``swing2d`` (:func:`shipped_scenes`).

Scene file reference
--------------------

```toml
name = "beam"                 # optional label; description = "..." likewise

[mesh]                        # a generator ...
generator = "box"             # "box" (3D tets) | "rectangle" (2D) | "cook" (Cook's membrane)
n = [20, 3, 3]                # cells per axis ("cook": n = 16, a single integer)
size = [2.0, 0.25, 0.25]      # [m], default all 1 (not for "cook")
origin = [0.0, 0.0, 0.0]      # default 0 (not for "cook")
# file = "part.msh"           # ... or any meshio-readable file, relative to the scene file
order = 1                     # 1 (P1, default) | 2 (P2: tri6/tet10); a file keeps its own
                              #   order unless given (order = 2 lifts a P1 file)
formulation = "standard"      # | "fbar" (finite strain) | "bbar" (small strain, for "linear"):
                              #   locking-free for nu -> 0.5; with order = 1 this is the
                              #   composite element (tri3x4/tet4x8 on the P2 node set)

[material]
model = "neo_hookean"         # a built-in name, or "module:function" for your psi(F, params)
E = 1e7                       # Young's modulus [Pa] and Poisson's ratio, or mu = ..., lam = ...
nu = 0.3
# plane = "strain"            # 2D only: "strain" (default) or "stress"
density = 1000.0              # [kg/m^3]; required for dynamics and gravity

[[dirichlet]]                 # any number of these; later entries override earlier ones
nodes = { plane = { axis = "x", value = 0.0 } }   # or { box = { lo = [..], hi = [..] } },
                              # { group = "name" } (mesh file groups), { where = "x < 1e-9" }
components = [0, 1, 2]        # default: all
displacement = [0, 0, 0]      # default 0; or { rotate = { axis = "x", angle_deg = 60,
                              #   center = [0, 0.5, 0.5], scale = 0.5 } }; or "module:function"
                              #   u(X) -> (m, dim), in dynamics also u(X, t)
# ramp_time = 0.5             # dynamics: the displacement grows linearly until this time

[[traction]]                  # dead load per reference area on boundary facets
facets = { plane = { axis = "x", value = 2.0 } }  # same selectors as nodes
traction = [0, 0, -100.0]     # [Pa], or total_force = [..] [N] spread over the facets' area

[[point_load]]
nodes = { box = { lo = [2, 0, 0], hi = [2, 0.25, 0.25] } }
force = [0, 0, -1.0]          # [N] on each node, or total_force = [..] shared equally

[gravity]
g = [0, 0, -9.81]             # [m/s^2]

[solver]                      # any field of jaxelastic.NewtonSettings, plus:
linear = "auto"               # "auto" (sparse Cholesky <= 10k dofs, else AMG-CG), "direct",
                              # "amg", or "cg" (matrix-free PCG inside jit)
rtol = 1e-8

[integrator]
type = "dynamic"              # "static" (default; load_steps = k applies loads in k steps)
h = 0.02                      # time step [s]
duration = 10.0               # [s] (the maximum when settle = true)
method = "backward_euler"     # or "bdf2"
alpha = 2.0                   # mass-proportional Rayleigh damping [1/s]; beta: stiffness [s]
settle = true                 # stop once kinetic < settle_tol * elastic energy
settle_tol = 1e-8             # ... for settle_steps consecutive steps (default 5)
initial_velocity = [0, 0, 0]  # [m/s], or "module:function" v(X) -> (m, dim)
compare_static = true         # also solve the static problem and report the difference

[output]
every = 5                     # write a VTU every k time steps (and the first and last)
vtu = true                    # ParaView time series (.vtu files + .pvd)
png = true                    # pictures: final shape, tip displacement, energies
probes = [[2.0, 0.125, 0.125]]  # report the displacement at the node nearest each point
```

Vectors have one entry per mesh dimension. ``axis`` is ``0/1/2`` or ``"x"/"y"/"z"``.
``where`` is a boolean expression of the rest positions (``X`` ``(n, dim)``, or ``x``,
``y``, ``z``) evaluated by a small interpreter, **not** ``eval``: it allows numbers,
arithmetic, comparisons, ``&``/``|``/``~``/``and``/``or``/``not``, indexing ``X[:, 0]``,
``pi`` and the NumPy functions ``abs sqrt hypot minimum maximum sin cos arctan2 isclose
logical_and logical_or logical_not`` (also as ``np.abs`` …). A ``"module:function"`` is
imported with the scene file's directory first on ``sys.path``; user materials receive
``params = Lame(mu, lam)``. A static scene needs a Dirichlet condition; all elastic
parameters are validated with ``jaxelastic.materials.lame``.

Running a scene and reading its outputs
---------------------------------------

```
jaxelastic run [SCENE] --out DIR [--set integrator.duration=1.0 ...] [--no-progress]
python -m jaxelastic run twist --out results/twist      # a shipped scene by name
jaxelastic scenes                                        # list the shipped scenes
```

In Python: ``summary = jaxelastic.scenes.run_scene("my.toml", "out")`` (enable float64
first); ``load_scene`` and ``build`` give the validated scene and its arrays. ``DIR``
receives, each file written atomically:

* ``dynamic.pvd`` + ``dynamic_NNNN.vtu`` (every ``[output].every`` steps) and/or
  ``static.pvd`` + ``static_0000.vtu``: open the ``.pvd`` in ParaView and apply *Warp By
  Vector* with ``displacement``; cell data ``J``, ``green_strain``, ``stress_P``,
  ``von_mises``, ``energy_density``; point data ``velocity`` in dynamics;
* ``final_shape.png`` (rest, final and static shapes), and in dynamics
  ``tip_displacement.png`` (first probe, or the node farthest from the supports) and
  ``energy.png``;
* ``summary.json``: ``scene`` (with defaults), ``mesh``, ``material``, ``solver``,
  ``timings`` (build, first step including compilation, median step, static solve,
  outputs, total), ``dynamic.per_step`` (time, Newton and CG iterations, residual,
  kinetic/elastic/load-potential/total energy), ``static`` (iterations, residual
  history, reaction force vs applied load), ``probes``, ``comparison`` (static vs
  dynamic: max nodal distance, relative to the tip deflection).
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import importlib
import inspect
import math
import os
import re
import sys
import types
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, NamedTuple

from ._where import WhereError, check_where, where_mask

if TYPE_CHECKING:  # annotations only: importing this module does not import JAX
    import jax

    from .dynamics import Integrator
    from .io import MeshData
    from .loads import Dirichlet
    from .materials import Lame
    from .mesh import Mesh
    from .potential import Potential
    from .solvers.newton import NewtonSettings

try:
    import tomllib
except ModuleNotFoundError:  # Python < 3.11
    import tomli as tomllib

__all__ = [
    "SCENE_DOCS",
    "SceneError",
    "Scene",
    "Built",
    "load_scene",
    "apply_overrides",
    "shipped_scenes",
    "build",
    "run_scene",
    "where_mask",
]

SCENE_DOCS: str = re.sub(
    r"^(\S.*)\n-{3,}$",
    r"### \1",
    "Scene file reference\n" + (__doc__ or "").partition("\n\nScene file reference\n")[2],
    flags=re.MULTILINE,
)
"""The scene-file reference and how to run a scene (Markdown), for the README."""

_SCENE_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "scenes")
_GENERATOR_DIM = {"box": 3, "rectangle": 2, "cook": 2}
_AXES = {"x": 0, "y": 1, "z": 2}
_TOP = (
    "name",
    "description",
    "mesh",
    "material",
    "dirichlet",
    "traction",
    "point_load",
    "gravity",
    "solver",
    "integrator",
    "output",
    "fit",
)
_STATIC_KEYS = ("type", "load_steps")
_DYNAMIC_KEYS = (
    "type",
    "h",
    "duration",
    "method",
    "alpha",
    "beta",
    "settle",
    "settle_tol",
    "settle_steps",
    "initial_velocity",
    "compare_static",
)
_SOLVER_CHOICES = {
    "linear": ("auto", "cg", "direct", "amg"),
    "hessian": ("hvp", "element", "projected"),
    "preconditioner": ("block_jacobi", "jacobi", "none"),
}


class SceneError(ValueError):
    """An invalid scene; the message names the scene and the offending key."""


# ----------------------------------------------------------------------------------------
# the Scene object
# ----------------------------------------------------------------------------------------


def _freeze(obj):
    if isinstance(obj, Mapping):
        return types.MappingProxyType({k: _freeze(v) for k, v in obj.items()})
    if isinstance(obj, (list, tuple)):
        return tuple(_freeze(v) for v in obj)
    return obj


def _thaw(obj):
    if isinstance(obj, Mapping):
        return {k: _thaw(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_thaw(v) for v in obj]
    return obj


@dataclasses.dataclass(frozen=True)
class Scene:
    """A validated scene (read-only).

    Attributes:
        data: the scene as nested read-only mappings and tuples, with defaults filled in
            (a valid scene itself: ``load_scene(scene.to_dict())`` round-trips).
        label: how messages name the scene (the file name, or ``"<dict>"``).
        source: absolute path of the scene file, or None.
        base_dir: directory that relative paths and ``module:function`` imports resolve
            against.
        dim: spatial dimension when known before reading a mesh file, else None.
    """

    data: Mapping
    label: str
    source: str | None
    base_dir: str
    dim: int | None
    _dim_checks: tuple = dataclasses.field(default=(), repr=False, compare=False)

    def __getitem__(self, key):
        return self.data[key]

    def get(self, key, default=None):
        return self.data.get(key, default)

    @property
    def name(self) -> str:
        return self.data["name"]

    @property
    def static(self) -> bool:
        return self.data["integrator"]["type"] == "static"

    def to_dict(self) -> dict:
        """A plain, JSON-serialisable deep copy of :attr:`data`."""
        return _thaw(self.data)


# ----------------------------------------------------------------------------------------
# validation helpers
# ----------------------------------------------------------------------------------------


def _tname(x) -> str:
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


class _V:
    """Validation context: builds messages ``scene 'x.toml': <key> <problem>``."""

    def __init__(self, label: str):
        self.label = label

    def err(self, msg: str) -> SceneError:
        return SceneError(f"scene {self.label!r}: {msg}")

    def table(self, key, x, valid, required=()) -> dict:
        if not isinstance(x, Mapping):
            raise self.err(f"{key} must be a table, got {_tname(x)} {x!r}")
        for k in x:
            if k not in valid:
                where = f"{key}.{k}" if key else repr(k)
                kind = "unknown key" if key else "unknown top-level key"
                raise self.err(f"{kind} {where} (valid: {', '.join(valid)})")
        for k in required:
            if k not in x:
                raise self.err(f"{key}.{k} is required")
        return dict(x)

    def number(self, key, x, *, gt=None, ge=None, lt=None, le=None) -> float:
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            raise self.err(f"{key} must be a number, got {_tname(x)} {x!r}")
        if not math.isfinite(x):
            raise self.err(f"{key} must be finite, got {x!r}")
        for bound, ok, op in (
            (gt, lambda b: x > b, ">"),
            (ge, lambda b: x >= b, ">="),
            (lt, lambda b: x < b, "<"),
            (le, lambda b: x <= b, "<="),
        ):
            if bound is not None and not ok(bound):
                raise self.err(f"{key} must be {op} {bound:g}, got {x!r}")
        return x

    def integer(self, key, x, *, ge=None) -> int:
        if isinstance(x, bool) or not isinstance(x, int):
            raise self.err(f"{key} must be an integer, got {_tname(x)} {x!r}")
        if ge is not None and x < ge:
            raise self.err(f"{key} must be >= {ge}, got {x!r}")
        return x

    def boolean(self, key, x) -> bool:
        if not isinstance(x, bool):
            raise self.err(f"{key} must be true or false, got {_tname(x)} {x!r}")
        return x

    def string(self, key, x, choices=None) -> str:
        if not isinstance(x, str):
            raise self.err(f"{key} must be a string, got {_tname(x)} {x!r}")
        if choices is not None and x not in choices:
            raise self.err(f"{key} must be one of {', '.join(map(repr, choices))}, got {x!r}")
        return x

    def vector(self, key, x, checks: list, *, kind: str = "vec") -> list:
        if not isinstance(x, (list, tuple)) or not x:
            raise self.err(f"{key} must be a non-empty array of numbers, got {_tname(x)} {x!r}")
        out = [self.number(f"{key}[{i}]", v) for i, v in enumerate(x)]
        checks.append((kind, key, len(out)))
        return out

    def axis(self, key, x, checks: list) -> int | str:
        if isinstance(x, str):
            if x not in _AXES:
                raise self.err(f"{key} must be 0, 1, 2 or 'x', 'y', 'z', got {x!r}")
            checks.append(("axis", key, _AXES[x]))
            return x
        a = self.integer(key, x, ge=0)
        checks.append(("axis", key, a))
        return a


def _axis_index(a) -> int:
    return _AXES[a] if isinstance(a, str) else int(a)


@contextlib.contextmanager
def _on_path(directory: str):
    sys.path.insert(0, directory)
    try:
        yield
    finally:
        with contextlib.suppress(ValueError):
            sys.path.remove(directory)


def _import_callable(v: _V, key: str, spec: str, base_dir: str) -> Callable:
    """Resolve ``"module:function"`` (dotted attribute paths allowed after the colon)."""
    mod_name, _, attr = spec.partition(":")
    if not mod_name or not attr:
        raise v.err(f"{key}: {spec!r} is not of the form 'module:function'")
    try:
        with _on_path(base_dir):
            obj = importlib.import_module(mod_name)
    except Exception as e:  # noqa: BLE001 — any import failure is reported with the key
        raise v.err(f"{key}: cannot import module {mod_name!r} ({type(e).__name__}: {e})") from None
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise v.err(f"{key}: module {mod_name!r} has no attribute {attr!r}")
        obj = getattr(obj, part)
    if not callable(obj):
        raise v.err(f"{key}: {spec!r} is not callable")
    return obj


def _n_positional(fn) -> int:
    """Number of positional parameters ``fn`` accepts (a large number for ``*args``)."""
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


# ----------------------------------------------------------------------------------------
# sections
# ----------------------------------------------------------------------------------------


def _check_mesh(v: _V, x, base_dir: str, checks: list):
    key = "[mesh]"
    t = v.table(key, x, ("generator", "n", "size", "origin", "file", "order", "formulation"))
    if ("generator" in t) == ("file" in t):
        raise v.err(f"{key} needs exactly one of generator = ... or file = ...")
    fe = _check_mesh_element(v, key, t)
    if "file" in t:
        for k in ("n", "size", "origin"):
            if k in t:
                raise v.err(f"{key}.{k} is only valid with a generator (a file has its geometry)")
        path = os.path.join(base_dir, os.path.expanduser(v.string(f"{key}.file", t["file"])))
        path = os.path.normpath(path)
        if not os.path.isfile(path):
            raise v.err(f"{key}.file: no such mesh file {path!r}")
        return {"file": path, **fe}, None
    gen = v.string(f"{key}.generator", t["generator"], tuple(_GENERATOR_DIM))
    dim = _GENERATOR_DIM[gen]
    if gen == "cook":
        for k in ("size", "origin"):
            if k in t:
                raise v.err(f"{key}.{k} is not valid for generator 'cook' (fixed geometry)")
        n = t.get("n", 16)
        if isinstance(n, list) and len(n) == 1:
            n = n[0]
        return {"generator": gen, "n": v.integer(f"{key}.n", n, ge=1), **fe}, dim
    if "n" not in t:
        raise v.err(f"{key}.n is required for generator {gen!r}")
    n = t["n"]
    if not isinstance(n, list) or len(n) != dim:
        raise v.err(f"{key}.n must be an array of {dim} integers for {gen!r}, got {n!r}")
    out = {"generator": gen, "n": [v.integer(f"{key}.n[{i}]", a, ge=1) for i, a in enumerate(n)]}
    size = t.get("size", [1.0] * dim)
    out["size"] = v.vector(f"{key}.size", size, checks)
    for i, s in enumerate(out["size"]):
        v.number(f"{key}.size[{i}]", s, gt=0)
    out["origin"] = v.vector(f"{key}.origin", t.get("origin", [0.0] * dim), checks)
    return {**out, **fe}, dim


def _check_mesh_element(v: _V, key: str, t: dict) -> dict:
    """``order`` (1 | 2) and ``formulation`` ("standard" | "fbar" | "bbar") of [mesh]."""
    from .mesh import FORMULATIONS

    out = {
        "formulation": v.string(
            f"{key}.formulation", t.get("formulation", "standard"), FORMULATIONS
        )
    }
    if "order" in t:
        order = v.integer(f"{key}.order", t["order"], ge=1)
        if order not in (1, 2):
            raise v.err(f"{key}.order must be 1 or 2, got {order}")
        out["order"] = order
    elif "generator" in t:
        out["order"] = 1  # a file keeps its own order unless order = ... is given
    return out


def _check_material(v: _V, x, base_dir: str):
    key = "[material]"
    t = v.table(key, x, ("model", "E", "nu", "mu", "lam", "plane", "density"), ("model",))
    model = v.string(f"{key}.model", t["model"])
    from .materials import BUILTIN

    if ":" in model:
        _import_callable(v, f"{key}.model", model, base_dir)
    elif model not in BUILTIN:
        raise v.err(
            f"{key}.model: unknown material {model!r} (built-in: {', '.join(BUILTIN)}; or "
            "'module:function' for your own psi(F, params))"
        )
    out = {"model": model}
    has_E, has_mu = ("E" in t or "nu" in t), ("mu" in t or "lam" in t)
    if has_E == has_mu:
        raise v.err(f"{key} needs either E and nu, or mu and lam (exactly one pair)")
    if has_E:
        for k in ("E", "nu"):
            if k not in t:
                raise v.err(f"{key}.{k} is required (give E and nu together)")
        out["E"] = v.number(f"{key}.E", t["E"], gt=0)
        out["nu"] = v.number(f"{key}.nu", t["nu"], gt=-1, lt=0.5)
    else:
        for k in ("mu", "lam"):
            if k not in t:
                raise v.err(f"{key}.{k} is required (give mu and lam together)")
        out["mu"] = v.number(f"{key}.mu", t["mu"], gt=0)
        out["lam"] = v.number(f"{key}.lam", t["lam"])
        if not out["lam"] > -out["mu"]:
            raise v.err(f"{key}.lam must be > -mu (a positive bulk modulus), got {t['lam']!r}")
    if "plane" in t:
        out["plane"] = v.string(f"{key}.plane", t["plane"], ("strain", "stress"))
        if has_mu:
            raise v.err(f"{key}.plane needs E and nu (mu and lam are used as given)")
    if "density" in t:
        out["density"] = v.number(f"{key}.density", t["density"], gt=0)
    return out


def _parse_where(v: _V, key: str, expr: str) -> None:
    try:
        check_where(expr)
    except WhereError as e:
        raise v.err(f"{key}: {e} in {expr!r}") from None


def _check_selector(v: _V, key: str, x, checks: list):
    t = v.table(key, x, ("plane", "box", "group", "where"))
    if len(t) != 1:
        raise v.err(f"{key} needs exactly one of plane, box, group, where; got {sorted(t)}")
    ((kind, val),) = t.items()
    k = f"{key}.{kind}"
    if kind == "plane":
        p = v.table(k, val, ("axis", "value", "tol"), ("axis", "value"))
        out = {"axis": v.axis(f"{k}.axis", p["axis"], checks)}
        out["value"] = v.number(f"{k}.value", p["value"])
        if "tol" in p:
            out["tol"] = v.number(f"{k}.tol", p["tol"], gt=0)
        return {"plane": out}
    if kind == "box":
        b = v.table(k, val, ("lo", "hi"), ("lo", "hi"))
        lo, hi = v.vector(f"{k}.lo", b["lo"], checks), v.vector(f"{k}.hi", b["hi"], checks)
        if len(lo) != len(hi) or any(a > c for a, c in zip(lo, hi, strict=True)):
            raise v.err(f"{k}: lo must not exceed hi componentwise, got lo={lo}, hi={hi}")
        return {"box": {"lo": lo, "hi": hi}}
    if kind == "group":
        return {"group": v.string(k, val)}
    _parse_where(v, k, v.string(k, val))
    return {"where": val}


def _check_displacement(v: _V, key: str, x, base_dir: str, checks: list):
    if isinstance(x, str):
        _import_callable(v, key, x, base_dir)
        return x
    if isinstance(x, Mapping):
        t = v.table(key, x, ("rotate",), ("rotate",))
        k = f"{key}.rotate"
        r = v.table(k, t["rotate"], ("axis", "angle_deg", "center", "scale"), ("angle_deg",))
        out = {"axis": v.axis(f"{k}.axis", r.get("axis", "z"), [])}  # checked as "rotate"
        out["angle_deg"] = v.number(f"{k}.angle_deg", r["angle_deg"])
        if "center" in r:
            out["center"] = v.vector(f"{k}.center", r["center"], checks)
        out["scale"] = v.number(f"{k}.scale", r.get("scale", 1.0))
        checks.append(("rotate", k, _axis_index(out["axis"])))
        return {"rotate": out}
    return v.vector(key, x, checks)


def _check_dirichlet(v: _V, x, base_dir: str, checks: list):
    if isinstance(x, Mapping):
        raise v.err("[dirichlet] must be an array of tables: write [[dirichlet]]")
    if not isinstance(x, list):
        raise v.err(f"[dirichlet] must be an array of tables, got {_tname(x)}")
    out = []
    for i, entry in enumerate(x):
        key = f"[dirichlet][{i}]"
        t = v.table(key, entry, ("nodes", "components", "displacement", "ramp_time"), ("nodes",))
        d = {"nodes": _check_selector(v, f"{key}.nodes", t["nodes"], checks)}
        if "components" in t:
            c = t["components"]
            if not isinstance(c, list) or not c:
                raise v.err(f"{key}.components must be a non-empty array, got {c!r}")
            comps = [v.axis(f"{key}.components[{j}]", a, checks) for j, a in enumerate(c)]
            if len({_axis_index(a) for a in comps}) != len(comps):
                raise v.err(f"{key}.components repeats a component: {c!r}")
            d["components"] = comps
        if "displacement" in t:
            d["displacement"] = _check_displacement(
                v, f"{key}.displacement", t["displacement"], base_dir, checks
            )
        if "ramp_time" in t:
            d["ramp_time"] = v.number(f"{key}.ramp_time", t["ramp_time"], gt=0)
        out.append(d)
    return out


def _check_loads(v: _V, section: str, x, checks: list):
    if isinstance(x, Mapping):
        raise v.err(f"[{section}] must be an array of tables: write [[{section}]]")
    if not isinstance(x, list):
        raise v.err(f"[{section}] must be an array of tables, got {_tname(x)}")
    where, value = ("facets", "traction") if section == "traction" else ("nodes", "force")
    out = []
    for i, entry in enumerate(x):
        key = f"[{section}][{i}]"
        t = v.table(key, entry, (where, value, "total_force"), (where,))
        if (value in t) == ("total_force" in t):
            raise v.err(f"{key} needs exactly one of {value} = [..] or total_force = [..]")
        d = {where: _check_selector(v, f"{key}.{where}", t[where], checks)}
        k = value if value in t else "total_force"
        d[k] = v.vector(f"{key}.{k}", t[k], checks)
        out.append(d)
    return out


def _check_solver(v: _V, x):
    from .solvers.newton import NewtonSettings

    key = "[solver]"
    fields = NewtonSettings._fields + ("linear",)
    t = v.table(key, x, fields)
    defaults = dict(NewtonSettings._field_defaults, linear="auto")
    out = {}
    for k, val in t.items():
        d, kk = defaults.get(k), f"{key}.{k}"
        if isinstance(d, bool):
            out[k] = v.boolean(kk, val)
        elif isinstance(d, int):
            out[k] = v.integer(kk, val, ge=0 if k == "atol" else 1)
        elif isinstance(d, float):
            out[k] = v.number(kk, val, ge=0)
        elif isinstance(d, str):
            out[k] = v.string(kk, val, _SOLVER_CHOICES.get(k))
        else:
            out[k] = val
    if out.get("armijo") is not None and not out["armijo"] < 1:
        raise v.err(f"{key}.armijo must be < 1, got {out['armijo']!r}")
    return out


def _check_integrator(v: _V, x, base_dir: str, checks: list):
    key = "[integrator]"
    if not isinstance(x, Mapping):
        raise v.err(f"{key} must be a table, got {_tname(x)}")
    kind = v.string(f"{key}.type", x.get("type", "static"), ("static", "dynamic"))
    if kind == "static":
        for k in x:
            if k not in _STATIC_KEYS:
                raise v.err(
                    f"unknown key {key}.{k} for type = 'static' (valid: {', '.join(_STATIC_KEYS)})"
                )
        return {
            "type": "static",
            "load_steps": v.integer(f"{key}.load_steps", x.get("load_steps", 1), ge=1),
        }
    t = v.table(key, x, _DYNAMIC_KEYS, ("h", "duration"))
    out = {"type": "dynamic"}
    out["h"] = v.number(f"{key}.h", t["h"], gt=0)
    out["duration"] = v.number(f"{key}.duration", t["duration"], gt=0)
    if out["duration"] < out["h"] * (1 - 1e-12):
        raise v.err(f"{key}.duration must be >= h = {out['h']!r}, got {out['duration']!r}")
    out["method"] = v.string(
        f"{key}.method", t.get("method", "backward_euler"), ("backward_euler", "bdf2")
    )
    out["alpha"] = v.number(f"{key}.alpha", t.get("alpha", 0.0), ge=0)
    out["beta"] = v.number(f"{key}.beta", t.get("beta", 0.0), ge=0)
    out["settle"] = v.boolean(f"{key}.settle", t.get("settle", False))
    out["settle_tol"] = v.number(f"{key}.settle_tol", t.get("settle_tol", 1e-8), gt=0)
    out["settle_steps"] = v.integer(f"{key}.settle_steps", t.get("settle_steps", 5), ge=1)
    out["compare_static"] = v.boolean(f"{key}.compare_static", t.get("compare_static", False))
    if "initial_velocity" in t:
        iv = t["initial_velocity"]
        if isinstance(iv, str):
            _import_callable(v, f"{key}.initial_velocity", iv, base_dir)
            out["initial_velocity"] = iv
        else:
            out["initial_velocity"] = v.vector(f"{key}.initial_velocity", iv, checks)
    return out


def _check_output(v: _V, x, checks: list):
    key = "[output]"
    t = v.table(key, x, ("every", "vtu", "png", "probes"))
    out = {
        "every": v.integer(f"{key}.every", t.get("every", 1), ge=1),
        "vtu": v.boolean(f"{key}.vtu", t.get("vtu", True)),
        "png": v.boolean(f"{key}.png", t.get("png", True)),
    }
    probes = t.get("probes", [])
    if not isinstance(probes, list):
        raise v.err(f"{key}.probes must be an array of points, got {_tname(probes)}")
    out["probes"] = [v.vector(f"{key}.probes[{i}]", p, checks) for i, p in enumerate(probes)]
    return out


def _check_dims(v: _V, checks, dim: int) -> None:
    """Check vector lengths and axis indices against the mesh dimension."""
    for kind, key, n in checks:
        if kind == "vec" and n != dim:
            raise v.err(f"{key} must have {dim} components (the mesh is {dim}D), got {n}")
        if kind == "axis" and n >= dim:
            raise v.err(f"{key} must be an axis of a {dim}D mesh (0..{dim - 1}), got {n}")
        if kind == "rotate" and dim == 2 and n != 2:
            raise v.err(f"{key}.axis must be 'z' (2) in 2D, got {n}")
        if kind == "rotate" and n > 2:
            raise v.err(f"{key}.axis must be 0, 1, 2 or 'x', 'y', 'z', got {n}")


def _validate(v: _V, raw, base_dir: str):
    t = v.table("", raw, _TOP, ())
    for k in ("mesh", "material"):
        if k not in t:
            raise v.err(f"[{k}] is required")
    checks: list = []
    data = {
        "name": v.string("name", t.get("name", "scene")),
        "description": v.string("description", t.get("description", "")),
    }
    data["mesh"], dim = _check_mesh(v, t["mesh"], base_dir, checks)
    data["material"] = _check_material(v, t["material"], base_dir)
    data["dirichlet"] = _check_dirichlet(v, t.get("dirichlet", []), base_dir, checks)
    data["traction"] = _check_loads(v, "traction", t.get("traction", []), checks)
    data["point_load"] = _check_loads(v, "point_load", t.get("point_load", []), checks)
    if "gravity" in t:
        g = v.table("[gravity]", t["gravity"], ("g",), ("g",))
        data["gravity"] = {"g": v.vector("[gravity].g", g["g"], checks)}
    data["solver"] = _check_solver(v, t.get("solver", {}))
    data["integrator"] = _check_integrator(v, t.get("integrator", {}), base_dir, checks)
    data["output"] = _check_output(v, t.get("output", {}), checks)
    if "fit" in t:  # material identification: validated and run by jaxelastic._scene_fit
        from ._scene_fit import check_fit

        data["fit"] = check_fit(v, t["fit"], data)

    mat, integ = data["material"], data["integrator"]
    dynamic = integ["type"] == "dynamic"
    if "density" not in mat:
        if dynamic:
            raise v.err("[material].density is required for a dynamic scene")
        if "gravity" in data:
            raise v.err("[material].density is required with [gravity]")
    if not dynamic:
        if not data["dirichlet"]:
            raise v.err(
                "[dirichlet]: a static scene needs at least one Dirichlet condition "
                "(else rigid motions are free)"
            )
        for i, d in enumerate(data["dirichlet"]):
            if "ramp_time" in d:
                raise v.err(f"[dirichlet][{i}].ramp_time is only valid in a dynamic scene")
            u = d.get("displacement")
            if isinstance(u, str):
                fn = _import_callable(v, f"[dirichlet][{i}].displacement", u, base_dir)
                if _n_positional(fn) < 1:
                    raise v.err(f"[dirichlet][{i}].displacement: {u!r} must accept u(X)")
    if dim is not None:
        if dim == 3 and "plane" in mat:
            raise v.err("[material].plane applies to 2D meshes only")
        _check_dims(v, checks, dim)
    return data, dim, tuple(checks)


# ----------------------------------------------------------------------------------------
# loading
# ----------------------------------------------------------------------------------------


def shipped_scenes() -> dict[str, str]:
    """Name → path of the scene files shipped with jaxelastic (``default``, ``twist``, …)."""
    if not os.path.isdir(_SCENE_DIR):
        return {}
    names = sorted(f for f in os.listdir(_SCENE_DIR) if f.endswith(".toml"))
    return {f[: -len(".toml")]: os.path.join(_SCENE_DIR, f) for f in names}


def apply_overrides(data: Mapping, overrides: Mapping[str, Any]) -> dict:
    """A deep copy of a raw scene dict with dotted-path overrides applied.

    ``{"mesh.n": [6, 2, 2], "integrator.duration": 0.5, "dirichlet.0.displacement": [..]}``;
    an integer path component indexes an array of tables. Missing tables are created.
    """
    out = copy.deepcopy(_thaw(data))
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
            names the scene and the key).
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
        path = os.fspath(source)
        shipped = shipped_scenes()
        if not os.path.exists(path) and path.removesuffix(".toml") in shipped:
            path = shipped[path.removesuffix(".toml")]
        path = os.path.abspath(path)
        label = os.path.basename(path)
        if not os.path.isfile(path):
            raise SceneError(
                f"scene {os.fspath(source)!r}: no such file (shipped scenes: "
                f"{', '.join(shipped) or 'none'})"
            )
        try:
            with open(path, "rb") as f:
                raw = tomllib.load(f)
        except tomllib.TOMLDecodeError as e:
            raise SceneError(f"scene {label!r}: invalid TOML: {e}") from None
        except UnicodeDecodeError as e:
            raise SceneError(f"scene {label!r}: not a UTF-8 text file ({e})") from None
        bdir = os.path.abspath(base_dir or os.path.dirname(path))
    else:
        raise TypeError(f"load_scene() takes a path, a dict or a Scene, got {type(source)}")
    if overrides:
        raw = apply_overrides(raw, overrides)
    v = _V(label)
    data, dim, checks = _validate(v, raw, bdir)
    return Scene(_freeze(data), label, path, bdir, dim, checks)


# ----------------------------------------------------------------------------------------
# build and run (implemented in jaxelastic._scene_run, imported on first use)
# ----------------------------------------------------------------------------------------


class Built(NamedTuple):
    """A scene turned into arrays and functions (everything :func:`run_scene` needs).

    Attributes:
        scene: the :class:`~jaxelastic.scenes.Scene`.
        mesh: the rest mesh; mesh_data: the :class:`~jaxelastic.io.MeshData` of a mesh
            file (named sets), or None for a generator.
        psi: the strain-energy density; params: ``Lame(mu, lam)``.
        potential: base :class:`~jaxelastic.potential.Potential` (``mass`` only in
            dynamics, ``f_ext`` only with loads or gravity).
        bc: Dirichlet data with the full prescribed displacement (statics) or at t = 0.
        bc_fn: ``s ↦ Dirichlet``: in statics ``s`` is the load factor in [0, 1], in
            dynamics the time [s].
        time_dependent: whether ``bc_fn`` changes with time (dynamics).
        settings: :class:`~jaxelastic.solvers.newton.NewtonSettings`.
        linear: the linear solver (None = matrix-free CG, or a
            :class:`~jaxelastic.solvers.host.HostLinearSolver`), from ``[solver].linear``.
        integrator: :class:`~jaxelastic.dynamics.Integrator`, or None (statics).
        x0: ``(n_nodes, dim)`` initial positions (the rest shape); v0: initial velocities
            ``(n_nodes, dim)`` (zero on Dirichlet dofs), or None (statics).
        probes: ``(node, point)`` per ``[output].probes`` entry (nearest node).
        tip: node whose displacement is plotted over time (first probe, or the node
            farthest from the Dirichlet nodes).
    """

    scene: Scene
    mesh: Mesh
    mesh_data: MeshData | None
    psi: Callable
    params: Lame
    potential: Potential
    bc: Dirichlet
    bc_fn: Callable[[float], Dirichlet]
    time_dependent: bool
    settings: NewtonSettings
    linear: Any
    integrator: Integrator | None
    x0: jax.Array
    v0: jax.Array | None
    probes: list
    tip: int


def build(scene) -> Built:
    """Turn a scene (a :class:`Scene`, a path, a shipped name or a dict) into arrays.

    The :class:`~jaxelastic.potential.Potential` holds only what the scene needs: no mass
    in statics, no ``f_ext`` without loads or gravity.

    Raises:
        SceneError: problems only visible with the mesh (a selection that matches no
            node, an unknown group, wrong vector lengths for a mesh file's dimension, a
            user function returning the wrong shape, a material failing at F = I).
    """
    from ._scene_run import build as _build

    return _build(scene)


def run_scene(scene, out_dir, progress: bool = True) -> dict:
    """Solve a scene and write its outputs into ``out_dir``; returns the summary dict.

    Static scenes: Newton (``load_steps`` increments). Dynamic scenes: one jitted time
    step per iteration of a host loop with a progress bar, stopping early once settled;
    with ``compare_static`` also the static solution of the same load.

    Writes (each file atomically): ``summary.json`` (the scene, timings, Newton and CG
    iterations and energies per step, final residual, probes, static/dynamic difference);
    with ``[output].vtu`` a ParaView series ``dynamic.pvd`` + ``dynamic_NNNN.vtu`` and/or
    ``static.pvd`` + ``static_0000.vtu`` (displacement, velocity, J, Green strain, P,
    von Mises stress, energy density); with ``[output].png`` ``final_shape.png`` and, for
    dynamics, ``tip_displacement.png`` and ``energy.png``. ``out_dir`` is created; a
    path that is a file is refused, and so is an input file (scene, mesh) that an output
    would overwrite.

    Raises:
        SceneError: invalid scene or output directory.
        SolveError: a Newton solve failed (``summary.json`` is still written, with
            ``"status": "failed"`` and the error).
    """
    from ._scene_run import run_scene as _run

    return _run(scene, out_dir, progress=progress)
