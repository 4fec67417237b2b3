"""Implicit time integration as incremental-potential minimisation.

Backward Euler (first order, dissipative):
``x_{n+1} = argmin ½‖x − x̃‖²_M / h² + E(x) − f_extᵀx``, ``x̃ = x_n + h v_n``,
``v_{n+1} = (x_{n+1} − x_n)/h``.

BDF2 (second order): ``x̃ = (4x_n − x_{n−1})/3 + (2h/3)(4v_n − v_{n−1})/3``, weight
``1/(2h/3)²``, ``v_{n+1} = (3x_{n+1} − 4x_n + x_{n−1})/(2h)``; its first step is backward
Euler. (Kane et al. 2000; Martin et al. 2011, *Example-based elastic materials*; Kim &
Eberle 2022, §"Time integration".)

Optional Rayleigh damping ``f_d = −(α M + β K(x_n)) v_{n+1}`` enters as a potential.
Each step is one Newton solve (:func:`jaxelastic.solvers.newton.newton`), warm-started
from the previous positions; whole trajectories run under ``lax.scan`` (:func:`rollout`)
or in a host loop with a progress bar and per-step outputs (:func:`simulate`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp

from .loads import Dirichlet
from .potential import Potential
from .potential import value as potential_value
from .solvers.newton import (
    NewtonResult,
    NewtonSettings,
    SolveError,
    Status,
    make_linear,
    newton,
)

__all__ = [
    "Integrator",
    "State",
    "init_state",
    "step",
    "advance",
    "rollout",
    "simulate",
    "kinetic_energy",
    "total_energy",
]


class Integrator(NamedTuple):
    """Static integrator settings.

    Attributes:
        h: time step [s].
        method: ``"backward_euler"`` or ``"bdf2"``.
        alpha: mass-proportional Rayleigh damping [1/s] (0 = off, compiled out).
        beta: stiffness-proportional Rayleigh damping [s] (0 = off, compiled out).
    """

    h: float
    method: str = "backward_euler"
    alpha: float = 0.0
    beta: float = 0.0


class State(NamedTuple):
    """Dynamic state: positions and velocities now and one step back, time, step count."""

    x: jax.Array
    v: jax.Array
    x_prev: jax.Array
    v_prev: jax.Array
    t: jax.Array
    n: jax.Array


def init_state(x0: jax.Array, v0: jax.Array | None = None, t0: float = 0.0) -> State:
    """Initial state at rest positions ``x0`` ``(n_nodes, dim)`` with velocities ``v0``."""
    x0 = jnp.asarray(x0)
    v0 = jnp.zeros_like(x0) if v0 is None else jnp.asarray(v0, x0.dtype)
    return State(x0, v0, x0, v0, jnp.asarray(t0, x0.dtype), jnp.asarray(0, jnp.int32))


def kinetic_energy(mass: jax.Array, v: jax.Array) -> jax.Array:
    """``½ Σ m_a ‖v_a‖²`` for lumped masses ``(n_nodes,)`` and velocities ``(n_nodes, dim)``."""
    return 0.5 * jnp.sum(mass[:, None] * v * v)


def total_energy(base: Potential, state: State) -> jax.Array:
    """Kinetic + elastic + external potential energy of ``state`` (for energy plots)."""
    static = base.replace(mass=None, x_tilde=None, inertia_weight=None)
    return kinetic_energy(base.mass, state.v) + potential_value(static, state.x)


def _step_potential(base: Potential, state: State, integ: Integrator, bdf2_now):
    h = integ.h
    x, v, xp, vp = state.x, state.v, state.x_prev, state.v_prev
    if integ.method == "backward_euler":
        x_tilde, heff, x_ref = x + h * v, h, x
    elif integ.method == "bdf2":
        be = (x + h * v, h, x)
        b2 = (
            (4.0 * x - xp) / 3.0 + (2.0 * h / 3.0) * (4.0 * v - vp) / 3.0,
            2.0 * h / 3.0,
            (4.0 * x - xp) / 3.0,
        )
        x_tilde, heff, x_ref = jax.tree_util.tree_map(
            lambda a, b: jnp.where(bdf2_now, b, a), be, b2
        )
    else:
        raise ValueError(f"method must be 'backward_euler' or 'bdf2', got {integ.method!r}")
    dt_factor = jnp.where(bdf2_now, 1.5, 1.0) / h if integ.method == "bdf2" else 1.0 / h
    kw = dict(x_tilde=x_tilde, inertia_weight=1.0 / heff**2)
    if integ.alpha:
        kw.update(x_prev=x_ref, mass_damping=integ.alpha * dt_factor)
    if integ.beta:
        kw.update(x_prev=x_ref, stiffness_damping=integ.beta * dt_factor)
    return base.replace(**kw)


def step(
    base: Potential,
    state: State,
    bc: Dirichlet,
    integ: Integrator,
    settings: NewtonSettings = NewtonSettings(),
    linear=None,
) -> tuple[State, NewtonResult]:
    """Advance one time step (pure, jit-compatible).

    Args:
        base: potential with ``mass`` (lumped, ``(n_nodes,)``) and optional ``f_ext``.
        state: current :class:`State`.
        bc: Dirichlet data at time ``t + h``.
        integ: :class:`Integrator`; settings: Newton settings.
        linear: optional :class:`~jaxelastic.solvers.host.HostLinearSolver` (static).

    Newton starts from the inertial predictor x̃ or from x_n, whichever has the lower
    incremental potential (x̃ saves an iteration on smooth motion; x_n is safer at large h).

    Returns:
        ``(new_state, newton_result)``; on failure the state is not advanced (the status
        says why).
    """

    def solve(pot, x0, bc):
        return newton(pot, x0, bc, settings, linear)

    return advance(base, state, bc, integ, solve)


def advance(
    base: Potential,
    state: State,
    bc: Dirichlet,
    integ: Integrator,
    solve: Callable[[Potential, jax.Array, Dirichlet], NewtonResult],
) -> tuple[State, NewtonResult]:
    """One time step with a given equilibrium solver (the body of :func:`step`).

    Args:
        solve: ``(pot, x_start, bc) ↦ NewtonResult`` minimising the step potential (e.g.
            :func:`~jaxelastic.solvers.newton.newton`, or the differentiable
            :func:`~jaxelastic.implicit.equilibrium_result`).
    """
    if base.mass is None:
        raise ValueError("dynamics needs lumped masses: Potential(mass=lumped_mass(...))")
    bdf2_now = state.n > 0
    pot = _step_potential(base, state, integ, bdf2_now)
    # start from whichever of x̃ and x_n has the lower Π (x̃ saves a Newton iteration on
    # smooth motion; at large h it can overshoot or invert, where x_n is better)
    e_tilde = potential_value(pot, pot.x_tilde)
    e_n = potential_value(pot, state.x)
    use_tilde = jnp.isfinite(e_tilde) & ~(e_tilde > e_n)
    x_start = jnp.where(use_tilde, pot.x_tilde, state.x)
    res = solve(pot, x_start, bc)
    x_new = res.x
    h = integ.h
    if integ.method == "bdf2":
        v_new = jnp.where(
            bdf2_now,
            (3.0 * x_new - 4.0 * state.x + state.x_prev) / (2.0 * h),
            (x_new - state.x) / h,
        )
    else:
        v_new = (x_new - state.x) / h
    ok = res.status == Status.SUCCESS
    new = State(x_new, v_new, state.x, state.v, state.t + h, state.n + 1)
    new = jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), new, state)
    return new, res


def rollout(
    base: Potential,
    state: State,
    bc_fn: Callable[[jax.Array], Dirichlet],
    integ: Integrator,
    n_steps: int,
    settings: NewtonSettings = NewtonSettings(),
    linear=None,
):
    """``n_steps`` steps under ``lax.scan`` (one compiled loop; jit it with static sizes).

    Args:
        bc_fn: ``t ↦ Dirichlet`` written with jnp (traced), evaluated at each new time.

    Returns:
        ``(final_state, (positions (n_steps, n_nodes, dim), statuses, newton_steps,
        linear_iterations))``. Once a step fails, later steps are skipped (state frozen,
        status kept).
    """

    def body(carry, _):
        st, failed = carry
        new, res = step(base, st, bc_fn(st.t + integ.h), integ, settings, linear)
        failed = failed | (res.status != Status.SUCCESS)
        new = jax.tree_util.tree_map(lambda a, b: jnp.where(failed, b, a), new, st)
        return (new, failed), (new.x, res.status, res.steps, res.linear_iterations)

    (final, _), ys = jax.lax.scan(body, (state, jnp.asarray(False)), None, length=n_steps)
    return final, ys


_step_jit = jax.jit(step, static_argnames=("integ", "settings", "linear"))


def simulate(
    base: Potential,
    state: State,
    bc: Dirichlet | Callable[[float], Dirichlet],
    integ: Integrator,
    n_steps: int,
    *,
    settings: NewtonSettings = NewtonSettings(),
    linear="auto",
    callback: Callable[[State, NewtonResult], None] | None = None,
    progress: bool = True,
    throw: bool = True,
) -> tuple[State, list[dict]]:
    """Host loop over :func:`step` (compiled once) with a progress bar and per-step stats.

    Args:
        bc: fixed Dirichlet data, or a Python function ``t ↦ Dirichlet``.
        callback: called after every successful step with ``(state, result)`` (outputs).
        linear: ``"auto"``, ``"cg"``, ``"direct"``, ``"amg"`` or a prebuilt
            :class:`~jaxelastic.solvers.host.HostLinearSolver` (see
            :func:`~jaxelastic.solvers.newton.make_linear`); the Dirichlet mask must not
            change over time.
        throw: raise :class:`SolveError` on a failed step (else stop and return).

    Returns:
        ``(final_state, stats)``: one dict per step with time, status, Newton and CG
        iterations, residual, wall time.
    """
    from tqdm import tqdm

    stats = []
    it = tqdm(range(n_steps), desc="time steps", disable=not progress, leave=False)
    for _ in it:
        t_next = float(state.t) + integ.h
        bc_now = bc(t_next) if callable(bc) else bc
        t0 = time.perf_counter()
        if isinstance(linear, str):
            linear = make_linear(base.mesh, bc_now, linear)
        new, res = _step_jit(base, state, bc_now, integ, settings, linear)
        jax.block_until_ready(new)
        wall = time.perf_counter() - t0
        status = int(res.status)
        stats.append(
            dict(
                t=t_next,
                status=Status(status).name,
                newton_steps=int(res.steps),
                linear_iterations=int(res.linear_iterations),
                residual=float(res.residual),
                line_search_cutbacks=int(res.line_search_cutbacks),
                wall_time=wall,
            )
        )
        if status != Status.SUCCESS:
            if throw:
                raise SolveError(res, what=f"time step to t={t_next:g}")
            break
        state = new
        if callback is not None:
            callback(state, res)
    return state, stats
