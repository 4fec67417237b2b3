"""Host (NumPy/SciPy) linear algebra behind the device conjugate-gradient loop.

The device CG (:func:`jaxelastic.solvers.linear.krylov`) runs every Krylov iteration; the host
only factorises the assembled Newton matrix and applies the result:

* :mod:`~jaxelastic.solvers.host.assembled`: :class:`HostLinearSolver`, one per (mesh,
  Dirichlet mask): the sparsity pattern, a back end (:func:`make_backend`) and the
  factorise / apply calls the device reaches through ``jax.pure_callback``;
* :mod:`~jaxelastic.solvers.host.pattern`: the sparsity pattern of the global Hessian and
  the rigid-body modes;
* :mod:`~jaxelastic.solvers.host.direct`: :class:`DirectSolver` (PARDISO, CHOLMOD,
  cholespy, SuperLU), with :mod:`~jaxelastic.solvers.host.pardiso` (MKL PARDISO by ctypes);
* :mod:`~jaxelastic.solvers.host.amg`: :class:`AMGSolver` (PyAMG smoothed aggregation,
  Chebyshev smoothing, hierarchy reuse);
* :mod:`~jaxelastic.solvers.host.krylov`: :func:`host_cg`, the host twin of the device CG;
* :mod:`~jaxelastic.solvers.host.products`: threaded sparse products;
* :mod:`~jaxelastic.solvers.host.heap`: freed heap memory back to the OS between steps.

Host-only packages (pypardiso, scikit-sparse, cholespy, pyamg) are imported inside the
functions that use them, never at import time.
"""

from . import amg as amg
from . import assembled as assembled
from . import direct as direct
from . import heap as heap
from . import krylov as krylov
from . import pardiso as pardiso
from . import pattern as pattern
from . import products as products
from .amg import AMGSolver as AMGSolver
from .assembled import BACKEND_KINDS as BACKEND_KINDS
from .assembled import NONFINITE as NONFINITE
from .assembled import NOT_POSITIVE_DEFINITE as NOT_POSITIVE_DEFINITE
from .assembled import SUCCESS as SUCCESS
from .assembled import ContentCache as ContentCache
from .assembled import HostLinearSolver as HostLinearSolver
from .assembled import content_key as content_key
from .assembled import make_backend as make_backend
from .direct import DIRECT_BACKENDS as DIRECT_BACKENDS
from .direct import DirectSolver as DirectSolver
from .direct import available_direct_backends as available_direct_backends
from .heap import map_large_blocks as map_large_blocks
from .heap import release_free_memory as release_free_memory
from .krylov import host_cg as host_cg
from .pattern import SparsityPattern as SparsityPattern
from .pattern import local_upper as local_upper
from .pattern import rigid_body_modes as rigid_body_modes
from .products import galerkin_product as galerkin_product
from .products import split_matvec as split_matvec

__all__ = [
    "amg",
    "assembled",
    "direct",
    "heap",
    "pardiso",
    "krylov",
    "pattern",
    "products",
    "AMGSolver",
    "HostLinearSolver",
    "ContentCache",
    "content_key",
    "SUCCESS",
    "NONFINITE",
    "NOT_POSITIVE_DEFINITE",
    "make_backend",
    "BACKEND_KINDS",
    "DirectSolver",
    "available_direct_backends",
    "DIRECT_BACKENDS",
    "release_free_memory",
    "map_large_blocks",
    "host_cg",
    "SparsityPattern",
    "rigid_body_modes",
    "local_upper",
    "split_matvec",
    "galerkin_product",
]
