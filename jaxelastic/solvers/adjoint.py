"""Differentiating through a static equilibrium by the implicit function theorem.

:func:`jaxelastic.solve` returns the Newton solution ``x*(θ)`` of ``min_x Π(x; θ)`` subject
to ``x_D = bc.values_D``; this module makes it differentiable with respect to everything in
the :class:`~jaxelastic.potential.Potential` (material parameters — shared scalars or
per-cell fields —, ``f_ext``, masses, …) and the Dirichlet values ``bc.values``, without
ever differentiating the Newton iterations. At the solution the free residual vanishes,
``g_f(x*, θ) = 0``, so with ``K = ∂²Π/∂x²`` (symmetric)::

    K_ff λ = x̄_f                        (one adjoint solve)
    θ̄      = −(∂g_f/∂θ)ᵀ λ               (jax.vjp of the free-dof gradient)
    v̄_D    = x̄_D − (K λ)_D               (Dirichlet values; λ is zero on prescribed dofs)

Reverse mode (``ImplicitAdjoint(mode="reverse")``, the default) is a ``jax.custom_vjp``
(nothing beyond x* is computed in the forward pass). Forward mode (``mode="forward"``,
needed by ``jax.jvp``/``jacfwd``) is a ``jax.custom_jvp`` whose tangent solve
``K_ff ẋ_f = −(∂g_f/∂θ)·θ̇ − K_fD v̇_D`` is a transposable ``lax.custom_linear_solve``, so
reverse mode works over it too (at the price of the Hessian at x* in the forward pass). We
chose this over ``lax.custom_root``, which would re-derive the tangent system from a
residual function and hide the Dirichlet split and the failure flag.

The adjoint/tangent system is solved by the Newton solver's linear solver in its exact
mode (:meth:`~jaxelastic.solvers.linear.LinearSolver.exact`: block-Jacobi PCG on the exact
Hessian; host back ends: device PCG preconditioned by the last Newton factorisation). The
forward solve runs on ``lax.stop_gradient`` of the inputs, so under an eager ``jax.grad``
or ``jax.jvp`` it is the same solve, on concrete values, as without differentiation
(:func:`~jaxelastic.solvers.newton.minimize`); the adjoint and tangent computations are
compiled functions of their own.

A follower pressure on an open surface (``Pressure.follower``) has no potential and a
non-symmetric Jacobian ``J`` (the symmetric Hessian plus the skew pressure stiffness,
:meth:`~jaxelastic.mechanics.pressure.Pressure.skew_vp`): its reverse-mode adjoint solves
``J_ffᵀ λ = x̄_f`` with the transpose and ``v̄_D = x̄_D − (Jᵀλ)_D``, its forward-mode
tangent ``J_ff ẋ_f = −(∂g_f/∂θ)·θ̇ − J_fD v̇_D`` (a ``lax.custom_linear_solve`` whose
transpose solves with ``Jᵀ``, so reverse over forward works too); both by restarted GMRES
(:func:`~jaxelastic.solvers.linear.nonsymmetric.gmres`, Saad & Schultz 1986) preconditioned by
the linear solver's preconditioner of the symmetric part
(:meth:`~jaxelastic.solvers.linear.LinearSolver.symmetric_preconditioner`).

Failure is loud: if the forward Newton solve or the adjoint solve did not converge,
*every* floating-point cotangent is NaN; :func:`value_and_grad` (and the fitting loop)
raise :class:`GradientError`. Gradients are never silently computed at a non-equilibrium
point.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import cast

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.ad_checkpoint import checkpoint_name
from jax.core import Tracer
from jax.custom_derivatives import SymbolicZero

from ..loads import Dirichlet
from ..mechanics import potential as pot_mod
from ..mechanics.potential import Potential
from ..mechanics.pressure import is_conservative
from .linear import HostSolver, LinearState, NewtonSystem, assemble_upper, exact_system
from .linear.nonsymmetric import gmres
from .linear.system import mass_or_zeros
from .newton import Newton, minimize, solved_potential
from .results import Solution, Status

__all__ = [
    "ImplicitAdjoint",
    "GradientError",
    "X_STAR",
    "MODES",
    "differentiable_minimize",
    "differentiable_solution",
    "value_and_grad",
    "check_finite_gradients",
]

MODES = ("reverse", "forward")

X_STAR = "jaxelastic.x_star"
"""``jax.ad_checkpoint.checkpoint_name`` of the Newton solution and status inside a
reverse-mode solve: a ``jax.checkpoint`` policy saving these names
(``save_only_these_names(X_STAR)``) never re-runs a Newton solve when rematerialising."""


class GradientError(RuntimeError):
    """A gradient through an equilibrium solve is not valid (forward or adjoint solve failed)."""


@dataclasses.dataclass(frozen=True)
class ImplicitAdjoint:
    """Implicit-function-theorem derivatives of a solve (frozen, hashable).

    A gradient ``θ̄ = −(∂g_f/∂θ)ᵀλ`` is far less sensitive to the adjoint residual than λ
    itself. Measured on the 5,184-tet 3D neo-Hookean cantilever of ``scripts/bench_fit.py``
    (matrix-free PCG adjoint, d loss/d(E, ν)): relative deviation from the rtol = 1e-12
    gradient 2e-12 at rtol = 1e-10, 7e-12 at 1e-8, 1.5e-8 at 1e-6; fourth-order central
    differences agree with all of them to 1.4e-8 (their own truncation error). The default
    1e-10 keeps two orders of magnitude of margin below a 1e-6 gradient-accuracy goal.

    Attributes:
        rtol: relative residual tolerance of the adjoint/tangent solve (``‖r‖ ≤ rtol·‖b‖``).
        max_iter: iteration cap of that solve.
        mode: ``"reverse"`` (``jax.custom_vjp``: grad, vjp, jacrev) or ``"forward"``
            (``jax.custom_jvp`` with a transposable tangent solve: jvp, jacfwd *and* reverse
            mode).
    """

    rtol: float = 1e-10
    max_iter: int = 20000
    mode: str = "reverse"

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"adjoint mode must be one of {MODES}, got {self.mode!r}")
        if not self.rtol > 0:
            raise ValueError(f"adjoint rtol must be > 0, got {self.rtol!r}")


def _float0_like(a):
    return np.zeros(np.shape(a), dtype=jax.dtypes.float0)


def _is_float(a) -> bool:
    return jnp.issubdtype(jnp.result_type(a), jnp.inexact)


def _nan_unless(ok, tree):
    def f(leaf):
        if leaf is None or not hasattr(leaf, "dtype") or not _is_float(leaf):
            return leaf
        return jnp.where(ok, leaf, jnp.nan).astype(leaf.dtype)

    return jax.tree_util.tree_map(f, tree)


def _solve_ff(solver: Newton, lstate, adj: ImplicitAdjoint, system: NewtonSystem, rhs):
    """Solve ``K_ff y = rhs_f`` (y = 0 on prescribed dofs). Returns ``(y, converged)``."""
    fm = system.free.astype(rhs.dtype)
    b = fm * rhs
    res = solver.linear.exact(lstate, system, b, adj.rtol, adj.max_iter)
    y = fm * res.x
    ok = (res.status == Status.SUCCESS) | (jnp.sum(b * b) == 0)
    return y, ok & jnp.all(jnp.isfinite(y))


def _zeros_like_tree(tree):
    return jax.tree_util.tree_map(_zero_tangent, tree)


def _pullback(pot, mask, x, ok, lam, H_lam, xbar, which: tuple[bool, ...]):
    """``(pot̄, bc̄.values)`` from the adjoint λ: ``θ̄ = −(∂g_f/∂θ)ᵀλ``,
    ``v̄_D = x̄_D − (Kᵀλ)_D`` (``H_lam`` = Kᵀλ, the Hessian K symmetric unless a follower
    load); NaN unless ``ok``.

    ``which``: per leaf of ``pot``, whether it is differentiated (JAX's ``perturbed``
    flag); only those leaves' cotangents are formed, the others are None (zero): an eager
    gradient with respect to a material parameter neither computes nor compiles the
    derivative with respect to the mesh coordinates, loads or masses."""
    fm = (~mask).astype(x.dtype)
    leaves, tree = jax.tree.flatten(pot)
    idx = [i for i, w in enumerate(which) if w]

    def g_free(sub):
        ls = list(leaves)
        for i, v in zip(idx, sub, strict=True):
            ls[i] = v
        return fm * pot_mod.gradient(tree.unflatten(ls), x)

    _, vjp = jax.vjp(g_free, [leaves[i] for i in idx])
    (sub_bar,) = vjp(-lam)
    bars: list = [None] * len(leaves)
    for i, v in zip(idx, sub_bar, strict=True):
        bars[i] = v
    pot_bar = tree.unflatten(bars)
    vals_bar = jnp.where(mask, xbar - H_lam, 0.0)
    return _nan_unless(ok, pot_bar), _nan_unless(ok, vals_bar)


def _nonsymmetric_ff(
    solver: Newton, lstate, adj: ImplicitAdjoint, system: NewtonSystem, rhs, *, transpose: bool
):
    """Solve ``J_ff y = rhs_f`` (``transpose``: ``J_ffᵀ y = rhs_f``) with the true,
    non-symmetric tangent ``J`` of a follower load (``system``: :func:`exact_system` with
    ``exact_tangent=True``; ``Jᵀ = J − 2·skew``) by GMRES preconditioned by the linear
    solver's preconditioner of the symmetric part. Returns ``(y, converged)``."""
    fm = system.free.astype(rhs.dtype)
    b = fm * rhs
    term = system.pot.pressure
    assert term is not None
    x = system.x

    def AT(v):
        w = fm * v
        return fm * (system.H(w) - 2.0 * term.skew_vp(x, w)) + (1.0 - fm) * v

    M, _ = solver.linear.symmetric_preconditioner(lstate, system, system.Ke, jnp.int32(0))
    bn = jnp.sqrt(jnp.sum(b * b))
    res = gmres(AT if transpose else system.A, b, M, tol=adj.rtol * bn, max_iter=adj.max_iter)
    y = fm * res.x
    ok = (res.status == Status.SUCCESS) | (bn == 0)
    return y, ok & jnp.all(jnp.isfinite(y))


def _transpose_solve(solver: Newton, lstate, pot: Potential, x, mask, adj: ImplicitAdjoint, xbar):
    """A follower load's adjoint ``J_ffᵀ λ = x̄_f`` with the true (non-symmetric) Jacobian
    ``J = ∂g/∂x``: ``(λ, Jᵀλ, converged)`` (:func:`_nonsymmetric_ff`)."""
    system = exact_system(pot, x, mask, exact_tangent=True)
    lam, ok = _nonsymmetric_ff(solver, lstate, adj, system, xbar, transpose=True)
    _, JT = jax.vjp(lambda y: pot_mod.gradient(pot, y), x)
    return lam, JT(lam)[0], ok


@functools.partial(jax.jit, static_argnums=(0, 1, 8))
def _cotangents(solver: Newton, adj: ImplicitAdjoint, pot, bc, x, status, lstate, xbar, which):
    """``(pot̄, bc̄)`` of x* from ``x̄`` (one adjoint solve; NaN if anything failed)."""
    mask = bc.mask
    if is_conservative(pot.pressure):
        system = exact_system(pot, x, mask)
        lam, adj_ok = _solve_ff(solver, lstate, adj, system, xbar)
        K_lam = system.H(lam)  # symmetric: Kᵀλ = Kλ
    else:  # a follower load: the transpose of the non-symmetric Jacobian
        lam, K_lam, adj_ok = _transpose_solve(solver, lstate, pot, x, mask, adj, xbar)
    ok = (status == Status.SUCCESS) & adj_ok
    return _pullback(pot, bc.mask, x, ok, lam, K_lam, xbar, which)


def _host_adjoint(solver: Newton, pot, lstate, *arrays) -> bool:
    """Whether the adjoint solve runs as a Python call on the host (an eager gradient
    with a host linear solver, the exact Hessian the assembled element matrix): then no
    compiled piece holds a callback, so JAX's persistent cache keeps them all."""
    return (
        isinstance(solver.linear, HostSolver)
        and getattr(lstate, "host", None) is not None
        and not pot_mod.has_coupling(pot)
        and pot.stiffness_damping is None
        and is_conservative(pot.pressure)
        and not any(isinstance(a, Tracer) for t in (pot, *arrays) for a in jax.tree.leaves(t))
    )


@functools.partial(jax.jit, static_argnums=4)
def _exact_upper(pot, x, mask, element_map, nnz_upper: int):
    """Exact element Hessians at x, their assembled upper-triangle data and the mass
    diagonal (the operator of :func:`_cotangents`, for a host solve)."""
    system = exact_system(pot, x, mask)
    data = assemble_upper(system.Ke, element_map, nnz_upper)
    return system.Ke, data, mass_or_zeros(system), (~mask).astype(x.dtype)


@functools.partial(jax.jit, static_argnums=8)
def _host_pullback(pot, mask, x, status, lam, adj_ok, xbar, Ke, which):
    ok = (status == Status.SUCCESS) & adj_ok & jnp.all(jnp.isfinite(lam))
    H_lam = pot_mod.element_hessian_vp(pot, Ke, lam)
    return _pullback(pot, mask, x, ok, lam, H_lam, xbar, which)


def _host_cotangents(solver: Newton, adj: ImplicitAdjoint, pot, bc, x, status, lstate, xbar, which):
    """:func:`_cotangents` outside jit: the adjoint solve a Python call of the host
    solver between two compiled pieces."""
    host = lstate.host
    Ke, data, md, fm = _exact_upper(pot, x, bc.mask, host.element_map, host.nnz_upper)
    b = np.asarray(fm * xbar)
    y, ok = solver.linear.host_exact(lstate, data, md, b, adj.rtol, adj.max_iter)
    lam = jnp.asarray(np.asarray(y) * np.asarray(fm), x.dtype)
    return _host_pullback(pot, bc.mask, x, status, lam, jnp.asarray(ok), xbar, Ke, which)


@functools.lru_cache(maxsize=64)
def _attach_fn(solver: Newton, adj: ImplicitAdjoint):
    """``attach(pot, bc, x*, status, lstate) = x*`` with the implicit-function-theorem VJP
    (one per settings pair; settings hold no state, so the cache holds no factorisation)."""

    @jax.custom_vjp
    def attach(pot, bc, x, status, lstate):
        return x

    def fwd(pot, bc, x, status, lstate):
        # which leaves of pot are differentiated: a structure (() or None per leaf), so
        # that bwd sees it as static
        flags = tuple(() if p.perturbed else None for p in jax.tree.leaves(pot))
        value = functools.partial(jax.tree.map, lambda p: p.value)
        saved = (value(pot), value(bc), x.value, status.value, value(lstate), flags)
        return x.value, saved

    def bwd(saved, xbar):
        pot, bc, x, status, lstate, flags = saved
        which = tuple(f is not None for f in flags)
        if isinstance(xbar, SymbolicZero):
            xbar = jnp.zeros_like(x)
        args = (pot, bc, x, status, lstate, xbar, which)
        if _host_adjoint(solver, pot, lstate, bc, x, xbar):
            pot_bar, vals_bar = _host_cotangents(solver, adj, *args)
        else:
            pot_bar, vals_bar = _cotangents(solver, adj, *args)
        # the cotangent of the bool mask is a float0 numpy array, which JAX takes for it
        bc_bar = Dirichlet(mask=cast(jax.Array, _float0_like(bc.mask)), values=vals_bar)
        return (pot_bar, bc_bar, jnp.zeros_like(x), _float0_like(status), _zeros_like_tree(lstate))

    attach.defvjp(fwd, bwd, symbolic_zeros=True)
    return attach


def _flag_rest_shape(pot, res: Solution) -> Solution:
    """``res`` with status INVERTED where a rest cell of ``pot.mesh`` has a non-positive
    weight (rest points moved by :meth:`~jaxelastic.mesh.Mesh.with_points` inside jit that
    invert or collapse a cell: outside jit that is refused before, naming the cells).
    One reduction over the weights; sharded meshes (zero-weight padding) are not checked."""
    mesh = pot.mesh
    if getattr(mesh, "halo", None) is not None:
        return res
    ok = jnp.all(lax.stop_gradient(mesh.weights) > 0)
    return res._replace(status=jnp.where(ok, res.status, Status.INVERTED).astype(res.status.dtype))


def _reverse(solver: Newton, lstate, adj: ImplicitAdjoint, pot, bc, x0) -> Solution:
    stop = lax.stop_gradient
    res = _flag_rest_shape(pot, minimize(solver, lstate, stop(pot), stop(bc), stop(x0)))
    return _attach_reverse(solver, lstate, adj, pot, bc, res)


def _attach_reverse(solver: Newton, lstate, adj: ImplicitAdjoint, pot, bc, res) -> Solution:
    x = checkpoint_name(res.x, X_STAR)
    status = checkpoint_name(res.status, X_STAR)
    # x* minimises the potential with its terms at the stiffness the solve adapted to
    x = _attach_fn(solver, adj)(solved_potential(pot, res), bc, x, status, lstate)
    return res._replace(x=x, status=status)


def _zero_tangent(a):
    return jnp.zeros_like(a) if _is_float(a) else _float0_like(a)


@functools.partial(jax.jit, static_argnums=(0, 1))
def _tangent(solver: Newton, adj: ImplicitAdjoint, pot, bc, res: Solution, lstate, pot_dot, bc_dot):
    """``ẋ`` of x* (one tangent solve, transposable; NaN if anything failed)."""
    x = res.x
    fm = (~bc.mask).astype(x.dtype)
    follower = not is_conservative(pot.pressure)
    system = exact_system(solved_potential(pot, res), x, bc.mask, exact_tangent=follower)

    def g_free(p):  # at the stiffness the solve adapted to
        return fm * pot_mod.gradient(solved_potential(p, res), x)

    _, g_dot = jax.jvp(g_free, (pot,), (pot_dot,))  # (∂g_f/∂θ)·θ̇
    v_dot = (1.0 - fm) * bc_dot.values  # ẋ_D = v̇_D
    rhs = -(g_dot + fm * system.H(v_dot))

    def solve(_, b):  # not differentiated: only linear in b, NaN if it failed
        if follower:
            y, ok = _nonsymmetric_ff(solver, lstate, adj, system, b, transpose=False)
        else:
            y, ok = _solve_ff(solver, lstate, adj, system, b)
        return jnp.where(ok, y, jnp.nan)

    def transpose_solve(_, b):  # (a follower load's J_ffᵀ, for reverse over forward)
        y, ok = _nonsymmetric_ff(solver, lstate, adj, system, b, transpose=True)
        return jnp.where(ok, y, jnp.nan)

    if follower:
        y = lax.custom_linear_solve(system.A, rhs, solve, transpose_solve=transpose_solve)
    else:
        y = lax.custom_linear_solve(system.A, rhs, solve, symmetric=True)
    # multiplying by 1 or NaN keeps the tangent linear (and so transposable)
    scale = jnp.where(res.status == Status.SUCCESS, 1.0, jnp.nan).astype(x.dtype)
    return scale * (fm * y + v_dot)


@functools.lru_cache(maxsize=64)
def _forward_fn(solver: Newton, adj: ImplicitAdjoint):
    """Forward-mode rule: ``K_ff ẋ_f = −(∂g_f/∂θ)·θ̇ − K_fD v̇_D``, ``ẋ_D = v̇_D``."""

    @jax.custom_jvp
    def solve_fn(pot, bc, x0, lstate):
        return _flag_rest_shape(pot, minimize(solver, lstate, pot, bc, x0))

    @solve_fn.defjvp
    def jvp(primals, tangents):
        pot, bc, x0, lstate = primals
        pot_dot, bc_dot, _, _ = tangents
        res = solve_fn(pot, bc, x0, lstate)
        x_dot = _tangent(solver, adj, pot, bc, res, lstate, pot_dot, bc_dot)
        res_dot = jax.tree_util.tree_map(_zero_tangent, res)._replace(x=x_dot)
        return res, res_dot

    return solve_fn


@functools.lru_cache(maxsize=64)
def _forward_attach_fn(solver: Newton, adj: ImplicitAdjoint):
    """Forward-mode rule of :func:`differentiable_solution` (the tangent of
    :func:`_forward_fn` at a given solution)."""

    @jax.custom_jvp
    def attach(pot, bc, res, lstate):
        return res

    @attach.defjvp
    def jvp(primals, tangents):
        pot, bc, res, lstate = primals
        pot_dot, bc_dot, _, _ = tangents
        x_dot = _tangent(solver, adj, pot, bc, res, lstate, pot_dot, bc_dot)
        res_dot = jax.tree_util.tree_map(_zero_tangent, res)._replace(x=x_dot)
        return res, res_dot

    return attach


def differentiable_solution(
    solver: Newton, lstate: LinearState, adj: ImplicitAdjoint, pot: Potential, bc: Dirichlet, res
) -> Solution:
    """``res``, a solve of ``pot`` and ``bc`` found without derivatives (e.g. the last
    sub-step of a continuation, or a Newton solve on ``lax.stop_gradient`` inputs), with
    implicit derivatives of ``res.x`` with respect to ``pot`` and ``bc.values``, as
    :func:`differentiable_minimize` would give them, without solving again.

    ``res.status`` says whether ``res.x`` is an equilibrium of ``pot`` (not SUCCESS: the
    derivatives are NaN); ``res.stats`` must hold what
    :func:`~jaxelastic.solvers.newton.solved_potential` reads for ``pot``'s adaptive terms
    (nothing for a potential without contact). Pure and jit-able."""
    res = jax.tree_util.tree_map(lax.stop_gradient, res)
    if adj.mode == "reverse":
        return _attach_reverse(solver, lstate, adj, pot, bc, res)
    return _forward_attach_fn(solver, adj)(pot, bc, res, lstate)


def differentiable_minimize(
    solver: Newton, lstate: LinearState, adj: ImplicitAdjoint, pot: Potential, bc: Dirichlet, x0
) -> Solution:
    """:func:`~jaxelastic.solvers.newton.minimize` with implicit derivatives of ``x`` (the
    body of :func:`jaxelastic.solve`; ``solver.linear`` resolved, ``lstate`` its state).
    Pure and jit-able."""
    if adj.mode == "reverse":
        return _reverse(solver, lstate, adj, pot, bc, x0)
    return _forward_fn(solver, adj)(pot, bc, x0, lstate)


def check_finite_gradients(grads) -> None:
    """Raise :class:`GradientError` if any floating leaf of ``grads`` is not finite."""
    leaves = [
        leaf
        for leaf in jax.tree_util.tree_leaves(grads)
        if hasattr(leaf, "dtype") and _is_float(leaf)
    ]
    if any(not bool(jnp.all(jnp.isfinite(leaf))) for leaf in leaves):
        raise GradientError(
            "gradient through an equilibrium solve is not finite: the forward Newton solve "
            "or the adjoint linear solve did not converge (check the Solution status)"
        )


def value_and_grad(fun: Callable, argnums=0, has_aux: bool = False, jit: bool = True):
    """Host-level ``jax.value_and_grad`` that raises :class:`GradientError` when a gradient
    is non-finite (an equilibrium solve inside ``fun`` failed) instead of returning it."""
    vg = jax.value_and_grad(fun, argnums=argnums, has_aux=has_aux)
    if jit:
        vg = jax.jit(vg)

    @functools.wraps(fun)
    def wrapped(*args, **kw):
        out = vg(*args, **kw)
        check_finite_gradients(out[1])
        return out

    return wrapped
