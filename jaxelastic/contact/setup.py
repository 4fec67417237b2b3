"""Building a :class:`~jaxelastic.contact.term.Contact` for a potential: contact nodes,
automatic d̂ and κ, friction on/off, self-contact, and the adaptive κ update between
steps."""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..mechanics.potential import Potential, elastic_element_hessians, node_hessian_blocks
from ..mesh import boundary_nodes
from .friction import EPS_REL
from .log_barrier import adapt_kappa, default_dhat, kappa_from_stiffness
from .pairs import make_self_contact
from .term import Contact

__all__ = ["make_contact", "with_contact", "contact_nodes", "auto_kappa", "adapt"]


def contact_nodes(mesh) -> np.ndarray:
    """``(m,)`` int32 contact nodes: the boundary nodes (P2: corners and mid-sides)."""
    return np.asarray(boundary_nodes(mesh), dtype=np.int32)


def auto_kappa(pot: Potential, nodes) -> jax.Array:
    """κ [N/m] from the elastic Hessian at the rest shape: the mean diagonal node stiffness
    over ``nodes`` (:func:`~jaxelastic.contact.log_barrier.kappa_from_stiffness`); inertia and
    any contact term of ``pot`` are left out. One element-Hessian evaluation.
    """
    base = pot.replace(contact=None, mass=None, mass_damping=None)
    return _kappa(base, jnp.asarray(nodes))


@jax.jit
def _kappa(base: Potential, nodes):
    Ke = elastic_element_hessians(base, base.mesh.points, project=True)
    return kappa_from_stiffness(node_hessian_blocks(base, Ke), nodes)


def make_contact(
    pot: Potential,
    obstacles: Sequence = (),
    *,
    self_contact: bool = False,
    margin=None,
    nodes=None,
    dhat=None,
    kappa=None,
    friction: bool | None = None,
    self_friction=None,
    eps=None,
    t=0.0,
) -> Contact:
    """A :class:`Contact` of ``pot``'s body with ``obstacles``.

    Args:
        pot: the potential (its mesh, material and masses set κ).
        obstacles: obstacles (:mod:`~jaxelastic.contact.obstacles`); at least one unless
            ``self_contact``.
        self_contact: also barrier contact between the body's own boundary primitives
            (:mod:`~jaxelastic.contact.pairs`; broad phase at the rest shape).
        margin: self-contact motion bound [m] (default ``min(10 d̂, ¼ shortest boundary
            edge)``: :func:`~jaxelastic.contact.pairs.make_self_contact`).
        nodes: ``(m,)`` contact nodes (default: every boundary node).
        dhat: barrier reach [m] (default 1e-3 × the rest bounding-box diagonal).
        kappa: barrier stiffness [N/m] (default :func:`auto_kappa`).
        friction: lagged friction on/off (default: on if an obstacle has μ > 0); the lag
            starts at the rest shape (:meth:`Contact.lag` moves it).
        self_friction: Coulomb coefficient μ of self-contact pairs (default None: no
            friction between them; needs ``self_contact``;
            :mod:`~jaxelastic.contact.pair_friction`), lagged with the obstacle friction.
        eps: friction slip tolerance [m] (default 1e-5 × the bounding-box diagonal).
        t: initial obstacle time [s].

    Raises:
        ValueError: no obstacle and no self-contact, a contact node inside an obstacle at
            the rest shape, two boundary primitives touching at the rest shape, or
            ``self_friction`` without ``self_contact`` or negative.
    """
    obstacles = tuple(obstacles)
    if not obstacles and not self_contact:
        raise ValueError("make_contact needs at least one obstacle or self_contact=True")
    X = pot.mesh.points
    dt = X.dtype
    nodes = jnp.asarray(contact_nodes(pot.mesh) if nodes is None else nodes, jnp.int32)
    dhat = default_dhat(X) if dhat is None else jnp.asarray(dhat, dt)
    kappa = auto_kappa(pot, nodes) if kappa is None else jnp.asarray(kappa, dt)
    c = Contact(nodes, obstacles, jnp.asarray(dhat, dt), jnp.asarray(kappa, dt), jnp.asarray(t, dt))
    if self_contact:
        sc = make_self_contact(pot.mesh, c.dhat, margin)
        dself = float(sc.min_distance(X))
        if not dself > 0:
            raise ValueError(
                f"make_contact: two boundary primitives of the body touch at the rest shape "
                f"(distance {dself:.3g} m); self-contact needs a surface that is apart from "
                "itself except where primitives share a node"
            )
        c = c.replace(self_contact=sc)
    dmin = float(jnp.min(c.distances(X), initial=jnp.inf))
    if not dmin > 0:
        raise ValueError(
            f"make_contact: a contact node is inside an obstacle at the rest shape (min "
            f"distance {dmin:.3g} m): move the obstacle or the mesh so they start apart"
        )
    if friction is None:
        friction = any(float(jnp.asarray(ob.friction)) > 0 for ob in obstacles)
    eps = EPS_REL * float(default_dhat(X, 1.0)) if eps is None else eps
    if friction and obstacles:
        c = c.lag(X, eps=eps)
    if self_friction is not None:
        negative = isinstance(self_friction, (int, float)) and not self_friction >= 0
        if not self_contact or negative:
            raise ValueError(
                f"make_contact: self_friction = {self_friction} needs self_contact=True "
                "and a coefficient >= 0"
            )
        c = c.with_self_friction(X, jnp.asarray(self_friction, dt), eps)
    return c


def with_contact(pot: Potential, obstacles: Sequence = (), **kw) -> Potential:
    """``pot`` with a contact term (:func:`make_contact`, same keywords)."""
    return pot.replace(contact=make_contact(pot, obstacles, **kw))


def adapt(contact: Contact, x: jax.Array, max_kappa=None) -> Contact:
    """``contact`` with κ doubled if the smallest gap (obstacles and self-contact) at
    ``x`` is below 1e-2·d̂
    (:func:`~jaxelastic.contact.log_barrier.adapt_kappa`); jit-able."""
    k = adapt_kappa(contact.kappa, contact.min_distance(x), contact.dhat, max_kappa)
    return contact.replace(kappa=k)
