"""Fitting cases: one experiment each, a static load case or an observed trajectory.

The case protocol (:class:`Case`; :func:`~jaxelastic.fitting.fit` needs nothing else):

* ``weight``: the case's weight in the loss;
* ``mesh``: the rest mesh (region labels and the default regularisation graph refer to it);
* ``initial_warm() -> W``: a pytree of arrays, the first Newton initial guess(es);
* ``bind(solver) -> PreparedSolver``: the solver with its linear solver's state for this
  case's mesh and Dirichlet pattern (:func:`jaxelastic.solvers.prepare_solver`), called
  once outside jit;
* ``evaluate(params, warm, solver, adjoint) -> (loss, CaseAux)``: the unweighted scalar
  misfit at the ψ parameters ``params``, pure, jit-able and reverse-mode differentiable
  (:func:`jaxelastic.solve` / :func:`jaxelastic.dynamics.rollout` differentiate by the
  implicit function theorem), and a :class:`CaseAux` (new warm start, ``ok``, counts).
"""

from __future__ import annotations

import abc
import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..dynamics import Integrator, State, rollout
from ..loads import Dirichlet
from ..mechanics.potential import Potential
from ..solvers import ImplicitAdjoint, Newton, PreparedSolver, Status, prepare_solver, solve
from .observations import observation_loss

__all__ = ["Case", "CaseAux", "LoadCase", "TrajectoryCase"]


class CaseAux(NamedTuple):
    """Auxiliary output of ``case.evaluate`` (one per case and evaluation).

    Attributes:
        warm: the new warm start (same pytree structure as ``case.initial_warm()``).
        ok: bool scalar, every forward solve of the case converged (status SUCCESS).
        newton_steps: int scalar, total Newton iterations of the case.
        linear_iterations: int scalar, total linear-solver iterations of the case.
    """

    warm: Any
    ok: jax.Array
    newton_steps: jax.Array
    linear_iterations: jax.Array


class Case(abc.ABC):
    """Abstract fitting case (see the module docstring for the protocol)."""

    weight: float

    @property
    @abc.abstractmethod
    def mesh(self):
        """The rest :class:`~jaxelastic.mesh.Mesh` of the case."""

    @abc.abstractmethod
    def initial_warm(self):
        """The first initial guess(es), a pytree of arrays."""

    @abc.abstractmethod
    def evaluate(self, params, warm, solver: Newton, adjoint: ImplicitAdjoint):
        """``(unweighted loss, CaseAux)`` at ψ parameters ``params``."""

    def bind(self, solver: Newton) -> Newton | PreparedSolver:
        """``solver`` as is (override to bind a host linear solver to the case)."""
        return solver


@dataclasses.dataclass(frozen=True)
class LoadCase(Case):
    """One static experiment: a potential (its ``params`` are replaced by the fitted ones),
    the Dirichlet data, and observed positions.

    The loss is :func:`~jaxelastic.fitting.observation_loss` (relative squared misfit; 1 at
    the rest shape).

    Attributes:
        pot: potential (mesh, ``f_ext``, ψ); ``params`` is ignored.
        bc: Dirichlet data.
        observed: ``(n_obs, dim)`` observed deformed positions of ``nodes``.
        nodes: ``(n_obs,)`` int marker-node indices, or None for all nodes.
        weight: weight of this case in the loss.
    """

    pot: Potential
    bc: Dirichlet
    observed: Any
    nodes: Any = None
    weight: float = 1.0

    @property
    def mesh(self):
        return self.pot.mesh

    def initial_warm(self):
        """Rest positions ``(n_nodes, dim)``."""
        return self.pot.mesh.points

    def bind(self, solver: Newton) -> Newton | PreparedSolver:
        """``solver`` with its linear solver bound to this mesh and Dirichlet pattern."""
        return prepare_solver(solver, self.pot.mesh, self.bc)

    def evaluate(self, params, warm, solver: Newton, adjoint: ImplicitAdjoint):
        """(unweighted loss, :class:`CaseAux`) at ψ parameters ``params``."""
        pot = self.pot.replace(params=params)
        sol = solve(pot, self.bc, x0=warm, solver=solver, adjoint=adjoint, throw=False)
        loss = observation_loss(sol.x, self.observed, self.pot.mesh.points, self.nodes)
        aux = CaseAux(
            sol.x, sol.status == Status.SUCCESS, sol.stats["steps"], sol.stats["linear_iterations"]
        )
        return loss, aux


jax.tree_util.register_dataclass(
    LoadCase, data_fields=["pot", "bc", "observed", "nodes", "weight"], meta_fields=[]
)


@dataclasses.dataclass(frozen=True)
class TrajectoryCase(Case):
    """A fitting case observing a dynamic trajectory at some frames.

    The loss is ``Σ_k ‖x_{s_k}[nodes] − observed_k‖² / Σ_k ‖observed_k − X[nodes]‖²`` over
    the observed frames ``k`` (``X``: rest positions), i.e.
    :func:`~jaxelastic.fitting.observation_loss` pooled over frames. The trajectory is
    :func:`jaxelastic.dynamics.rollout` (each step differentiated implicitly).

    Attributes:
        pot: potential with lumped ``mass`` and loads; its ``params`` are replaced.
        state0: initial :class:`~jaxelastic.dynamics.State`.
        bc: Dirichlet data (fixed in time).
        observed: ``(n_frames, n_obs, dim)`` observed positions.
        frames: ``(n_frames,)`` int, the step after which each frame is observed (1-based:
            frame ``s`` is the state at ``t₀ + s·h``), each in ``1..n_steps``.
        integ: :class:`~jaxelastic.dynamics.Integrator` (static).
        n_steps: steps to simulate (static); at least ``max(frames)``.
        nodes: ``(n_obs,)`` int marker nodes, or None for all nodes.
        weight: weight of the case in the fit.
        checkpoint: memory policy of the rollout (static; see
            :func:`jaxelastic.dynamics.rollout`).
    """

    pot: Potential
    state0: State
    bc: Dirichlet
    observed: Any
    frames: Any
    integ: Integrator | None = dataclasses.field(metadata=dict(static=True), default=None)
    n_steps: int = dataclasses.field(metadata=dict(static=True), default=0)
    nodes: Any = None
    weight: float = 1.0
    checkpoint: Any = dataclasses.field(metadata=dict(static=True), default=None)

    def __post_init__(self):
        if self.integ is None:
            raise ValueError("TrajectoryCase needs an Integrator (integ=...)")
        if isinstance(self.frames, np.ndarray | list | tuple):
            fr = np.asarray(self.frames, dtype=np.int32)
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

    @property
    def mesh(self):
        return self.pot.mesh

    def initial_warm(self):
        """Initial guesses ``(n_steps, n_nodes, dim)``: the initial positions repeated."""
        x0 = jnp.asarray(self.state0.x)
        return jnp.broadcast_to(x0, (self.n_steps, *x0.shape))

    def bind(self, solver: Newton) -> Newton | PreparedSolver:
        """``solver`` with its linear solver bound to this mesh and Dirichlet pattern."""
        return prepare_solver(solver, self.pot.mesh, self.bc)

    def evaluate(self, params, warm, solver: Newton, adjoint: ImplicitAdjoint):
        """``(loss, CaseAux)`` at ψ parameters ``params`` (pure, jit-able, differentiable)."""
        assert self.integ is not None  # checked in __post_init__
        _, traj = rollout(
            self.pot.replace(params=params),
            self.state0,
            self.bc,
            self.integ,
            self.n_steps,
            solver=solver,
            adjoint=adjoint,
            checkpoint=self.checkpoint,
            warm=warm,
        )
        xs = traj.frames[jnp.asarray(self.frames) - 1]  # (n_frames, n_nodes, dim)
        X = self.pot.mesh.points
        if self.nodes is not None:
            xs, X = xs[:, self.nodes], X[self.nodes]
        num = jnp.sum((xs - self.observed) ** 2)
        den = jnp.sum((self.observed - X[None]) ** 2)
        aux = CaseAux(
            warm=traj.frames,
            ok=jnp.all(traj.status == Status.SUCCESS),
            newton_steps=jnp.sum(traj.stats["steps"]),
            linear_iterations=jnp.sum(traj.stats["linear_iterations"]),
        )
        return num / den, aux


jax.tree_util.register_dataclass(
    TrajectoryCase,
    data_fields=["pot", "state0", "bc", "observed", "frames", "nodes", "weight"],
    meta_fields=["integ", "n_steps", "checkpoint"],
)
