"""P1 → P2 / composite lifting, the formulation switch, and views of quadratic meshes.

Re-exported by :mod:`jaxelastic.mesh` (``jaxelastic.mesh.to_quadratic`` etc.).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .core import Mesh, check_formulation, from_arrays
from .elements import TET4X8, TRI3X4, edge_table

__all__ = ["to_quadratic", "with_formulation", "vertex_nodes", "linear_cells"]


def to_quadratic(mesh: Mesh, *, composite: bool = False, formulation: str | None = None) -> Mesh:
    """P1 → P2 (``tri6``/``tet10``) by adding a node at the midpoint of every edge.

    Shared edges get one node. P1 node indices are kept; the new nodes are appended in the
    lexicographic order of their edges' sorted end-node pairs (deterministic).

    Args:
        mesh: a ``tri3``/``tet4`` mesh.
        composite: build the composite element ``tri3x4``/``tet4x8`` (same nodes; each cell
            split into 4 / 8 linear sub-simplices) instead of P2.
        formulation: ``"standard"``/``"fbar"``/``"bbar"``; default: ``"fbar"`` when ``composite``
            (that is what the composite element is for), else ``mesh.formulation``.

    Returns:
        A new :class:`Mesh` (same float dtype) with ``n_nodes + n_edges`` nodes.
    """
    el = mesh.element_type
    if el.n_nodes != el.dim + 1:
        raise ValueError(f"to_quadratic needs a P1 mesh, got element {el.name!r}")
    if formulation is None:
        formulation = "fbar" if composite else mesh.formulation
    cells = np.asarray(mesh.cells, dtype=np.int64)
    X = np.asarray(mesh.points, dtype=np.float64)
    loc = edge_table(el)  # (e, 2)
    pairs = np.sort(cells[:, loc], axis=2)  # (c, e, 2)
    edges, inv = np.unique(pairs.reshape(-1, 2), axis=0, return_inverse=True)
    mids = X[edges].mean(axis=1)
    new_cells = np.concatenate([cells, X.shape[0] + inv.reshape(cells.shape[0], -1)], axis=1)
    name = {2: "tri3x4", 3: "tet4x8"}[el.dim] if composite else {2: "tri6", 3: "tet10"}[el.dim]
    return from_arrays(
        np.concatenate([X, mids]),
        new_cells,
        name,
        orient="refuse",
        dtype=mesh.points.dtype,
        formulation=formulation,
    )


def with_formulation(mesh: Mesh, formulation: str) -> Mesh:
    """The same mesh with another formulation (``"standard"``, ``"fbar"``, ``"bbar"``).

    Raises:
        ValueError: unknown formulation, or F-bar/B-bar on a P1 mesh (one quadrature point
            per cell: F-bar would change nothing; use ``to_quadratic(mesh, composite=True)``).
    """
    check_formulation(formulation)
    el = mesh.element_type
    if formulation != "standard" and el.n_nodes == el.dim + 1:
        raise ValueError(
            "formulation 'fbar' on a P1 mesh changes nothing (one quadrature point per cell); "
            "use to_quadratic(mesh, composite=True) for the composite F-bar element"
        )
    return dataclasses.replace(mesh, formulation=formulation)


def vertex_nodes(mesh: Mesh) -> np.ndarray:
    """Sorted indices of the nodes that are cell corners (all nodes for P1), ``(m,)``."""
    return np.unique(np.asarray(mesh.cells)[:, : mesh.dim + 1])


def linear_cells(mesh: Mesh) -> np.ndarray:
    """Linear sub-simplices covering the mesh, ``(m, dim+1)`` node indices (positive
    orientation at rest for straight-sided cells): the cells themselves for P1, the red
    refinement (4 triangles / 8 tets per cell) for P2 and composite meshes. Used for
    plotting and for interpolating P2 fields piecewise linearly."""
    el = mesh.element_type
    cells = np.asarray(mesh.cells)
    if el.n_nodes == el.dim + 1:
        return cells
    sub = np.asarray((TRI3X4 if el.dim == 2 else TET4X8).sub_cells)
    return cells[:, sub].reshape(-1, el.dim + 1)
