"""Pressure on the boundary of a cavity as a potential term: ``Π_p(x) = −Σ_s p_s V_s(x)``.

A pressure ``p`` [Pa] acting on the *deformed* boundary facets ``S`` of a body (a follower
load, ``t = −p n da`` with ``n`` the body's outward normal: positive pushes into the body)
is conservative when ``S`` bounds a cavity that is closed, or whose opening is closed by a
lid that does not move or that slides in a plane (a symmetry plane). Its potential is then
``−p V(x)`` with the cavity volume

``V(x) = −(1/d) ∫_S (x − c)·n da``   (d = 2: an area per unit thickness)

(the divergence theorem over the cavity, whose outward normal is −n on S). The lid is the
cone of segments from the surface's rim to the closing point ``c``; its contribution
``(1/d)∫_lid (x − c)·n da`` is zero for any rim position because ``x − c`` lies in the
cone's tangent plane, so ``V`` is exactly the volume enclosed by ``S`` and that cone. The
cone is fixed when the rim is fixed, and stays in a plane when the rim slides on a plane
through ``c``: those are the conservative cases (:func:`check_closed` checks them against the
Dirichlet data), and then ``−∂Π_p/∂x = p ∂V/∂x`` is the follower force ``−p ∫ n N_a da`` on
every free degree of freedom (Bonet & Wood, *Nonlinear Continuum Mechanics for Finite
Element Analysis*, 2nd ed. 2008, §8.4.3 "enclosed volume" and §8.4.1 the pressure
stiffness; Simo, Taylor & Wriggers 1991 for the symmetry of the closed case). An external
pressure on a closed outer surface is the same term (its "cavity" volume is minus the
body's volume).

:class:`Pressure` is a frozen pytree held by
:class:`~jaxelastic.mechanics.potential.Potential` (``pressure=None`` by default: nothing of
it is traced). ``V`` is a sum over facets, each a polynomial in its nodes' positions
integrated exactly by the facet rule (:func:`~jaxelastic.mesh.elements.facet_rule`: P1,
P2 and composite facets), so its Hessian is one ``(k·d, k·d)`` block per facet;
:meth:`Pressure.add_hessian_blocks` adds each to the element Hessian of the cell that owns
the facet, so every linear solver and preconditioner sees it. The pressure stiffness
``−p ∂²V/∂x²`` is symmetric but indefinite (PSD-projected per touched cell when Newton
asks for projected Hessians).

Build one with :func:`pressure_term` (or :func:`jaxelastic.loads.pressure_load` with the
facet selectors of the tractions).

**Open surfaces with a moving rim** (``follower=True``): the load has no potential. The
term's gradient is then the exact follower residual ``p ∫ n N_a da`` facet by facet
(:func:`facet_forces`), its Hessian blocks the *symmetric part* of the true facet tangent
(so every symmetric solver and preconditioner still applies to them) and
:meth:`Pressure.skew_vp` the skew part ``(J − Jᵀ)/2`` as a matrix-free product: Newton
(``Newton(tangent="auto")``) solves with their sum, the true tangent, by GMRES
preconditioned by the symmetric part (quadratic convergence); ``tangent="symmetric"``
leaves the skew part out (a quasi-Newton, linear convergence). Its energy ``−p V`` of the
cone-closed surface serves only to reject inverted trial steps: the Newton line search
accepts a step on the decrease of the residual (:func:`is_conservative`). Derivatives
through such a solve, reverse and forward mode, solve with the true Jacobian or its
transpose (:mod:`jaxelastic.solvers.adjoint`).

**Volume control** (the cavity volume prescribed, the pressure an unknown): with ``target``
``T`` and ``kappa`` ``κ`` set, the term is the augmented Lagrangian

``Π_p(x) = −Σ_s λ_s V_s(x) + Σ_s κ_s/2 (V_s(x) − T_s)²``

(Hestenes 1969, Powell 1969; Bertsekas, *Constrained Optimization and Lagrange Multiplier
Methods*, 1982, ch. 2) whose multiplier estimate ``λ`` is the ``pressure`` field: its
minimiser is an equilibrium under the pressure ``p = λ − κ(V − T)``, and the update
``λ ← p`` (:func:`jaxelastic.solvers.solve_volume_controlled`) drives ``V → T``. Its
Hessian adds ``κ ∇V ∇Vᵀ``, a rank-one coupling of all the surface's nodes, which Newton
applies as an operator (:meth:`Pressure.coupling`) next to the element Hessians (where
``−p ∇²V`` goes): it makes the inner problem convex past a pressure limit point, where the
pressure-controlled tangent has a negative eigenvalue.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ..mesh import Mesh
from ..mesh.elements import facet_rule, get_element
from .psd import project_psd

__all__ = [
    "Pressure",
    "facet_forces",
    "is_conservative",
    "pressure_term",
    "rim_edges",
    "check_closed",
    "facet_volume",
]


def facet_volume(element: str, xf: jax.Array, c: jax.Array) -> jax.Array:
    """One facet's share ``−(1/d) ∫_f (x − c)·n da`` of a cavity volume [length^d].

    Args:
        element: the mesh's element name (its facet interpolation and rule).
        xf: ``(k, d)`` positions of the facet's nodes (the body's outward orientation of
            :func:`~jaxelastic.mesh.boundary_facets`).
        c: ``(d,)`` the closing point.
    """
    N, dN, w = facet_rule(get_element(element))  # (r, k), (r, k, d-1), (r,)
    d = xf.shape[1]
    xq = jnp.asarray(N, xf.dtype) @ xf - c[None, :]  # (r, d)
    T = jnp.einsum("ka,rkb->rab", xf, jnp.asarray(dN, xf.dtype))  # (r, d, d-1)
    if d == 2:
        nvec = jnp.stack([T[:, 1, 0], -T[:, 0, 0]], axis=-1)  # (t_y, -t_x)
    else:
        nvec = jnp.cross(T[..., 0], T[..., 1])
    return -jnp.sum(jnp.asarray(w, xf.dtype) * jnp.sum(xq * nvec, axis=-1)) / d


def facet_forces(element: str, xf: jax.Array, p: jax.Array) -> jax.Array:
    """The follower force ``−p ∫_f n N_a da`` on one facet's nodes, ``(k, d)`` [force]
    (``n``: the body's outward normal of the deformed facet; exact for the facet rule).

    Args:
        element: the mesh's element name; xf: ``(k, d)`` node positions; p: the pressure.
    """
    N, dN, w = facet_rule(get_element(element))
    d = xf.shape[1]
    T = jnp.einsum("ka,rkb->rab", xf, jnp.asarray(dN, xf.dtype))  # (r, d, d-1)
    if d == 2:
        nvec = jnp.stack([T[:, 1, 0], -T[:, 0, 0]], axis=-1)
    else:
        nvec = jnp.cross(T[..., 0], T[..., 1])
    wN = jnp.asarray(w, xf.dtype)[:, None] * jnp.asarray(N, xf.dtype)  # (r, k)
    return -p * jnp.einsum("rk,rd->kd", wN, nvec)


@dataclasses.dataclass(frozen=True)
class Pressure:
    """Pressures on the boundary surfaces of cavities (see the module docstring).

    Attributes:
        facets: ``(m, k)`` int32 node indices of the loaded facets, outward oriented.
        surface: ``(m,)`` int32 which surface (cavity) each facet bounds, ``0 … n_s − 1``.
        cells: ``(m,)`` int32 the cell owning each facet.
        slots: ``(m, k)`` int32 each facet node's local index in its cell.
        touched: ``(t,)`` int32 the distinct owning cells (for the PSD projection).
        origin: ``(n_s, d)`` the closing point ``c`` of each surface [length].
        pressure: ``(n_s,)`` the pressure on each surface [Pa]; positive pushes into the
            body (inflates a cavity).
        target: ``(n_s,)`` prescribed volumes ``T`` [length^d] (volume control), or None.
        kappa: ``(n_s,)`` augmented-Lagrangian penalties ``κ`` [Pa/length^d] (0: that
            surface is pressure controlled), or None (no volume control).
        element: static, the mesh's element name.
        follower: static; True for an open surface whose rim moves (not conservative:
            the exact follower residual, a non-symmetric tangent).
    """

    facets: jax.Array
    surface: jax.Array
    cells: jax.Array
    slots: jax.Array
    touched: jax.Array
    origin: jax.Array
    pressure: jax.Array
    target: jax.Array | None = None
    kappa: jax.Array | None = None
    element: str = dataclasses.field(metadata=dict(static=True), default="tri3")
    follower: bool = dataclasses.field(metadata=dict(static=True), default=False)

    def replace(self, **kw) -> Pressure:
        return dataclasses.replace(self, **kw)

    @property
    def n_surfaces(self) -> int:
        return int(self.pressure.shape[0])

    def scaled(self, s) -> Pressure:
        """The same surfaces with every pressure times ``s`` (a load factor)."""
        return self.replace(pressure=s * self.pressure)

    def facet_volumes(self, x: jax.Array) -> jax.Array:
        """``(m,)`` each facet's share of its cavity's volume at ``x`` ``(n_nodes, d)``."""
        c = self.origin.astype(x.dtype)[self.surface]  # (m, d)
        return jax.vmap(lambda xf, ci: facet_volume(self.element, xf, ci))(x[self.facets], c)

    def volumes(self, x: jax.Array) -> jax.Array:
        """``(n_s,)`` the cavity volumes at ``x`` [length^d] (areas in 2D)."""
        return jax.ops.segment_sum(
            self.facet_volumes(x), self.surface, num_segments=self.n_surfaces
        )

    def energy(self, x: jax.Array) -> jax.Array:
        """``Π_p(x) = −Σ_s p_s V_s(x)`` (+ ``Σ κ_s/2 (V_s − T_s)²`` under volume control)
        [energy]."""
        V = self.volumes(x)
        e = -jnp.sum(self.pressure.astype(x.dtype) * V)
        if self.kappa is not None:
            dv = V - self._target(x.dtype)
            e = e + 0.5 * jnp.sum(self.kappa.astype(x.dtype) * dv * dv)
        return e

    def _target(self, dtype) -> jax.Array:
        if self.target is None:
            raise TypeError("Pressure: kappa is set but target is None (volume control needs both)")
        return self.target.astype(dtype)

    def effective_pressures(self, x: jax.Array) -> jax.Array:
        """``(n_s,)`` the pressures the term exerts at ``x`` [Pa]: ``p`` (or, under volume
        control, ``λ − κ(V − T)``)."""
        p = self.pressure.astype(x.dtype)
        if self.kappa is None:
            return p
        return p - self.kappa.astype(x.dtype) * (self.volumes(x) - self._target(x.dtype))

    def volume_gradients(self, x: jax.Array) -> jax.Array:
        """``(n_s, n_nodes, d)`` the gradients ``∂V_s/∂x``."""
        _, vjp = jax.vjp(self.volumes, x)
        return jax.vmap(lambda e: vjp(e)[0])(jnp.eye(self.n_surfaces, dtype=x.dtype))

    def coupling(self, x: jax.Array):
        """Volume control's rank-one Hessian ``Σ_s κ_s ∇V_s ∇V_sᵀ`` as ``v ↦ H_c v``
        (``(n_nodes, d) -> (n_nodes, d)``), or None without volume control."""
        if self.kappa is None:
            return None
        G = self.volume_gradients(x)  # (n_s, n, d)
        k = self.kappa.astype(x.dtype)

        def apply(v):
            return jnp.einsum("s,snd->nd", k * jnp.einsum("snd,nd->s", G, v), G)

        return apply

    def gradient(self, x: jax.Array) -> jax.Array:
        """``∂Π_p/∂x`` ``(n_nodes, d)``: minus the follower forces ``−p ∫ n N_a da`` (for a
        ``follower`` term: minus the exact follower forces, which are no gradient)."""
        if not self.follower:
            return jax.grad(self.energy)(x)
        p = self.effective_pressures(x)[self.surface]
        f = jax.vmap(lambda xf, q: facet_forces(self.element, xf, q))(x[self.facets], p)
        return -jnp.zeros_like(x).at[self.facets].add(f)

    def hvp(self, x: jax.Array, v: jax.Array) -> jax.Array:
        """``(∂²Π_p/∂x²)·v`` ``(n_nodes, d)`` (the pressure stiffness; for a ``follower``
        term the symmetric part of the tangent, ``(J + Jᵀ)v/2``)."""
        if not self.follower:
            return jax.jvp(self.gradient, (x,), (v,))[1]
        Jv = jax.jvp(self.gradient, (x,), (v,))[1]
        JTv = jax.vjp(self.gradient, x)[1](v)[0]
        return 0.5 * (Jv + JTv)

    def skew_vp(self, x: jax.Array, v: jax.Array) -> jax.Array:
        """``½(J − Jᵀ)·v`` ``(n_nodes, d)``, the skew part of the tangent ``J = ∂g/∂x`` of
        :meth:`gradient` (zero for a conservative term): the symmetric part
        (:meth:`hvp`, :meth:`facet_hessians`) plus this is the true tangent ``J v`` of a
        ``follower`` term."""
        if not self.follower:
            return jnp.zeros_like(v)
        Jv = jax.jvp(self.gradient, (x,), (v,))[1]
        JTv = jax.vjp(self.gradient, x)[1](v)[0]
        return 0.5 * (Jv - JTv)

    def facet_hessians(self, x: jax.Array) -> jax.Array:
        """``(m, k·d, k·d)`` the Hessian of ``Π_p`` per facet (node-major), without volume
        control's rank-one part (:meth:`coupling`)."""
        c = self.origin.astype(x.dtype)[self.surface]
        xf = x[self.facets]  # (m, k, d)
        m, k, d = xf.shape

        def one(xf, ci):
            return jax.hessian(lambda y: facet_volume(self.element, y.reshape(k, d), ci))(
                xf.reshape(-1)
            )

        p = self.effective_pressures(x)[self.surface]
        if self.follower:  # the symmetric part of −∂f/∂x per facet

            def tangent(xf, q):
                J = jax.jacfwd(lambda y: facet_forces(self.element, y.reshape(k, d), q))(
                    xf.reshape(-1)
                ).reshape(k * d, k * d)
                return -0.5 * (J + J.T)

            return jax.vmap(tangent)(xf, p)
        H = jax.vmap(one)(xf, c)  # (m, k·d, k·d)
        return -p[:, None, None] * H

    def add_hessian_blocks(self, Ke: jax.Array, x: jax.Array, project: bool = False) -> jax.Array:
        """``Ke`` ``(n_cells, kc·d, kc·d)`` with each facet's Hessian added to its owning
        cell's element Hessian (``project``: the touched cells PSD-projected after)."""
        c, kd = Ke.shape[0], Ke.shape[1]
        d = x.shape[1]
        kc = kd // d
        m, k = self.facets.shape
        H = self.facet_hessians(x).astype(Ke.dtype).reshape(m, k, d, k, d)
        H = H.transpose(0, 1, 3, 2, 4)  # (m, a, b, d, d)
        K4 = Ke.reshape(c, kc, d, kc, d)
        ci = self.cells[:, None, None]
        K4 = K4.at[ci, self.slots[:, :, None], :, self.slots[:, None, :], :].add(H)
        Ke = K4.reshape(Ke.shape)
        if project:
            Ke = Ke.at[self.touched].set(project_psd(Ke[self.touched]))
        return Ke


jax.tree_util.register_dataclass(
    Pressure,
    data_fields=[
        "facets",
        "surface",
        "cells",
        "slots",
        "touched",
        "origin",
        "pressure",
        "target",
        "kappa",
    ],
    meta_fields=["element", "follower"],
)


# -- construction (host) ---------------------------------------------------------------------


def is_conservative(term: Pressure | None) -> bool:
    """Whether a pressure term (or None) has a potential (static): not a ``follower``."""
    return term is None or not term.follower


def _corner_keys(corners: np.ndarray, n: int) -> np.ndarray:
    """One int64 key per row of sorted corner indices ``(..., d)``."""
    key = corners[..., 0].astype(np.int64)
    for j in range(1, corners.shape[-1]):
        key = key * n + corners[..., j]
    return key


def _facet_owners(mesh: Mesh, facets: np.ndarray, what: str):
    """``(oriented facets, owning cells, local slots)`` of boundary ``facets``, or a
    ValueError naming the first facet that is not a facet of the mesh or is interior."""
    el = mesh.element_type
    cells = np.asarray(mesh.cells, dtype=np.int64)
    local = np.asarray(el.facet_nodes)  # (f, k)
    d, n = mesh.dim, mesh.n_nodes
    all_keys = _corner_keys(np.sort(cells[:, local][:, :, :d], axis=2), n).ravel()  # (c·f,)
    order = np.argsort(all_keys, kind="stable")
    sorted_keys = all_keys[order]
    q = _corner_keys(np.sort(facets[:, :d], axis=1), n)  # (m,)
    lo = np.searchsorted(sorted_keys, q, side="left")
    hi = np.searchsorted(sorted_keys, q, side="right")
    for i in np.flatnonzero(hi - lo != 1)[:1]:
        f = facets[i].tolist()
        if hi[i] == lo[i]:
            raise ValueError(
                f"{what}: facet {i} (nodes {f}) is not a facet of any cell of the mesh"
            )
        owners = (order[lo[i] : hi[i]] // local.shape[0]).tolist()
        raise ValueError(
            f"{what}: facet {i} (nodes {f}) is an interior facet (shared by cells {owners}); "
            "a pressure acts on boundary facets only"
        )
    flat = order[lo]
    owner, j = flat // local.shape[0], flat % local.shape[0]
    out_f = cells[owner[:, None], local[j]]  # the cell's own, outward orientation
    slots = (cells[owner][:, None, :] == out_f[:, :, None]).argmax(axis=2)
    return out_f, owner, slots


def rim_edges(facets: np.ndarray, dim: int) -> np.ndarray:
    """The rim of a facet set: ``(r, q)`` node indices of the boundary of the surface.

    2D: the end nodes of the open polyline, ``(r, 1)``; 3D: the edges used by exactly one
    facet, ``(r, 2)`` corners, or ``(r, 3)`` with the mid-edge node for 6-node facets.
    Empty for a closed surface.
    """
    facets = np.asarray(facets, dtype=np.int64)
    if dim == 2:
        ends, counts = np.unique(facets[:, :2], return_counts=True)
        return ends[counts == 1][:, None]
    pairs = [(0, 1), (1, 2), (2, 0)]
    mids = [3, 4, 5]
    e = np.concatenate([facets[:, list(p)] for p in pairs])  # (3m, 2)
    key = np.sort(e, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    once = counts[inv.ravel()] == 1
    if facets.shape[1] == 6:
        mid = np.concatenate([facets[:, j] for j in mids])[:, None]
        return np.concatenate([e, mid], axis=1)[once]
    return e[once]


def _default_origin(X: np.ndarray, facets: np.ndarray, dim: int) -> np.ndarray:
    """The rest centroid of the rim's nodes, or of the surface's corners if it is closed."""
    rim = rim_edges(facets, dim)
    nodes = np.unique(rim) if rim.size else np.unique(facets[:, :dim])
    return X[nodes].mean(axis=0)


def _pressures(pressure, n_s: int, what: str) -> np.ndarray:
    """``(n_s,)`` finite pressures from a scalar or one per surface, or a ValueError."""
    p = np.asarray(pressure, dtype=np.float64)
    p = np.broadcast_to(p, (n_s,)) if p.ndim == 0 else p
    if p.shape != (n_s,):
        raise ValueError(f"{what}: pressure must be a scalar or have shape ({n_s},), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{what}: pressure must be finite, got {p.tolist()}")
    return p


def _origins(origin, n_s: int, d: int, what: str) -> np.ndarray:
    """``(n_s, d)`` finite closing points from one or one per surface, or a ValueError."""
    o = np.asarray(origin, dtype=np.float64)
    o = np.broadcast_to(o, (n_s, d)) if o.shape == (d,) else o
    if o.shape != (n_s, d) or not np.all(np.isfinite(o)):
        raise ValueError(
            f"{what}: origin must be finite with shape ({d},) or ({n_s}, {d}), got "
            f"{np.asarray(origin).tolist()!r}"
        )
    return o


def pressure_term(
    mesh: Mesh, facets, pressure, origin=None, *, what: str = "pressure", follower: bool = False
) -> Pressure:
    """A :class:`Pressure` term from facet sets of a mesh (host; once per scene).

    Args:
        mesh: the rest mesh.
        facets: one ``(m, k)`` array of boundary facets (node indices, either orientation,
            e.g. from :func:`~jaxelastic.loads.facets_where`) or a list of them, one per
            surface (cavity).
        pressure: ``()`` or ``(n_s,)`` the pressure on each surface [Pa] (positive pushes
            into the body).
        origin: ``(d,)`` or ``(n_s, d)`` closing points ``c`` [length], or None: the rest
            centroid of each surface's rim (of its corners if closed). A rim that slides
            on a symmetry plane needs ``c`` on that plane (:func:`check_closed`).
        what: how error messages name the term.
        follower: an open surface whose rim moves (no potential; see the module docstring).

    Raises:
        ValueError: an empty facet set, a facet that is not a boundary facet of the mesh
            (interior, or not a facet at all), a non-finite pressure or origin, or arrays
            of the wrong shape.
    """
    X = np.asarray(mesh.points, dtype=np.float64)
    d = mesh.dim
    k = len(mesh.element_type.facet_nodes[0])
    sets = [facets] if not isinstance(facets, (list, tuple)) else list(facets)
    if not sets:
        raise ValueError(f"{what}: no surfaces given")
    n_s = len(sets)
    p = _pressures(pressure, n_s, what)
    fs, owners, slots, surf, origins = [], [], [], [], []
    for s, f in enumerate(sets):
        name = what if n_s == 1 else f"{what} (surface {s})"
        f = np.asarray(f)
        if f.ndim != 2 or f.shape[1] != k or f.dtype.kind not in "iu":
            raise ValueError(
                f"{name}: facets must be an integer array of shape (m, {k}) ({k}-node facets of "
                f"{mesh.element}), got {f.shape} {f.dtype}"
            )
        if f.shape[0] == 0:
            raise ValueError(
                f"{name}: the facet set is empty (the selector matched no boundary facet)"
            )
        if f.min() < 0 or f.max() >= X.shape[0]:
            raise ValueError(f"{name}: facets reference node indices outside [0, {X.shape[0]})")
        of, ow, sl = _facet_owners(mesh, f.astype(np.int64), name)
        fs.append(of)
        owners.append(ow)
        slots.append(sl)
        surf.append(np.full(of.shape[0], s))
        origins.append(_default_origin(X, of, d))
    if origin is not None:
        origins = list(_origins(origin, n_s, d, what))
    dt = np.dtype(mesh.points.dtype)
    cells = np.concatenate(owners)
    i32 = jnp.int32
    return Pressure(
        facets=jnp.asarray(np.concatenate(fs), i32),
        surface=jnp.asarray(np.concatenate(surf), i32),
        cells=jnp.asarray(cells, i32),
        slots=jnp.asarray(np.concatenate(slots), i32),
        touched=jnp.asarray(np.unique(cells), i32),
        origin=jnp.asarray(np.stack(origins).astype(dt)),
        pressure=jnp.asarray(p.astype(dt)),
        element=mesh.element,
        follower=bool(follower),
    )


def check_closed(term: Pressure, points, mask, values=None, *, what: str = "pressure") -> None:
    """Check that every surface's rim is fixed or slides on a plane through its closing
    point, so the pressure is conservative (its potential ``−p V`` is exact).

    A rim edge (3D; a rim node in 2D) passes when all its nodes are fixed in every
    component, or when for some axis ``i`` all its nodes and the closing point lie on the
    plane ``X_i = c_i`` and component ``i`` of every node is prescribed to stay there.

    Args:
        term: the :class:`Pressure` (concrete).
        points: ``(n_nodes, d)`` rest positions; mask: ``(n_nodes, d)`` bool, the
            prescribed dofs; values: ``(n_nodes, d)`` the prescribed positions (default: rest).

    Raises:
        ValueError: a rim edge that moves freely, naming the surface, its nodes and what to
            do (the follower load on such a surface has a non-symmetric tangent: no
            potential).
    """
    if term.follower:  # declared non-conservative: nothing to check
        return
    X = np.asarray(points, dtype=np.float64)
    mask = np.asarray(mask, dtype=bool)
    vals = X if values is None else np.asarray(values, dtype=np.float64)
    d = X.shape[1]
    facets, surf = np.asarray(term.facets), np.asarray(term.surface)
    origin = np.asarray(term.origin, dtype=np.float64)
    tol = 1e-8 * max(float(np.ptp(X, axis=0).max()), 1.0)
    for s in range(origin.shape[0]):
        rim = rim_edges(facets[surf == s], d)
        if rim.size == 0:
            continue
        c = origin[s]
        fixed = mask[rim].all(axis=(1, 2))  # (r,)
        ok = fixed.copy()
        for i in range(d):
            on_plane = (np.abs(X[rim, i] - c[i]) <= tol).all(axis=1)
            stays = (mask[rim, i] & (np.abs(vals[rim, i] - c[i]) <= tol)).all(axis=1)
            ok |= on_plane & stays
        if not ok.all():
            bad = rim[~ok]
            name = what if origin.shape[0] == 1 else f"{what} (surface {s})"
            raise ValueError(
                f"{name}: {bad.shape[0]} of {rim.shape[0]} rim edge(s) of the loaded surface "
                f"are neither fixed nor sliding on a symmetry plane through the closing point "
                f"c = {c.tolist()} (e.g. nodes {bad[0].tolist()} at {X[bad[0]].tolist()}): the "
                "follower pressure is then not conservative (no potential, non-symmetric "
                "tangent). Fix the rim, constrain it to a symmetry plane through c (set the "
                "closing point with origin = [...]), load a closed surface, or declare the "
                "load a follower load (follower=True: exact residual, non-symmetric tangent)"
            )
