"""The one entry point for "find x*": :func:`solve`.

In the spirit of optimistix's ``root_find(fn, solver, y0, args, *, adjoint, throw)``:
``solve(pot, bc, *, x0, solver, adjoint, throw) -> Solution``, the same defaults
everywhere (statics, load stepping, dynamics steps, fitting), differentiable by the
implicit function theorem whenever it is differentiated (:mod:`.adjoint`).
"""

from __future__ import annotations

import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
from jax.core import Tracer

from ..loads import Dirichlet
from ..potential import Potential
from .adjoint import ImplicitAdjoint, differentiable_minimize
from .linear import bind_linear
from .newton import Newton
from .results import Solution, SolveError, Status

__all__ = ["solve", "bind_solver", "is_traced"]


def is_traced(*trees) -> bool:
    """Whether any leaf of ``trees`` is a JAX tracer (we are inside jit/vmap/grad)."""
    return any(isinstance(a, Tracer) for t in trees for a in jax.tree_util.tree_leaves(t))


def bind_solver(solver: Newton, mesh, bc: Dirichlet) -> Newton:
    """``solver`` with its linear solver resolved and bound for ``mesh`` and ``bc.mask``
    (:func:`~jaxelastic.solvers.linear.bind_linear`); call it once outside jit to reuse a
    host factorisation pattern across many solves."""
    if not isinstance(solver, Newton):
        raise TypeError(f"solver must be a je.Newton(...), got {type(solver).__name__}")
    linear = bind_linear(solver.linear, mesh, bc)
    return solver if linear is solver.linear else dataclasses.replace(solver, linear=linear)


@functools.partial(jax.jit, static_argnames=("solver", "adjoint"))
def _solve_jit(pot, bc, x0, solver, adjoint):
    return differentiable_minimize(solver, adjoint, pot, bc, x0)


def _check_inputs(pot: Potential, bc: Dirichlet, x0):
    if not isinstance(pot, Potential):
        raise TypeError(f"pot must be a je.Potential, got {type(pot).__name__}")
    if not isinstance(bc, Dirichlet):
        raise TypeError(
            f"bc must be je.Dirichlet data (e.g. je.loads.fix(mesh, nodes)), got "
            f"{type(bc).__name__}"
        )
    shape = tuple(pot.mesh.points.shape)
    for name, a in (("bc.mask", bc.mask), ("bc.values", bc.values)):
        if tuple(jnp.shape(a)) != shape:
            raise ValueError(f"{name} must have shape {shape} (n_nodes, dim), got {jnp.shape(a)}")
    if x0 is None:
        return pot.mesh.points
    if tuple(jnp.shape(x0)) != shape:
        raise ValueError(f"x0 must have shape {shape} (n_nodes, dim), got {jnp.shape(x0)}")
    return jnp.asarray(x0, pot.mesh.points.dtype)


def solve(
    pot: Potential,
    bc: Dirichlet,
    *,
    x0: jax.Array | None = None,
    solver: Newton = Newton(),
    adjoint: ImplicitAdjoint = ImplicitAdjoint(),
    throw: bool = True,
) -> Solution:
    """Minimise Π(x) subject to ``x[bc.mask] = bc.values[bc.mask]``.

    Jit-able, vmap-able (with the matrix-free :class:`~jaxelastic.solvers.linear.CG`) and
    differentiable: under ``jax.grad``/``jax.vjp`` (default ``ImplicitAdjoint()``) or
    ``jax.jvp``/``jax.jacfwd`` (``ImplicitAdjoint(mode="forward")``) the derivatives of
    ``x`` with respect to every floating leaf of ``pot`` (material parameters, ``f_ext``,
    masses, …) and to ``bc.values`` come from the implicit function theorem (one linear
    solve with the Hessian at x*), never from the Newton iterations; if the solve failed
    they are NaN. Derivatives with respect to ``x0`` are zero.

    Args:
        pot: the :class:`~jaxelastic.potential.Potential` (elastic energy, loads, inertia).
        bc: :class:`~jaxelastic.loads.Dirichlet` data.
        x0: ``(n_nodes, dim)`` initial positions (default: the rest shape; Dirichlet dofs
            need not be in place).
        solver: :class:`~jaxelastic.solvers.newton.Newton` settings and linear solver
            (default ``linear="auto"``: sparse Cholesky up to 10k dofs in 3D, AMG-CG above,
            matrix-free CG on traced meshes).
        adjoint: :class:`~jaxelastic.solvers.adjoint.ImplicitAdjoint` settings of the
            derivative solves.
        throw: outside jit, raise :class:`~jaxelastic.solvers.results.SolveError` unless
            the status is SUCCESS. Inside jit nothing is raised: read ``status``.

    Returns:
        :class:`~jaxelastic.solvers.results.Solution` (``x``, ``status``, ``stats``; outside
        jit ``stats["wall_time"]`` is the wall-clock time of the solve in seconds).
    """
    x0 = _check_inputs(pot, bc, x0)
    solver = bind_solver(solver, pot.mesh, bc)
    if not isinstance(adjoint, ImplicitAdjoint):
        raise TypeError(f"adjoint must be je.ImplicitAdjoint(...), got {type(adjoint).__name__}")
    if is_traced(pot, bc, x0):
        return differentiable_minimize(solver, adjoint, pot, bc, x0)
    t0 = time.perf_counter()
    res = jax.block_until_ready(_solve_jit(pot, bc, x0, solver, adjoint))
    stats = dict(res.stats, wall_time=time.perf_counter() - t0)
    res = res._replace(stats=stats)
    if throw and int(res.status) != Status.SUCCESS:
        raise SolveError(res, "Newton solve")
    return res
