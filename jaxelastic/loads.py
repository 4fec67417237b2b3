"""Boundary conditions and loads: Dirichlet data, tractions, point loads, gravity, reactions.

Node sets are chosen on the host (NumPy) once per scene: by predicate on rest positions, by
box or plane, or from a mesh file's physical groups (:mod:`jaxelastic.io`). Dead loads
(tractions per reference area, point loads, body forces) are integrated once into a
constant nodal vector ``f_ext`` of shape ``(n_nodes, dim)`` [force]; the solvers add
``−f_extᵀx`` to the potential only when a scene has loads.

Consistent integration on linear facets/cells: a constant traction t on a facet of rest
measure A gives ``A·t/dim`` to each of its ``dim`` nodes (∫N_a dA = A/dim); a body force
density ρg on a cell of rest measure V gives ``ρ g V/(dim+1)`` per node, which is also the
lumped mass times g.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .energy import first_piola, forces
from .kinematics import deformation_gradients
from .mesh import Mesh, boundary_facets

__all__ = [
    "Dirichlet",
    "fix",
    "combine",
    "no_dirichlet",
    "nodes_where",
    "nodes_in_box",
    "nodes_on_plane",
    "facets_where",
    "facet_normals",
    "traction_load",
    "point_load",
    "gravity_load",
    "lumped_mass",
    "reaction_force",
    "facet_tractions",
]


class Dirichlet(NamedTuple):
    """Prescribed positions on a subset of degrees of freedom.

    Attributes:
        mask: ``(n_nodes, dim)`` bool, True where the dof is prescribed.
        values: ``(n_nodes, dim)`` prescribed *positions* at those dofs (ignored elsewhere).
    """

    mask: jax.Array
    values: jax.Array


def no_dirichlet(mesh: Mesh) -> Dirichlet:
    """No prescribed dofs (free-floating body: only valid with inertia)."""
    return Dirichlet(mask=jnp.zeros(mesh.points.shape, dtype=bool), values=jnp.asarray(mesh.points))


def _node_array(nodes, n: int) -> np.ndarray:
    idx = np.asarray(nodes)
    if idx.dtype == bool:
        if idx.shape != (n,):
            raise ValueError(f"boolean node mask must have shape ({n},), got {idx.shape}")
        idx = np.flatnonzero(idx)
    idx = idx.astype(np.int64).ravel()
    if idx.size and (idx.min() < 0 or idx.max() >= n):
        raise ValueError(f"node indices must lie in [0, {n})")
    return idx


def fix(
    mesh: Mesh,
    nodes,
    components=None,
    displacement: np.ndarray | Callable | None = None,
) -> Dirichlet:
    """Prescribe the displacement of ``nodes`` (all components or some).

    Args:
        mesh: the mesh (rest positions X).
        nodes: node indices ``(m,)`` or a boolean mask ``(n_nodes,)``.
        components: which components to prescribe, e.g. ``(0,)`` or ``(0, 2)``; all when None.
        displacement: None (clamped, u = 0), a constant ``(dim,)`` vector, an ``(m, dim)``
            array, or a function ``u(X) -> (m, dim)`` of the rest positions ``(m, dim)``.

    Returns:
        A :class:`Dirichlet` whose values are prescribed positions X + u.
    """
    X = np.asarray(mesh.points)
    n, d = X.shape
    idx = _node_array(nodes, n)
    if idx.size == 0:
        raise ValueError("fix(): the node set is empty (check the predicate/box/group)")
    comps = np.arange(d) if components is None else np.asarray(components, dtype=np.int64)
    if comps.size == 0 or comps.min() < 0 or comps.max() >= d:
        raise ValueError(f"components must be a subset of 0..{d - 1}, got {components!r}")
    if displacement is None:
        u = np.zeros((idx.size, d))
    elif callable(displacement):
        u = np.asarray(displacement(X[idx]), dtype=np.float64)
    else:
        u = np.broadcast_to(np.asarray(displacement, dtype=np.float64), (idx.size, d))
    if u.shape != (idx.size, d):
        raise ValueError(f"displacement must give shape ({idx.size}, {d}), got {u.shape}")
    if not np.isfinite(u).all():
        raise ValueError("prescribed displacement contains NaN/inf")
    mask = np.zeros((n, d), dtype=bool)
    mask[np.ix_(idx, comps)] = True
    values = X.copy()
    values[np.ix_(idx, comps)] += u[:, comps]
    return Dirichlet(mask=jnp.asarray(mask), values=jnp.asarray(values, dtype=mesh.points.dtype))


def combine(*bcs: Dirichlet) -> Dirichlet:
    """Union of Dirichlet sets; later sets override earlier ones where they overlap."""
    if not bcs:
        raise ValueError("combine() needs at least one Dirichlet set")
    mask, values = bcs[0].mask, bcs[0].values
    for b in bcs[1:]:
        values = jnp.where(b.mask, b.values, values)
        mask = mask | b.mask
    return Dirichlet(mask=mask, values=values)


def nodes_where(mesh: Mesh, predicate: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """Indices of nodes whose rest position satisfies ``predicate(X) -> (n,) bool``."""
    X = np.asarray(mesh.points)
    sel = np.asarray(predicate(X), dtype=bool)
    if sel.shape != (X.shape[0],):
        raise ValueError(f"predicate must return shape ({X.shape[0]},), got {sel.shape}")
    return np.flatnonzero(sel)


def nodes_in_box(mesh: Mesh, lo, hi, tol: float = 1e-9) -> np.ndarray:
    """Indices of nodes with ``lo − tol ≤ X ≤ hi + tol`` componentwise."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return nodes_where(mesh, lambda X: np.all((X >= lo - tol) & (X <= hi + tol), axis=1))


def nodes_on_plane(mesh: Mesh, axis: int, value: float, tol: float | None = None) -> np.ndarray:
    """Indices of nodes with ``X[axis] ≈ value`` (tolerance relative to the mesh size)."""
    X = np.asarray(mesh.points)
    if tol is None:
        tol = 1e-8 * max(float(np.ptp(X, axis=0).max()), 1.0)
    return nodes_where(mesh, lambda X: np.abs(X[:, axis] - value) <= tol)


def facets_where(mesh: Mesh, predicate: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """Boundary facets ``(m, dim)`` whose every node satisfies ``predicate(X) -> bool``."""
    facets = boundary_facets(mesh)
    ok = np.asarray(predicate(np.asarray(mesh.points)), dtype=bool)
    return facets[ok[facets].all(axis=1)]


def facet_normals(points, facets) -> tuple[np.ndarray, np.ndarray]:
    """Unit outward normals ``(m, dim)`` and measures ``(m,)`` of boundary facets."""
    P = np.asarray(points)[np.asarray(facets)]
    if P.shape[-1] == 2:
        t = P[:, 1] - P[:, 0]
        nvec = np.stack([t[:, 1], -t[:, 0]], axis=1)
    else:
        nvec = 0.5 * np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    area = np.linalg.norm(nvec, axis=1)
    return nvec / area[:, None], area


def traction_load(mesh: Mesh, facets, traction) -> np.ndarray:
    """Nodal forces ``(n_nodes, dim)`` of a dead traction on boundary facets.

    Args:
        facets: ``(m, dim)`` node indices of boundary facets.
        traction: force per *reference* area, ``(dim,)`` or ``(m, dim)`` [Pa];
            a callable ``t(X_centroid (m, dim)) -> (m, dim)``.
    """
    X = np.asarray(mesh.points)
    facets = np.asarray(facets, dtype=np.int64)
    n, d = X.shape
    _, area = facet_normals(X, facets)
    if callable(traction):
        t = np.asarray(traction(X[facets].mean(axis=1)), float)
    else:
        t = np.broadcast_to(np.asarray(traction, float), (facets.shape[0], d))
    f = np.zeros((n, d))
    share = (area[:, None] * t) / facets.shape[1]
    for a in range(facets.shape[1]):
        np.add.at(f, facets[:, a], share)
    return f


def point_load(mesh: Mesh, nodes, force) -> np.ndarray:
    """Nodal forces ``(n_nodes, dim)`` with ``force`` ``(dim,)`` or ``(m, dim)`` on ``nodes``."""
    X = np.asarray(mesh.points)
    idx = _node_array(nodes, X.shape[0])
    f = np.zeros_like(X)
    np.add.at(f, idx, np.broadcast_to(np.asarray(force, float), (idx.size, X.shape[1])))
    return f


def lumped_mass(mesh: Mesh, density) -> np.ndarray:
    """Lumped (row-sum) nodal masses ``(n_nodes,)`` [kg] from density ρ [kg/m^dim]
    (scalar or per cell): ``m_a = Σ_c ρ_c |T_c| / (dim + 1)`` for P1."""
    vol = np.asarray(mesh.volumes)
    rho = np.broadcast_to(np.asarray(density, float), vol.shape)
    if np.any(rho <= 0) or not np.all(np.isfinite(rho)):
        raise ValueError("density must be finite and > 0")
    cells = np.asarray(mesh.cells)
    m = np.zeros(mesh.n_nodes)
    share = rho * vol / cells.shape[1]
    for a in range(cells.shape[1]):
        np.add.at(m, cells[:, a], share)
    return m


def gravity_load(mesh: Mesh, density, g) -> np.ndarray:
    """Nodal body forces ``(n_nodes, dim)`` of gravity ``g`` (``(dim,)`` [m/s²])."""
    return lumped_mass(mesh, density)[:, None] * np.asarray(g, float)[None, :]


def reaction_force(
    psi, x, mesh: Mesh, params, dirichlet: Dirichlet, f_ext=None, inertia=None
) -> jax.Array:
    """Total force ``(dim,)`` that the supports exert on the body at the prescribed dofs.

    At equilibrium the internal forces balance loads and reactions; the reaction on each
    prescribed dof is ``∂Π/∂x`` there (elastic gradient minus external load). Summed over
    the set, it balances the applied loads: ``reaction + Σ f_ext = 0`` in statics.
    """
    r = -forces(psi, x, mesh, params)
    if f_ext is not None:
        r = r - f_ext
    if inertia is not None:
        r = r + inertia
    return jnp.sum(jnp.where(dirichlet.mask, r, 0.0), axis=0)


def facet_tractions(psi, x, mesh: Mesh, params, facets) -> np.ndarray:
    """Nominal traction ``τ = P·N`` ``(m, dim)`` on boundary facets (force / reference area).

    P is evaluated in the cell that owns each facet (first quadrature point), N is the
    outward rest normal.
    """
    facets = np.asarray(facets, dtype=np.int64)
    el = mesh.element_type
    cells = np.asarray(mesh.cells)
    local = np.asarray(el.facet_nodes)
    all_f = np.sort(cells[:, local].reshape(-1, local.shape[1]), axis=1)
    owner = {tuple(k): i // local.shape[0] for i, k in enumerate(all_f)}
    try:
        cidx = np.array([owner[tuple(k)] for k in np.sort(facets, axis=1)])
    except KeyError as e:
        raise ValueError(f"facet {e.args[0]} is not a facet of any cell") from None
    N, _ = facet_normals(mesh.points, facets)
    F = deformation_gradients(x, mesh)[cidx, 0]
    ax = jax.tree_util.tree_map(lambda leaf: None if jnp.ndim(leaf) == 0 else 0, params)
    p = jax.tree_util.tree_map(lambda leaf: leaf if jnp.ndim(leaf) == 0 else leaf[cidx], params)
    P = jax.vmap(first_piola(psi), in_axes=(0, ax))(F, p)
    return np.asarray(jnp.einsum("mij,mj->mi", P, jnp.asarray(N)))
