"""The Levenberg–Marquardt safeguard of the Newton loop: a shift ``λ`` of the Hessian.

Plain Newton solves ``H Δ = −g`` and backtracks along Δ. Where H is nearly singular along
a curved valley (a body that may rotate almost freely: the linearised rotation overshoots,
the line search cuts the step back, the next step overshoots the other way) it stalls:
the residual oscillates and the loop ends with MAX_STEPS. The safeguard (on with
``Newton(regularize=True)``, the default) solves ``(H + λI) Δ = −g`` instead, which
shortens the step and turns it towards steepest descent (Levenberg 1944; Marquardt 1963;
Nocedal & Wright, *Numerical Optimization*, 2nd ed., §10.3 and algorithm 4.1 for the
ratio test):

* λ = 0 (plain Newton, the fast path) until the loop misbehaves: a line search that finds
  no acceptable step, or :data:`PATIENCE` iterations without a new smallest residual
  with the Dirichlet dofs in place (:func:`progress`).
  λ then starts at the stiffness the failed step saw, ``σ = ‖g_f‖/‖Δ_f‖`` [force/length]
  (for ``H Δ = −g`` a Rayleigh-quotient-like value between H's extreme eigenvalues), and
  a failed line search does not end the solve but is retried with the larger shift, at
  most :data:`RESCUES` times in a row;
* while λ > 0, the ratio ``ρ`` of the actual decrease of Π to the decrease the shifted
  quadratic model predicts, ``m = −gᵀΔ − ½ΔᵀHΔ = −½gᵀΔ + ½λ‖Δ‖²`` (from
  ``(H + λI)Δ = −g``; no extra product), adapts it: a full step with ``ρ > RHO_GOOD``
  (or Π below its round-off, where ρ is noise) divides λ by :data:`DOWN`; a cut-back or
  failed step, or ``ρ < RHO_BAD``, multiplies it by :data:`UP` (at least σ);
* once λ falls below :data:`OFF` times σ it is 0 again: plain Newton, whose quadratic
  convergence near a solution is not delayed.

The shift enters the Newton system as a diagonal like the lumped mass (:func:`shifted`),
so every linear solver — direct, CG and matrix-free CG (the operator ``H + λI``), AMG,
multilevel — and the projected retry solve the shifted system without a change of their
own. ``stats["regularized"]`` counts the iterations solved with λ > 0.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ...mechanics import potential as pot_mod
from ...mechanics.potential import Potential

__all__ = [
    "shifted",
    "Shift",
    "adapt",
    "progress",
    "PATIENCE",
    "RESCUES",
    "UP",
    "DOWN",
    "OFF",
    "RHO_GOOD",
    "RHO_BAD",
]

PATIENCE = 8
"""Iterations without a new smallest free residual after which the shift starts. Plain
Newton far from a solution may raise the residual for a few iterations while Π falls
(measured: 2–4 on the untangling starts of the robustness tests before they converge)."""

RESCUES = 6
"""Failed line searches retried with a larger shift in a row before the solve stops with
LINE_SEARCH_FAILED (λ grows by :data:`UP` each: 4⁶ ≈ 4000 σ, where the step is a short
steepest-descent step that only a Π without a decrease, e.g. pure round-off, rejects)."""

UP = 4.0
"""Factor on λ after a rejected, cut-back or poorly predicted step."""

DOWN = 3.0
"""Divisor of λ after a full step the model predicted well."""

OFF = 1e-3
"""λ below this fraction of the step's stiffness σ is set to 0 (plain Newton)."""

RHO_GOOD = 0.75
"""A full step whose actual decrease exceeds this fraction of the predicted one lowers λ."""

RHO_BAD = 0.25
"""A step whose actual decrease is below this fraction of the predicted one raises λ."""


def shifted(pot: Potential, lam) -> Potential:
    """``pot`` whose lumped-mass diagonal (:func:`~jaxelastic.mechanics.potential.mass_diagonal`)
    is raised by ``lam`` [force/length] on every node: its Hessian is ``H + λI``.

    Only for building the Newton system (its energy and gradient are not Π's): the inertia
    and mass-damping weights are folded into one mass with weight 1. Traceable; ``lam``: a
    scalar of the mesh's dtype (0 on the fast path: the same compiled solve).
    """
    X = pot.mesh.points
    md = pot_mod.mass_diagonal(pot)
    base = jnp.zeros(X.shape[:1], X.dtype) if md is None else md
    return pot.replace(
        mass=base + lam,
        inertia_weight=jnp.ones((), X.dtype),
        x_tilde=X if pot.x_tilde is None else pot.x_tilde,
        mass_damping=None,
    )


def progress(best, since, rn, placed):
    """``(best, since)`` after an iterate with free residual ``rn``: the smallest free
    residual with the Dirichlet dofs in place (``placed``) and the iterations since it was
    set. While a boundary motion is still being applied the residual may grow by design:
    both restart (``+inf``, 0). Plain Newton counts as stalled at ``since ≥``
    :data:`PATIENCE`."""
    better = rn < best
    best = jnp.where(placed, jnp.where(better, rn, best), jnp.inf).astype(best.dtype)
    since = jnp.where(placed & ~better, since + 1, 0).astype(jnp.int32)
    return best, since


class Shift(NamedTuple):
    """The shift's next value and what it decided (all arrays).

    Attributes:
        lam: λ for the next iteration [force/length]; rescue: a failed line search is
            retried (the solve keeps running); fails: failed line searches in a row.
    """

    lam: jax.Array
    rescue: jax.Array
    fails: jax.Array


def adapt(
    lam, fails, engaged, *, g_free, d_free, alpha, accepted, e0, e1, near, stall, projected
) -> Shift:
    """The shift after one iteration solved with ``lam``.

    Args:
        lam: this iteration's λ; fails: failed line searches in a row before it;
            engaged: whether a shift was used before in this solve (then a poor plain
            Newton step restarts it at once).
        g_free, d_free: ``(n_nodes, dim)`` the gradient and the step on the free dofs.
        alpha: the step length accepted (meaningless when not ``accepted``).
        e0, e1: Π before and at the accepted step; near: Π's round-off hides the decrease
            (:data:`~jaxelastic.solvers.newton.iteration.NEAR_EPS`).
        stall: plain Newton stalled (:func:`progress`).
        projected: the step was solved on PSD-projected element Hessians (the shifted
            exact Hessian was not positive definite: λ is below its most negative
            eigenvalue, and the projection's stiffer model would crawl along a valley).
    """
    dtype = g_free.dtype
    tiny = jnp.finfo(dtype).tiny
    gd = jnp.sum(g_free * d_free)
    dd = jnp.sum(d_free * d_free)
    sigma = jnp.sqrt(jnp.sum(g_free * g_free) / jnp.maximum(dd, tiny))
    predicted = -0.5 * gd + 0.5 * lam * dd
    rho = (e0 - e1) / jnp.maximum(predicted, tiny)
    full = accepted & (alpha == 1.0)
    good = full & (near | (rho > RHO_GOOD))
    bad = ~accepted | (alpha < 1.0) | (~near & (rho < RHO_BAD)) | projected
    raised = jnp.maximum(UP * lam, sigma)
    active = jnp.where(bad, raised, jnp.where(good, lam / DOWN, lam))
    active = jnp.where(active < OFF * sigma, 0.0, active)
    start = ~accepted | stall | (engaged & bad)  # plain Newton misbehaved: start at σ
    new = jnp.where(lam > 0, active, jnp.where(start, sigma, 0.0))
    new = jnp.where(jnp.isfinite(new), new, 0.0).astype(dtype)
    fails = jnp.where(accepted, 0, fails + 1).astype(jnp.int32)
    rescue = ~accepted & (new > 0) & (fails <= RESCUES)
    return Shift(lam=new, rescue=rescue, fails=fails)
