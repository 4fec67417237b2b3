"""The rest-shape mesh: a frozen pytree preprocessed once, and its validating constructor.

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
generators or :func:`~jaxelastic.mesh.to_quadratic`) and the composite F-bar element
(``tri3x4``/``tet4x8``, ``formulation="fbar"`` with order 1). ``Mesh.formulation`` (static)
selects F-bar/B-bar in the energy kernels; see :mod:`jaxelastic.mesh.elements` and
:func:`~jaxelastic.mechanics.kinematics.f_bar`.
"""

from __future__ import annotations

import dataclasses
import itertools
import warnings
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer

from . import geometry
from .elements import Element, get_element

__all__ = ["Mesh", "MeshError", "from_arrays", "FORMULATIONS", "check_formulation"]

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
        element: static :class:`~jaxelastic.mesh.elements.Element` name (``"tri3"``,
            ``"tet4"``, ``"tri6"``, ``"tet10"``, ``"tri3x4"``, ``"tet4x8"``).
        formulation: static; ``"standard"`` (ψ at every quadrature point's F) or ``"fbar"``
            (F̄ = (J̄/J)^{1/d} F with J̄ the cell average of J, see
            :func:`~jaxelastic.mechanics.kinematics.deformation_gradients`), or ``"bbar"`` (its
            small-strain analogue for small-strain materials, Hughes 1980).
        halo: a :class:`~jaxelastic.parallel.halo.Halo` when the mesh is sharded over devices
            (:func:`jaxelastic.shard`: the energy kernels then run per shard under
            ``shard_map`` and exchange interface nodes only), else None.
    """

    points: jax.Array
    cells: jax.Array
    dN: jax.Array
    weights: jax.Array
    incidence: jax.Array
    halo: Any = None
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

    def with_points(self, points) -> Mesh:
        """The same mesh (cells, incidence, element, formulation) on other rest points.

        The rest quantities (``dN``, ``weights``) are recomputed from ``points`` by JAX
        functions (:func:`~jaxelastic.mesh.geometry.rest_quantities`), so this is valid
        under ``jit`` and differentiable: ``jax.grad``/``jax.jvp`` of a loss of a solve on
        the returned mesh flow to ``points`` (shape gradients). The topology is not touched
        (no reorientation: a cell inverted by the new points is an error).

        Args:
            points: ``(n_nodes, dim)`` new rest positions [length] (cast to the mesh's
                float dtype).

        Raises:
            MeshError: ``points`` of another shape; outside jit (concrete values, also the
                primal of an eager ``jax.grad``), NaN/inf points or cells that the new
                points invert or collapse, named
                (:func:`~jaxelastic.mesh.geometry.describe_invalid`). Inside jit nothing
                can be raised: :func:`jaxelastic.solve` then returns status ``INVERTED``
                for such a mesh, and :func:`~jaxelastic.mesh.geometry.invalid_cells` gives
                the flag per cell.
            ValueError: a mesh sharded over devices (move the points before sharding).
        """
        if self.halo is not None:
            raise ValueError("with_points: shard the mesh after moving its points (je.shard)")
        shape = tuple(jnp.shape(points))
        if shape != tuple(self.points.shape):
            raise MeshError(
                f"with_points: points must have shape (n_nodes, dim) = "
                f"{tuple(self.points.shape)} like mesh.points, got {shape}"
            )
        X = jnp.asarray(points)
        if not jnp.issubdtype(X.dtype, jnp.floating):
            X = X.astype(self.points.dtype)
        X = X if X.dtype == self.points.dtype else X.astype(self.points.dtype)
        dN, w, _ = geometry.rest_quantities(X, self.cells, self.element_type)
        new = dataclasses.replace(self, points=X, dN=dN, weights=w)
        concrete = jax.lax.stop_gradient(X)
        if not isinstance(concrete, Tracer):
            _check_moved(new, concrete)
        return new


jax.tree_util.register_dataclass(
    Mesh,
    data_fields=["points", "cells", "dN", "weights", "incidence", "halo"],
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


def check_formulation(formulation: str) -> None:
    """Raise :class:`ValueError` unless ``formulation`` is one of :data:`FORMULATIONS`."""
    if formulation not in FORMULATIONS:
        raise ValueError(f"formulation must be one of {FORMULATIONS}, got {formulation!r}")


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
        dtype: float dtype of the stored arrays, float32 or float64 (default: JAX's default
            float, float64 with x64 enabled, else float32, whatever the points' dtype). It
            is kept as given: a float32 mesh with x64 enabled computes in float32, and
            :class:`~jaxelastic.mechanics.potential.Potential` refuses float64 loads or parameters
            on it rather than mixing precisions (the loads builders return the mesh's
            dtype).
        formulation: ``"standard"``, ``"fbar"`` or ``"bbar"`` (not for P1 cells, where it
            changes nothing: use ``to_quadratic(mesh, composite=True)``).

    Raises:
        MeshError: a ``dtype`` other than float32/float64, wrong shapes or dimension,
            NaN/inf coordinates, out-of-range or
            duplicate indices within a cell, nodes used by no cell, zero-measure cells,
            or inverted cells with ``orient="refuse"``; P2/composite cells whose rest
            Jacobian changes sign between quadrature points (misplaced mid-edge nodes).
    """
    if orient not in ("fix", "refuse"):
        raise ValueError(f"orient must be 'fix' or 'refuse', got {orient!r}")
    check_formulation(formulation)
    dtype = _float_dtype(dtype)
    pts = _parse_points(points)
    cls = _parse_cells(cells)
    el = _resolve_element(element, pts.shape[1], cls.shape[1], formulation)
    _check_topology(pts, cls)
    cls = cls.astype(np.int32)
    cls = _check_geometry(pts, cls, el, orient)
    _check_folds(pts, cls, el)
    _warn_coincident(pts, cls)
    dN, w, _ = geometry.rest_quantities(pts, cls, el)  # (c, q, k, d) = ∇̂N J⁻¹, (c, q)
    return Mesh(
        points=jnp.asarray(pts, dtype=dtype),
        cells=jnp.asarray(cls),
        dN=jnp.asarray(dN, dtype=dtype),
        weights=jnp.asarray(w, dtype=dtype),
        incidence=jnp.asarray(_incidence(cls, pts.shape[0])),
        element=el.name,
        formulation=formulation,
    )


def _check_moved(mesh: Mesh, X) -> None:
    """Refuse non-finite moved points and the cells they invert or collapse (concrete)."""
    bad_pts = ~np.isfinite(np.asarray(X)).all(axis=1)
    if bad_pts.any():
        idx = np.flatnonzero(bad_pts)
        raise MeshError(
            f"with_points: {idx.size} point(s) have NaN/inf coordinates, e.g. nodes "
            f"{idx[:5].tolist()}"
        )
    concrete = jax.tree_util.tree_map(jax.lax.stop_gradient, mesh)
    bad = np.asarray(geometry.invalid_cells(concrete))
    if bad.any():
        raise MeshError(
            "with_points: " + geometry.describe_invalid(concrete, bad) + "; the new rest "
            "points must keep every cell positively oriented (smaller shape steps, or a "
            "smoother update of the interior nodes)"
        )


def _float_dtype(dtype):
    """The mesh's float dtype: ``dtype`` (float32/float64) or JAX's default float."""
    if dtype is None:
        return jnp.zeros(()).dtype  # float64 if x64 is enabled, else float32
    try:
        dt = np.dtype(dtype)
    except TypeError:
        raise MeshError(f"dtype must be float32 or float64, got {dtype!r}") from None
    if dt not in (np.dtype(np.float32), np.dtype(np.float64)):
        raise MeshError(f"dtype must be float32 or float64, got {dt}")
    return dt


def _parse_points(points) -> np.ndarray:
    """``(n_nodes, dim)`` float64 rest points; raises :class:`MeshError` on bad shapes."""
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] not in (2, 3):
        raise MeshError(f"points must have shape (n_nodes, 2) or (n_nodes, 3), got {pts.shape}")
    if not np.issubdtype(pts.dtype, np.number):
        raise MeshError(f"points must be numeric, got dtype {pts.dtype}")
    return pts.astype(np.float64)


def _parse_cells(cells) -> np.ndarray:
    """``(n_cells, nodes_per_cell)`` integer cells (integral floats accepted)."""
    cls = np.asarray(cells)
    if cls.ndim != 2:
        raise MeshError(f"cells must have shape (n_cells, nodes_per_cell), got {cls.shape}")
    if cls.shape[0] == 0:
        raise MeshError("mesh has no cells")
    if not np.issubdtype(cls.dtype, np.integer):
        if np.issubdtype(cls.dtype, np.floating) and np.all(cls == np.round(cls)):
            cls = cls.astype(np.int64)
        else:
            raise MeshError(f"cells must hold integer node indices, got dtype {cls.dtype}")
    return cls


def _resolve_element(element: str | None, dim: int, n_per_cell: int, formulation) -> Element:
    """The :class:`Element` named (or inferred from ``dim`` and nodes per cell), checked
    against the points' dimension, the cells' width and the formulation."""
    if element is None:
        element = _INFER.get((dim, n_per_cell))
        if element is None:
            raise MeshError(
                f"cannot infer the element from {dim}D points and {n_per_cell}-node cells; "
                "supported: 3- or 6-node triangles in 2D, 4- or 10-node tetrahedra in 3D"
            )
    try:
        el = get_element(element)
    except ValueError as e:
        raise MeshError(str(e)) from None
    if el.dim != dim:
        raise MeshError(f"element {el.name!r} is {el.dim}D but points are {dim}D")
    if n_per_cell != el.n_nodes:
        raise MeshError(
            f"element {el.name!r} has {el.n_nodes} nodes per cell, cells have {n_per_cell}"
        )
    if formulation != "standard" and el.n_nodes == el.dim + 1:
        raise MeshError(
            "formulation 'fbar' on P1 cells changes nothing (one quadrature point per cell); "
            "use to_quadratic(mesh, composite=True) for the composite F-bar element"
        )
    return el


def _check_topology(pts: np.ndarray, cls: np.ndarray) -> None:
    """Finite coordinates; every index in range, distinct within its cell, every node used."""
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


def _check_geometry(pts: np.ndarray, cls: np.ndarray, el: Element, orient: str):
    """Refuse degenerate and internally folded cells, fix or refuse inverted ones.

    Returns:
        the cells, reoriented where needed so that every ``det J > 0``.
    """
    dim = pts.shape[1]
    Jac = geometry.rest_jacobians(pts, cls, el)  # (c, q, d, d)
    with np.errstate(all="ignore"):  # (over/underflow is refused below)
        detJ = np.linalg.det(Jac)  # (c, q)
    # scale-aware degeneracy test: measure relative to (longest vertex-to-vertex edge)^dim
    h2 = np.zeros(cls.shape[0])
    for a, b in itertools.combinations(range(dim + 1), 2):  # the simplex's vertices
        e = pts[cls[:, a]] - pts[cls[:, b]]
        np.maximum(h2, np.einsum("cd,cd->c", e, e), out=h2)
    h = np.sqrt(h2)
    with np.errstate(all="ignore"):  # over/underflow: refused below with the reason
        rel = detJ / np.maximum(h, np.finfo(float).tiny)[:, None] ** dim
    if not (np.isfinite(rel).all() and np.isfinite(detJ).all()):
        ext = float(np.ptp(pts, axis=0).max()) if pts.size else 0.0
        raise MeshError(
            f"the cells' rest measures over- or underflow float64 (coordinates spanning "
            f"{ext:.3g}): rescale the coordinates to units where the body is between about "
            "1e-30 and 1e30 across (e.g. metres or millimetres)"
        )
    degenerate = (np.abs(rel) < geometry.RELATIVE_MEASURE_MIN).any(axis=1)
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
    if not inverted.any():
        return cls
    c = np.flatnonzero(inverted)
    if orient == "refuse":
        raise MeshError(
            f"{c.size} cell(s) are inverted at rest (negative orientation), e.g. cell "
            f"{c[0]}: nodes {cls[c[0]].tolist()}; pass orient='fix' to reorient them"
        )
    warnings.warn(
        f"reoriented {c.size} of {cls.shape[0]} cell(s) with negative rest orientation",
        UserWarning,
        stacklevel=3,
    )
    cls = cls.copy()
    cls[c] = cls[c][:, _FLIP[el.n_nodes]]
    return cls


def _check_folds(pts: np.ndarray, cls: np.ndarray, el: Element) -> None:
    """Refuse a tangled mesh: an interior facet whose two cells lie on the same side of it
    (cells that overlap, e.g. a fold left by reorienting inverted cells), or a facet
    shared by more than two cells (non-manifold)."""
    d = pts.shape[1]
    local = np.asarray(el.facet_nodes)[:, :d]  # (f, d) corner slots of each facet
    n_f = local.shape[0]
    corners = cls[:, : d + 1]
    fac = corners[:, local]  # (c, f, d); a simplex's facet f misses exactly one corner
    opp = np.array([sorted(set(range(d + 1)) - set(row.tolist()))[0] for row in local])
    key_nodes = np.sort(fac, axis=2).reshape(-1, d).astype(np.int64)  # (c·f, d)
    n = max(int(pts.shape[0]), 1)
    if n**d < 2**63:  # one int64 per facet: a 1-D unique, ~10x faster than by rows
        key = key_nodes[:, 0]
        for j in range(1, d):
            key = key * n + key_nodes[:, j]
        _, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    else:
        _, inv, counts = np.unique(key_nodes, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    if (counts > 2).any():
        k = int(np.flatnonzero(counts > 2)[0])
        shared = np.flatnonzero(inv == k) // n_f
        raise MeshError(
            f"{int((counts > 2).sum())} facet(s) are shared by more than two cells (first: "
            f"cells {shared.tolist()}): the mesh is not a manifold (overlapping cells)"
        )
    # the side of each cell's opposite corner relative to its facet, the facet's nodes in
    # the common (sorted) order: two cells on a shared facet must have opposite sides
    order = np.argsort(inv, kind="stable")
    pair = counts[inv[order]] == 2
    a, b = order[pair][0::2], order[pair][1::2]  # the two cell-facets of each shared facet
    o_all = corners[:, opp].reshape(-1)  # (c·f,) the corner opposite each cell-facet
    same = _side(pts, key_nodes[a], o_all[a]) == _side(pts, key_nodes[a], o_all[b])
    if same.any():
        i = int(np.flatnonzero(same)[0])
        c1, c2 = int(a[i] // n_f), int(b[i] // n_f)
        raise MeshError(
            f"the mesh is tangled: {int(same.sum())} interior facet(s) have both their cells "
            f"on the same side (first: cells {c1} and {c2} across nodes "
            f"{key_nodes[a[i]].tolist()}), so cells overlap (a folded mesh: e.g. inverted cells "
            "that reorienting cannot fix). Repair the mesh (move the misplaced nodes)"
        )


def _side(pts: np.ndarray, facet: np.ndarray, o: np.ndarray) -> np.ndarray:
    """The sign of the orientation of each facet ``(m, d)`` (node indices) and point
    ``o`` ``(m,)``: which side of the facet's line or plane the point is on."""
    P0 = pts[facet[:, 0]]
    e1, v = pts[facet[:, 1]] - P0, pts[o] - P0
    if pts.shape[1] == 2:
        return np.sign(e1[:, 0] * v[:, 1] - e1[:, 1] * v[:, 0])
    e2 = pts[facet[:, 2]] - P0
    n = np.stack(
        [
            e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1],
            e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2],
            e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0],
        ],
        axis=1,
    )
    return np.sign(np.einsum("md,md->m", n, v))


def _warn_coincident(pts: np.ndarray, cls: np.ndarray) -> None:
    """Warn about nodes at the same rest position that no cell joins: the mesh is split
    there (a crack or an unmerged seam), and the parts move independently."""
    ext = float(np.ptp(pts, axis=0).max()) if len(pts) else 0.0
    q = np.round(pts / max(ext * 1e-12, np.finfo(float).tiny)).astype(np.int64)
    _, first, inv, counts = np.unique(
        q, axis=0, return_index=True, return_inverse=True, return_counts=True
    )
    dup = counts[inv.ravel()] > 1
    if not dup.any():
        return
    i = int(np.flatnonzero(dup & (np.arange(len(pts)) != first[inv.ravel()]))[0])
    j = int(first[inv.ravel()[i]])
    warnings.warn(
        f"{int(dup.sum())} nodes share their rest position with another node (e.g. nodes {j} "
        f"and {i} at {pts[i].tolist()}): the mesh is split there and its parts are not "
        "connected. Merge duplicated nodes (e.g. meshio's or your mesher's 'remove "
        "duplicates') unless the split is intended (a crack)",
        UserWarning,
        stacklevel=3,
    )


def _incidence(cells: np.ndarray, n_nodes: int) -> np.ndarray:
    """``(n_nodes, max_valence)`` int32 node → flat cell-slot table, padded with the
    number of slots (see :attr:`Mesh.incidence`)."""
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
