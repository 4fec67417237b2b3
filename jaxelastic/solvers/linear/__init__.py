"""Linear solvers of the Newton system: settings, explicit state, one ``auto`` table.

``gmres`` (the one GMRES loop, for non-symmetric operators) → ``protocol``
(:class:`LinearSolver`, :class:`LinearState`) → ``system`` (the Newton operator) →
``krylov`` (the one device CG, :class:`CG`) → ``host`` (:class:`Direct`,
:class:`AMG`) and ``multilevel`` (:class:`Multilevel`) → ``auto`` (what ``"auto"`` picks)
→ ``selection`` (:func:`resolve`, :func:`init_linear`).
"""

from .auto import AUTO_DIRECT_MAX_DOFS as AUTO_DIRECT_MAX_DOFS
from .auto import AUTO_DIRECT_MAX_DOFS_P2 as AUTO_DIRECT_MAX_DOFS_P2
from .auto import AUTO_DIRECT_MAX_DOFS_QUADRATIC as AUTO_DIRECT_MAX_DOFS_QUADRATIC
from .auto import LINEAR_SOLVERS as LINEAR_SOLVERS
from .auto import choose as choose
from .host import AMG as AMG
from .host import Direct as Direct
from .host import HostSolver as HostSolver
from .host import assemble_upper as assemble_upper
from .krylov import CG as CG
from .krylov import block_jacobi as block_jacobi
from .krylov import cg as cg
from .krylov import jacobi as jacobi
from .multilevel import Multilevel as Multilevel
from .nonsymmetric import gmres as gmres
from .protocol import LinearSolver as LinearSolver
from .protocol import LinearState as LinearState
from .selection import bind_linear as bind_linear
from .selection import init_linear as init_linear
from .selection import resolve as resolve
from .system import NewtonSystem as NewtonSystem
from .system import exact_system as exact_system
from .system import newton_system as newton_system

__all__ = [
    "AUTO_DIRECT_MAX_DOFS",
    "AUTO_DIRECT_MAX_DOFS_P2",
    "AUTO_DIRECT_MAX_DOFS_QUADRATIC",
    "LINEAR_SOLVERS",
    "choose",
    "CG",
    "cg",
    "gmres",
    "block_jacobi",
    "jacobi",
    "AMG",
    "Direct",
    "HostSolver",
    "assemble_upper",
    "Multilevel",
    "LinearSolver",
    "LinearState",
    "bind_linear",
    "init_linear",
    "resolve",
    "NewtonSystem",
    "exact_system",
    "newton_system",
]
