"""IPC's smoothly clamped log barrier and the choice of its stiffness κ and reach d̂.

``b(d; d̂) = −(d − d̂)² ln(d/d̂)`` for ``0 < d < d̂``, 0 for ``d ≥ d̂`` and +∞ for ``d ≤ 0``
(Li et al. 2020, "Incremental Potential Contact", ACM TOG 39(4), eq. 6). It is C² at
``d = d̂`` (b = b' = b'' = 0 there), b' < 0 and b'' > 0 on ``(0, d̂)``; here d is the
unsquared signed distance of a node to an obstacle, so b has units [m²] and the contact
energy ``κ Σ b`` needs κ in [N/m] — a stiffness, which :func:`kappa_from_stiffness`
takes from the elastic Hessian (IPC §4.3 balances the barrier against the elasticity;
here κ equals the mean diagonal node stiffness of the elastic + inertia Hessian, so the
barrier's curvature at ``d = d̂/2``, 6.4 κ, is of the order of the body's own).
:func:`adapt_kappa` doubles κ when a gap gets too small (IPC's adaptive κ update, between
steps); :func:`kappa_update` is the same rule inside a Newton solve, applied by
:class:`~jaxelastic.solvers.newton.Newton` after every iteration (IPC's rule as in the
ipc-toolkit's ``update_barrier_stiffness``: double κ while the smallest gap is below the
threshold and still shrinking between consecutive iterates, at most to
``KAPPA_MAX_FACTOR`` × the starting κ).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = [
    "barrier",
    "barrier_d1",
    "barrier_d2",
    "DHAT_REL",
    "DHAT_MAX_REL",
    "default_dhat",
    "kappa_from_stiffness",
    "adapt_kappa",
    "SMALL_GAP",
    "KAPPA_MAX_FACTOR",
    "kappa_update",
]

DHAT_REL = 1e-3
"""Default barrier reach d̂ relative to the body's size (:func:`default_dhat`)."""

DHAT_MAX_REL = 0.1
"""The largest d̂ accepted, relative to the body's size: a reach beyond it pushes the
obstacle's force across a large part of the body (and ends in MAX_STEPS)."""

SMALL_GAP = 1e-2
""":func:`adapt_kappa` doubles κ once the smallest gap falls below this fraction of d̂."""

KAPPA_MAX_FACTOR = 100.0
"""Default bound of the in-solve κ adaptation (:func:`kappa_update`): κ ≤ 100 × its
starting value (as IPC's ``κ_max = 100 κ_min``: ipc-toolkit ``initial_barrier_stiffness``)."""


def _inside(d, dhat):
    inside = (d > 0) & (d < dhat)
    return inside, jnp.where(inside, d, dhat)  # a safe d for the log's branch


def barrier(d: jax.Array, dhat) -> jax.Array:
    """``b(d; d̂)`` [m²] elementwise: +inf for d ≤ 0, 0 for d ≥ d̂ (any shape)."""
    inside, ds = _inside(d, dhat)
    b = jnp.where(inside, -((ds - dhat) ** 2) * jnp.log(ds / dhat), 0.0)
    return jnp.where(d <= 0, jnp.inf, b)


def barrier_d1(d: jax.Array, dhat) -> jax.Array:
    """``b'(d)`` [m] (analytic; ≤ 0): ``−2(d − d̂) ln(d/d̂) − (d − d̂)²/d`` on (0, d̂)."""
    inside, ds = _inside(d, dhat)
    return jnp.where(inside, -2 * (ds - dhat) * jnp.log(ds / dhat) - (ds - dhat) ** 2 / ds, 0.0)


def barrier_d2(d: jax.Array, dhat) -> jax.Array:
    """``b''(d)`` [1] (analytic; ≥ 0): ``−2 ln(d/d̂) − 4(d − d̂)/d + (d − d̂)²/d²``."""
    inside, ds = _inside(d, dhat)
    r = (ds - dhat) / ds
    return jnp.where(inside, -2 * jnp.log(ds / dhat) - 4 * r + r * r, 0.0)


def default_dhat(points: jax.Array, rel: float = DHAT_REL) -> jax.Array:
    """``rel`` × the body's size ``2·max‖X − X̄‖`` of ``points`` ``(n, dim)`` [m] (X̄ their
    mean): rotation invariant, and the bounding-box diagonal of a box centred on its mean
    (a rotated block gets the d̂ of the unrotated one)."""
    c = jnp.mean(points, axis=0, keepdims=True)  # (1, dim)
    return rel * 2.0 * jnp.sqrt(jnp.max(jnp.sum((points - c) ** 2, axis=1)))


def kappa_from_stiffness(node_blocks: jax.Array, nodes: jax.Array) -> jax.Array:
    """κ [N/m]: the mean diagonal entry of the ``(n_nodes, dim, dim)`` Hessian node blocks
    over the contact ``nodes`` (IPC §4.3-style balance of barrier and elasticity).

    With ``n`` the mean, the barrier's normal stiffness ``κ b''(d)`` equals the body's node
    stiffness at ``d ≈ 0.6 d̂`` and grows like ``κ d̂²/d²`` closer in.
    """
    # the mean diagonal entry as trace/dim: the same for PSD blocks, and rotation invariant
    tr = jnp.abs(jnp.trace(node_blocks[nodes], axis1=1, axis2=2))  # (m,)
    return jnp.mean(tr) / node_blocks.shape[-1]


def adapt_kappa(kappa, min_gap, dhat, max_kappa=None):
    """κ doubled when ``0 < min_gap < SMALL_GAP·d̂`` (IPC's adaptive update; capped at
    ``max_kappa`` if given), else unchanged. Scalars; jit-able."""
    small = (min_gap > 0) & (min_gap < SMALL_GAP * dhat)
    k2 = 2.0 * kappa if max_kappa is None else jnp.minimum(2.0 * kappa, max_kappa)
    return jnp.where(small, k2, kappa)


def kappa_update(kappa, kappa_max, gap, prev_gap, dhat):
    """IPC's adaptive barrier stiffness inside a solve (Li et al. 2020 §4.3 and
    supplementary; ipc-toolkit ``update_barrier_stiffness``): ``min(2κ, κ_max)`` when the
    smallest gap is below ``SMALL_GAP·d̂`` at this iterate *and* the previous one and still
    shrinking (``0 < gap < prev_gap``), else κ.

    A gap that keeps closing means the barrier is too soft for the load it carries: the
    iterates approach d = 0, where b'' ~ d̂²/d² makes Newton's system ill-conditioned and
    the contact force inaccurate; doubling κ moves the equilibrium gap out by about the
    same factor. Bounded, so a solve changes κ at most ``log2(κ_max/κ)`` times.

    Args:
        kappa, kappa_max: ``()`` current and largest stiffness [N/m]; gap, prev_gap: ``()``
            smallest node–obstacle distance now and at the previous iterate [m]; dhat: d̂ [m].

    Returns:
        ``()`` the new κ [N/m] (jit-able).
    """
    thr = SMALL_GAP * dhat
    closing = (gap > 0) & (gap < thr) & (prev_gap < thr) & (gap < prev_gap)
    return jnp.where(closing, jnp.minimum(2.0 * kappa, jnp.maximum(kappa_max, kappa)), kappa)
