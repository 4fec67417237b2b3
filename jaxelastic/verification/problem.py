"""The benchmark problem record and the small helpers the problem definitions share."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping

import numpy as np

from ..loads import Dirichlet
from ..mechanics.potential import Potential
from ..mesh import Mesh

__all__ = ["Benchmark", "node_at", "edge_load_2d"]


@dataclasses.dataclass(frozen=True, eq=False)
class Benchmark:
    """A reference problem: what to minimise, what is fixed, and the known answer.

    Only the definition: solve it with ``je.solve(b.pot, b.bc, ...)`` (or load stepping,
    see ``steps``) and compare with ``reference``.

    Attributes:
        name: short identifier (``"cook"``, ``"timoshenko"``, ...).
        pot: the potential: mesh, ψ, parameters and external nodal forces ``f_ext``
            ``(n_nodes, dim)`` [force].
        bc: the Dirichlet data.
        reference: named reference values (e.g. ``{"u_y": 23.96}``), in the problem's units.
        citation: where the reference values come from.
        probes: named node-index arrays where the reference quantities are read
            (e.g. ``{"point": array([i])}``).
        exact: the exact displacement field, ``X (k, dim) -> (u (k, dim), ∂u/∂X (k, dim,
            dim))``, when one is known.
        lame: ``(μ, λ)`` of the small-strain energy norm (for error norms), when meaningful.
        steps: suggested load increments (0: one plain solve is expected to converge).
    """

    name: str
    pot: Potential
    bc: Dirichlet
    reference: Mapping[str, float] = dataclasses.field(default_factory=dict)
    citation: str = ""
    probes: Mapping[str, np.ndarray] = dataclasses.field(default_factory=dict)
    exact: Callable | None = None
    lame: tuple[float, float] | None = None
    steps: int = 0

    @property
    def mesh(self) -> Mesh:
        return self.pot.mesh

    @property
    def psi(self) -> Callable:
        return self.pot.psi

    @property
    def params(self):
        return self.pot.params


def node_at(mesh: Mesh, point, tol: float = 1e-8) -> int:
    """Index of the node at ``point`` ``(dim,)`` [length]; raises :class:`ValueError` if the
    nearest node is farther than ``tol`` times the mesh extent (at least 1)."""
    X = np.asarray(mesh.points)
    d = np.linalg.norm(X - np.asarray(point, float), axis=1)
    i = int(np.argmin(d))
    if d[i] > tol * max(1.0, float(np.ptp(X))):
        raise ValueError(f"no node at {point} (nearest {X[i]})")
    return i


def _gauss01(n: int):
    p, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (p + 1.0), 0.5 * w


def edge_load_2d(mesh: Mesh, facets, t_fn, n_gauss: int = 5) -> np.ndarray:
    """Consistent nodal forces ``∫ N_a t(X) ds`` of a traction field on 2D boundary facets.

    Args:
        mesh: a 2D mesh.
        facets: ``(m, 2)`` (P1) or ``(m, 3)`` (corner, corner, mid: P2, or composite P1
            whose field is linear on each half) node indices, as
            :func:`~jaxelastic.mesh.boundary_facets` returns them.
        t_fn: ``X (k, 2) -> t (k, 2)`` traction [force/length].
        n_gauss: Gauss–Legendre points per (half-)edge.

    Returns:
        ``(n_nodes, 2)`` nodal forces [force].
    """
    X = np.asarray(mesh.points)
    facets = np.asarray(facets)
    f = np.zeros_like(X)
    s, w = _gauss01(n_gauss)
    composite = mesh.element_type.is_composite if facets.shape[1] == 3 else False
    if facets.shape[1] == 2:
        segs = [(s, w, np.stack([1 - s, s], 1))]
    elif composite:
        a, b = 0.5 * s, 0.5 + 0.5 * s
        z = np.zeros_like(s)
        segs = [
            (a, 0.5 * w, np.stack([1 - 2 * a, z, 2 * a], 1)),
            (b, 0.5 * w, np.stack([z, 2 * b - 1, 2 - 2 * b], 1)),
        ]
    else:
        segs = [(s, w, np.stack([(1 - s) * (1 - 2 * s), s * (2 * s - 1), 4 * s * (1 - s)], 1))]
    A, B = X[facets[:, 0]], X[facets[:, 1]]
    length = np.linalg.norm(B - A, axis=1)
    for sq, wq, N in segs:
        for k in range(sq.size):
            Xq = A + sq[k] * (B - A)
            t = np.asarray(t_fn(Xq), float)
            for a in range(facets.shape[1]):
                np.add.at(f, facets[:, a], (wq[k] * N[k, a] * length)[:, None] * t)
    return f
