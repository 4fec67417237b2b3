"""jaxelastic: differentiable finite-element elasticity in JAX.

Write a strain-energy density ``psi(F, params) -> scalar``; get the first Piola–Kirchhoff
stress, nodal forces, Hessian-vector products, element Hessians and implicit solvers by
autodiff, on linear and quadratic triangles (2D) and tetrahedra (3D), with an F-bar option
for nearly incompressible solids; differentiate through static and dynamic solves by the
implicit function theorem and fit material parameters with optax.

The top level holds what a user types (mesh constructors and I/O, ``Lame`` and
``neo_hookean``, ``fix``, ``Potential``, ``solve`` and the solver settings, ``simulate``,
``fit``, ``shard``); everything else lives in its package: :mod:`~jaxelastic.mesh`,
:mod:`~jaxelastic.materials`, :mod:`~jaxelastic.kinematics` (the toolbox of a ψ author),
:mod:`~jaxelastic.mechanics`, :mod:`~jaxelastic.loads`, :mod:`~jaxelastic.solvers`,
:mod:`~jaxelastic.dynamics`, :mod:`~jaxelastic.fitting`, :mod:`~jaxelastic.contact`,
:mod:`~jaxelastic.io`, :mod:`~jaxelastic.postprocess`, :mod:`~jaxelastic.parallel`,
:mod:`~jaxelastic.verification`.

The library never changes JAX's global configuration: enable float64 yourself with
``jax.config.update("jax_enable_x64", True)`` (tests, scripts and the CLI do).
"""

import importlib
from typing import TYPE_CHECKING

from .deprecation import moved_attributes

if TYPE_CHECKING:  # the names as the type checker and the API docs see them
    from . import contact as contact
    from . import dynamics as dynamics
    from . import fitting as fitting
    from . import io as io
    from . import loads as loads
    from . import materials as materials
    from . import mechanics as mechanics
    from . import mesh as mesh
    from . import parallel as parallel
    from . import postprocess as postprocess
    from . import solvers as solvers
    from . import verification as verification
    from .dynamics import Integrator as Integrator
    from .dynamics import simulate as simulate
    from .fitting import fit as fit
    from .io import read_mesh as read_mesh
    from .io import write_vtu as write_vtu
    from .loads import Dirichlet as Dirichlet
    from .loads import fix as fix
    from .materials import Lame as Lame
    from .materials import neo_hookean as neo_hookean
    from .mechanics import kinematics as kinematics
    from .mechanics.kernels import energy as energy
    from .mechanics.kernels import first_piola as first_piola
    from .mechanics.kernels import forces as forces
    from .mechanics.potential import Potential as Potential
    from .mesh import Mesh as Mesh
    from .mesh import MeshError as MeshError
    from .mesh import box as box
    from .mesh import cook_membrane as cook_membrane
    from .mesh import from_arrays as from_arrays
    from .mesh import rectangle as rectangle
    from .mesh import to_quadratic as to_quadratic
    from .mesh import with_formulation as with_formulation
    from .parallel.sharding import shard as shard
    from .solvers import AMG as AMG
    from .solvers import CG as CG
    from .solvers import Direct as Direct
    from .solvers import ImplicitAdjoint as ImplicitAdjoint
    from .solvers import Multilevel as Multilevel
    from .solvers import Newton as Newton
    from .solvers import Solution as Solution
    from .solvers import SolveError as SolveError
    from .solvers import Status as Status
    from .solvers import solve as solve
    from .solvers import solve_incremental as solve_incremental
    from .solvers import unloaded_shape as unloaded_shape

__all__ = [
    # packages
    "contact",
    "dynamics",
    "fitting",
    "io",
    "kinematics",
    "loads",
    "materials",
    "mechanics",
    "mesh",
    "parallel",
    "postprocess",
    "solvers",
    "verification",
    # meshes and files
    "Mesh",
    "MeshError",
    "box",
    "rectangle",
    "cook_membrane",
    "from_arrays",
    "to_quadratic",
    "with_formulation",
    "read_mesh",
    "write_vtu",
    # materials, loads, the potential
    "Lame",
    "neo_hookean",
    "fix",
    "Dirichlet",
    "Potential",
    "first_piola",
    "energy",
    "forces",
    # solving
    "solve",
    "solve_incremental",
    "unloaded_shape",
    "Newton",
    "CG",
    "Direct",
    "AMG",
    "Multilevel",
    "ImplicitAdjoint",
    "Solution",
    "SolveError",
    "Status",
    # dynamics, identification, devices
    "simulate",
    "Integrator",
    "fit",
    "shard",
]

__version__ = "0.1.0"


_MOVED = {
    # name: (where it is now, what to write instead)
    "lame": (
        "jaxelastic.materials:lame",
        "je.Lame.from_E_nu(E, nu) (or je.materials.lame for the tuple)",
    ),
    "project_psd": ("jaxelastic.mechanics:project_psd", "je.mechanics.project_psd"),
    "svd_rv": ("jaxelastic.mechanics.kinematics:svd_rv", "je.kinematics.svd_rv"),
    "polar": ("jaxelastic.mechanics.kinematics:polar", "je.kinematics.polar"),
    "deformation_gradients": (
        "jaxelastic.mechanics.kinematics:deformation_gradients",
        "je.kinematics.deformation_gradients",
    ),
    "assemble": ("jaxelastic.mechanics:assemble", "je.mechanics.assemble"),
    "energy_densities": ("jaxelastic.mechanics:energy_densities", "je.mechanics.energy_densities"),
    "hvp": ("jaxelastic.mechanics:hvp", "je.mechanics.hvp"),
    "element_hessians": ("jaxelastic.mechanics:element_hessians", "je.mechanics.element_hessians"),
    # the former top-level element_forces returned the per-element gradients, +dE/dx
    "element_forces": (
        "jaxelastic.mechanics:element_gradients",
        "je.mechanics.element_gradients for these values (+dE/dx per element), or "
        "je.mechanics.element_forces for -dE/dx, the sign of je.forces",
    ),
    "Partition": ("jaxelastic.parallel:Partition", "je.parallel.Partition"),
    "potential": ("jaxelastic.mechanics.potential", "je.mechanics.potential"),
    "sharding": ("jaxelastic.parallel.sharding", "je.parallel.sharding"),
    "distributed": ("jaxelastic.parallel.distributed", "je.parallel.distributed"),
    "reference": ("jaxelastic.materials.reference", "je.materials.reference"),
    "rubber": (
        "jaxelastic.materials.rubber",
        "je.materials.rubber (or je.materials.mooney_rivlin, ...)",
    ),
    "fibres": ("jaxelastic.materials.fibres", "je.materials.fibres"),
    "spectral": ("jaxelastic.materials.spectral", "je.materials.spectral"),
    "fusion": ("jaxelastic.mechanics.fusion", "je.mechanics.fusion"),
    "benchmarks": ("jaxelastic.verification", "je.verification"),
    "crosscheck": (
        "jaxelastic.verification.derivative_check",
        "je.verification.derivative_check",
    ),
}

# names that moved into their packages still resolve, with a DeprecationWarning
_moved = moved_attributes(__name__, "je", _MOVED)

_LAZY = {
    # name: (module, attribute; None: the module itself)
    "contact": (".contact", None),
    "dynamics": (".dynamics", None),
    "fitting": (".fitting", None),
    "io": (".io", None),
    "loads": (".loads", None),
    "materials": (".materials", None),
    "mechanics": (".mechanics", None),
    "mesh": (".mesh", None),
    "parallel": (".parallel", None),
    "postprocess": (".postprocess", None),
    "solvers": (".solvers", None),
    "verification": (".verification", None),
    "Integrator": (".dynamics", "Integrator"),
    "simulate": (".dynamics", "simulate"),
    "fit": (".fitting", "fit"),
    "read_mesh": (".io", "read_mesh"),
    "write_vtu": (".io", "write_vtu"),
    "Dirichlet": (".loads", "Dirichlet"),
    "fix": (".loads", "fix"),
    "Lame": (".materials", "Lame"),
    "neo_hookean": (".materials", "neo_hookean"),
    "kinematics": (".mechanics", "kinematics"),
    "energy": (".mechanics.kernels", "energy"),
    "first_piola": (".mechanics.kernels", "first_piola"),
    "forces": (".mechanics.kernels", "forces"),
    "Potential": (".mechanics.potential", "Potential"),
    "Mesh": (".mesh", "Mesh"),
    "MeshError": (".mesh", "MeshError"),
    "box": (".mesh", "box"),
    "cook_membrane": (".mesh", "cook_membrane"),
    "from_arrays": (".mesh", "from_arrays"),
    "rectangle": (".mesh", "rectangle"),
    "to_quadratic": (".mesh", "to_quadratic"),
    "with_formulation": (".mesh", "with_formulation"),
    "shard": (".parallel.sharding", "shard"),
    "AMG": (".solvers", "AMG"),
    "CG": (".solvers", "CG"),
    "Direct": (".solvers", "Direct"),
    "ImplicitAdjoint": (".solvers", "ImplicitAdjoint"),
    "Multilevel": (".solvers", "Multilevel"),
    "Newton": (".solvers", "Newton"),
    "Solution": (".solvers", "Solution"),
    "SolveError": (".solvers", "SolveError"),
    "Status": (".solvers", "Status"),
    "solve": (".solvers", "solve"),
    "solve_incremental": (".solvers", "solve_incremental"),
    "unloaded_shape": (".solvers", "unloaded_shape"),
}


def __getattr__(name: str):
    """The top-level names, each imported when first used (PEP 562): ``import jaxelastic``
    itself imports neither JAX nor SciPy, so the ``jaxelastic`` command handles Ctrl-C
    from its first line on (:mod:`jaxelastic.cli`)."""
    if name not in _LAZY:
        return _moved(name)
    where, attribute = _LAZY[name]
    target = importlib.import_module(where, __name__)
    value = target if attribute is None else getattr(target, attribute)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
