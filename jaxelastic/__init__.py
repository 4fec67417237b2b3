"""jaxelastic: differentiable finite-element elasticity in JAX.

Write a strain-energy density ``psi(F, params) -> scalar``; get the first Piola–Kirchhoff
stress, nodal forces, Hessian-vector products, element Hessians and implicit solvers by
autodiff, on linear and quadratic triangles (2D) and tetrahedra (3D), with an F-bar option
for nearly incompressible solids; differentiate through static and dynamic solves by the
implicit function theorem and fit material parameters with optax.

The library never changes JAX's global configuration: enable float64 yourself with
``jax.config.update("jax_enable_x64", True)`` (tests, scripts and the CLI do).
"""

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
from . import verification as benchmarks
from . import verification as verification
from .dynamics import Integrator as Integrator
from .io import read_mesh as read_mesh
from .io import write_vtu as write_vtu
from .loads import Dirichlet as Dirichlet
from .materials import Lame as Lame
from .materials import lame as lame
from .materials import reference as reference
from .mechanics import kinematics as kinematics
from .mechanics import potential as potential
from .mechanics.hessians import element_hessians as element_hessians
from .mechanics.kernels import assemble as assemble
from .mechanics.kernels import element_forces as element_forces
from .mechanics.kernels import energy as energy
from .mechanics.kernels import energy_densities as energy_densities
from .mechanics.kernels import first_piola as first_piola
from .mechanics.kernels import forces as forces
from .mechanics.kernels import hvp as hvp
from .mechanics.kinematics import deformation_gradients as deformation_gradients
from .mechanics.kinematics import polar as polar
from .mechanics.kinematics import svd_rv as svd_rv
from .mechanics.potential import Potential as Potential
from .mechanics.psd import project_psd as project_psd
from .mesh import Mesh as Mesh
from .mesh import MeshError as MeshError
from .mesh import box as box
from .mesh import cook_membrane as cook_membrane
from .mesh import from_arrays as from_arrays
from .mesh import rectangle as rectangle
from .mesh import to_quadratic as to_quadratic
from .mesh import with_formulation as with_formulation
from .parallel import distributed as distributed
from .parallel import sharding as sharding
from .parallel.sharding import Partition as Partition
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
from .verification import derivative_check as crosscheck

__all__ = [
    "contact",
    "dynamics",
    "fitting",
    "io",
    "loads",
    "materials",
    "mechanics",
    "mesh",
    "parallel",
    "postprocess",
    "solvers",
    "verification",
    "benchmarks",
    "crosscheck",
    "distributed",
    "kinematics",
    "potential",
    "reference",
    "sharding",
    "Integrator",
    "read_mesh",
    "write_vtu",
    "Dirichlet",
    "Lame",
    "lame",
    "reference",
    "kinematics",
    "potential",
    "element_hessians",
    "assemble",
    "element_forces",
    "energy",
    "energy_densities",
    "first_piola",
    "forces",
    "hvp",
    "deformation_gradients",
    "polar",
    "svd_rv",
    "Potential",
    "project_psd",
    "Mesh",
    "MeshError",
    "box",
    "cook_membrane",
    "from_arrays",
    "rectangle",
    "to_quadratic",
    "with_formulation",
    "distributed",
    "sharding",
    "Partition",
    "shard",
    "AMG",
    "CG",
    "Direct",
    "ImplicitAdjoint",
    "Multilevel",
    "Newton",
    "Solution",
    "SolveError",
    "Status",
    "solve",
    "solve_incremental",
]

__version__ = "0.1.0"
