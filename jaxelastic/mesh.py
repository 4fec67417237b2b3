"""The rest-shape mesh: a frozen pytree preprocessed once, and mesh generators.

A :class:`Mesh` holds the rest points, the cells, and everything about the rest shape that
the mechanics needs (shape-function gradients at quadrature points, quadrature weights
including the rest measure, and a node→cell-slot incidence table for scatter-free
assembly). It is built on the host with NumPy by :func:`from_arrays`, which validates the
input, and then passed to jitted functions *as an argument* (never closed over: closing a
jitted function over large arrays makes XLA constant-fold them at compile time).

Orientation policy: a cell with negative rest measure (clockwise triangle, left-handed
tetrahedron) is **reoriented** (two corners swapped, with their mid-edge nodes for P2) with
a :class:`UserWarning` naming how many were fixed; ``orient="refuse"`` raises instead.
Zero-measure cells are always refused, and so are P2 cells whose rest Jacobian changes
sign between quadrature points.

Elements: P1 (``tri3``/``tet4``, the default), P2 (``tri6``/``tet10``, ``order=2`` in the
generators or :func:`to_quadratic`) and the composite F-bar element (``tri3x4``/``tet4x8``,
``formulation="fbar"`` with order 1). ``Mesh.formulation`` (static) selects F-bar/B-bar in
the energy kernels; see :mod:`jaxelastic.elements` and
:func:`~jaxelastic.kinematics.f_bar`.
"""

from __future__ import annotations

import dataclasses
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from .elements import Element, get_element

__all__ = [
    "Mesh",
    "MeshError",
    "from_arrays",
    "rectangle",
    "box",
    "cook_membrane",
    "boundary_facets",
    "boundary_nodes",
    "to_quadratic",
    "with_formulation",
    "vertex_nodes",
    "linear_cells",
    "FORMULATIONS",
]

FORMULATIONS = ("standard", "fbar", "bbar")


class MeshError(ValueError):
    """Raised for invalid mesh input (the message names the problem and the offenders)."""


@dataclasses.dataclass(frozen=True)
class Mesh:
    """Rest shape of a finite-element mesh (a JAX pytree).

    Attributes:
        points: ``(n_nodes, dim)`` rest positions [length].
        cells: ``(n_cells, nodes_per_cell)`` int32 connectivity.
        dN: ``(n_cells, n_q, nodes_per_cell, dim)`` physical shape-function gradients
            ``∂N_a/∂X_j`` at quadrature points [1/length].
        weights: ``(n_cells, n_q)`` quadrature weights times the rest Jacobian
            [length^dim]; ``weights.sum(1)`` is the rest measure |T| of each cell.
        incidence: ``(n_nodes, max_valence)`` int32; entry ``c*k + a`` says node is local
            node ``a`` of cell ``c``; padded with ``n_cells*nodes_per_cell`` (a zero slot).
        element: static :class:`~jaxelastic.elements.Element` name (``"tri3"``, ``"tet4"``,
            ``"tri6"``, ``"tet10"``, ``"tri3x4"``, ``"tet4x8"``).
        formulation: static; ``"standard"`` (ψ at every quadrature point's F) or ``"fbar"``
            (F̄ = (J̄/J)^{1/d} F with J̄ the cell average of J, see
            :func:`~jaxelastic.kinematics.deformation_gradients`), or ``"bbar"`` (its
            small-strain analogue for small-strain materials, Hughes 1980).
    """

    points: jax.Array
    cells: jax.Array
    dN: jax.Array
    weights: jax.Array
    incidence: jax.Array
    element: str = dataclasses.field(metadata=dict(static=True), default="tri3")
    formulation: str = dataclasses.field(metadata=dict(static=True), default="standard")

    @property
    def dim(self) -> int:
        return self.points.shape[1]

    @property
    def n_nodes(self) -> int:
        return self.points.shape[0]

    @property
    def n_cells(self) -> int:
        return self.cells.shape[0]

    @property
    def n_dofs(self) -> int:
        return self.points.size

    @property
    def volumes(self) -> jax.Array:
        """Rest measure |T| of each cell, ``(n_cells,)`` (area in 2D, volume in 3D)."""
        return self.weights.sum(axis=1)

    @property
    def Dm_inv(self) -> jax.Array:
        """``(n_cells, dim, dim)`` inverse rest shape matrices Dm⁻¹ (P1 elements only)."""
        if self.element not in ("tri3", "tet4"):
            raise ValueError("Dm_inv is defined for linear (P1) elements only")
        return self.dN[:, 0, 1:, :]

    @property
    def element_type(self) -> Element:
        return get_element(self.element)


jax.tree_util.register_dataclass(
    Mesh,
    data_fields=["points", "cells", "dN", "weights", "incidence"],
    meta_fields=["element", "formulation"],
)


_INFER = {(2, 3): "tri3", (3, 4): "tet4", (2, 6): "tri6", (3, 10): "tet10"}
# local node permutation swapping corners 1 and 2 (and the mid-edge nodes with them)
_FLIP = {
    3: [0, 2, 1],
    4: [0, 2, 1, 3],
    6: [0, 2, 1, 5, 4, 3],
    10: [0, 2, 1, 3, 6, 5, 4, 7, 9, 8],
}


def _check_formulation(formulation: str) -> None:
    if formulation not in FORMULATIONS:
        raise ValueError(f"formulation must be one of {FORMULATIONS}, got {formulation!r}")


def _rest_jacobians(points: np.ndarray, cells: np.ndarray, element: Element) -> np.ndarray:
    """``(n_cells, n_q, dim, dim)`` rest Jacobians ``∂X/∂ξ`` (equal to Dm for P1)."""
    gref = element.shape_gradients()  # (q, k, d)
    xe = points[cells]  # (c, k, d)
    return np.einsum("cka,qkb->cqab", xe, gref)


def _incidence(cells: np.ndarray, n_nodes: int) -> np.ndarray:
    flat = cells.ravel()
    pad = flat.size
    order = np.argsort(flat, kind="stable")
    counts = np.bincount(flat, minlength=n_nodes)
    vmax = int(counts.max()) if counts.size else 0
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank = np.arange(flat.size) - np.repeat(starts, counts)
    table = np.full((n_nodes, max(vmax, 1)), pad, dtype=np.int32)
    table[flat[order], rank] = order
    return table


def from_arrays(
    points,
    cells,
    element: str | None = None,
    *,
    orient: str = "fix",
    dtype=None,
    formulation: str = "standard",
) -> Mesh:
    """Validate rest points and cells and build a :class:`Mesh`.

    Args:
        points: ``(n_nodes, dim)`` rest positions, dim 2 or 3.
        cells: ``(n_cells, nodes_per_cell)`` integer connectivity.
        element: ``"tri3"``/``"tet4"``/``"tri6"``/``"tet10"``/``"tri3x4"``/``"tet4x8"`` (or
            meshio's ``"triangle"``/``"tetra"``/``"triangle6"``/``"tetra10"``); inferred
            from the shapes when omitted (6-node cells: ``tri6``, 10-node: ``tet10``).
        orient: ``"fix"`` (reorient negatively oriented cells, with a warning) or
            ``"refuse"`` (raise :class:`MeshError`).
        dtype: float dtype of the stored arrays (default: the points' dtype if it is a
            float type JAX accepts, else JAX's default float).
        formulation: ``"standard"``, ``"fbar"`` or ``"bbar"`` (not for P1 cells, where it
            changes nothing: use ``to_quadratic(mesh, composite=True)``).

    Raises:
        MeshError: wrong shapes or dimension, NaN/inf coordinates, out-of-range or
            duplicate indices within a cell, nodes used by no cell, zero-measure cells,
            or inverted cells with ``orient="refuse"``; P2/composite cells whose rest
            Jacobian changes sign between quadrature points (misplaced mid-edge nodes).
    """
    if orient not in ("fix", "refuse"):
        raise ValueError(f"orient must be 'fix' or 'refuse', got {orient!r}")
    _check_formulation(formulation)
    pts = np.asarray(points)
    cls = np.asarray(cells)
    if pts.ndim != 2 or pts.shape[1] not in (2, 3):
        raise MeshError(f"points must have shape (n_nodes, 2) or (n_nodes, 3), got {pts.shape}")
    if not np.issubdtype(pts.dtype, np.number):
        raise MeshError(f"points must be numeric, got dtype {pts.dtype}")
    pts = pts.astype(np.float64)
    dim = pts.shape[1]
    if cls.ndim != 2:
        raise MeshError(f"cells must have shape (n_cells, nodes_per_cell), got {cls.shape}")
    if cls.shape[0] == 0:
        raise MeshError("mesh has no cells")
    if not np.issubdtype(cls.dtype, np.integer):
        if np.issubdtype(cls.dtype, np.floating) and np.all(cls == np.round(cls)):
            cls = cls.astype(np.int64)
        else:
            raise MeshError(f"cells must hold integer node indices, got dtype {cls.dtype}")
    if element is None:
        element = _INFER.get((dim, cls.shape[1]))
        if element is None:
            raise MeshError(
                f"cannot infer the element from {dim}D points and {cls.shape[1]}-node cells; "
                "supported: 3- or 6-node triangles in 2D, 4- or 10-node tetrahedra in 3D"
            )
    try:
        el = get_element(element)
    except ValueError as e:
        raise MeshError(str(e)) from None
    if el.dim != dim:
        raise MeshError(f"element {el.name!r} is {el.dim}D but points are {dim}D")
    if cls.shape[1] != el.n_nodes:
        raise MeshError(
            f"element {el.name!r} has {el.n_nodes} nodes per cell, cells have {cls.shape[1]}"
        )
    if formulation != "standard" and el.n_nodes == el.dim + 1:
        raise MeshError(
            "formulation 'fbar' on P1 cells changes nothing (one quadrature point per cell); "
            "use to_quadratic(mesh, composite=True) for the composite F-bar element"
        )
    bad = ~np.isfinite(pts).all(axis=1)
    if bad.any():
        idx = np.flatnonzero(bad)
        raise MeshError(f"{idx.size} point(s) have NaN/inf coordinates, e.g. nodes {idx[:5]}")
    n = pts.shape[0]
    oor = (cls < 0) | (cls >= n)
    if oor.any():
        c = np.flatnonzero(oor.any(axis=1))
        raise MeshError(
            f"{c.size} cell(s) reference node indices outside [0, {n}), e.g. cell {c[0]}: "
            f"{cls[c[0]].tolist()}"
        )
    srt = np.sort(cls, axis=1)
    dup = (srt[:, 1:] == srt[:, :-1]).any(axis=1)
    if dup.any():
        c = np.flatnonzero(dup)
        raise MeshError(
            f"{c.size} cell(s) repeat a node index, e.g. cell {c[0]}: {cls[c[0]].tolist()}"
        )
    used = np.zeros(n, dtype=bool)
    used[cls.ravel()] = True
    if not used.all():
        u = np.flatnonzero(~used)
        raise MeshError(
            f"{u.size} node(s) belong to no cell (e.g. {u[:5].tolist()}); they would have no "
            "stiffness. Remove them first (jaxelastic.io.read_mesh prunes them for you)."
        )
    cls = cls.astype(np.int32)

    Jac = _rest_jacobians(pts, cls, el)  # (c, q, d, d)
    detJ = np.linalg.det(Jac)  # (c, q)
    # scale-aware degeneracy test: measure relative to (longest edge)^dim
    xe = pts[cls]
    edges = xe[:, :, None, :] - xe[:, None, :, :]
    h = np.sqrt((edges**2).sum(-1).max(axis=(1, 2)))
    rel = detJ / np.maximum(h, np.finfo(float).tiny)[:, None] ** dim
    degenerate = (np.abs(rel) < 1e-12).any(axis=1)
    if degenerate.any():
        c = np.flatnonzero(degenerate)
        raise MeshError(
            f"{c.size} cell(s) have zero rest measure (collinear/coplanar nodes), e.g. cell "
            f"{c[0]}: nodes {cls[c[0]].tolist()}"
        )
    mixed = (detJ < 0).any(axis=1) & (detJ > 0).any(axis=1)
    if mixed.any():
        c = np.flatnonzero(mixed)
        raise MeshError(
            f"{c.size} {el.name} cell(s) have a rest Jacobian that changes sign inside the "
            f"cell (misplaced mid-edge nodes), e.g. cell {c[0]}: nodes {cls[c[0]].tolist()}"
        )
    inverted = (detJ < 0).all(axis=1)
    if inverted.any():
        c = np.flatnonzero(inverted)
        if orient == "refuse":
            raise MeshError(
                f"{c.size} cell(s) are inverted at rest (negative orientation), e.g. cell "
                f"{c[0]}: nodes {cls[c[0]].tolist()}; pass orient='fix' to reorient them"
            )
        warnings.warn(
            f"reoriented {c.size} of {cls.shape[0]} cell(s) with negative rest orientation",
            UserWarning,
            stacklevel=2,
        )
        cls = cls.copy()
        cls[c] = cls[c][:, _FLIP[el.n_nodes]]
        Jac = _rest_jacobians(pts, cls, el)
        detJ = np.linalg.det(Jac)

    gref = el.shape_gradients()  # (q, k, d)
    Jinv = np.linalg.inv(Jac)  # (c, q, d, d)
    dN = np.einsum("qkb,cqba->cqka", gref, Jinv)
    w = detJ * np.asarray(el.quad_weights)[None, :]
    inc = _incidence(cls, n)
    if dtype is None:
        dtype = jnp.zeros(()).dtype  # float64 if x64 is enabled, else float32
    return Mesh(
        points=jnp.asarray(pts, dtype=dtype),
        cells=jnp.asarray(cls),
        dN=jnp.asarray(dN, dtype=dtype),
        weights=jnp.asarray(w, dtype=dtype),
        incidence=jnp.asarray(inc),
        element=el.name,
        formulation=formulation,
    )


def _check_counts(**counts):
    for k, v in counts.items():
        if int(v) != v or v < 1:
            raise ValueError(f"{k} must be a positive integer, got {v!r}")


def rectangle(
    nx: int,
    ny: int,
    size=(1.0, 1.0),
    origin=(0.0, 0.0),
    *,
    order: int = 1,
    formulation: str = "standard",
    **kw,
) -> Mesh:
    """Structured triangle mesh of a rectangle: ``nx × ny`` cells, 2 triangles each.

    Args:
        nx, ny: cells along x and y.
        size: ``(Lx, Ly)`` [length].
        origin: lower-left corner.
        order, formulation: see :func:`_finish` (``order=2`` → ``tri6``;
            ``formulation="fbar"`` with order 1 → composite ``tri3x4``).

    Returns:
        For the default order 1, a ``tri3`` mesh with ``(nx+1)(ny+1)`` nodes and
        ``2·nx·ny`` triangles. Node ``i + (nx+1)·j`` sits at ``origin + (i·Lx/nx, j·Ly/ny)``.
    """
    _check_counts(nx=nx, ny=ny)
    x = np.linspace(0.0, size[0], nx + 1) + origin[0]
    y = np.linspace(0.0, size[1], ny + 1) + origin[1]
    X, Y = np.meshgrid(x, y, indexing="xy")
    pts = np.stack([X.ravel(), Y.ravel()], axis=1)
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="xy")
    n0 = (i + (nx + 1) * j).ravel()
    n1, n2, n3 = n0 + 1, n0 + nx + 2, n0 + nx + 1
    tris = np.concatenate([np.stack([n0, n1, n2], 1), np.stack([n0, n2, n3], 1)])
    return _finish(pts, tris, "tri3", order, formulation, kw)


# Kuhn (Freudenthal) subdivision of the unit cube along the main diagonal 0→7: six tets,
# positively oriented. Corner c = bx + 2·by + 4·bz.
_KUHN = np.array(
    [[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]]
)


def box(
    nx: int,
    ny: int,
    nz: int,
    size=(1.0, 1.0, 1.0),
    origin=(0.0, 0.0, 0.0),
    *,
    order: int = 1,
    formulation: str = "standard",
    **kw,
) -> Mesh:
    """Structured tetrahedral mesh of a box: ``nx·ny·nz`` cubes, 6 conforming tets each.

    Each cube is split into six tets along a diagonal (Kuhn/Freudenthal); the split is
    mirrored in alternate cubes along each axis so the mesh has no preferred direction.

    Args:
        nx, ny, nz: cells along each axis.
        size: ``(Lx, Ly, Lz)`` [length].
        origin: the minimum corner.
        order, formulation: see :func:`_finish` (``order=2`` → ``tet10``;
            ``formulation="fbar"`` with order 1 → composite ``tet4x8``).

    Returns:
        For the default order 1, a ``tet4`` mesh with ``(nx+1)(ny+1)(nz+1)`` nodes and
        ``6·nx·ny·nz`` tets; node ``i + (nx+1)(j + (ny+1)k)`` sits at
        ``origin + (i·Lx/nx, j·Ly/ny, k·Lz/nz)``.
    """
    _check_counts(nx=nx, ny=ny, nz=nz)
    axes = [np.linspace(0.0, size[a], n + 1) + origin[a] for a, n in enumerate((nx, ny, nz))]
    Z, Y, X = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)

    def node(i, j, k):
        return i + (nx + 1) * (j + (ny + 1) * k)

    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    i, j, k = i.ravel(), j.ravel(), k.ravel()
    # Mirror the Kuhn split in every other cube along each axis (corner bit b -> b xor
    # parity): the mesh stays conforming (neighbours across a face share its mirror state
    # in the two in-face axes, so they split that face along the same diagonal) and has no
    # preferred diagonal direction, so a symmetric load gives a symmetric response.
    pi, pj, pk = i & 1, j & 1, k & 1
    corners = np.stack(
        [
            node(
                i + ((c & 1) ^ pi),
                j + (((c >> 1) & 1) ^ pj),
                k + (((c >> 2) & 1) ^ pk),
            )
            for c in range(8)
        ],
        axis=1,
    )
    tets = corners[:, _KUHN]  # (cubes, 6, 4)
    flip = ((pi + pj + pk) & 1).astype(bool)  # an odd number of mirrors reverses orientation
    tets[flip] = tets[flip][:, :, [0, 2, 1, 3]]
    tets = tets.reshape(-1, 4)
    return _finish(pts, tets, "tet4", order, formulation, kw)


def cook_membrane(n: int, *, order: int = 1, formulation: str = "standard", **kw) -> Mesh:
    """Cook's membrane: the trapezoid (0,0), (48,44), (48,60), (0,44), ``n × n`` quads split
    into ``2n²`` triangles.

    The left edge ``x = 0`` is the clamped side, the right edge ``x = 48`` the loaded one;
    node ``i + (n+1)·j`` is at parameter ``(i/n, j/n)``, so the loaded-edge mid-point
    (48, 52) is a node when ``n`` is even (for ``order=2`` always: the mid-edge node of
    the middle edge). ``order``/``formulation`` as in :func:`_finish`. See Cook (1974);
    REFERENCES "Cook's membrane".
    """
    _check_counts(n=n)
    s = np.linspace(0.0, 1.0, n + 1)
    S, T = np.meshgrid(s, s, indexing="xy")
    S, T = S.ravel(), T.ravel()
    x = 48.0 * S
    y_bot = 44.0 * S
    y_top = 44.0 + 16.0 * S
    y = y_bot + T * (y_top - y_bot)
    pts = np.stack([x, y], 1)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="xy")
    n0 = (i + (n + 1) * j).ravel()
    n1, n2, n3 = n0 + 1, n0 + n + 2, n0 + n + 1
    tris = np.concatenate([np.stack([n0, n1, n2], 1), np.stack([n0, n2, n3], 1)])
    return _finish(pts, tris, "tri3", order, formulation, kw)


def boundary_facets(mesh: Mesh) -> np.ndarray:
    """Facets (edges in 2D, triangles in 3D) that belong to exactly one cell.

    Returns:
        ``(n_facets, n_facet_nodes)`` int array of node indices: the ``dim`` corners,
        oriented so the right-hand-rule normal points out of the body (edge ``(a, b)``:
        normal ``(t_y, -t_x)``), then for P2/composite meshes the facet's mid-edge nodes
        (2D: 3 nodes ``(a, b, mid)``; 3D: 6 nodes ``(a, b, c, m_ab, m_bc, m_ca)``, the
        meshio ``line3``/``triangle6`` order).
    """
    el = mesh.element_type
    cells = np.asarray(mesh.cells)
    local = np.asarray(el.facet_nodes)  # (f, m)
    facets = cells[:, local].reshape(-1, local.shape[1])
    key = np.sort(facets[:, : mesh.dim], axis=1)  # corners identify a facet
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return facets[counts[inv.ravel()] == 1]


def boundary_nodes(mesh: Mesh) -> np.ndarray:
    """Sorted indices of nodes on the boundary, ``(n_boundary,)``."""
    return np.unique(boundary_facets(mesh))


def _finish(pts, cells, p1: str, order: int, formulation: str, kw) -> Mesh:
    """Build the generator's mesh: P1 for ``order=1``; ``order=2`` → P2 (``tri6``/``tet10``);
    ``formulation="fbar"`` (or ``"bbar"``) with order 1 → the composite element
    (``tri3x4``/``tet4x8``, P1 displacements on the P2 node set with one volume constraint
    per cell), with order 2 → P2 + F-bar (B-bar)."""
    if order not in (1, 2):
        raise ValueError(f"order must be 1 or 2, got {order!r}")
    _check_formulation(formulation)
    m = from_arrays(pts, cells, p1, **kw)
    if order == 1 and formulation == "standard":
        return m
    return to_quadratic(m, composite=order == 1, formulation=formulation)


# P2 / composite conversions live in quadratic.py (re-exported here)
from .quadratic import (  # noqa: E402
    linear_cells,
    to_quadratic,
    vertex_nodes,
    with_formulation,
)
