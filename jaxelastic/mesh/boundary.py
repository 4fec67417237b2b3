"""Boundary of a mesh: the facets that belong to exactly one cell, and their nodes."""

from __future__ import annotations

import numpy as np

from .core import Mesh

__all__ = ["boundary_facets", "boundary_nodes"]


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
    corners = np.sort(facets[:, : mesh.dim], axis=1).astype(np.int64)  # identify a facet
    n = max(int(corners.max(initial=0)) + 1, 1)
    if n**mesh.dim < 2**63:  # one int64 per facet: a 1-D unique (0.04 s against the
        key = corners[:, 0]  # row-wise unique's 0.42 s at 146k tets)
        for j in range(1, mesh.dim):
            key = key * n + corners[:, j]
        _, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    else:
        _, inv, counts = np.unique(corners, axis=0, return_inverse=True, return_counts=True)
    return facets[counts[inv.ravel()] == 1]


def boundary_nodes(mesh: Mesh) -> np.ndarray:
    """Sorted indices of nodes on the boundary, ``(n_boundary,)``."""
    return np.unique(boundary_facets(mesh))
