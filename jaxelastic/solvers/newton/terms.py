"""The term protocol: how a potential term other than elasticity takes part in the loop.

A term listed by :func:`~jaxelastic.potential.loop_terms` (today the contact term,
:class:`~jaxelastic.contact.Contact`) may

* bound a step: ``step_bound(x, step) -> α₀`` (the line search starts at ``min(1, α₀)``);
* be refreshed on the host between iterations: ``refreshed(x, step) -> term`` (a new
  broad phase for the coming step; only the Python loop can call it, so under ``jit`` a
  term must stay valid along the whole solve — contact's motion bound does that);
* adapt a stiffness inside the solve: ``adapt_init(x, max_factor) -> state | None``,
  ``adapt(state, x) -> (state, changed)``, ``adapted(state) -> term`` and
  ``stats(state) -> dict`` (IPC's κ), and ``solved(stats) -> term`` (the term a finished
  solve converged on).

The Newton driver only calls these functions, never a term by name.
"""

from __future__ import annotations

import jax.numpy as jnp

from ...mechanics import potential as pot_mod
from ...mechanics.potential import Potential

__all__ = [
    "init_states",
    "with_states",
    "step_bound",
    "refreshed",
    "adapt",
    "stats",
    "solved_potential",
    "needs_host_refresh",
]


def init_states(max_factor: float, pot: Potential, x0) -> dict:
    """The adaptation states of the terms that adapt (``max_factor > 1``), by name."""
    if not max_factor > 1:
        return {}
    out = {}
    for name, t in pot_mod.loop_terms(pot).items():
        st = t.adapt_init(x0, max_factor)
        if st is not None:
            out[name] = st
    return out


def with_states(pot: Potential, states: dict) -> Potential:
    """``pot`` with its adapting terms at the given states."""
    if not states:
        return pot
    terms = pot_mod.loop_terms(pot)
    return pot_mod.with_loop_terms(pot, {n: terms[n].adapted(st) for n, st in states.items()})


def step_bound(pot: Potential, x, step):
    """The largest safe fraction of ``step`` ``(n_nodes, dim)`` allowed by every term
    (``inf`` without one)."""
    a = jnp.asarray(jnp.inf, x.dtype)
    for t in pot_mod.loop_terms(pot).values():
        a = jnp.minimum(a, t.step_bound(x, step))
    return a


def needs_host_refresh(pot: Potential) -> bool:
    """Whether a term wants a host refresh between iterations (the Python loop)."""
    return any(getattr(t, "host_refresh", False) for t in pot_mod.loop_terms(pot).values())


def refreshed(pot: Potential, x, step=None) -> Potential:
    """(host) ``pot`` with every term refreshed for the coming ``step`` from ``x``."""
    terms = pot_mod.loop_terms(pot)
    return pot_mod.with_loop_terms(pot, {n: t.refreshed(x, step) for n, t in terms.items()})


def adapt(pot: Potential, states: dict, x) -> tuple[dict, jnp.ndarray]:
    """``(new states, whether any changed)`` after one accepted iterate ``x``."""
    terms = pot_mod.loop_terms(pot)
    changed = jnp.asarray(False)
    new = {}
    for n, st in states.items():
        new[n], c = terms[n].adapt(st, x)
        changed = changed | c
    return new, changed


def stats(pot: Potential, states: dict) -> dict:
    """The statistics the adapting terms report in a solution (e.g. ``kappa``)."""
    terms = pot_mod.loop_terms(pot)
    out = {}
    for n, st in states.items():
        out.update(terms[n].adapt_stats(st))
    return out


def solved_potential(pot: Potential, res) -> Potential:
    """The potential a solve ``res`` of ``pot`` converged on: its adapting terms at the
    stiffness the solve ended with (``res.stats``; the ratio to the starting one is a
    constant, so derivatives with respect to the stiffness pass through). Unchanged where
    nothing adapted."""
    terms = pot_mod.loop_terms(pot)
    return pot_mod.with_loop_terms(pot, {n: t.solved(res.stats) for n, t in terms.items()})
