"""The contact term of the potential: barrier (+ lagged friction) on boundary nodes.

:class:`Contact` is a frozen pytree held by :class:`~jaxelastic.potential.Potential`
(``contact=None`` by default: then nothing of this module is traced). For contact nodes
``a`` (the boundary nodes; P2: corner and mid-side) and obstacles ``o``:

``Π_c(x) = κ Σ_{o,a} b(d_o(x_a); d̂) + Σ_{o,a} μ_o λ_oa f₀(‖u_oa‖)``

(IPC: Li et al. 2020, "Incremental Potential Contact", ACM TOG 39(4); barrier
:mod:`~jaxelastic.contact.barrier`, friction :mod:`~jaxelastic.contact.friction`). Π_c is
a sum of per-node terms, so its Hessian is block diagonal: one ``(dim, dim)`` block per
contact node, PSD-projected for Newton (eigenvalues clamped at 0; exact for a half-space,
where it is ``κ b''(d) n nᵀ``; around a convex obstacle the tangential eigenvalue
``κ b'(d)/ρ`` is negative). :meth:`Contact.add_hessian_blocks` adds each block to one
element containing the node, so the element-Hessian array the solvers already take
(CG's block Jacobi, the host Cholesky / AMG, the device multigrid) carries contact too.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from ..energy import project_psd
from .barrier import barrier, barrier_d1
from .ccd import ccd_step, safe_norm
from .friction import FrictionLag, friction_node_energy, tangent_basis

__all__ = ["Contact"]


@dataclasses.dataclass(frozen=True)
class Contact:
    """Barrier contact of a body's boundary nodes with rigid obstacles.

    Attributes:
        nodes: ``(m,)`` int32 indices of the contact nodes.
        obstacles: tuple of obstacles (:mod:`~jaxelastic.contact.obstacles`).
        dhat: ``()`` barrier reach d̂ [m].
        kappa: ``()`` barrier stiffness κ [N/m].
        t: ``()`` time at which the obstacles' prescribed motion is evaluated [s].
        friction: :class:`~jaxelastic.contact.friction.FrictionLag` or None (frictionless).

    Build one with :func:`~jaxelastic.contact.make_contact` (automatic κ, d̂).
    """

    nodes: jax.Array
    obstacles: tuple
    dhat: jax.Array
    kappa: jax.Array
    t: jax.Array
    friction: FrictionLag | None = None

    def replace(self, **kw) -> Contact:
        return dataclasses.replace(self, **kw)

    # -- geometry --------------------------------------------------------------------
    def offsets(self) -> jax.Array:
        """``(n_obs, dim)`` obstacle translations at :attr:`t` [m]."""
        return jnp.stack([ob.offset(self.t) for ob in self.obstacles])

    def mu(self) -> jax.Array:
        """``(n_obs,)`` friction coefficients."""
        return jnp.stack([jnp.asarray(ob.friction, self.dhat.dtype) for ob in self.obstacles])

    def distances(self, x: jax.Array) -> jax.Array:
        """``(n_obs, m)`` signed distances [m] of the contact nodes of ``x`` ``(n, dim)``."""
        xn = x[self.nodes]
        return jnp.stack(
            [jax.vmap(lambda p, ob=ob: ob.distance(p, self.t))(xn) for ob in self.obstacles]
        )

    def min_distance(self, x: jax.Array) -> jax.Array:
        """Smallest node–obstacle distance [m] (≤ 0: penetration)."""
        return jnp.min(self.distances(x))

    # -- energy and derivatives ------------------------------------------------------
    def _node_data(self):
        """Per-node friction data (leading axis m) or None."""
        f = self.friction
        if f is None:
            return None
        return (f.x_lag, f.normal_force.T, jnp.swapaxes(f.basis, 0, 1))

    def _node_energy(self, xa, data, with_friction: bool = True) -> jax.Array:
        """Π_c of one node at ``xa`` ``(dim,)`` [J] (+inf inside an obstacle)."""
        e = jnp.zeros((), xa.dtype)
        for ob in self.obstacles:
            e = e + self.kappa * barrier(ob.distance(xa, self.t), self.dhat)
        f = self.friction
        if with_friction and f is not None and data is not None:
            x_lag, lam, basis = data
            dc = self.offsets() - f.offset_lag
            e = e + friction_node_energy(xa, x_lag, lam, basis, self.mu(), dc, f.eps)
        return e

    def _per_node(self, fn, x):
        return jax.vmap(fn)(x[self.nodes], self._node_data())

    def energy(self, x: jax.Array) -> jax.Array:
        """Π_c(x) [J] for ``x`` ``(n, dim)``; +inf if a node is inside an obstacle."""
        return jnp.sum(self._per_node(self._node_energy, x))

    def _scatter(self, x, g):
        return jnp.zeros_like(x).at[self.nodes].add(g)

    def gradient(self, x: jax.Array) -> jax.Array:
        """∂Π_c/∂x ``(n, dim)`` [N] (zero off the contact nodes)."""
        return self._scatter(x, self._per_node(jax.grad(self._node_energy), x))

    def forces(self, x: jax.Array, friction: bool = True) -> jax.Array:
        """Contact forces on the nodes ``−∂Π_c/∂x`` ``(n, dim)`` [N] (barrier only if not
        ``friction``)."""
        fn = jax.grad(lambda xa, d: self._node_energy(xa, d, friction))
        return -self._scatter(x, self._per_node(fn, x))

    def node_hessians(self, x: jax.Array, project: bool = True) -> jax.Array:
        """``(m, dim, dim)`` Hessian blocks of Π_c per contact node (PSD-projected if
        ``project``)."""
        H = self._per_node(jax.hessian(self._node_energy), x)
        return project_psd(H) if project else H

    def hvp(self, x: jax.Array, v: jax.Array, exact: bool = False) -> jax.Array:
        """``(∂²Π_c/∂x²) v`` ``(n, dim)``: with the projected blocks, or exact."""
        H = self.node_hessians(x, project=not exact)
        return self._scatter(x, jnp.einsum("mij,mj->mi", H, v[self.nodes]))

    def add_hessian_blocks(self, Ke: jax.Array, mesh: Any, x: jax.Array, project: bool = True):
        """``Ke`` ``(n_cells, k·d, k·d)`` with each contact node's block added to the
        diagonal block of the first element containing it (``mesh.incidence``)."""
        c, k = mesh.cells.shape
        d = x.shape[1]
        slot = mesh.incidence[self.nodes, 0]  # flat cell·k + local slot
        cell, loc = slot // k, slot % k
        K4 = Ke.reshape(c, k, d, k, d)
        H = self.node_hessians(x, project).astype(Ke.dtype)
        return K4.at[cell, loc, :, loc, :].add(H).reshape(Ke.shape)

    # -- line search, lagging, time --------------------------------------------------
    def ccd_step(self, x: jax.Array, step: jax.Array) -> jax.Array:
        """Largest safe initial step α₀ ∈ (0, 1] along ``step`` ``(n, dim)`` [m]
        (:func:`~jaxelastic.contact.ccd.ccd_step`)."""
        return ccd_step(self.obstacles, x[self.nodes], step[self.nodes], self.t)

    def normal_forces(self, x: jax.Array) -> jax.Array:
        """``(n_obs, m)`` barrier normal-force magnitudes κ|b'(d)| [N]."""
        return self.kappa * jnp.abs(barrier_d1(self.distances(x), self.dhat))

    def lag(self, x: jax.Array, eps=None) -> Contact:
        """This contact with friction lagged at ``x`` (normal forces, tangent bases,
        positions and obstacle translations now); ``eps`` [m] the slip tolerance (default:
        the current one, else 1e-2·d̂)."""
        xn = x[self.nodes]
        bases = []
        for ob in self.obstacles:
            n = jax.vmap(jax.grad(lambda p, ob=ob: ob.distance(p, self.t)))(xn)  # (m, dim)
            n = n / jnp.maximum(safe_norm(n), jnp.finfo(x.dtype).tiny)[:, None]
            bases.append(jax.vmap(tangent_basis)(n))
        if eps is None:
            eps = self.friction.eps if self.friction is not None else 1e-2 * self.dhat
        lag = FrictionLag(
            x_lag=xn,
            offset_lag=self.offsets(),
            normal_force=self.normal_forces(x),
            basis=jnp.stack(bases),
            eps=jnp.asarray(eps, x.dtype),
        )
        return self.replace(friction=lag)

    def at_time(self, t) -> Contact:
        """This contact with the obstacles at time ``t`` [s]."""
        return self.replace(t=jnp.asarray(t, self.dhat.dtype))

    def make_feasible(self, x: jax.Array, margin=None) -> jax.Array:
        """``x`` with every contact node inside an obstacle (d ≤ 0) pushed out along the SDF
        gradient to ``margin`` (default ½d̂): a feasible start after an obstacle moved.
        Other nodes are not moved."""
        margin = 0.5 * self.dhat if margin is None else margin
        xn = x[self.nodes]
        for ob in self.obstacles:
            d, n = jax.vmap(jax.value_and_grad(lambda p, ob=ob: ob.distance(p, self.t)))(xn)
            xn = xn + jnp.where(d <= 0, margin - d, 0.0)[:, None] * n
        return x.at[self.nodes].set(xn)


jax.tree_util.register_dataclass(
    Contact,
    data_fields=["nodes", "obstacles", "dhat", "kappa", "t", "friction"],
    meta_fields=[],
)
