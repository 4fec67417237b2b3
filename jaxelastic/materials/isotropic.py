"""Isotropic hyperelastic laws of Lamé parameters: ψ(F, params) → scalar.

Linear, St. Venant–Kirchhoff, corotated, fixed corotated, ARAP, neo-Hookean and stable
neo-Hookean (the table of them is :data:`~jaxelastic.materials.registry.BUILTIN`), and the
isochoric neo-Hookean of the JAX-FEM twist (:func:`isochoric_neo_hookean`, whose ``lam``
slot carries the bulk modulus). The rubber and soft-tissue families live in
:mod:`~jaxelastic.materials.rubber` and :mod:`~jaxelastic.materials.fibres`.

A material is nothing but a function of one unbatched deformation gradient ``F`` of shape
``(d, d)`` (d = 2 or 3) and a parameter pytree. Every derived quantity (P, forces, HVP,
element Hessians) is obtained by JAX transformations; any user function with the same
signature works everywhere a built-in does.

Units: ψ is energy per unit rest measure (Pa = J/m³ in 3D, J/m² per unit thickness in 2D);
μ and λ are in Pa.

All built-ins take :class:`~jaxelastic.materials.parameters.Lame` parameters and satisfy
ψ(I) = 0, P(I) = 0, and linearise at F = I to isotropic linear elasticity with the same
(μ, λ) — except ARAP, whose linearisation is the ν = 0 (λ = 0) material. Stable
neo-Hookean is shifted by a constant so that ψ(I) = 0 (the published forms have
ψ(I) = μ²/(2λ′) resp. that minus ``μ′/2·ln 4``); the shift changes no derivative.

Behaviour on inverted elements (J ≤ 0): ``neo_hookean`` and ``isochoric_neo_hookean``
return ``+inf`` (their energy is undefined there; solvers detect and report it); StVK is
finite but has zero energy at every reflection; the corotated family and stable neo-Hookean
are finite and push back toward J > 0.

``psi.defined_inverted = True`` marks the laws that are finite at J ≤ 0 (linear, StVK, the
corotated family, ARAP, stable neo-Hookean): a solution with an inverted cell is then
reported with a warning (``stats["min_J"]``); for every other ψ, user laws included unless
they carry the mark, it is the failure ``Status.INVERTED``
(:mod:`jaxelastic.solvers.newton`).
"""

from __future__ import annotations

import jax.numpy as jnp

from ..mechanics.kinematics import det, green_strain, small_strain, trace_S
from .parameters import Lame

__all__ = [
    "linear",
    "stvk",
    "corotated",
    "neo_hookean",
    "stable_neo_hookean",
    "stable_neo_hookean_log",
    "fixed_corotated",
    "arap",
    "isochoric_neo_hookean",
]


def linear(F, params: Lame):
    """Linear elasticity ``ψ = μ‖ε‖² + λ/2·tr²ε``, ``ε = ½(F+Fᵀ) − I``.

    Not rotation invariant. Sifakis & Barbič, *FEM Simulation of 3D Deformable Solids*
    (SIGGRAPH 2012 course notes), §3.2, eq. (3.3).
    """
    eps = small_strain(F)
    tr = jnp.trace(eps)
    return params.mu * jnp.sum(eps * eps) + 0.5 * params.lam * tr * tr


linear.is_quadratic = True  # ψ quadratic in F: Newton takes one exact step (solvers.newton)


def stvk(F, params: Lame):
    """St. Venant–Kirchhoff ``ψ = μ‖E‖² + λ/2·tr²E``, ``E = ½(FᵀF − I)``.

    Softens under compression and has zero energy at every reflection.
    Sifakis & Barbič 2012, §3.3, eq. (3.4).
    """
    E = green_strain(F)
    tr = jnp.trace(E)
    return params.mu * jnp.sum(E * E) + 0.5 * params.lam * tr * tr


def corotated(F, params: Lame):
    """Corotated linear elasticity ``ψ = μ‖S − I‖² + λ/2·tr²(S − I)``, ``F = R·S``.

    With the rotation-variant polar decomposition (signed singular values) it resists
    inversion. Written as ``μ(I_C − 2 tr S + d) + λ/2 (tr S − d)²``.
    Sifakis & Barbič 2012, §5.2, eq. (5.5); McAdams et al. 2011.
    """
    d = F.shape[0]
    trS = trace_S(F)
    IC = jnp.sum(F * F)
    return params.mu * (IC - 2.0 * trS + d) + 0.5 * params.lam * (trS - d) ** 2


def fixed_corotated(F, params: Lame):
    """Fixed corotated ``ψ = μ Σ(σᵢ − 1)² + λ/2 (J − 1)²`` (signed σ̂).

    Stomakhin, Howes, Schroeder & Teran, *Energetically consistent invertible
    elasticity*, SCA 2012, eq. (4). Written as ``μ(I_C − 2 tr S + d) + λ/2 (J − 1)²``.
    """
    d = F.shape[0]
    J = det(F)
    IC = jnp.sum(F * F)
    return params.mu * (IC - 2.0 * trace_S(F) + d) + 0.5 * params.lam * (J - 1.0) ** 2


def arap(F, params: Lame):
    """As-rigid-as-possible ``ψ = μ‖F − R‖² = μ Σ(σᵢ − 1)²`` (λ is ignored; ν = 0).

    Sorkine & Alexa, *As-rigid-as-possible surface modeling*, SGP 2007; as an elastic
    energy: Kim & Eberle, *Dynamic Deformables* (SIGGRAPH 2022 course), §5.
    """
    d = F.shape[0]
    IC = jnp.sum(F * F)
    return params.mu * (IC - 2.0 * trace_S(F) + d)


def _safe_log_pos(J):
    ok = J > 0
    return ok, jnp.log(jnp.where(ok, J, 1.0))


def neo_hookean(F, params: Lame):
    """Compressible neo-Hookean ``ψ = μ/2 (I_C − d) − μ ln J + λ/2 ln²J``.

    Undefined for J ≤ 0: returns ``+inf`` there (solvers treat that as a barrier and report
    inverted elements). In 2D with the 3D λ this is exactly the plane-strain model.
    Bonet & Wood, *Nonlinear Continuum Mechanics for FEA* (2nd ed., 2008), eq. (6.27);
    Sifakis & Barbič 2012, §3.4, eq. (3.6).
    """
    d = F.shape[0]
    J = det(F)
    ok, logJ = _safe_log_pos(J)
    IC = jnp.sum(F * F)
    psi = 0.5 * params.mu * (IC - d) - params.mu * logJ + 0.5 * params.lam * logJ**2
    return jnp.where(ok, psi, jnp.inf)


def stable_neo_hookean(F, params: Lame):
    """Stable neo-Hookean, production form, shifted so ψ(I) = 0.

    ``ψ = μ/2 (I_C − d) + λ′/2 (J − α)² − μ²/(2λ′)``, ``λ′ = λ + μ``, ``α = 1 + μ/λ′``.
    Defined for all F (finite under inversion). Note: without the log term it has a
    (non-physical) stationary point at total collapse F = 0.
    Kim & Eberle, *Dynamic Deformables* (SIGGRAPH 2022 course), §7.3 (eq. 7.13 and the
    "production" Lamé remapping of Smith, de Goes & Kim 2018, §3.4).
    """
    d = F.shape[0]
    lam_p = params.lam + params.mu
    alpha = 1.0 + params.mu / lam_p
    J = det(F)
    IC = jnp.sum(F * F)
    return 0.5 * params.mu * (IC - d) + 0.5 * lam_p * (J - alpha) ** 2 - 0.5 * params.mu**2 / lam_p


def stable_neo_hookean_log(F, params: Lame):
    """Stable neo-Hookean with the log term (3D only), shifted so ψ(I) = 0.

    ``ψ = μ′/2 (I_C − 3) + λ′/2 (J − α)² − μ′/2 ln(I_C + 1) + c``, with the Lamé
    remapping ``μ′ = 4μ/3``, ``λ′ = λ + 5μ/6``, ``α = 1 + 3μ′/(4λ′)`` and
    ``c = μ′/2 ln 4 − λ′/2 (1 − α)²``. The log term removes the collapsed stationary state.
    Smith, de Goes & Kim, *Stable Neo-Hookean Flesh Simulation*, ACM TOG 37(2), 2018,
    eqs. (14)–(18).
    """
    if F.shape != (3, 3):
        raise ValueError("stable_neo_hookean_log is defined in 3D only (F must be 3x3)")
    mu_p = 4.0 * params.mu / 3.0
    lam_p = params.lam + 5.0 * params.mu / 6.0
    alpha = 1.0 + 3.0 * mu_p / (4.0 * lam_p)
    J = det(F)
    IC = jnp.sum(F * F)
    c = 0.5 * mu_p * jnp.log(4.0) - 0.5 * lam_p * (1.0 - alpha) ** 2
    return (
        0.5 * mu_p * (IC - 3.0)
        + 0.5 * lam_p * (J - alpha) ** 2
        - 0.5 * mu_p * jnp.log(IC + 1.0)
        + c
    )


def isochoric_neo_hookean(F, params: Lame):
    """Isochoric neo-Hookean ``ψ = μ/2 (J^(−2/d)·tr(FᵀF) − d) + κ/2 (J − 1)²``.

    The hyperelasticity demo of JAX-FEM (the "twist" benchmark). ``params.mu`` is the
    shear modulus μ and ``params.lam`` carries the **bulk modulus** κ (not Lamé's λ).
    Undefined for J ≤ 0: returns ``+inf`` there, like the built-in neo-Hookean.
    """
    d = F.shape[0]
    J = det(F)
    ok = J > 0
    Js = jnp.where(ok, J, 1.0)
    IC = jnp.sum(F * F)
    psi = 0.5 * params.mu * (Js ** (-2.0 / d) * IC - d) + 0.5 * params.lam * (J - 1.0) ** 2
    return jnp.where(ok, psi, jnp.inf)


# finite (defined) at J ≤ 0: an inverted cell is a warning, not a failed solve
linear.defined_inverted = True
stvk.defined_inverted = True
corotated.defined_inverted = True
fixed_corotated.defined_inverted = True
arap.defined_inverted = True
stable_neo_hookean.defined_inverted = True
stable_neo_hookean_log.defined_inverted = True
