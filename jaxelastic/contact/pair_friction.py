"""IPC's lagged smoothed Coulomb friction between self-contact pairs.

Friction of a body's boundary against itself enters the potential as a dissipative
pseudo-energy (Li et al. 2020, "Incremental Potential Contact", ACM TOG 39(4), §5; the
ipc-toolkit's tangential collisions): for every self-contact pair ``k`` in reach at the
lag (distance ``d_k < d̂``),

``D_s(x) = Σ_k μ λ_k f₀(‖T_kᵀ (z_k(x) − z_k^lag)‖)``,  ``z_k(x) = Σ_i w_ki x_{n_ki}``,

with, frozen at the lagged positions ``x^lag`` (the start of the time or load step):

* ``w_k`` ``(q,)`` the closest-point weights of the pair's ``q`` nodes ``n_k``
  (``Σ_i w_ki = 0``), so that ``z_k`` is the vector between the two closest points and
  ``z_k − z_k^lag`` their relative displacement since the lag. Point–triangle:
  ``(1, −β₀, −β₁, −β₂)`` with the triangle's barycentrics of the closest point;
  edge–edge: ``(1 − s, s, −(1 − t), −t)`` with the two edge parameters; 2D point–edge:
  ``(1, −(1 − t), −t)``. The weights follow IPC's case split
  (:mod:`~jaxelastic.contact.distance`): a closest point at a corner or on a side gets
  that corner's or side's weights, so ``‖z_k^lag‖`` is the pair distance;
* ``T_k`` ``(dim, dim−1)`` an orthonormal basis ⊥ the pair normal ``z_k^lag/‖z_k^lag‖``
  (only ``T Tᵀ = I − n nᵀ`` enters ``‖Tᵀ u‖``, so any such basis gives the same energy);
* ``λ_k = κ |b'(d_k)|`` [N] the barrier's normal force (× the edge–edge mollifier
  ``m_ee(x^lag)`` of Li et al. 2020 eq. 23 for edge–edge pairs), 0 out of reach;

and ``f₀`` / ``ε`` the mollifier and slip tolerance of the obstacle friction
(:func:`~jaxelastic.contact.friction.f0`). The pairs are stored with their own node
indices (a copy of the candidate buffer's slots at the lag, fixed capacity, inert slots
``λ = 0``), so a broad phase re-run between the lag and the solve does not touch them.

Since ``z_k`` is linear in x, a pair's Hessian is ``w wᵀ ⊗ (T H_u Tᵀ)`` with ``H_u`` the
``(dim−1)²`` Hessian of ``μλ f₀(‖u‖)``, whose eigenvalues ``μλ f₁'(y)`` and
``μλ f₁(y)/y`` are ≥ 0: it is positive semidefinite (``project`` clamps ``H_u``'s
round-off). Its node-diagonal blocks ``w_i² T H_u Tᵀ`` go into the element Hessians, the
rest is the matrix-free coupling, as for the self-contact barrier
(:mod:`~jaxelastic.contact.pairs`).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from ..mechanics.psd import project_psd
from .distance import edge_edge_case, edge_edge_mollifier, point_triangle_case
from .friction import f0, tangent_basis
from .log_barrier import barrier_d1
from .pairs import SelfContact

__all__ = [
    "PairFrictionLag",
    "lag_pair_friction",
    "point_triangle_weights",
    "edge_edge_weights",
    "point_edge_weights_2d",
]


def _dot(a, b):
    return jnp.sum(a * b, axis=-1)


def _param(p, a, b):
    """Clamped parameter ``t ∈ [0, 1]`` of the point of segment ``a b`` closest to ``p``."""
    e = b - a
    ee = _dot(e, e)
    t = jnp.where(ee > 0, _dot(p - a, e) / jnp.where(ee > 0, ee, 1.0), 0.0)
    return jnp.clip(t, 0.0, 1.0)


def point_triangle_weights(p, t0, t1, t2) -> jax.Array:
    """``(4,)`` closest-point weights ``(1, −β₀, −β₁, −β₂)`` of a point–triangle pair
    (coordinates ``(3,)`` [m]; ``β`` the barycentrics of the point of the triangle
    closest to ``p``, by :func:`~jaxelastic.contact.distance.point_triangle_case`)."""
    case = point_triangle_case(p, t0, t1, t2)
    # interior: barycentrics of p's projection onto the plane
    e1, e2, r = t1 - t0, t2 - t0, p - t0
    a, b, c = _dot(e1, e1), _dot(e1, e2), _dot(e2, e2)
    f, g = _dot(r, e1), _dot(r, e2)
    det = a * c - b * b
    det = jnp.where(det > 0, det, 1.0)
    b1, b2 = (c * f - b * g) / det, (a * g - b * f) / det
    s01, s12, s20 = _param(p, t0, t1), _param(p, t1, t2), _param(p, t2, t0)
    one, zero = jnp.ones_like(s01), jnp.zeros_like(s01)
    beta = jnp.stack(
        [
            jnp.stack([one, zero, zero]),  # corner t0
            jnp.stack([zero, one, zero]),  # corner t1
            jnp.stack([zero, zero, one]),  # corner t2
            jnp.stack([1 - s01, s01, zero]),  # side t0t1
            jnp.stack([zero, 1 - s12, s12]),  # side t1t2
            jnp.stack([s20, zero, 1 - s20]),  # side t2t0
            jnp.stack([1 - b1 - b2, b1, b2]),  # interior
        ]
    )[case]
    return jnp.concatenate([one[None], -beta])


def edge_edge_weights(a0, a1, b0, b1) -> jax.Array:
    """``(4,)`` closest-point weights ``(1 − s, s, −(1 − t), −t)`` of an edge–edge pair
    (coordinates ``(3,)`` [m]; ``s``, ``t`` the closest points' parameters on ``a0 a1``
    and ``b0 b1``, by :func:`~jaxelastic.contact.distance.edge_edge_case`)."""
    case = edge_edge_case(a0, a1, b0, b1)
    d1, d2, r = a1 - a0, b1 - b0, a0 - b0
    a, e, b = _dot(d1, d1), _dot(d2, d2), _dot(d1, d2)
    c, f = _dot(d1, r), _dot(d2, r)
    den = a * e - b * b
    den = jnp.where(den > 0, den, 1.0)
    s_ll, t_ll = (b * f - c * e) / den, (a * f - b * c) / den  # line–line
    one, zero = jnp.ones_like(a), jnp.zeros_like(a)
    st = jnp.stack(
        [
            jnp.stack([zero, zero]),  # a0–b0
            jnp.stack([zero, one]),  # a0–b1
            jnp.stack([one, zero]),  # a1–b0
            jnp.stack([one, one]),  # a1–b1
            jnp.stack([zero, _param(a0, b0, b1)]),  # a0–edge b
            jnp.stack([one, _param(a1, b0, b1)]),  # a1–edge b
            jnp.stack([_param(b0, a0, a1), zero]),  # b0–edge a
            jnp.stack([_param(b1, a0, a1), one]),  # b1–edge a
            jnp.stack([s_ll, t_ll]),  # line–line
        ]
    )[case]
    s, t = st[0], st[1]
    return jnp.stack([1 - s, s, -(1 - t), -t])


def point_edge_weights_2d(p, e0, e1) -> jax.Array:
    """``(3,)`` closest-point weights ``(1, −(1 − t), −t)`` of a 2D point–edge pair
    (coordinates ``(2,)`` [m]; ``t`` the clamped parameter of the closest point)."""
    t = _param(p, e0, e1)
    return jnp.stack([jnp.ones_like(t), -(1 - t), -t])


@dataclasses.dataclass(frozen=True)
class PairFrictionLag:
    """Lagged friction of self-contact pairs (a pytree; every field a leaf).

    Attributes:
        pairs: ``(C, q)`` int32 node indices of each pair (3D: point–triangle then
            edge–edge slots, q = 4; 2D: point–edge, q = 3).
        weights: ``(C, q)`` closest-point weights (``Σ_i w_i = 0``).
        z_lag: ``(C, dim)`` ``Σ_i w_i x_i`` at the lag [m] (from the second closest point
            to the first).
        basis: ``(C, dim, dim−1)`` lagged tangent bases.
        normal_force: ``(C,)`` lagged normal forces λ [N] (0: inert slot).
        mu: ``()`` Coulomb coefficient μ of self-contact.
        eps: ``()`` slip tolerance ε [m].

    Build it with :func:`lag_pair_friction`.
    """

    pairs: jax.Array
    weights: jax.Array
    z_lag: jax.Array
    basis: jax.Array
    normal_force: jax.Array
    mu: jax.Array
    eps: jax.Array

    def replace(self, **kw) -> PairFrictionLag:
        return dataclasses.replace(self, **kw)

    # -- tangential slip --------------------------------------------------------------
    def _slip(self, x):
        """``(C, dim)`` relative displacements ``z(x) − z^lag`` [m] of ``x`` ``(n, dim)``."""
        z = jnp.einsum("cq,cqd->cd", self.weights, x[self.pairs])
        return z - self.z_lag

    def _coef(self):
        return self.mu * self.normal_force  # (C,)

    def slips(self, x: jax.Array) -> jax.Array:
        """``(C,)`` tangential slips ``‖Tᵀ(z(x) − z^lag)‖`` [m] of ``x`` ``(n, dim)``."""
        u = jnp.einsum("cdk,cd->ck", self.basis, self._slip(x))
        return jnp.sqrt(jnp.sum(u * u, axis=-1))

    def _pair_energy(self, dz, basis, coef):
        u = basis.T @ dz  # (dim-1,)
        return coef * f0(jnp.sum(u * u), self.eps)

    # -- energy and derivatives -----------------------------------------------------
    def energy(self, x: jax.Array) -> jax.Array:
        """``D_s(x)`` [J] for ``x`` ``(n, dim)`` [m]."""
        e = jax.vmap(self._pair_energy)(self._slip(x), self.basis, self._coef())
        return jnp.sum(e)

    def gradient(self, x: jax.Array) -> jax.Array:
        """``∂D_s/∂x`` ``(n, dim)`` [N]; zero at zero tangential slip."""
        gz = jax.vmap(jax.grad(self._pair_energy))(self._slip(x), self.basis, self._coef())
        return jnp.zeros_like(x).at[self.pairs].add(self.weights[:, :, None] * gz[:, None, :])

    def z_hessians(self, x: jax.Array, project: bool = True) -> jax.Array:
        """``(C, dim, dim)`` Hessians ``T H_u Tᵀ`` of the pair energies in ``z`` [N/m]
        (``H_u`` PSD-projected if ``project``: only round-off is clamped)."""

        def in_u(u, coef):
            return coef * f0(jnp.sum(u * u), self.eps)

        u = jnp.einsum("cdk,cd->ck", self.basis, self._slip(x))
        Hu = jax.vmap(jax.hessian(in_u))(u, self._coef())  # (C, dim-1, dim-1)
        if project:
            Hu = project_psd(Hu)
        return jnp.einsum("cik,ckl,cjl->cij", self.basis, Hu, self.basis)

    def hvp(self, x: jax.Array, v: jax.Array, project: bool = True) -> jax.Array:
        """``(∂²D_s/∂x²) v`` ``(n, dim)`` for ``v`` ``(n, dim)``."""
        Hz = self.z_hessians(x, project)
        r = jnp.einsum("cq,cqd->cd", self.weights, v[self.pairs])
        Hr = jnp.einsum("cij,cj->ci", Hz, r)
        return jnp.zeros_like(v).at[self.pairs].add(self.weights[:, :, None] * Hr[:, None, :])

    def node_blocks(self, x: jax.Array, project: bool = True) -> jax.Array:
        """``(n, dim, dim)`` node-diagonal blocks ``Σ w_i² T H_u Tᵀ`` of the pair
        Hessians, summed per node."""
        Hz = self.z_hessians(x, project)
        w2 = self.weights * self.weights  # (C, q)
        B = w2[:, :, None, None] * Hz[:, None]  # (C, q, dim, dim)
        d = x.shape[1]
        return jnp.zeros((x.shape[0], d, d), x.dtype).at[self.pairs].add(B)

    def coupling(self, x: jax.Array, project: bool = True):
        """``v ↦`` the part of ``(∂²D_s/∂x²) v`` coupling different nodes (``(n, dim) ->
        (n, dim)``; the pair Hessians without the blocks of :meth:`node_blocks`)."""
        Hz = self.z_hessians(x, project)
        w = self.weights

        def apply(v):
            vq = v[self.pairs]  # (C, q, dim)
            r = jnp.einsum("cq,cqd->cd", w, vq)
            rest = r[:, None, :] - w[:, :, None] * vq  # Σ_{j≠i} w_j v_j
            out = w[:, :, None] * jnp.einsum("cij,cqj->cqi", Hz, rest)
            return jnp.zeros_like(v).at[self.pairs].add(out)

        return apply


jax.tree_util.register_dataclass(
    PairFrictionLag,
    data_fields=["pairs", "weights", "z_lag", "basis", "normal_force", "mu", "eps"],
    meta_fields=[],
)


def lag_pair_friction(sc: SelfContact, x: jax.Array, dhat, kappa, mu, eps) -> PairFrictionLag:
    """The :class:`PairFrictionLag` of the candidate pairs of ``sc`` at ``x`` (jit-able).

    Args:
        sc: the self-contact (its candidate buffer must be complete at ``x``, as it is
            after a solve or :meth:`~jaxelastic.contact.pairs.SelfContact.refreshed`).
        x: ``(n, dim)`` lagged positions [m].
        dhat: barrier reach d̂ [m]; kappa: barrier stiffness κ [N/m].
        mu: Coulomb coefficient μ ``()``; eps: slip tolerance ε [m].

    Returns:
        capacity ``C₁ + C₂`` (the buffer's), ``λ = 0`` in empty slots and out of reach.
    """
    dt = x.dtype
    kinds: list[tuple[Any, Any, Any, Any]]
    if sc.dim == 2:
        kinds = [(sc.pt, sc.pt_valid, point_edge_weights_2d, None)]
    else:
        kinds = [(sc.pt, sc.pt_valid, point_triangle_weights, None)]
        if sc.ee.shape[0]:
            kinds.append((sc.ee, sc.ee_valid, edge_edge_weights, sc.ee_eps))
    pairs, weights, z_lag, lam = [], [], [], []
    for idx, valid, wfn, meps in kinds:
        xs = x[idx]  # (C, q, dim)
        w = jax.vmap(lambda s, f=wfn: f(*s))(xs)  # (C, q)
        z = jnp.einsum("cq,cqd->cd", w, xs)
        d = jnp.sqrt(jnp.sum(z * z, axis=-1))
        f = kappa * jnp.abs(barrier_d1(d, dhat))
        if meps is not None:
            f = f * jax.vmap(lambda s, e: edge_edge_mollifier(s[0], s[1], s[2], s[3], e))(xs, meps)
        pairs.append(idx)
        weights.append(w)
        z_lag.append(z)
        lam.append(jnp.where(valid & (d > 0) & (d < dhat), f, 0.0))
    lam_all = jnp.concatenate(lam).astype(dt)
    live = lam_all > 0  # inert slots: zero weights, so they touch no node
    z = jnp.where(live[:, None], jnp.concatenate(z_lag), 0.0)
    d = jnp.sqrt(jnp.sum(z * z, axis=-1))
    ok = d > 0
    n = z / jnp.where(ok, d, 1.0)[:, None]
    n = jnp.where(ok[:, None], n, jnp.eye(x.shape[1], dtype=dt)[0])  # any basis if d = 0
    return PairFrictionLag(
        pairs=jnp.concatenate(pairs).astype(jnp.int32),
        weights=jnp.where(live[:, None], jnp.concatenate(weights), 0.0).astype(dt),
        z_lag=z,
        basis=jax.vmap(tangent_basis)(n),
        normal_force=lam_all,
        mu=jnp.asarray(mu, dt),
        eps=jnp.asarray(eps, dt),
    )
