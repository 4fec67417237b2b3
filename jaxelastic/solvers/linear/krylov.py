"""The one conjugate-gradient loop of the library and the matrix-free :class:`CG` solver.

:func:`cg` runs under ``jit``/``vmap`` (``lax.while_loop``). It stops on the residual
(``‖r‖ ≤ tol``), at ``max_iter``, or on non-positive curvature ``pᵀAp ≤ 0`` (an indefinite
Hessian far from equilibrium): then it returns the last iterate, or the preconditioned
steepest-descent direction if that happens in the first iteration, and says so in its
status. Every other solver's Krylov iterations on the device are this loop.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
from jax import lax

from ...mechanics.potential import node_hessian_blocks
from ...parallel.sharding import is_sharded
from ..blocks import block_inverse_or_diagonal
from ..results import Solution, Status
from .protocol import LinearSolver
from .system import NewtonSystem

__all__ = ["cg", "block_jacobi", "jacobi", "CG"]


def _dot(a, b):
    return jnp.sum(a * b)


def cg(A: Callable, b: jax.Array, M: Callable | None = None, *, tol, max_iter: int, x0=None):
    """Solve ``A x = b`` for SPD ``A`` by preconditioned CG (jit- and vmap-compatible).

    Args:
        A: linear operator ``v ↦ A v`` on arrays shaped like ``b``.
        b: right-hand side (any shape, e.g. ``(n_nodes, dim)``).
        M: preconditioner ``r ↦ M⁻¹ r`` (identity if None).
        tol: absolute residual tolerance (scalar, may be traced).
        max_iter: maximum iterations (static).
        x0: initial guess (default zero).

    Returns:
        :class:`~jaxelastic.solvers.results.Solution` with ``status`` SUCCESS, MAX_STEPS or
        NEGATIVE_CURVATURE and ``stats`` ``iterations``, ``residual`` (recurrence norm).
    """
    if M is None:
        M = lambda r: r
    if x0 is None:
        x0, r0 = jnp.zeros_like(b), b
    else:
        r0 = b - A(x0)
    rn0 = jnp.sqrt(_dot(r0, r0))
    # already converged (e.g. the certifying PCG of a host adjoint): skip the
    # preconditioner, which for host back ends is a callback and a solve
    z0 = lax.cond(rn0 <= tol, jnp.zeros_like, M, r0)
    running = jnp.asarray(-1, jnp.int32)

    def cond(s):
        return (s[-1] < 0) & (s[-2] < max_iter)

    def body(s):
        x, r, z, p, rz, rn, k, status = s
        Ap = A(p)
        pAp = _dot(p, Ap)
        neg = ~(pAp > 0)
        alpha = rz / jnp.where(neg, 1.0, pAp)
        x_new = x + alpha * p
        r_new = r - alpha * Ap
        rn_new = jnp.sqrt(_dot(r_new, r_new))
        z_new = M(r_new)
        rz_new = _dot(r_new, z_new)
        p_new = z_new + rz_new / jnp.where(rz == 0, 1.0, rz) * p
        # on negative curvature keep the previous iterate (or z0 at k == 0)
        x_out = jnp.where(neg, jnp.where(k == 0, x0 + z0, x), x_new)
        st = jnp.where(neg, Status.NEGATIVE_CURVATURE, jnp.where(rn_new <= tol, 0, -1))
        return (
            x_out,
            jnp.where(neg, r, r_new),
            z_new,
            p_new,
            rz_new,
            jnp.where(neg, rn, rn_new),
            k + 1,
            st.astype(jnp.int32),
        )

    status0 = jnp.where(rn0 <= tol, jnp.int32(Status.SUCCESS), running)
    s0 = (x0, r0, z0, z0, _dot(r0, z0), rn0, jnp.asarray(0, jnp.int32), status0)
    x, _, _, _, _, rn, k, status = lax.while_loop(cond, body, s0)
    status = jnp.where(status < 0, jnp.int32(Status.MAX_STEPS), status)
    return Solution(x=x, status=status, stats=dict(iterations=k, residual=rn))


def block_jacobi(blocks: jax.Array, free: jax.Array, *, lapack: bool = True):
    """Node-block Jacobi preconditioner from ``(n, d, d)`` diagonal blocks.

    Prescribed dofs (``free == False``, shape ``(n, d)``) are decoupled (identity rows and
    columns). Blocks that are not positive definite fall back to ``|diag|`` (or 1).
    ``lapack=False`` inverts them with an unrolled Cholesky
    (:func:`~jaxelastic.solvers.blocks.spd_block_inverse`) instead of LAPACK, as a sharded
    program on several XLA:CPU devices must (jaxlib 0.10's batched LAPACK can deadlock
    there); the two agree to round-off, but only LAPACK gives bit-identical blocks in
    every compiled program.
    """
    d = blocks.shape[-1]
    eye = jnp.eye(d, dtype=blocks.dtype)[None]  # (1, d, d)
    fm = free.astype(blocks.dtype)
    B = blocks * fm[:, :, None] * fm[:, None, :] + eye * (1.0 - fm)[:, :, None]
    Binv = block_inverse_or_diagonal(B, lapack)

    def apply(r):
        return jnp.einsum("nij,nj->ni", Binv, r)

    return apply


def jacobi(blocks: jax.Array, free: jax.Array):
    """Point Jacobi preconditioner from the diagonals of the ``(n, d, d)`` node blocks."""
    diag = jnp.diagonal(blocks, axis1=1, axis2=2)
    diag = jnp.where(free & (diag > 0), diag, 1.0)
    inv = 1.0 / diag

    def apply(r):
        return inv * r

    return apply


@dataclasses.dataclass(frozen=True)
class CG(LinearSolver):
    """Matrix-free preconditioned CG under jit (vmap- and sharding-friendly).

    Attributes:
        preconditioner: ``"block_jacobi"`` (node blocks of the element Hessians),
            ``"jacobi"`` or ``"none"`` (then Newton with ``hessian="hvp"`` builds no element
            Hessian at all).
        max_iter: iteration cap per linear solve.
    """

    preconditioner: str = "block_jacobi"
    max_iter: int = 2000

    def __post_init__(self):
        if self.preconditioner not in ("block_jacobi", "jacobi", "none"):
            raise ValueError(
                "CG preconditioner must be 'block_jacobi', 'jacobi' or 'none', got "
                f"{self.preconditioner!r}"
            )
        if int(self.max_iter) < 1:
            raise ValueError(f"CG max_iter must be >= 1, got {self.max_iter!r}")

    @property
    def needs_element_hessians(self) -> bool:
        return self.preconditioner != "none"

    kind = "cg"
    shardable = True

    def _M(self, system: NewtonSystem, Ke, kind: str):
        if kind == "none" or Ke is None:
            return None
        blocks = node_hessian_blocks(system.pot, Ke)
        if kind == "jacobi":
            return jacobi(blocks, system.free)
        return block_jacobi(blocks, system.free, lapack=not is_sharded(system.pot.mesh))

    def symmetric_preconditioner(self, state, system: NewtonSystem, Ke, token):
        """The (block-)Jacobi preconditioner of ``Ke``'s node blocks (None for ``"none"``)."""
        return self._M(system, Ke, self.preconditioner), token

    def newton_step(self, state, system: NewtonSystem, A, Ke, rhs, tol, token) -> Solution:
        """Inexact solve of the Newton system to ``‖r‖ ≤ tol``."""
        return cg(A, rhs, self._M(system, Ke, self.preconditioner), tol=tol, max_iter=self.max_iter)

    def exact(self, state, system: NewtonSystem, b, rtol, max_iter: int) -> Solution:
        """Solve with the exact operator to ``‖r‖ ≤ rtol·‖b‖`` (adjoint/tangent systems):
        block-Jacobi PCG."""
        bn = jnp.sqrt(_dot(b, b))
        M = self._M(system, system.Ke, "block_jacobi")
        return cg(system.A, b, M, tol=rtol * bn, max_iter=max_iter)
