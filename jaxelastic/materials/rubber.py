"""Rubber-like isotropic hyperelasticity: Mooney–Rivlin, Yeoh, Ogden, Gent, Arruda–Boyce.

Every model is a plain ``psi(F, params) -> scalar`` for one unbatched ``F``:

* 3D: ``F`` of shape ``(3, 3)``;
* 2D: ``F`` of shape ``(2, 2)`` is **plane strain**: it is embedded in 3D as
  ``diag(F, 1)`` (``F_zz = 1``) and the 3D energy is evaluated; the in-plane P is the
  ``(2, 2)`` block of the 3D P.

All use the **isochoric/volumetric split** of Flory (1961, *Trans. Faraday Soc.* 57:829),
``ψ = ψ_iso(C̄) + U(J)`` with ``C̄ = J^{-2/3} C``, ``C = FᵀF``, ``J = det F``, the modified
invariants ``Ī₁ = J^{-2/3} I₁``, ``Ī₂ = J^{-4/3} I₂`` and modified stretches
``λ̄_i = J^{-1/3} λ_i`` — the way the literature (and Abaqus, FEBio) states these models
for nearly incompressible use (Holzapfel 2000, *Nonlinear Solid Mechanics*, §6.4). The
volumetric term is the same for all:

    U(J) = κ/4 (J² − 1 − 2 ln J),   U(1) = U′(1) = 0,   U″(1) = κ

(Simo & Taylor 1982, *CMAME* 35:107; used by Gasser, Ogden & Holzapfel 2006), so κ is the
small-strain bulk modulus and U → ∞ as J → 0⁺. For J ≤ 0 every model returns ``+inf``
(as ``neo_hookean`` does; the Newton line search rejects it). The models also work with
the F-bar formulation (``mesh.formulation = "fbar"``), which replaces F by F̄ before ψ.

Each linearises at F = I to isotropic linear elasticity with shear modulus
``params.shear_modulus`` and bulk modulus ``params.bulk_modulus`` (= κ): λ = κ − 2μ/3.

Units: every modulus (c_ij, μ, μ_p, κ) is a stress, and ψ has the same unit (energy per
unit rest volume). The defaults of ``<model>_params()`` are in **MPa**; α_p, J_m and λ_m
are dimensionless.

Default values: Ogden's three-term fit to Treloar's (1944) data on vulcanised natural rubber
(Ogden 1972, *Proc. R. Soc. Lond. A* 326:565 converted from kgf/cm² to MPa with
1 kgf/cm² = 0.0981 MPa) is used for ``ogden``; the constants of the other models are
least-squares fits, computed in this project, of each model's incompressible uniaxial
nominal stress to that Ogden curve (``tests/test_rubber.py::test_default_constants_fit``
recomputes them). κ defaults to 1000 × the initial shear modulus (ν ≈ 0.4995), a chosen,
not measured, value: natural rubber's measured bulk modulus is ≈ 2 GPa (ν ≈ 0.9999).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..mechanics.kinematics import det
from .spectral import power, stretch_sum

__all__ = [
    "embed_plane_strain",
    "embed_direction",
    "volumetric",
    "modified_invariants",
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
    "ARRUDA_BOYCE_COEFFS",
]

Scalar = jax.Array | float


# --------------------------------------------------------------------- shared kinematics
def embed_plane_strain(F: jax.Array) -> jax.Array:
    """``F`` as a ``(3, 3)`` matrix: 3D unchanged; 2D ``(2, 2)`` → ``diag(F, 1)`` (plane
    strain, ``F_zz = 1``)."""
    if F.shape == (3, 3):
        return F
    if F.shape == (2, 2):
        return jnp.zeros((3, 3), F.dtype).at[:2, :2].set(F).at[2, 2].set(1.0)
    raise ValueError(f"F must be 2x2 or 3x3, got shape {F.shape}")


def embed_direction(a, what: str = "a reference direction") -> jax.Array:
    """A reference direction as a ``(3,)`` vector: 3D unchanged, an in-plane ``(2,)``
    direction gets a zero third component (the plane-strain embedding of
    :func:`embed_plane_strain`).

    Raises:
        ValueError: any other shape (the message names ``what``).
    """
    a = jnp.asarray(a)
    if a.shape == (2,):
        a = jnp.concatenate([a, jnp.zeros((1,), a.dtype)])
    if a.shape != (3,):
        raise ValueError(f"{what} must have shape (3,) or (2,), got {a.shape}")
    return a


def safe_state(F: jax.Array):
    """``(ok, F3, J)``: ``ok = J > 0``; ``F3`` the 3D embedding of F, replaced by I where
    not ok (so no NaN enters a derivative through the untaken branch); ``J`` of ``F3``."""
    J = det(F)
    ok = J > 0
    F3 = embed_plane_strain(jnp.where(ok, F, jnp.eye(F.shape[0], dtype=F.dtype)))
    return ok, F3, jnp.where(ok, J, 1.0)


def volumetric(J, kappa):
    """``U(J) = κ/4 (J² − 1 − 2 ln J)`` [stress] for J > 0 (Simo & Taylor 1982); U″(1) = κ."""
    return 0.25 * kappa * (J * J - 1.0 - 2.0 * jnp.log(J))


def modified_invariants(F3: jax.Array, J):
    """``(Ī₁, Ī₂)`` of ``C̄ = J^{-2/3} FᵀF`` for a ``(3, 3)`` F with ``J = det F > 0``."""
    C = F3.T @ F3
    I1 = jnp.trace(C)
    I2 = 0.5 * (I1 * I1 - jnp.sum(C * C))
    return J ** (-2.0 / 3.0) * I1, J ** (-4.0 / 3.0) * I2


def _finite_where(ok, psi):
    return jnp.where(ok, psi, jnp.inf)


# ----------------------------------------------------------------------- Mooney–Rivlin
class MooneyRivlin(NamedTuple):
    """Mooney–Rivlin constants [stress]: ``c10``, ``c01``, bulk modulus ``kappa``.

    Each a scalar or a ``(n_cells,)`` per-cell field.
    """

    c10: Scalar
    c01: Scalar
    kappa: Scalar

    @property
    def shear_modulus(self):
        """Initial shear modulus ``μ = 2(c10 + c01)``."""
        return 2.0 * (self.c10 + self.c01)

    @property
    def bulk_modulus(self):
        """Initial bulk modulus κ."""
        return self.kappa


def mooney_rivlin(F: jax.Array, params: MooneyRivlin) -> jax.Array:
    """Compressible Mooney–Rivlin ``ψ = c10 (Ī₁ − 3) + c01 (Ī₂ − 3) + U(J)``.

    Mooney 1940, *J. Appl. Phys.* 11:582; Rivlin 1948, *Phil. Trans. R. Soc. A* 241:379;
    decoupled compressible form: Holzapfel 2000, §6.5. Shear modulus μ = 2(c10 + c01).
    Isochoric/volumetric split (module docstring). F: ``(d, d)``; ψ [stress].
    """
    ok, F3, J = safe_state(F)
    I1b, I2b = modified_invariants(F3, J)
    psi = params.c10 * (I1b - 3.0) + params.c01 * (I2b - 3.0) + volumetric(J, params.kappa)
    return _finite_where(ok, psi)


def mooney_rivlin_params(**overrides) -> MooneyRivlin:
    """Typical Mooney–Rivlin constants [MPa] of vulcanised natural rubber.

    ``c10 = 0.112, c01 = 0.112`` (μ = 0.448 MPa): least-squares fit of the incompressible
    uniaxial nominal stress ``2(λ − λ⁻²)(c10 + c01/λ)`` to Ogden's (1972) representation
    of Treloar's (1944) data for 1 ≤ λ ≤ 3 (module docstring); ``kappa = 1000 μ`` (chosen).
    Keyword arguments replace fields.
    """
    c10, c01 = 0.112, 0.112
    p = MooneyRivlin(c10, c01, 1000.0 * 2.0 * (c10 + c01))
    return p._replace(**overrides)


# ------------------------------------------------------------------------------- Yeoh
class Yeoh(NamedTuple):
    """Yeoh constants [stress]: ``c10, c20, c30`` and bulk modulus ``kappa``."""

    c10: Scalar
    c20: Scalar
    c30: Scalar
    kappa: Scalar

    @property
    def shear_modulus(self):
        """Initial shear modulus ``μ = 2 c10``."""
        return 2.0 * self.c10

    @property
    def bulk_modulus(self):
        """Initial bulk modulus κ."""
        return self.kappa


def yeoh(F: jax.Array, params: Yeoh) -> jax.Array:
    """Compressible Yeoh ``ψ = Σ_{i=1..3} c_i0 (Ī₁ − 3)^i + U(J)``.

    Yeoh 1993, *Rubber Chem. Technol.* 66:754. Shear modulus μ = 2 c10.
    Isochoric/volumetric split (module docstring). F: ``(d, d)``; ψ [stress].
    """
    ok, F3, J = safe_state(F)
    I1b, _ = modified_invariants(F3, J)
    x = I1b - 3.0
    psi = x * (params.c10 + x * (params.c20 + x * params.c30)) + volumetric(J, params.kappa)
    return _finite_where(ok, psi)


def yeoh_params(**overrides) -> Yeoh:
    """Typical Yeoh constants [MPa] of vulcanised natural rubber.

    ``c10 = 0.156, c20 = -6.21e-4, c30 = 2.91e-5`` (μ = 0.312 MPa): least-squares fit of the
    incompressible uniaxial nominal stress ``2(λ − λ⁻²) ∂ψ/∂Ī₁`` to Ogden's (1972)
    representation of Treloar's (1944) data for 1 ≤ λ ≤ 7 (module docstring);
    ``kappa = 1000 μ`` (chosen). Keyword arguments replace fields.
    """
    c10 = 0.156
    p = Yeoh(c10, -6.21e-4, 2.91e-5, 1000.0 * 2.0 * c10)
    return p._replace(**overrides)


# ------------------------------------------------------------------------------ Ogden
class Ogden(NamedTuple):
    """Three-term Ogden constants: ``mu1..mu3`` [stress], ``alpha1..alpha3`` [–], ``kappa``.

    Separate scalar leaves (each may be a ``(n_cells,)`` field), so every constant can be
    fitted or given per cell. Stability needs ``μ_p α_p > 0`` for every p.
    """

    mu1: Scalar
    mu2: Scalar
    mu3: Scalar
    alpha1: Scalar
    alpha2: Scalar
    alpha3: Scalar
    kappa: Scalar

    @property
    def shear_modulus(self):
        """Initial shear modulus ``μ = ½ Σ μ_p α_p``."""
        return 0.5 * (self.mu1 * self.alpha1 + self.mu2 * self.alpha2 + self.mu3 * self.alpha3)

    @property
    def bulk_modulus(self):
        """Initial bulk modulus κ."""
        return self.kappa


def ogden(F: jax.Array, params: Ogden) -> jax.Array:
    """Compressible Ogden ``ψ = Σ_{p=1..3} (μ_p/α_p)(λ̄₁^α_p + λ̄₂^α_p + λ̄₃^α_p − 3) + U(J)``.

    Ogden 1972, *Proc. R. Soc. Lond. A* 326:565; modified stretches
    ``λ̄_i = J^{-1/3} λ_i`` (Holzapfel 2000, §6.5). Shear modulus μ = ½ Σ μ_p α_p.
    ``Σ_i λ̄_i^α = J^{-α/3} Σ_i c_i^{α/2}`` over the eigenvalues c_i of C = FᵀF, evaluated
    with :func:`jaxelastic.materials.spectral.stretch_sum` (from an SVD of F), whose custom JVP
    keeps the gradient, Hessian and HVP finite at repeated stretches (F = I, uniaxial,
    equibiaxial) and makes the α_p differentiable. F: ``(d, d)``; ψ [stress].
    """
    ok, F3, J = safe_state(F)
    psi = volumetric(J, params.kappa)
    for mu, alpha in (
        (params.mu1, params.alpha1),
        (params.mu2, params.alpha2),
        (params.mu3, params.alpha3),
    ):
        s = J ** (-alpha / 3.0) * stretch_sum(F3, 0.5 * alpha, power)  # Σ λ̄_i^α
        psi = psi + mu / alpha * (s - 3.0)
    return _finite_where(ok, psi)


def ogden_params(**overrides) -> Ogden:
    """Ogden's three-term constants for Treloar's (1944) natural rubber data.

    ``μ = (0.618, 1.18e-3, −9.81e-3) MPa``, ``α = (1.3, 5.0, −2.0)`` (Ogden 1972:
    μ_p = 6.3, 0.012, −0.1 kgf/cm²); initial shear modulus ½ Σ μ_p α_p = 0.4145 MPa;
    ``kappa = 1000 μ`` (chosen). Keyword arguments replace fields.
    """
    p = Ogden(0.618, 1.18e-3, -9.81e-3, 1.3, 5.0, -2.0, 0.0)
    return p._replace(kappa=1000.0 * p.shear_modulus)._replace(**overrides)


# ------------------------------------------------------------------------------- Gent
class Gent(NamedTuple):
    """Gent constants: shear modulus ``mu`` [stress], limit ``Jm`` of Ī₁ − 3 [–], ``kappa``."""

    mu: Scalar
    Jm: Scalar
    kappa: Scalar

    @property
    def shear_modulus(self):
        """Initial shear modulus μ."""
        return self.mu

    @property
    def bulk_modulus(self):
        """Initial bulk modulus κ."""
        return self.kappa


def gent(F: jax.Array, params: Gent) -> jax.Array:
    """Compressible Gent ``ψ = −(μ J_m/2) ln(1 − (Ī₁ − 3)/J_m) + U(J)``.

    Gent 1996, *Rubber Chem. Technol.* 69:59. Shear modulus μ; chains lock as
    Ī₁ − 3 → J_m, beyond which ψ = +inf. Isochoric/volumetric split (module docstring).
    F: ``(d, d)``; ψ [stress].
    """
    ok, F3, J = safe_state(F)
    I1b, _ = modified_invariants(F3, J)
    arg = 1.0 - (I1b - 3.0) / params.Jm
    ok = ok & (arg > 0)
    arg = jnp.where(ok, arg, 1.0)
    psi = -0.5 * params.mu * params.Jm * jnp.log(arg) + volumetric(J, params.kappa)
    return _finite_where(ok, psi)


def gent_params(**overrides) -> Gent:
    """Typical Gent constants of vulcanised natural rubber.

    ``mu = 0.263 MPa, Jm = 86.3``: least-squares fit of the incompressible uniaxial nominal
    stress ``μ(λ − λ⁻²)/(1 − (λ² + 2/λ − 3)/J_m)`` to Ogden's (1972) representation of
    Treloar's (1944) data for 1 ≤ λ ≤ 7 (module docstring); ``kappa = 1000 μ`` (chosen).
    Keyword arguments replace fields.
    """
    p = Gent(0.263, 86.3, 263.0)
    return p._replace(**overrides)


# ----------------------------------------------------------------------- Arruda–Boyce
ARRUDA_BOYCE_COEFFS = (1.0 / 2.0, 1.0 / 20.0, 11.0 / 1050.0, 19.0 / 7000.0, 519.0 / 673750.0)
"""α_i of the five-term series of the inverse Langevin eight-chain energy (Arruda & Boyce
1993)."""


class ArrudaBoyce(NamedTuple):
    """Arruda–Boyce constants: ``mu`` (= n k θ) [stress], locking stretch ``lambda_m``
    (= √N) [–], ``kappa`` [stress]."""

    mu: Scalar
    lambda_m: Scalar
    kappa: Scalar

    @property
    def shear_modulus(self):
        """Initial shear modulus ``μ₀ = 2 μ Σ i α_i 3^{i−1}/λ_m^{2i−2}``
        (= μ(1 + 3/(5λ_m²) + 99/(175λ_m⁴) + 513/(875λ_m⁶) + 42039/(67375λ_m⁸)))."""
        lm2 = self.lambda_m**2
        return (
            2.0
            * self.mu
            * sum(
                i * a * 3.0 ** (i - 1) / lm2 ** (i - 1)
                for i, a in enumerate(ARRUDA_BOYCE_COEFFS, start=1)
            )
        )

    @property
    def bulk_modulus(self):
        """Initial bulk modulus κ."""
        return self.kappa


def arruda_boyce(F: jax.Array, params: ArrudaBoyce) -> jax.Array:
    """Compressible Arruda–Boyce (eight-chain) ``ψ = μ Σ_{i=1..5} α_i/λ_m^{2i−2} (Ī₁^i − 3^i)
    + U(J)``.

    Arruda & Boyce 1993, *J. Mech. Phys. Solids* 41:389: the inverse Langevin
    function truncated after its **fifth** term (α = 1/2, 1/20, 11/1050, 19/7000,
    519/673750, :data:`ARRUDA_BOYCE_COEFFS`), the series Abaqus uses. The initial shear
    modulus is ``params.shear_modulus`` (μ·(1 + 3/(5λ_m²) + …), not μ itself).
    Isochoric/volumetric split (module docstring). F: ``(d, d)``; ψ [stress].
    """
    ok, F3, J = safe_state(F)
    I1b, _ = modified_invariants(F3, J)
    lm2 = params.lambda_m**2
    psi = volumetric(J, params.kappa)
    for i, a in enumerate(ARRUDA_BOYCE_COEFFS, start=1):
        psi = psi + params.mu * a / lm2 ** (i - 1) * (I1b**i - 3.0**i)
    return _finite_where(ok, psi)


def arruda_boyce_params(**overrides) -> ArrudaBoyce:
    """Typical Arruda–Boyce constants of vulcanised natural rubber.

    ``mu = 0.261 MPa, lambda_m = 4.72``: least-squares fit of the incompressible uniaxial
    nominal stress to Ogden's (1972) representation of Treloar's (1944) data for
    1 ≤ λ ≤ 7 (module docstring); ``kappa = 1000 μ₀`` (chosen).
    Keyword arguments replace fields.
    """
    p = ArrudaBoyce(0.261, 4.72, 0.0)
    return p._replace(kappa=1000.0 * p.shear_modulus)._replace(**overrides)
