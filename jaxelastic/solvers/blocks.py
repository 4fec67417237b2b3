"""Inverses of batches of small symmetric positive definite blocks, without LAPACK.

Block-Jacobi and multilevel smoothers invert ``(n, b, b)`` diagonal blocks (b = 2, 3, 6,
12). jaxlib 0.10's batched LAPACK kernels (``cholesky``, ``inv``) split the batch over
XLA:CPU's intra-op thread pool and block on it, which deadlocks when a program runs on
several XLA:CPU devices of one process and the other devices hold the pool's threads in a
collective (measured: a sharded twist solve hung in ``dgetrf``). An unrolled Cholesky is
elementwise over the batch, so it runs anywhere (sharded, vmapped, float32) and, for
b ≤ 12, is as fast as the LAPACK call.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

__all__ = ["spd_block_inverse", "block_inverse_or_diagonal"]


def spd_block_inverse(B: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``(B⁻¹, ok)`` for symmetric blocks ``B`` of shape ``(n, b, b)``.

    ``ok`` (``(n,)`` bool) says the block is positive definite (every Cholesky pivot
    finite and > 0); where it is not, the returned inverse is meaningless (callers fall
    back, e.g. to ``1/|diag|``). Cost O(b³) elementwise operations per block, unrolled at
    trace time (b is static).
    """
    b = B.shape[-1]
    one = jnp.ones(B.shape[:-2], B.dtype)
    ok = jnp.ones(B.shape[:-2], bool)
    # the lower-triangular Cholesky factor, one array per entry
    L: list[list[Any]] = [[None] * b for _ in range(b)]
    for j in range(b):
        s = B[..., j, j]
        for k in range(j):
            s = s - L[j][k] * L[j][k]
        good = jnp.isfinite(s) & (s > 0)
        ok = ok & good
        ljj = jnp.sqrt(jnp.where(good, s, one))
        L[j][j] = ljj
        for i in range(j + 1, b):
            t = B[..., i, j]
            for k in range(j):
                t = t - L[i][k] * L[j][k]
            L[i][j] = t / ljj
    # W = L⁻¹ (lower triangular) by forward substitution, then B⁻¹ = Wᵀ W
    W: list[list[Any]] = [[None] * b for _ in range(b)]
    for j in range(b):
        W[j][j] = 1.0 / L[j][j]
        for i in range(j + 1, b):
            t = L[i][j] * W[j][j]
            for k in range(j + 1, i):
                t = t + L[i][k] * W[k][j]
            W[i][j] = -t / L[i][i]
    rows = []
    for r in range(b):
        row = []
        for c in range(b):
            acc = 0.0
            for k in range(max(r, c), b):
                acc = acc + W[k][r] * W[k][c]
            row.append(acc)
        rows.append(jnp.stack(row, axis=-1))
    return jnp.stack(rows, axis=-2), ok


def block_inverse_or_diagonal(B: jax.Array, lapack: bool = True) -> jax.Array:
    """Inverses of the symmetric blocks ``B`` ``(n, b, b)``; a block that is not positive
    definite falls back to ``diag(1/|B_ii|)`` (1 where ``B_ii = 0``).

    ``lapack=True``: Cholesky test + LAPACK ``inv`` (bit-identical in every compiled
    program); ``lapack=False``: :func:`spd_block_inverse` (no LAPACK call, as a sharded
    program on several XLA:CPU devices needs; equal to round-off).
    """
    eye = jnp.eye(B.shape[-1], dtype=B.dtype)[None]
    if lapack:
        L = jnp.linalg.cholesky(B)
        ok = jnp.all(jnp.isfinite(L), axis=(1, 2))
        inv = jnp.linalg.inv(jnp.where(ok[:, None, None], B, eye))
    else:
        inv, ok = spd_block_inverse(B)
    diag = jnp.abs(jnp.diagonal(B, axis1=1, axis2=2))
    diag = jnp.where(diag > 0, diag, 1.0)
    return jnp.where(ok[:, None, None], inv, eye / diag[:, :, None])
