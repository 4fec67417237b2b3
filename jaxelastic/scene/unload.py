"""The unloaded rest shape of a static scene: ``jaxelastic unload SCENE``.

The scene's mesh is read as the *observed, loaded* shape (e.g. segmented from an image);
its material, Dirichlet conditions and loads are the ones acting on it. The command finds
the rest shape whose loaded equilibrium is that mesh
(:func:`jaxelastic.unloaded_shape`), and writes into ``--out``:

* ``rest.vtu``: the mesh on the recovered rest points, with the displacement from rest to
  the loaded shape (the usual ``displacement`` point data: warp by it to see the scene's
  mesh);
* ``summary.json``: method, status, iterations, residual history, the round-trip error
  (a forward solve from the recovered rest shape against the scene's mesh) and wall time.

The loads are the scene's nodal loads as built on its mesh and held fixed (dead loads);
gravity built on the rest shape instead is available from Python
(``unloaded_shape(..., loads=lambda m: je.loads.gravity_load(m, rho, g))``).
"""

from __future__ import annotations

import os

import numpy as np

from ..io import write_json, write_vtu
from ..solvers import Status, unloaded_shape
from .errors import SceneError
from .problem import build

__all__ = ["unload_scene"]


def unload_scene(scene, out: str, method: str = "direct") -> dict:
    """Recover the rest shape of a static scene whose mesh is the loaded shape.

    Args:
        scene: a :class:`~jaxelastic.scene.load.Scene` (or a path, shipped name, dict).
        out: output directory (created if needed).
        method: ``"direct"`` or ``"fixed_point"`` (see :func:`jaxelastic.unloaded_shape`).

    Returns:
        The summary written to ``summary.json`` (``status`` is the name of a
        :class:`~jaxelastic.Status`).

    Raises:
        SceneError: a dynamic scene (an ``[integrator]`` other than static).
    """
    built = build(scene)
    if built.integrator is not None:
        raise SceneError(
            'jaxelastic unload needs a static scene ([integrator] type = "static"): the '
            "rest shape is that of an equilibrium"
        )
    mesh = built.mesh
    res = unloaded_shape(
        built.potential, built.bc, mesh.points, method=method, solver=built.solver, throw=False
    )
    os.makedirs(out, exist_ok=True)
    X = np.asarray(res.x)
    rest = mesh.with_points(res.x) if bool(res.ok) else mesh
    write_vtu(os.path.join(out, "rest.vtu"), rest, x=mesh.points)
    summary = dict(
        scene=built.scene.name,
        method=method,
        status=Status(int(res.status)).name,
        iterations=int(res.stats["steps"]),
        residual_history=[float(v) for v in res.stats["residual_history"]],
        round_trip=float(res.stats["round_trip"]),
        max_displacement=float(np.abs(np.asarray(mesh.points) - X).max()),
        wall_time=float(res.stats["wall_time"]),
        nodes=int(mesh.n_nodes),
        cells=int(mesh.n_cells),
    )
    write_json(os.path.join(out, "summary.json"), summary)
    return summary
