"""Spectral functions of ``C = FᵀF`` with finite derivatives at repeated principal stretches.

For a ``(n, n)`` matrix F with ``C = FᵀF = V diag(c) Vᵀ`` (``c = λ²``, the squared
principal stretches) and a scalar function ``h(c, a)`` (``a`` a scalar parameter, e.g. an
Ogden exponent):

* :func:`stretch_sum` ``Σ_i h(c_i, a)`` — a symmetric function of the eigenvalues of C;
* :func:`stretch_matrix` ``V diag(h(c, a)) Vᵀ`` — the isotropic matrix function of C.

Both are evaluated from an SVD of F (``eigh`` of FᵀF would square the condition number and
lose relative accuracy at small stretches). The derivatives of ``svd``/``eigh`` divide by
eigenvalue gaps and are NaN (or inf) when two eigenvalues coincide — at the rest state
``C = I`` and in uniaxial or equibiaxial stretch, the states every rubber test visits. Both
functions carry a ``jax.custom_jvp``:

* ``d Σ h(c_i) = ⟨V diag(∂h/∂c) Vᵀ, dC⟩ + Σ ∂h/∂a · da`` — a matrix function again;
* ``d(V diag(h) Vᵀ) = V (Γ ∘ (Vᵀ dC V)) Vᵀ + V diag(∂h/∂a) Vᵀ da`` with ``dC = Fᵀ dF +
  dFᵀ F`` and the Daleckii–Krein divided differences ``Γ_ij = (h(c_i) − h(c_j))/(c_i −
  c_j)``, replaced by ``∂h/∂c`` at the midpoint when ``|c_i − c_j| ≤ 1e-5·max(1, |c_i|,
  |c_j|)`` (Daleckii & Krein 1965, *AMS Transl.* 47:1; Bhatia, *Matrix Analysis*, 1997,
  Thm. V.3.3). The threshold balances the round-off of the quotient (≈ ε/1e-5 ≈ 2e-11)
  against the midpoint error (≈ 1e-10·|h‴|).

So ψ written with :func:`stretch_sum` has a finite gradient, Hessian and HVP in F (and
mixed derivatives in ``a`` of every order), repeated stretches included. Third derivatives
in F differentiate the SVD again and are not finite at repeated stretches (no solver or fit
here needs them).

``h`` must be a hashable, jnp-traceable scalar function ``h(c, a) -> scalar`` (a module-level
function); its derivatives are built once per ``h`` with ``jax.grad`` and cached.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp

__all__ = ["stretch_sum", "stretch_matrix", "power"]

_CLOSE = 1e-5  # relative eigenvalue gap below which Γ_ij uses the midpoint derivative


def power(c, a):
    """``h(c, a) = c^a`` (c > 0): with :func:`stretch_sum`, ``Σ c_i^a = tr(C^a)``."""
    return c**a


@functools.lru_cache(maxsize=64)  # bounded: keyed by user functions
def _d_c(h: Callable) -> Callable:
    """``∂h/∂c`` as a (cached, hence hashable and stable) scalar function."""
    return jax.grad(h, argnums=0)


@functools.lru_cache(maxsize=64)  # bounded: keyed by user functions
def _d_a(h: Callable) -> Callable:
    """``∂h/∂a`` as a (cached, hence hashable and stable) scalar function."""
    return jax.grad(h, argnums=1)


def _on_eigenvalues(h, c, a):
    """``h`` applied to every eigenvalue ``c`` ``(n,)`` at the scalar ``a``."""
    return jax.vmap(h, in_axes=(0, None))(c, a)


def _divided_differences(h, c, a):
    """Daleckii–Krein matrix ``Γ_ij`` ``(n, n)`` of ``h(·, a)`` on the eigenvalues ``c``."""
    hc = _on_eigenvalues(h, c, a)
    ci, cj = c[:, None], c[None, :]
    gap = ci - cj
    scale = jnp.maximum(1.0, jnp.maximum(jnp.abs(ci), jnp.abs(cj)))
    close = jnp.abs(gap) <= _CLOSE * scale
    quotient = (hc[:, None] - hc[None, :]) / jnp.where(close, 1.0, gap)
    mid = 0.5 * (ci + cj)
    n = c.shape[0]
    slope = jax.vmap(_d_c(h), in_axes=(0, None))(mid.reshape(-1), a).reshape(n, n)
    return jnp.where(close, slope, quotient)


def _matrix_jvp(h, c, V, a, dC):
    """``V diag(h(c)) Vᵀ`` and its Daleckii–Krein derivative along the symmetric ``dC``."""
    a_ = jnp.asarray(a, c.dtype)
    M = (V * _on_eigenvalues(h, c, a_)[None, :]) @ V.T
    G = _divided_differences(h, c, a_)
    return M, V @ (G * (V.T @ dC @ V)) @ V.T


def _right_singular(F):
    """``(c, V)`` of ``C = FᵀF`` from the SVD of F: ``c = σ²``, V the right singular vectors.

    Small stretches keep their relative accuracy (``eigh`` of FᵀF would square the
    condition number: σ = 1e-3 has a relative error ≈ 1e-10 in c).
    """
    _, s, Vt = jnp.linalg.svd(F)
    return s * s, Vt.T


@functools.partial(jax.custom_jvp, nondiff_argnums=(2,))
def stretch_sum(F: jax.Array, a, h: Callable) -> jax.Array:
    """``Σ_i h(λ_i², a)`` over the principal stretches λ_i (singular values) of F.

    Evaluated from an SVD of F for accuracy at small stretches. Gradient
    ``∂/∂F = 2F·V diag(∂h/∂c) Vᵀ``; Hessian by Daleckii–Krein on ``C = FᵀF`` (finite at
    repeated stretches).

    Args:
        F: ``(n, n)`` matrix; a: scalar parameter of ``h``; h: ``h(c, a)`` (static).
    """
    c, _ = _right_singular(F)
    return jnp.sum(_on_eigenvalues(h, c, jnp.asarray(a, c.dtype)))


@stretch_sum.defjvp
def _stretch_sum_jvp(h, primals, tangents):
    F, a = primals
    dF, da = tangents
    y = stretch_sum(F, a, h)
    M = stretch_matrix(F, a, _d_c(h))  # ∂y/∂C
    dy = 2.0 * jnp.sum((F @ M) * dF) + stretch_sum(F, a, _d_a(h)) * da
    return y, dy


@functools.partial(jax.custom_jvp, nondiff_argnums=(2,))
def stretch_matrix(F: jax.Array, a, h: Callable) -> jax.Array:
    """``V diag(h(λ², a)) Vᵀ`` — the matrix function of ``C = FᵀF`` — from an SVD of F."""
    c, V = _right_singular(F)
    hc = _on_eigenvalues(h, c, jnp.asarray(a, c.dtype))
    return (V * hc[None, :]) @ V.T


@stretch_matrix.defjvp
def _stretch_matrix_jvp(h, primals, tangents):
    F, a = primals
    dF, da = tangents
    c, V = _right_singular(F)
    M, dM = _matrix_jvp(h, c, V, a, F.T @ dF + dF.T @ F)
    return M, dM + stretch_matrix(F, a, _d_a(h)) * da
