"""Differentiable static equilibrium by the implicit function theorem.

:func:`equilibrium` returns the Newton solution ``x*(θ)`` of ``min_x Π(x; θ)`` subject to
``x_D = bc.values_D`` and is differentiable in reverse mode with respect to everything in
the :class:`~jaxelastic.potential.Potential` (material parameters — shared scalars or
per-cell fields —, ``f_ext``, masses, …) and in the Dirichlet values ``bc.values``.

The backward pass never differentiates the Newton iterations. At the solution the free
residual vanishes, ``g_f(x*, θ) = 0``, so with ``K = ∂²Π/∂x²`` (symmetric)::

    K_ff λ = x̄_f                        (one adjoint solve)
    θ̄      = −(∂g_f/∂θ)ᵀ λ               (jax.vjp of the free-dof gradient)
    v̄_D    = x̄_D − (K λ)_D               (Dirichlet values; λ is zero on prescribed dofs)

The adjoint system is solved by matrix-free PCG on the exact Hessian (element Hessians
at x*, block-Jacobi preconditioned, relative tolerance ``AdjointSettings.rtol``), or — when
the forward solve was given a :class:`~jaxelastic.solvers.host.HostLinearSolver` — by host
PCG on the assembled K(x*) preconditioned by the factorisation (or AMG hierarchy) the last
Newton step left behind (:meth:`~jaxelastic.solvers.host.HostLinearSolver.adjoint`): that
Hessian is within ``O(‖x* − x_{k−1}‖)`` of K(x*), so a few iterations replace a new
factorisation. The in-jit PCG then only certifies the residual.

Failure is loud: if the forward Newton solve did not converge (status ≠ SUCCESS) or the
adjoint solve did not converge, *every* floating-point cotangent is NaN; the host-level
helpers (:func:`value_and_grad`, :func:`fit`) check for that and raise
:class:`GradientError`. Gradients are never silently computed at a non-equilibrium point.

Forward mode (``jax.jvp``/``jax.jacfwd``): ``equilibrium(..., mode="forward")`` is a
``jax.custom_jvp`` whose rule solves the tangent system (same solvers, NaN on failure)::

    K_ff ẋ_f = −(∂g_f/∂θ)·θ̇ − K_fD v̇_D,   ẋ_D = v̇_D

through ``lax.custom_linear_solve(symmetric=True)``. We chose this over ``lax.custom_root``
(which would re-derive the tangent system from a residual function and hide the Dirichlet
split and failure flag) because the linear solve is transposable: the same function also
supports reverse mode, where JAX transposes the tangent solve into the adjoint solve. The
default ``mode="reverse"`` keeps the leaner ``jax.custom_vjp`` (nothing beyond ``x*`` is
computed in the forward pass).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.ad_checkpoint import checkpoint_name

from . import potential as pot_mod
from .loads import Dirichlet
from .potential import Potential
from .solvers.linear import block_jacobi, cg
from .solvers.newton import NewtonResult, NewtonSettings, Status, make_linear, newton

__all__ = [
    "MODES",
    "X_STAR",
    "AdjointSettings",
    "GradientError",
    "equilibrium",
    "equilibrium_result",
    "value_and_grad",
]


class GradientError(RuntimeError):
    """A gradient through an equilibrium solve is not valid (forward or adjoint solve failed)."""


class AdjointSettings(NamedTuple):
    """Static settings of the adjoint (and tangent) solve (hashable).

    A gradient ``θ̄ = −(∂g_f/∂θ)ᵀλ`` is far less sensitive to the adjoint residual than λ
    itself. Measured on the 5,184-tet 3D neo-Hookean cantilever of ``scripts/bench_fit.py``
    (matrix-free PCG adjoint, d loss/d(E, ν)): relative deviation from the rtol = 1e-12
    gradient 2e-12 at rtol = 1e-10, 7e-12 at 1e-8, 1.5e-8 at 1e-6; fourth-order central
    differences agree with all of them to 1.4e-8 (their own truncation error). The default
    1e-10 keeps two orders of magnitude of margin below the ≤ 1e-6 gradient-accuracy goal
    for per-cell fields as well (tests/test_fitting.py, tests/test_implicit.py).

    Attributes:
        rtol: relative residual tolerance of the adjoint PCG (``‖r‖ ≤ rtol·‖x̄_f‖``).
        max_iter: PCG iteration cap.
    """

    rtol: float = 1e-10
    max_iter: int = 20000


DEFAULT_ADJOINT = AdjointSettings()


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


def _hessian_operator(pot: Potential, x, Ke):
    """Exact Hessian matvec at x (element Hessians + lumped mass; HVP if stiffness damping)."""
    if pot.stiffness_damping is not None:
        return lambda v: pot_mod.hessian_vp(pot, x, v)

    def H(v):
        return pot_mod.element_hessian_vp(pot, Ke, v)

    return H


def _operators(pot: Potential, x, mask):
    """Exact Hessian pieces at x: element Hessians, H, the Dirichlet-masked operator
    ``A = P_f H P_f + P_D`` and the block-Jacobi preconditioner of ``A``."""
    free = ~mask
    fm = free.astype(x.dtype)
    Ke = pot_mod.elastic_element_hessians(pot, x, project=False)
    H = _hessian_operator(pot, x, Ke)

    def A(v):
        return fm * H(fm * v) + (1.0 - fm) * v

    M = block_jacobi(pot_mod.node_hessian_blocks(pot, Ke), free)
    return Ke, H, A, M


def _solve_ff(pot: Potential, x, mask, rhs, linear, adj: AdjointSettings, ops):
    """Solve ``K_ff y = rhs_f`` (y = 0 on prescribed dofs) with the operators ``ops`` of
    :func:`_operators`. Returns ``(y, converged)``."""
    Ke, H, A, M = ops
    fm = (~mask).astype(x.dtype)
    b = fm * rhs
    bn = jnp.sqrt(jnp.sum(b * b))
    if linear is None:
        y0 = jnp.zeros_like(b)
    else:
        # host PCG on the assembled exact Hessian, preconditioned by the factorisation (or
        # AMG hierarchy) of the last Newton step (refactorised only if that stalls); the
        # block-Jacobi PCG below then only certifies the residual with JAX's own operator
        md = pot_mod._mass_diag(pot)
        md = jnp.zeros(x.shape[:1], x.dtype) if md is None else md
        shapes = (
            jax.ShapeDtypeStruct(x.shape, x.dtype),
            jax.ShapeDtypeStruct((), jnp.int32),
            jax.ShapeDtypeStruct((), jnp.bool_),
        )
        y0, _, _ = jax.pure_callback(
            linear.adjoint,
            shapes,
            Ke,
            md,
            b,
            jnp.asarray(adj.rtol, x.dtype),
            vmap_method="sequential",  # jacfwd/jacrev: one host solve per column
        )
        y0 = jnp.where(jnp.all(jnp.isfinite(y0)), fm * y0, 0.0)
    r0 = b - A(y0)
    res = cg(A, r0, M, tol=adj.rtol * bn, max_iter=adj.max_iter)
    y = fm * (y0 + res.x)
    ok = (res.status == 0) | (bn == 0)
    return y, ok & jnp.all(jnp.isfinite(y))


def _adjoint_solve(pot: Potential, x, mask, rhs, linear, adj: AdjointSettings):
    """Solve ``K_ff λ = rhs_f`` (λ = 0 on prescribed dofs). Returns (λ, H, converged)."""
    ops = _operators(pot, x, mask)
    lam, ok = _solve_ff(pot, x, mask, rhs, linear, adj, ops)
    return lam, ops[1], ok


X_STAR = "jaxelastic.x_star"
"""``jax.ad_checkpoint.checkpoint_name`` of the Newton solution and status inside
:func:`equilibrium` (reverse mode): a ``jax.checkpoint`` policy saving these names
(``save_only_these_names(X_STAR)``) never re-runs a Newton solve when rematerialising."""


@functools.cache
def _attach_fn(linear, adj: AdjointSettings):
    """``attach(pot, bc, x*, status) = x*`` with the implicit-function-theorem VJP."""

    @jax.custom_vjp
    def attach(pot, bc, x, status):
        return x

    def fwd(pot, bc, x, status):
        return x, (pot, bc, x, status)

    def bwd(saved, xbar):
        pot, bc, x, status = saved
        mask = bc.mask
        fm = (~mask).astype(x.dtype)
        lam, H, adj_ok = _adjoint_solve(pot, x, mask, xbar, linear, adj)
        ok = (status == Status.SUCCESS) & adj_ok

        def g_free(p):
            return fm * pot_mod.gradient(p, x)

        _, vjp = jax.vjp(g_free, pot)
        (pot_bar,) = vjp(-lam)
        vals_bar = jnp.where(mask, xbar - H(lam), 0.0)
        bc_bar = Dirichlet(mask=_float0_like(mask), values=vals_bar)
        pot_bar = _nan_unless(ok, pot_bar)
        bc_bar = _nan_unless(ok, bc_bar)
        return pot_bar, bc_bar, jnp.zeros_like(x), _float0_like(status)

    attach.defvjp(fwd, bwd)
    return attach


@functools.cache
def _equilibrium_fn(settings: NewtonSettings, linear, adj: AdjointSettings):
    """Reverse mode: Newton on stopped inputs, then :func:`_attach_fn` (custom VJP)."""
    attach = _attach_fn(linear, adj)

    def solve_fn(pot, x0, bc):
        stop = lax.stop_gradient
        res = newton(stop(pot), stop(x0), stop(bc), settings, linear)
        x = checkpoint_name(res.x, X_STAR)
        status = checkpoint_name(res.status, X_STAR)
        x = attach(pot, bc, x, status)
        return res._replace(x=x, status=status, wall_time=jnp.asarray(jnp.nan, x0.dtype))

    return solve_fn


def _zero_tangent(a):
    """Zero tangent of an output leaf (float0 for integer leaves)."""
    if _is_float(a):
        return jnp.zeros_like(a)
    return _float0_like(a)


@functools.cache
def _equilibrium_jvp_fn(settings: NewtonSettings, linear, adj: AdjointSettings):
    """Forward-mode rule: ``K_ff ẋ_f = −(∂g_f/∂θ)·θ̇ − K_fD v̇_D``, ``ẋ_D = v̇_D``.

    The tangent solve is a ``lax.custom_linear_solve`` with ``symmetric=True``, so JAX can
    transpose it: reverse mode over this rule (``jax.grad``) is the same adjoint solve.
    """

    @jax.custom_jvp
    def solve_fn(pot, x0, bc):
        res = newton(pot, x0, bc, settings, linear)
        return res._replace(wall_time=jnp.asarray(jnp.nan, x0.dtype))

    @solve_fn.defjvp
    def jvp(primals, tangents):
        pot, x0, bc = primals
        pot_dot, _, bc_dot = tangents
        res = solve_fn(pot, x0, bc)
        x = res.x
        mask = bc.mask
        fm = (~mask).astype(x.dtype)
        ops = _operators(pot, x, mask)
        H, A = ops[1], ops[2]

        def g_free(p):
            return fm * pot_mod.gradient(p, x)

        _, g_dot = jax.jvp(g_free, (pot,), (pot_dot,))  # (∂g_f/∂θ)·θ̇
        v_dot = (1.0 - fm) * bc_dot.values  # ẋ_D = v̇_D
        rhs = -(g_dot + fm * H(v_dot))

        def solve(_, b):  # not differentiated: only linear in b, NaN if it failed
            y, ok = _solve_ff(pot, x, mask, b, linear, adj, ops)
            return jnp.where(ok, y, jnp.nan)

        y = lax.custom_linear_solve(A, rhs, solve, symmetric=True)
        # multiplying by 1 or NaN keeps the tangent linear (and so transposable)
        scale = jnp.where(res.status == Status.SUCCESS, 1.0, jnp.nan).astype(x.dtype)
        x_dot = scale * (fm * y + v_dot)
        res_dot = jax.tree_util.tree_map(_zero_tangent, res)._replace(x=x_dot)
        return res, res_dot

    return solve_fn


MODES = ("reverse", "forward")


def equilibrium_result(
    pot: Potential,
    bc: Dirichlet,
    x0: jax.Array | None = None,
    settings: NewtonSettings = NewtonSettings(),
    linear=None,
    adjoint: AdjointSettings = DEFAULT_ADJOINT,
    mode: str = "reverse",
) -> NewtonResult:
    """Like :func:`equilibrium` but returns the whole :class:`NewtonResult` (status,
    iterations, …); only ``.x`` carries derivatives. Pure and jit-compatible."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if x0 is None:
        x0 = pot.mesh.points
    if isinstance(linear, str):
        linear = make_linear(pot.mesh, bc, linear)
    make = _equilibrium_fn if mode == "reverse" else _equilibrium_jvp_fn
    return make(settings, linear, adjoint)(pot, jnp.asarray(x0), bc)


def equilibrium(
    pot: Potential,
    bc: Dirichlet,
    x0: jax.Array | None = None,
    settings: NewtonSettings = NewtonSettings(),
    linear=None,
    adjoint: AdjointSettings = DEFAULT_ADJOINT,
    mode: str = "reverse",
) -> jax.Array:
    """Differentiable static equilibrium ``x*`` ``(n_nodes, dim)`` (pure, jit-compatible).

    Differentiable with respect to ``pot`` (all floating leaves: material parameters,
    ``f_ext``, …) and ``bc.values`` by the implicit function theorem (one linear solve with
    the Hessian at ``x*``). The derivative with respect to ``x0`` is zero. If the forward
    Newton solve (or the adjoint/tangent solve) failed, all derivatives are NaN.

    Args:
        pot: the potential; bc: Dirichlet data; x0: initial guess (default: rest shape).
        settings: Newton settings (use a tight ``rtol``, e.g. 1e-10, for accurate gradients).
        linear: None (matrix-free PCG forward and adjoint), a HostLinearSolver, or a
            string for :func:`~jaxelastic.solvers.newton.make_linear` (outside jit only).
        adjoint: :class:`AdjointSettings` (also used for the tangent solve).
        mode: ``"reverse"`` (default): a ``jax.custom_vjp``, reverse mode only (``grad``,
            ``vjp``, ``jacrev``). ``"forward"``: a ``jax.custom_jvp`` whose tangent solve is
            a transposable ``lax.custom_linear_solve``: ``jvp``/``jacfwd`` *and* reverse
            mode (JAX transposes the tangent solve into the same adjoint solve), at the
            price of computing the Hessian at ``x*`` in the forward pass.
    """
    return equilibrium_result(pot, bc, x0, settings, linear, adjoint, mode).x


def _check_finite_grads(grads):
    leaves = [
        leaf
        for leaf in jax.tree_util.tree_leaves(grads)
        if hasattr(leaf, "dtype") and _is_float(leaf)
    ]
    if any(not bool(jnp.all(jnp.isfinite(leaf))) for leaf in leaves):
        raise GradientError(
            "gradient through an equilibrium solve is not finite: the forward Newton solve "
            "or the adjoint linear solve did not converge (check the NewtonResult status)"
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
        _check_finite_grads(out[1])
        return out

    return wrapped
