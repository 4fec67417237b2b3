"""Continuous collision detection against obstacles: the largest safe Newton step.

IPC's line search (Li et al. 2020, "Incremental Potential Contact", ACM TOG 39(4), §4.4)
starts every backtracking search at a step that keeps every iterate intersection-free:
``α₀ = min(1, s · τ*)`` where τ* is the earliest time of impact of any contact node moving
along its Newton step and ``s = SAFETY = 0.8`` leaves part of the gap (the barrier, +∞ at
d ≤ 0, rejects anything the CCD would miss). For obstacles the time of impact of a node is
analytic (plane, sphere, box: a ray intersection) or a conservative-advancement lower
bound (capsule, user SDFs: each iterate advances by the current distance, safe for a
1-Lipschitz signed distance).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp

__all__ = ["SAFETY", "CA_ITERATIONS", "safe_norm", "conservative_toi", "ccd_step"]

SAFETY = 0.8
"""Fraction of the time of impact taken as the initial line-search step (IPC's 0.8)."""

CA_ITERATIONS = 24
"""Conservative-advancement iterations of :func:`conservative_toi` (each one is safe)."""


def safe_norm(v: jax.Array) -> jax.Array:
    """‖v‖ over the last axis with a finite (zero) derivative at v = 0."""
    s = jnp.sum(v * v, axis=-1)
    ok = s > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, s, 1.0)), 0.0)


def conservative_toi(dist: Callable, x: jax.Array, p: jax.Array, limit: float = 2.0):
    """Lower bound of the time of impact along ``x + τ p`` by conservative advancement.

    Each iterate advances by ``d(x + τp)/‖p‖``, safe for any SDF with ‖∇d‖ ≤ 1 (a true
    Euclidean signed distance): the returned τ never passes the surface.

    Args:
        dist: ``x (dim,) -> ()`` signed distance [m]; x, p: ``(dim,)`` point and step [m].
        limit: stop once τ exceeds this (the step is then unrestricted).

    Returns:
        τ ``()`` [fraction of p]: +inf if the advance passes ``limit``; 0 if the point
        starts inside.
    """
    pn = safe_norm(p)
    tiny = jnp.finfo(x.dtype).tiny

    def body(_, tau):
        d = dist(x + tau * p)
        return jnp.where(tau > limit, tau, tau + jnp.maximum(d, 0.0) / jnp.maximum(pn, tiny))

    tau = jax.lax.fori_loop(0, CA_ITERATIONS, body, jnp.zeros((), x.dtype))
    return jnp.where((pn == 0) | (tau > limit), jnp.inf, tau)


def ccd_step(obstacles: Sequence, xn: jax.Array, pn: jax.Array, t) -> jax.Array:
    """The largest initial line-search step ``α₀ ∈ (0, 1]`` keeping every node outside
    every obstacle: ``min(1, SAFETY · min_{a,o} τ_o(x_a, p_a))``.

    Args:
        obstacles: the obstacles (each with ``toi(x, p, t)``); xn: ``(m, dim)`` contact-node
            positions [m]; pn: ``(m, dim)`` their Newton step [m]; t: obstacle time [s].

    Returns:
        α₀ ``()``; a node already touching (τ = 0) gives a tiny but positive step, which
        the backtracking line search then treats as a failure (no +∞ energy is accepted).
    """
    alpha = jnp.ones((), xn.dtype)
    for ob in obstacles:
        tau = jax.vmap(lambda x, p, ob=ob: ob.toi(x, p, t))(xn, pn)  # (m,)
        alpha = jnp.minimum(alpha, SAFETY * jnp.min(tau))
    return jnp.maximum(alpha, jnp.finfo(xn.dtype).tiny)
