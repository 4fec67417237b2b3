"""Reference elements: shape functions, their gradients and quadrature rules.

An :class:`Element` is static, hashable metadata (it is never traced). The mesh stores,
per cell and quadrature point, the physical shape-function gradients ``dN`` and the
quadrature weights (rest measure included). Energy, forces, HVP and element Hessians are
written against that generic ``(cells, quad points, nodes, dim)`` layout, so an element is
a table here and nothing else.

* ``tri3``/``tet4`` (P1): one quadrature point, at which ``dN[:, 0, 1:, :] == Dm⁻¹``.
* ``tri6``/``tet10`` (P2, isoparametric, so curved cells read from files work): node order
  of meshio/VTK ``triangle6`` (corners, then edges (0,1), (1,2), (2,0)) and ``tetra10``
  (corners, then edges (0,1), (1,2), (0,2), (0,3), (1,3), (2,3)). Shape functions
  ``N_i = L_i(2L_i − 1)`` at corners and ``4 L_a L_b`` at edge mid-nodes (barycentric
  ``L``; Zienkiewicz, Taylor & Zhu, *The FEM: its basis and fundamentals*, 7th ed., §6.5).
  Quadrature: ``tri6`` the 6-point degree-4 rule with positive weights (Dunavant 1985,
  IJNME 21:1129, closed form of Strang & Fix 1973); ``tet10`` the 14-point degree-5 rule
  with positive weights (Walkington 2000; Keast 1986). Why these degrees: on a curved
  (isoparametric) cell ``∇N_a det J`` is a polynomial of degree 2 (tri6) / 5 (tet10), and
  integrating it exactly is what makes the patch test (an affine map gives zero interior
  forces for every ψ) exact on curved cells; the cheaper 4-point degree-2 tet rule (Abaqus
  C3D10) is exact only on straight-sided cells (measured: 4e-6 residual forces on a mildly
  curved patch) and under-integrates nonlinear ψ. Both rules exceed the degree 2 needed
  for linear elasticity on straight cells.
* ``tri3x4``/``tet4x8`` (composite P1): the P2 node set, each cell split into 4 / 8 linear
  sub-simplices (red refinement; the tet's interior diagonal joins the mid-nodes of edges
  (0,1) and (2,3)). Each sub-simplex is one "quadrature point" with its own constant
  gradient, so plain energy equals P1 on the refined mesh; with the ``"fbar"`` formulation
  the patch carries one volume constraint (Thoutireddy et al. 2002, IJNME 53:1337;
  de Souza Neto et al. 2005, IJNME 62:353).

Facets: ``facet_nodes`` lists the local nodes of each facet (corners first, then the facet's
mid-edge nodes in the order (a,b), (b,c), (c,a)), outward for a positively oriented cell.
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np

__all__ = [
    "Element",
    "ELEMENTS",
    "TRI3",
    "TET4",
    "TRI6",
    "TET10",
    "TRI3X4",
    "TET4X8",
    "TRI_EDGES",
    "TET_EDGES",
    "get_element",
    "facet_rule",
    "edge_table",
    "ref_nodes",
]

_SQ = np.sqrt


def _tri_deg4():
    """6-point degree-4 rule on the unit triangle (Dunavant 1985), weights sum to 1/2."""
    r = _SQ(38.0 - 44.0 * _SQ(2.0 / 5.0))
    a, b = (8.0 - _SQ(10.0) + r) / 18.0, (8.0 - _SQ(10.0) - r) / 18.0
    s = _SQ(213125.0 - 53320.0 * _SQ(10.0))
    wa, wb = (620.0 + s) / 3720.0 / 2.0, (620.0 - s) / 3720.0 / 2.0
    pts = [(a, a), (1 - 2 * a, a), (a, 1 - 2 * a), (b, b), (1 - 2 * b, b), (b, 1 - 2 * b)]
    return tuple(pts), (wa,) * 3 + (wb,) * 3


def _tet_deg5():
    """14-point degree-5 rule with positive weights (Walkington 2000; Keast 1986), sum 1/6.

    Constants refined by Newton on the moment equations (exact to ~1e-17).
    """
    pts, w = [], []
    for a, wa in (
        (0.0927352503108912, 0.01224884051939366),
        (0.3108859192633006, 0.01878132095300264),
    ):
        for k in range(4):
            L = [a] * 4
            L[k] = 1.0 - 3.0 * a
            pts.append(tuple(L[1:]))
            w.append(wa)
    b = 0.4544962958743504
    for i, j in itertools.combinations(range(4), 2):
        L = [0.5 - b] * 4
        L[i] = L[j] = b
        pts.append(tuple(L[1:]))
        w.append(0.007091003462846911)
    return tuple(pts), tuple(w)


def _gauss_line3():
    """3-point Gauss–Legendre rule on [0, 1] (degree 5), weights sum to 1."""
    g = _SQ(0.6) / 2.0
    return ((0.5 - g,), (0.5,), (0.5 + g,)), (5.0 / 18.0, 8.0 / 18.0, 5.0 / 18.0)


# local edges (pairs of corners) of the P2 mid-nodes, in meshio/VTK order
TRI_EDGES = ((0, 1), (1, 2), (2, 0))
TET_EDGES = ((0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3))


def edge_table(element: Element) -> np.ndarray:
    """``(n_edges, 2)`` local corner pairs of an element's edges, in the order of the P2
    mid-edge nodes (meshio/VTK): 3 edges for a triangle, 6 for a tetrahedron.

    Args:
        element: an :class:`Element` (only its ``dim`` is used).
    """
    return np.asarray(TRI_EDGES if element.dim == 2 else TET_EDGES)


def _bary(xi: np.ndarray) -> np.ndarray:
    """Barycentric coordinates ``(n, d+1)`` of reference points ``(n, d)``."""
    return np.concatenate([1.0 - xi.sum(axis=1, keepdims=True), xi], axis=1)


def _p2_values(xi: np.ndarray, edges) -> np.ndarray:
    L = _bary(xi)
    corners = L * (2.0 * L - 1.0)
    mids = np.stack([4.0 * L[:, a] * L[:, b] for a, b in edges], axis=1)
    return np.concatenate([corners, mids], axis=1)


def _p2_gradients(xi: np.ndarray, edges) -> np.ndarray:
    n, d = xi.shape
    L = _bary(xi)
    dL = np.concatenate([-np.ones((1, d)), np.eye(d)])  # (d+1, d): ∂L_i/∂ξ_j
    g_corner = (4.0 * L - 1.0)[:, :, None] * dL[None]  # (n, d+1, d)
    g_mid = np.stack(
        [4.0 * (L[:, a, None] * dL[b] + L[:, b, None] * dL[a]) for a, b in edges], axis=1
    )
    return np.concatenate([g_corner, g_mid], axis=1)


def ref_nodes(dim: int) -> np.ndarray:
    """Reference coordinates of the P2 nodes (corners, then edge mid-points),
    ``(n_nodes, dim)``; ``dim`` is 2 (6 nodes) or 3 (10 nodes)."""
    corners = np.concatenate([np.zeros((1, dim)), np.eye(dim)])
    edges = TRI_EDGES if dim == 2 else TET_EDGES
    return np.concatenate([corners, [(corners[a] + corners[b]) / 2 for a, b in edges]])


def _oriented(sub, nodes: np.ndarray):
    """Reorder each sub-simplex (tuple of local nodes) to positive orientation."""
    out = []
    for s in sub:
        s = list(s)
        D = (nodes[s[1:]] - nodes[s[0]]).T
        if np.linalg.det(D) < 0:
            s[1], s[2] = s[2], s[1]
        out.append(tuple(s))
    return tuple(out)


_TRI_SUB = ((0, 3, 5), (3, 1, 4), (5, 4, 2), (3, 4, 5))
# corner tets, then the octahedron split along the diagonal 4–9 (mid(0,1)–mid(2,3))
_TET_SUB = (
    (0, 4, 6, 7),
    (4, 1, 5, 8),
    (6, 5, 2, 9),
    (7, 8, 9, 3),
    (4, 9, 5, 6),
    (4, 9, 6, 7),
    (4, 9, 7, 8),
    (4, 9, 8, 5),
)


@dataclasses.dataclass(frozen=True)
class Element:
    """A reference element with its quadrature rule.

    Attributes:
        name: ``"tri3"``, ``"tet4"``, ``"tri6"``, ``"tet10"``, ``"tri3x4"``, ``"tet4x8"``.
        dim: spatial dimension, 2 or 3.
        n_nodes: nodes per cell.
        meshio_type: the meshio cell-type name of the node layout.
        quad_points: ``(n_q, dim)`` reference coordinates of quadrature points (for
            composite elements: the sub-simplex centroids).
        quad_weights: ``(n_q,)`` reference weights (summing to the reference measure).
        facet_nodes: local node indices of each facet, ``(n_facets, n_facet_nodes)``,
            ordered so that facet normals computed with the right-hand rule on the corners
            point outward for a positively oriented cell.
        order: polynomial order of the displacement (1 or 2; composite elements are 1).
        sub_cells: composite elements: ``(n_sub, dim+1)`` local nodes of each linear
            sub-simplex (one per quadrature point); empty otherwise.
    """

    name: str
    dim: int
    n_nodes: int
    meshio_type: str
    quad_points: tuple
    quad_weights: tuple
    facet_nodes: tuple
    order: int = 1
    sub_cells: tuple = ()

    @property
    def n_quad(self) -> int:
        return len(self.quad_weights)

    @property
    def n_corners(self) -> int:
        return self.dim + 1

    @property
    def is_composite(self) -> bool:
        return bool(self.sub_cells)

    @property
    def facet_kind(self) -> str:
        """``"p1"``, ``"p2"`` or ``"composite"``: how fields vary along a facet."""
        return "composite" if self.is_composite else ("p2" if self.order == 2 else "p1")

    def shape_functions(self, xi) -> np.ndarray:
        """Shape-function values ``(n, n_nodes)`` at reference points ``xi`` ``(n, dim)``."""
        xi = np.atleast_2d(np.asarray(xi, dtype=np.float64))
        if self.n_nodes == self.dim + 1:
            return _bary(xi)
        if self.is_composite:
            raise ValueError(f"{self.name!r} is piecewise linear; use sub_cells")
        return _p2_values(xi, TRI_EDGES if self.dim == 2 else TET_EDGES)

    def shape_gradients(self, xi=None) -> np.ndarray:
        """Reference gradients ``∂N_a/∂ξ_j``, ``(n_q, n_nodes, dim)``, at the quadrature
        points (default) or at ``xi`` ``(n, dim)`` (not for composite elements)."""
        if self.is_composite:
            if xi is not None:
                raise ValueError(f"{self.name!r} gradients are defined per sub-simplex")
            nodes = ref_nodes(self.dim)
            g1 = np.concatenate([-np.ones((1, self.dim)), np.eye(self.dim)])
            out = np.zeros((len(self.sub_cells), self.n_nodes, self.dim))
            for s, sub in enumerate(self.sub_cells):
                D = (nodes[list(sub[1:])] - nodes[sub[0]]).T  # ξ = Y0 + D η
                out[s, list(sub)] = g1 @ np.linalg.inv(D)
            return out
        q = np.asarray(self.quad_points if xi is None else xi, dtype=np.float64)
        q = np.atleast_2d(q)
        if self.n_nodes == self.dim + 1:
            g = np.concatenate([-np.ones((1, self.dim)), np.eye(self.dim)])
            return np.broadcast_to(g, (q.shape[0], self.n_nodes, self.dim)).copy()
        return _p2_gradients(q, TRI_EDGES if self.dim == 2 else TET_EDGES)

    def mass_rule(self) -> tuple[np.ndarray, np.ndarray]:
        """A rule exact to degree ≥ 4 on the reference simplex (for ``∫N_a N_b``), as
        ``(points (n, dim), weights (n,))`` (the P2 stiffness rules)."""
        p, w = _tri_deg4() if self.dim == 2 else _tet_deg5()
        return np.asarray(p), np.asarray(w)


_TRI_FACETS: tuple[tuple[int, ...], ...] = ((0, 1), (1, 2), (2, 0))
# outward for positive orientation det[x1-x0, x2-x0, x3-x0] > 0
_TET_FACETS: tuple[tuple[int, ...], ...] = ((0, 2, 1), (0, 1, 3), (1, 2, 3), (0, 3, 2))


def _p2_facets(dim: int) -> tuple:
    edges = TRI_EDGES if dim == 2 else TET_EDGES
    mid = {frozenset(e): dim + 1 + i for i, e in enumerate(edges)}
    out = []
    for f in _TRI_FACETS if dim == 2 else _TET_FACETS:
        ring = [(f[0], f[1])] if dim == 2 else [(f[0], f[1]), (f[1], f[2]), (f[2], f[0])]
        out.append(tuple(f) + tuple(mid[frozenset(e)] for e in ring))
    return tuple(out)


def _composite(name, dim, meshio_type, sub):
    nodes = ref_nodes(dim)
    sub = _oriented(sub, nodes)
    ref = 0.5 if dim == 2 else 1.0 / 6.0
    cents = tuple(tuple(nodes[list(s)].mean(axis=0)) for s in sub)
    return Element(
        name=name,
        dim=dim,
        n_nodes=len(nodes),
        meshio_type=meshio_type,
        quad_points=cents,
        quad_weights=(ref / len(sub),) * len(sub),
        facet_nodes=_p2_facets(dim),
        order=1,
        sub_cells=sub,
    )


TRI3 = Element("tri3", 2, 3, "triangle", ((1.0 / 3.0, 1.0 / 3.0),), (0.5,), _TRI_FACETS)
TET4 = Element("tet4", 3, 4, "tetra", ((0.25, 0.25, 0.25),), (1.0 / 6.0,), _TET_FACETS)
TRI6 = Element("tri6", 2, 6, "triangle6", *_tri_deg4(), _p2_facets(2), order=2)
TET10 = Element("tet10", 3, 10, "tetra10", *_tet_deg5(), _p2_facets(3), order=2)
TRI3X4 = _composite("tri3x4", 2, "triangle6", _TRI_SUB)
TET4X8 = _composite("tet4x8", 3, "tetra10", _TET_SUB)

_ALL = (TRI3, TET4, TRI6, TET10, TRI3X4, TET4X8)
ELEMENTS = {e.name: e for e in _ALL}
_BY_MESHIO = {e.meshio_type: e for e in (TRI3, TET4, TRI6, TET10)}


def get_element(name: str) -> Element:
    """Look an element up by its jaxelastic name (``"tri6"``) or meshio name (``"triangle6"``;
    a meshio name maps to the standard, not the composite, element)."""
    if name in ELEMENTS:
        return ELEMENTS[name]
    if name in _BY_MESHIO:
        return _BY_MESHIO[name]
    raise ValueError(
        f"unsupported element type {name!r}; supported: "
        f"{sorted(ELEMENTS)} (meshio: {sorted(_BY_MESHIO)})"
    )


def facet_rule(element: Element) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Facet shape functions at a facet quadrature rule, for consistent facet integrals.

    Returns:
        ``(N (n, m), dN (n, m, dim-1), w (n,))``: the ``m`` facet-node shape functions and
        their gradients with respect to the facet's reference coordinates at ``n`` points,
        with weights summing to the reference facet measure (1 for a line, 1/2 for a
        triangle). Composite facets are integrated exactly sub-facet by sub-facet (the
        field is piecewise linear there): points/weights concatenate the sub-facet rules.
    """
    if element.dim == 2:
        (p, w), facet_dim = _gauss_line3(), 1
        p = np.asarray(p)
        nodes = np.array([[0.0], [1.0], [0.5]])
        subs = ((0, 2), (2, 1))
    else:
        (p, w), facet_dim = _tri_deg4(), 2
        p = np.asarray(p)
        nodes = ref_nodes(2)
        subs = _TRI_SUB
    w = np.asarray(w)
    kind = element.facet_kind
    if kind == "p1":
        L = _bary(p)
        g = np.concatenate([-np.ones((1, facet_dim)), np.eye(facet_dim)])
        return L, np.broadcast_to(g, (len(w),) + g.shape).copy(), w
    if kind == "p2":
        if facet_dim == 1:
            s = p[:, 0]
            N = np.stack([(1 - s) * (1 - 2 * s), s * (2 * s - 1), 4 * s * (1 - s)], axis=1)
            dN = np.stack([4 * s - 3, 4 * s - 1, 4 - 8 * s], axis=1)[:, :, None]
            return N, dN, w
        return _p2_values(p, TRI_EDGES), _p2_gradients(p, TRI_EDGES), w
    # composite: map the rule into each sub-facet, piecewise-linear shape functions
    Ns, dNs, ws = [], [], []
    g1 = np.concatenate([-np.ones((1, facet_dim)), np.eye(facet_dim)])
    for sub in subs:
        Y = nodes[list(sub)]
        D = (Y[1:] - Y[0]).T  # (fd, fd)
        L = _bary(p)  # sub-facet barycentric = shape function values
        N = np.zeros((len(w), len(nodes)))
        N[:, list(sub)] = L
        dN = np.zeros((len(w), len(nodes), facet_dim))
        dN[:, list(sub)] = g1 @ np.linalg.inv(D)
        Ns.append(N)
        dNs.append(dN)
        ws.append(w * abs(np.linalg.det(D)))
    return np.concatenate(Ns), np.concatenate(dNs), np.concatenate(ws)
