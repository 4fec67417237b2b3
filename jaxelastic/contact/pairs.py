"""Self-contact: the barrier over boundary primitive pairs from a host broad phase.

:class:`SelfContact` is a frozen pytree held by :class:`~jaxelastic.contact.Contact`
(``self_contact=None``: nothing of it is traced). It holds the body's boundary surface
and a fixed-capacity buffer of candidate pairs (:mod:`~jaxelastic.contact.broadphase`,
computed on the host at positions ``x_ref``): 3D point–triangle and edge–edge, 2D
point–edge. The energy (IPC: Li et al. 2020, "Incremental Potential Contact", ACM TOG
39(4), eqs. 6 and 23, with unsquared distances as the obstacle term)

``Π_s(x) = κ Σ_{pt} b(d_pt(x); d̂) + κ Σ_{ee} m_ee(x) b(d_ee(x); d̂)``

sums over the buffer. The buffer is *complete* — it holds every pair closer than d̂ —
while no surface node has moved more than ``margin`` from ``x_ref``: the broad phase
takes every pair whose boxes come within ``d̂ + 2·margin``, and a pair's distance changes
by at most twice its nodes' largest motion. The line search keeps every trial inside
that motion bound and before every candidate pair's additive-CCD time of impact
(:func:`~jaxelastic.contact.ccd.additive_toi`), so every iterate is intersection-free;
:meth:`SelfContact.refreshed` (host) re-runs the broad phase when the iterate has used
part of the bound (``je.solve`` does it before a solve, between the Newton iterations of
its host loop, and when a jitted solve ran into the bound).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from ..mechanics.psd import project_psd
from .broadphase import (
    HEADROOM,
    Surface,
    candidate_pairs,
    capacity_for,
    pad_pairs,
    surface_of,
)
from .ccd import additive_toi, motion_toi
from .distance import (
    edge_edge_d2,
    edge_edge_mollifier,
    mollifier_eps,
    point_edge_d2_2d,
    point_triangle_d2,
)
from .log_barrier import barrier

__all__ = [
    "SelfContact",
    "make_self_contact",
    "MARGIN_DHAT",
    "MARGIN_EDGE",
    "REFRESH_FRACTION",
    "STEP_MARGIN_MAX",
    "RESERVE_MAX",
    "HESSIAN_FRACTION",
    "hessian_slots",
]

MARGIN_DHAT = 10.0
"""Default motion bound (``margin``) of a broad phase: 10 d̂, at most
:data:`MARGIN_EDGE` × the shortest rest boundary edge."""

MARGIN_EDGE = 0.25
"""Cap of the default motion bound, relative to the shortest boundary edge: a larger
bound takes in neighbours' neighbours (the candidate count grows like its square on a
surface, its cube in a fold), and across a body one element thick (the ``fold`` strip:
shortest edge = thickness) a bound above half the shortest edge takes in every pair of
opposite faces at rest (measured: 0.25 × mean edge = 0.01 m on the strip, 0.02 m thick,
gave 3.7× the pairs of 0.25 × shortest edge)."""

RESERVE_MAX = 4
"""A buffer that grows makes room for the candidates of the longest step's bound
(``STEP_MARGIN_MAX·base_margin``), at most this multiple of the pairs it must hold now:
on the ``fold`` strip (one element thick) those are 3.6× the default bound's and then the
whole fold runs on one buffer shape; at 48k tets they are ~20× and would cost more per
Newton iteration than they save."""

STEP_MARGIN_MAX = 4.0
"""A broad phase over a Newton step takes a motion bound of at most this multiple of the
default one (:meth:`~jaxelastic.contact.Contact.refreshed`), if its candidates fit the
buffer (else the default bound: the step is cut at it). A longer bound only saves Newton
steps; it never grows the buffer (each growth is a re-jit, and the bound's candidates
grow like its square: at 48k tets 4× the default made the buffers 100× the pairs)."""

REFRESH_FRACTION = 0.5
""":meth:`SelfContact.needs_refresh` once a surface node has moved this fraction of the
margin since the broad phase."""


HESSIAN_FRACTION = 8
"""Pair Hessians are taken over the closest ``1/HESSIAN_FRACTION`` of a buffer's slots
(:func:`hessian_slots`): only pairs within d̂ have one, a small part of the candidates
(which reach ``d̂ + 2·margin``, with headroom); :meth:`SelfContact.refreshed` grows the
buffer when more than half of those slots would be within d̂."""


def hessian_slots(capacity: int) -> int:
    """The number ``K`` of a ``capacity``-slot buffer's closest pairs that get a Hessian:
    ``capacity / HESSIAN_FRACTION``, at least ``min(capacity, 128)``."""
    return min(int(capacity), max(128, int(capacity) // HESSIAN_FRACTION))


@dataclasses.dataclass(frozen=True)
class SelfContact:
    """Candidate pairs of a body's own boundary (a pytree; ``dim`` static).

    Attributes:
        faces: ``(n_f, 3)`` int32 boundary triangles (3D; ``(0, 3)`` in 2D).
        edges: ``(n_e, 2)`` int32 boundary edges.
        nodes: ``(m,)`` int32 surface nodes.
        rest: ``(n_nodes, dim)`` rest positions [m] (the mollifier's ε_×).
        pt: ``(C₁, 4)`` point–triangle (2D: ``(C₁, 3)`` point–edge) node indices.
        pt_valid: ``(C₁,)`` bool, the filled slots.
        ee: ``(C₂, 4)`` edge–edge node indices (``(0, 4)`` in 2D).
        ee_valid: ``(C₂,)`` bool; ee_eps: ``(C₂,)`` mollifier thresholds ε_× [m⁴].
        x_ref: ``(m, dim)`` surface-node positions of the broad phase [m].
        margin: ``()`` motion bound [m] within which the buffer is complete.
        base_margin: ``()`` the default motion bound [m] (a refresh never takes less).
        dim: 2 or 3 (static).
    """

    faces: jax.Array
    edges: jax.Array
    nodes: jax.Array
    rest: jax.Array
    pt: jax.Array
    pt_valid: jax.Array
    ee: jax.Array
    ee_valid: jax.Array
    ee_eps: jax.Array
    x_ref: jax.Array
    margin: jax.Array
    base_margin: jax.Array
    dim: int = dataclasses.field(default=3, metadata=dict(static=True))

    def replace(self, **kw) -> SelfContact:
        return dataclasses.replace(self, **kw)

    @property
    def capacity(self) -> tuple[int, int]:
        """``(C₁, C₂)`` buffer sizes."""
        return int(self.pt.shape[0]), int(self.ee.shape[0])

    # -- geometry ----------------------------------------------------------------------
    def _pt_d2(self, xs):
        if self.dim == 2:
            return point_edge_d2_2d(xs[0], xs[1], xs[2])
        return point_triangle_d2(xs[0], xs[1], xs[2], xs[3])

    @staticmethod
    def _ee_d2(xs):
        return edge_edge_d2(xs[0], xs[1], xs[2], xs[3])

    def distances(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        """``((C₁,), (C₂,))`` unsigned pair distances [m] at ``x`` ``(n, dim)``; +inf in
        empty slots."""
        d1 = jax.vmap(self._pt_d2)(x[self.pt])
        d2 = jax.vmap(self._ee_d2)(x[self.ee]) if self.ee.shape[0] else jnp.zeros((0,), x.dtype)
        inf = jnp.asarray(jnp.inf, x.dtype)
        d1 = jnp.where(self.pt_valid, jnp.sqrt(jnp.maximum(d1, 0.0)), inf)
        d2 = jnp.where(self.ee_valid, jnp.sqrt(jnp.maximum(d2, 0.0)), inf)
        return d1, d2

    def min_distance(self, x: jax.Array) -> jax.Array:
        """Smallest candidate-pair distance [m] (+inf with no candidate). Exact below d̂
        while the buffer is complete; above d̂ it is the smallest over the candidates."""
        d1, d2 = self.distances(x)
        inf = jnp.asarray(jnp.inf, x.dtype)
        return jnp.minimum(jnp.min(d1, initial=inf), jnp.min(d2, initial=inf))

    # -- energy and derivatives --------------------------------------------------------
    def _pt_energy(self, xs, valid, dhat, kappa):
        d2 = self._pt_d2(xs)
        return _barrier_of_d2(d2, valid, dhat, kappa)

    def _ee_energy(self, xs, valid, eps, dhat, kappa):
        d2 = self._ee_d2(xs)
        m = edge_edge_mollifier(xs[0], xs[1], xs[2], xs[3], eps)
        return m * _barrier_of_d2(d2, valid, dhat, kappa)

    def _terms(self):
        """``(indices, energy(xs, *data, dhat, kappa), data)`` per pair kind."""
        out: list[tuple[Any, Any, tuple]] = [(self.pt, self._pt_energy, (self.pt_valid,))]
        if self.ee.shape[0]:
            out.append((self.ee, self._ee_energy, (self.ee_valid, self.ee_eps)))
        return out

    def energy(self, x: jax.Array, dhat, kappa) -> jax.Array:
        """Π_s(x) [J] for ``x`` ``(n, dim)``; +inf if a candidate pair touches."""
        e = jnp.zeros((), x.dtype)
        for idx, fn, data in self._terms():
            e = e + jnp.sum(jax.vmap(lambda xs, *a, fn=fn: fn(xs, *a, dhat, kappa))(x[idx], *data))
        return e

    def gradient(self, x: jax.Array, dhat, kappa) -> jax.Array:
        """∂Π_s/∂x ``(n, dim)`` [N]."""
        g = jnp.zeros_like(x)
        for idx, fn, data in self._terms():
            gp = jax.vmap(jax.grad(lambda xs, *a, fn=fn: fn(xs, *a, dhat, kappa)))(x[idx], *data)
            g = g.at[idx].add(gp)
        return g

    def pair_hessians(self, x: jax.Array, dhat, kappa, project: bool = True) -> list:
        """Per kind ``(indices (K, q), H (K, q, dim, q, dim))``: the pair Hessians,
        PSD-projected per pair (as IPC) if ``project``, of the ``K =``
        :func:`hessian_slots` ``(C)`` closest candidate pairs (every pair within d̂ while
        there are at most K: :meth:`refreshed` keeps it so; beyond d̂ the Hessian is 0).
        Only those are differentiated twice and projected (measured on the ``fold``
        strip, 4096 + 8192 slots: 285 ms for every slot, the bulk of a Newton iteration).
        """
        out = []
        d = x.shape[1]
        for idx, fn, data in self._terms():
            C = idx.shape[0]
            K = hessian_slots(C)
            if K < C:  # the K closest: a top-k of the distances, then a gather
                d2fn = self._ee_d2 if idx is self.ee else self._pt_d2
                d2 = jnp.where(data[0], jax.vmap(d2fn)(x[idx]), jnp.inf)
                sel = lax.top_k(-d2, K)[1]
                idx, data = idx[sel], tuple(a[sel] for a in data)
            H = jax.vmap(jax.hessian(lambda xs, *a, fn=fn: fn(xs, *a, dhat, kappa)))(x[idx], *data)
            C, q = idx.shape
            H = H.reshape(C, q * d, q * d)
            if project:
                H = project_psd(H)
            out.append((idx, H.reshape(C, q, d, q, d)))
        return out

    def hvp(self, x, v, dhat, kappa, project: bool = True) -> jax.Array:
        """``(∂²Π_s/∂x²) v`` ``(n, dim)`` (projected pair Hessians unless not ``project``)."""
        return _apply(self.pair_hessians(x, dhat, kappa, project), v, offdiag=False)

    def coupling(self, x, dhat, kappa, project: bool = True, hessians=None):
        """``v ↦`` the part of ``(∂²Π_s/∂x²) v`` that couples *different* nodes (the
        pair Hessians without their node-diagonal blocks, which
        :meth:`node_blocks` gives), with the pair Hessians computed once, here (or
        ``hessians``: :meth:`pair_hessians` at ``x``, computed before)."""
        hs = self.pair_hessians(x, dhat, kappa, project) if hessians is None else hessians
        return lambda v: _apply(hs, v, offdiag=True)

    def node_blocks(self, x, dhat, kappa, project: bool = True, hessians=None) -> jax.Array:
        """``(n, dim, dim)`` node-diagonal blocks of the pair Hessians, summed per node
        (``hessians``: :meth:`pair_hessians` at ``x``, if computed before)."""
        d = x.shape[1]
        B = jnp.zeros((x.shape[0], d, d), x.dtype)
        hs = self.pair_hessians(x, dhat, kappa, project) if hessians is None else hessians
        for idx, H in hs:
            q = idx.shape[1]
            diag = H[:, jnp.arange(q), :, jnp.arange(q), :]  # (q, C, d, d)
            B = B.at[idx.T].add(diag)
        return B

    # -- line search -------------------------------------------------------------------
    def ccd_step(self, x: jax.Array, step: jax.Array) -> jax.Array:
        """The largest safe step τ ∈ [0, 1] along ``step`` ``(n, dim)``: inside the motion
        bound and before every candidate pair's additive-CCD time of impact."""
        u = x[self.nodes] - self.x_ref
        tau = jnp.minimum(1.0, motion_toi(u, step[self.nodes], self.margin))
        split = 1
        for idx, valid in ((self.pt, self.pt_valid), (self.ee, self.ee_valid)):
            if not idx.shape[0]:
                continue
            d2 = self._pt_d2 if idx is self.pt else self._ee_d2
            toi = jax.vmap(lambda xs, ps, d2=d2, s=split, t=tau: additive_toi(d2, xs, ps, s, t))(
                x[idx], step[idx]
            )
            tau = jnp.minimum(tau, jnp.min(jnp.where(valid, toi, 1.0), initial=1.0))
            split = 2
        return tau

    # -- host side ---------------------------------------------------------------------
    def needs_refresh(self, x) -> bool:
        """(host) Whether a surface node of ``x`` has moved ``REFRESH_FRACTION·margin``
        since the broad phase."""
        u = np.asarray(x)[np.asarray(self.nodes)] - np.asarray(self.x_ref)
        return bool(
            np.max(np.sqrt(np.sum(u * u, axis=1)), initial=0.0)
            >= REFRESH_FRACTION * float(self.margin)
        )

    def refreshed(self, x, dhat, margin=None, fallback=None) -> SelfContact:
        """(host, concrete ``x`` ``(n, dim)``) The broad phase re-run at ``x`` with motion
        bound ``margin`` [m] (default: the current one): candidate pairs within
        ``d̂ + 2·margin``, the buffer kept if it fits. Else it grows
        (:func:`~jaxelastic.contact.broadphase.capacity_for`: one power-of-2 level for both
        kinds, 2× headroom, at most every possible pair; room for the candidates of the
        longest step's bound, up to :data:`RESERVE_MAX` × the current ones): every growth
        is a new buffer shape, which re-jits whatever takes it. With ``fallback`` [m] (a
        smaller bound), a ``margin`` whose candidates do not fit takes ``fallback`` instead
        (which may grow)."""
        margin = float(self.margin) if margin is None else float(margin)
        xh = np.asarray(x, dtype=np.float64)
        surf = Surface(
            self.dim,
            np.asarray(self.faces),
            np.asarray(self.edges),
            np.asarray(self.nodes),
        )
        dhat = float(dhat)
        pt, ee = candidate_pairs(xh, surf, dhat + 2.0 * margin * (1 + 1e-6))
        cap = self.capacity
        if (len(pt) > cap[0] or len(ee) > cap[1]) and fallback is not None:
            margin = float(fallback)
            pt, ee = candidate_pairs(xh, surf, dhat + 2.0 * margin * (1 + 1e-6))
        if len(pt) > cap[0] or len(ee) > cap[1]:
            counts = (len(pt), len(ee))
            reserve = STEP_MARGIN_MAX * float(self.base_margin)
            if reserve > margin:  # room for a long step's candidates, within reason
                more = map(len, candidate_pairs(xh, surf, dhat + 2.0 * reserve))
                counts = tuple(
                    max(c, min(m, RESERVE_MAX * c)) for c, m in zip(counts, more, strict=True)
                )
            cap = _grown(counts, cap, surf)
        out = self._padded(xh, pt, ee, cap, margin)
        # the pairs within d̂ now: each kind's Hessian slots keep room for twice as many
        near = np.asarray(_near_counts(out, jnp.asarray(x, self.rest.dtype), dhat))
        if np.any(HEADROOM * near > np.array([hessian_slots(c) for c in cap])):
            counts = tuple(
                max(len(a), HESSIAN_FRACTION * int(n)) for a, n in zip((pt, ee), near, strict=True)
            )
            new = _grown(counts, cap, surf)
            if new != cap:
                out = self._padded(xh, pt, ee, new, margin)
        return out

    def _padded(self, xh, pt, ee, cap, margin) -> SelfContact:
        """(host) This contact with candidate pairs ``pt``, ``ee`` found at ``xh`` padded
        to capacities ``cap`` and motion bound ``margin``."""
        pt, pt_valid = pad_pairs(pt, cap[0])
        ee, ee_valid = pad_pairs(ee, cap[1]) if self.dim == 3 else (ee, np.zeros(0, bool))
        X = np.asarray(self.rest, dtype=np.float64)
        if len(ee):
            r = X[ee]
            eps = mollifier_eps(r[:, 0], r[:, 1], r[:, 2], r[:, 3])
            eps = np.where(ee_valid, np.asarray(eps), 1.0)
        else:
            eps = np.zeros(0)
        dt = self.rest.dtype
        return self.replace(
            pt=jnp.asarray(pt),
            pt_valid=jnp.asarray(pt_valid),
            ee=jnp.asarray(ee),
            ee_valid=jnp.asarray(ee_valid),
            ee_eps=jnp.asarray(eps, dt),
            x_ref=jnp.asarray(xh[np.asarray(self.nodes)], dt),
            margin=jnp.asarray(margin, dt),
        )

    @property
    def counts(self) -> tuple[int, int]:
        """(host) ``(point–primitive, edge–edge)`` filled slots."""
        return int(np.sum(np.asarray(self.pt_valid))), int(np.sum(np.asarray(self.ee_valid)))


jax.tree_util.register_dataclass(
    SelfContact,
    data_fields=[
        "faces",
        "edges",
        "nodes",
        "rest",
        "pt",
        "pt_valid",
        "ee",
        "ee_valid",
        "ee_eps",
        "x_ref",
        "margin",
        "base_margin",
    ],
    meta_fields=["dim"],
)


def _grown(counts, cap, surf: Surface) -> tuple[int, int]:
    """(host) :func:`~jaxelastic.contact.broadphase.capacity_for` ``counts`` from ``cap``,
    bounded by the numbers of all possible pairs of ``surf``."""
    nn, nf, ne = len(surf.nodes), len(surf.faces), len(surf.edges)
    if surf.dim == 2:
        return capacity_for((counts[0], 0), cap, (nn * ne, 0))
    return capacity_for(counts, cap, (nn * nf, ne * (ne - 1) // 2))


@jax.jit
def _near_counts(sc: SelfContact, x, dhat):
    """``(2,)`` numbers of point–primitive and edge–edge candidate pairs within ``dhat``."""
    d1, d2 = sc.distances(x)
    return jnp.stack([jnp.sum(d1 < dhat), jnp.sum(d2 < dhat)])


def _barrier_of_d2(d2, valid, dhat, kappa):
    """``κ b(√d²; d̂)`` with zero (and zero derivatives) outside reach or in empty slots."""
    active = valid & (d2 < dhat * dhat)
    ok = active & (d2 > 0)
    d = jnp.sqrt(jnp.where(ok, d2, dhat * dhat))
    e = kappa * barrier(d, dhat)
    return jnp.where(active, jnp.where(d2 > 0, e, jnp.inf), 0.0)


def _apply(hs, v, offdiag: bool):
    out = jnp.zeros_like(v)
    for idx, H in hs:
        q = idx.shape[1]
        if offdiag:
            H = H * (1.0 - jnp.eye(q, dtype=H.dtype))[None, :, None, :, None]
        out = out.at[idx].add(jnp.einsum("cidje,cje->cid", H, v[idx]))
    return out


def make_self_contact(mesh, dhat, margin=None, x=None) -> SelfContact:
    """The :class:`SelfContact` of ``mesh``'s boundary with its broad phase run at ``x``
    (default: the rest shape) and motion bound ``margin`` [m] (default
    ``min(MARGIN_DHAT·d̂, MARGIN_EDGE·shortest boundary edge)``)."""
    surf = surface_of(mesh)
    X = mesh.points
    dt = X.dtype
    dim = int(mesh.dim)
    q = 3 if dim == 2 else 4
    i32 = jnp.int32
    sc = SelfContact(
        faces=jnp.asarray(surf.faces, i32),
        edges=jnp.asarray(surf.edges, i32),
        nodes=jnp.asarray(surf.nodes, i32),
        rest=X,
        pt=jnp.zeros((0, q), i32),
        pt_valid=jnp.zeros((0,), bool),
        ee=jnp.zeros((0, 4), i32),
        ee_valid=jnp.zeros((0,), bool),
        ee_eps=jnp.zeros((0,), dt),
        x_ref=X[surf.nodes],
        margin=jnp.asarray(0.0, dt),
        base_margin=jnp.asarray(0.0, dt),
        dim=dim,
    )
    if margin is None:
        Xh = np.asarray(X, dtype=np.float64)
        e = Xh[surf.edges[:, 1]] - Xh[surf.edges[:, 0]]
        h = float(np.min(np.sqrt(np.sum(e * e, axis=1)))) if len(e) else float(dhat)
        margin = min(MARGIN_DHAT * float(dhat), MARGIN_EDGE * h)
    sc = sc.replace(base_margin=jnp.asarray(float(margin), dt))
    return sc.refreshed(X if x is None else x, dhat, margin)
