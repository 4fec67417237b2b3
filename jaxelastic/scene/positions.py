"""Observed node positions read from a file: the one check of their values.

A scene names observed deformed positions of mesh nodes in two places — ``[fit].observed``
(one shape per target, :func:`~jaxelastic.scene.fit.read_observed`) and a
``kind = "positions"`` measurement (one shape per load level,
:mod:`~jaxelastic.scene.measurements`). :func:`check_positions` is what both require of the
array once its nodes are known: the shape, finite rows and a shape that differs from the
rest shape.
"""

from __future__ import annotations

import numpy as np

from .load import Scene

__all__ = ["check_positions", "REST_ATOL"]

REST_ATOL = 1e-12
"""Observed positions within this fraction of the nodes' extent of their rest positions
(at every level) count as the rest shape: a file that observed no motion."""


def check_positions(
    scene: Scene, where: str, pos, nodes: np.ndarray, dim: int, rest=None, levels=None
) -> np.ndarray:
    """``pos`` as float64 ``([levels,] n, dim)`` positions [length] of ``nodes`` ``(n,)``.

    Args:
        scene: the scene (its errors name the scene file); where: the key and the file.
        pos: the positions read, one shape ``(n, dim)`` or ``levels`` of them.
        nodes: the checked node indices (:func:`~jaxelastic.scene.measurements.check_nodes`).
        rest: ``(n_nodes, dim)`` rest positions of the mesh, or None (not compared).
        levels: the number of load levels, or None for one shape.

    Raises:
        SceneError: naming ``where`` and the row: a wrong shape, a non-finite row, or
            positions equal to the rest shape (at every level).
    """
    pos = np.asarray(pos, np.float64)
    lead = () if levels is None else (int(levels),)
    want = (*lead, nodes.size, dim)
    if pos.shape != want or 0 in pos.shape:
        raise scene.error(
            f"{where}: {nodes.size} nodes need positions of shape {want}; got {pos.shape}"
        )
    bad = np.argwhere(~np.isfinite(pos).all(axis=-1))
    if bad.size:
        *level, row = (int(i) for i in bad[0])
        at = f"level {level[0]}, " if level else ""
        raise scene.error(f"{where}: {at}row {row} (node {int(nodes[row])}) is not finite")
    if rest is not None:
        X = np.asarray(rest)[nodes]
        atol = REST_ATOL * max(float(np.ptp(X)), 1e-300)
        if np.allclose(pos, X, rtol=0.0, atol=atol):
            every = " at every level" if levels is not None else ""
            raise scene.error(f"{where}: the positions equal the rest shape{every} (nothing moved)")
    return pos
