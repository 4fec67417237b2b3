"""Solvers: one :func:`solve` for x*, Newton, linear solvers, host back ends, adjoints.

``results`` (Status, Solution, SolveError) → ``linear`` (the one CG, CG/Direct/AMG
objects) → ``newton`` (Newton settings and loop) → ``adjoint`` (implicit-function-theorem
derivatives) → ``solve`` (the entry point) → ``continuation`` (load stepping on solve).
"""

from .adjoint import X_STAR as X_STAR
from .adjoint import GradientError as GradientError
from .adjoint import ImplicitAdjoint as ImplicitAdjoint
from .adjoint import check_finite_gradients as check_finite_gradients
from .adjoint import value_and_grad as value_and_grad
from .continuation import scaled_dirichlet as scaled_dirichlet
from .continuation import solve_incremental as solve_incremental
from .host import HostLinearSolver as HostLinearSolver
from .linear import AMG as AMG
from .linear import AUTO_DIRECT_MAX_DOFS as AUTO_DIRECT_MAX_DOFS
from .linear import CG as CG
from .linear import LINEAR_SOLVERS as LINEAR_SOLVERS
from .linear import Direct as Direct
from .linear import Multilevel as Multilevel
from .linear import bind_linear as bind_linear
from .linear import cg as cg
from .newton import Newton as Newton
from .newton import contact_potential as contact_potential
from .results import Solution as Solution
from .results import SolveError as SolveError
from .results import Status as Status
from .solve import bind_solver as bind_solver
from .solve import is_traced as is_traced
from .solve import solve as solve
