"""Hand-derived first Piola–Kirchhoff stresses and the five-step force recipe.

These exist **only to cross-check autodiff** (``first_piola(psi)``): they are written
independently from the closed forms of the literature, not derived from the ψ code.

* P formulas: Sifakis & Barbič, *FEM Simulation of 3D Deformable Solids* (SIGGRAPH 2012
  course notes), §3 (linear, StVK, neo-Hookean) and §5 (corotated); Stomakhin et al. 2012
  (fixed corotated); Kim & Eberle 2022, §7 (stable neo-Hookean); Smith, de Goes & Kim 2018
  (stable neo-Hookean with log term).
* Five-step recipe (Sifakis & Barbič 2012, §4.4, Algorithm 1): ``Ds``, ``F = Ds·Dm⁻¹``,
  ``P(F)``, ``H = −W·P·Dm⁻ᵀ``; the columns of H are the forces on nodes 1..d and
  ``f₀ = −Σ columns``, accumulated per vertex.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .kinematics import cofactor, det, polar

__all__ = [
    "P_linear",
    "P_stvk",
    "P_corotated",
    "P_neo_hookean",
    "P_fixed_corotated",
    "P_stable_neo_hookean",
    "P_stable_neo_hookean_log",
    "P_arap",
    "HAND_P",
    "five_step_forces",
]


def _I(F):
    return jnp.eye(F.shape[0], dtype=F.dtype)


def P_linear(F, p):
    """``P = 2μ ε + λ tr(ε) I``, ε = ½(F+Fᵀ) − I."""
    eps = 0.5 * (F + F.T) - _I(F)
    return 2.0 * p.mu * eps + p.lam * jnp.trace(eps) * _I(F)


def P_stvk(F, p):
    """``P = F(2μE + λ tr(E) I)``, E = ½(FᵀF − I)."""
    E = 0.5 * (F.T @ F - _I(F))
    return F @ (2.0 * p.mu * E + p.lam * jnp.trace(E) * _I(F))


def P_corotated(F, p):
    """``P = R(2μ(S − I) + λ tr(S − I) I)`` with the rotation-variant polar F = RS."""
    R, S = polar(F)
    return R @ (2.0 * p.mu * (S - _I(F)) + p.lam * jnp.trace(S - _I(F)) * _I(F))


def P_fixed_corotated(F, p):
    """``P = 2μ(F − R) + λ(J − 1) cof F``."""
    R, _ = polar(F)
    return 2.0 * p.mu * (F - R) + p.lam * (det(F) - 1.0) * cofactor(F)


def P_arap(F, p):
    """``P = 2μ(F − R)``."""
    R, _ = polar(F)
    return 2.0 * p.mu * (F - R)


def P_neo_hookean(F, p):
    """``P = μ(F − F⁻ᵀ) + λ ln J F⁻ᵀ`` (J > 0)."""
    FinvT = jnp.linalg.inv(F).T
    return p.mu * (F - FinvT) + p.lam * jnp.log(det(F)) * FinvT


def P_stable_neo_hookean(F, p):
    """``P = μF + λ′(J − α) cof F``, λ′ = λ + μ, α = 1 + μ/λ′."""
    lam_p = p.lam + p.mu
    alpha = 1.0 + p.mu / lam_p
    return p.mu * F + lam_p * (det(F) - alpha) * cofactor(F)


def P_stable_neo_hookean_log(F, p):
    """``P = μ′(1 − 1/(I_C + 1))F + λ′(J − α) cof F`` (3D)."""
    mu_p = 4.0 * p.mu / 3.0
    lam_p = p.lam + 5.0 * p.mu / 6.0
    alpha = 1.0 + 3.0 * mu_p / (4.0 * lam_p)
    IC = jnp.sum(F * F)
    return mu_p * (1.0 - 1.0 / (IC + 1.0)) * F + lam_p * (det(F) - alpha) * cofactor(F)


HAND_P = {
    "linear": P_linear,
    "stvk": P_stvk,
    "corotated": P_corotated,
    "neo_hookean": P_neo_hookean,
    "fixed_corotated": P_fixed_corotated,
    "stable_neo_hookean": P_stable_neo_hookean,
    "stable_neo_hookean_log": P_stable_neo_hookean_log,
    "arap": P_arap,
}
"""Built-in model name → hand-derived P(F, params)."""


def five_step_forces(P_fn, x: jax.Array, mesh, params) -> jax.Array:
    """Nodal forces by the lecture notes' recipe with a hand-derived P (P1 meshes only).

    Args:
        P_fn: ``P(F, params)`` for one F (e.g. :data:`HAND_P` ``["neo_hookean"]``).
        x: ``(n_nodes, d)`` positions; mesh: a P1 mesh; params: shared (scalar) pytree.

    Returns:
        ``(n_nodes, d)`` forces, accumulated with a scatter-add per vertex.
    """
    cells = mesh.cells
    Dm_inv = mesh.Dm_inv  # (c, d, d)
    W = mesh.volumes  # (c,)
    xe = x[cells]
    Ds = jnp.swapaxes(xe[:, 1:, :] - xe[:, :1, :], 1, 2)  # (c, d, d): columns x_i − x_0
    F = Ds @ Dm_inv
    P = jax.vmap(P_fn, in_axes=(0, None))(F, params)
    H = -W[:, None, None] * P @ jnp.swapaxes(Dm_inv, 1, 2)  # (c, d, d)
    f_nodes = jnp.swapaxes(H, 1, 2)  # row i = force on local node i+1
    f0 = -f_nodes.sum(axis=1)
    fe = jnp.concatenate([f0[:, None, :], f_nodes], axis=1)  # (c, d+1, d)
    return jnp.zeros_like(x).at[cells.reshape(-1)].add(fe.reshape(-1, x.shape[1]))
