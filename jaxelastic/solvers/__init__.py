"""Solvers: one :func:`solve` for x*, Newton, linear solvers, host back ends, adjoints.

``results`` (Status, Solution, SolveError) → ``linear`` (settings, state, the ``auto``
table, the one CG) → ``newton`` (settings, state, the one loop) → ``adjoint``
(implicit-function-theorem derivatives) → ``equilibrium`` (:func:`solve`, the entry point)
→ ``continuation`` (load stepping on solve), ``volume_control`` (prescribed cavity volumes,
the pressures unknown) → ``inverse`` (the unloaded rest shape of an observed loaded one,
:func:`unloaded_shape`).
"""

from ..deprecation import moved_attributes
from .adjoint import X_STAR as X_STAR
from .adjoint import GradientError as GradientError
from .adjoint import ImplicitAdjoint as ImplicitAdjoint
from .adjoint import check_finite_gradients as check_finite_gradients
from .adjoint import value_and_grad as value_and_grad
from .continuation import scaled_dirichlet as scaled_dirichlet
from .continuation import solve_incremental as solve_incremental
from .equilibrium import PreparedSolver as PreparedSolver
from .equilibrium import bind_solver as bind_solver
from .equilibrium import is_traced as is_traced
from .equilibrium import prepare_solver as prepare_solver
from .equilibrium import solve as solve
from .host import HostLinearSolver as HostLinearSolver
from .inverse import unloaded_shape as unloaded_shape
from .linear import AMG as AMG
from .linear import AUTO_DIRECT_MAX_DOFS as AUTO_DIRECT_MAX_DOFS
from .linear import CG as CG
from .linear import LINEAR_SOLVERS as LINEAR_SOLVERS
from .linear import Direct as Direct
from .linear import LinearSolver as LinearSolver
from .linear import LinearState as LinearState
from .linear import Multilevel as Multilevel
from .linear import bind_linear as bind_linear
from .linear import cg as cg
from .linear import init_linear as init_linear
from .newton import Newton as Newton
from .newton import NewtonState as NewtonState
from .newton import solved_potential as solved_potential
from .results import Solution as Solution
from .results import SolveError as SolveError
from .results import SolveWarning as SolveWarning
from .results import Status as Status
from .volume_control import cavity_compliance as cavity_compliance
from .volume_control import solve_volume_controlled as solve_volume_controlled

__all__ = [
    "X_STAR",
    "GradientError",
    "ImplicitAdjoint",
    "check_finite_gradients",
    "value_and_grad",
    "scaled_dirichlet",
    "solve_incremental",
    "unloaded_shape",
    "solve_volume_controlled",
    "cavity_compliance",
    "bind_solver",
    "PreparedSolver",
    "is_traced",
    "prepare_solver",
    "solve",
    "HostLinearSolver",
    "AMG",
    "AUTO_DIRECT_MAX_DOFS",
    "CG",
    "LINEAR_SOLVERS",
    "Direct",
    "LinearSolver",
    "LinearState",
    "Multilevel",
    "bind_linear",
    "cg",
    "init_linear",
    "Newton",
    "NewtonState",
    "solved_potential",
    "Solution",
    "SolveError",
    "SolveWarning",
    "Status",
]

__getattr__ = moved_attributes(
    __name__,
    "je.solvers",
    {
        "contact_potential": (
            "jaxelastic.solvers.newton:solved_potential",
            "je.solvers.solved_potential (same arguments)",
        )
    },
)
