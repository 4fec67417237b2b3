"""Built-in hyperelastic materials: strain-energy densities ψ(F, params) → scalar.

The rubber and soft-tissue families (Mooney–Rivlin, Yeoh, Ogden, Gent, Arruda–Boyce,
Holzapfel–Gasser–Ogden) live in :mod:`jaxelastic.rubber` and :mod:`jaxelastic.fibres` and
are re-exported here with their parameter types (:data:`FAMILIES`, :data:`FAMILY_PARAMS`).

A material is nothing but a function of one unbatched deformation gradient ``F`` of shape
``(d, d)`` (d = 2 or 3) and a parameter pytree. Every derived quantity (P, forces, HVP,
element Hessians) is obtained by JAX transformations; any user function with the same
signature works everywhere a built-in does.

Units: ψ is energy per unit rest measure (Pa = J/m³ in 3D, J/m² per unit thickness in 2D);
μ and λ are in Pa.

All built-ins take :class:`Lame` parameters and satisfy ψ(I) = 0, P(I) = 0, and linearise
at F = I to isotropic linear elasticity with the same (μ, λ) — except ARAP, whose
linearisation is the ν = 0 (λ = 0) material. Stable neo-Hookean is shifted by a constant
so that ψ(I) = 0 (the published forms have ψ(I) = μ²/(2λ′) resp. that minus ``μ′/2·ln 4``);
the shift changes no derivative.

Behaviour on inverted elements (J ≤ 0): ``neo_hookean`` returns ``+inf`` (its energy is
undefined there; solvers detect and report it); StVK is finite but has zero energy at
every reflection; the corotated family and stable neo-Hookean are finite and push back
toward J > 0.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .fibres import HolzapfelGasserOgden as HolzapfelGasserOgden
from .fibres import fibre_pair as fibre_pair
from .fibres import holzapfel_gasser_ogden as holzapfel_gasser_ogden
from .fibres import holzapfel_gasser_ogden_params as holzapfel_gasser_ogden_params
from .fibres import per_cell_fibres as per_cell_fibres
from .mechanics.kinematics import det, green_strain, small_strain, trace_S
from .rubber import ArrudaBoyce as ArrudaBoyce
from .rubber import Gent as Gent
from .rubber import MooneyRivlin as MooneyRivlin
from .rubber import Ogden as Ogden
from .rubber import Yeoh as Yeoh
from .rubber import arruda_boyce as arruda_boyce
from .rubber import arruda_boyce_params as arruda_boyce_params
from .rubber import gent as gent
from .rubber import gent_params as gent_params
from .rubber import mooney_rivlin as mooney_rivlin
from .rubber import mooney_rivlin_params as mooney_rivlin_params
from .rubber import ogden as ogden
from .rubber import ogden_params as ogden_params
from .rubber import yeoh as yeoh
from .rubber import yeoh_params as yeoh_params

__all__ = [
    "Lame",
    "lame",
    "check_lame",
    "LAME_RATIO_MAX",
    "linear",
    "stvk",
    "corotated",
    "neo_hookean",
    "stable_neo_hookean",
    "stable_neo_hookean_log",
    "fixed_corotated",
    "arap",
    "BUILTIN",
    "MooneyRivlin",
    "mooney_rivlin",
    "mooney_rivlin_params",
    "Yeoh",
    "yeoh",
    "yeoh_params",
    "Ogden",
    "ogden",
    "ogden_params",
    "Gent",
    "gent",
    "gent_params",
    "ArrudaBoyce",
    "arruda_boyce",
    "arruda_boyce_params",
    "HolzapfelGasserOgden",
    "holzapfel_gasser_ogden",
    "holzapfel_gasser_ogden_params",
    "fibre_pair",
    "per_cell_fibres",
    "FAMILIES",
    "FAMILY_PARAMS",
]


class Lame(NamedTuple):
    """Lamé parameters, the parameter pytree of the built-in models.

    Attributes:
        mu: shear modulus μ [Pa]; scalar, or ``(n_cells,)`` for a per-cell field.
        lam: first Lamé parameter λ [Pa]; same shape convention.
    """

    mu: jax.Array | float
    lam: jax.Array | float


LAME_RATIO_MAX = 1e12
"""The largest λ/μ :func:`check_lame` accepts: ν = 0.5 − 5·10⁻¹³, beyond which float64
cannot resolve the shear response next to the volumetric one (the residual's round-off
floor exceeds the loads, and a solve would stop at it with a meaningless answer)."""


def check_lame(params: Lame, dim: int) -> None:
    """Refuse concrete Lamé parameters no elastic solid has, or float64 cannot resolve.

    Needs μ > 0 and a positive bulk modulus ``λ + 2μ/dim`` (stability of the linearised
    response), everything finite, and ``λ/μ ≤`` :data:`LAME_RATIO_MAX`. Traced parameters
    (inside ``jit``/``grad``) are not checked.

    Raises:
        ValueError: naming the parameter, the first offending cell and what to do.
    """
    try:
        mu = np.asarray(params.mu, dtype=np.float64)
        lam = np.asarray(params.lam, dtype=np.float64)
    except Exception:  # noqa: BLE001 — traced, or a global array another process holds
        return  # (multi-process sharding): not checked here
    mu, lam = np.broadcast_arrays(np.atleast_1d(mu), np.atleast_1d(lam))

    def where(bad) -> str:
        i = int(np.flatnonzero(bad.ravel())[0])
        return "" if bad.size == 1 else f" (at {int(bad.sum())} cell(s), first cell {i})"

    bad = ~(np.isfinite(mu) & np.isfinite(lam))
    if bad.any():
        raise ValueError(f"Lame parameters must be finite{where(bad)}")
    if (bad := mu <= 0).any():
        raise ValueError(
            f"shear modulus mu must be > 0{where(bad)}, got {mu.ravel()[bad.ravel()][0]!r}: "
            "build the parameters with je.Lame(*je.lame(E, nu))"
        )
    if (bad := lam + 2.0 * mu / dim <= 0).any():
        raise ValueError(
            f"the bulk modulus lam + 2 mu / {dim} must be > 0{where(bad)} (Poisson's ratio "
            "above -1): build the parameters with je.Lame(*je.lame(E, nu))"
        )
    if (bad := lam > LAME_RATIO_MAX * mu).any():
        raise ValueError(
            f"lam / mu exceeds {LAME_RATIO_MAX:.0e}{where(bad)} (Poisson's ratio within 5e-13 "
            "of 0.5): float64 cannot resolve the shear response next to the volumetric one. "
            "Use nu <= 0.4999999 with an F-bar or P2 element for near-incompressibility"
        )


def lame(E, nu, dim: int = 3, plane: str = "strain") -> tuple:
    """Lamé parameters (μ, λ) from Young's modulus E [Pa] and Poisson's ratio ν.

    ``μ = E/(2(1+ν))``; in 3D and in 2D plane strain ``λ = Eν/((1+ν)(1−2ν))``; in 2D plane
    stress ``λ = Eν/((1+ν)(1−ν))`` (the effective 2D λ* of a thin plate). Works on traced
    arrays (differentiable in E, ν); concrete values are validated.

    Args:
        E: Young's modulus, > 0.
        nu: Poisson's ratio in (−1, 0.5).
        dim: 2 or 3.
        plane: ``"strain"`` or ``"stress"`` (used only when ``dim == 2``).

    Raises:
        ValueError: E ≤ 0, ν outside (−1, 0.5), NaN/inf, bad ``dim`` or ``plane``.
    """
    if dim not in (2, 3):
        raise ValueError(f"dim must be 2 or 3, got {dim!r}")
    if plane not in ("strain", "stress"):
        raise ValueError(f"plane must be 'strain' or 'stress', got {plane!r}")
    E_c, nu_c = _concrete(E, "Young's modulus E"), _concrete(nu, "Poisson's ratio nu")
    if E_c is not None:
        if not np.all(np.isfinite(E_c)):
            raise ValueError(f"Young's modulus E must be finite, got {E!r}")
        if np.any(E_c <= 0):
            raise ValueError(f"Young's modulus E must be > 0, got {E!r}")
    if nu_c is not None:
        if not np.all(np.isfinite(nu_c)):
            raise ValueError(f"Poisson's ratio nu must be finite, got {nu!r}")
        if np.any(nu_c <= -1.0) or np.any(nu_c >= 0.5):
            raise ValueError(f"Poisson's ratio nu must lie in (-1, 0.5), got {nu!r}")
    mu = E / (2.0 * (1.0 + nu))
    if dim == 2 and plane == "stress":
        lam = E * nu / ((1.0 + nu) * (1.0 - nu))
    else:
        lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return mu, lam


def _concrete(v, name: str = "value"):
    """NumPy value of ``v``, or None when it is a tracer (validated only when concrete)."""
    try:
        a = np.asarray(v)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return None
    if a.dtype.kind not in "biuf":
        raise TypeError(f"{name} must be a real number or an array of them, got {v!r}")
    return a


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


BUILTIN = {
    "linear": linear,
    "stvk": stvk,
    "corotated": corotated,
    "neo_hookean": neo_hookean,
    "stable_neo_hookean": stable_neo_hookean,
    "stable_neo_hookean_log": stable_neo_hookean_log,
    "fixed_corotated": fixed_corotated,
    "arap": arap,
}
"""Name → ψ of every built-in model (a read-only mapping by convention)."""


FAMILIES = {
    "mooney_rivlin": mooney_rivlin,
    "yeoh": yeoh,
    "ogden": ogden,
    "gent": gent,
    "arruda_boyce": arruda_boyce,
    "holzapfel_gasser_ogden": holzapfel_gasser_ogden,
}
"""Name → ψ of the rubber and soft-tissue models (:mod:`jaxelastic.rubber`,
:mod:`jaxelastic.fibres`), each with its own parameter type (not :class:`Lame`)."""

FAMILY_PARAMS = {
    "mooney_rivlin": mooney_rivlin_params,
    "yeoh": yeoh_params,
    "ogden": ogden_params,
    "gent": gent_params,
    "arruda_boyce": arruda_boyce_params,
    "holzapfel_gasser_ogden": holzapfel_gasser_ogden_params,
}
"""Name → ``<name>_params(**overrides)``, the documented typical parameters of each of
:data:`FAMILIES` (their types expose ``shear_modulus`` and ``bulk_modulus``)."""
