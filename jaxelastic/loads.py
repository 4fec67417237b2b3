"""Boundary conditions and loads: Dirichlet data, tractions, point loads, gravity, masses,
pressure on cavities.

Node sets are chosen on the host (NumPy) once per scene: by predicate on rest positions, by
box or plane, or from a mesh file's physical groups (:mod:`jaxelastic.io`). Dead loads
(tractions per reference area, point loads, body forces) are integrated once into a
constant nodal vector ``f_ext`` of shape ``(n_nodes, dim)`` [force]; the solvers add
``−f_extᵀx`` to the potential only when a scene has loads.

Pressure on cavity boundaries (a follower load on the deformed surface) is not a constant
vector but a term of the potential, ``−p V(x)``: :func:`pressure_load` builds it from the
same facet sets (:class:`~jaxelastic.mechanics.pressure.Pressure`, for
``Potential(..., pressure=...)``).

Consistent integration: a constant traction t on a facet gives ``t·∫N_a dA`` to its nodes
(linear facets: ``A·t/dim`` each; 3-node P2 edges: ``A/6, A/6, 2A/3``; 6-node P2 triangles:
0 at corners and ``A/3`` at mid-nodes; composite facets are piecewise linear), integrated
with the isoparametric facet geometry (:func:`facet_integrals`). Masses are lumped: row sums
for P1 and composite cells, HRZ diagonal scaling for P2 (:func:`lumped_mass`); gravity is
mass × g by default, or the consistent ``∫ρ g N_a dV`` (``consistent=True``).

The builders return NumPy arrays in the mesh's float dtype (so a float32 mesh gets float32
loads and masses, which :class:`~jaxelastic.mechanics.potential.Potential` requires) and
refuse arguments of the wrong shape with a message naming the argument, the expected and the
given shape. Reactions and facet tractions of a solved state are in
:mod:`jaxelastic.postprocess`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from numpy.typing import ArrayLike

from .deprecation import moved_attributes
from .mechanics.pressure import Pressure, pressure_term
from .mesh import Mesh, boundary_facets, facet_owners, geometry
from .mesh.elements import Element

__all__ = [
    "Dirichlet",
    "fix",
    "combine",
    "with_rest_points",
    "no_dirichlet",
    "nodes_where",
    "nodes_in_box",
    "nodes_on_plane",
    "facets_where",
    "facet_normals",
    "facet_integrals",
    "traction_load",
    "pressure_load",
    "point_load",
    "gravity_load",
    "lumped_mass",
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


def _mesh_dtype(mesh: Mesh, a) -> np.ndarray:
    """``a`` as a NumPy array in the mesh's float dtype (a JAX array where ``a`` is
    traced: a load of a moved rest shape, :meth:`~jaxelastic.mesh.Mesh.with_points`)."""
    if isinstance(a, Tracer):
        return a.astype(mesh.points.dtype)  # pyright: ignore[reportReturnType]
    return np.asarray(a, dtype=np.dtype(mesh.points.dtype))


def _rest_points(points):
    """Rest points for the geometry: float64 NumPy, or the JAX array itself when traced
    (then the loads are differentiable with respect to them)."""
    if isinstance(points, Tracer):
        return points
    return np.asarray(points, dtype=np.float64)


def _per_item(value, m: int, d: int, name: str, what: str) -> np.ndarray:
    """``value`` ``(d,)`` or ``(m, d)`` broadcast to ``(m, d)`` float64, or a ValueError
    naming ``name``, the expected and the given shape."""
    v = np.asarray(value, dtype=np.float64)
    if v.shape not in ((d,), (1, d), (m, d)):
        raise ValueError(
            f"{name} must have shape ({d},) or ({m}, {d}) (one per {what}), got {v.shape}"
        )
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be finite, got {np.count_nonzero(~np.isfinite(v))} NaN/inf")
    return np.broadcast_to(v, (m, d))


def _node_array(nodes, n: int) -> np.ndarray:
    idx = np.asarray(nodes)
    if idx.dtype == bool:
        if idx.shape != (n,):
            raise ValueError(f"boolean node mask must have shape ({n},), got {idx.shape}")
        idx = np.flatnonzero(idx)
    if idx.size and idx.dtype.kind not in "iu":
        raise ValueError(
            f"node indices must be integers (or a boolean mask of shape ({n},)), got dtype "
            f"{idx.dtype}"
        )
    idx = idx.astype(np.int64).ravel()
    if idx.size and (idx.min() < 0 or idx.max() >= n):
        raise ValueError(f"node indices must lie in [0, {n})")
    return idx


def fix(
    mesh: Mesh,
    nodes,
    components=None,
    displacement: ArrayLike | Callable | None = None,
) -> Dirichlet:
    """Prescribe the displacement of ``nodes`` (all components or some).

    Args:
        mesh: the mesh (rest positions X).
        nodes: node indices ``(m,)`` or a boolean mask ``(n_nodes,)``.
        components: which components to prescribe, e.g. ``(0,)`` or ``(0, 2)``; all when None.
            Integers only: ``fix(mesh, nodes, [0.4, 0, 0])`` is refused (a displacement
            goes in ``displacement=``).
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
    comps = np.arange(d) if components is None else _components(components, d)
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


def with_rest_points(bc: Dirichlet, old_points, new_points) -> Dirichlet:
    """``bc`` on a moved rest shape: the same mask and prescribed *displacements*.

    The values of a :class:`Dirichlet` are positions ``X + u``; when the rest points move
    from ``old_points`` to ``new_points`` (:meth:`~jaxelastic.mesh.Mesh.with_points`), the
    prescribed dofs follow them: ``values = new + (values − old)``. Pure and differentiable
    in ``new_points`` (shape gradients, :func:`jaxelastic.unloaded_shape`).

    Args:
        bc: Dirichlet data built on the rest points ``old_points`` ``(n_nodes, dim)``.
        new_points: ``(n_nodes, dim)`` the moved rest points.
    """
    new = jnp.asarray(new_points)
    old = jnp.asarray(old_points, new.dtype)
    values = jnp.asarray(bc.values, new.dtype)
    return Dirichlet(mask=bc.mask, values=new + (values - old))


def _components(components, d: int) -> np.ndarray:
    """``components`` as int64 axis indices, refusing anything that is not an integer
    (a displacement vector passed in its place, booleans)."""
    a = np.asarray(components)
    if a.dtype == bool or not np.issubdtype(a.dtype, np.integer):
        raise TypeError(
            f"fix(): components must be integer axis indices in 0..{d - 1} (e.g. (0,) or "
            f"(0, 2)), got {components!r}; to prescribe a displacement pass it as "
            f"displacement=..., e.g. fix(mesh, nodes, displacement={components!r})"
        )
    return a.astype(np.int64).ravel()


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


def nodes_on_plane(
    mesh: Mesh, axis: int | str, value: float, tol: float | None = None
) -> np.ndarray:
    """Indices of nodes with ``X[axis] ≈ value`` (tolerance relative to the mesh size);
    ``axis`` an index ``0 … dim−1`` or ``"x"``, ``"y"``, ``"z"``."""
    X = np.asarray(mesh.points)
    d = X.shape[1]
    if isinstance(axis, str) and axis in "xyz"[:d] and len(axis) == 1:
        axis = "xyz".index(axis)
    if isinstance(axis, bool) or not isinstance(axis, (int, np.integer)) or not 0 <= axis < d:
        names = ", ".join(f'"{c}"' for c in "xyz"[:d])
        raise ValueError(f"axis must be 0 … {d - 1} or {names} for a {d}D mesh, got {axis!r}")
    if tol is None:
        tol = 1e-8 * max(float(np.ptp(X, axis=0).max()), 1.0)
    return nodes_where(mesh, lambda X: np.abs(X[:, axis] - value) <= tol)


def facets_where(mesh: Mesh, predicate: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """Boundary facets ``(m, n_facet_nodes)`` whose every node satisfies
    ``predicate(X) -> bool`` (corners and, for P2/composite meshes, mid-edge nodes)."""
    facets = boundary_facets(mesh)
    ok = np.asarray(predicate(np.asarray(mesh.points)), dtype=bool)
    return facets[ok[facets].all(axis=1)]


def _facet_element(dim: int, n_facet_nodes: int, element: Element | str | None) -> Element:
    from .mesh.elements import get_element

    if element is not None:
        el = get_element(element) if isinstance(element, str) else element
    else:
        el = get_element(
            {(2, 2): "tri3", (3, 3): "tet4", (2, 3): "tri6", (3, 6): "tet10"}.get(
                (dim, n_facet_nodes), "tri3"
            )
        )
    if el.dim != dim or len(el.facet_nodes[0]) != n_facet_nodes:
        raise ValueError(
            f"{n_facet_nodes}-node facets in {dim}D do not belong to element {el.name!r}"
        )
    return el


def facet_integrals(points, facets, element: Element | str | None = None):
    """Integrals over rest boundary facets with the element's facet interpolation.

    Args:
        points: ``(n_nodes, dim)`` rest positions (traced points give JAX arrays, so shape
            gradients flow through facet areas and normals; see
            :func:`~jaxelastic.mesh.geometry.facet_integrals`).
        facets: ``(m, n_facet_nodes)`` node indices (as :func:`~jaxelastic.mesh.boundary_facets`).
        element: the mesh's element (name or :class:`~jaxelastic.mesh.elements.Element`); by
            default P1 or P2 from the number of facet nodes (composite meshes: pass it).

    Returns:
        ``(shape_integrals (m, n_facet_nodes), area (m,), normal (m, dim))``: ``∫N_a dA``
        per facet node, the facet measure, and the unit outward normal of the facet's
        vector area ``∫n dA`` (the exact normal for straight facets).
    """
    X = _rest_points(points)
    facets = np.asarray(facets, dtype=np.int64)
    if facets.ndim != 2:
        raise ValueError(f"facets must have shape (m, n_facet_nodes), got {facets.shape}")
    el = _facet_element(X.shape[1], facets.shape[1], element)
    return geometry.facet_integrals(X, facets, el)


def facet_normals(points, facets, element: Element | str | None = None):
    """Unit outward normals ``(m, dim)`` and measures ``(m,)`` of boundary facets
    (``(m, dim)`` linear facets or P2 facets; see :func:`facet_integrals`)."""
    _, area, normal = facet_integrals(points, facets, element)
    return normal, area


def traction_load(mesh: Mesh, facets, traction) -> np.ndarray:
    """Nodal forces ``(n_nodes, dim)`` of a dead traction on boundary facets.

    Args:
        facets: ``(m, n_facet_nodes)`` node indices of boundary facets (an interior
            facet, shared by two cells, is refused: its load would act inside the body).
        traction: force per *reference* area, ``(dim,)`` or ``(m, dim)`` [Pa];
            a callable ``t(X_centroid (m, dim)) -> (m, dim)`` (centroid of the corners).
            Constant per facet, integrated consistently: ``f_a = t ∫N_a dA``.
    """
    X = _rest_points(mesh.points)
    facets = np.asarray(facets, dtype=np.int64)
    n, d = X.shape
    k = len(mesh.element_type.facet_nodes[0])
    if facets.ndim != 2 or facets.shape[1] != k:
        raise ValueError(
            f"facets must have shape (m, {k}) ({k}-node facets of {mesh.element}), got "
            f"{facets.shape}"
        )
    if facets.size and (facets.min() < 0 or facets.max() >= n):
        raise ValueError(f"facets reference node indices outside [0, {n})")
    if facets.size:
        facet_owners(mesh, facets, where="traction_load")  # boundary facets only
    Nint, _, _ = facet_integrals(X, facets, mesh.element_type)
    m = facets.shape[0]
    if callable(traction):
        t = np.asarray(traction(np.asarray(jax.lax.stop_gradient(X))[facets[:, :d]].mean(axis=1)))
        t = t.astype(np.float64)
        if t.shape != (m, d):
            raise ValueError(f"traction(X) must return shape ({m}, {d}), got {t.shape}")
    else:
        t = _per_item(traction, m, d, "traction", "facet")
    if isinstance(X, Tracer):  # a moved rest shape: differentiable in its points
        tj = jnp.asarray(t, X.dtype)
        vals = Nint[:, :, None] * tj[:, None, :]  # (m, k, d)
        f = jnp.zeros((n, d), X.dtype).at[facets.reshape(-1)].add(vals.reshape(-1, d))
        return _mesh_dtype(mesh, f)
    f = np.zeros((n, d))
    for a in range(facets.shape[1]):
        np.add.at(f, facets[:, a], Nint[:, a, None] * t)
    return _mesh_dtype(mesh, f)


def pressure_load(mesh: Mesh, facets, pressure, origin=None, *, follower: bool = False) -> Pressure:
    """A follower pressure on boundary facets as a potential term ``−Σ_s p_s V_s(x)``.

    Args:
        facets: ``(m, n_facet_nodes)`` boundary facets (e.g. :func:`facets_where`), or a
            list of such arrays, one per cavity surface.
        pressure: [Pa] ``()`` or one per surface; positive pushes against the body's outward
            normal, into the body (an internal pressure inflates its cavity).
        origin: the closing point of each surface's opening (default: the rest centroid of
            its rim); a rim sliding on a symmetry plane needs it on that plane.

    Returns:
        A :class:`~jaxelastic.mechanics.pressure.Pressure` for
        ``Potential(..., pressure=...)``; ``term.volumes(x)`` gives the cavity volumes. It is
        exact (conservative) for closed cavities and for rims that are fixed or slide on a
        symmetry plane; :func:`jaxelastic.solve` checks that against its Dirichlet data.
        ``follower=True`` declares an open surface whose rim moves: the exact follower
        residual, no potential, a non-symmetric tangent (Newton solves with it by GMRES:
        :attr:`~jaxelastic.solvers.newton.Newton.tangent`).
    """
    return pressure_term(mesh, facets, pressure, origin, follower=follower)


def point_load(mesh: Mesh, nodes, force) -> np.ndarray:
    """Nodal forces ``(n_nodes, dim)`` with ``force`` ``(dim,)`` or ``(m, dim)`` on ``nodes``."""
    X = np.asarray(mesh.points, dtype=np.float64)
    idx = _node_array(nodes, X.shape[0])
    f = np.zeros_like(X)
    np.add.at(f, idx, _per_item(force, idx.size, X.shape[1], "force", "node"))
    return _mesh_dtype(mesh, f)


def _density(mesh: Mesh, density) -> np.ndarray:
    rho = np.asarray(density, float)
    if rho.shape not in ((), (mesh.n_cells,)):
        raise ValueError(
            f"density must be a scalar or have shape ({mesh.n_cells},) (one per cell), got "
            f"{rho.shape}"
        )
    rho = np.broadcast_to(rho, (mesh.n_cells,))
    if np.any(rho <= 0) or not np.all(np.isfinite(rho)):
        raise ValueError("density must be finite and > 0")
    return rho


def _scatter(mesh: Mesh, cells: np.ndarray, share: np.ndarray) -> np.ndarray:
    m = np.zeros(mesh.n_nodes)
    for a in range(cells.shape[1]):
        np.add.at(m, cells[:, a], share[:, a])
    return m


def lumped_mass(mesh: Mesh, density) -> np.ndarray:
    """Lumped nodal masses ``(n_nodes,)`` [kg] from density ρ [kg/m^dim] (scalar or per cell).

    * P1: row sums, ``m_a = Σ_c ρ_c |T_c| / (dim + 1)``;
    * composite (``tri3x4``/``tet4x8``): row sums over the linear sub-simplices;
    * P2: HRZ diagonal scaling (Hinton, Rock & Zienkiewicz 1976, *Earthquake Eng. Struct.
      Dyn.* 4:245): ``m_a = ρ V M_aa / Σ_b M_bb`` with ``M_aa = ∫N_a² dV`` (row sums would
      give zero corner masses for ``tri6`` and negative ones for ``tet10``). All positive;
      each cell's masses add up to ρV.
    """
    rho = _density(mesh, density)
    X = _rest_points(mesh.points)
    traced = isinstance(X, Tracer)
    w = mesh.weights if traced else np.asarray(mesh.weights, dtype=np.float64)
    cells = mesh.cells if traced else np.asarray(mesh.cells)
    return _mesh_dtype(mesh, geometry.lumped_masses(X, cells, mesh.element_type, w, rho))


def gravity_load(mesh: Mesh, density, g, *, consistent: bool = False) -> np.ndarray:
    """Nodal body forces ``(n_nodes, dim)`` of gravity ``g`` (``(dim,)`` [m/s²]).

    By default lumped mass × g, so a body in free fall under :mod:`~jaxelastic.dynamics`
    (which uses the same lumped masses) accelerates rigidly. ``consistent=True`` gives the
    work-equivalent ``ρ g ∫N_a dV`` (identical for P1 and composite cells; for P2 it is the
    load of the optimal convergence rates, with negative corner shares on ``tet10``).
    """
    gv = np.asarray(g, float)
    if gv.shape != (mesh.dim,):
        raise ValueError(f"g must have shape ({mesh.dim},) for a {mesh.dim}D mesh, got {gv.shape}")
    if not np.isfinite(gv).all():
        raise ValueError(f"g must be finite, got {gv.tolist()}")
    X = _rest_points(mesh.points)
    if isinstance(X, Tracer):  # a moved rest shape: differentiable in its points
        gj = jnp.asarray(gv, X.dtype)
        if not consistent or mesh.element_type.order == 1:
            return _mesh_dtype(mesh, lumped_mass(mesh, density)[:, None] * gj[None, :])
        n1, _ = geometry.consistent_shape_integrals(X, mesh.cells, mesh.element_type)
        rho_j = jnp.asarray(_density(mesh, density), X.dtype)
        f = (
            jnp.zeros(X.shape[0], X.dtype)
            .at[mesh.cells.reshape(-1)]
            .add((rho_j[:, None] * n1).reshape(-1))
        )
        return _mesh_dtype(mesh, f[:, None] * gj[None, :])
    if not consistent or mesh.element_type.order == 1:
        return _mesh_dtype(mesh, lumped_mass(mesh, density).astype(np.float64)[:, None] * gv)
    rho = _density(mesh, density)
    n1, _ = geometry.consistent_shape_integrals(X, np.asarray(mesh.cells), mesh.element_type)
    return _mesh_dtype(
        mesh, _scatter(mesh, np.asarray(mesh.cells), rho[:, None] * n1)[:, None] * gv
    )


# reactions and facet tractions moved to jaxelastic.postprocess (a higher layer: the
# forward imports it by name, on access only); the old names still resolve
__getattr__ = moved_attributes(
    __name__,
    "jaxelastic.loads",
    {
        n: (f"jaxelastic.postprocess:{n}", f"jaxelastic.postprocess.{n}")
        for n in ("reaction_force", "facet_tractions")
    },
)
