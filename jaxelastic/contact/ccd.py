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


# ---------------------------------------------------------------------- self-contact

ACCD_SCALE = 0.1
"""Additive CCD stops once a pair's distance has fallen to this fraction of its start
(Li et al. 2021, "Codimensional Incremental Potential Contact", Alg. 1, s = 0.1): the
returned time leaves every pair at least that fraction of its gap."""

ACCD_ITERATIONS = 64
"""Iteration cap of :func:`additive_toi` (every iterate is safe; stopping early is
conservative)."""


def additive_toi(
    dist2: Callable, xs: jax.Array, ps: jax.Array, split: int, t_max: float | jax.Array = 1.0
):
    """Additive CCD (Li et al. 2021, "Codimensional IPC", ACM TOG 40(4), Alg. 1): a
    lower bound of the time of impact of one primitive pair moving along ``xs + τ ps``.

    The relative motion is bounded by ``l_p = max_{i<split} ‖p̄_i‖ + max_{i≥split} ‖p̄_i‖``
    with ``p̄ = p − mean(p)`` (the pair's distance shrinks at most at rate l_p), so
    advancing τ by ``0.9 d(τ)/l_p`` can never cross; it stops once ``d`` falls below
    ``ACCD_SCALE·d(0)``.

    Args:
        dist2: ``xs (q, dim) -> ()`` squared distance of the pair [m²].
        xs, ps: ``(q, dim)`` positions and step [m] (rows ``< split``: one primitive).
        split: 1 for point–triangle / point–edge, 2 for edge–edge.
        t_max: the end of the step (τ beyond it is not needed).

    Returns:
        τ ``()`` ∈ [0, t_max]: ``t_max`` when the pair cannot meet within the step.
    """
    p = ps - jnp.mean(ps, axis=0, keepdims=True)
    n = safe_norm(p)
    lp = jnp.max(n[:split]) + jnp.max(n[split:])
    tiny = jnp.finfo(xs.dtype).tiny
    d0 = jnp.sqrt(jnp.maximum(dist2(xs), 0.0))
    g = ACCD_SCALE * d0
    t_max = jnp.asarray(t_max, xs.dtype)

    def cond(c):
        t, tl, k, done = c
        return (~done) & (k < ACCD_ITERATIONS)

    def body(c):
        t, tl, k, _ = c
        d = jnp.sqrt(jnp.maximum(dist2(xs + (t + tl) * p), 0.0))
        hit = (t > 0) & (d < g)  # the last advance brought it too close: keep t
        t_new = jnp.where(hit, t, t + tl)
        over = t_new >= t_max
        tl_new = 0.9 * d / jnp.maximum(lp, tiny)
        return (jnp.minimum(t_new, t_max), tl_new, k + 1, hit | over)

    moving = lp > 0
    tl0 = (1.0 - ACCD_SCALE) * d0 / jnp.maximum(lp, tiny)
    c0 = (jnp.zeros((), xs.dtype), tl0, jnp.asarray(0, jnp.int32), ~moving | (d0 <= 0))
    t, _, _, _ = jax.lax.while_loop(cond, body, c0)
    return jnp.where(moving, jnp.where(d0 > 0, t, 0.0), t_max)


def motion_toi(u: jax.Array, p: jax.Array, margin) -> jax.Array:
    """The largest τ with ``‖u_a + τ p_a‖ ≤ margin`` for every row a (``u``, ``p``:
    ``(m, dim)`` [m]; ``u`` the displacement since the broad phase, ``‖u_a‖ ≤ margin``):
    the motion bound that keeps the self-contact candidate list complete."""
    pp = jnp.sum(p * p, axis=-1)
    up = jnp.sum(u * p, axis=-1)
    uu = jnp.sum(u * u, axis=-1)
    disc = jnp.maximum(up * up - pp * (uu - margin * margin), 0.0)
    ok = pp > 0
    tau = jnp.where(ok, (-up + jnp.sqrt(disc)) / jnp.where(ok, pp, 1.0), jnp.inf)
    return jnp.maximum(jnp.min(tau), 0.0)
