"""Hand-derived first Piola–Kirchhoff stresses and the five-step force recipe.

These exist **only to cross-check autodiff** (``first_piola(psi)``): they are written
independently from the closed forms of the literature, not derived from the ψ code.

* P formulas: Sifakis & Barbič, *FEM Simulation of 3D Deformable Solids* (SIGGRAPH 2012
  course notes), §3 (linear, StVK, neo-Hookean) and §5 (corotated); Stomakhin et al. 2012
  (fixed corotated); Kim & Eberle 2022, §7 (stable neo-Hookean); Smith, de Goes & Kim 2018
  (stable neo-Hookean with log term).
* Rubber and tissue (:mod:`jaxelastic.materials.rubber`, :mod:`jaxelastic.materials.fibres`,
  :mod:`jaxelastic.materials.cardiac`: Guccione's ``S = ∂ψ/∂E``, ``P = F S``):
  P written from the invariant derivatives ``∂Ī₁/∂F = J^{-2/3}(2F − ⅔ I₁ F⁻ᵀ)``,
  ``∂Ī₂/∂F = J^{-4/3}(2(I₁F − FC) − ⁴⁄₃ I₂ F⁻ᵀ)``, ``∂Ī₄/∂F = J^{-2/3}(2F a⊗a − ⅔ I₄ F⁻ᵀ)``
  and ``∂U/∂F = κ/2 (J² − 1) F⁻ᵀ`` (Holzapfel 2000, *Nonlinear Solid Mechanics*,
  §6.4–6.5); Ogden in principal stretches from an SVD, ``P = U diag(∂ψ/∂λ_i) Vᵀ`` (Ogden
  1984, *Non-linear Elastic Deformations*, §4.3). 2D is plane strain: the (2, 2) block of
  the 3D P of ``diag(F, 1)``.
* Five-step recipe (Sifakis & Barbič 2012, §4.4, Algorithm 1): ``Ds``, ``F = Ds·Dm⁻¹``,
  ``P(F)``, ``H = −W·P·Dm⁻ᵀ``; the columns of H are the forces on nodes 1..d and
  ``f₀ = −Σ columns``, accumulated per vertex.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..mechanics.checks import cell_params_axes
from ..mechanics.kinematics import cofactor, det, polar
from .rubber import ARRUDA_BOYCE_COEFFS, embed_plane_strain

__all__ = [
    "P_linear",
    "P_stvk",
    "P_corotated",
    "P_neo_hookean",
    "P_fixed_corotated",
    "P_stable_neo_hookean",
    "P_stable_neo_hookean_log",
    "P_arap",
    "P_mooney_rivlin",
    "P_yeoh",
    "P_ogden",
    "P_gent",
    "P_arruda_boyce",
    "P_holzapfel_gasser_ogden",
    "P_guccione",
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


def _iso_parts(F):
    """3D embedding and the pieces of the invariant derivatives: ``(F3, J, FinvT, I1b,
    dI1b, I2b, dI2b)``, with ``dI1b = ∂Ī₁/∂F`` and ``dI2b = ∂Ī₂/∂F`` ``(3, 3)``."""
    F3 = embed_plane_strain(F)
    J = det(F3)
    FinvT = jnp.linalg.inv(F3).T
    C = F3.T @ F3
    I1 = jnp.trace(C)
    I2 = 0.5 * (I1 * I1 - jnp.trace(C @ C))
    j23, j43 = J ** (-2.0 / 3.0), J ** (-4.0 / 3.0)
    dI1b = j23 * (2.0 * F3 - (2.0 / 3.0) * I1 * FinvT)
    dI2b = j43 * (2.0 * (I1 * F3 - F3 @ C) - (4.0 / 3.0) * I2 * FinvT)
    return F3, J, FinvT, j23 * I1, dI1b, j43 * I2, dI2b


def _P_vol(J, FinvT, kappa):
    """``∂U/∂F = U′(J) J F⁻ᵀ = κ/2 (J² − 1) F⁻ᵀ`` for ``U = κ/4 (J² − 1 − 2 ln J)``."""
    return 0.5 * kappa * (J * J - 1.0) * FinvT


def _block(P3, F):
    d = F.shape[0]
    return P3[:d, :d]


def P_mooney_rivlin(F, p):
    """``P = c10 ∂Ī₁/∂F + c01 ∂Ī₂/∂F + κ/2 (J² − 1) F⁻ᵀ``."""
    _, J, FinvT, _, dI1b, _, dI2b = _iso_parts(F)
    return _block(p.c10 * dI1b + p.c01 * dI2b + _P_vol(J, FinvT, p.kappa), F)


def P_yeoh(F, p):
    """``P = (c10 + 2c20 x + 3c30 x²) ∂Ī₁/∂F + ∂U/∂F``, x = Ī₁ − 3."""
    _, J, FinvT, I1b, dI1b, _, _ = _iso_parts(F)
    x = I1b - 3.0
    w1 = p.c10 + 2.0 * p.c20 * x + 3.0 * p.c30 * x * x
    return _block(w1 * dI1b + _P_vol(J, FinvT, p.kappa), F)


def P_gent(F, p):
    """``P = μ/2 / (1 − (Ī₁ − 3)/J_m) ∂Ī₁/∂F + ∂U/∂F``."""
    _, J, FinvT, I1b, dI1b, _, _ = _iso_parts(F)
    w1 = 0.5 * p.mu / (1.0 - (I1b - 3.0) / p.Jm)
    return _block(w1 * dI1b + _P_vol(J, FinvT, p.kappa), F)


def P_arruda_boyce(F, p):
    """``P = μ Σ i α_i Ī₁^{i−1}/λ_m^{2i−2} ∂Ī₁/∂F + ∂U/∂F``."""
    _, J, FinvT, I1b, dI1b, _, _ = _iso_parts(F)
    lm2 = p.lambda_m**2
    w1 = sum(
        p.mu * i * a * I1b ** (i - 1) / lm2 ** (i - 1)
        for i, a in enumerate(ARRUDA_BOYCE_COEFFS, start=1)
    )
    return _block(w1 * dI1b + _P_vol(J, FinvT, p.kappa), F)


def P_ogden(F, p):
    """``P = U diag(∂ψ/∂λ_i) Vᵀ`` (SVD F = U diag(λ) Vᵀ, J > 0) with
    ``∂ψ/∂λ_i = Σ_p μ_p J^{-α_p/3} (λ_i^{α_p−1} − λ_i⁻¹/3 Σ_k λ_k^{α_p}) + κ/2 (J² − 1)/λ_i``."""
    F3 = embed_plane_strain(F)
    U, lam, Vt = jnp.linalg.svd(F3)
    J = jnp.prod(lam)
    dpsi = 0.5 * p.kappa * (J * J - 1.0) / lam
    for mu, a in ((p.mu1, p.alpha1), (p.mu2, p.alpha2), (p.mu3, p.alpha3)):
        dpsi = dpsi + mu * J ** (-a / 3.0) * (lam ** (a - 1.0) - jnp.sum(lam**a) / (3.0 * lam))
    return _block((U * dpsi[None, :]) @ Vt, F)


def P_holzapfel_gasser_ogden(F, p):
    """``P = μ/2 ∂Ī₁/∂F + ∂U/∂F + Σ_i k1 ⟨Ē_i⟩ exp(k2 Ē_i²) (κ ∂Ī₁/∂F + (1 − 3κ) ∂Ī₄ᵢ/∂F)``
    with ``∂Ī₄/∂F = J^{-2/3}(2 F a⊗a − ⅔ I₄ F⁻ᵀ)``."""
    F3, J, FinvT, I1b, dI1b, _, _ = _iso_parts(F)
    P = 0.5 * p.mu * dI1b + _P_vol(J, FinvT, p.bulk)
    k = p.kappa_dispersion
    for a0 in (p.a01, p.a02):
        a = jnp.asarray(a0)
        if a.shape == (2,):
            a = jnp.concatenate([a, jnp.zeros((1,), a.dtype)])
        a = a / jnp.linalg.norm(a)
        I4 = jnp.dot(F3 @ a, F3 @ a)
        dI4b = J ** (-2.0 / 3.0) * (2.0 * jnp.outer(F3 @ a, a) - (2.0 / 3.0) * I4 * FinvT)
        E = k * (I1b - 3.0) + (1.0 - 3.0 * k) * (J ** (-2.0 / 3.0) * I4 - 1.0)
        w = jnp.where(E > 0, p.k1 * E * jnp.exp(p.k2 * E * E), 0.0)
        P = P + w * (k * dI1b + (1.0 - 3.0 * k) * dI4b)
    return _block(P, F)


def P_guccione(F, p):
    """``P = F S + κ/2 (J² − 1) F⁻ᵀ`` with ``S = C e^Q R (B ∘ Ê) Rᵀ``, ``Ê = Rᵀ E R`` the
    Green–Lagrange strain in the orthonormal (f, s, n) basis R (columns; s Gram–Schmidt
    against f), B the exponents (b_f on ff; b_t on ss, nn, sn, ns; b_fs on fs, sf, fn, nf)
    and ``Q = Σ B_ij Ê_ij²`` (Guccione, McCulloch & Waldman 1991: ``S = ∂ψ/∂E``)."""
    F3 = embed_plane_strain(F)
    J = det(F3)
    FinvT = jnp.linalg.inv(F3).T

    def pad(a):
        a = jnp.asarray(a)
        return jnp.concatenate([a, jnp.zeros((1,), a.dtype)]) if a.shape == (2,) else a

    f = pad(p.f0) / jnp.linalg.norm(pad(p.f0))
    s = pad(p.s0) - jnp.dot(pad(p.s0), f) * f
    s = s / jnp.linalg.norm(s)
    R = jnp.stack([f, s, jnp.cross(f, s)], axis=1)
    E_loc = R.T @ (0.5 * (F3.T @ F3 - jnp.eye(3, dtype=F3.dtype))) @ R
    B = jnp.array([[p.bf, p.bfs, p.bfs], [p.bfs, p.bt, p.bt], [p.bfs, p.bt, p.bt]])
    Q = jnp.sum(B * E_loc * E_loc)
    S = p.C * jnp.exp(Q) * (R @ (B * E_loc) @ R.T)
    return _block(F3 @ S + _P_vol(J, FinvT, p.kappa), F)


HAND_P = {
    "linear": P_linear,
    "stvk": P_stvk,
    "corotated": P_corotated,
    "neo_hookean": P_neo_hookean,
    "fixed_corotated": P_fixed_corotated,
    "stable_neo_hookean": P_stable_neo_hookean,
    "stable_neo_hookean_log": P_stable_neo_hookean_log,
    "arap": P_arap,
    "mooney_rivlin": P_mooney_rivlin,
    "yeoh": P_yeoh,
    "ogden": P_ogden,
    "gent": P_gent,
    "arruda_boyce": P_arruda_boyce,
    "holzapfel_gasser_ogden": P_holzapfel_gasser_ogden,
    "guccione": P_guccione,
}
"""Built-in model name → hand-derived P(F, params)."""


def five_step_forces(P_fn, x: jax.Array, mesh, params) -> jax.Array:
    """Nodal forces by the lecture notes' recipe with a hand-derived P (P1 meshes only).

    Args:
        P_fn: ``P(F, params)`` for one F (e.g. :data:`HAND_P` ``["neo_hookean"]``).
        x: ``(n_nodes, d)`` positions; mesh: a P1 mesh; params: a pytree of shared
            (scalar) and per-cell (leading axis ``n_cells``) leaves, as for ``je.forces``.

    Returns:
        ``(n_nodes, d)`` forces, accumulated with a scatter-add per vertex.
    """
    cells = mesh.cells
    Dm_inv = mesh.Dm_inv  # (c, d, d)
    W = mesh.volumes  # (c,)
    xe = x[cells]
    Ds = jnp.swapaxes(xe[:, 1:, :] - xe[:, :1, :], 1, 2)  # (c, d, d): columns x_i − x_0
    F = Ds @ Dm_inv
    P = jax.vmap(P_fn, in_axes=(0, cell_params_axes(params, mesh.n_cells)))(F, params)
    H = -W[:, None, None] * P @ jnp.swapaxes(Dm_inv, 1, 2)  # (c, d, d)
    f_nodes = jnp.swapaxes(H, 1, 2)  # row i = force on local node i+1
    f0 = -f_nodes.sum(axis=1)
    fe = jnp.concatenate([f0[:, None, :], f_nodes], axis=1)  # (c, d+1, d)
    return jnp.zeros_like(x).at[cells.reshape(-1)].add(fe.reshape(-1, x.shape[1]))
