"""Fibre-reinforced soft tissue: the Holzapfel–Gasser–Ogden model with fibre dispersion.

``holzapfel_gasser_ogden(F, params)`` is a plain ψ for one unbatched F (``(3, 3)``, or
``(2, 2)`` in plane strain: embedded as ``diag(F, 1)``, see :mod:`jaxelastic.materials.rubber`). Two
fibre families with unit reference directions ``a01``, ``a02`` are part of the parameter
pytree, either shared (shape ``(3,)``, for a single-F call) or per cell (shape
``(n_cells, 3)``, the leading-axis convention of
:func:`jaxelastic.mechanics.checks.cell_params_axes`);
:func:`per_cell_fibres` broadcasts shared directions for use with a mesh. The directions
are material (reference) vectors: the deformation maps them to ``F a0`` automatically, so
rotating the mesh and the fibres together leaves the energy unchanged.

Units: μ, k1, bulk are stresses (defaults in **kPa**); k2, κ (dispersion) dimensionless.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from .rubber import embed_direction, modified_invariants, safe_state, volumetric

__all__ = [
    "HolzapfelGasserOgden",
    "holzapfel_gasser_ogden",
    "holzapfel_gasser_ogden_params",
    "fibre_pair",
    "fibre_strain",
    "per_cell_fibres",
]

Scalar = jax.Array | float


class HolzapfelGasserOgden(NamedTuple):
    """HGO constants and fibre directions.

    Attributes:
        mu: shear modulus of the neo-Hookean matrix (HGO's c) [stress].
        k1: fibre stiffness [stress], ≥ 0 (k1 = 0: the isotropic matrix alone).
        k2: fibre exponential stiffening [–], > 0.
        kappa_dispersion: fibre dispersion κ ∈ [0, 1/3] [–] (0: aligned fibres, 1/3:
            isotropic distribution; Gasser, Ogden & Holzapfel 2006).
        bulk: bulk modulus of the volumetric term [stress].
        a01, a02: reference directions of the two fibre families, ``(3,)`` (shared) or
            ``(n_cells, 3)``; normalised inside ψ (must be nonzero). In 2D a ``(2,)``
            direction is padded with a zero z component.

    The scalar fields may also be ``(n_cells,)`` per-cell fields.
    """

    mu: Scalar
    k1: Scalar
    k2: Scalar
    kappa_dispersion: Scalar
    bulk: Scalar
    a01: jax.Array
    a02: jax.Array

    def for_cells(self, n_cells: int) -> HolzapfelGasserOgden:
        """These parameters with shared ``(3,)`` directions broadcast to ``(n_cells, 3)``
        (:func:`per_cell_fibres`): :class:`~jaxelastic.mechanics.potential.Potential`
        calls it, so the documented ``holzapfel_gasser_ogden_params()`` works in a solve."""
        return per_cell_fibres(self, n_cells)

    @property
    def shear_modulus(self):
        """Initial shear modulus: the matrix μ (the fibres carry no load at F = I)."""
        return self.mu

    @property
    def bulk_modulus(self):
        """Initial bulk modulus."""
        return self.bulk


def _unit3(a) -> jax.Array:
    a = embed_direction(a, "a fibre direction")
    return a / jnp.sqrt(jnp.sum(a * a))


def fibre_strain(F3: jax.Array, J, a0, kappa, I1b):
    """``Ē = κ(Ī₁ − 3) + (1 − 3κ)(Ī₄ − 1)``, ``Ī₄ = J^{-2/3} a0·(FᵀF)a0`` (scalar, [–]).

    Args:
        F3: ``(3, 3)`` deformation gradient with ``J = det F3 > 0``; a0: ``(3,)`` or
            ``(2,)`` direction; kappa: dispersion; I1b: Ī₁ of F3.
    """
    a = _unit3(a0)
    Fa = F3 @ a
    I4b = J ** (-2.0 / 3.0) * jnp.sum(Fa * Fa)
    return kappa * (I1b - 3.0) + (1.0 - 3.0 * kappa) * (I4b - 1.0)


FIBRE_STRAIN_FLOOR = 16
"""A fibre strain ``Ē`` below this many ulps of 1 counts as unstretched: at F = I the unit
direction's rounding leaves ``Ī₄ − 1`` at ±1 ulp, which would switch the tension-only
fibres on (their tangent jumps by 2k1 at Ē = 0); the cut changes ψ by at most
``k1/2·(16 eps)²``, far below ψ's own round-off."""


def _fibre_energy(E, k1, k2):
    """``k1/(2k2) (exp(k2 ⟨E⟩²) − 1)`` with the Macaulay bracket ⟨E⟩ = max(E, 0)
    (``Ē`` within :data:`FIBRE_STRAIN_FLOOR` ulps of 0 counts as 0)."""
    tol = FIBRE_STRAIN_FLOOR * jnp.finfo(jnp.result_type(E)).eps
    Ep = jnp.where(E > tol, E, 0.0)
    return 0.5 * k1 / k2 * jnp.expm1(k2 * Ep * Ep)


def holzapfel_gasser_ogden(F: jax.Array, params: HolzapfelGasserOgden) -> jax.Array:
    """HGO with dispersion: ``ψ = μ/2 (Ī₁ − 3) + U(J) + Σ_{i=1,2} k1/(2k2) [exp(k2⟨Ē_i⟩²) − 1]``.

    ``Ē_i = κ(Ī₁ − 3) + (1 − 3κ)(Ī_{4,i} − 1)``, ``Ī_{4,i} = a0i · C̄ a0i``; the isochoric
    invariants of the decoupled form (Holzapfel, Gasser & Ogden 2000, *J. Elasticity* 61:1,
    §4, κ = 0; dispersion: Gasser, Ogden & Holzapfel 2006, *J. R. Soc. Interface* 3:15,
    §2); ``U(J) = bulk/4 (J² − 1 − 2 ln J)`` as in :mod:`jaxelastic.materials.rubber`.

    Tension only: a fibre family contributes only when ``Ē_i > 0`` (the Macaulay bracket;
    for κ = 0 that is exactly ``Ī₄ > 1``, fibres stretched). The switch is C¹: ψ and P are
    continuous across ``Ē_i = 0`` (the fibre term and its stress vanish there); the tangent
    stiffness jumps by ``2k1 (∂Ē_i/∂F)⊗(∂Ē_i/∂F)``, bounded, so Newton converges. Switching
    on ``Ī₄ > 1`` instead would make ψ jump whenever κ > 0. At F = I (Ē_i = 0) the fibres
    carry nothing: the linearisation is the matrix (μ, bulk).

    Known limitation of the decoupled form (Sansour 2008, *Eur. J. Mech. A* 27:28): with
    isochoric Ī₄ the fibres do not resist a purely volumetric stretch. Returns +inf for
    J ≤ 0. F: ``(d, d)``; ψ [stress].
    """
    ok, F3, J = safe_state(F)
    I1b, _ = modified_invariants(F3, J)
    psi = 0.5 * params.mu * (I1b - 3.0) + volumetric(J, params.bulk)
    for a0 in (params.a01, params.a02):
        E = fibre_strain(F3, J, a0, params.kappa_dispersion, I1b)
        psi = psi + _fibre_energy(E, params.k1, params.k2)
    return jnp.where(ok, psi, jnp.inf)


def fibre_pair(angle_deg: float, axis1=(1.0, 0.0, 0.0), axis2=(0.0, 1.0, 0.0)):
    """Two unit directions at ``±angle`` from ``axis1`` in the plane of ``axis1, axis2``.

    Returns:
        ``(a01, a02)``, each a ``(3,)`` array.
    """
    e1, e2 = jnp.asarray(axis1, float), jnp.asarray(axis2, float)
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    return c * e1 + s * e2, c * e1 - s * e2


def holzapfel_gasser_ogden_params(**overrides) -> HolzapfelGasserOgden:
    """HGO constants of the media of a rabbit carotid artery [kPa].

    ``mu = 3.0, k1 = 2.3632, k2 = 0.8393``, fibres at ±29.0° from the circumferential
    direction e1 in the (e1 = circumferential, e2 = axial) plane (Holzapfel, Gasser &
    Ogden 2000, §5); ``kappa_dispersion = 0`` (the 2000 model
    has none); ``bulk = 100 μ = 300`` (chosen for near-incompressibility, ν ≈ 0.495: the
    source is incompressible). Keyword arguments replace fields.
    """
    a01, a02 = fibre_pair(29.0)
    p = HolzapfelGasserOgden(3.0, 2.3632, 0.8393, 0.0, 300.0, a01, a02)
    return p._replace(**overrides)


def per_cell_fibres(params: HolzapfelGasserOgden, n_cells: int) -> HolzapfelGasserOgden:
    """``params`` with shared ``(3,)`` directions broadcast to ``(n_cells, 3)``.

    :func:`jaxelastic.mechanics.kernels.energy` treats a non-scalar leaf as a per-cell field, so a
    shared direction must be broadcast before a mesh-level call.
    """

    def cells(a):
        a = jnp.asarray(a)
        return jnp.broadcast_to(a, (n_cells, a.shape[-1])) if a.ndim == 1 else a

    return params._replace(a01=cells(params.a01), a02=cells(params.a02))
