"""Device-resident aggregation multigrid, the preconditioner of ``je.Multilevel``.

* :mod:`~jaxelastic.solvers.multilevel.hierarchy`: the host setup, once per (mesh,
  Dirichlet mask): aggregation, tentative prolongators, index maps (:class:`Hierarchy`);
* :mod:`~jaxelastic.solvers.multilevel.cycle`: per Newton step, on the device, the Galerkin
  products, Chebyshev smoothers and the V/W-cycle ``r ↦ M⁻¹r`` (:func:`preconditioner`);
* :mod:`~jaxelastic.solvers.multilevel.sharded`: the same on a mesh sharded over devices
  (:class:`ShardedHierarchy`, :func:`sharded_preconditioner`).
"""

from .cycle import ell_matvec as ell_matvec
from .cycle import preconditioner as preconditioner
from .hierarchy import Hierarchy as Hierarchy
from .hierarchy import Level as Level
from .hierarchy import build_hierarchy as build_hierarchy
from .hierarchy import canonical_order as canonical_order
from .sharded import ShardedHierarchy as ShardedHierarchy
from .sharded import build_sharded_hierarchy as build_sharded_hierarchy
from .sharded import sharded_preconditioner as sharded_preconditioner

__all__ = [
    "Hierarchy",
    "Level",
    "ShardedHierarchy",
    "build_hierarchy",
    "build_sharded_hierarchy",
    "canonical_order",
    "preconditioner",
    "sharded_preconditioner",
    "ell_matvec",
]
