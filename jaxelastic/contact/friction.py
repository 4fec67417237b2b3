"""IPC's smoothed Coulomb friction with a lagged normal force and tangent basis.

Friction enters the potential as a dissipative pseudo-energy (Li et al. 2020, "Incremental
Potential Contact", ACM TOG 39(4), §5): for node a against obstacle o,

``D = Σ_{o,a} μ_o λ_oa f₀(‖u_oa‖)``,  ``u_oa = T_oaᵀ [(x_a − x_a^lag) − (c_o(t) − c_o(t^lag))]``

with the normal force ``λ_oa = κ |b'(d_oa)|`` [N] and the ``(dim, dim−1)`` tangent basis
``T_oa`` (orthonormal, ⊥ the SDF gradient) frozen at the lagged positions ``x^lag`` (the
start of the time or load step) and ``c_o`` the obstacle's prescribed translation.
``f₀`` is IPC's C¹ mollifier of ``y ↦ y`` with ``f₀' = f₁``:
``f₁(y) = −y²/ε² + 2y/ε`` for ``y < ε`` and 1 beyond, ``f₀(y) = −y³/(3ε²) + y²/ε + ε/3``
for ``y < ε`` and y beyond, so static friction is approximated by a stiff elastic response
up to a tangential slip ``ε`` [m] (``ε_v h`` in dynamics). The Hessian of ``f₀(‖u‖)`` has
eigenvalues ``f₁'(y) ≥ 0`` (along u) and ``f₁(y)/y ≥ 0`` (across): positive semidefinite.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

__all__ = ["f0", "f1", "tangent_basis", "FrictionLag", "friction_node_energy", "EPS_REL"]

EPS_REL = 1e-5
"""Default slip tolerance ε relative to the bounding-box diagonal in quasi-static steps."""


def f1(y: jax.Array, eps) -> jax.Array:
    """IPC's friction mollifier ``f₁(y)`` (1 for ``y ≥ ε``), y ≥ 0 [m], ε [m]."""
    s = y / eps
    return jnp.where(y < eps, -s * s + 2 * s, 1.0)


def f0(y2: jax.Array, eps) -> jax.Array:
    """``f₀`` [m] as a function of the squared slip ``y² = u·u`` [m²] (finite derivatives
    at u = 0): ``−y³/(3ε²) + y²/ε + ε/3`` for ``y < ε``, else y."""
    ok = y2 > 0
    y = jnp.where(ok, jnp.sqrt(jnp.where(ok, y2, 1.0)), 0.0)
    small = -(y2 * y) / (3 * eps * eps) + y2 / eps + eps / 3
    return jnp.where(y < eps, small, y)


def tangent_basis(n: jax.Array) -> jax.Array:
    """An orthonormal ``(dim, dim−1)`` basis of the plane ⊥ the unit normal ``n`` ``(dim,)``."""
    if n.shape[-1] == 2:
        return jnp.stack([-n[1], n[0]])[:, None]
    e = jnp.where(
        jnp.abs(n[0]) < 0.9, jnp.array([1.0, 0, 0], n.dtype), jnp.array([0, 1.0, 0], n.dtype)
    )
    t1 = jnp.cross(n, e)
    t1 = t1 / jnp.sqrt(jnp.sum(t1 * t1))
    t2 = jnp.cross(n, t1)
    return jnp.stack([t1, t2], axis=1)


@dataclasses.dataclass(frozen=True)
class FrictionLag:
    """The lagged friction data of one step (a pytree; every field a leaf).

    Attributes:
        x_lag: ``(m, dim)`` contact-node positions at the lag [m].
        offset_lag: ``(n_obs, dim)`` obstacle translations at the lag time [m].
        normal_force: ``(n_obs, m)`` lagged normal forces λ [N] (0 out of reach).
        basis: ``(n_obs, m, dim, dim−1)`` lagged tangent bases.
        eps: ``()`` slip tolerance ε [m].
    """

    x_lag: jax.Array
    offset_lag: jax.Array
    normal_force: jax.Array
    basis: jax.Array
    eps: jax.Array

    def replace(self, **kw) -> FrictionLag:
        return dataclasses.replace(self, **kw)


jax.tree_util.register_dataclass(
    FrictionLag,
    data_fields=["x_lag", "offset_lag", "normal_force", "basis", "eps"],
    meta_fields=[],
)


def friction_node_energy(xa, x_lag_a, lam_a, basis_a, mu, dc, eps) -> jax.Array:
    """Friction pseudo-energy [J] of one node against every obstacle.

    Args:
        xa, x_lag_a: ``(dim,)`` position now and at the lag [m]; lam_a: ``(n_obs,)`` lagged
        normal forces [N]; basis_a: ``(n_obs, dim, dim−1)``; mu: ``(n_obs,)`` friction
        coefficients; dc: ``(n_obs, dim)`` obstacle translations since the lag [m];
        eps: slip tolerance [m].
    """
    rel = (xa - x_lag_a)[None, :] - dc  # (n_obs, dim)
    u = jnp.einsum("oij,oi->oj", basis_a, rel)  # (n_obs, dim-1)
    return jnp.sum(mu * lam_a * f0(jnp.sum(u * u, axis=-1), eps))
