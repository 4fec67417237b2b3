"""Meshes: the rest-shape :class:`Mesh` pytree, generators, P1 → P2 lifting, boundaries.

Modules: :mod:`~jaxelastic.mesh.core` (the pytree and its validating constructor),
:mod:`~jaxelastic.mesh.elements` (reference elements and quadrature rules),
:mod:`~jaxelastic.mesh.geometry` (the rest quantities as functions of the rest points, on
NumPy or JAX arrays: what makes :meth:`Mesh.with_points` differentiable),
:mod:`~jaxelastic.mesh.generators` (rectangle, box, Cook's membrane, spherical shell,
annulus, truncated ellipsoid),
:mod:`~jaxelastic.mesh.quadratic` (P2 / composite lifting, formulation switch) and
:mod:`~jaxelastic.mesh.boundary` (boundary facets and nodes). Sharded solves partition a
mesh over devices with :mod:`jaxelastic.parallel`.
"""

from . import elements as elements
from . import geometry as geometry
from .boundary import boundary_facets as boundary_facets
from .boundary import boundary_nodes as boundary_nodes
from .boundary import connected_parts as connected_parts
from .boundary import facet_owners as facet_owners
from .core import FORMULATIONS as FORMULATIONS
from .core import Mesh as Mesh
from .core import MeshError as MeshError
from .core import check_formulation as check_formulation
from .core import from_arrays as from_arrays
from .generators import annulus as annulus
from .generators import box as box
from .generators import cook_membrane as cook_membrane
from .generators import ellipsoid_surfaces as ellipsoid_surfaces
from .generators import rectangle as rectangle
from .generators import spherical_shell as spherical_shell
from .generators import truncated_ellipsoid as truncated_ellipsoid
from .geometry import invalid_cells as invalid_cells
from .quadratic import linear_cells as linear_cells
from .quadratic import to_quadratic as to_quadratic
from .quadratic import vertex_nodes as vertex_nodes
from .quadratic import with_formulation as with_formulation

__all__ = [
    "Mesh",
    "MeshError",
    "FORMULATIONS",
    "check_formulation",
    "from_arrays",
    "rectangle",
    "box",
    "cook_membrane",
    "spherical_shell",
    "annulus",
    "truncated_ellipsoid",
    "ellipsoid_surfaces",
    "boundary_facets",
    "boundary_nodes",
    "facet_owners",
    "connected_parts",
    "to_quadratic",
    "with_formulation",
    "vertex_nodes",
    "linear_cells",
    "elements",
    "geometry",
    "invalid_cells",
]
