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
  implicit function theorem), and a :class:`CaseAux` (new warm start, ``ok``, counts);
* optionally ``residuals(params, warm, solver, adjoint) -> (r, CaseAux)``: the residual
  vector whose squared norm is the loss, for the Gauss–Newton uncertainty of a fit
  (differentiated in forward mode), and ``sigma_known``: whether ``r`` is weighted by the
  measurement standard deviations (then ``loss = χ²``).

A case is a pytree (its arrays are traced by the compiled objective): a frozen dataclass
registered with :func:`jax.tree_util.register_dataclass`, as the cases here are.

:class:`LoadPathCase` is one experiment as a sequence of load levels with observations of
any kind (:mod:`jaxelastic.fitting.measurements`) at every level.
"""

from __future__ import annotations

import abc
import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer

from ..dynamics import Integrator, State, rollout
from ..loads import Dirichlet
from ..mechanics import forces
from ..mechanics.potential import Potential
from ..solvers import ImplicitAdjoint, Newton, PreparedSolver, Status, prepare_solver, solve
from ..solvers.adjoint import differentiable_solution
from ..solvers.results import Solution
from .measurements import Observation, SolvedState
from .observations import observation_loss

__all__ = ["Case", "CaseAux", "LoadCase", "TrajectoryCase", "LoadPathCase"]


class CaseAux(NamedTuple):
    """Auxiliary output of ``case.evaluate`` (one per case and evaluation).

    Attributes:
        warm: the new warm start (same pytree structure as ``case.initial_warm()``).
        ok: bool scalar, every forward solve of the case converged (status SUCCESS).
        newton_steps: int scalar, total Newton iterations of the case.
        linear_iterations: int scalar, total linear-solver iterations of the case.
        status: int scalar, the first failed solve's :class:`~jaxelastic.solvers.Status`
            (0: all converged), or None (a case that does not report it).
        level: int scalar, the first load level whose solve failed (−1: none), or None.
    """

    warm: Any
    ok: jax.Array
    newton_steps: jax.Array
    linear_iterations: jax.Array
    status: Any = None
    level: Any = None


class Case(abc.ABC):
    """Abstract fitting case (see the module docstring for the protocol)."""

    weight: float
    sigma_known: bool = False
    """Whether :meth:`residuals` are weighted by measurement standard deviations."""

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

    def bind(self, solver: Newton) -> Newton | PreparedSolver | None:
        """The solver ``evaluate`` receives: override to return
        :func:`~jaxelastic.solvers.prepare_solver` ``(solver, mesh, bc)`` (a pytree, bound
        once outside jit), or None for a case without solves; the default returns
        ``solver`` as is, which the compiled objective refuses with this advice."""
        return solver

    def residuals(self, params, warm, solver: Newton, adjoint: ImplicitAdjoint):
        """``(r, CaseAux)`` with ``Σ r² = loss`` (optional; needed for the uncertainty)."""
        raise NotImplementedError(f"{type(self).__name__} defines no residuals()")


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

    def _solve(self, params, warm, solver, adjoint):
        pot = self.pot.replace(params=params)
        sol = solve(pot, self.bc, x0=warm, solver=solver, adjoint=adjoint, throw=False)
        st = jnp.asarray(sol.status, jnp.int32)
        ok = st == Status.SUCCESS
        aux = CaseAux(
            sol.x, ok, sol.stats["steps"], sol.stats["linear_iterations"], st, jnp.int32(-1)
        )
        return sol.x, aux

    def evaluate(self, params, warm, solver: Newton, adjoint: ImplicitAdjoint):
        """(unweighted loss, :class:`CaseAux`) at ψ parameters ``params``."""
        x, aux = self._solve(params, warm, solver, adjoint)
        return observation_loss(x, self.observed, self.pot.mesh.points, self.nodes), aux

    def residuals(self, params, warm, solver: Newton, adjoint: ImplicitAdjoint):
        """``(x[nodes] − observed)/‖observed − X[nodes]‖`` raveled (relative: σ unknown)."""
        x, aux = self._solve(params, warm, solver, adjoint)
        X = self.pot.mesh.points
        if self.nodes is not None:
            x, X = x[self.nodes], X[self.nodes]
        scale = jnp.sqrt(jnp.sum((self.observed - X) ** 2))
        return jnp.ravel((x - self.observed) / scale), aux


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


def _concrete(a) -> bool:
    """Whether ``a`` is a user-given value (checked), not a leaf JAX rebuilt a case from."""
    if isinstance(a, Tracer):
        return False
    return isinstance(a, np.ndarray | list | tuple | jax.Array)


@dataclasses.dataclass(frozen=True)
class LoadPathCase(Case):
    """One experiment as a sequence of load levels, observed at every level.

    At level ``k`` the potential's external forces are ``s_k·f_ext`` and the prescribed
    displacements ``s_k·(bc.values − X)``; the levels are solved in order, each from the
    previous iterate's solution of the same level (on the first evaluation, the secant
    through the two previous levels' solutions: the previous level's solution plus its
    increment scaled to this level's). A level whose solve fails is retried from the
    previous level's solution in sub-steps (the increment halved up to ``max_cutbacks``
    times); a level still failing makes the case fail (``CaseAux.ok`` False, with its
    status and level), never skipped. The converged solution of every level (one Newton
    solve from the warm start where that converges) is differentiated by the implicit adjoint
    (:func:`~jaxelastic.solvers.adjoint.differentiable_solution`: no second solve), one
    adjoint solve per level (``jax.lax.scan`` over the levels: compiled once whatever
    their number). Cavity pressures (``pot.pressure``) scale like the forces, ``s_k·p``.

    The loss is the χ² misfit ``Σ_obs Σ_levels Σ ((pred − data)/σ)²`` of the
    observations (:mod:`jaxelastic.fitting.measurements`).

    Attributes:
        pot: potential at load factor 1 (mesh, ``f_ext``, ψ); ``params`` is replaced.
        bc: Dirichlet data at load factor 1.
        factors: ``(n_levels,)`` load factors (any order; usually increasing).
        observations: tuple of :class:`~jaxelastic.fitting.measurements.Observation`,
            each with data for every level.
        weight: weight of the case in the loss.
        max_cutbacks: halvings of a failing level's increment before it counts as failed
            (static).

    Raises:
        ValueError: (at construction) empty or non-finite factors, an observation whose
            data do not have one entry per level, non-finite data, σ ≤ 0, or a contact
            term (not supported).
    """

    pot: Potential
    bc: Dirichlet
    factors: Any
    observations: tuple
    weight: float = 1.0
    max_cutbacks: int = dataclasses.field(default=4, metadata=dict(static=True))
    sigma_known = True

    def __post_init__(self):
        if not _concrete(self.factors):
            return
        f = np.asarray(self.factors, dtype=np.float64)
        object.__setattr__(self, "factors", f)
        object.__setattr__(self, "observations", tuple(self.observations))
        if f.ndim != 1 or f.size == 0 or not np.all(np.isfinite(f)):
            raise ValueError(f"factors must be a non-empty 1-D list of numbers, got {f.tolist()}")
        if not self.observations:
            raise ValueError("a LoadPathCase needs at least one observation")
        for i, o in enumerate(self.observations):
            if not isinstance(o, Observation):
                raise TypeError(f"observations[{i}] must be an Observation, got {type(o)}")
            o.check()
            if o.n_levels != f.size:
                raise ValueError(
                    f"observations[{i}] ({o.kind}) has data for {o.n_levels} load levels, "
                    f"factors lists {f.size}"
                )
        if self.pot.contact is not None:
            raise ValueError("a LoadPathCase does not support contact terms")
        if self.pot.pressure is not None and self.pot.pressure.kappa is not None:
            raise ValueError("a LoadPathCase scales pressures: volume control is not supported")
        if int(self.max_cutbacks) < 0:
            raise ValueError(f"max_cutbacks must be >= 0, got {self.max_cutbacks}")

    @property
    def mesh(self):
        return self.pot.mesh

    def initial_warm(self):
        """``(positions (n_levels, n_nodes, dim), valid)``: rest positions, not valid (the
        first evaluation starts every level from the secant through the two previous
        levels' solutions)."""
        X = jnp.asarray(self.pot.mesh.points)
        return (jnp.broadcast_to(X, (len(self.factors), *X.shape)), jnp.asarray(False))

    def bind(self, solver: Newton) -> Newton | PreparedSolver:
        """``solver`` with its linear solver bound to this mesh and Dirichlet pattern."""
        return prepare_solver(solver, self.pot.mesh, self.bc)

    def at(self, s, params):
        """``(potential, Dirichlet)`` at load factor ``s`` and ψ parameters ``params``."""
        X = self.pot.mesh.points
        f, p = self.pot.f_ext, self.pot.pressure
        pot = self.pot.replace(params=params, f_ext=None if f is None else s * f)
        pot = pot if p is None else pot.replace(pressure=p.scaled(s))
        return pot, Dirichlet(self.bc.mask, X + s * (self.bc.values - X))

    def predictions(self, params, warm, solver, adjoint: ImplicitAdjoint):
        """``(predictions, CaseAux)``: per observation its predictions at every level
        (leading axis: level); pure, jit-able, differentiable."""
        xs_warm, valid = warm
        X = self.pot.mesh.points
        solver = prepare_solver(solver, self.pot.mesh, self.bc)
        need_r = any(o.needs_reactions for o in self.observations)
        datas = tuple(o.data for o in self.observations)

        def level(carry, inp):
            x_prev, s_prev, x_pp, s_pp = carry
            s, xw, data_k = inp
            pot, bc = self.at(s, params)
            # without a previous evaluation's solution: the secant through the two previous
            # levels' solutions (the first level: the rest shape), a first-order predictor
            ds = s_prev - s_pp
            t = jnp.where(ds != 0, (s - s_prev) / jnp.where(ds != 0, ds, 1.0), 0.0)
            x0 = jnp.where(valid, xw, x_prev + t * (x_prev - x_pp))
            x_k, st_k, trials = _reach(self, params, solver, x0, x_prev, s_prev, s)
            found = Solution(x=x_k, status=st_k, stats={})  # (no adaptive terms: no contact)
            sol = differentiable_solution(
                solver.newton, solver.linear_state, adjoint, pot, bc, found
            )
            R = None
            if need_r:
                R = -forces(pot.psi, sol.x, pot.mesh, pot.params)
                R = R if pot.f_ext is None else R - pot.f_ext
            state = SolvedState(sol.x, R, params, pot.mesh)
            obs = self.observations
            preds = tuple(o.predict(state, d) for o, d in zip(obs, data_k, strict=True))
            st = jnp.asarray(sol.status, jnp.int32)
            out = (preds, sol.x, st, trials)
            return (sol.x, s, x_prev, s_prev), out

        s0 = jnp.zeros((), X.dtype)
        factors = jnp.asarray(self.factors, X.dtype)
        _, out = jax.lax.scan(level, (X, s0, X, s0), (factors, xs_warm, datas))
        preds, xs, st, trials = out
        failed = st != Status.SUCCESS
        first = jnp.argmax(failed)
        aux = CaseAux(
            warm=(xs, jnp.asarray(True)),
            ok=~jnp.any(failed),
            newton_steps=jnp.sum(trials[:, 1]),
            linear_iterations=jnp.sum(trials[:, 2]),
            status=jnp.where(jnp.any(failed), st[first], 0),
            level=jnp.where(jnp.any(failed), first, -1).astype(jnp.int32),
        )
        return preds, aux

    def residuals(self, params, warm, solver, adjoint: ImplicitAdjoint):
        """``((pred − data)/σ`` of every observation and level, raveled; CaseAux)."""
        preds, aux = self.predictions(params, warm, solver, adjoint)
        r = [
            jnp.ravel((p - o.target(o.data)) / o.sigma)
            for p, o in zip(preds, self.observations, strict=True)
        ]
        return jnp.concatenate(r), aux

    def evaluate(self, params, warm, solver, adjoint: ImplicitAdjoint):
        """``(χ², CaseAux)`` at ψ parameters ``params``."""
        r, aux = self.residuals(params, warm, solver, adjoint)
        return jnp.sum(r * r), aux


jax.tree_util.register_dataclass(
    LoadPathCase,
    data_fields=["pot", "bc", "factors", "observations", "weight"],
    meta_fields=["max_cutbacks"],
)


def _reach(case: LoadPathCase, params, solver, x0, x_prev, s_prev, s):
    """The solution of level ``s`` (no derivatives): one solve from ``x0``; if it fails,
    sub-steps from the previous level's ``(x_prev, s_prev)`` with the increment halved on
    every failure, at most ``case.max_cutbacks`` times (either direction). Returns
    ``(x, status, counts)``: the last converged positions (level ``s``'s solution where
    ``status`` is SUCCESS; else the last failed trial's status), and ``(trials, Newton
    steps, linear iterations)``."""
    stop = jax.lax.stop_gradient
    params, x0, x_prev, s_prev, s = stop((params, x0, x_prev, s_prev, s))
    max_cut = int(case.max_cutbacks)

    one = jnp.ones((), s.dtype)

    def cond(c):
        _, t_done, _, cuts, _, _ = c
        return (t_done < one) & (cuts <= max_cut)

    def body(c):  # t ∈ [0, 1] goes from the previous level (s_prev) to this one (s)
        x, t_done, dt, cuts, counts, _ = c
        t_try = jnp.minimum(one, t_done + dt)
        # the last trial is at s itself (not s_prev + (s − s_prev), a rounding away)
        pot, bc = case.at(jnp.where(t_try < one, s_prev + t_try * (s - s_prev), s), params)
        start = jnp.where(counts[0] == 0, x0, x)
        sol = solve(pot, bc, x0=start, solver=solver, throw=False)
        st = jnp.asarray(sol.status, jnp.int32)
        ok = st == Status.SUCCESS
        its = [jnp.ones((), jnp.int32), sol.stats["steps"], sol.stats["linear_iterations"]]
        its = jnp.stack([jnp.asarray(a, jnp.int32) for a in its])
        return (
            jnp.where(ok, sol.x, x),
            jnp.where(ok, t_try, t_done),
            jnp.where(ok, dt, 0.5 * dt),
            cuts + jnp.where(ok, 0, 1),
            counts + its,
            st,
        )

    zero = jnp.zeros((), s.dtype)
    init = (x_prev, zero, one, jnp.int32(0), jnp.zeros(3, jnp.int32), jnp.int32(Status.SUCCESS))
    x, t_done, _, _, counts, st = jax.lax.while_loop(cond, body, init)
    return x, jnp.where(t_done < one, st, Status.SUCCESS).astype(jnp.int32), counts
