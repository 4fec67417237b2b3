"""Measurements: one protocol that maps a solved state to predicted data, and its kinds.

An :class:`Observation` holds measured data of one kind at every load level of a case
(leading axis: the level) and its standard deviation σ (in the data's units). Its
:meth:`~Observation.predict` maps a :class:`SolvedState` (positions, support reactions,
parameters, mesh) to the prediction of one level's data; the weighted residuals
``(pred − data)/σ`` of every observation of every level form one Gaussian misfit
``Σ ((pred − data)/σ)²`` (χ²), whatever the kinds (Tarantola 2005, *Inverse Problem
Theory*, §3.2). Kinds:

* :class:`Positions`: positions of nodes ``(n, dim)`` [m];
* :class:`Points`: displacements ``(n, dim)`` [m] at material points given by their rest
  coordinates, located once on the host (:func:`locate_points`) and interpolated with the
  element's own shape functions (P1 and P2), optionally only some components (2D DIC);
* :class:`Reaction`: the resultant support force on a node set along a direction [N]
  (force–displacement curves);
* :class:`Moment`: the resultant support moment on a node set about an axis through a
  point [N·m] (torsion tests);
* :class:`CavityVolume`: the volume enclosed by a cavity's deformed boundary surface
  [m³] (:meth:`Pressure.volumes <jaxelastic.mechanics.pressure.Pressure.volumes>`;
  pressure–volume curves of a ventricle or a balloon);
* :class:`Surface`: a measured point cloud of the deformed shape without correspondence:
  the signed distance of each point to the nearest boundary facet of the deformed mesh
  (point-to-triangle in 3D, point-to-segment in 2D; Ericson 2005, *Real-Time Collision
  Detection*, §5.1.5), smooth through zero where the nearest point lies inside a facet.

Every kind is a frozen dataclass pytree: data arrays are traced, the layout (components,
element order) static. New kinds subclass :class:`Observation` and register themselves
with :func:`jax.tree_util.register_dataclass`.
"""

from __future__ import annotations

import abc
import dataclasses
from typing import Any, ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..mechanics.pressure import Pressure, pressure_term
from ..mesh import boundary_facets
from ..mesh.elements import TET_EDGES, TRI_EDGES

__all__ = [
    "SolvedState",
    "Observation",
    "Positions",
    "Points",
    "Reaction",
    "Moment",
    "CavityVolume",
    "Surface",
    "locate_points",
    "point_to_facet_distance",
    "COMPONENTS",
]

COMPONENTS = ("x", "y", "z")
"""Names of the displacement components, in axis order."""


class SolvedState(NamedTuple):
    """The solved state an observation predicts from (one load level).

    Attributes:
        x: ``(n_nodes, dim)`` equilibrium positions [m].
        reactions: ``(n_nodes, dim)`` nodal support forces on the body ``∂Π/∂x`` [N]
            (zero at free dofs up to the solver tolerance), or None when no observation
            of the case needs them.
        params: the ψ parameters of the solve.
        mesh: the rest mesh.
    """

    x: Any
    reactions: Any
    params: Any
    mesh: Any


class Observation(abc.ABC):
    """Abstract observation: ``data`` with a leading level axis, ``sigma`` > 0 (see the
    module docstring). Subclasses define :meth:`predict`."""

    data: Any
    sigma: Any
    kind: ClassVar[str] = "observation"
    needs_reactions: ClassVar[bool] = False

    @abc.abstractmethod
    def predict(self, state: SolvedState, level_data):
        """The prediction of one level's measured quantity (the shape of
        :meth:`target`), given that level's ``data`` (only :class:`Surface` reads it)."""

    def target(self, level_data):
        """The measured quantity of one level (default: its data)."""
        return level_data

    @property
    def n_levels(self) -> int:
        """Number of load levels the data covers."""
        return int(np.shape(self.data)[0])

    def residuals(self, state: SolvedState, level_data):
        """Weighted residuals ``(pred − measured)/σ`` of one level, raveled."""
        pred = self.predict(state, level_data)
        return jnp.ravel((pred - self.target(level_data)) / self.sigma)

    def check(self) -> None:
        """Raise ValueError on non-finite data or σ ≤ 0 (outside jit)."""
        s = np.asarray(self.sigma, dtype=np.float64)
        if not (np.all(np.isfinite(s)) and np.all(s > 0)):
            raise ValueError(f"{self.kind} observation: sigma must be > 0 and finite, got {s}")
        bad = np.argwhere(~np.isfinite(np.asarray(self.data, dtype=np.float64)))
        if bad.size:
            idx = tuple(int(i) for i in bad[0])
            raise ValueError(
                f"{self.kind} observation: data is not finite at index {idx} (level, entry, ...)"
            )


def _register(cls, data, meta=()):
    jax.tree_util.register_dataclass(cls, data_fields=list(data), meta_fields=list(meta))
    return cls


@dataclasses.dataclass(frozen=True)
class Positions(Observation):
    """Deformed positions of nodes.

    Attributes:
        nodes: ``(n,)`` int node indices.
        data: ``(n_levels, n, dim)`` measured positions [m].
        sigma: standard deviation of each coordinate [m].
    """

    nodes: Any
    data: Any
    sigma: Any = 1.0
    kind: ClassVar[str] = "positions"

    def predict(self, state: SolvedState, level_data=None):
        return state.x[self.nodes]


_register(Positions, ["nodes", "data", "sigma"])


@dataclasses.dataclass(frozen=True)
class Points(Observation):
    """Displacements at material points (DIC), interpolated in the cell containing each.

    Build with :meth:`at` (locates the points once on the host).

    Attributes:
        cells: ``(n, k)`` int, the nodes of the cell containing each point.
        shape: ``(n, k)`` shape-function values of those nodes at the point.
        rest: ``(n, dim)`` rest coordinates of the points [m].
        data: ``(n_levels, n, c)`` measured displacements [m] of the observed components.
        sigma: standard deviation of each measured component [m].
        components: static tuple of the observed axes (e.g. ``(0, 1)``).
    """

    cells: Any
    shape: Any
    rest: Any
    data: Any
    sigma: Any = 1.0
    components: tuple = dataclasses.field(default=(0, 1, 2), metadata=dict(static=True))
    kind: ClassVar[str] = "points"

    @classmethod
    def at(cls, mesh, points, displacements, sigma, components=None) -> Points:
        """Locate ``points`` ``(n, dim)`` [m] in ``mesh``; ``displacements``
        ``(n_levels, n, dim)`` [m] (only ``components``, names ``"x"``, ``"y"``, ``"z"``
        or axes, are kept; default all), or ``(n_levels, n, len(components))`` already
        reduced to them.

        Raises:
            ValueError: a point outside the body, or shapes that do not match.
        """
        dim = int(mesh.dim)
        comps = _components(components, dim)
        pts = np.asarray(points, dtype=np.float64)
        u = np.asarray(displacements, dtype=np.float64)
        reduced = u.ndim == 3 and u.shape[2] == len(comps) < dim
        n = pts.shape[0] if pts.ndim == 2 else -1
        if (
            pts.ndim != 2
            or pts.shape[1] != dim
            or u.ndim != 3
            or u.shape[1] != n
            or not (reduced or u.shape[2] == dim)
        ):
            raise ValueError(
                f"points must be (n, {dim}) and displacements (n_levels, n, {dim}); got "
                f"{pts.shape} and {u.shape}"
            )
        if not reduced:
            u = u[..., list(comps)]
        cell, N = locate_points(mesh, pts)
        nodes = np.asarray(mesh.cells)[cell]
        dt = mesh.points.dtype
        return cls(
            jnp.asarray(nodes),
            jnp.asarray(N, dt),
            jnp.asarray(pts, dt),
            jnp.asarray(u, dt),
            sigma,
            comps,
        )

    def predict(self, state: SolvedState, level_data=None):
        x = jnp.einsum("nk,nkd->nd", self.shape, state.x[self.cells])
        return (x - self.rest)[:, list(self.components)]


_register(Points, ["cells", "shape", "rest", "data", "sigma"], ["components"])


def _components(components, dim: int) -> tuple[int, ...]:
    if components is None:
        return tuple(range(dim))
    out = []
    for c in components:
        axis = COMPONENTS.index(c) if c in COMPONENTS else c
        if not isinstance(axis, int | np.integer) or not 0 <= int(axis) < dim:
            raise ValueError(f"components must be among {COMPONENTS[:dim]}, got {components!r}")
        out.append(int(axis))
    if not out or len(set(out)) != len(out):
        raise ValueError(f"components must be distinct and non-empty, got {components!r}")
    return tuple(out)


@dataclasses.dataclass(frozen=True)
class Reaction(Observation):
    """Resultant support force on a node set along a direction (a testing machine's load
    cell): ``Σ_{a ∈ nodes} R_a · direction`` [N], R the support force on the body.

    Attributes:
        nodes: ``(k,)`` int nodes (normally a Dirichlet node set).
        direction: ``(dim,)`` unit vector.
        data: ``(n_levels,)`` measured forces [N].
        sigma: standard deviation [N].
    """

    nodes: Any
    direction: Any
    data: Any
    sigma: Any = 1.0
    kind: ClassVar[str] = "reaction"
    needs_reactions: ClassVar[bool] = True

    def predict(self, state: SolvedState, level_data=None):
        return jnp.sum(state.reactions[self.nodes] @ self.direction)


_register(Reaction, ["nodes", "direction", "data", "sigma"])


@dataclasses.dataclass(frozen=True)
class Moment(Observation):
    """Resultant support moment on a node set about an axis through ``origin`` (torsion):
    ``Σ_a ((x_a − origin) × R_a) · axis`` [N·m] at the deformed positions; in 2D the
    out-of-plane moment (``axis`` unused, pass ``(1.0,)``).

    Attributes:
        nodes: ``(k,)`` int nodes; axis: ``(3,)`` unit vector (3D); origin: ``(dim,)`` [m];
        data: ``(n_levels,)`` measured moments [N·m]; sigma: [N·m].
    """

    nodes: Any
    axis: Any
    origin: Any
    data: Any
    sigma: Any = 1.0
    kind: ClassVar[str] = "moment"
    needs_reactions: ClassVar[bool] = True

    def predict(self, state: SolvedState, level_data=None):
        r = state.x[self.nodes] - self.origin[None, :]
        R = state.reactions[self.nodes]
        if r.shape[-1] == 2:
            return jnp.sum(r[:, 0] * R[:, 1] - r[:, 1] * R[:, 0])
        return jnp.sum(jnp.cross(r, R) @ self.axis)


_register(Moment, ["nodes", "axis", "origin", "data", "sigma"])


@dataclasses.dataclass(frozen=True)
class CavityVolume(Observation):
    """The volumes of cavities at the deformed positions (pressure–volume curves):
    ``V_s(x) = −(1/d) ∫_{S_s} (x − c_s)·n da`` of each surface of ``cavity``, closed by
    the cone to its point ``c_s`` (:mod:`jaxelastic.mechanics.pressure`; an area per unit
    thickness in 2D).

    Build with :meth:`at`, or from the pressure term that loads the cavity
    (``CavityVolume(pot.pressure, volumes, sigma)``: its pressures are not used).

    Attributes:
        cavity: :class:`~jaxelastic.mechanics.pressure.Pressure` whose surfaces bound the
            cavities (``n_s`` of them).
        data: ``(n_levels,)`` measured volumes of a single cavity, or ``(n_levels, n_s)``
            [m³].
        sigma: standard deviation [m³].
    """

    cavity: Pressure
    data: Any
    sigma: Any = 1.0
    kind: ClassVar[str] = "cavity_volume"

    @classmethod
    def at(cls, mesh, facets, volumes, sigma, origin=None) -> CavityVolume:
        """The cavity bounded by ``facets`` (boundary facets of ``mesh``, one ``(m, k)``
        array or a list, one per cavity) closed at ``origin`` (default: the centroid of
        the rim, see :func:`~jaxelastic.mechanics.pressure.pressure_term`), measured
        ``volumes`` [m³] at every level."""
        term = pressure_term(mesh, facets, 0.0, origin, what="cavity volume")
        return cls(term, jnp.asarray(volumes, mesh.points.dtype), sigma)

    def predict(self, state: SolvedState, level_data=None):
        v = self.cavity.volumes(state.x)
        return v[0] if np.ndim(self.data) == 1 else v

    def check(self) -> None:
        """Also refuse data that is not ``(n_levels,)`` for one cavity or
        ``(n_levels, n_s)``."""
        super().check()
        n_s, shape = int(self.cavity.pressure.shape[0]), np.shape(self.data)
        ok = (len(shape) == 1 and n_s == 1) or (len(shape) == 2 and shape[1] == n_s)
        if not ok:
            want = "(n_levels,) or " if n_s == 1 else ""
            raise ValueError(
                f"cavity_volume observation: data must be {want}(n_levels, {n_s}) for "
                f"{n_s} cavit{'y' if n_s == 1 else 'ies'}, got shape {shape}"
            )


_register(CavityVolume, ["cavity", "data", "sigma"])


@dataclasses.dataclass(frozen=True)
class Surface(Observation):
    """A measured point cloud of the deformed boundary, without correspondence: predicted
    is the signed distance of each point to the nearest boundary facet of the deformed
    mesh (every facet is tried), measured is zero.

    Build with :meth:`at`. Facets of P2 meshes are taken flat (their corners).

    Attributes:
        facets: ``(n_facets, dim)`` int corner nodes of the boundary facets (outward).
        data: ``(n_levels, m, dim)`` measured deformed positions [m].
        sigma: standard deviation of a point's distance to the surface [m].
    """

    facets: Any
    data: Any
    sigma: Any = 1.0
    kind: ClassVar[str] = "surface"

    @classmethod
    def at(cls, mesh, points, sigma, facets=None) -> Surface:
        """``points`` ``(n_levels, m, dim)`` [m] against the boundary of ``mesh`` (or the
        given ``facets``, ``(n_facets, ≥ dim)`` int, outward)."""
        dim = int(mesh.dim)
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 3 or p.shape[2] != dim or p.shape[1] == 0:
            raise ValueError(f"surface points must be (n_levels, m, {dim}), got {p.shape}")
        f = boundary_facets(mesh) if facets is None else np.asarray(facets)
        return cls(jnp.asarray(f[:, :dim]), jnp.asarray(p, mesh.points.dtype), sigma)

    def predict(self, state: SolvedState, level_data=None):
        """Signed distance ``(m,)`` of the level's points to the nearest deformed facet."""
        x = state.x
        d = jax.vmap(lambda p: point_to_facet_distance(p, x[self.facets]))(level_data)
        i = jnp.argmin(jnp.abs(d), axis=1)
        return jnp.take_along_axis(d, i[:, None], axis=1)[:, 0]

    def target(self, level_data):
        return jnp.zeros(level_data.shape[:-1], level_data.dtype)


_register(Surface, ["facets", "data", "sigma"])


# ----------------------------------------------------------------------------------------
# geometry
# ----------------------------------------------------------------------------------------


def _segment_distance(p, a, b):
    """Signed distance of p to segment ab (2D), positive on the right-hand-rule normal's
    side ``(t_y, −t_x)``; linear in p where the foot lies inside the segment."""
    t = b - a
    length2 = t @ t
    s = jnp.clip(((p - a) @ t) / length2, 0.0, 1.0)
    n = jnp.stack([t[1], -t[0]]) / jnp.sqrt(length2)
    h = (p - a) @ n
    q = a + s * t
    e = p - q
    far = jnp.sqrt(jnp.maximum(e @ e, 1e-300))
    inside = (s > 0.0) & (s < 1.0)
    return jnp.where(inside, h, jnp.where(h >= 0.0, far, -far))


def _unsigned_segment(p, a, b):
    t = b - a
    s = jnp.clip(((p - a) @ t) / (t @ t), 0.0, 1.0)
    e = p - (a + s * t)
    return jnp.sqrt(jnp.maximum(e @ e, 1e-300))


def _triangle_distance(p, a, b, c):
    """Signed distance of p to triangle abc (3D), positive on the side of the normal
    ``(b − a) × (c − a)``; the plane distance where the foot lies inside the triangle,
    else the nearest edge's distance with the plane distance's sign."""
    n = jnp.cross(b - a, c - a)
    n = n / jnp.sqrt(n @ n)
    h = (p - a) @ n
    q = p - h * n  # foot in the plane
    # inside test: q on the inner side of every edge
    ins = [jnp.cross(v - u, q - u) @ n for u, v in ((a, b), (b, c), (c, a))]
    inside = (ins[0] >= 0.0) & (ins[1] >= 0.0) & (ins[2] >= 0.0)
    edge = jnp.minimum(
        jnp.minimum(_unsigned_segment(p, a, b), _unsigned_segment(p, b, c)),
        _unsigned_segment(p, c, a),
    )
    return jnp.where(inside, h, jnp.where(h >= 0.0, edge, -edge))


def point_to_facet_distance(p, corners):
    """Signed distance ``(n_facets,)`` of one point ``p`` ``(dim,)`` to each facet
    ``corners`` ``(n_facets, dim, dim)`` (segments in 2D, triangles in 3D) [m]."""
    if p.shape[-1] == 2:
        return jax.vmap(lambda c: _segment_distance(p, c[0], c[1]))(corners)
    return jax.vmap(lambda c: _triangle_distance(p, c[0], c[1], c[2]))(corners)


def _p2_shape(L: np.ndarray, dim: int) -> np.ndarray:
    edges = TRI_EDGES if dim == 2 else TET_EDGES
    corners = L * (2.0 * L - 1.0)
    mids = np.stack([4.0 * L[:, a] * L[:, b] for a, b in edges], axis=1)
    return np.concatenate([corners, mids], axis=1)


def locate_points(mesh, points, tol: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """The cell containing each rest point and the shape-function values there (host).

    Straight-sided simplices: the barycentric coordinates in the cell's corners give the
    P1 values, and the P2 values ``L_i(2L_i − 1)``, ``4 L_i L_j`` (Zienkiewicz & Taylor
    2000, *The Finite Element Method*, vol. 1, §8.8).

    Args:
        mesh: a P1 or P2 simplex :class:`~jaxelastic.mesh.Mesh`.
        points: ``(n, dim)`` rest coordinates [m].
        tol: a point counts as inside when every barycentric coordinate ≥ −tol.
    Returns:
        ``(cell (n,) int, N (n, nodes_per_cell))``.
    Raises:
        ValueError: a point outside the body (its index and coordinates named), or a
            composite element.
    """
    el = mesh.element_type
    if el.is_composite:
        raise ValueError(f"points cannot be located in composite {el.name!r} cells")
    dim = int(mesh.dim)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, dim)
    X = np.asarray(mesh.points, dtype=np.float64)
    corners = X[np.asarray(mesh.cells)[:, : dim + 1]]  # (c, d+1, d)
    Tinv = np.linalg.inv(np.transpose(corners[:, 1:] - corners[:, :1], (0, 2, 1)))
    cell = np.full(pts.shape[0], -1)
    L = np.zeros((pts.shape[0], dim + 1))
    chunk = max(1, 2_000_000 // max(len(corners), 1))
    for s in range(0, pts.shape[0], chunk):
        p = pts[s : s + chunk]
        xi = np.einsum("cij,pcj->pci", Tinv, p[:, None, :] - corners[None, :, 0])  # (p, c, d)
        lam = np.concatenate([1.0 - xi.sum(-1, keepdims=True), xi], axis=-1)
        worst = lam.min(axis=-1)  # (p, c)
        best = worst.argmax(axis=1)
        ok = worst[np.arange(p.shape[0]), best] >= -tol
        cell[s : s + chunk] = np.where(ok, best, -1)
        L[s : s + chunk] = lam[np.arange(p.shape[0]), best]
    if np.any(cell < 0):
        i = int(np.flatnonzero(cell < 0)[0])
        raise ValueError(
            f"point {i} at {pts[i].tolist()} lies outside the body "
            f"({int(np.sum(cell < 0))} of {pts.shape[0]} points are outside)"
        )
    N = L if el.order == 1 else _p2_shape(L, dim)
    return cell, N
