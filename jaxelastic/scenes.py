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

import copy
import dataclasses
import os
import re
import types
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, NamedTuple

# validation lives in _scene_check; the private names are re-exported for _scene_run/_scene_fit
from ._scene_check import (  # noqa: F401
    _V,
    SceneError,
    _axis_index,
    _check_dims,
    _import_callable,
    _n_positional,
    _parse_where,
    _validate,
)
from ._where import where_mask

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
