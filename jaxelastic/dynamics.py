"""Implicit time integration as incremental-potential minimisation.

Backward Euler (first order, dissipative):
``x_{n+1} = argmin ½‖x − x̃‖²_M / h² + E(x) − f_extᵀx``, ``x̃ = x_n + h v_n``,
``v_{n+1} = (x_{n+1} − x_n)/h``.

BDF2 (second order): ``x̃ = (4x_n − x_{n−1})/3 + (2h/3)(4v_n − v_{n−1})/3``, weight
``1/(2h/3)²``, ``v_{n+1} = (3x_{n+1} − 4x_n + x_{n−1})/(2h)``; its first step is backward
Euler. (Kane et al. 2000; Martin et al. 2011, *Example-based elastic materials*; Kim &
Eberle 2022, §"Time integration".)

Optional Rayleigh damping ``f_d = −(α M + β K(x_n)) v_{n+1}`` enters as a potential.
Each step is one :func:`jaxelastic.solve` of the step's incremental potential, warm-started
from the previous positions. Two drivers share that step (:func:`step`):

* :func:`rollout`: a whole trajectory under ``lax.scan`` (one compiled loop), differentiable
  step by step: each step's solve is differentiated implicitly, so the reverse sweep is the
  discrete adjoint of the integrator (one adjoint solve per step, never the Newton
  iterations), with respect to the base potential (material parameters, loads, masses),
  the initial state ``(x₀, v₀)`` and Dirichlet values.
* :func:`simulate`: the host loop (progress bar, per-step records and energies, outputs
  and early stops through a callback), one compiled step per time step.

Memory of a reverse sweep through :func:`rollout` (``checkpoint``):

* ``None``: everything JAX would keep (per step: ``x*``, ``x̃``, the step's Dirichlet values;
  with ``ImplicitAdjoint(mode="forward")`` also the element Hessians, ``n_cells·(k·d)²``
  floats per step).
* ``"step"``: each step is a ``jax.checkpoint`` that saves only the Newton solution and
  status (:data:`~jaxelastic.solvers.adjoint.X_STAR`) besides the carried state: the
  backward pass recomputes the cheap algebra but never re-runs a Newton solve.
* an int ``s``: segments of ``s`` steps, each a ``jax.checkpoint`` saving nothing but the
  state at its start (Griewank & Walther 2008, *Evaluating Derivatives*, §12.1 "binomial
  checkpointing"; with ``s ≈ √n`` memory is O(√n) states): the backward pass re-solves one
  segment at a time, i.e. about twice the Newton work of the forward pass.

Measured (2D cantilever, 27 nodes, 200 steps, loss on the tip only, stored residuals of
the reverse sweep in units of one state = 4 position arrays): reverse mode: None 106,
``"step"`` 156 (it stores the carried state, more than the step's own residuals), 14-step
segments 13; forward mode: None 2,345 (element Hessians), ``"step"`` 106, segments 13.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer

from .loads import Dirichlet
from .mechanics.kernels import energy
from .mechanics.potential import Potential
from .mechanics.potential import value as potential_value
from .solvers import (
    X_STAR,
    ImplicitAdjoint,
    Newton,
    PreparedSolver,
    Solution,
    SolveError,
    Status,
    is_traced,
    prepare_solver,
    solve,
)

__all__ = [
    "Integrator",
    "State",
    "init_state",
    "step",
    "Trajectory",
    "rollout",
    "simulate",
    "kinetic_energy",
    "total_energy",
    "static_potential",
    "check_time_step",
    "H_MIN",
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


def _mass(base: Potential) -> jax.Array:
    """The lumped masses of ``base``; TypeError when it has none (a static potential)."""
    if base.mass is None:
        raise TypeError("Potential.mass is None: the kinetic energy needs lumped masses")
    return base.mass


def total_energy(base: Potential, state: State) -> jax.Array:
    """Kinetic + elastic + external potential energy of ``state`` (for energy plots)."""
    static = base.replace(mass=None, x_tilde=None, inertia_weight=None)
    return kinetic_energy(_mass(base), state.v) + potential_value(static, state.x)


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
    if base.contact is not None:  # friction lagged at x_n; obstacles at t + h
        c = base.contact.at_time(state.t)
        c = c.lag(x) if c.has_friction else c
        kw.update(contact=c.at_time(state.t + h))
    return base.replace(**kw)


def _start(pot: Potential, state: State, warm):
    """Start Newton from whichever of x̃, x_n (and ``warm``) has the lowest step potential:
    x̃ saves a Newton iteration on smooth motion; at large h it can overshoot or invert,
    where x_n is better."""
    x_tilde = pot.x_tilde
    assert x_tilde is not None  # set by _step_potential
    if pot.contact is not None:  # a moving obstacle may have swept over x_n
        state = state._replace(x=pot.contact.make_feasible(state.x))
        if pot.contact.self_contact is not None:  # x̃ is not checked for self-intersection
            return state.x
    e_tilde = potential_value(pot, x_tilde)
    e_n = potential_value(pot, state.x)
    use_tilde = jnp.isfinite(e_tilde) & ~(e_tilde > e_n)
    x_start = jnp.where(use_tilde, x_tilde, state.x)
    if warm is not None:
        better = potential_value(pot, warm) < jnp.minimum(e_n, jnp.where(use_tilde, e_tilde, e_n))
        x_start = jnp.where(better, warm, x_start)
    return x_start


def _advance(
    base: Potential, state: State, bc: Dirichlet, integ: Integrator, solver, adjoint, warm
):
    pot = _step_potential(base, state, integ, state.n > 0)
    res = solve(pot, bc, x0=_start(pot, state, warm), solver=solver, adjoint=adjoint, throw=False)
    return _next_state(state, res.x, res.ok, integ), res


def _next_state(state: State, x_new, ok, integ: Integrator) -> State:
    """The state after a step to ``x_new``; ``state`` itself unless ``ok``."""
    bdf2_now = state.n > 0
    h = integ.h
    if integ.method == "bdf2":
        v_new = jnp.where(
            bdf2_now,
            (3.0 * x_new - 4.0 * state.x + state.x_prev) / (2.0 * h),
            (x_new - state.x) / h,
        )
    else:
        v_new = (x_new - state.x) / h
    new = State(x_new, v_new, state.x, state.v, state.t + h, state.n + 1)
    return jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), new, state)


_SCALARS = ("inertia_weight", "mass_damping", "stiffness_damping")


def _strong_scalars(pot: Potential) -> Potential:
    """``pot`` with its scalar weights as strongly typed arrays of the mesh's dtype (a
    Python float would come out of jit weakly typed: another compilation of the solve)."""
    dt = pot.mesh.points.dtype
    kw = {k: jnp.asarray(getattr(pot, k), dt) for k in _SCALARS if getattr(pot, k) is not None}
    return pot.replace(**kw)


def static_potential(base: Potential, integ: Integrator) -> Potential:
    """The static potential of ``base`` in the pytree structure of :func:`simulate`'s step
    potentials: ``x̃ = x_prev = X`` with zero inertia and damping weights.

    Π is exactly the static one (``E − f_extᵀx``: the extra terms are ``0·(…)``), and a
    :func:`~jaxelastic.solve` of it reuses the compiled Newton solve of the time steps
    instead of compiling its own (a scene's static comparison does that). The rigid-body
    check of static solves applies (zero inertia weight).

    Args:
        base: the dynamic potential (with ``mass``); integ: the :class:`Integrator` whose
            step potentials it must match (its damping terms).
    """
    _mass(base)
    X = base.mesh.points
    zero = jnp.zeros((), X.dtype)
    kw: dict[str, Any] = dict(x_tilde=X, inertia_weight=zero)
    if integ.alpha:
        kw.update(x_prev=X, mass_damping=zero)
    if integ.beta:
        kw.update(x_prev=X, stiffness_damping=zero)
    return base.replace(**kw)


H_MIN = 1e-150
"""The smallest time step accepted [s]: the inertia term m/h² must stay finite in float64
(a subnormal h makes it overflow, and the step fails with NaN)."""


def check_time_step(h) -> None:
    """Refuse a time step ``h`` [s] that is not a finite number in [:data:`H_MIN`, ∞).

    Raises:
        ValueError: naming ``h`` and what to do.
    """
    try:
        f = float(h)
    except (TypeError, ValueError):
        raise ValueError(f"time step h must be a number [s], got {h!r}") from None
    if not (math.isfinite(f) and f > 0):
        raise ValueError(f"time step h must be a finite number > 0 [s], got {h!r}")
    if f < H_MIN:
        raise ValueError(
            f"time step h = {f!r} s is below {H_MIN:g} s: the inertia term m/h^2 overflows "
            "float64. Use a time step of the order of the dynamics you want to see"
        )


def _check_dynamic(base: Potential, integ: Integrator):
    if base.mass is None:
        raise ValueError(
            "dynamics needs lumped masses: Potential(mass=je.loads.lumped_mass(mesh, density))"
        )
    if not isinstance(integ, Integrator):
        raise TypeError(f"integ must be a je.Integrator(h, ...), got {type(integ).__name__}")
    if not isinstance(integ.h, Tracer):
        check_time_step(integ.h)
    if integ.method not in ("backward_euler", "bdf2"):
        raise ValueError(f"method must be 'backward_euler' or 'bdf2', got {integ.method!r}")
    for name in ("alpha", "beta"):
        v = getattr(integ, name)
        if not isinstance(v, Tracer) and not (math.isfinite(float(v)) and float(v) >= 0):
            raise ValueError(
                f"Rayleigh damping {name} must be finite and >= 0 (0 = off), got {v!r}: a "
                "negative damping coefficient feeds energy into the body"
            )


def step(
    pot: Potential,
    state: State,
    bc: Dirichlet,
    integ: Integrator,
    *,
    solver: Newton | PreparedSolver = Newton(),
    adjoint: ImplicitAdjoint = ImplicitAdjoint(),
    warm: jax.Array | None = None,
) -> tuple[State, Solution]:
    """Advance one time step (pure, jit-able, differentiable).

    Args:
        pot: base potential with lumped ``mass`` ``(n_nodes,)`` and optional ``f_ext``.
        state: current :class:`State`.
        bc: Dirichlet data at time ``t + h``.
        integ: :class:`Integrator`.
        solver: :class:`~jaxelastic.solvers.newton.Newton` (under jit with a traced mesh,
            bind host linear solvers first: :func:`~jaxelastic.solvers.prepare_solver`).
        adjoint: derivative settings of the step's solve.
        warm: optional ``(n_nodes, dim)`` extra initial guess (used if its step potential
            is lower than that of x̃ and x_n).

    Returns:
        ``(new_state, solution)``; on failure the state is not advanced (the status says
        why).
    """
    _check_dynamic(pot, integ)
    solver = prepare_solver(solver, pot.mesh, bc)
    return _advance(pot, state, bc, integ, solver, adjoint, warm)


class Trajectory(NamedTuple):
    """Per-step outputs of :func:`rollout` (leading axis ``n_steps``).

    Attributes:
        frames: ``observe(state)`` after every step (default: positions
            ``(n_steps, n_nodes, dim)``); differentiable.
        status: ``(n_steps,)`` status per step (a failed step freezes the state).
        stats: ``steps`` and ``linear_iterations``, each ``(n_steps,)``.
    """

    frames: Any
    status: jax.Array
    stats: dict


def _positions(state: State):
    return state.x


def _check_rollout(n_steps, checkpoint, warm, x_shape):
    if n_steps < 1:
        raise ValueError(f"n_steps must be >= 1, got {n_steps}")
    if not (checkpoint is None or checkpoint == "step" or isinstance(checkpoint, int)):
        raise ValueError(f"checkpoint must be None, 'step' or an int, got {checkpoint!r}")
    if isinstance(checkpoint, int) and not isinstance(checkpoint, bool) and checkpoint < 1:
        raise ValueError(f"checkpoint segment length must be >= 1, got {checkpoint}")
    if warm is not None and tuple(warm.shape) != (n_steps, *x_shape):
        raise ValueError(f"warm must have shape {(n_steps, *x_shape)}, got {warm.shape}")


def _segmented_scan(body, carry, warm, n_steps: int, seg: int, x_shape):
    """``lax.scan`` of ``body`` in checkpointed segments of ``seg`` steps."""

    def scan(c, xs, length):
        return jax.lax.scan(body, c, xs, length=length)

    seg = min(seg, n_steps)
    n_seg, rest = divmod(n_steps, seg)
    segment = jax.checkpoint(lambda c, xs: scan(c, xs, seg))
    w_main = None if warm is None else warm[: n_seg * seg].reshape(n_seg, seg, *x_shape)
    carry, ys = jax.lax.scan(segment, carry, w_main, length=n_seg)
    ys = jax.tree_util.tree_map(lambda a: a.reshape(n_seg * seg, *a.shape[2:]), ys)
    if rest:
        tail = jax.checkpoint(lambda c, xs: scan(c, xs, rest))
        carry, ys_rest = tail(carry, None if warm is None else warm[n_seg * seg :])
        ys = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), ys, ys_rest)
    return carry, ys


def rollout(
    pot: Potential,
    state0: State,
    bc: Dirichlet | Callable[[jax.Array], Dirichlet],
    integ: Integrator,
    n_steps: int,
    *,
    solver: Newton | PreparedSolver = Newton(),
    adjoint: ImplicitAdjoint = ImplicitAdjoint(),
    checkpoint: None | str | int = None,
    observe: Callable[[State], Any] | None = None,
    warm: jax.Array | None = None,
) -> tuple[State, Trajectory]:
    """``n_steps`` implicit steps under ``lax.scan``, differentiable step by step.

    Args:
        pot: base potential with lumped ``mass`` ``(n_nodes,)`` (and ``f_ext``, params, …).
        state0: initial :class:`State` (``x``, ``v`` differentiable).
        bc: Dirichlet data, fixed or ``t ↦ Dirichlet`` written with jnp (evaluated at each
            new time; its values are differentiable through closed-over arrays).
        integ: :class:`Integrator` (static).
        n_steps: number of steps (static).
        solver: Newton settings (a tight ``rtol``, e.g. 1e-10, for accurate gradients).
        adjoint: derivative settings (``mode="forward"`` for jvp).
        checkpoint: None, ``"step"`` or a segment length (see the module docstring).
        observe: ``State ↦ pytree`` recorded after each step (default: positions); return
            only what the loss needs to keep the stored trajectory small.
        warm: optional ``(n_steps, n_nodes, dim)`` initial guesses (e.g. the trajectory of
            a previous fit iterate).

    Returns:
        ``(final_state, Trajectory)``. Once a step fails the state is frozen; derivatives
        of anything downstream of a failed step are NaN.
    """
    _check_dynamic(pot, integ)
    n_steps = int(n_steps)
    x_shape = tuple(state0.x.shape)
    _check_rollout(n_steps, checkpoint, warm, x_shape)
    observe = _positions if observe is None else observe
    bc_fn = bc if callable(bc) else (lambda t: bc)
    solver = prepare_solver(solver, pot.mesh, bc_fn(state0.t + integ.h))

    def body(carry, w):
        st, failed = carry
        new, res = _advance(pot, st, bc_fn(st.t + integ.h), integ, solver, adjoint, w)
        failed = failed | ~res.ok
        new = jax.tree_util.tree_map(lambda a, b: jnp.where(failed, b, a), new, st)
        stats = dict(steps=res.stats["steps"], linear_iterations=res.stats["linear_iterations"])
        return (new, failed), (observe(new), res.status, stats)

    if checkpoint == "step":
        body = jax.checkpoint(body, policy=jax.checkpoint_policies.save_only_these_names(X_STAR))
    carry = (state0, jnp.asarray(False))
    if isinstance(checkpoint, int) and not isinstance(checkpoint, bool):
        carry, ys = _segmented_scan(body, carry, warm, n_steps, checkpoint, x_shape)
    else:
        carry, ys = jax.lax.scan(body, carry, warm, length=n_steps)
    frames, status, stats = ys
    return carry[0], Trajectory(frames, status, stats)


def _energies(base: Potential, x, v):
    """``[½vᵀMv, E(x), −f_extᵀ(x − X)]`` of a state (kinetic, elastic, external)."""
    ke = kinetic_energy(_mass(base), v)
    el = energy(base.psi, x, base.mesh, base.params)
    ext = (
        jnp.zeros((), x.dtype)
        if base.f_ext is None
        else -jnp.sum(base.f_ext * (x - base.mesh.points))
    )
    return jnp.stack([ke, el, ext])


@functools.partial(jax.jit, static_argnames="integ")
def _prepare_step(base: Potential, state: State, integ: Integrator):
    """The step potential and Newton's start of :func:`simulate`'s step."""
    pot = _strong_scalars(_step_potential(base, state, integ, state.n > 0))
    return pot, _start(pot, state, None)


@functools.partial(jax.jit, static_argnames="integ")
def _finish_step(base: Potential, state: State, x_new, status, integ: Integrator):
    """The new state of :func:`simulate`'s step and its energies."""
    new = _next_state(state, x_new, status == Status.SUCCESS, integ)
    return new, _energies(base, new.x, new.v)


def _step_record(t: float, res: Solution, en, wall: float) -> dict:
    st = res.stats
    return dict(
        t=t,
        status=Status(int(res.status)).name,
        newton_steps=int(st["steps"]),
        linear_iterations=int(st["linear_iterations"]),
        residual=float(st["residual"]),
        line_search_cutbacks=int(st["line_search_cutbacks"]),
        min_J=float(st["min_J"]),
        min_J_cell=int(st["min_J_cell"]),
        max_strain=float(st["max_strain"]),
        achieved_rtol=float(st["achieved_rtol"]),
        floor_limited=bool(st.get("floor_limited", False)),
        wall_time=wall,
        kinetic=float(en[0]),
        elastic=float(en[1]),
        external=float(en[2]),
    )


class _NoBar:
    """A silent stand-in for a tqdm bar."""

    def update(self, n: int = 1) -> None:
        pass

    def close(self) -> None:
        pass


def _progress_bar(total: int, progress: bool):
    """A tqdm bar over ``total`` steps, or a silent stand-in when ``progress`` is off or
    tqdm is not installed (a lean install)."""
    if progress:
        try:
            from tqdm import tqdm
        except ImportError:
            return _NoBar()
        return tqdm(total=total, desc="time steps", leave=False)
    return _NoBar()


def _pressure_schedule(pot: Potential, pressure_at) -> Callable[[float], Potential]:
    """``t ↦`` the base potential of the step ending at ``t``: ``pot`` itself, or with the
    pressures ``pressure_at(t)`` (same shapes and dtype: one compiled step for all)."""
    if pressure_at is None:
        return lambda t: pot
    term = pot.pressure
    if term is None:
        raise ValueError(
            "simulate: pressure_at is given but the potential has no pressure term "
            "(Potential(..., pressure=je.loads.pressure_load(...)))"
        )
    if not callable(pressure_at):
        raise TypeError(f"pressure_at must be a function t -> pressures, got {pressure_at!r}")
    shape, dtype = term.pressure.shape, term.pressure.dtype

    def at(t: float) -> Potential:
        p = np.broadcast_to(np.asarray(pressure_at(t), dtype=np.dtype(dtype)), shape)
        if not np.all(np.isfinite(p)):
            raise ValueError(f"simulate: pressure_at({t:g}) is not finite: {p}")
        return pot.replace(pressure=term.replace(pressure=jnp.asarray(p)))

    return at


def simulate(
    pot: Potential,
    state: State,
    bc: Dirichlet | Callable[[float], Dirichlet],
    integ: Integrator,
    n_steps: int,
    *,
    solver: Newton | PreparedSolver = Newton(),
    callback: Callable[[State, Solution, dict], bool | None] | None = None,
    progress: bool = True,
    throw: bool = True,
    pressure_at: Callable[[float], Any] | None = None,
) -> tuple[State, list[dict]]:
    """The host loop over time steps (one compiled step), with progress bar and records.

    Args:
        pot: base potential with lumped ``mass``; state: initial :class:`State`.
        bc: fixed Dirichlet data, or a Python function ``t ↦ Dirichlet`` (same mask at all
            times).
        integ: :class:`Integrator`; n_steps: maximum number of steps.
        solver: :class:`~jaxelastic.solvers.newton.Newton` (its linear solver is bound once).
        callback: called after every successful step with ``(state, solution, record)``;
            return True to stop (e.g. once the body has settled), None/False to go on.
        progress: show a tqdm progress bar.
        throw: raise :class:`~jaxelastic.solvers.results.SolveError` on a failed step (else
            stop and return; the last record has the failed status).
        pressure_at: a Python function ``t ↦`` the pressures ``(n_surfaces,)`` [Pa] of
            ``pot.pressure`` at time ``t`` (e.g. a ramp; each step uses its end time), or
            None: the term's own pressures at every step (a step load).

    Returns:
        ``(final_state, records)``: one dict per step with ``t``, ``status``,
        ``newton_steps``, ``linear_iterations``, ``residual``, ``line_search_cutbacks``,
        ``wall_time`` [s] and the energies of the new state ``kinetic``, ``elastic``,
        ``external`` (``−f_extᵀ(x − X)``).
    """
    _check_dynamic(pot, integ)
    if is_traced(pot, state):
        raise ValueError("simulate is a host loop: call it outside jit (use rollout inside)")
    bc_at = bc if callable(bc) else (lambda t: bc)
    loads_at = _pressure_schedule(pot, pressure_at)
    solver = prepare_solver(solver, pot.mesh, bc_at(float(state.t) + integ.h))
    records: list[dict] = []
    bar = _progress_bar(int(n_steps), progress)
    try:
        for _ in range(int(n_steps)):
            t_next = float(state.t) + integ.h
            t0 = time.perf_counter()
            # three compiled pieces: the step potential, the solve (one compilation shared
            # with every solve of a potential of this structure, e.g. static_potential)
            # and the new state with its energies
            if pot.contact is not None and pot.contact.self_friction is not None:
                # pair friction is lagged over the candidate pairs: complete them at x_n
                pot = pot.replace(contact=pot.contact.refreshed(state.x))
            base = loads_at(t_next)
            step_pot, x_start = _prepare_step(base, state, integ)
            res = solve(step_pot, bc_at(t_next), x0=x_start, solver=solver, throw=False)
            new, en = _finish_step(base, state, res.x, res.status, integ)
            jax.block_until_ready(new)
            rec = _step_record(t_next, res, en, time.perf_counter() - t0)
            records.append(rec)
            bar.update(1)
            if not bool(res.ok):
                if throw:
                    raise SolveError(res, what=f"time step to t={t_next:g}")
                break
            state = new
            if callback is not None and callback(state, res, rec):
                break
    finally:
        bar.close()
    return state, records
