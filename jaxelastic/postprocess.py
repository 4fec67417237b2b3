"""Stress recovery and support reactions from a solved state.

* :func:`cell_fields`: per-cell J, Green strain, first Piola and Cauchy stress, von Mises
  stress and ψ (quadrature-weighted averages; in 2D the plane-strain σ_zz from the 3D
  embedding of ψ);
* :func:`nodal_stress`: recovered, continuous nodal Cauchy and von Mises stresses (local L2
  projection for P2, element averages for P1), averaged over the elements of each node;
* :func:`stress_fields`: both from one jitted evaluation (what
  :func:`~jaxelastic.io.vtk.write_vtu` writes);
* :func:`reaction_force`: the total force the supports exert at the prescribed dofs;
* :func:`facet_tractions`: the nominal traction ``τ = P·N`` on boundary facets.
"""

from __future__ import annotations

import functools
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from .loads import Dirichlet, facet_integrals
from .mechanics.checks import cell_params_axes, check_positions, check_psi, psi_name
from .mechanics.kernels import first_piola, forces
from .mechanics.kinematics import deformation_gradients, det, green_strain
from .mechanics.quadrature_fields import first_point_params, over_quadrature
from .mesh import Mesh, facet_owners
from .mesh.elements import ref_nodes

__all__ = ["cell_fields", "nodal_stress", "stress_fields", "reaction_force", "facet_tractions"]


def _von_mises(s3, xp=jnp):
    """Von Mises stress of ``(..., 3, 3)`` Cauchy stresses (``xp``: ``jnp`` under jit, or
    ``np`` for host arrays)."""
    eye = xp.eye(3, dtype=s3.dtype).reshape((1,) * (s3.ndim - 2) + (3, 3))
    dev = s3 - xp.trace(s3, axis1=-2, axis2=-1)[..., None, None] / 3.0 * eye
    return xp.sqrt(1.5 * xp.sum(dev * dev, axis=(-2, -1)))


def _embed3(F):
    """The 3D embedding ``diag(F, 1)`` of in-plane ``(..., 2, 2)`` deformation gradients."""
    F3 = jnp.zeros(F.shape[:-2] + (3, 3), F.dtype).at[..., :2, :2].set(F)
    return F3.at[..., 2, 2].set(1.0)


# the in-plane probe of the plane-strain consistency test ψ₂(F) = ψ₃(diag(F, 1)) + const
_PROBE = np.array([[1.1, 0.07], [-0.04, 0.93]])


def _plane_strain_parts(psi, F, J, params, ax):
    """σ_zz ``(c, q)`` of the 3D embedding and, per cell, the relative mismatch of the
    in-plane P of ψ on 3×3 F against ψ on 2×2 F at a fixed probe F (0 when ψ on 2×2 F
    is the plane-strain restriction of ψ on 3×3 F)."""
    P3 = jax.vmap(over_quadrature(first_piola(psi)), in_axes=(0, ax))(_embed3(F), params)
    szz = P3[..., 2, 2] / J  # σ = P Fᵀ / J and row z of diag(F, 1) is e_z
    Fp = jnp.asarray(_PROBE, F.dtype)
    c = J.shape[0]
    params = first_point_params(params)  # the probe: one point per cell
    P2p = jax.vmap(lambda p: first_piola(psi)(Fp, p), in_axes=(ax,), axis_size=c)(params)
    P3p = jax.vmap(lambda p: first_piola(psi)(_embed3(Fp), p), in_axes=(ax,), axis_size=c)(params)
    diff = jnp.max(jnp.abs(P3p[:, :2, :2] - P2p), axis=(-2, -1))
    scale = jnp.max(jnp.abs(P2p), axis=(-2, -1))
    mismatch = jnp.where(scale > 0, diff / jnp.where(scale > 0, scale, 1.0), diff)
    return szz, mismatch


def _linear_basis(xi) -> np.ndarray:
    """``(n, d+1)`` values of the linear monomials ``1, ξ₁, …, ξ_d`` at reference points."""
    xi = np.asarray(xi, dtype=np.float64)
    return np.concatenate([np.ones((xi.shape[0], 1)), xi], axis=1)


def _recovery_incidence(element) -> np.ndarray:
    """``(n_q, k)`` 0/1: which element nodes each quadrature point's (constant) stress is
    attributed to in the nodal average: all nodes for P1 (one point), the sub-simplex's
    nodes for the composite elements (one point per sub-simplex)."""
    if element.is_composite:
        B = np.zeros((element.n_quad, element.n_nodes))
        for s, sub in enumerate(element.sub_cells):
            B[s, list(sub)] = 1.0
        return B
    return np.ones((element.n_quad, element.n_nodes))


def _nodal_average(s3, mesh):
    """Recovered nodal Cauchy stress ``(n_nodes, 9)`` from quadrature values ``(c, q, 3, 3)``.

    P2 (``order == 2``): per element, the weighted least-squares (local L2) fit of a linear
    field in the reference coordinates to the quadrature values, evaluated at the element's
    nodes (exact when the stress is linear in the element, as for linear elasticity on a
    straight-sided P2 element); P1 and the composite elements: the piecewise-constant value
    of the (sub-)simplex. Each node then takes the average of its elements' values weighted
    by the element (sub-simplex) measure.
    """
    el = mesh.element_type
    c, q = s3.shape[:2]
    sq = s3.reshape(c, q, 9)
    w = mesh.weights  # (c, q) [length^d]
    if el.order == 2 and not el.is_composite:
        Pq = jnp.asarray(_linear_basis(el.quad_points), s3.dtype)  # (q, d+1)
        Pn = jnp.asarray(_linear_basis(ref_nodes(el.dim)), s3.dtype)  # (k, d+1)
        G = jnp.einsum("qi,cq,qj->cij", Pq, w, Pq)
        coef = jnp.linalg.solve(G, jnp.einsum("qi,cq,cqx->cix", Pq, w, sq))  # (c, d+1, 9)
        wts = jnp.broadcast_to(w.sum(axis=1)[:, None], (c, el.n_nodes))
        num = jnp.einsum("ki,cix->ckx", Pn, coef) * wts[..., None]
    else:
        B = jnp.asarray(_recovery_incidence(el), s3.dtype)  # (q, k)
        num = jnp.einsum("qk,cq,cqx->ckx", B, w, sq)
        wts = jnp.einsum("qk,cq->ck", B, w)
    idx = mesh.cells.reshape(-1)
    n = mesh.points.shape[0]
    total = jax.ops.segment_sum(num.reshape(-1, 9), idx, num_segments=n)
    weight = jax.ops.segment_sum(wts.reshape(-1), idx, num_segments=n)
    return total / jnp.where(weight > 0, weight, jnp.nan)[:, None]


@functools.partial(jax.jit, static_argnums=(0, 4))
def _cell_fields(psi, x, mesh, params, embed: bool):
    F = deformation_gradients(x, mesh)  # (c, q, d, d); F̄ under the F-bar formulation
    c, q, d = F.shape[:3]
    ax = cell_params_axes(params, mesh.n_cells)
    P = jax.vmap(over_quadrature(first_piola(psi)), in_axes=(0, ax))(F, params)
    W = jax.vmap(over_quadrature(psi), in_axes=(0, ax))(F, params)  # (c, q)
    J = jax.vmap(jax.vmap(det))(F)
    sigma = P @ jnp.swapaxes(F, -1, -2) / J[..., None, None]  # Cauchy σ = P Fᵀ / J
    s3 = jnp.zeros((c, q, 3, 3), F.dtype).at[..., :d, :d].set(sigma)  # σ_zz = 0 for now
    wn = mesh.weights / jnp.sum(mesh.weights, axis=1, keepdims=True)  # (c, q)

    def avg(a):  # weighted average over the quadrature points
        return jnp.einsum("cq,cq...->c...", wn, a)

    out = {
        "J": avg(J),
        "green_strain": avg(jax.vmap(jax.vmap(green_strain))(F)).reshape(c, d * d),
        "stress_P": avg(P).reshape(c, d * d),
        "cauchy_stress": avg(s3).reshape(c, 9),
        "von_mises": avg(_von_mises(s3)),
        "energy_density": avg(W),
        "cauchy_stress_nodal": _nodal_average(s3, mesh),
    }
    if embed:
        szz, mismatch = _plane_strain_parts(psi, F, J, params, ax)
        s3z = s3.at[..., 2, 2].set(szz)
        out["von_mises_plane_strain"] = avg(_von_mises(s3z))
        out["cauchy_stress_plane_strain"] = avg(s3z).reshape(c, 9)
        out["cauchy_stress_nodal_plane_strain"] = _nodal_average(s3z, mesh)
        out["stress_zz"] = avg(szz)
        out["mismatch"] = mismatch
    return out


def _accepts_3d(psi, mesh: Mesh, params) -> str | None:
    """None if ψ returns a scalar for a 3×3 F, else why not (for the warning)."""
    try:
        check_psi(psi, 3, mesh.points.dtype, params, mesh.n_cells, where="cell_fields")
    except Exception as e:  # noqa: BLE001 — any failure means: no 3D embedding
        return f"{type(e).__name__}: {e}"
    return None


def cell_fields(psi, x, mesh: Mesh, params, *, plane: str = "strain") -> dict[str, np.ndarray]:
    """Per-cell output fields, averaged over the cell's quadrature points with their weights
    (the one value for P1; of F̄ under F-bar), jitted, mesh passed as an argument.

    In 2D the von Mises stress needs the out-of-plane Cauchy stress σ_zz. Plane strain
    (``plane="strain"``, the default, as in :func:`~jaxelastic.materials.lame`): σ_zz is the
    zz Cauchy stress of the 3D embedding ``F₃ = diag(F, 1)`` of the same ψ, ``P₃_zz / J``
    (for linear elasticity ``σ_zz = ν(σ_xx + σ_yy)``). That is the plane-strain σ_zz
    whenever ψ on 2×2 F is the restriction of ψ on 3×3 F (true for every built-in
    material); if ψ does not accept a 3×3 F, or its in-plane stress on ``diag(F, 1)``
    differs from the 2D one (a genuinely 2D model), a :class:`UserWarning` says so and
    von Mises is written with σ_zz = 0 and without ``stress_zz``. Plane stress
    (``plane="stress"``): σ_zz = 0 exactly.

    Args:
        psi: strain-energy density ``psi(F, params)`` [energy / rest measure].
        x: ``(n_nodes, dim)`` current positions [length].
        mesh: the rest mesh.
        params: material parameters (shared scalars or per-cell leaves).
        plane: 2D only: ``"strain"`` or ``"stress"`` (ignored in 3D).

    Returns:
        ``J`` ``(n_cells,)``: det F; ``green_strain`` ``(n_cells, d²)``: E = ½(FᵀF − I)
        row-major; ``stress_P`` ``(n_cells, d²)``: first Piola P [Pa]; ``cauchy_stress``
        ``(n_cells, 9)``: the Cauchy stress σ = P Fᵀ/J as a row-major 3×3 tensor [Pa]
        (in 2D with σ_zz as above, zero shear out of plane); ``von_mises`` ``(n_cells,)``:
        of σ [Pa]; ``energy_density`` ``(n_cells,)``: ψ [Pa]; in 2D ``stress_zz``
        ``(n_cells,)``: the σ_zz used [Pa] (0 in plane stress). Recovered nodal
        stresses: :func:`nodal_stress`.
    """
    return stress_fields(psi, x, mesh, params, plane=plane)[0]


def nodal_stress(psi, x, mesh: Mesh, params, *, plane: str = "strain") -> dict[str, np.ndarray]:
    """Recovered, continuous nodal (point) stresses, e.g. to read a peak stress at a notch.

    The Cauchy stress σ = P Fᵀ/J at the quadrature points is turned into one value per
    element node and averaged over the elements that share the node, weighted by the
    element measure:

    * P2 (``tri6``, ``tet10``): per element the local L2 projection (weighted least
      squares over the quadrature points) of σ onto linear fields, evaluated at the 6 / 10
      nodes. For linear elasticity on straight-sided P2 elements σ is linear in the
      element, so this is the element's own nodal stress, exactly.
    * P1 (``tri3``, ``tet4``): the constant stress of each cell; composite F-bar elements
      (``tri3x4``, ``tet4x8``): the constant stress of each linear sub-simplex.

    A stress field the elements represent exactly (uniform for P1, linear for P2) is
    recovered exactly at every node; elsewhere the averaging recovers the peak far better
    than the largest cell average (the concentration at a hole of a plate, within the
    discretisation error of the P2 field). σ_zz in 2D is that of :func:`cell_fields`.

    Args:
        psi, x, mesh, params, plane: as for :func:`cell_fields`.

    Returns:
        ``cauchy_stress_nodal`` ``(n_nodes, 9)``: row-major 3×3 Cauchy stress [Pa];
        ``von_mises_nodal`` ``(n_nodes,)``: the von Mises stress of that tensor [Pa].
    """
    return stress_fields(psi, x, mesh, params, plane=plane)[1]


def stress_fields(psi, x, mesh: Mesh, params, *, plane: str = "strain") -> tuple[dict, dict]:
    """``(cell fields, point fields)``: :func:`cell_fields` and :func:`nodal_stress` of
    positions ``x`` ``(n_nodes, dim)`` [length] from one jitted evaluation (the plane-strain
    σ_zz decision and its warning here). Pass the pair to
    :func:`~jaxelastic.io.vtk.write_vtu` (``fields=``) to write a state whose stresses are
    also needed elsewhere (e.g. a picture coloured by ``von_mises_nodal``) without
    evaluating them twice.

    Args:
        psi, x, mesh, params, plane: as for :func:`cell_fields`.

    Returns:
        ``(cells, points)``: dicts of host (numpy) arrays, ``cells`` as
        :func:`cell_fields` returns (leading axis ``n_cells``), ``points`` as
        :func:`nodal_stress` returns (leading axis ``n_nodes``).
    """
    if plane not in ("strain", "stress"):
        raise ValueError(f"plane must be 'strain' or 'stress', got {plane!r}")
    check_positions(x, mesh, where="cell_fields")
    check_psi(psi, mesh.dim, mesh.points.dtype, params, mesh.n_cells, where="cell_fields")
    strain2d = mesh.dim == 2 and plane == "strain"
    why = _accepts_3d(psi, mesh, params) if strain2d else None
    embed = strain2d and why is None
    out = _cell_fields(psi, jnp.asarray(x, dtype=mesh.points.dtype), mesh, params, embed)
    out = {k: np.asarray(v) for k, v in out.items()}
    nodal = out.pop("cauchy_stress_nodal")
    if embed:
        mismatch = float(np.nanmax(out.pop("mismatch")))
        vm, szz = out.pop("von_mises_plane_strain"), out.pop("stress_zz")
        sig, sig_n = (
            out.pop("cauchy_stress_plane_strain"),
            out.pop("cauchy_stress_nodal_plane_strain"),
        )
        tol = float(np.sqrt(np.finfo(out["J"].dtype).eps))
        if mismatch <= tol:
            out["von_mises"], out["stress_zz"], out["cauchy_stress"] = vm, szz, sig
            nodal = sig_n
        else:
            why = (
                f"its in-plane stress on diag(F, 1) differs from that on F by {mismatch:.2g} "
                "(relative): it is not the plane-strain restriction of a 3D model"
            )
    elif mesh.dim == 2 and plane == "stress":
        out["stress_zz"] = np.zeros_like(out["J"])
    if why is not None:
        warnings.warn(
            f"plane strain: von_mises is written with σ_zz = 0 (the in-plane stress state) "
            f"and without stress_zz, since σ_zz cannot be taken from the 3D embedding of ψ "
            f"{psi_name(psi)!r}: {why}",
            UserWarning,
            stacklevel=3,
        )
    # in numpy: eager jnp ops took 0.09 s (dispatch + compile or persistent-cache loads)
    # in a fresh CLI process, numpy takes 2 ms at 27k nodes
    vm = _von_mises(np.asarray(nodal).reshape(-1, 3, 3), np)
    points = {"cauchy_stress_nodal": nodal, "von_mises_nodal": vm}
    return out, points


def reaction_force(
    psi, x, mesh: Mesh, params, dirichlet: Dirichlet, f_ext=None, inertia=None
) -> jax.Array:
    """Total force ``(dim,)`` that the supports exert on the body at the prescribed dofs.

    At equilibrium the internal forces balance loads and reactions; the reaction on each
    prescribed dof is ``∂Π/∂x`` there (elastic gradient minus external load). Summed over
    the set, it balances the applied loads: ``reaction + Σ f_ext = 0`` in statics.
    """
    for name, a in (("f_ext", f_ext), ("inertia", inertia), ("dirichlet.mask", dirichlet.mask)):
        if a is not None:
            check_positions(a, mesh, name=name, where="reaction_force")
    r = -forces(psi, x, mesh, params)
    if f_ext is not None:
        r = r - f_ext
    if inertia is not None:
        r = r + inertia
    return jnp.sum(jnp.where(dirichlet.mask, r, 0.0), axis=0)


def facet_tractions(psi, x, mesh: Mesh, params, facets) -> np.ndarray:
    """Nominal traction ``τ = P·N`` ``(m, dim)`` on boundary facets (force / reference area).

    P is the weighted average over the quadrature points of the cell that owns each facet
    (the one value for P1; of P(F̄) under F-bar), N is the outward rest normal of that cell
    (whatever the order of the facet's nodes).

    Raises:
        ValueError: a row that is not a boundary facet (interior facets are refused).
    """
    check_positions(x, mesh, where="facet_tractions")
    check_psi(psi, mesh.dim, mesh.points.dtype, params, mesh.n_cells, where="facet_tractions")
    facets = np.asarray(facets, dtype=np.int64)
    el = mesh.element_type
    d = mesh.dim
    cidx = facet_owners(mesh, facets, where="facet_tractions")  # boundary facets only
    _, _, N = facet_integrals(mesh.points, facets, el)
    # outward from the owning cell whatever the facet's node order: N points away from
    # the cell's centroid (the cell lies on one side of its own facet)
    X = np.asarray(mesh.points, dtype=np.float64)
    cells = np.asarray(mesh.cells)
    away = X[facets[:, :d]].mean(1) - X[cells[cidx, : d + 1]].mean(1)  # (m, d)
    N = np.where(np.sum(np.asarray(N) * away, axis=1, keepdims=True) < 0, -N, N)
    return np.asarray(_tractions(psi, x, mesh, params, jnp.asarray(cidx), jnp.asarray(N)))


@functools.partial(jax.jit, static_argnums=0)
def _tractions(psi, x, mesh, params, cidx, N):
    F = deformation_gradients(x, mesh)[cidx]  # (m, q, d, d)
    w = mesh.weights[cidx]  # (m, q)
    ax = jax.tree_util.tree_map(lambda leaf: None if jnp.ndim(leaf) == 0 else 0, params)
    p = jax.tree_util.tree_map(lambda leaf: leaf if jnp.ndim(leaf) == 0 else leaf[cidx], params)
    Pq = jax.vmap(over_quadrature(first_piola(psi)), in_axes=(0, ax))(F, p)
    P = jnp.einsum("mq,mqij->mij", w, Pq) / jnp.sum(w, axis=1)[:, None, None]
    return jnp.einsum("mij,mj->mi", P, N.astype(P.dtype))
