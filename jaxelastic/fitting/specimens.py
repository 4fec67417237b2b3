"""A specimen for identification studies: a plate with a hole pulled in tension, and its
synthetic measurements (support force and DIC displacements on one face).

The plate (half-width ``W``, hole radius ``a``, half-thickness ``T``) is meshed by one
eighth — the quarter ``x, y ≥ 0`` of the half-thickness ``z ∈ [0, T]`` — with a structured
O-grid: the :func:`~jaxelastic.mesh.box` tetrahedra of the index cube ``(u, v, w) ∈ [0,
1]³`` mapped to ``θ = u·π/2`` around the hole, ``v`` from the hole (radius ``a``) to the
square's edge and ``z = w·T``. Symmetry planes ``x = 0``, ``y = 0`` and ``z = 0`` are
held in their normal direction; the edge ``x = W`` is pulled by ``δ`` along x (the grips
of a testing machine, free to contract). The hole concentrates the strain (Kirsch's factor
3 in linear elasticity; Timoshenko & Goodier 1970, *Theory of Elasticity*, §35), so the
field is inhomogeneous and one test identifies more than one constant.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from .. import loads
from ..mesh import Mesh, box, from_arrays, to_quadratic
from ..solvers import ImplicitAdjoint, Newton
from .cases import LoadPathCase
from .measurements import Points, Reaction

__all__ = ["HoleTest", "plate_with_hole", "hole_test", "dic_points", "synthetic_measurements"]


def plate_with_hole(
    n_theta: int,
    n_r: int,
    n_z: int = 1,
    *,
    half_width: float = 2.0,
    radius: float = 0.5,
    half_thickness: float = 0.2,
    order: int = 1,
) -> Mesh:
    """Tetrahedral mesh of one eighth of a plate with a central hole (see the module).

    Args:
        n_theta: cells around the quarter hole (even: the 45° ray is a node line);
        n_r: cells from the hole to the edge; n_z: cells through the half-thickness.
        half_width, radius, half_thickness: ``W``, ``a``, ``T`` [m] (``a < W``).
        order: 1 (``tet4``, the hole a polygon) or 2 (``tet10``, the hole's mid-edge
            nodes on the circle: quadratic cells along the hole).
    Returns:
        A mesh of ``6·n_theta·n_r·n_z`` tets.
    """
    if not 0 < radius < half_width or not half_thickness > 0:
        raise ValueError("need 0 < radius < half_width and half_thickness > 0")
    cube = box(n_theta, n_r, n_z)
    u, v, w = np.asarray(cube.points, dtype=np.float64).T
    th = u * np.pi / 2
    c, s = np.cos(th), np.sin(th)
    outer = half_width / np.maximum(c, s)  # distance to the square's edge along the ray
    r = radius + v * (outer - radius)
    pts = np.stack([r * c, r * s, w * half_thickness], axis=1)
    pts[np.isclose(u, 0.0), 1] = 0.0  # exact symmetry planes
    pts[np.isclose(u, 1.0), 0] = 0.0
    cells = np.asarray(cube.cells).copy()
    e = pts[cells[:, 1:]] - pts[cells[:, :1]]
    neg = np.linalg.det(e) < 0
    cells[neg] = cells[neg][:, [0, 2, 1, 3]]
    mesh = from_arrays(pts, cells, "tet4")
    if order == 1:
        return mesh
    mesh = to_quadratic(mesh)  # then the hole's mid-edge nodes moved onto the circle
    P = np.asarray(mesh.points, dtype=np.float64).copy()
    r = np.linalg.norm(P[:, :2], axis=1)
    on_hole = (r < radius * (1 + 1e-9)) & (r > radius * np.cos(np.pi / (2 * n_theta)) * 0.999)
    P[on_hole, :2] *= (radius / r[on_hole])[:, None]
    return from_arrays(P, np.asarray(mesh.cells), "tet10")


class HoleTest(NamedTuple):
    """The tension test of :func:`hole_test`.

    Attributes:
        mesh: the specimen; bc: Dirichlet data at full pull; pulled: ``(k,)`` nodes of the
        gripped edge ``x = W``; top: the face ``z = T`` (DIC) as its z value.
    """

    mesh: Any
    bc: Any
    pulled: Any
    top: float


def hole_test(mesh: Mesh, pull: float) -> HoleTest:
    """Symmetry conditions and a pull ``pull`` [m] along x of the edge ``x = W``."""
    X = np.asarray(mesh.points)
    W, T = float(X[:, 0].max()), float(X[:, 2].max())
    sym = [loads.fix(mesh, loads.nodes_on_plane(mesh, a, 0.0), components=(a,)) for a in range(3)]
    pulled = loads.nodes_on_plane(mesh, 0, W)
    grip = loads.fix(mesh, pulled, components=(0,), displacement=[pull, 0.0, 0.0])
    return HoleTest(mesh, loads.combine(*sym, grip), pulled, T)


def dic_points(test: HoleTest, n: int, seed: int, margin: float = 0.1) -> np.ndarray:
    """``(n, 3)`` random points of the top face ``z = T``, at least ``margin`` [m] from
    the hole and inside the plate (so they lie in any mesh of it)."""
    X = np.asarray(test.mesh.points)
    W = float(X[:, 0].max())
    a = float(np.min(np.linalg.norm(X[:, :2], axis=1)))
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        p = rng.uniform(0.02 * W, 0.98 * W, size=2)
        if np.linalg.norm(p) >= a + margin:
            out.append([p[0], p[1], test.top])
    return np.asarray(out)


def synthetic_measurements(
    test: HoleTest, pot, factors, points, noise: float, seed: int, solver: Newton
) -> tuple[LoadPathCase, dict]:
    """A load path of ``test`` solved at ``pot.params`` and observed with Gaussian noise.

    The support force on the gripped edge along x and the in-plane (x, y) displacements at
    ``points`` at every load factor, each with ``σ = noise × RMS`` of its signal.

    Returns:
        ``(case, data)``: the noise-free case (its predictions) and ``data`` with
        ``force`` ``(L,)``, ``displacements`` ``(L, n, 2)``, ``sigma_force`` and
        ``sigma_u``.
    """
    e = jnp.asarray([1.0, 0.0, 0.0], test.mesh.points.dtype)
    L, n = len(factors), len(points)
    obs = (
        Reaction(jnp.asarray(test.pulled), e, jnp.zeros(L), 1.0),
        Points.at(test.mesh, points, np.zeros((L, n, 3)), 1.0, components=("x", "y")),
    )
    case = LoadPathCase(pot, test.bc, factors, obs)
    bound = case.bind(solver)
    (force, u), aux = case.predictions(pot.params, case.initial_warm(), bound, ImplicitAdjoint())
    if not bool(aux.ok):
        raise RuntimeError(f"synthetic solve failed at level {int(aux.level)}")
    force, u = np.asarray(force), np.asarray(u)
    rng = np.random.default_rng(seed)
    sf = noise * float(np.sqrt(np.mean(force**2)))
    su = noise * float(np.sqrt(np.mean(u**2)))
    data = dict(
        force=force + sf * rng.standard_normal(force.shape),
        displacements=u + su * rng.standard_normal(u.shape),
        sigma_force=sf,
        sigma_u=su,
    )
    return case, data
