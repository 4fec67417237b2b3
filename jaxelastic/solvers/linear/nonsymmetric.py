"""The one GMRES loop of the library: restarted, right-preconditioned, under ``jit``.

:func:`gmres` solves a non-symmetric system ``A x = b`` (the true tangent of a follower
load, the tangent and adjoint solves of implicit differentiation through one) to a
residual tolerance, with an iteration count and an honest status: SUCCESS when the true
residual ``‖b − A x‖`` meets the tolerance, MAX_STEPS when the iteration cap is reached
first or a restart cycle makes no progress (stagnation), NONFINITE on a NaN. Right
preconditioning (``A M⁻¹ y = b``, ``x = M⁻¹ y``) makes the minimised residual the true one,
so the stopping test needs no unpreconditioned recomputation inside a cycle (Saad &
Schultz 1986; Saad, *Iterative Methods for Sparse Linear Systems*, 2nd ed. 2003, §9.3.2).
The Arnoldi basis is orthogonalised by classical Gram–Schmidt applied twice (one batched
product per pass, as accurate as modified Gram–Schmidt for this use: Giraud, Langou &
Rozložník 2005); the Hessenberg least-squares problem is reduced by Givens rotations.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
from jax import lax
from jax.scipy.linalg import solve_triangular

from ..results import Solution, Status

__all__ = ["gmres", "GMRES_RESTART"]

GMRES_RESTART = 30
"""Krylov dimension of one restart cycle (the basis holds ``GMRES_RESTART + 1`` vectors of
the size of ``b``). Preconditioned by the symmetric part's factorisation, a follower
tangent's GMRES converges within a few iterations, far inside one cycle."""


def _norm(a):
    return jnp.sqrt(jnp.sum(a * a))


def _cycle(A, M, b, x, r, tol, budget, m: int):
    """One restart cycle of at most ``min(m, budget)`` Arnoldi steps from ``x`` with its
    residual ``r = b − A x``: ``(x_new, steps)``."""
    beta = _norm(r)
    dtype = b.dtype
    V = jnp.zeros((m + 1, *b.shape), dtype).at[0].set(r / jnp.where(beta > 0, beta, 1.0))
    H = jnp.zeros((m + 1, m), dtype)  # the rotated Hessenberg matrix (upper triangular)
    cs = jnp.zeros((m,), dtype)
    sn = jnp.zeros((m,), dtype)
    g = jnp.zeros((m + 1,), dtype).at[0].set(beta)  # rotated right-hand side βe₁
    rows = jnp.arange(m + 1, dtype=jnp.int32)

    def project(V, w, j):  # one classical Gram–Schmidt pass against V[0 … j]
        h = jnp.where(rows <= j, jnp.tensordot(V, w, axes=w.ndim), 0.0)  # (m + 1,)
        return w - jnp.tensordot(h, V, axes=1), h

    def cond(c):
        j, _, _, _, _, g = c
        return (j < m) & (j < budget) & (jnp.abs(g[j]) > tol)

    def body(c):
        j, V, H, cs, sn, g = c
        w = A(M(V[j]))
        w, h1 = project(V, w, j)
        w, h2 = project(V, w, j)
        h = h1 + h2
        hn = _norm(w)
        V = V.at[j + 1].set(w / jnp.where(hn > 0, hn, 1.0))
        h = h.at[j + 1].set(hn)

        def rotate(i, h):  # the rotations of the earlier columns
            a, c_ = h[i], h[i + 1]
            new = h.at[i].set(cs[i] * a + sn[i] * c_).at[i + 1].set(-sn[i] * a + cs[i] * c_)
            return jnp.where(i < j, new, h)

        h = lax.fori_loop(jnp.int32(0), jnp.int32(m), rotate, h)
        a, c_ = h[j], h[j + 1]
        den = jnp.sqrt(a * a + c_ * c_)
        cj = jnp.where(den > 0, a / jnp.where(den > 0, den, 1.0), 1.0)
        sj = jnp.where(den > 0, c_ / jnp.where(den > 0, den, 1.0), 0.0)
        h = h.at[j].set(den).at[j + 1].set(0.0)
        g = g.at[j + 1].set(-sj * g[j]).at[j].set(cj * g[j])
        return j + 1, V, H.at[:, j].set(h), cs.at[j].set(cj), sn.at[j].set(sj), g

    j0 = jnp.asarray(0, jnp.int32)
    j, V, H, _, _, g = lax.while_loop(cond, body, (j0, V, H, cs, sn, g))
    # the upper-triangular least-squares system of the j steps taken (identity beyond)
    idx = jnp.arange(m, dtype=jnp.int32)
    used = idx < j
    R = jnp.where(used[:, None] & used[None, :], H[:m], 0.0)
    R = R + jnp.diag(jnp.where(used, 0.0, 1.0).astype(dtype))
    y = solve_triangular(R, jnp.where(used, g[:m], 0.0), lower=False)
    dx = M(jnp.tensordot(y, V[:m], axes=1))
    return x + dx, j


def gmres(
    A: Callable,
    b: jax.Array,
    M: Callable | None = None,
    *,
    tol,
    max_iter: int,
    restart: int = GMRES_RESTART,
    x0=None,
) -> Solution:
    """Solve ``A x = b`` by restarted, right-preconditioned GMRES (jit-compatible).

    Args:
        A: linear operator ``v ↦ A v`` on arrays shaped like ``b`` (any shape, e.g.
            ``(n_nodes, dim)``); need not be symmetric.
        b: right-hand side.
        M: preconditioner ``r ↦ M⁻¹ r`` (identity if None).
        tol: absolute tolerance on the true residual ``‖b − A x‖`` (scalar, may be traced).
        max_iter: cap on the total Arnoldi steps over all cycles (static).
        restart: Krylov dimension of a cycle (static).
        x0: initial guess (default zero).

    Returns:
        :class:`~jaxelastic.solvers.results.Solution` with ``status`` SUCCESS, MAX_STEPS
        (the cap, or a cycle that made no progress) or NONFINITE, and ``stats``
        ``iterations`` (Arnoldi steps), ``residual`` (the true residual norm at ``x``).
    """
    if M is None:
        M = lambda r: r
    m = int(max(1, min(restart, max_iter)))
    x = jnp.zeros_like(b) if x0 is None else x0
    rn = _norm(b) if x0 is None else _norm(b - A(x))
    zero = jnp.asarray(0, jnp.int32)

    r = b if x0 is None else b - A(x)

    def cond(c):
        _, _, rn, k, stuck = c
        return (rn > tol) & (k < jnp.int32(max_iter)) & ~stuck & jnp.isfinite(rn)

    def body(c):
        x, r, rn, k, _ = c
        x_new, j = _cycle(A, M, b, x, r, tol, jnp.int32(max_iter) - k, m)
        r_new = b - A(x_new)  # the true residual (the status is decided on it)
        rn_new = _norm(r_new)
        # a cycle that takes no step or does not reduce the residual is stagnation
        # (e.g. a tolerance below round-off): stop and say so
        # (a non-finite residual is kept: the status says NONFINITE)
        stuck = (j == 0) | ~(rn_new < rn)
        keep = stuck & ~(rn_new < rn) & jnp.isfinite(rn_new)
        pick = functools.partial(jnp.where, keep)
        return pick(x, x_new), pick(r, r_new), pick(rn, rn_new), k + j, stuck

    x, _, rn, k, _ = lax.while_loop(cond, body, (x, r, rn, zero, jnp.asarray(False)))
    st = jnp.where(rn <= tol, Status.SUCCESS, Status.MAX_STEPS)
    st = jnp.where(jnp.isfinite(rn) & jnp.all(jnp.isfinite(x)), st, Status.NONFINITE)
    return Solution(x=x, status=st.astype(jnp.int32), stats=dict(iterations=k, residual=rn))
