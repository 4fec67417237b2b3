"""Building a :class:`~jaxelastic.contact.term.Contact` for a potential: contact nodes,
automatic d̂ and κ, friction on/off, self-contact, and the adaptive κ update between
steps."""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer

from ..mechanics.potential import Potential, elastic_element_hessians, node_hessian_blocks
from ..mesh import boundary_facets, boundary_nodes
from .friction import EPS_REL
from .log_barrier import DHAT_MAX_REL, adapt_kappa, default_dhat, kappa_from_stiffness
from .obstacles import check_obstacle, interior_point
from .pairs import make_self_contact
from .term import Contact

__all__ = [
    "make_contact",
    "with_contact",
    "contact_nodes",
    "auto_kappa",
    "adapt",
    "check_apart",
    "check_barrier",
]


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

    Long because: the checks of every input come first, then the term is built in the
    order its parts depend on each other (d̂ and κ, self-contact, friction); split, the
    order would be spread over several functions.

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
        ValueError: no obstacle and no self-contact, an invalid obstacle
            (:func:`~jaxelastic.contact.obstacles.check_obstacle`), ``dhat`` or ``kappa``
            ≤ 0 or non-finite, or ``dhat`` beyond ``DHAT_MAX_REL`` × the body's size
            (:func:`check_barrier`), an obstacle that intersects the rest body
            (:func:`check_apart`), two boundary primitives touching at the rest shape, or
            ``self_friction`` without ``self_contact`` or negative.
    """
    obstacles = tuple(obstacles)
    if not obstacles and not self_contact:
        raise ValueError("make_contact needs at least one obstacle or self_contact=True")
    for i, ob in enumerate(obstacles):
        check_obstacle(ob, f"obstacle {i}")
    X = pot.mesh.points
    dt = X.dtype
    nodes = jnp.asarray(contact_nodes(pot.mesh) if nodes is None else nodes, jnp.int32)
    check_barrier(X, dhat, kappa)
    dhat = default_dhat(X) if dhat is None else jnp.asarray(dhat, dt)
    kappa = auto_kappa(pot, nodes) if kappa is None else jnp.asarray(kappa, dt)
    check_apart(pot.mesh, obstacles, t)
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


def check_barrier(points, dhat, kappa) -> None:
    """Refuse a barrier reach ``dhat`` [m] or stiffness ``kappa`` [N/m] that is not a
    finite positive number, and a ``dhat`` above :data:`~.log_barrier.DHAT_MAX_REL` times
    the body's size (the barrier would push across the whole body). None: automatic.

    Raises:
        ValueError: naming ``dhat`` or ``kappa``.
    """
    size = float(default_dhat(points, 1.0))
    for name, v, unit in (("dhat", dhat, "m"), ("kappa", kappa, "N/m")):
        if v is None:
            continue
        if isinstance(v, Tracer):
            continue  # traced: not checked
        try:
            f = float(v)
        except (TypeError, ValueError):
            raise ValueError(f"{name} must be a number [{unit}], got {v!r}") from None
        if not (np.isfinite(f) and f > 0):
            raise ValueError(
                f"{name} must be a finite number > 0 [{unit}], got {v!r}; leave it out for "
                "the automatic value"
            )
    if dhat is not None and not isinstance(dhat, Tracer) and float(dhat) > DHAT_MAX_REL * size:
        raise ValueError(
            f"dhat = {float(dhat):.3g} m is more than {DHAT_MAX_REL:g} x the body's size "
            f"({size:.3g} m): the barrier would act across the body. The barrier reach is a "
            f"small gap (default {float(default_dhat(points)):.3g} m); leave dhat out for it"
        )


def _describe(point) -> str:
    return "(" + ", ".join(f"{float(v):.4g}" for v in np.asarray(point)) + ")"


FACET_ITERATIONS = 64
"""Frank–Wolfe iterations of :func:`check_apart`'s search for the point of a boundary
facet closest to (or deepest in) an obstacle."""


@jax.jit
def _facet_closest(ob, t, V):
    """Per facet ``V`` ``(f, d, dim)`` (its corners), the point of smallest signed distance
    to ``ob`` found by Frank–Wolfe on the facet (a simplex) from its centroid: exact in the
    limit for a convex obstacle, whose signed distance is a convex function."""

    def one(Vf):
        def f(x):
            return ob.distance(x, t)

        def body(k, c):
            x, best, xb = c
            g = jax.grad(f)(x)
            v = Vf[jnp.argmin(Vf @ g)]  # the facet corner the gradient points away from
            x = x + (2.0 / (k + 2.0)) * (v - x)
            fx = f(x)
            better = fx < best
            return x, jnp.where(better, fx, best), jnp.where(better, x, xb)

        x0 = jnp.mean(Vf, axis=0)
        _, _, xb = jax.lax.fori_loop(0, FACET_ITERATIONS, body, (x0, f(x0), x0))
        return xb

    return jax.vmap(one)(V)


def check_apart(mesh, obstacles: Sequence, t=0.0) -> None:
    """Refuse an obstacle that intersects the rest body, naming it.

    Not only the nodes: the obstacles' signed distances are evaluated at every node and
    cell centroid and at the point of each boundary facet closest to the obstacle (a
    Frank–Wolfe search, :data:`FACET_ITERATIONS` steps: a box poking through a face
    between nodes is found), and an obstacle whose own interior point
    (:func:`~jaxelastic.contact.obstacles.interior_point`: a sphere's centre, a box's
    centre, …) lies in a cell is inside the body even where no sample point is inside it
    (a small sphere between nodes). Host work, once per contact.

    Raises:
        ValueError: ``obstacle i (Type) intersects the body at the rest shape …``.
    """
    if not obstacles:
        return
    X = np.asarray(mesh.points, dtype=np.float64)
    d = mesh.dim
    cells = np.asarray(mesh.cells)
    corners = X[cells[:, : d + 1]]  # (c, d+1, d) the simplex corners (P2: the vertices)
    facets = boundary_facets(mesh)[:, :d]  # (f, d) corner nodes
    T = np.swapaxes(corners[:, 1:] - corners[:, :1], 1, 2)  # (c, d, d) columns: edges
    ok = np.abs(np.linalg.det(T)) > 0
    dt = mesh.points.dtype
    for i, ob in enumerate(obstacles):
        kind = type(ob).__name__
        fn = jax.jit(jax.vmap(lambda x, ob=ob: ob.distance(x, t)))
        samples = {"node": X, "cell centroid": corners.mean(1)}
        if len(facets):  # the closest point of each boundary facet (convex obstacles)
            samples["boundary facet point"] = np.asarray(
                _facet_closest(ob, jnp.asarray(t, dt), jnp.asarray(X[facets], dt))
            )
        for what, P in samples.items():
            if len(P) == 0:
                continue
            dist = np.asarray(fn(jnp.asarray(P, dt)), dtype=np.float64)
            bad = ~(dist > 0)
            if bad.any():
                j = int(np.argmin(np.where(np.isnan(dist), -np.inf, dist)))
                raise ValueError(
                    f"obstacle {i} ({kind}) intersects the body at the rest shape: "
                    f"{int(bad.sum())} {what}(s) inside it (signed distance {dist[j]:.3g} m "
                    f"at {_describe(P[j])}). Move the obstacle or the mesh so they start "
                    "apart (the barrier keeps them apart only from a separated start)"
                )
        p = interior_point(ob)
        if p is None or not ok.any():
            continue
        p = np.asarray(p, np.float64) + np.asarray(ob.offset(t), np.float64)
        lam = np.full((len(cells), d), -1.0)
        lam[ok] = np.linalg.solve(T[ok], (p - corners[ok, 0])[..., None])[..., 0]
        inside = (lam >= 0).all(1) & (lam.sum(1) <= 1)
        if inside.any():
            raise ValueError(
                f"obstacle {i} ({kind}) intersects the body at the rest shape: its interior "
                f"point {_describe(p)} lies in cell {int(np.argmax(inside))}. Move the "
                "obstacle or the mesh so they start apart"
            )
