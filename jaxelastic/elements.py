"""Reference elements: shape-function gradients and quadrature rules.

An :class:`Element` is static, hashable metadata (it is never traced). The mesh stores,
per cell and quadrature point, the physical shape-function gradients ``dN`` and the
quadrature weights (rest measure included). Energy, forces, HVP and element Hessians are
written against that generic ``(cells, quad points, nodes, dim)`` layout, so adding an
element (P2 triangles/tetrahedra) means adding a table here, nothing else.

P1 (linear) elements have one quadrature point, at which ``dN[:, 0, 1:, :] == Dm⁻¹`` and
``dN[:, 0, 0, :] == -Σ_k Dm⁻¹[k, :]``, so ``F = Σ_a x_a ⊗ ∇N_a = Ds·Dm⁻¹``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["Element", "ELEMENTS", "TRI3", "TET4", "get_element"]


@dataclasses.dataclass(frozen=True)
class Element:
    """A reference element with its quadrature rule.

    Attributes:
        name: ``"tri3"`` or ``"tet4"`` (meshio names: ``"triangle"``, ``"tetra"``).
        dim: spatial dimension, 2 or 3.
        n_nodes: nodes per cell.
        meshio_type: the meshio cell-type name.
        quad_points: ``(n_q, dim)`` reference coordinates of quadrature points.
        quad_weights: ``(n_q,)`` reference weights (summing to the reference measure).
        facet_nodes: local node indices of each facet, ``(n_facets, n_facet_nodes)``,
            ordered so that facet normals computed with the right-hand rule point outward
            for a positively oriented cell.
    """

    name: str
    dim: int
    n_nodes: int
    meshio_type: str
    quad_points: tuple
    quad_weights: tuple
    facet_nodes: tuple

    @property
    def n_quad(self) -> int:
        return len(self.quad_weights)

    def shape_gradients(self) -> np.ndarray:
        """Reference gradients ``∂N_a/∂ξ_j`` at the quadrature points, ``(n_q, n_nodes, dim)``."""
        q = np.asarray(self.quad_points, dtype=np.float64)
        if self.name in ("tri3", "tet4"):
            g = np.zeros((self.n_nodes, self.dim))
            g[0, :] = -1.0
            g[1:, :] = np.eye(self.dim)
            return np.broadcast_to(g, (q.shape[0], self.n_nodes, self.dim)).copy()
        raise NotImplementedError(f"shape gradients for element {self.name!r}")


TRI3 = Element(
    name="tri3",
    dim=2,
    n_nodes=3,
    meshio_type="triangle",
    quad_points=((1.0 / 3.0, 1.0 / 3.0),),
    quad_weights=(0.5,),
    facet_nodes=((0, 1), (1, 2), (2, 0)),
)

TET4 = Element(
    name="tet4",
    dim=3,
    n_nodes=4,
    meshio_type="tetra",
    quad_points=((0.25, 0.25, 0.25),),
    quad_weights=(1.0 / 6.0,),
    # outward for positive orientation det[x1-x0, x2-x0, x3-x0] > 0
    facet_nodes=((0, 2, 1), (0, 1, 3), (1, 2, 3), (0, 3, 2)),
)

ELEMENTS = {e.name: e for e in (TRI3, TET4)}
_BY_MESHIO = {e.meshio_type: e for e in (TRI3, TET4)}


def get_element(name: str) -> Element:
    """Look an element up by its jaxelastic name (``"tri3"``) or meshio name (``"triangle"``)."""
    if name in ELEMENTS:
        return ELEMENTS[name]
    if name in _BY_MESHIO:
        return _BY_MESHIO[name]
    raise ValueError(
        f"unsupported element type {name!r}; supported: "
        f"{sorted(ELEMENTS)} (meshio: {sorted(_BY_MESHIO)})"
    )
