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
    key = np.sort(facets[:, : mesh.dim], axis=1)  # corners identify a facet
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return facets[counts[inv.ravel()] == 1]


def boundary_nodes(mesh: Mesh) -> np.ndarray:
    """Sorted indices of nodes on the boundary, ``(n_boundary,)``."""
    return np.unique(boundary_facets(mesh))
