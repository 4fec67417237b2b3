"""Nonlinear and linear solvers (Newton, CG, sparse host linear algebra)."""

from .continuation import IncrementalResult as IncrementalResult
from .continuation import solve_incremental as solve_incremental
from .host import HostLinearSolver as HostLinearSolver
from .newton import NewtonResult as NewtonResult
from .newton import NewtonSettings as NewtonSettings
from .newton import SolveError as SolveError
from .newton import Status as Status
from .newton import make_linear as make_linear
from .newton import newton as newton
from .newton import solve as solve
