"""Observation helpers of ``jaxelastic fit`` (see :mod:`jaxelastic._scene_fit`): nested-mesh
node matching (targets from a refined mesh), random marker nodes, region labels from
``where`` expressions, and reading observed positions from ``.npy``/``.npz``/``.csv``.
"""

from __future__ import annotations

import os

import numpy as np

from ._where import where_mask
from .scenes import _V

__all__ = ["nested_nodes", "choose_markers", "region_labels"]


def nested_nodes(fine_points, coarse_points, tol: float = 1e-9) -> np.ndarray:
    """Index of each coarse node among the fine nodes at the same rest position.

    Args:
        fine_points: ``(n_fine, dim)``; coarse_points: ``(n_coarse, dim)`` rest positions.
        tol: relative to the bounding-box diagonal.
    Returns:
        ``(n_coarse,)`` int indices into the fine mesh.
    Raises:
        ValueError: a coarse node has no fine node at its position (not a nested mesh).
    """
    from scipy.spatial import cKDTree

    fine, coarse = np.asarray(fine_points), np.asarray(coarse_points)
    d, idx = cKDTree(fine).query(coarse)
    diag = float(np.linalg.norm(np.ptp(fine, axis=0)))
    if d.size and d.max() > tol * max(diag, 1e-300):
        raise ValueError(
            f"meshes are not nested: a coarse node is {d.max():.3g} from any fine node"
        )
    return idx.astype(np.int64)


def choose_markers(mask, fraction: float, seed: int, candidates=None) -> np.ndarray:
    """Sorted random marker nodes: ``max(1, round(fraction·n_nodes))`` of the nodes that are
    not fully prescribed (``mask`` ``(n_nodes, dim)`` bool) and, if given, in
    ``candidates``; all such nodes when ``fraction = 1``."""
    mask = np.asarray(mask)
    n = mask.shape[0]
    ok = ~mask.all(axis=1)
    if candidates is not None:
        sel = np.zeros(n, bool)
        sel[np.asarray(candidates)] = True
        ok &= sel
    pool = np.flatnonzero(ok)
    if fraction >= 1.0:
        return pool
    k = min(pool.size, max(1, int(round(fraction * n))))
    return np.sort(np.random.default_rng(seed).choice(pool, size=k, replace=False))


def region_labels(mesh, regions) -> np.ndarray:
    """``(n_cells,)`` int labels: the first ``where`` expression a cell centroid satisfies,
    ``len(regions)`` for cells matching none."""
    X = np.asarray(mesh.points)[np.asarray(mesh.cells)].mean(axis=1)  # (n_cells, dim)
    labels = np.full(X.shape[0], len(regions), dtype=np.int32)
    for i, expr in reversed(list(enumerate(regions))):
        labels[where_mask(expr, X)] = i
    return labels


def _per_region(x, n: int) -> np.ndarray:
    return np.broadcast_to(np.asarray(x, float), (n,)).copy()


def _read_observed(v: _V, key: str, path: str, n_nodes: int, dim: int):
    """(positions (n_obs, dim), nodes (n_obs,)) from a .npy / .npz / .csv file."""
    if not os.path.isfile(path):
        raise v.err(f"{key}: no such file {path!r}")
    nodes = None
    try:
        if path.endswith(".npy"):
            pos = np.load(path)
        elif path.endswith(".npz"):
            with np.load(path) as z:
                if "positions" not in z:
                    raise v.err(f"{key}: {path!r} has no array 'positions' (has {list(z)})")
                pos = z["positions"]
                nodes = z["nodes"] if "nodes" in z else None
        elif path.endswith((".csv", ".txt")):
            a = np.loadtxt(path, delimiter="," if path.endswith(".csv") else None, ndmin=2)
            if a.shape[1] != dim + 1:
                raise v.err(f"{key}: {path!r} must have columns node, x, y[, z] ({dim + 1})")
            nodes, pos = a[:, 0], a[:, 1:]
        else:
            raise v.err(f"{key}: {path!r} must be a .npy, .npz or .csv file")
    except (OSError, ValueError) as e:
        raise v.err(f"{key}: cannot read {path!r}: {e}") from None
    pos = np.asarray(pos, float)
    if nodes is None:
        if pos.shape != (n_nodes, dim):
            raise v.err(
                f"{key}: expected positions of all {n_nodes} nodes ({n_nodes}, {dim}), "
                f"got {pos.shape}"
            )
        nodes = np.arange(n_nodes)
    nodes = np.asarray(nodes)
    if nodes.ndim != 1 or not np.all(nodes == np.round(nodes)):
        raise v.err(f"{key}: node indices must be integers")
    nodes = nodes.astype(np.int64)
    if pos.shape != (nodes.size, dim) or nodes.min() < 0 or nodes.max() >= n_nodes:
        raise v.err(
            f"{key}: {nodes.size} node indices in [0, {n_nodes}) with positions "
            f"({nodes.size}, {dim}) expected, got {pos.shape}"
        )
    if not np.isfinite(pos).all():
        raise v.err(f"{key}: positions must be finite")
    return pos, nodes
