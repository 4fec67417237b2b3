"""The Newton loop's state: :class:`NewtonState`, :func:`init`, :func:`terminate` and the
:class:`~jaxelastic.solvers.results.Solution` of a finished state."""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from ...loads import Dirichlet
from ...mechanics.kinematics import deformation_extremes
from ...mechanics.potential import Potential
from ..results import RUNNING, Solution, Status
from . import terms
from .iteration import min_J, norm, status_of, value_and_grad
from .settings import Newton

__all__ = [
    "NewtonState",
    "init",
    "terminate",
    "solution",
    "body_length",
    "defined_inverted",
    "FLOOR_REFERENCE",
]


class NewtonState(NamedTuple):
    """Everything the Newton loop carries between iterations (a pytree).

    Attributes:
        x: ``(n_nodes, dim)`` the current iterate; g: ``(n_nodes, dim)`` ∇Π there;
        energy: Π(x) (``+inf`` where undefined).
        k: iterations done; status: int32, ``RUNNING`` (−1) or a
            :class:`~jaxelastic.solvers.results.Status`.
        ref: the residual's reference scale (largest free residual, ‖f_ext‖, reaction on
            the prescribed dofs at ``x0`` or Dirichlet right-hand side seen) [force].
        hist: ``(max_steps + 1,)`` free residual norms; lin_hist: ``(max_steps,)`` linear
            iterations; alpha_hist: ``(max_steps,)`` accepted step lengths (NaN: none).
        cuts: line-search halvings; neg: negative-curvature linear solves; short: linear
            solves that stopped short of their tolerance (iteration cap, stagnation or a
            non-finite result: the step was the solver's best iterate); proj: projected
            retries; floor: the residual's round-off floor at the last iterate.
        lam: the Levenberg–Marquardt shift of the next iteration [force/length] (0: plain
            Newton; :mod:`~jaxelastic.solvers.newton.levenberg`); reg: iterations solved
            with a shift; fails: failed line searches in a row; best, since: the smallest
            free residual with the Dirichlet dofs in place and the iterations since
            (:func:`~jaxelastic.solvers.newton.levenberg.progress`).
        terms: adaptation states of the potential's terms, by name
            (:mod:`~jaxelastic.solvers.newton.terms`).
    """

    x: jax.Array
    g: jax.Array
    energy: jax.Array
    k: jax.Array
    status: jax.Array
    ref: jax.Array
    hist: jax.Array
    lin_hist: jax.Array
    alpha_hist: jax.Array
    cuts: jax.Array
    neg: jax.Array
    short: jax.Array
    proj: jax.Array
    floor: jax.Array
    lam: jax.Array
    reg: jax.Array
    fails: jax.Array
    best: jax.Array
    since: jax.Array
    terms: Any


def init(s: Newton, pot: Potential, bc: Dirichlet, x0) -> NewtonState:
    """The state before the first iteration from ``x0`` ``(n_nodes, dim)`` (traceable)."""
    mask, dtype = bc.mask, x0.dtype
    fm = (~mask).astype(dtype)
    ts = terms.init_states(s.kappa_max_factor, pot, x0)
    e0, g0 = value_and_grad(s, terms.with_states(pot, ts), x0)
    rn0 = norm(g0 * fm)
    dn0 = norm(jnp.where(mask, bc.values - x0, 0.0))
    ref0 = norm(pot.f_ext * fm) if pot.f_ext is not None else jnp.zeros((), dtype)
    # the reaction on the prescribed dofs is the load a displacement-driven body carries:
    # a warm start (a nearby solution) is converged relative to it, as a solve from rest
    # is, not relative to its own small residual
    ref = jnp.maximum(jnp.maximum(ref0, norm(g0 * (1.0 - fm))), rn0)
    st0 = status_of(s, rn0, dn0, ref, 0)
    inverted = jnp.where(min_J(pot, x0) <= 0, Status.INVERTED, Status.NONFINITE)
    st0 = jnp.where(jnp.isfinite(e0), st0, inverted)
    zero = jnp.asarray(0, jnp.int32)
    return NewtonState(
        x=x0,
        g=g0,
        energy=e0,
        k=zero,
        status=st0.astype(jnp.int32),
        ref=ref,
        hist=jnp.full((s.max_steps + 1,), jnp.nan, dtype).at[0].set(rn0),
        lin_hist=jnp.zeros((s.max_steps,), jnp.int32),
        alpha_hist=jnp.full((s.max_steps,), jnp.nan, dtype),
        cuts=zero,
        neg=zero,
        short=zero,
        proj=zero,
        floor=jnp.zeros((), dtype),
        lam=jnp.zeros((), dtype),
        reg=zero,
        fails=zero,
        best=jnp.where(dn0 == 0, rn0, jnp.inf).astype(dtype),
        since=zero,
        terms=ts,
    )


def terminate(state: NewtonState) -> jax.Array:
    """Whether the loop stops (bool array): the status is no longer ``RUNNING``."""
    return state.status != RUNNING


def body_length(pot: Potential) -> jax.Array:
    """Diagonal of the rest bounding box [length] (the scale of ``Newton.xtol``)."""
    X = pot.mesh.points
    return jnp.sqrt(jnp.sum((jnp.max(X, axis=0) - jnp.min(X, axis=0)) ** 2))


FLOOR_REFERENCE = 100.0
"""``stats["floor_limited"]`` is only set where the residual's reference force exceeds
this multiple of the round-off floor: below it the solve had nothing to resolve (an
unloaded or freely moving body), and no relative tolerance was meaningful."""


def defined_inverted(psi) -> bool:
    """Whether ψ is marked finite and meaningful at J ≤ 0 (``psi.defined_inverted = True``:
    the built-in linear, StVK, corotated, fixed corotated, ARAP and stable neo-Hookean
    laws; static)."""
    return getattr(psi, "defined_inverted", False) is True


def solution(pot: Potential, state: NewtonState, s: Newton | None = None) -> Solution:
    """The :class:`~jaxelastic.solvers.results.Solution` of a finished state.

    Besides the loop's counters, ``stats`` holds the state's most deformed cells
    (:func:`~jaxelastic.mechanics.kinematics.deformation_extremes`: ``min_J``,
    ``min_J_cell``, ``max_strain``, ``max_strain_cell``) and, with the settings ``s``,
    the tolerance the residual had to meet (``tolerance`` = max(atol, rtol·ref)
    [force]), the residual's reference ``residual_reference`` [force], the relative
    residual reached (``achieved_rtol`` = residual / ref) and ``floor_limited`` (True:
    SUCCESS at the round-off floor above the requested tolerance). A SUCCESS whose
    state has a cell at J ≤ 0 becomes ``Status.INVERTED`` unless ψ is
    :func:`defined_inverted`.
    """
    res = state.hist[state.k]
    ext = deformation_extremes(state.x, pot.mesh)
    status = state.status
    if not defined_inverted(pot.psi):
        inverted = (status == Status.SUCCESS) & ~(ext.min_J > 0)
        status = jnp.where(inverted, Status.INVERTED, status).astype(jnp.int32)
    stats = dict(
        steps=state.k,
        linear_iterations=jnp.sum(state.lin_hist),
        residual=res,
        energy=state.energy,
        residual_history=state.hist,
        linear_history=state.lin_hist,
        step_history=state.alpha_hist,
        line_search_cutbacks=state.cuts,
        negative_curvature=state.neg,
        linear_unconverged=state.short,
        projected=state.proj,
        regularized=state.reg,
        residual_floor=state.floor,
        residual_reference=state.ref,
        achieved_rtol=res / jnp.maximum(state.ref, jnp.finfo(state.ref.dtype).tiny),
        min_J=ext.min_J,
        min_J_cell=ext.min_J_cell,
        max_strain=ext.max_strain,
        max_strain_cell=ext.max_strain_cell,
        wall_time=jnp.asarray(jnp.nan, state.x.dtype),
    )
    if s is not None:
        tol = jnp.maximum(jnp.asarray(s.atol, res.dtype), s.rtol * state.ref)
        stats["tolerance"] = tol
        # (a reference force itself near round-off, e.g. an unloaded body, asks nothing)
        meaningful = state.ref > FLOOR_REFERENCE * state.floor
        stats["floor_limited"] = (status == Status.SUCCESS) & (res > tol) & meaningful
    stats.update(terms.stats(pot, state.terms))
    return Solution(x=state.x, status=status, stats=stats)
