"""Differentiable implicit dynamics: rollouts whose every step is differentiated implicitly.

Each backward-Euler/BDF2 step is the minimiser of an incremental potential
(:func:`jaxelastic.dynamics.advance`), whose inertial predictor ``x̃``, previous positions and
inertia weight are fields of the step's :class:`~jaxelastic.potential.Potential`. Solving it
with :func:`jaxelastic.implicit.equilibrium_result` therefore makes the whole trajectory
differentiable — with respect to the base potential (material parameters, loads, masses),
the initial state ``(x₀, v₀)`` and Dirichlet values — by one adjoint solve per step in the
reverse sweep (the discrete adjoint of the integrator; never the Newton iterations).

Memory (``checkpoint``): a reverse sweep over a ``lax.scan`` stores per-step residuals.

* ``None``: everything JAX would keep (per step: ``x*``, ``x̃``, the step's Dirichlet values;
  with ``mode="forward"`` also the element Hessians, ``n_cells·(k·d)²`` floats per step).
* ``"step"``: each step is a ``jax.checkpoint`` that saves only the Newton solution and
  status (:data:`~jaxelastic.implicit.X_STAR`) besides the carried state: the backward
  pass recomputes the cheap algebra but never re-runs a Newton solve.
* an int ``s``: segments of ``s`` steps, each a ``jax.checkpoint`` saving nothing but the
  state at its start (Griewank & Walther 2008, *Evaluating Derivatives*, §12.1 "binomial
  checkpointing"; with ``s ≈ √n`` memory is O(√n) states): the backward pass re-solves one
  segment at a time, i.e. about twice the Newton work of the forward pass.

Measured (2D cantilever, 27 nodes, 200 steps, loss on the tip only, stored residuals of
the reverse sweep in units of one state = 4 position arrays): ``mode="reverse"``: None 106,
``"step"`` 156 (it stores the carried state, more than the step's own residuals), 14-step
segments 13; ``mode="forward"``: None 2,345 (element Hessians), ``"step"`` 106, segments 13.
Same gradient in every variant (tests/test_implicit.py, slow tests).

:class:`TrajectoryCase` is a fitting case (protocol of :mod:`jaxelastic.fitting`) observing
positions at some frames of a trajectory.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .dynamics import Integrator, State, advance
from .implicit import DEFAULT_ADJOINT, X_STAR, AdjointSettings, equilibrium_result
from .loads import Dirichlet
from .parametrization import CaseAux
from .potential import Potential
from .potential import value as potential_value
from .solvers.newton import NewtonSettings, Status

__all__ = ["Trajectory", "rollout", "TrajectoryCase"]


class Trajectory(NamedTuple):
    """Per-step outputs of :func:`rollout` (leading axis ``n_steps``).

    Attributes:
        frames: ``observe(state)`` after every step (default: positions
            ``(n_steps, n_nodes, dim)``); differentiable.
        status: ``(n_steps,)`` Newton status per step (a failed step freezes the state).
        newton_steps: ``(n_steps,)`` Newton iterations per step.
        linear_iterations: ``(n_steps,)`` linear-solver iterations per step.
    """

    frames: Any
    status: jax.Array
    newton_steps: jax.Array
    linear_iterations: jax.Array


def _positions(state: State):
    return state.x


def rollout(
    base: Potential,
    state0: State,
    bc: Dirichlet | Callable[[jax.Array], Dirichlet],
    integ: Integrator,
    n_steps: int,
    *,
    settings: NewtonSettings = NewtonSettings(),
    linear=None,
    adjoint: AdjointSettings = DEFAULT_ADJOINT,
    checkpoint: None | str | int = None,
    observe: Callable[[State], Any] | None = None,
    warm: jax.Array | None = None,
    mode: str = "reverse",
) -> tuple[State, Trajectory]:
    """``n_steps`` implicit steps under ``lax.scan``, differentiable step by step.

    Args:
        base: potential with lumped ``mass`` ``(n_nodes,)`` (and ``f_ext``, params, …).
        state0: initial :class:`~jaxelastic.dynamics.State` (``x``, ``v`` differentiable).
        bc: Dirichlet data, fixed or ``t ↦ Dirichlet`` written with jnp (evaluated at each
            new time; its values are differentiable through closed-over arrays).
        integ: :class:`~jaxelastic.dynamics.Integrator` (static).
        n_steps: number of steps (static).
        settings: Newton settings (a tight ``rtol``, e.g. 1e-10, for accurate gradients).
        linear: None (PCG under jit) or a :class:`~jaxelastic.solvers.host.HostLinearSolver`.
        adjoint: adjoint/tangent solve settings.
        checkpoint: None, ``"step"`` or a segment length (see the module docstring).
        observe: ``State ↦ pytree`` recorded after each step (default: positions); return
            only what the loss needs to keep the stored trajectory small.
        warm: optional ``(n_steps, n_nodes, dim)`` initial guesses (e.g. the trajectory of
            a previous fit iterate); each step starts from whichever of ``x̃``, ``x_n`` and
            ``warm[k]`` has the lowest step potential.
        mode: ``"reverse"`` or ``"forward"`` (see :func:`jaxelastic.implicit.equilibrium`).

    Returns:
        ``(final_state, Trajectory)``. Once a step fails the state is frozen; derivatives
        of anything downstream of a failed step are NaN.
    """
    if base.mass is None:
        raise ValueError("dynamics needs lumped masses: Potential(mass=lumped_mass(...))")
    n_steps = int(n_steps)
    if n_steps < 1:
        raise ValueError(f"n_steps must be >= 1, got {n_steps}")
    if not (checkpoint is None or checkpoint == "step" or isinstance(checkpoint, int)):
        raise ValueError(f"checkpoint must be None, 'step' or an int, got {checkpoint!r}")
    if isinstance(checkpoint, int) and not isinstance(checkpoint, bool) and checkpoint < 1:
        raise ValueError(f"checkpoint segment length must be >= 1, got {checkpoint}")
    observe = _positions if observe is None else observe
    bc_fn = bc if callable(bc) else (lambda t: bc)
    x_shape = state0.x.shape
    if warm is not None and tuple(warm.shape) != (n_steps, *x_shape):
        raise ValueError(f"warm must have shape {(n_steps, *x_shape)}, got {warm.shape}")

    def body(carry, w):
        st, failed = carry

        def solve(pot, x_start, bc_now):
            if w is not None:
                better = potential_value(pot, w) < potential_value(pot, x_start)
                x_start = jnp.where(better, w, x_start)
            return equilibrium_result(pot, bc_now, x_start, settings, linear, adjoint, mode)

        new, res = advance(base, st, bc_fn(st.t + integ.h), integ, solve)
        failed = failed | (res.status != Status.SUCCESS)
        new = jax.tree_util.tree_map(lambda a, b: jnp.where(failed, b, a), new, st)
        out = (observe(new), res.status, res.steps, res.linear_iterations)
        return (new, failed), out

    if checkpoint == "step":
        policy = jax.checkpoint_policies.save_only_these_names(X_STAR)
        body = jax.checkpoint(body, policy=policy)

    def scan(carry, xs, length):
        return jax.lax.scan(body, carry, xs, length=length)

    carry = (state0, jnp.asarray(False))
    if isinstance(checkpoint, int) and not isinstance(checkpoint, bool):
        seg = min(checkpoint, n_steps)
        n_seg, rest = divmod(n_steps, seg)
        segment = jax.checkpoint(lambda c, xs: scan(c, xs, seg))
        w_main = None if warm is None else warm[: n_seg * seg].reshape(n_seg, seg, *x_shape)
        carry, ys = jax.lax.scan(segment, carry, w_main, length=n_seg)
        ys = jax.tree_util.tree_map(lambda a: a.reshape(n_seg * seg, *a.shape[2:]), ys)
        if rest:
            tail = jax.checkpoint(lambda c, xs: scan(c, xs, rest))
            carry, ys_rest = tail(carry, None if warm is None else warm[n_seg * seg :])
            ys = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), ys, ys_rest)
    else:
        carry, ys = scan(carry, warm, n_steps)
    final, _ = carry
    return final, Trajectory(*ys)


@dataclasses.dataclass(frozen=True)
class TrajectoryCase:
    """A fitting case observing a dynamic trajectory (protocol of :mod:`jaxelastic.fitting`).

    The loss is ``Σ_k ‖x_{s_k}[nodes] − observed_k‖² / Σ_k ‖observed_k − X[nodes]‖²`` over
    the observed frames ``k`` (``X``: rest positions), i.e.
    :func:`~jaxelastic.parametrization.observation_loss` summed over frames.

    Attributes:
        base: potential with lumped ``mass`` and loads; its ``params`` are replaced.
        state0: initial :class:`~jaxelastic.dynamics.State`.
        bc: Dirichlet data (fixed in time).
        observed: ``(n_frames, n_obs, dim)`` observed positions.
        frames: ``(n_frames,)`` int, the step after which each frame is observed (1-based:
            frame ``s`` is the state at ``t₀ + s·h``), each in ``1..n_steps``.
        integ: :class:`~jaxelastic.dynamics.Integrator` (static).
        n_steps: steps to simulate (static); at least ``max(frames)``.
        nodes: ``(n_obs,)`` int marker nodes, or None for all nodes.
        weight: weight of the case in the fit.
        linear: None (PCG under jit) or a host linear solver (static).
        checkpoint: see :func:`rollout` (static).
    """

    base: Potential
    state0: State
    bc: Dirichlet
    observed: Any
    frames: Any
    integ: Integrator = dataclasses.field(metadata=dict(static=True), default=None)
    n_steps: int = dataclasses.field(metadata=dict(static=True), default=0)
    nodes: Any = None
    weight: float = 1.0
    linear: Any = dataclasses.field(metadata=dict(static=True), default=None)
    checkpoint: Any = dataclasses.field(metadata=dict(static=True), default=None)

    def __post_init__(self):
        if self.integ is None:
            raise ValueError("TrajectoryCase needs an Integrator (integ=...)")
        frames = self.frames
        if isinstance(frames, np.ndarray | list | tuple):
            fr = np.asarray(frames, dtype=np.int32)
            object.__setattr__(self, "frames", fr)
            if fr.ndim != 1 or fr.size == 0 or fr.min() < 1 or fr.max() > self.n_steps:
                raise ValueError(
                    f"frames must be a non-empty 1-D list of steps in 1..n_steps="
                    f"{self.n_steps}, got {fr.tolist()}"
                )
            if np.shape(self.observed)[0] != fr.size:
                raise ValueError(
                    f"observed has {np.shape(self.observed)[0]} frames, frames lists {fr.size}"
                )

    def initial_warm(self):
        """Initial guesses ``(n_steps, n_nodes, dim)``: the initial positions repeated."""
        x0 = jnp.asarray(self.state0.x)
        return jnp.broadcast_to(x0, (self.n_steps, *x0.shape))

    def evaluate(self, params, warm, settings: NewtonSettings, adjoint: AdjointSettings):
        """``(loss, CaseAux)`` for material ``params`` (pure, jit-able, differentiable)."""
        base = self.base.replace(params=params)
        _, traj = rollout(
            base,
            self.state0,
            self.bc,
            self.integ,
            self.n_steps,
            settings=settings,
            linear=self.linear,
            adjoint=adjoint,
            checkpoint=self.checkpoint,
            warm=warm,
        )
        xs = traj.frames[jnp.asarray(self.frames) - 1]  # (n_frames, n_nodes, dim)
        X = self.base.mesh.points
        if self.nodes is not None:
            xs, X = xs[:, self.nodes], X[self.nodes]
        num = jnp.sum((xs - self.observed) ** 2)
        den = jnp.sum((self.observed - X[None]) ** 2)
        aux = CaseAux(
            warm=traj.frames,
            ok=jnp.all(traj.status == Status.SUCCESS),
            newton_steps=jnp.sum(traj.newton_steps),
            linear_iterations=jnp.sum(traj.linear_iterations),
        )
        return num / den, aux


jax.tree_util.register_dataclass(
    TrajectoryCase,
    data_fields=["base", "state0", "bc", "observed", "frames", "nodes", "weight"],
    meta_fields=["integ", "n_steps", "linear", "checkpoint"],
)
