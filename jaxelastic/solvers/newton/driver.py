"""The one Newton loop: :func:`step` on a :class:`~.state.NewtonState` and :func:`minimize`.

One iteration is three pieces — :func:`prepare` (element Hessians, the Newton operator and
right-hand side), the linear solve with its projected retry (:func:`linear_step`, the only
piece that differs between the two ways the loop runs) and :func:`finish` (direction,
line search, status, adaptation of the potential's terms). :func:`minimize` runs the loop

* under ``lax.while_loop`` when its inputs are traced (inside ``jit``/``vmap``; host
  linear solvers are then ``jax.pure_callback`` calls), or when they are concrete and
  nothing needs the host: the whole loop is then one compiled program (:func:`solve_jit`);
* as a Python loop over the compiled pieces when they are concrete and the linear solve
  runs on the host (:class:`~jaxelastic.solvers.linear.Direct`,
  :class:`~jaxelastic.solvers.linear.AMG`) or a term wants a host refresh between
  iterations (the self-contact broad phase). Where the Newton operator is the assembled
  element matrix the host solve is a plain Python call on data the device assembled, so
  no compiled piece holds a callback and all of them go to JAX's persistent compilation
  cache; the freed heap is returned to the OS after large steps.

Both run the same functions in the same order, so they give the same iterates; which one
runs depends only on whether the inputs are concrete — not on whether the solve is
differentiated (:func:`jaxelastic.solve` solves on ``lax.stop_gradient`` of its inputs,
which are concrete under an eager ``jax.grad``).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.core import Tracer

from ...loads import Dirichlet
from ...mechanics import potential as pot_mod
from ...mechanics.potential import Potential
from ...mechanics.pressure import is_conservative
from ..host.heap import release_free_memory
from ..linear import LinearState, NewtonSystem, assemble_upper, newton_system
from ..linear.system import operator_is_assembled
from ..results import RUNNING, Solution, Status
from . import levenberg, terms
from .iteration import (
    STALL,
    Correction,
    descent,
    energy_scale,
    exact_tangent,
    is_quadratic,
    line_search,
    near_tol,
    newton_rhs,
    norm,
    residual_floor,
    status_of,
    value_and_grad,
)
from .retry import projected_upper, with_retry
from .settings import Newton
from .state import NewtonState, body_length, init, solution, terminate

__all__ = [
    "Prepared",
    "prepare",
    "linear_step",
    "finish",
    "step",
    "minimize",
    "solve_jit",
    "runs_on_host",
    "TRIM_BYTES",
]


class Prepared(NamedTuple):
    """The linear system of one iteration: ``system`` and ``K_ff Δ_f = rhs`` to ``tol``;
    ``dD``: the Dirichlet part of the step; ``bn``: ‖rhs‖."""

    system: NewtonSystem
    dD: jax.Array
    rhs: jax.Array
    tol: jax.Array
    bn: jax.Array


def _traced(*trees) -> bool:
    return any(isinstance(a, Tracer) for t in trees for a in jax.tree_util.tree_leaves(t))


def prepare(s: Newton, pot: Potential, bc: Dirichlet, state: NewtonState, Ke=None, pair_h=None):
    """The Newton operator at ``state.x`` and the step's right-hand side (``pot``: with
    its terms at ``state.terms``; ``Ke``/``pair_h``: already computed at ``state.x``)."""
    x = state.x
    need = s.linear.needs_element_hessians
    sp = _shifted(s, pot, state.lam)
    exact = exact_tangent(s, pot)
    system = newton_system(
        sp, x, ~bc.mask, hessian=s.hessian, need_Ke=need, Ke=Ke, pair_h=pair_h, exact_tangent=exact
    )
    dD = jnp.where(bc.mask, bc.values - x, 0.0)
    rhs, tol, bn = newton_rhs(s, system, state.g, dD, state.ref)
    return Prepared(system, dD, rhs, tol, bn)


def _regularized(s: Newton, pot: Potential) -> bool:
    """Whether the Levenberg–Marquardt safeguard runs: ``s.regularize``, and a potential
    whose loads are conservative (it adapts λ by the energy's actual against predicted
    decrease; a follower load has no energy, and there its line search on the simplified
    Newton correction leads)."""
    return s.regularize and is_conservative(pot.pressure)


def _shifted(s: Newton, pot: Potential, lam) -> Potential:
    """The potential of the Newton system: its Hessian shifted by ``lam``·I
    (:func:`~.levenberg.shifted`) with the safeguard on."""
    return levenberg.shifted(pot, lam) if _regularized(s, pot) else pot


def _retry_enabled(s: Newton, system: NewtonSystem) -> bool:
    return s.hessian != "projected" and system.Ke is not None


def linear_step(s: Newton, lstate: LinearState, system: NewtonSystem, rhs, tol) -> Solution:
    """The linear solve of a Newton step inside a trace, with the projected retry (a
    non-symmetric tangent: GMRES on the true operator, without it)."""
    Ke = system.Ke
    elementwise = s.hessian != "hvp"  # system.A is the element-Hessian operator of Ke

    if not system.symmetric:  # GMRES on the true tangent: no projected retry (GMRES
        # needs no definiteness; the host factorisation of an indefinite symmetric part is
        # pivoted), a GMRES short of its tolerance says so in its status
        res = s.linear.nonsymmetric_step(lstate, system, system.A, Ke, rhs, tol, jnp.int32(0))
        res = with_retry(lambda k, token: res, rhs, traced=True, enabled=False)
        return res._replace(x=jnp.where(system.free, res.x, 0.0))

    def attempt(k, token):
        if not _retry_enabled(s, system):
            return s.linear.newton_step(lstate, system, system.A, Ke, rhs, tol, token)
        K = lax.cond(k == 0, lambda: Ke, lambda: pot_mod.projected_element_hessians(system.pot, Ke))
        if elementwise:
            A = system.operator(K)
        else:

            def A(v):
                return lax.cond(k == 0, system.A, system.operator(K), v)

        return s.linear.newton_step(lstate, system, A, K, rhs, tol, token)

    res = with_retry(attempt, rhs, traced=True, enabled=_retry_enabled(s, system))
    return res._replace(x=jnp.where(system.free, res.x, 0.0))


def finish(
    s: Newton,
    pot: Potential,
    bc: Dirichlet,
    state: NewtonState,
    length,
    prep: Prepared,
    lin,
    lstate: LinearState,
) -> NewtonState:
    """The rest of an iteration once the linear solve ``lin`` is done: direction, line
    search, new state and status, then the terms' adaptation (``lstate``: the linear
    solver's state, for the simplified Newton corrections of a non-conservative load's
    line search)."""
    x, g, k = state.x, state.g, state.k
    system = prep.system
    mask, xD = bc.mask, bc.values
    fm = (~mask).astype(x.dtype)
    d = descent(system, g, prep.dD, lin)
    near = _near_solution(pot, system, state, d)
    floor = residual_floor(pot, system, x, fm)
    correction = _follower_correction(s, lstate, pot, prep, lin, x)
    if correction is not None:  # a follower load: no energy to decrease; the line
        near = jnp.asarray(True)  # search tests the correction or the residual's decrease

    alpha, xt, et, gt, acc, cuts = line_search(
        s, pot, bc, x, g, state.energy, d, near, floor, correction
    )
    x_new = jnp.where(acc, xt, x)
    g_new = jnp.where(acc, gt, g)
    rn = norm(g_new * fm)
    dn = norm(jnp.where(mask, xD - x_new, 0.0))
    # bn = ‖g_f + K_fD Δ_D‖ is the force a Dirichlet motion induces: the reference of a
    # purely displacement-driven solve (whose free residual is 0 at the rest shape)
    ref = jnp.maximum(jnp.maximum(state.ref, rn), prep.bn)
    st = _step_status(s, pot, state, rn, dn, ref, floor, alpha, acc, d, length)
    best, since = levenberg.progress(state.best, state.since, rn, dn == 0)
    shift = levenberg.adapt(
        state.lam,
        state.fails,
        state.reg > 0,
        g_free=g * fm,
        d_free=d * fm,
        alpha=alpha,
        accepted=acc,
        e0=state.energy,
        e1=et,
        near=near,
        stall=since >= levenberg.PATIENCE,
        projected=lin.stats["projected"],
    )
    if _regularized(s, pot):  # a failed line search is retried with a larger shift
        st = jnp.where(shift.rescue & (st == Status.LINE_SEARCH_FAILED), RUNNING, st)
        st = jnp.where(shift.rescue & (k + 1 >= s.max_steps), Status.MAX_STEPS, st)
    its = lin.stats["iterations"].astype(jnp.int32)
    neg = lin.status == Status.NEGATIVE_CURVATURE
    short = (lin.status == Status.MAX_STEPS) | (lin.status == Status.NONFINITE)  # inexact
    new = state._replace(
        x=x_new,
        g=g_new,
        energy=jnp.where(acc, et, state.energy),
        k=k + 1,
        status=st.astype(jnp.int32),
        ref=ref,
        hist=state.hist.at[k + 1].set(rn),
        lin_hist=state.lin_hist.at[k].set(its),
        alpha_hist=state.alpha_hist.at[k].set(jnp.where(acc, alpha, jnp.nan)),
        cuts=state.cuts + cuts.astype(jnp.int32),
        neg=state.neg + neg.astype(jnp.int32),
        short=state.short + short.astype(jnp.int32),
        proj=state.proj + lin.stats["projected"].astype(jnp.int32),
        floor=floor,
        lam=shift.lam if _regularized(s, pot) else state.lam,
        reg=state.reg + (state.lam > 0).astype(jnp.int32),
        fails=shift.fails,
        best=best,
        since=since,
    )
    return _adapt(s, pot, new)


def _near_solution(pot: Potential, system, state: NewtonState, d):
    """Whether the predicted decrease ``|gᵀd|`` is below Π's round-off scale
    (:func:`~.iteration.near_tol`): the line search then accepts on the residual."""
    x = state.x
    escale = jnp.maximum(jnp.abs(state.energy), energy_scale(pot, x, system.Ke))
    tiny = jnp.finfo(x.dtype).tiny
    return jnp.abs(jnp.sum(state.g * d)) <= near_tol(x.dtype) * jnp.maximum(escale, tiny)


def _follower_correction(s: Newton, lstate, pot: Potential, prep: Prepared, lin, x):
    """The simplified Newton correction ``r ↦ ‖K_k⁻¹ r‖`` (solved to the step's relative
    forcing, with its forcing term η) that a follower load's line search tests, or None
    for a conservative potential (whose line search decreases the energy)."""
    if is_conservative(pot.pressure):
        return None
    tiny = jnp.finfo(x.dtype).tiny
    system = prep.system

    def simplified(r):
        tol = prep.tol / jnp.maximum(prep.bn, tiny) * norm(r)
        return norm(linear_step(s, lstate, system, -r, tol).x)

    eta = jnp.clip(lin.stats["residual"] / jnp.maximum(prep.bn, tiny), 0.0, 1.0)
    return Correction(simplified, eta.astype(x.dtype))


def _step_status(s: Newton, pot, state: NewtonState, rn, dn, ref, floor, alpha, acc, d, length):
    """The status after a step: converged (the tolerance, the round-off floor once a full
    step stalls or the potential is quadratic, or a full Newton step below ``xtol``),
    LINE_SEARCH_FAILED when no trial was accepted, else RUNNING or MAX_STEPS."""
    k = state.k
    # the floor only counts once a full step no longer reduces the residual (or the
    # potential is quadratic, where one exact step is the answer)
    stalled = ((alpha == 1.0) & (rn >= STALL * state.hist[k])) | is_quadratic(pot)
    st = status_of(s, rn, dn, ref, k + 1, jnp.where(stalled, floor, 0.0))
    # (a Newton step, not one the Levenberg-Marquardt shift shortened)
    full = acc & (alpha == 1.0) & (dn == 0) & (state.lam == 0)
    tiny_step = full & (jnp.max(jnp.abs(d)) <= s.xtol * length)
    st = jnp.where((st == RUNNING) & tiny_step & jnp.isfinite(rn), Status.SUCCESS, st)
    return jnp.where(acc, st, Status.LINE_SEARCH_FAILED)


def _adapt(s: Newton, pot: Potential, state: NewtonState) -> NewtonState:
    """The state after the terms' adaptation: a changed stiffness re-evaluates Π and its
    gradient at the accepted iterate and keeps the solve running (a status reached with
    the old stiffness does not hold for the new one)."""
    if not state.terms:
        return state
    ts, changed = terms.adapt(pot, state.terms, state.x)

    def refresh():
        return value_and_grad(s, terms.with_states(pot, ts), state.x)

    energy, g = lax.cond(changed, refresh, lambda: (state.energy, state.g))
    st = state.status
    fine = (st == RUNNING) | (st == Status.SUCCESS)
    more = changed & fine & (state.k < s.max_steps)
    st = jnp.where(more, RUNNING, st).astype(jnp.int32)
    return state._replace(terms=ts, energy=energy, g=g, status=st)


def step(
    s: Newton, lstate: LinearState, pot: Potential, bc: Dirichlet, state: NewtonState, length
) -> NewtonState:
    """One Newton iteration inside a trace (``pot``: the potential with its terms at their
    starting states)."""
    p = terms.with_states(pot, state.terms)
    prep = prepare(s, p, bc, state)
    lin = linear_step(s, lstate, prep.system, prep.rhs, prep.tol)
    return finish(s, p, bc, state, length, prep, lin, lstate)


def _traced_minimize(s: Newton, lstate: LinearState, pot: Potential, bc: Dirichlet, x0) -> Solution:
    length = body_length(pot)
    state = lax.while_loop(
        lambda st: ~terminate(st),
        lambda st: step(s, lstate, pot, bc, st, length),
        init(s, pot, bc, x0),
    )
    return solution(pot, state, s)


solve_jit = jax.jit(_traced_minimize, static_argnums=0)
"""The whole loop as one compiled program (concrete inputs, no host piece)."""


def runs_on_host(s: Newton, pot: Potential) -> bool:
    """Whether concrete inputs run the Python loop: the linear solve runs on the host or a
    term wants a host refresh between iterations."""
    return bool(s.linear.on_host) or terms.needs_host_refresh(pot)


def minimize(s: Newton, lstate: LinearState, pot: Potential, bc: Dirichlet, x0) -> Solution:
    """Minimise Π(x) subject to ``x[bc.mask] = bc.values[bc.mask]`` (not differentiated:
    :func:`jaxelastic.solve` adds the implicit derivatives).

    Args:
        s: settings with a resolved linear solver (:func:`~jaxelastic.solvers.linear.resolve`).
        lstate: that solver's state (:func:`~jaxelastic.solvers.linear.init_linear`).
        pot, bc: the problem; x0: ``(n_nodes, dim)`` initial positions.
    """
    if isinstance(s.linear, str):
        raise ValueError("minimize needs resolved linear-solver settings (use je.solve)")
    if _traced(pot, bc, x0, lstate):
        return _traced_minimize(s, lstate, pot, bc, x0)
    if not runs_on_host(s, pot):
        return solve_jit(s, lstate, pot, bc, x0)
    return _python_loop(s, lstate, pot, bc, x0)


# -- the compiled pieces of the Python loop --------------------------------------------------


@functools.partial(jax.jit, static_argnums=0)
def _loop_start(s: Newton, pot: Potential, bc: Dirichlet, x0):
    return init(s, pot, bc, x0), body_length(pot)


@functools.partial(jax.jit, static_argnums=0)
def _loop_prepare(s: Newton, pot: Potential, bc: Dirichlet, state: NewtonState):
    p = terms.with_states(pot, state.terms)
    # coupling data (self-contact pair Hessians): computed (and compiled) here only
    ph = pot_mod.coupling_data(p, state.x)
    prep = prepare(s, p, bc, state, pair_h=ph)
    return prep.system.Ke, prep.rhs, prep.tol, prep.bn, ph


def _system(s: Newton, pot, bc, state: NewtonState, Ke, ph) -> NewtonSystem:
    """The Newton operator from the element Hessians already computed at ``state.x``."""
    need = s.linear.needs_element_hessians
    sp = _shifted(s, pot, state.lam)
    exact = exact_tangent(s, pot)
    return newton_system(
        sp,
        state.x,
        ~bc.mask,
        hessian=s.hessian,
        need_Ke=need,
        Ke=Ke,
        pair_h=ph,
        exact_tangent=exact,
    )


@functools.partial(jax.jit, static_argnums=0)
def _loop_linear(s: Newton, lstate, pot, bc, state: NewtonState, Ke, rhs, tol, ph) -> Solution:
    p = terms.with_states(pot, state.terms)
    return linear_step(s, lstate, _system(s, p, bc, state, Ke, ph), rhs, tol)


@functools.partial(jax.jit, static_argnums=0)
def _loop_finish(s: Newton, lstate, pot, bc, state: NewtonState, length, Ke, rhs, tol, bn, lin, ph):
    p = terms.with_states(pot, state.terms)
    # (the operator is applied here only by a non-conservative load's line search)
    system = _system(s, p, bc, state, Ke, ph)
    dD = jnp.where(bc.mask, bc.values - state.x, 0.0)
    return finish(s, p, bc, state, length, Prepared(system, dD, rhs, tol, bn), lin, lstate)


_solution_jit = jax.jit(solution, static_argnums=2)


@functools.partial(jax.jit, static_argnames="nnz_upper")
def _upper(pot: Potential, Ke, element_map, lam, nnz_upper: int):
    """The assembled upper data of Ke (the map an argument: no callback, so the
    persistent cache keeps it) and the mass diagonal ``(n_nodes,)`` (zeros for none)
    plus the Levenberg–Marquardt shift ``lam``."""
    md = pot_mod.mass_diagonal(pot)
    if md is None:
        md = jnp.zeros(pot.mesh.points.shape[:1], Ke.dtype)
    return assemble_upper(Ke, element_map, nnz_upper), md + lam


def _host_linear_step(
    s: Newton, lstate, pot: Potential, bc: Dirichlet, Ke, rhs, tol, lam
) -> Solution:
    """The linear solve of a Newton step outside jit on the assembled operator: data
    assembled on the device, the host solve a Python call, the projected retry on the
    assembled data (:func:`~.retry.projected_upper`); ``lam``: the shift."""
    host = lstate.host
    nnz = host.nnz_upper
    data, md = _upper(pot, Ke, host.element_map, lam, nnz)
    free = np.asarray(~bc.mask)
    box = {"data": data}

    def attempt(k, token):
        if k == 1:
            box["data"] = projected_upper(
                box["data"], Ke, host.element_map, nnz, pot_mod.projection_dim(pot)
            )
        dx, its, st = s.linear.host_step(lstate, box["data"], md, rhs, tol)
        stats = dict(iterations=its, residual=0.0)
        return Solution(x=np.asarray(dx) * free, status=np.int32(st), stats=stats)  # type: ignore[arg-type]

    res = with_retry(attempt, rhs, traced=False, enabled=s.hessian != "projected")
    return res._replace(x=jnp.asarray(res.x, rhs.dtype))


TRIM_BYTES = 32 << 20
"""The Python loop returns the freed heap to the OS after a Newton step whose element
Hessians took at least this many bytes (glibc keeps freed blocks below 32 MB in its
arenas). Smaller problems skip it: on the default scene (1,080 tets, 365 Newton steps)
trimming every step cost 0.5 s of a 3.2 s run."""


def _python_loop(s: Newton, lstate, pot: Potential, bc: Dirichlet, x0) -> Solution:
    """The loop in Python over compiled pieces (concrete inputs only)."""
    state, length = _loop_start(s, pot, bc, x0)
    # (the true tangent of a follower load is not the assembled symmetric matrix: its
    # GMRES runs compiled, the host factorisation of the symmetric part a callback)
    on_host = (
        bool(s.linear.on_host)
        and operator_is_assembled(s.hessian, pot)
        and not exact_tangent(s, pot)
    )
    while int(state.status) == RUNNING:
        p = terms.with_states(pot, state.terms)
        Ke, rhs, tol, bn, ph = _loop_prepare(s, pot, bc, state)
        if on_host:
            lin = _host_linear_step(s, lstate, p, bc, Ke, rhs, tol, state.lam)
        else:
            lin = _loop_linear(s, lstate, pot, bc, state, Ke, rhs, tol, ph)
        # refresh the terms for the coming step (self-contact: a new broad phase)
        d = jnp.where(bc.mask, bc.values - state.x, lin.x)
        pot = terms.refreshed(pot, state.x, d)
        state = _loop_finish(s, lstate, pot, bc, state, length, Ke, rhs, tol, bn, lin, ph)
        # drop this step's element Hessians before the next _prepare makes new ones:
        # otherwise two (n_cells, m, m) arrays are live at its peak (168 MB each at 146k tets)
        big = Ke is not None and Ke.nbytes >= TRIM_BYTES
        del Ke, lin, ph
        if big:
            release_free_memory()
    return _solution_jit(pot, state, s)
