"""Rule-based fibre fields: the helix rule of an idealised ellipsoidal ventricle.

:func:`helix_fibres` gives per-point fibre and sheet directions ``(f0, s0)`` for a thick
prolate ellipsoid (long axis z) whose endocardium has radii ``(r_s, r_l)`` = ``endo`` and
epicardium ``epi``: the transmural coordinate t ∈ [0, 1] of a point X is the one for which
X lies on the ellipsoid of radii ``endo + t (epi − endo)``; on it,
``X = (r_s sin u cos v, r_s sin u sin v, r_l cos u)`` with u ∈ [−π, 0]. The helix angle
α = α_endo + t (α_epi − α_endo) (linear through the wall) and

    f0 = sin α e_u + cos α e_v,    s0 = the outward unit normal of that ellipsoid,

with e_u, e_v the normalised tangents ∂X/∂u, ∂X/∂v (Land et al. 2015, *Proc. R. Soc. A*
471:20150641, problem 3: endocardium r_s = 7, r_l = 17 mm, epicardium 10, 20 mm, base at
z = 5 mm, α from +90° to −90°). f0 ⟂ s0 by construction (both unit). The directions are
the reference ones the materials take: HGO's ``a01`` and Guccione's ``f0``/``s0``.

:func:`helix_basis` samples the rule on a mesh: at the cell centroids (one direction per
cell, ``(n_cells, 3)``) or at the quadrature points (an
:class:`~jaxelastic.mechanics.quadrature_fields.AtQuadrature` of ``(n_cells, n_q, 3)``). The
helix turns by 180° through the wall: with one to three cells through the thickness a
direction per cell resolves it coarsely (the quadrature points of a P2 tet sample it at
four depths per cell).
"""

from __future__ import annotations

from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np

from ..mechanics.quadrature_fields import AtQuadrature
from ..mesh.geometry import quadrature_points

__all__ = ["helix_fibres", "helix_basis", "transmural_coordinate", "LAND_ENDO", "LAND_EPI"]

LAND_ENDO = (7.0, 17.0)
"""Endocardial radii ``(r_short, r_long)`` [mm] of the Land et al. (2015) ventricle."""
LAND_EPI = (10.0, 20.0)
"""Epicardial radii ``(r_short, r_long)`` [mm] of the Land et al. (2015) ventricle."""

_BISECTIONS = 60  # halves the bracket [-1, 2] to ~3e-18: below float64 resolution of t


def transmural_coordinate(points, endo=LAND_ENDO, epi=LAND_EPI) -> jax.Array:
    """t with ``ρ²/r_s(t)² + z²/r_l(t)² = 1``, radii interpolated linearly in t.

    Args:
        points: ``(n, 3)`` reference positions (the ellipsoid centred at the origin).
        endo, epi: ``(r_short, r_long)`` of the inner and outer surfaces [length].

    Returns:
        ``(n,)`` t, 0 on the endocardium, 1 on the epicardium (found by bisection on
        [−1, 2]; points outside the wall give t outside [0, 1], not clipped).
    """
    X = jnp.asarray(points)
    rho2 = X[:, 0] ** 2 + X[:, 1] ** 2
    z2 = X[:, 2] ** 2
    (a0, b0), (a1, b1) = endo, epi

    def g(t):  # decreasing in t while the radii grow
        a, b = a0 + t * (a1 - a0), b0 + t * (b1 - b0)
        return rho2 / (a * a) + z2 / (b * b) - 1.0

    def halve(_, lohi):
        lo, hi = lohi
        mid = 0.5 * (lo + hi)
        inside = g(mid) > 0  # the point lies outside the mid ellipsoid: t > mid
        return jnp.where(inside, mid, lo), jnp.where(inside, hi, mid)

    lo = jnp.full(X.shape[0], -1.0, X.dtype)
    lo, hi = jax.lax.fori_loop(0, _BISECTIONS, halve, (lo, lo + 3.0))
    return 0.5 * (lo + hi)


def helix_fibres(
    points, endo=LAND_ENDO, epi=LAND_EPI, alpha_endo=90.0, alpha_epi=-90.0
) -> tuple[jax.Array, jax.Array]:
    """Fibre and sheet directions of the helix rule (see the module).

    Args:
        points: ``(n, 3)`` reference points (cell centroids or quadrature points) [length].
        endo, epi: ``(r_short, r_long)`` of the endocardium and epicardium [length].
        alpha_endo, alpha_epi: helix angles [degrees] on the two surfaces (differentiable).

    Returns:
        ``(f0, s0)``, each ``(n, 3)`` unit rows, f0 ⟂ s0; at the apex axis (ρ = 0) e_v is
        taken along y.
    """
    X = jnp.asarray(points)
    t = transmural_coordinate(X, endo, epi)
    (a0, b0), (a1, b1) = endo, epi
    rs, rl = a0 + t * (a1 - a0), b0 + t * (b1 - b0)
    rho = jnp.sqrt(X[:, 0] ** 2 + X[:, 1] ** 2)
    on_axis = rho <= 1e-12 * rs
    rho_safe = jnp.where(on_axis, 1.0, rho)
    cv = jnp.where(on_axis, 1.0, -X[:, 0] / rho_safe)  # x = r_s sin u cos v, sin u = −ρ/r_s
    sv = jnp.where(on_axis, 0.0, -X[:, 1] / rho_safe)
    sin_u, cos_u = -rho / rs, X[:, 2] / rl
    e_u = jnp.stack([rs * cos_u * cv, rs * cos_u * sv, -rl * sin_u], axis=1)
    e_u = e_u / jnp.linalg.norm(e_u, axis=1, keepdims=True)
    e_v = jnp.stack([sv, -cv, jnp.zeros_like(cv)], axis=1)  # ∂X/∂v / |∂X/∂v| (sin u ≤ 0)
    normal = jnp.stack([X[:, 0] / rs**2, X[:, 1] / rs**2, X[:, 2] / rl**2], axis=1)
    s0 = normal / jnp.linalg.norm(normal, axis=1, keepdims=True)
    alpha = jnp.deg2rad(alpha_endo + t * (alpha_epi - alpha_endo))
    f0 = jnp.sin(alpha)[:, None] * e_u + jnp.cos(alpha)[:, None] * e_v
    return f0, s0


def helix_basis(
    mesh,
    *,
    at: Literal["cells", "quadrature"] = "quadrature",
    endo=LAND_ENDO,
    epi=LAND_EPI,
    alpha_endo=90.0,
    alpha_epi=-90.0,
):
    """:func:`helix_fibres` sampled on a mesh: ``(f0, s0)`` for Guccione's basis (or
    ``f0`` alone for HGO's ``a01``, or :class:`~jaxelastic.materials.ActiveTension`).

    Args:
        mesh: a 3D :class:`~jaxelastic.mesh.Mesh` of the ventricle wall [length].
        at: ``"cells"``: at the centroids of the cells' corner nodes, each ``(n_cells, 3)``;
            ``"quadrature"``: at the quadrature points
            (:func:`~jaxelastic.mesh.geometry.quadrature_points`), each an
            :class:`~jaxelastic.mechanics.quadrature_fields.AtQuadrature` of
            ``(n_cells, n_q, 3)`` (for P1 cells n_q = 1: the centroid again).
        endo, epi, alpha_endo, alpha_epi: as :func:`helix_fibres`.

    Raises:
        ValueError: ``at`` is neither, or the mesh is not 3D.
    """
    if at not in ("cells", "quadrature"):
        raise ValueError(f"helix_basis: at must be 'cells' or 'quadrature', got {at!r}")
    if mesh.dim != 3:
        raise ValueError(f"helix_basis: the helix rule needs a 3D mesh, got a {mesh.dim}D one")
    kw = dict(endo=endo, epi=epi, alpha_endo=alpha_endo, alpha_epi=alpha_epi)
    if at == "cells":
        corners = np.asarray(mesh.cells)[:, : mesh.dim + 1]
        return helix_fibres(jnp.asarray(mesh.points)[corners].mean(axis=1), **kw)
    X = quadrature_points(mesh.points, mesh.cells, mesh.element_type)  # (c, q, 3)
    c, q, d = X.shape
    f0, s0 = helix_fibres(jnp.reshape(X, (c * q, d)), **kw)
    return AtQuadrature(f0.reshape(c, q, d)), AtQuadrature(s0.reshape(c, q, d))
