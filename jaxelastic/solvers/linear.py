"""Matrix-free preconditioned conjugate gradients under ``jit``, and its preconditioners.

Operators act on ``(n_nodes, dim)`` arrays. CG stops on the residual (``‖r‖ ≤ tol``), at
``max_iter``, or on non-positive curvature ``pᵀAp ≤ 0`` (an indefinite Hessian far from
equilibrium): then it returns the last iterate, or the preconditioned steepest-descent
direction if that happens in the first iteration, and says so in its status.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

__all__ = [
    "CGResult",
    "CG_CONVERGED",
    "CG_MAX_ITER",
    "CG_NEGATIVE_CURVATURE",
    "cg",
    "block_jacobi",
    "jacobi",
]

CG_CONVERGED = 0
CG_MAX_ITER = 1
CG_NEGATIVE_CURVATURE = 2


class CGResult(NamedTuple):
    """Result of :func:`cg`: solution ``(n, d)``, iterations, status code, residual norm."""

    x: jax.Array
    iterations: jax.Array
    status: jax.Array
    residual: jax.Array


def _dot(a, b):
    return jnp.sum(a * b)


def cg(A, b, M=None, *, tol, max_iter: int) -> CGResult:
    """Solve ``A x = b`` for SPD ``A`` by preconditioned CG (jit-compatible).

    Args:
        A: linear operator ``v ↦ A v`` on arrays shaped like ``b``.
        b: right-hand side ``(n, d)``.
        M: preconditioner ``r ↦ M⁻¹ r`` (identity if None).
        tol: absolute residual tolerance (scalar, may be traced).
        max_iter: maximum iterations (static).
    """
    if M is None:
        M = lambda r: r
    x0 = jnp.zeros_like(b)
    r0 = b
    z0 = M(r0)
    p0 = z0
    rz0 = _dot(r0, z0)
    rn0 = jnp.sqrt(_dot(r0, r0))

    def cond(s):
        x, r, z, p, rz, rn, k, status = s
        return (status < 0) & (k < max_iter)

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
        beta = rz_new / jnp.where(rz == 0, 1.0, rz)
        p_new = z_new + beta * p
        # on negative curvature keep the previous iterate (or z0 at k == 0)
        x_keep = jnp.where(k == 0, z0, x)
        x_out = jnp.where(neg, x_keep, x_new)
        status_new = jnp.where(neg, CG_NEGATIVE_CURVATURE, jnp.where(rn_new <= tol, 0, -1))
        return (
            x_out,
            jnp.where(neg, r, r_new),
            z_new,
            p_new,
            rz_new,
            jnp.where(neg, rn, rn_new),
            k + 1,
            status_new,
        )

    init_status = jnp.where(rn0 <= tol, CG_CONVERGED, -1)
    s0 = (x0, r0, z0, p0, rz0, rn0, jnp.asarray(0), init_status)
    x, r, z, p, rz, rn, k, status = lax.while_loop(cond, body, s0)
    status = jnp.where(status < 0, CG_MAX_ITER, status)
    return CGResult(x=x, iterations=k, status=status, residual=rn)


def block_jacobi(blocks: jax.Array, free: jax.Array):
    """Node-block Jacobi preconditioner from ``(n, d, d)`` diagonal blocks.

    Prescribed dofs (``free == False``, shape ``(n, d)``) are decoupled (identity rows and
    columns). Blocks that are not positive definite fall back to ``|diag|`` (or 1).
    """
    d = blocks.shape[-1]
    eye = jnp.eye(d, dtype=blocks.dtype)[None]  # (1, d, d)
    fm = free.astype(blocks.dtype)
    B = blocks * fm[:, :, None] * fm[:, None, :] + eye * (1.0 - fm)[:, :, None]
    L = jnp.linalg.cholesky(B)
    ok = jnp.all(jnp.isfinite(L), axis=(1, 2))
    diag = jnp.abs(jnp.diagonal(B, axis1=1, axis2=2))
    diag = jnp.where(diag > 0, diag, 1.0)
    Binv = jnp.where(
        ok[:, None, None],
        jnp.linalg.inv(jnp.where(ok[:, None, None], B, eye)),
        eye / diag[:, :, None],
    )

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
