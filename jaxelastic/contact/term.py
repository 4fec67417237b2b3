"""The contact term of the potential: barrier (+ lagged friction) on boundary nodes, and
self-contact between boundary primitives.

:class:`Contact` is a frozen pytree held by :class:`~jaxelastic.mechanics.potential.Potential`
(``contact=None`` by default: then nothing of this module is traced). For contact nodes
``a`` (the boundary nodes; P2: corner and mid-side) and obstacles ``o``:

``Π_c(x) = κ Σ_{o,a} b(d_o(x_a); d̂) + Σ_{o,a} μ_o λ_oa f₀(‖u_oa‖)``

(IPC: Li et al. 2020, "Incremental Potential Contact", ACM TOG 39(4); barrier
:mod:`~jaxelastic.contact.log_barrier`, friction :mod:`~jaxelastic.contact.friction`). Π_c is
a sum of per-node terms, so its Hessian is block diagonal: one ``(dim, dim)`` block per
contact node, PSD-projected for Newton (eigenvalues clamped at 0; exact for a half-space,
where it is ``κ b''(d) n nᵀ``; around a convex obstacle the tangential eigenvalue
``κ b'(d)/ρ`` is negative). :meth:`Contact.add_hessian_blocks` adds each block to one
element containing the node, so the element-Hessian array the solvers already take
(CG's block Jacobi, the host Cholesky / AMG, the device multigrid) carries contact too.

Self-contact (``self_contact``, :mod:`~jaxelastic.contact.pairs`) adds
``κ Σ_pairs [m] b(d_pair)``. A pair's ``(q·dim)²`` Hessian couples 3–4 nodes of different
elements, so it takes two routes: its node-diagonal blocks are folded into the element
Hessians like the obstacle blocks (every preconditioner and factorisation sees them), and
the rest, which couples different nodes, is the matrix-free :meth:`Contact.coupling`
operator that Newton adds to its Hessian operator (so CG-type solves, including the
host ones used as preconditioners, see the whole Hessian; see docs/guide/contact.md).
With ``self_friction`` (:mod:`~jaxelastic.contact.pair_friction`) the pairs' lagged
friction ``Σ_k μ λ_k f₀(‖T_kᵀ Δu_k‖)`` takes the same two routes.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..mechanics.psd import project_psd
from .ccd import ccd_step, safe_norm
from .friction import FrictionLag, friction_node_energy, tangent_basis
from .log_barrier import barrier, barrier_d1, kappa_update
from .pair_friction import PairFrictionLag, lag_pair_friction
from .pairs import STEP_MARGIN_MAX as STEP_MARGIN_MAX
from .pairs import SelfContact

__all__ = ["Contact", "STEP_MARGIN_MAX"]


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
        self_contact: :class:`~jaxelastic.contact.pairs.SelfContact` or None (no
            self-contact; then ``obstacles`` must not be empty).
        self_friction: :class:`~jaxelastic.contact.pair_friction.PairFrictionLag` (lagged
            friction of the self-contact pairs, with its μ) or None (frictionless pairs).

    Build one with :func:`~jaxelastic.contact.make_contact` (automatic κ, d̂).
    """

    nodes: jax.Array
    obstacles: tuple
    dhat: jax.Array
    kappa: jax.Array
    t: jax.Array
    friction: FrictionLag | None = None
    self_contact: SelfContact | None = None
    self_friction: PairFrictionLag | None = None

    def replace(self, **kw) -> Contact:
        return dataclasses.replace(self, **kw)

    # -- geometry --------------------------------------------------------------------
    def offsets(self) -> jax.Array:
        """``(n_obs, dim)`` obstacle translations at :attr:`t` [m]."""
        if not self.obstacles:
            d = 0 if self.self_contact is None else self.self_contact.rest.shape[1]
            return jnp.zeros((0, d), self.dhat.dtype)
        return jnp.stack([ob.offset(self.t) for ob in self.obstacles])

    def mu(self) -> jax.Array:
        """``(n_obs,)`` friction coefficients."""
        if not self.obstacles:
            return jnp.zeros((0,), self.dhat.dtype)
        return jnp.stack([jnp.asarray(ob.friction, self.dhat.dtype) for ob in self.obstacles])

    def distances(self, x: jax.Array) -> jax.Array:
        """``(n_obs, m)`` signed distances [m] of the contact nodes of ``x`` ``(n, dim)``."""
        xn = x[self.nodes]
        if not self.obstacles:
            return jnp.zeros((0, xn.shape[0]), x.dtype)
        return jnp.stack(
            [jax.vmap(lambda p, ob=ob: ob.distance(p, self.t))(xn) for ob in self.obstacles]
        )

    def min_distance(self, x: jax.Array) -> jax.Array:
        """Smallest node–obstacle or (self-contact) pair distance [m] (≤ 0: penetration;
        +inf with neither in reach)."""
        d = jnp.min(self.distances(x), initial=jnp.inf)
        if self.self_contact is not None:
            d = jnp.minimum(d, self.self_contact.min_distance(x))
        return d

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
        """Π_c(x) [J] for ``x`` ``(n, dim)``; +inf if a node is inside an obstacle or a
        self-contact pair touches."""
        e = jnp.zeros((), x.dtype)
        if self.obstacles:
            e = e + jnp.sum(self._per_node(self._node_energy, x))
        if self.self_contact is not None:
            e = e + self.self_contact.energy(x, self.dhat, self.kappa)
        if self.self_friction is not None:
            e = e + self.self_friction.energy(x)
        return e

    def _scatter(self, x, g):
        return jnp.zeros_like(x).at[self.nodes].add(g)

    def _self_gradient(self, x):
        return self.self_contact.gradient(x, self.dhat, self.kappa)  # type: ignore[union-attr]

    def gradient(self, x: jax.Array) -> jax.Array:
        """∂Π_c/∂x ``(n, dim)`` [N] (zero off the contact nodes)."""
        g = jnp.zeros_like(x)
        if self.obstacles:
            g = self._scatter(x, self._per_node(jax.grad(self._node_energy), x))
        if self.self_contact is not None:
            g = g + self._self_gradient(x)
        if self.self_friction is not None:
            g = g + self.self_friction.gradient(x)
        return g

    def forces(self, x: jax.Array, friction: bool = True) -> jax.Array:
        """Contact forces on the nodes ``−∂Π_c/∂x`` ``(n, dim)`` [N] (barrier only if not
        ``friction``); self-contact forces (and their friction) included: they sum to
        zero."""
        f = jnp.zeros_like(x)
        if self.obstacles:
            fn = jax.grad(lambda xa, d: self._node_energy(xa, d, friction))
            f = -self._scatter(x, self._per_node(fn, x))
        if self.self_contact is not None:
            f = f - self._self_gradient(x)
        if friction and self.self_friction is not None:
            f = f - self.self_friction.gradient(x)
        return f

    def node_hessians(self, x: jax.Array, project: bool = True) -> jax.Array:
        """``(m, dim, dim)`` Hessian blocks of the obstacle term per contact node
        (PSD-projected if ``project``)."""
        H = self._per_node(jax.hessian(self._node_energy), x)
        return project_psd(H) if project else H

    def hvp(self, x: jax.Array, v: jax.Array, exact: bool = False) -> jax.Array:
        """``(∂²Π_c/∂x²) v`` ``(n, dim)``: with the projected blocks, or exact."""
        Hv = jnp.zeros_like(v)
        if self.obstacles:
            H = self.node_hessians(x, project=not exact)
            Hv = self._scatter(x, jnp.einsum("mij,mj->mi", H, v[self.nodes]))
        if self.self_contact is not None:
            Hv = Hv + self.self_contact.hvp(x, v, self.dhat, self.kappa, project=not exact)
        if self.self_friction is not None:
            Hv = Hv + self.self_friction.hvp(x, v, project=not exact)
        return Hv

    def pair_hessians(self, x: jax.Array, exact: bool = False) -> list | None:
        """The self-contact pair Hessians at ``x`` ``(n, dim)``
        (:meth:`~jaxelastic.contact.pairs.SelfContact.pair_hessians`; projected unless
        ``exact``), or None without self-contact: computed once, they can be handed to
        :meth:`coupling` in another compiled piece."""
        if self.self_contact is None:
            return None
        return self.self_contact.pair_hessians(x, self.dhat, self.kappa, project=not exact)

    def coupling(self, x: jax.Array, exact: bool = False, pair_hessians=None):
        """The self-contact Hessian's coupling of different nodes as ``v ↦ H_c v``
        (``(n, dim) -> (n, dim)``; projected pair Hessians unless ``exact``, or the given
        :meth:`pair_hessians` at ``x``), or None without self-contact. Newton adds it to
        the element-Hessian operator, whose :meth:`add_hessian_blocks` hold the
        node-diagonal rest."""
        if self.self_contact is None:
            return None
        cpl = self.self_contact.coupling(
            x, self.dhat, self.kappa, project=not exact, hessians=pair_hessians
        )
        if self.self_friction is None:
            return cpl
        cpl_f = self.self_friction.coupling(x, project=not exact)  # pair friction's
        return lambda v: cpl(v) + cpl_f(v)

    def add_hessian_blocks(
        self, Ke: jax.Array, mesh: Any, x: jax.Array, project: bool = True, pair_hessians=None
    ):
        """``Ke`` ``(n_cells, k·d, k·d)`` with each contact node's block (obstacles, and
        the node-diagonal blocks of the self-contact pair Hessians) added to the diagonal
        block of the first element containing it (``mesh.incidence``); ``pair_hessians``:
        :meth:`pair_hessians` at ``x`` with the same projection, if computed before."""
        c, k = mesh.cells.shape
        d = x.shape[1]
        K4 = Ke.reshape(c, k, d, k, d)
        if self.obstacles:
            slot = mesh.incidence[self.nodes, 0]  # flat cell·k + local slot
            cell, loc = slot // k, slot % k
            H = self.node_hessians(x, project).astype(Ke.dtype)
            K4 = K4.at[cell, loc, :, loc, :].add(H)
        sc = self.self_contact
        if sc is not None:
            slot = mesh.incidence[sc.nodes, 0]
            cell, loc = slot // k, slot % k
            B = sc.node_blocks(x, self.dhat, self.kappa, project, hessians=pair_hessians)
            if self.self_friction is not None:  # its pairs' nodes are surface nodes
                B = B + self.self_friction.node_blocks(x, project)
            B = B[sc.nodes].astype(Ke.dtype)
            K4 = K4.at[cell, loc, :, loc, :].add(B)
        return K4.reshape(Ke.shape)

    # -- line search, lagging, time --------------------------------------------------
    def ccd_step(self, x: jax.Array, step: jax.Array) -> jax.Array:
        """Largest safe initial step α₀ ∈ (0, 1] along ``step`` ``(n, dim)`` [m]
        (:func:`~jaxelastic.contact.ccd.ccd_step`)."""
        a = ccd_step(self.obstacles, x[self.nodes], step[self.nodes], self.t)
        if self.self_contact is not None:
            a = jnp.minimum(a, self.self_contact.ccd_step(x, step))
            a = jnp.maximum(a, jnp.finfo(x.dtype).tiny)
        return a

    # -- the Newton loop's term protocol (jaxelastic.solvers.newton.terms) ----------------
    def step_bound(self, x: jax.Array, step: jax.Array) -> jax.Array:
        """The line search's starting fraction of ``step``: :meth:`ccd_step`."""
        return self.ccd_step(x, step)

    @property
    def host_refresh(self) -> bool:
        """Whether the Newton loop should refresh this term on the host between
        iterations (:meth:`refreshed`): with self-contact, whose broad phase is host work."""
        return self.self_contact is not None

    def adapt_init(self, x: jax.Array, max_factor: float):
        """The state of IPC's in-solve κ adaptation (:func:`~.log_barrier.kappa_update`) from
        ``x``: κ, its cap ``max_factor·κ`` and the smallest gap."""
        k0 = jnp.asarray(self.kappa, x.dtype)
        return dict(kappa=k0, kappa_max=k0 * max_factor, gap=self.min_distance(x).astype(x.dtype))

    def adapt(self, state: dict, x: jax.Array):
        """``(state, changed)`` after an accepted iterate ``x``: κ doubled (up to its cap)
        while the smallest gap is below ``SMALL_GAP·d̂`` and still shrinking."""
        gap = self.min_distance(x)
        kappa = kappa_update(state["kappa"], state["kappa_max"], gap, state["gap"], self.dhat)
        return dict(state, kappa=kappa, gap=gap), kappa != state["kappa"]

    def adapted(self, state: dict) -> Contact:
        """This contact at the adapted κ of ``state``."""
        return self.replace(kappa=state["kappa"])

    @staticmethod
    def adapt_stats(state: dict) -> dict:
        """What a solve reports of the adaptation: ``kappa``."""
        return dict(kappa=state["kappa"])

    def solved(self, stats: dict) -> Contact:
        """This contact at the κ a solve ended with (``stats["kappa"]``; the ratio is a
        constant, so derivatives with respect to κ pass through)."""
        if "kappa" not in stats:
            return self
        ratio = jax.lax.stop_gradient(stats["kappa"] / self.kappa)
        return self.replace(kappa=self.kappa * ratio)

    # -- self-contact broad phase (host) -----------------------------------------------
    def refreshed(self, x, step=None, force: bool = False) -> Contact:
        """(host, concrete arrays) This contact with the self-contact broad phase re-run
        at ``x`` ``(n, dim)`` if a surface node has used half its motion bound (or
        ``force``, or a ``step`` ``(n, dim)`` [m] — the next Newton step — would leave
        it): the new bound is ``max(base_margin, 1.1·max_a ‖step_a‖)``, at most
        ``STEP_MARGIN_MAX·base_margin`` (a longer step is cut by the bound), and
        ``base_margin`` if that bound's candidates do not fit the buffer (a long step
        never grows it). Unchanged without self-contact."""
        sc = self.self_contact
        if sc is None:
            return self
        m0 = float(sc.base_margin)
        margin = m0
        if step is not None:
            s = np.asarray(step)[np.asarray(sc.nodes)]
            smax = float(np.max(np.sqrt(np.sum(s * s, axis=1)), initial=0.0))
            margin = min(max(m0, 1.1 * smax), STEP_MARGIN_MAX * m0)
            xh = np.asarray(x)
            u = xh[np.asarray(sc.nodes)] - np.asarray(sc.x_ref)
            um = float(np.max(np.sqrt(np.sum(u * u, axis=1)), initial=0.0))
            force = force or um + margin / 1.1 > float(sc.margin)
        if not (force or sc.needs_refresh(x)):
            return self
        fallback = m0 if margin > m0 else None  # a longer bound only if it fits the buffer
        return self.replace(self_contact=sc.refreshed(x, self.dhat, margin, fallback))

    def outran(self, x) -> bool:
        """(host) Whether a solve ending at ``x`` may have been held back by the
        self-contact motion bound (a surface node moved half of it)."""
        sc = self.self_contact
        return sc is not None and sc.needs_refresh(x)

    def normal_forces(self, x: jax.Array) -> jax.Array:
        """``(n_obs, m)`` barrier normal-force magnitudes κ|b'(d)| [N]."""
        return self.kappa * jnp.abs(barrier_d1(self.distances(x), self.dhat))

    @property
    def has_friction(self) -> bool:
        """Whether friction is on (obstacles or self-contact pairs): then :meth:`lag` it
        at the start of every time or load step."""
        return self.friction is not None or self.self_friction is not None

    def lag(self, x: jax.Array, eps=None) -> Contact:
        """This contact with friction lagged at ``x`` ``(n, dim)`` [m]: the obstacle
        friction (normal forces, tangent bases, positions and obstacle translations now;
        turned on here if no friction is on yet, as :func:`make_contact` does) and, if on,
        the self-contact pair friction (:meth:`with_self_friction`, same μ). ``eps`` [m]
        the slip tolerance (default: the current one, else 1e-2·d̂). Jit-able."""
        out = self
        sf = self.self_friction
        if self.obstacles and (self.friction is not None or sf is None):
            out = out.replace(friction=self._lag_obstacles(x, eps))
        if sf is not None:
            out = out.with_self_friction(x, sf.mu, sf.eps if eps is None else eps)
        return out

    def with_self_friction(self, x: jax.Array, mu, eps) -> Contact:
        """This contact with friction μ ``()`` on its self-contact pairs, lagged at ``x``
        ``(n, dim)`` [m] over the current candidate buffer
        (:func:`~jaxelastic.contact.pair_friction.lag_pair_friction`; the buffer must be
        complete at ``x``), slip tolerance ``eps`` [m]. Jit-able.

        Raises:
            ValueError: without self-contact.
        """
        if self.self_contact is None:
            raise ValueError(
                "self-contact friction needs self-contact: make_contact(..., self_contact=True)"
            )
        lag = lag_pair_friction(self.self_contact, x, self.dhat, self.kappa, mu, eps)
        return self.replace(self_friction=lag)

    def _lag_obstacles(self, x: jax.Array, eps) -> FrictionLag:
        xn = x[self.nodes]
        bases = []
        for ob in self.obstacles:
            n = jax.vmap(jax.grad(lambda p, ob=ob: ob.distance(p, self.t)))(xn)  # (m, dim)
            n = n / jnp.maximum(safe_norm(n), jnp.finfo(x.dtype).tiny)[:, None]
            bases.append(jax.vmap(tangent_basis)(n))
        if eps is None:
            eps = self.friction.eps if self.friction is not None else 1e-2 * self.dhat
        return FrictionLag(
            x_lag=xn,
            offset_lag=self.offsets(),
            normal_force=self.normal_forces(x),
            basis=jnp.stack(bases),
            eps=jnp.asarray(eps, x.dtype),
        )

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
    data_fields=[
        "nodes",
        "obstacles",
        "dhat",
        "kappa",
        "t",
        "friction",
        "self_contact",
        "self_friction",
    ],
    meta_fields=[],
)
