"""Verification: reference problems with known answers, and the autodiff cross-check.

Each benchmark builder returns a :class:`Benchmark`: the potential (mesh, ψ, parameters,
loads), the Dirichlet data, and the reference values with their citations. Definitions
only: nothing here solves (``je.solve(b.pot, b.bc)`` does).

* Cook's membrane (:mod:`~jaxelastic.verification.cook`): :func:`cook_linear`,
  :func:`cook_incompressible`, :func:`cook_neo_hookean`.
* Cantilevers (:mod:`~jaxelastic.verification.cantilever`): :func:`timoshenko_cantilever`
  with its exact field :func:`timoshenko_exact`; :func:`cantilever3d` against
  :func:`beam_deflection`.
* Patch tests (:mod:`~jaxelastic.verification.patch`): :func:`macneal_harder_patch`,
  :func:`affine_patch`.
* Homogeneous states (:mod:`~jaxelastic.verification.homogeneous`): :func:`uniaxial_tension`,
  :func:`simple_shear`.
* Treloar's (1944) rubber data (:mod:`~jaxelastic.verification.treloar`):
  :data:`TRELOAR_UNIAXIAL`, :data:`TRELOAR_EQUIBIAXIAL`, :data:`TRELOAR_PURE_SHEAR`
  (stretch [-], nominal stress [MPa]).
* The JAX-FEM twist (:mod:`~jaxelastic.verification.torsion`): :func:`twist`.
* The autodiff cross-check (:mod:`~jaxelastic.verification.derivative_check`):
  :func:`crosscheck`, autodiff stress, forces and HVPs against the hand-derived P of
  :mod:`jaxelastic.materials.reference` and finite differences
  (``python -m jaxelastic crosscheck``).
"""

from . import derivative_check as derivative_check
from .cantilever import CANTILEVER3D as CANTILEVER3D
from .cantilever import TIMOSHENKO as TIMOSHENKO
from .cantilever import beam_deflection as beam_deflection
from .cantilever import cantilever3d as cantilever3d
from .cantilever import timoshenko_cantilever as timoshenko_cantilever
from .cantilever import timoshenko_exact as timoshenko_exact
from .cook import COOK_INCOMPRESSIBLE_REF as COOK_INCOMPRESSIBLE_REF
from .cook import COOK_LINEAR_REF as COOK_LINEAR_REF
from .cook import COOK_NEO_HOOKEAN_REF as COOK_NEO_HOOKEAN_REF
from .cook import cook_incompressible as cook_incompressible
from .cook import cook_linear as cook_linear
from .cook import cook_neo_hookean as cook_neo_hookean
from .derivative_check import crosscheck as crosscheck
from .homogeneous import pull_bc as pull_bc
from .homogeneous import simple_shear as simple_shear
from .homogeneous import uniaxial_tension as uniaxial_tension
from .patch import MH_POINTS as MH_POINTS
from .patch import MH_QUADS as MH_QUADS
from .patch import PATCH_C as PATCH_C
from .patch import PATCH_F0 as PATCH_F0
from .patch import affine_patch as affine_patch
from .patch import macneal_harder_patch as macneal_harder_patch
from .patch import patch_mesh as patch_mesh
from .problem import Benchmark as Benchmark
from .problem import edge_load_2d as edge_load_2d
from .problem import node_at as node_at
from .torsion import TWIST_THETA as TWIST_THETA
from .torsion import twist as twist
from .torsion import twist_displacement as twist_displacement
from .treloar import TRELOAR as TRELOAR
from .treloar import TRELOAR_EQUIBIAXIAL as TRELOAR_EQUIBIAXIAL
from .treloar import TRELOAR_PURE_SHEAR as TRELOAR_PURE_SHEAR
from .treloar import TRELOAR_UNIAXIAL as TRELOAR_UNIAXIAL
from .treloar import TreloarCurve as TreloarCurve

__all__ = [
    "derivative_check",
    "CANTILEVER3D",
    "TIMOSHENKO",
    "beam_deflection",
    "cantilever3d",
    "timoshenko_cantilever",
    "timoshenko_exact",
    "COOK_INCOMPRESSIBLE_REF",
    "COOK_LINEAR_REF",
    "COOK_NEO_HOOKEAN_REF",
    "cook_incompressible",
    "cook_linear",
    "cook_neo_hookean",
    "pull_bc",
    "simple_shear",
    "uniaxial_tension",
    "MH_POINTS",
    "MH_QUADS",
    "PATCH_C",
    "PATCH_F0",
    "affine_patch",
    "macneal_harder_patch",
    "patch_mesh",
    "Benchmark",
    "edge_load_2d",
    "node_at",
    "TWIST_THETA",
    "twist",
    "twist_displacement",
    "crosscheck",
    "TRELOAR",
    "TRELOAR_EQUIBIAXIAL",
    "TRELOAR_PURE_SHEAR",
    "TRELOAR_UNIAXIAL",
    "TreloarCurve",
]
