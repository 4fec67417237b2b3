"""Rest geometry as functions of the rest points: Jacobians, shape-function gradients,
quadrature weights, facet integrals, lumped masses, and the check of the rest cells.

Everything here is a function of ``(points, cells, element)`` and nothing else: the cells
(and every table derived from them: incidence, sparsity patterns, partitions) are topology,
prepared once on the host; the points are the rest *geometry*. Each function runs on either
array library:

* NumPy input (the host, float64): what :func:`~jaxelastic.mesh.from_arrays` and the load
  builders of :mod:`jaxelastic.loads` use on concrete meshes, exactly as before;
* JAX input (concrete or traced): what :meth:`~jaxelastic.mesh.Mesh.with_points` uses, so
  ``jax.grad``/``jax.jvp`` of any loss flow to the rest points through the rest quantities
  (``dN``, weights, facet areas and normals, masses). Inverses and determinants are the
  closed forms for 2×2 and 3×3 matrices (no batched LAPACK, smooth derivatives).

The formulas are those of the isoparametric map ``X(ξ) = Σ_a N_a(ξ) X_a``:
``J = ∂X/∂ξ = Σ_a X_a ⊗ ∇̂N_a``, ``∇N_a = J⁻ᵀ∇̂N_a``, ``dV = det J dξ`` (Zienkiewicz, Taylor &
Zhu, *The FEM: its basis and fundamentals*, 7th ed., §6.5); composite elements use the same
with each sub-simplex's constant gradients (:mod:`~jaxelastic.mesh.elements`).

A rest cell is *valid* when ``det J > 0`` at every quadrature point and its measure is not
negligible against its longest edge (``min_q det J / h^dim ≥ 1e-12``, the test of
:func:`~jaxelastic.mesh.from_arrays`). :func:`invalid_cells` gives the flag per cell (usable
under jit); :func:`check_rest_cells` raises a :class:`~jaxelastic.mesh.MeshError` naming them
(outside jit).
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer

from .elements import Element, facet_rule

__all__ = [
    "RELATIVE_MEASURE_MIN",
    "array_module",
    "rest_jacobians",
    "inverse_and_det",
    "rest_quantities",
    "relative_measures",
    "invalid_cells",
    "describe_invalid",
    "facet_integrals",
    "lumped_masses",
    "consistent_shape_integrals",
    "quadrature_points",
]

RELATIVE_MEASURE_MIN = 1e-12
"""A cell whose smallest ``det J / h^dim`` (h: its longest vertex-to-vertex edge) is below
this is degenerate (collapsed): refused by :func:`~jaxelastic.mesh.from_arrays` and flagged
by :func:`invalid_cells`."""


def array_module(*arrays):
    """``jax.numpy`` if any argument is a JAX array (concrete or traced), else ``numpy``."""
    return jnp if any(isinstance(a, jax.Array | Tracer) for a in arrays) else np


def _const(xp, a, like):
    """The NumPy constant ``a`` in ``like``'s library and float dtype (strict promotion)."""
    return xp.asarray(a, dtype=like.dtype) if xp is jnp else np.asarray(a, dtype=np.float64)


def rest_jacobians(points, cells, element: Element):
    """Rest Jacobians ``J = ∂X/∂ξ`` at the quadrature points, ``(n_cells, n_q, dim, dim)``
    (``= Dm`` for P1).

    Args:
        points: ``(n_nodes, dim)`` rest positions [length]; cells: ``(n_cells, k)`` int;
        element: the cells' :class:`~jaxelastic.mesh.elements.Element`.
    """
    xp = array_module(points)
    gref = _const(xp, element.shape_gradients(), points)  # (q, k, d)
    xe = points[cells]  # (c, k, d)
    if xp is np:
        return np.matmul(xe.swapaxes(1, 2)[:, None], gref[None])  # (BLAS; einsum 2x slower)
    # one dot_general with no batch dimension (contract k): a GEMM, not tiny batched dots
    return jnp.einsum("cka,qkb->cqab", xe, gref)


def inverse_and_det(J):
    """``(J⁻¹, det J)`` of a stack of 2×2 or 3×3 matrices ``(..., d, d)``.

    NumPy: LAPACK (``np.linalg``). JAX: the adjugate closed form (no batched LAPACK, which
    deadlocks in multi-device programs; smooth derivatives of every order). Where
    ``det J == 0`` the JAX inverse is the adjugate itself (finite), never inf/NaN: such a
    cell is invalid (:func:`invalid_cells`) and reported, not divided by zero.
    """
    if array_module(J) is np:
        with np.errstate(all="ignore"):  # over/underflow and singular cells: refused by callers
            return np.linalg.inv(J), np.linalg.det(J)
    d = J.shape[-1]
    if d == 2:
        det = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
        adj = jnp.stack(
            [
                jnp.stack([J[..., 1, 1], -J[..., 0, 1]], axis=-1),
                jnp.stack([-J[..., 1, 0], J[..., 0, 0]], axis=-1),
            ],
            axis=-2,
        )
    elif d == 3:
        c0 = jnp.cross(J[..., :, 1], J[..., :, 2])  # columns of cof J
        c1 = jnp.cross(J[..., :, 2], J[..., :, 0])
        c2 = jnp.cross(J[..., :, 0], J[..., :, 1])
        det = jnp.sum(J[..., :, 0] * c0, axis=-1)
        adj = jnp.stack([c0, c1, c2], axis=-2)  # rows of adj J = (cof J)ᵀ
    else:
        raise ValueError(f"inverse_and_det expects 2x2 or 3x3 matrices, got {J.shape[-2:]}")
    safe = jnp.where(det != 0, det, 1.0)
    return adj / safe[..., None, None], det


def rest_quantities(points, cells, element: Element):
    """The rest quantities the mechanics needs: ``(dN, weights, detJ)``.

    Returns:
        ``dN`` ``(n_cells, n_q, k, dim)`` physical shape-function gradients ``∇̂N J⁻¹``
        [1/length]; ``weights`` ``(n_cells, n_q)`` quadrature weights times ``det J``
        [length^dim] (their row sums are the cell measures); ``detJ`` ``(n_cells, n_q)``.
        In the points' library and (JAX) float dtype.
    """
    xp = array_module(points)
    J = rest_jacobians(points, cells, element)
    Jinv, detJ = inverse_and_det(J)
    gref = _const(xp, element.shape_gradients(), points)  # (q, k, d)
    qw = _const(xp, element.quad_weights, points)
    if xp is np:
        dN = np.matmul(gref[None], Jinv)  # (c, q, k, d)
    else:  # unrolled over the reference axis (fused, no batched tiny matmul)
        d = gref.shape[-1]
        dN = sum(gref[None, :, :, j, None] * Jinv[:, :, None, j, :] for j in range(d))
    return dN, detJ * qw[None, :], detJ


def relative_measures(points, cells, element: Element, detJ=None):
    """``min_q det J / h^dim`` per cell, ``(n_cells,)`` (h: the longest vertex-to-vertex
    edge; dimensionless): 1/2 (2D) or 1/6 (3D) times a shape-quality number, negative for
    inverted cells, ≈ 0 for collapsed ones. ``detJ``: from :func:`rest_quantities` if known."""
    xp = array_module(points)
    if detJ is None:
        detJ = rest_quantities(points, cells, element)[2]
    dim = element.dim
    h2 = None
    for a, b in itertools.combinations(range(dim + 1), 2):  # the simplex's vertices
        e = points[cells[:, a]] - points[cells[:, b]]
        s = xp.sum(e * e, axis=1)
        h2 = s if h2 is None else xp.maximum(h2, s)
    assert h2 is not None
    tiny = xp.finfo(detJ.dtype).tiny
    h = xp.sqrt(xp.maximum(h2, tiny))
    return xp.min(detJ, axis=1) / h**dim


def invalid_cells(mesh):
    """Bool ``(n_cells,)``: rest cells that are inverted (``det J ≤ 0`` somewhere) or
    collapsed (relative measure below :data:`RELATIVE_MEASURE_MIN`), or whose geometry is
    not finite. Pure and jit-able (a flag inside jit; :func:`describe_invalid` outside)."""
    xp = array_module(mesh.points)
    pts, cells = mesh.points, mesh.cells
    if xp is np:
        pts, cells = np.asarray(pts), np.asarray(cells)
    detJ = mesh.weights / _const(xp, mesh.element_type.quad_weights, mesh.weights)[None, :]
    rel = relative_measures(pts, cells, mesh.element_type, detJ)
    finite = xp.all(xp.isfinite(mesh.dN), axis=(1, 2, 3)) & xp.isfinite(rel)
    return ~(finite & (rel >= RELATIVE_MEASURE_MIN))


def describe_invalid(mesh, bad) -> str:
    """A message naming the invalid rest cells ``bad`` (bool ``(n_cells,)``, concrete) of
    ``mesh``: how many, the first few indices with their nodes, and whether they are
    inverted or collapsed."""
    bad = np.asarray(bad, dtype=bool)
    idx = np.flatnonzero(bad)
    cells = np.asarray(mesh.cells)
    w = np.asarray(mesh.weights)
    inverted = idx[(w[idx] < 0).any(axis=1)]
    kinds = []
    if inverted.size:
        kinds.append(f"{inverted.size} inverted (det J < 0)")
    if idx.size - inverted.size:
        kinds.append(f"{idx.size - inverted.size} collapsed or non-finite (measure ≈ 0)")
    first = "; ".join(f"cell {c}: nodes {cells[c].tolist()}" for c in idx[:5])
    return f"{idx.size} rest cell(s) are invalid ({', '.join(kinds)}), e.g. {first}" + (
        " …" if idx.size > 5 else ""
    )


def _scatter_add(xp, n: int, idx, vals):
    """``out[idx[i]] += vals[i]``: ``(n, …)`` from ``idx`` ``(m,)`` and ``vals`` ``(m, …)``."""
    if xp is np:
        out = np.zeros((n,) + vals.shape[1:])
        np.add.at(out, idx, vals)
        return out
    return jnp.zeros((n,) + vals.shape[1:], vals.dtype).at[idx].add(vals)


def facet_integrals(points, facets, element: Element):
    """Integrals over rest boundary facets with the element's facet interpolation.

    Args:
        points: ``(n_nodes, dim)`` rest positions [length].
        facets: ``(m, n_facet_nodes)`` int node indices (as
            :func:`~jaxelastic.mesh.boundary_facets`).
        element: the mesh's :class:`~jaxelastic.mesh.elements.Element`.

    Returns:
        ``(shape_integrals (m, n_facet_nodes), area (m,), normal (m, dim))``: ``∫N_a dA``
        per facet node [length^(dim-1)], the facet measure, and the unit outward normal of
        the facet's vector area ``∫n dA`` (the exact normal for straight facets).
    """
    xp = array_module(points)
    d = points.shape[1]
    N, dN, w = (_const(xp, a, points) for a in facet_rule(element))  # (r,k), (r,k,d-1), (r,)
    T = xp.einsum("mka,rkb->mrab", points[facets], dN)  # tangents (m, r, d, d-1)
    if d == 2:
        nvec = xp.stack([T[..., 1, 0], -T[..., 0, 0]], axis=-1)  # (t_y, -t_x)
    else:
        nvec = xp.cross(T[..., 0], T[..., 1])
    da = xp.sqrt(xp.sum(nvec * nvec, axis=-1))  # (m, r) surface Jacobian
    area = da @ w
    vec = xp.einsum("r,mra->ma", w, nvec)
    normal = vec / xp.sqrt(xp.sum(vec * vec, axis=1, keepdims=True))
    return xp.einsum("r,mr,rk->mk", w, da, N), area, normal


def consistent_shape_integrals(points, cells, element: Element):
    """Per cell, with the element's mass rule (degree ≥ 4): ``(∫N_a dV, ∫N_a² dV)``, each
    ``(n_cells, k)`` [length^dim] (P2 cells: the consistent body load and HRZ lumping)."""
    xp = array_module(points)
    xi, w = element.mass_rule()
    N = _const(xp, element.shape_functions(xi), points)  # (r, k)
    G = element.shape_gradients(xi)  # (r, k, d)
    J = xp.einsum("cka,rkb->crab", points[cells], _const(xp, G, points))
    _, detJ = inverse_and_det(J)  # (c, r)
    wd = detJ * _const(xp, w, points)[None, :]
    return wd @ N, wd @ (N * N)


def quadrature_points(points, cells, element: Element):
    """Rest positions of the quadrature points, ``(n_cells, n_q, dim)`` [length]:
    ``X_q = Σ_a N_a(ξ_q) X_a`` (composite elements: the centroid of each linear
    sub-simplex, its one quadrature point). The points where per-point material data
    (:class:`~jaxelastic.mechanics.quadrature_fields.AtQuadrature`) is sampled."""
    xp = array_module(points)
    xe = points[cells]  # (c, k, d)
    if element.is_composite:
        sub = np.asarray(element.sub_cells)  # (q, d + 1)
        return xe[:, sub].mean(axis=2)
    N = _const(xp, element.shape_functions(element.quad_points), points)  # (q, k)
    return xp.einsum("qk,cka->cqa", N, xe)


def lumped_masses(points, cells, element: Element, weights, density):
    """Lumped nodal masses ``(n_nodes,)`` [mass] from density ρ (scalar or ``(n_cells,)``).

    * P1: row sums, ``m_a = Σ_c ρ_c |T_c| / (dim + 1)``;
    * composite (``tri3x4``/``tet4x8``): row sums over the linear sub-simplices;
    * P2: HRZ diagonal scaling (Hinton, Rock & Zienkiewicz 1976, *Earthquake Eng. Struct.
      Dyn.* 4:245): ``m_a = ρ V M_aa / Σ_b M_bb`` with ``M_aa = ∫N_a² dV``.

    Args:
        points, cells, element: the rest geometry; weights: ``(n_cells, n_q)`` its
            quadrature weights (:func:`rest_quantities`); density: ρ [mass/length^dim],
            already checked (finite, positive).
    """
    xp = array_module(points, weights, density)
    n_cells = cells.shape[0]
    rho = xp.broadcast_to(xp.asarray(density, dtype=weights.dtype), (n_cells,))
    n = points.shape[0]
    if element.is_composite:
        sub = np.asarray(element.sub_cells)  # (s, d+1)
        share = weights * rho[:, None] / (element.dim + 1)  # (c, s)
        idx = cells[:, sub].reshape(-1)  # (c·s·(d+1),)
        vals = xp.broadcast_to(share[:, :, None], (n_cells, sub.shape[0], sub.shape[1]))
        return _scatter_add(xp, n, idx, vals.reshape(-1))
    k = cells.shape[1]
    if element.order == 1:
        share = rho * xp.sum(weights, axis=1) / k  # (c,)
        return _scatter_add(xp, n, cells.reshape(-1), xp.repeat(share, k))
    n1, n2 = consistent_shape_integrals(points, cells, element)
    vol = xp.sum(n1, axis=1)
    share = (rho * vol)[:, None] * n2 / xp.sum(n2, axis=1, keepdims=True)  # (c, k)
    return _scatter_add(xp, n, cells.reshape(-1), share.reshape(-1))
