"""Passive myocardium (Guccione's law) and active fibre tension.

``guccione(F, params)`` is a plain ψ for one unbatched F (``(3, 3)``, or ``(2, 2)`` in
plane strain, embedded as ``diag(F, 1)``, see :mod:`jaxelastic.materials.rubber`):

    ψ = C/2 (e^Q − 1) + U(J),
    Q = b_f E_ff² + b_t (E_ss² + E_nn² + E_sn² + E_ns²) + b_fs (E_fs² + E_sf² + E_fn² + E_nf²),

with ``E = ½(FᵀF − I)`` the Green–Lagrange strain written in the local fibre–sheet–normal
basis ``(f0, s0, n0 = f0 × s0)`` (Guccione, McCulloch & Waldman 1991, *J. Biomech. Eng.*
113:42, eq. 1), and the volumetric penalty ``U(J) = κ/4 (J² − 1 − 2 ln J)`` of
:mod:`jaxelastic.materials.rubber`. **Form**: the *full* (not isochoric) E with a penalty on
J, the form of the cardiac verification benchmarks (Land et al. 2015, *Proc. R. Soc. A*
471:20150641); as κ grows both forms tend to the same incompressible law.

The basis vectors are material (reference) directions, shared (``(3,)``, or ``(2,)`` padded
with z = 0), per cell (``(n_cells, 3)``; :func:`per_cell_basis` broadcasts shared ones) or
per quadrature point (an :class:`~jaxelastic.mechanics.quadrature_fields.AtQuadrature` of
``(n_cells, n_q, 3)``: :func:`~jaxelastic.materials.fibre_rules.helix_basis` with
``at="quadrature"``, or :func:`per_quadrature_basis`).
Inside ψ, ``f0`` is normalised and ``s0`` is Gram–Schmidt orthogonalised against ``f0`` and
normalised, so any non-parallel pair is accepted
(:func:`~jaxelastic.materials.registry.check_guccione` refuses a zero or parallel pair).

Active tension (:func:`with_active_tension`): ``ψ_a = T_a/2 (I₄f − 1)``, ``I₄f = f0·C f0``,
whose second Piola stress is ``S_a = T_a f0⊗f0`` (Land et al. 2015, problem 3) and first
Piola stress ``P_a = T_a F f0⊗f0``.

Units: C, κ and T_a are stresses (defaults in **kPa**, the benchmark's unit); b_f, b_t, b_fs
are dimensionless.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..mechanics.quadrature_fields import AtQuadrature, is_at_quadrature
from .rubber import embed_direction, embed_plane_strain, safe_state, volumetric

__all__ = [
    "Guccione",
    "guccione",
    "guccione_params",
    "guccione_basis",
    "per_cell_basis",
    "per_quadrature_basis",
    "ActiveTension",
    "with_active_tension",
]

Scalar = jax.Array | float


class Guccione(NamedTuple):
    """Guccione constants and the local fibre–sheet basis.

    Attributes:
        C: stiffness scale [stress], > 0.
        bf: fibre exponent [–], > 0.
        bt: transverse (sheet–normal plane) exponent [–], > 0.
        bfs: fibre–sheet/fibre–normal shear exponent [–], > 0.
        kappa: bulk modulus of the volumetric penalty [stress], > 0.
        f0: fibre direction (reference), ``(3,)``/``(2,)`` shared, ``(n_cells, 3)`` per
            cell, or ``AtQuadrature((n_cells, n_q, 3))`` per quadrature point.
        s0: sheet direction (reference), same shapes; orthogonalised against f0 in ψ.

    The scalar fields may also be ``(n_cells,)`` per-cell fields.
    """

    C: Scalar
    bf: Scalar
    bt: Scalar
    bfs: Scalar
    kappa: Scalar
    f0: jax.Array
    s0: jax.Array

    @property
    def shear_modulus(self):
        """The smallest initial shear modulus, ``C·min(b_t, b_fs)/2`` (sheet–normal shear
        ``C b_t/2``, fibre shear ``C b_fs/2``); the linearised law is anisotropic."""
        return 0.5 * self.C * jnp.minimum(self.bt, self.bfs)

    @property
    def bulk_modulus(self):
        """Initial bulk modulus: κ plus the Guccione term's ``C(b_f + 2b_t)/9``."""
        return self.kappa + self.C * (self.bf + 2.0 * self.bt) / 9.0


def guccione_basis(f0, s0) -> jax.Array:
    """The orthonormal ``(3, 3)`` matrix ``R = [f, s, n]`` (columns) of one cell.

    ``f = f0/|f0|``, ``s`` = s0 orthogonalised against f (Gram–Schmidt) and normalised,
    ``n = f × s``. f0, s0: ``(3,)`` or ``(2,)`` (padded with z = 0), nonzero, not parallel.
    """
    f = embed_direction(f0, "a basis direction")
    f = f / jnp.sqrt(jnp.sum(f * f))
    s = embed_direction(s0, "a basis direction")
    s = s - jnp.sum(s * f) * f
    s = s / jnp.sqrt(jnp.sum(s * s))
    return jnp.stack([f, s, jnp.cross(f, s)], axis=1)


def _weights(p: Guccione) -> jax.Array:
    """``(3, 3)`` weights B with ``Q = Σ_ij B_ij E_ij²`` in the (f, s, n) basis."""
    bf, bt, bfs = (jnp.asarray(v) for v in (p.bf, p.bt, p.bfs))
    return jnp.stack(
        [jnp.stack([bf, bfs, bfs]), jnp.stack([bfs, bt, bt]), jnp.stack([bfs, bt, bt])]
    )


def guccione(F: jax.Array, params: Guccione) -> jax.Array:
    """Guccione's law: ``ψ = C/2 (e^Q − 1) + κ/4 (J² − 1 − 2 ln J)`` (see the module).

    Returns +inf for J ≤ 0. F: ``(d, d)``; ψ [stress].
    """
    ok, F3, J = safe_state(F)
    R = guccione_basis(params.f0, params.s0)
    E = 0.5 * (F3.T @ F3 - jnp.eye(3, dtype=F3.dtype))
    El = R.T @ E @ R
    Q = jnp.sum(_weights(params) * El * El)
    psi = 0.5 * params.C * jnp.expm1(Q) + volumetric(J, params.kappa)
    return jnp.where(ok, psi, jnp.inf)


def guccione_params(**overrides) -> Guccione:
    """The constants of the Land et al. (2015) beam and active-ventricle problems [kPa].

    ``C = 2, b_f = 8, b_t = 2, b_fs = 4`` (problems 1 and 3), fibres along x and sheets along
    y; ``kappa = 1000`` (a chosen penalty, 500 C: the benchmark is incompressible).
    Keyword arguments replace fields.
    """
    p = Guccione(2.0, 8.0, 2.0, 4.0, 1000.0, jnp.array([1.0, 0.0, 0.0]), jnp.array([0.0, 1.0, 0.0]))
    return p._replace(**overrides)


def per_cell_basis(params: Guccione, n_cells: int) -> Guccione:
    """``params`` with shared ``(3,)`` f0, s0 broadcast to ``(n_cells, 3)`` (a mesh-level
    call treats a non-scalar leaf as a per-cell field)."""

    def cells(a):
        a = jnp.asarray(a)
        return jnp.broadcast_to(a, (n_cells, a.shape[-1])) if a.ndim == 1 else a

    return params._replace(f0=cells(params.f0), s0=cells(params.s0))


def per_quadrature_basis(params: Guccione, n_cells: int, n_q: int) -> Guccione:
    """``params`` with f0, s0 (shared ``(3,)`` or per cell ``(n_cells, 3)``) broadcast to
    per-quadrature-point fields ``AtQuadrature((n_cells, n_q, 3))`` (already per-point ones
    are kept). ``n_q = mesh.weights.shape[1]``.

    Raises:
        ValueError: a direction of another shape.
    """

    def points(a):
        if is_at_quadrature(a):
            return a
        a = jnp.asarray(a)
        if a.ndim == 1 or (a.ndim == 2 and a.shape[0] == n_cells):
            return AtQuadrature(jnp.broadcast_to(a[..., None, :], (n_cells, n_q, a.shape[-1])))
        raise ValueError(
            f"per_quadrature_basis: a direction must be (d,) or (n_cells={n_cells}, d), "
            f"got {a.shape}"
        )

    return params._replace(f0=points(params.f0), s0=points(params.s0))


class ActiveTension(NamedTuple):
    """Parameters of :func:`with_active_tension`.

    Attributes:
        passive: the parameters of the passive ψ.
        Ta: active tension [stress], scalar or ``(n_cells,)``. Ramp it with the load
            factor by passing ``s·T_a`` at each increment.
        f0: the fibre direction it acts along, ``(3,)``/``(2,)``, ``(n_cells, 3)`` or
            ``AtQuadrature((n_cells, n_q, 3))`` (normalised inside ψ).
    """

    passive: object
    Ta: Scalar
    f0: jax.Array

    def scaled(self, s) -> ActiveTension:
        """These parameters with the tension ``s·T_a`` (a load factor ``s``; the passive
        law unchanged): the ``params_path`` of :func:`~jaxelastic.solve_incremental` that
        ramps the contraction with the loads."""
        return self._replace(Ta=s * jnp.asarray(self.Ta))


@functools.cache
def with_active_tension(psi: Callable) -> Callable:
    """``ψ(F, ActiveTension) = psi(F, passive) + T_a/2 (f·Cf − 1)``, f = f0/|f0|.

    The first Piola stress of the active term is ``T_a F f⊗f``, its second Piola stress
    ``S_a = T_a f⊗f`` (Land et al. 2015, problem 3). The term is a potential in the
    reference configuration, so the Newton tangent stays symmetric. Cached per ``psi``: the
    same wrapped function is returned each time (one jit compilation).
    """

    def active(F: jax.Array, params: ActiveTension) -> jax.Array:
        f = embed_direction(params.f0, "a basis direction")
        f = f / jnp.sqrt(jnp.sum(f * f))
        Ff = embed_plane_strain(F) @ f
        I4 = jnp.sum(Ff * Ff)
        return psi(F, params.passive) + 0.5 * params.Ta * (I4 - 1.0)

    active.__name__ = f"active_{getattr(psi, '__name__', 'psi')}"
    active.__doc__ = f"{getattr(psi, '__name__', 'psi')} with an active fibre tension."
    return active
